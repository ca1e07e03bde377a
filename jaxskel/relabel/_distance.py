"""Pose-invariant distances between marker fragments (Kirk et al. 2005, §4), in JAX.

For two fragments i and j that are never seen together the paper defines

    D_ij = min over frames a in p_i, b in p_j of | m_{i,a} - A_ab m_{j,b} |,

where ``A_ab = (R, t)`` is the rigid motion that best aligns frame b onto frame a
(Horn) over the markers present in both. If i and j are one physical marker,
some pair of frames shows (locally) the same pose and D_ij is of the order of
the noise; two different markers stay about their spacing apart.

Kernels:

* :func:`sampled_min_distance` -- the paper's coarse pass. Every unordered pair
  (a, b) of sampled frames is aligned once, uniformly over the shared markers,
  and that alignment serves every fragment pair: ``E[i, j] = |x_a[i] - A_ab x_b[j]|``
  is an (M, M) matrix per frame pair with a running minimum (and its argmin
  frames) kept over pairs. A rigid motion preserves distances, so the
  transposed matrix is the candidate for "i at frame b, j at frame a"; one
  alignment serves both orders.
* :func:`refine_min_distance` -- the paper's local search around the best
  samples, coarse to fine, for chosen fragment pairs. Here each alignment
  belongs to one fragment pair and is weighted towards the reference markers
  that move with it (see :func:`_pair_distance`): on an articulated body the
  segment carrying the marker matters, the far limbs do not.
* :func:`pair_distance_at` -- the same distance at given frames, no search (the
  prediction error of a merge across its gap).
* :func:`distance_spread` -- standard deviation over time of the distance
  between markers; markers on one rigid segment keep it near the noise level
  (Kirk et al. §3.1), which is how co-moving neighbours are found.

Inputs are ``(x, mask)`` with missing samples zeroed; no NaN enters traced
code. ``inf`` marks pairs that could not be compared.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._math.rotation import horn_align

__all__ = [
    "sampled_min_distance",
    "refine_min_distance",
    "pair_distance_at",
    "distance_spread",
]


@functools.partial(jax.jit, static_argnames=("min_common",))
def sampled_min_distance(
    xs: Float[Array, "S M 3"],
    ms: Bool[Array, "S M"],
    block_samples: Int[Array, "B Bs"],
    block_alive: Int[Array, "B P"],
    block_pairs: Int[Array, "Q 2"],
    *,
    min_common: int = 4,
) -> tuple[Float[Array, "M M"], Int[Array, "M M"], Int[Array, "M M"]]:
    """The paper's D over all pairs of sampled frames, with the argmin frames.

    Sampled frames come in time blocks of ``Bs`` consecutive samples; only the
    ``P`` markers alive in a block (present in one of its samples) can have a
    finite distance there, so each block pair works on a (P, P) tile instead of
    the full (M, M) matrix. For a block pair (A, B) every frame pair (a in A,
    b in B) is aligned uniformly over all markers shared by a and b, and the
    tile ``E[i, j] = min_{a, b} |x_a[i] - A_ab x_b[j]|`` (i alive in A, j in B) is
    folded into a running minimum. Block pairs with A < B give the orientation
    "i seen before j"; the other one is the transpose, taken at the end.

    Parameters
    ----------
    xs, ms
        Positions and presence of M markers at S sampled frames. Index S-1 must
        be an empty sample and index M-1 a never-present marker: padding
        entries of the block tables point there.
    block_samples
        (B, Bs) sample indices of each block (padding: S-1).
    block_alive
        (B, P) markers alive in each block (padding: M-1).
    block_pairs
        (Q, 2) block index pairs (A, B) with A <= B (padding rows: an all-padding block).
    min_common
        Frame pairs sharing fewer markers are not aligned (Horn needs >= 3).

    Returns
    -------
    d, fi, fj
        ``d[i, j] = min |x_{fi}[i] - A x_{fj}[j]|`` (metres, inf if never
        comparable) and the sample indices ``fi[i, j]`` (frame of i) and
        ``fj[i, j]`` (frame of j) of the minimum. ``d`` is symmetric.
    """
    n_markers = xs.shape[1]

    def align(a, b):
        common = ms[a] & ms[b]
        rot, shift = horn_align(xs[b], xs[a], common.astype(xs.dtype))
        return rot, shift, jnp.sum(common) >= min_common

    def step(carry, pair):
        best, fi, fj = carry
        sa, sb = block_samples[pair[0]], block_samples[pair[1]]
        ia, ib = block_alive[pair[0]], block_alive[pair[1]]
        fa, fb = (g.ravel() for g in jnp.meshgrid(sa, sb, indexing="ij"))
        rot, shift, enough = jax.vmap(align)(fa, fb)  # (Bs*Bs, ...)
        p = xs[fa][:, ia]  # (Bs*Bs, P, 3): i at frame a
        q = jnp.einsum("nij,npj->npi", rot, xs[fb][:, ib]) + shift[:, None, :]
        # Centre on the tile's first marker to keep the expanded square accurate.
        c = p[:, :1]
        p, q = p - c, q - c
        d2 = (
            jnp.sum(p * p, -1)[:, :, None]
            + jnp.sum(q * q, -1)[:, None, :]
            - 2.0 * p @ jnp.swapaxes(q, 1, 2)
        )
        pair_ok = enough & (fa != fb)  # a frame is not compared with itself
        ok = ms[fa][:, ia][:, :, None] & ms[fb][:, ib][:, None, :] & pair_ok[:, None, None]
        d2 = jnp.where(ok, jnp.maximum(d2, 0.0), jnp.inf)
        k = jnp.argmin(d2, axis=0)
        tile = jnp.min(d2, axis=0)
        old = best[ia[:, None], ib[None, :]]
        better = tile < old
        best = best.at[ia[:, None], ib[None, :]].set(jnp.where(better, tile, old))
        fi = fi.at[ia[:, None], ib[None, :]].set(jnp.where(better, fa[k], fi[ia[:, None], ib[None, :]]))
        fj = fj.at[ia[:, None], ib[None, :]].set(jnp.where(better, fb[k], fj[ia[:, None], ib[None, :]]))
        return (best, fi, fj), None

    init = (
        jnp.full((n_markers, n_markers), jnp.inf, xs.dtype),
        jnp.zeros((n_markers, n_markers), block_samples.dtype),
        jnp.zeros((n_markers, n_markers), block_samples.dtype),
    )
    (best, fi, fj), _ = jax.lax.scan(step, init, block_pairs)
    # Symmetrise: "i at b, j at a" is stored at [j, i].
    use_t = best.T < best
    d = jnp.sqrt(jnp.where(use_t, best.T, best))
    return d, jnp.where(use_t, fj.T, fi), jnp.where(use_t, fi.T, fj)


def _pair_distance(
    xq: Float[Array, "F K 3"],
    mq: Bool[Array, "F K"],
    xr: Float[Array, "F C 3"],
    mr: Bool[Array, "F C"],
    ref_weight: Float[Array, " C"],
    near: Int[Array, " N"],
    i: Int[Array, ""],
    j: Int[Array, ""],
    a: Int[Array, ""],
    b: Int[Array, ""],
    radius: Float[Array, ""],
    floor: Float[Array, ""],
    min_common: int,
) -> Float[Array, ""]:
    """``|xq_a[i] - A xq_b[j]|``, A aligning the reference markers of frame b onto frame a.

    Only the references ``near`` (indices into C) take part. The Horn weight of
    reference k (present in both frames) is

        w_k = ref_weight_k * exp(-|xr_a[k] - xq_a[i]|^2 / (2 radius^2)) + floor * max(w),

    i.e. the references that move rigidly with the pair (``ref_weight``) and are
    near marker i; the small floor keeps the alignment defined (it falls back to
    the paper's uniform weights) when no weighted neighbour is present.
    ``radius = inf`` drops the proximity factor. References with zero
    ``ref_weight`` are left out entirely. inf if i is absent at a, j at b, or
    fewer than ``min_common`` references are shared.
    """
    xa, xb = xr[a, near], xr[b, near]
    # References with zero ref_weight (the ones under test) never take part.
    common = mr[a, near] & mr[b, near] & (ref_weight[near] > 0)
    r2 = jnp.sum((xa - xq[a, i]) ** 2, axis=-1)
    proximity = jnp.where(jnp.isinf(radius), 1.0, jnp.exp(-0.5 * r2 / radius**2))
    w = jnp.where(common, proximity * ref_weight[near], 0.0)
    w = jnp.where(common, w + floor * jnp.max(w) + jnp.finfo(xq.dtype).tiny, 0.0)
    rot, shift = horn_align(xb, xa, w)
    d = jnp.linalg.norm(xq[a, i] - (rot @ xq[b, j] + shift))
    ok = mq[a, i] & mq[b, j] & (jnp.sum(common) >= min_common)
    return jnp.where(ok, d, jnp.inf)


def _nearest_references(xq, xr, mr, ref_weight, i, frame, n_nearest):
    """Indices of the ``n_nearest`` weighted references closest to query i at ``frame``.

    Under the proximity weights only these matter; gathering them once makes
    every alignment of a search O(n_nearest) instead of O(C).
    """
    dist2 = jnp.sum((xr[frame] - xq[frame, i]) ** 2, axis=-1)
    score = jnp.where(mr[frame] & (ref_weight > 0), -dist2, -jnp.inf)
    return jax.lax.top_k(score, n_nearest)[1]


@functools.partial(jax.jit, static_argnames=("half_width", "n_nearest", "min_common", "chunk"))
def refine_min_distance(
    xq: Float[Array, "F K 3"],
    mq: Bool[Array, "F K"],
    xr: Float[Array, "F C 3"],
    mr: Bool[Array, "F C"],
    ref_weight: Float[Array, "P C"],
    pairs: Int[Array, "P 2"],
    seeds: Int[Array, "P 2"],
    steps: Int[Array, " L"],
    radius: Float[Array, ""],
    floor: Float[Array, ""],
    *,
    half_width: int = 3,
    n_nearest: int = 24,
    min_common: int = 4,
    chunk: int = 64,
) -> tuple[Float[Array, " P"], Int[Array, "P 2"]]:
    """Coarse-to-fine search of the best frame pair around each seed.

    For query pair ``(i, j)`` with seed frames ``(a, b)`` (a: frame of i), each
    level evaluates ``(a + u s, b + v s)`` for ``u, v in -h..h`` (s: the level's
    step; frames clipped to the recording) and moves the seed to the best one,
    so ``len(steps) (2h+1)^2`` alignments search a window of about
    ``h * sum(steps)`` frames. The seed itself is evaluated at every level, so
    the result never exceeds the seed's distance.

    The queries ``xq`` (fragments whose distance is wanted) and the references
    ``xr`` (markers the frames are aligned on) are separate arrays: the
    references may be the queries themselves (the paper) or the markers merged
    so far, weighted per pair by ``ref_weight`` (zero for the references under
    test, small for markers that do not move rigidly with the pair).

    Returns the minimum distance per pair (inf if no valid frame pair was met)
    and the frame pair achieving it. P must be a multiple of ``chunk``.
    """
    n_frames = xq.shape[0]
    offsets = jnp.arange(-half_width, half_width + 1, dtype=seeds.dtype)
    du, dv = (g.ravel() for g in jnp.meshgrid(offsets, offsets, indexing="ij"))
    distance = jax.vmap(
        _pair_distance, in_axes=(None, None, None, None, None, None, None, None, 0, 0, None, None, None)
    )

    def one(pair, seed, weight):
        i, j = pair[0], pair[1]
        near = _nearest_references(xq, xr, mr, weight, i, seed[0], n_nearest)

        def level(carry, step):
            best, a0, b0 = carry
            a = jnp.clip(a0 + du * step, 0, n_frames - 1)
            b = jnp.clip(b0 + dv * step, 0, n_frames - 1)
            d = distance(xq, mq, xr, mr, weight, near, i, j, a, b, radius, floor, min_common)
            k = jnp.argmin(d)
            better = d[k] < best
            return (
                jnp.where(better, d[k], best),
                jnp.where(better, a[k], a0),
                jnp.where(better, b[k], b0),
            ), None

        init = (jnp.asarray(jnp.inf, xq.dtype), seed[0], seed[1])
        (best, a, b), _ = jax.lax.scan(level, init, steps.astype(seeds.dtype))
        return best, jnp.stack([a, b])

    best, frames = jax.lax.map(
        lambda args: jax.vmap(one)(*args),
        (
            pairs.reshape(-1, chunk, 2),
            seeds.reshape(-1, chunk, 2),
            ref_weight.reshape(-1, chunk, ref_weight.shape[-1]),
        ),
    )
    return best.reshape(-1), frames.reshape(-1, 2)


@functools.partial(jax.jit, static_argnames=("n_nearest", "min_common"))
def pair_distance_at(
    xq: Float[Array, "F K 3"],
    mq: Bool[Array, "F K"],
    xr: Float[Array, "F C 3"],
    mr: Bool[Array, "F C"],
    ref_weight: Float[Array, "P C"],
    pairs: Int[Array, "P 2"],
    frames: Int[Array, "P 2"],
    radius: Float[Array, ""],
    floor: Float[Array, ""],
    *,
    n_nearest: int = 24,
    min_common: int = 4,
) -> Float[Array, " P"]:
    """:func:`_pair_distance` of each query pair at its given frame pair (no search)."""

    def one(pair, frame, weight):
        near = _nearest_references(xq, xr, mr, weight, pair[0], frame[0], n_nearest)
        return _pair_distance(
            xq, mq, xr, mr, weight, near, pair[0], pair[1], frame[0], frame[1], radius, floor, min_common
        )

    return jax.vmap(one)(pairs, frames, ref_weight)


@jax.jit
def distance_spread(
    xq: Float[Array, "F K 3"],
    mq: Bool[Array, "F K"],
    xr: Float[Array, "F C 3"],
    mr: Bool[Array, "F C"],
) -> tuple[Float[Array, "K C"], Int[Array, "K C"]]:
    """Standard deviation over time of each query-to-reference distance, and over how many frames.

    Taken over the frames where both are present (zero where they never are).
    One query at a time, so memory is O(F C).
    """

    def row(args):
        x, m = args
        d = jnp.linalg.norm(xr - x[:, None, :], axis=-1)
        w = (mr & m[:, None]).astype(xq.dtype)
        n = jnp.sum(w, axis=0)
        mean = jnp.sum(w * d, axis=0) / jnp.maximum(n, 1.0)
        var = jnp.sum(w * (d - mean) ** 2, axis=0) / jnp.maximum(n, 1.0)
        return jnp.sqrt(var), n.astype(jnp.int32)

    return jax.lax.map(row, (jnp.swapaxes(xq, 0, 1), mq.T))
