"""The rotation kit: quaternions, rotation matrices, rotation vectors, rigid alignment.

Conventions (used everywhere in jaxskel):

* **Quaternions** are ``(w, x, y, z)``, ``w`` the scalar part, in the last axis
  (``... 4``). A rotation is a unit quaternion; ``q`` and ``-q`` are the same rotation,
  and functions that pick one return ``w >= 0``. The product is Hamilton's:
  ``quat_multiply(p, q)`` applies ``q`` first, then ``p``, and
  ``quat_to_matrix(p q) = quat_to_matrix(p) @ quat_to_matrix(q)``.
* **Rotations are active** and act on column vectors: ``quat_rotate(q, v) = q v q* =
  R(q) @ v`` turns the vector, in a fixed frame.
* **Rotation vectors** (``... 3``, "axis-angle") are the axis times the angle in radians
  (right-hand rule); :func:`axis_angle_to_quat` is the exponential map and
  :func:`quat_to_axis_angle` its inverse on angles in ``[0, pi]``.
* **Poses.** A pose ``(R, t)`` maps a point from a segment's local frame to the world:
  ``x_world = R @ x_local + t``, so the columns of ``R`` are the local axes in world
  coordinates.
* **Masks, not NaNs**: weights select which points take part.

The kit has three forms; the rest of jaxskel composes them rather than writing rotation
maths of its own:

* this module's JAX functions on arrays of structures (``... 4``, ``... 3``,
  ``... 3 3``): pure, jit/vmap/grad-able, following the dtype of their input;
* :mod:`jaxskel._math.rotation_planes`: the operations the batched IK needs, on
  structures of arrays (tuples of component arrays, vectorised along the frames axis),
  under the same names; each agrees with its namesake here to rounding, and where the
  arithmetic is the same (the product, the conjugate) the function here is the planes
  one on unstacked components;
* host forms, named ``..._np`` (numpy, float64, eager), for code that stays on the host
  in numpy, such as the synthetic-data generator.
"""

from __future__ import annotations

from types import ModuleType

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import rotation_planes

__all__ = [
    "axis_angle_to_matrix_np",
    "axis_angle_to_quat",
    "cross_covariance",
    "det3",
    "horn_align",
    "inverse_right_jacobian",
    "matrix_to_quat",
    "quat_conjugate",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_to_axis_angle",
    "quat_to_matrix",
    "quat_to_matrix_np",
    "quat_twist_angle",
    "skew",
    "skew_np",
    "slerp",
]


# ------------------------------------------------------------------ quaternions
def quat_multiply(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product ``p q`` (apply q first, then p); broadcasts."""
    out = rotation_planes.quat_multiply(tuple(jnp.moveaxis(p, -1, 0)), tuple(jnp.moveaxis(q, -1, 0)))
    return jnp.stack(out, axis=-1)


def quat_conjugate(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Conjugate (the inverse of a unit quaternion)."""
    return jnp.stack(rotation_planes.quat_conjugate(tuple(jnp.moveaxis(q, -1, 0))), axis=-1)


def quat_normalize(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Unit quaternion with non-negative ``w`` (a canonical sign; safe at q = 0)."""
    n = jnp.sqrt(jnp.sum(q * q, axis=-1, keepdims=True))
    q = q / jnp.where(n > 0, n, 1.0)
    return jnp.where(q[..., :1] < 0, -q, q)


def _quat_to_matrix(xp: ModuleType, q):
    w, x, y, z = xp.moveaxis(q, -1, 0)
    n = w * w + x * x + y * y + z * z
    s = 2.0 / xp.where(n > 0, n, 1.0)
    rows = [
        [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def quat_to_matrix(q: Float[Array, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a (not necessarily unit) quaternion; scale is divided out."""
    return _quat_to_matrix(jnp, q)


def matrix_to_quat(m: Float[Array, "... 3 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion (w >= 0) of a rotation matrix.

    Uses the largest of the four diagonal combinations (Shepperd's method), so it
    is accurate for every rotation including half turns.
    """
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack(
        [
            jnp.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            jnp.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            jnp.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            jnp.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    pick = jnp.argmax(jnp.stack([tr, m00, m11, m22], -1), axis=-1)
    q = jnp.take_along_axis(cands, pick[..., None, None], axis=-2)[..., 0, :]
    return quat_normalize(q)


def quat_rotate(q: Float[Array, "... 4"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Rotate vectors ``v`` by unit quaternions ``q`` (broadcasting): ``R(q) @ v``."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def quat_twist_angle(q: Float[Array, "... 4"], axis: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Angle in ``[-pi, pi]`` of the twist of ``q`` about the unit ``axis``: the rotation
    about ``axis`` closest to ``q``. With ``q = (w, v)`` and ``w >= 0`` (either sign is
    taken), ``2 atan2(v . axis, w)``: for unit quaternions ``tr(A^T B) = 4 (a . b)^2 - 1``,
    and ``a . b`` is largest over the rotations ``b`` about the axis at that angle.
    """
    sign = jnp.where(q[..., 0] < 0, -1.0, 1.0)
    return 2.0 * jnp.arctan2(sign * jnp.sum(q[..., 1:] * axis, -1), sign * q[..., 0])


# ------------------------------------------------------------ rotation vectors
def axis_angle_to_quat(rotvec: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """Quaternion of a rotation vector (axis * angle in radians); smooth at 0."""
    theta2 = jnp.sum(rotvec * rotvec, axis=-1, keepdims=True)
    small = theta2 < 1e-12
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    half = 0.5 * theta
    # sin(theta/2)/theta, with its Taylor series near 0 so gradients stay finite.
    k = jnp.where(small, 0.5 - theta2 / 48.0, jnp.sin(half) / theta)
    w = jnp.where(small, 1.0 - theta2 / 8.0, jnp.cos(half))
    return jnp.concatenate([w, k * rotvec], axis=-1)


def quat_to_axis_angle(q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Rotation vector (angle in [0, pi]) of a unit quaternion."""
    q = quat_normalize(q)
    w = q[..., :1]
    u = q[..., 1:]
    s2 = jnp.sum(u * u, axis=-1, keepdims=True)
    small = s2 < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    angle = 2.0 * jnp.arctan2(s, w)
    k = jnp.where(small, 2.0 / jnp.where(w == 0, 1.0, w), angle / s)
    return k * u


def slerp(a: Float[Array, "... 4"], b: Float[Array, "... 4"], alpha: Float[Array, "..."]) -> Float[Array, "... 4"]:
    """Spherical interpolation ``a exp(alpha log(a^-1 b))`` (shortest arc; ``alpha`` 0 gives
    ``a``, 1 gives ``b`` up to sign)."""
    d = quat_to_axis_angle(quat_multiply(quat_conjugate(a), b))
    return quat_multiply(a, axis_angle_to_quat(alpha[..., None] * d))


def inverse_right_jacobian(e: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """``Jr^-1(e)``: ``log(exp(e) exp(d)) = e + Jr^-1(e) d + O(d^2)`` on SO(3), as
    ``I + [e]x / 2 + c [e]x^2`` with ``c = 1/theta^2 - (1 + cos theta) / (2 theta sin theta)``
    (``theta = |e|``; its Taylor series ``1/12 + theta^2/720`` near 0)."""
    theta2 = jnp.sum(e * e, axis=-1)
    small = theta2 < 1e-8
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    coef = jnp.where(
        small,
        1.0 / 12.0 + theta2 / 720.0,
        1.0 / jnp.where(small, 1.0, theta2) - (1 + jnp.cos(theta)) / (2 * theta * jnp.sin(theta)),
    )
    k = skew(e)
    eye = jnp.eye(3, dtype=e.dtype)
    return eye + 0.5 * k + coef[..., None, None] * (k @ k)


# --------------------------------------------------------------------- matrices
def _skew(xp: ModuleType, v):
    x, y, z = xp.moveaxis(v, -1, 0)
    o = xp.zeros_like(x)
    return xp.stack([xp.stack([o, -z, y], -1), xp.stack([z, o, -x], -1), xp.stack([-y, x, o], -1)], -2)


def skew(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Cross-product matrix ``[v]x``: ``skew(a) @ b == cross(a, b)``."""
    return _skew(jnp, v)


def det3(m: Float[Array, "... 3 3"]) -> Float[Array, "..."]:
    """Determinant of (batches of) 3x3 matrices by cofactor expansion along the first row.

    Elementwise arithmetic that XLA fuses; ``jnp.linalg.det`` is an LU factorisation per
    matrix (a LAPACK call on CPU).
    """
    return (
        m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
        - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
        + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0])
    )


# -------------------------------------------------------------- rigid alignment
def cross_covariance(
    source: Float[Array, "N 3"], target: Float[Array, "N 3"], weights: Float[Array, " N"]
) -> tuple[Float[Array, " 3"], Float[Array, " 3"], Float[Array, "3 3"]]:
    """Weighted means ``mu_x``, ``mu_y`` and cross-covariance ``M = sum_i w_i (y_i - mu_y)(x_i - mu_x)^T /
    sum_i w_i`` of a source ``x`` and a target ``y`` cloud (zeros where no point has weight): what a
    least-squares rigid alignment of the two needs."""
    w = weights.astype(source.dtype)
    wsum = jnp.sum(w)
    wn = w / jnp.where(wsum > 0, wsum, 1.0)
    mu_s = jnp.sum(wn[:, None] * source, axis=0)
    mu_t = jnp.sum(wn[:, None] * target, axis=0)
    return mu_s, mu_t, jnp.einsum("n,ni,nj->ij", wn, target - mu_t, source - mu_s)


def horn_align(
    source: Float[Array, "N 3"],
    target: Float[Array, "N 3"],
    weights: Float[Array, " N"] | None = None,
) -> tuple[Float[Array, "3 3"], Float[Array, " 3"]]:
    """Weighted least-squares rigid alignment (Horn 1987 / Kabsch via SVD).

    Returns ``(R, t)`` minimising ``sum_i w_i |R source_i + t - target_i|^2`` with
    R a proper rotation (det +1). Points with zero weight are ignored, so a mask
    can be passed as ``weights``. With fewer than three non-collinear weighted
    points the rotation is not unique; the SVD then returns one minimiser.
    vmap it over frames/segments; it is differentiable where the alignment is unique.
    """
    if weights is None:
        weights = jnp.ones(source.shape[:-1], dtype=source.dtype)
    mu_s, mu_t, cov = cross_covariance(source, target, weights)
    u, _, vt = jnp.linalg.svd(cov)
    # det(U V^T) = det(U) det(V^T), each +-1: two cofactor expansions, no third factorisation.
    d = jnp.sign(det3(u) * det3(vt))
    d = jnp.where(d == 0, 1.0, d)
    diag = jnp.array([1.0, 1.0, 0.0], dtype=source.dtype) + jnp.array([0.0, 0.0, 1.0], dtype=source.dtype) * d
    rot = (u * diag) @ vt
    return rot, mu_t - rot @ mu_s


# ------------------------------------------------------------------- host forms
def skew_np(v: Float[np.ndarray, "... 3"]) -> Float[np.ndarray, "... 3 3"]:
    """Host form (numpy, float64) of :func:`skew`."""
    return _skew(np, np.asarray(v, dtype=float))


def quat_to_matrix_np(q: Float[np.ndarray, "... 4"]) -> Float[np.ndarray, "... 3 3"]:
    """Host form (numpy, float64) of :func:`quat_to_matrix`, for host-side orchestration
    (eager JAX would compile each of its operations for every new array shape)."""
    return _quat_to_matrix(np, np.asarray(q, dtype=float))


def axis_angle_to_matrix_np(rotvec: Float[np.ndarray, "... 3"]) -> Float[np.ndarray, "... 3 3"]:
    """Host form (numpy, float64): the rotation matrix ``exp([r]x)`` of rotation vectors r,
    by Rodrigues' formula

        R = I + sin(a) K + (1 - cos(a)) K^2,   a = |r|,  K = [r / a]x.

    Equals ``quat_to_matrix(axis_angle_to_quat(r))`` to rounding. For code that stays on
    the host (the synthetic-data generator, plots), where eager JAX would compile every
    operation anew for each array shape.
    """
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1)[..., None, None]
    unit = r / np.where(angle[..., 0] > 0, angle[..., 0], 1.0)
    k = _skew(np, unit)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
