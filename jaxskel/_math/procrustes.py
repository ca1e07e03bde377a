"""Generalised Procrustes analysis of point clouds (masked), vmapped over frames and sets."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .rotation import horn_align

__all__ = ["align_to_reference", "procrustes"]

#: Generalised Procrustes stops when no point of the mean cloud moves more than this
#: (metres) in a pass, or after ``_GPA_MAX_PASSES``: the mean converges linearly, and a
#: tenth of a micrometre is far below any marker noise.
_GPA_TOL, _GPA_MAX_PASSES = 1e-7, 8


def align_to_reference(
    points: Float[Array, "F S P 3"], weights: Float[Array, "F S P"], ref: Float[Array, "S P 3"],
    ref_weights: Float[Array, "S P"],
) -> tuple[Float[Array, "F S 3 3"], Float[Array, "F S 3"]]:
    """Every frame's cloud aligned to the reference (Horn, weights = presence x reference
    presence): ``R x + t`` maps a frame's points onto ``ref``."""
    align = jax.vmap(jax.vmap(horn_align, in_axes=(0, 0, 0)), in_axes=(0, None, 0))
    return align(points, ref, weights * ref_weights[None])


@jax.jit
def procrustes(
    points: Float[Array, "F S P 3"],
    weights: Float[Array, "F S P"],
    ref: Float[Array, "S P 3"],
    ref_weights: Float[Array, "S P"],
) -> tuple[Float[Array, "S P 3"], Float[Array, "F S 3 3"], Float[Array, "F S 3"], Float[Array, "S P"]]:
    """Generalised Procrustes per segment (masked), vmapped over frames and segments.

    Iterates: align every frame's cloud to the reference (Horn, weights = presence x
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
