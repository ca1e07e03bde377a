"""Generalised Procrustes analysis of point clouds (masked), vmapped over frames and sets."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .linalg import eigh3
from .rotation import cross_covariance

__all__ = ["align_to_reference", "closed_form_align", "procrustes"]

#: Generalised Procrustes stops when no point of the mean cloud moves more than this
#: (metres) in a pass, or after ``_GPA_MAX_PASSES``: the mean converges linearly, and a
#: tenth of a micrometre is far below any marker noise.
_GPA_TOL, _GPA_MAX_PASSES = 1e-7, 8


def closed_form_align(
    source: Float[Array, "N 3"], target: Float[Array, "N 3"], weights: Float[Array, " N"]
) -> tuple[Float[Array, "3 3"], Float[Array, " 3"]]:
    """Weighted least-squares rigid alignment (Kabsch), without an SVD: ``(R, t)``
    minimising ``sum_i w_i |R source_i + t - target_i|^2``, ``det R = +1``.

    With the weighted cross-covariance ``M = sum_i w_i (y_i - mu_y)(x_i - mu_x)^T`` (``x``
    source, ``y`` target) and its SVD ``M = U S V^T``, the minimiser is ``U diag(1, 1,
    det(U V^T)) V^T``. Here ``V``'s two leading columns come from the closed-form
    eigendecomposition of ``M^T M`` (:func:`jaxskel._math.linalg.eigh3`), ``u_k = M v_k /
    |M v_k|`` (``u_2`` made orthogonal to ``u_1``) and both third columns are the cross
    products of the first two, so ``U`` and ``V`` are proper rotations and ``R = U V^T`` is
    the Kabsch solution (the sign of the third singular value absorbs the determinant).
    A planar cloud (three markers) has ``s_3 = 0`` and loses nothing. Fewer than three
    non-collinear weighted points leave ``R`` partly free: one minimiser is returned
    (``u_2`` any direction orthogonal to ``u_1`` when ``M v_2`` vanishes; the identity
    when no point has weight). Equals :func:`jaxskel._math.rotation.horn_align` to about
    ``eps |M| / s_2^2``; for the per-frame marker-only poses of long recordings, where a
    batched SVD would dominate. Not meant to be differentiated (its eigenvalue formula
    has unbounded derivatives where singular values meet): the learning API keeps
    ``horn_align``.
    """
    mu_s, mu_t, m = cross_covariance(source, target, weights)
    _, v = eigh3(m.T @ m)  # ascending: v[:, 2] is the leading right singular vector
    v1, v2 = v[:, 2], v[:, 1]
    a1, a2 = m @ v1, m @ v2
    n1 = jnp.linalg.norm(a1)
    u1 = a1 / jnp.where(n1 > 0, n1, 1.0)
    a2 = a2 - (u1 @ a2) * u1
    n2 = jnp.linalg.norm(a2)
    # Collinear points: any unit vector orthogonal to u1 (the cross product with the axis
    # u1 is least aligned with).
    other = jnp.cross(u1, jnp.eye(3, dtype=m.dtype)[jnp.argmin(jnp.abs(u1))])
    free = n2 <= 1e-12 * jnp.maximum(n1, jnp.finfo(m.dtype).tiny)
    u2 = jnp.where(free, other / jnp.maximum(jnp.linalg.norm(other), jnp.finfo(m.dtype).tiny),
                   a2 / jnp.where(n2 > 0, n2, 1.0))
    u = jnp.stack([u1, u2, jnp.cross(u1, u2)], axis=1)
    vv = jnp.stack([v1, v2, jnp.cross(v1, v2)], axis=1)
    rot = jnp.where(n1 > 0, u @ vv.T, jnp.eye(3, dtype=m.dtype))
    return rot, mu_t - rot @ mu_s


def align_to_reference(
    points: Float[Array, "F S P 3"], weights: Float[Array, "F S P"], ref: Float[Array, "S P 3"],
    ref_weights: Float[Array, "S P"],
) -> tuple[Float[Array, "F S 3 3"], Float[Array, "F S 3"]]:
    """Every frame's cloud aligned to the reference (:func:`closed_form_align`, weights =
    presence x reference presence): ``R x + t`` maps a frame's points onto ``ref``."""
    align = jax.vmap(jax.vmap(closed_form_align, in_axes=(0, 0, 0)), in_axes=(0, None, 0))
    return align(points, ref, weights * ref_weights[None])


@jax.jit
def procrustes(
    points: Float[Array, "F S P 3"],
    weights: Float[Array, "F S P"],
    ref: Float[Array, "S P 3"],
    ref_weights: Float[Array, "S P"],
) -> tuple[Float[Array, "S P 3"], Float[Array, "F S 3 3"], Float[Array, "F S 3"], Float[Array, "S P"]]:
    """Generalised Procrustes per segment (masked), vmapped over frames and segments.

    Iterates: align every frame's cloud to the reference (Kabsch, weights = presence x
    reference presence), reference <- weighted mean of the aligned clouds, until no
    reference point moves by more than ``_GPA_TOL`` (at most ``_GPA_MAX_PASSES``
    passes). Returns the mean cloud, each frame's alignment ``(R, t)`` (``R x + t`` maps
    the frame to the mean) and each point's RMS scatter about the mean.
    """
    def aligned(ref, ref_w):
        rot, t = align_to_reference(points, weights, ref, ref_w)
        return rot, t, jnp.einsum("fsij,fspj->fspi", rot, points) + t[:, :, None, :]

    def update(carry):
        ref, ref_w, _, passes = carry
        _, _, cloud = aligned(ref, ref_w)
        total = jnp.sum(weights, axis=0)
        mean = jnp.sum(weights[..., None] * cloud, axis=0) / jnp.maximum(total, 1e-12)[..., None]
        new_w = (total > 0).astype(ref_w.dtype)
        move = jnp.max(jnp.where(new_w[..., None] > 0, jnp.abs(mean - ref), 0.0))
        return mean, new_w, move, passes + 1

    def more(carry):
        _, _, move, passes = carry
        return (passes < _GPA_MAX_PASSES) & (move > _GPA_TOL)

    init = (ref, ref_weights, jnp.asarray(jnp.inf, ref.dtype), jnp.asarray(0))
    ref, ref_w, _, _ = jax.lax.while_loop(more, update, init)
    rot, t, cloud = aligned(ref, ref_w)
    sq = jnp.sum((cloud - ref[None]) ** 2, axis=-1)
    rms = jnp.sqrt(jnp.sum(weights * sq, axis=0) / jnp.maximum(jnp.sum(weights, axis=0), 1.0))
    return ref, rot, t, rms
