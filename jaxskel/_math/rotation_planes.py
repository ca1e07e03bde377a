"""Rotations as tuples of component arrays ("planes"): the structure-of-arrays form of
:mod:`jaxskel._math.rotation`.

A quaternion is the tuple ``(w, x, y, z)`` of arrays of one batch shape, a rotation
vector the tuple of its three components and a matrix the 9-tuple of its entries row by
row (:mod:`jaxskel._math.planes`). Every operation is elementwise over the batch, so XLA
vectorises it along the arrays' minor axis (the batched IK keeps frames on the last
axis) instead of a minor axis of 3 or 4. The conventions are those of
:mod:`jaxskel._math.rotation` (order ``(w, x, y, z)``, Hamilton product, active
rotations), and a function here computes what its namesake there does, to rounding:

==========================  ==========================================================
here                        :mod:`jaxskel._math.rotation`
==========================  ==========================================================
``quat_multiply``           ``quat_multiply`` (the same arithmetic)
``quat_conjugate``          ``quat_conjugate`` (the same arithmetic)
``quat_normalize``          ``quat_normalize`` (here by ``rsqrt``)
``unit_quat_to_matrix``     ``quat_to_matrix``, for unit quaternions only
``axis_angle_to_quat``      ``axis_angle_to_quat``
``quat_to_axis_angle``      ``quat_to_axis_angle``, for unit quaternions only
``inverse_right_jacobian``  ``inverse_right_jacobian`` (``[e]x^2`` expanded)
``horn_quat``               ``horn_align``, with a prior where the data leave the
                            rotation free (power iteration, no SVD)
==========================  ==========================================================
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .planes import vdot, vscale

__all__ = [
    "axis_angle_to_quat",
    "horn_quat",
    "inverse_right_jacobian",
    "quat_conjugate",
    "quat_multiply",
    "quat_normalize",
    "quat_to_axis_angle",
    "unit_quat_to_matrix",
]

#: Added to the shift of Horn's matrix so that an all-zero covariance divides by no zero.
_TINY = 1e-30


def quat_multiply(p, q):
    """Hamilton product ``p q`` (apply q first, then p)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_conjugate(q):
    """Conjugate (the inverse of a unit quaternion)."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_normalize(q):
    """Unit quaternion with non-negative ``w`` (a canonical sign; safe at q = 0)."""
    n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    s = jnp.where(q[0] < 0, -1.0, 1.0) * jax.lax.rsqrt(jnp.where(n2 > 0, n2, 1.0))
    return tuple(s * c for c in q)


def unit_quat_to_matrix(q):
    """Rotation matrix (9-tuple, row-major) of a *unit* quaternion (its norm is not divided out)."""
    w, x, y, z = q
    x2, y2, z2 = x + x, y + y, z + z
    xx, yy, zz = x * x2, y * y2, z * z2
    xy, xz, yz = x * y2, x * z2, y * z2
    wx, wy, wz = w * x2, w * y2, w * z2
    return (1 - yy - zz, xy - wz, xz + wy, xy + wz, 1 - xx - zz, yz - wx, xz - wy, yz + wx, 1 - xx - yy)


def axis_angle_to_quat(v):
    """Quaternion ``exp(v / 2)`` of a rotation vector (axis times angle, radians); smooth at 0."""
    theta2 = vdot(v, v)
    small = theta2 < 1e-12
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    # sin(theta/2)/theta, with its Taylor series near 0 so gradients stay finite.
    k = jnp.where(small, 0.5 - theta2 / 48.0, jnp.sin(0.5 * theta) / theta)
    w = jnp.where(small, 1.0 - theta2 / 8.0, jnp.cos(0.5 * theta))
    return (w, k * v[0], k * v[1], k * v[2])


def quat_to_axis_angle(q):
    """Rotation vector (angle in [0, pi]) of a *unit* quaternion (either sign)."""
    sign = jnp.where(q[0] < 0, -1.0, 1.0)
    w = sign * q[0]
    u = (sign * q[1], sign * q[2], sign * q[3])
    s2 = vdot(u, u)
    small = s2 < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    k = jnp.where(small, 2.0 / jnp.where(w == 0, 1.0, w), 2.0 * jnp.arctan2(s, w) / s)
    return vscale(k, u)


def inverse_right_jacobian(e):
    """``Jr^-1(e)`` (9-tuple): ``log(exp(e) exp(d)) = e + Jr^-1(e) d + O(d^2)``, as
    ``I + [e]x / 2 + c [e]x^2`` with ``c = 1/theta^2 - (1 + cos theta) / (2 theta sin theta)``
    and ``[e]x^2 = e e^T - theta^2 I`` (``theta = |e|``)."""
    theta2 = vdot(e, e)
    small = theta2 < 1e-8
    safe = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe)
    c = jnp.where(small, 1.0 / 12.0 + theta2 / 720.0, 1.0 / safe - (1 + jnp.cos(theta)) / (2 * theta * jnp.sin(theta)))
    x, y, z = e
    return (
        1.0 + c * (x * x - theta2), -0.5 * z + c * x * y, 0.5 * y + c * x * z,
        0.5 * z + c * x * y, 1.0 + c * (y * y - theta2), -0.5 * x + c * y * z,
        -0.5 * y + c * x * z, 0.5 * x + c * y * z, 1.0 + c * (z * z - theta2),
    )  # fmt: skip


def horn_quat(mcov, q_default, squarings: int):
    """Rotation ``q`` maximising Horn's criterion ``sum_k dst_k . R(q) src_k`` for the
    cross-covariance ``mcov[3 a + b] = sum_k src_k[a] dst_k[b]`` (9-tuple), closest to
    ``q_default`` where the data leave it free. Unit quaternion, ``w >= 0``.

    Horn (1987): ``q`` is the top eigenvector of a symmetric 4x4 matrix ``N`` built from
    ``mcov``; its eigenvalues are sums ``+-s1 +-s2 +-s3`` of ``mcov``'s singular values, so
    shifted by ``sqrt(3) |mcov|_F`` it is positive semi-definite, and ``squarings`` repeated squarings, each rescaled to unit
    trace, raise its spectrum to the power ``2^squarings``, so ``N^(2^k) q_default``
    points along the top eigenvector, or into the top eigenspace where it is degenerate.
    Where ``q_default`` is (nearly) orthogonal to it the largest column of that power is
    taken instead, and an all-zero ``mcov`` returns ``q_default`` (normalised).
    """
    s = mcov
    fro2 = sum(c * c for c in s)
    shift = jnp.sqrt(3.0 * fro2) + _TINY
    n00 = s[0] + s[4] + s[8] + shift
    n01 = s[5] - s[7]
    n02 = s[6] - s[2]
    n03 = s[1] - s[3]
    n11 = s[0] - s[4] - s[8] + shift
    n12 = s[1] + s[3]
    n13 = s[6] + s[2]
    n22 = -s[0] + s[4] - s[8] + shift
    n23 = s[5] + s[7]
    n33 = -s[0] - s[4] + s[8] + shift
    idx = ((0, 1, 2, 3), (1, 4, 5, 6), (2, 5, 7, 8), (3, 6, 8, 9))
    upper = ((0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3))

    def square(_, n):
        sq = [sum(n[idx[i][k]] * n[idx[k][j]] for k in range(4)) for i, j in upper]
        scale = 1.0 / (sq[0] + sq[4] + sq[7] + sq[9])
        return tuple(c * scale for c in sq)

    n = (n00, n01, n02, n03, n11, n12, n13, n22, n23, n33)
    first = 1.0 / (n00 + n11 + n22 + n33)
    n = tuple(c * first for c in n)
    n = jax.lax.fori_loop(0, squarings, square, n)
    v = [sum(n[idx[i][k]] * q_default[k] for k in range(4)) for i in range(4)]
    # q_default (nearly) orthogonal to the answer: take N's largest column instead.
    diag = [n[idx[i][i]] for i in range(4)]
    best = [n[idx[i][0]] for i in range(4)]
    top = diag[0]
    for j in range(1, 4):
        better = diag[j] > top
        best = [jnp.where(better, n[idx[i][j]], best[i]) for i in range(4)]
        top = jnp.where(better, diag[j], top)
    weak = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3]) < 2.5e-3 * top * top
    usable = fro2 > 1e-300
    v = [jnp.where(usable, jnp.where(weak, bc, vc), qd) for vc, bc, qd in zip(v, best, q_default)]
    return quat_normalize(tuple(v))
