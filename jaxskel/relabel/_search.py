"""Host side of the fragment distances D: sampling, candidates, padding, weights.

Decides what the JAX kernels of :mod:`jaxskel.relabel._distance` compute and
pads every array to bucket sizes (:func:`jaxskel._math.padding.bucket_size`) so that a few
compiled shapes serve recordings of many sizes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from .._math.padding import bucket_size
from ._distance import (
    distance_spread,
    pair_distance_at,
    refine_min_distance,
    sampled_min_distance,
)
from ._fragments import Fragments

__all__ = ["sampled_distance", "candidate_pairs", "rigid_weight", "PairSearch"]

# Sampled frames per time block of the coarse pass.
_BLOCK = 8
# Fragment pairs per vmapped batch of the search.
_CHUNK = 64
# Search grid half-width: a (2h+1)^2 grid of frame pairs per level.
_HALF_WIDTH = 3
# References gathered per pair for the local alignment (the rest weigh ~0).
_N_NEAREST = 24
# Relative weight floor of the local alignment (see _relabel_distance._pair_distance).
_WEIGHT_FLOOR = 1e-6
# Rigidity is judged on about _SPREAD_FRAMES frames spread over the recording,
# and only over at least _MIN_SHARED_FRAMES shared frames.
_SPREAD_FRAMES = 1024
_MIN_SHARED_FRAMES = 10
_MIN_RIGID_WEIGHT = 1e-12


def _pad(a: np.ndarray, shape: tuple[int, ...], fill: Any = 0) -> np.ndarray:
    out = np.full(shape, fill, dtype=a.dtype)
    out[tuple(slice(0, s) for s in a.shape)] = a
    return out


def _padded_rows(n: int) -> int:
    """Rows padded to a bucket that is a whole number of _CHUNK batches."""
    return _CHUNK * bucket_size(-(-max(n, 1) // _CHUNK), minimum=1)


def sampled_distance(
    xf: Float[np.ndarray, "F K 3"],
    mf: Bool[np.ndarray, "F K"],
    frags: Fragments,
    interval: int,
    min_common: int,
) -> tuple[Float[np.ndarray, "K K"], Int[np.ndarray, "K K"], Int[np.ndarray, "K K"], int]:
    """The paper's coarse D on sampled frames: (D, frame of i, frame of j, number of samples).

    Samples: every ``interval`` frames plus the middle frame of each fragment
    the grid misses (frames with fewer than ``min_common`` markers are
    skipped), grouped in time blocks of _BLOCK samples for the tiled kernel.
    """
    n_frames, k = mf.shape
    grid = np.arange(0, n_frames, interval)
    missed = ~mf[grid].any(axis=0)
    samples = np.unique(np.concatenate([grid, (frags.start + frags.stop)[missed] // 2]))
    samples = samples[mf[samples].sum(axis=1) >= min_common]
    n_blocks = -(-samples.size // _BLOCK)
    # Padding: sample index sp-1 is an empty sample, marker index kp-1 is never present.
    sp, kp = bucket_size(samples.size + 1), bucket_size(k + 1, minimum=8)
    block_samples = np.full((n_blocks + 1, _BLOCK), sp - 1, dtype=np.int32)
    block_samples[:n_blocks].ravel()[: samples.size] = np.arange(samples.size)
    alive = [np.flatnonzero(mf[samples[b[b < samples.size]]].any(axis=0)) for b in block_samples[:n_blocks]]
    width = bucket_size(max((a.size for a in alive), default=1), minimum=8)
    block_alive = np.full((n_blocks + 1, width), kp - 1, dtype=np.int32)
    for b, a in enumerate(alive):
        block_alive[b, : a.size] = a
    first, second = np.triu_indices(n_blocks)
    # Padding rows pair the empty block (index n_blocks) with itself.
    block_pairs = np.full((bucket_size(first.size, minimum=8), 2), n_blocks, dtype=np.int32)
    block_pairs[: first.size] = np.stack([first, second], axis=1)
    d, fi, fj = sampled_min_distance(
        jnp.asarray(_pad(xf[samples], (sp, kp, 3))),
        jnp.asarray(_pad(mf[samples], (sp, kp))),
        jnp.asarray(block_samples),
        jnp.asarray(block_alive),
        jnp.asarray(block_pairs),
        min_common=min_common,
    )
    frame = np.append(samples, 0)  # sample index -> frame; the padding sample is never a minimum
    fi = frame[np.minimum(np.asarray(fi)[:k, :k], samples.size)]
    fj = frame[np.minimum(np.asarray(fj)[:k, :k], samples.size)]
    return np.asarray(d)[:k, :k], fi, fj, int(samples.size)


def candidate_pairs(
    distance: Float[np.ndarray, "K K"], compatible: Bool[np.ndarray, "K K"], frags: Fragments, n: int
) -> Int[np.ndarray, "P 2"]:
    """Fragment pairs worth searching: for each fragment its ``n`` nearest in D
    and its ``n`` nearest in time before and after. Unique rows (i, j), i < j.
    """
    k = frags.size
    n = min(n, k)
    row = np.repeat(np.arange(k), n)
    picks = []
    by_distance = np.argsort(np.where(compatible, distance, np.inf), axis=1, kind="stable")[:, :n]
    ok = np.take_along_axis(compatible & np.isfinite(distance), by_distance, axis=1)
    picks.append(np.stack([row[ok.ravel()], by_distance[ok]], axis=1))
    # Frames from the end of i to the start of j (inf unless j starts after i).
    gap = np.where(
        frags.start[None, :] >= frags.stop[:, None], frags.start[None, :] - frags.stop[:, None], np.inf
    )
    for g in (gap, gap.T):  # successors of i, then predecessors of i
        nearest = np.argsort(g, axis=1, kind="stable")[:, :n]
        ok = np.isfinite(np.take_along_axis(g, nearest, axis=1))
        picks.append(np.stack([row[ok.ravel()], nearest[ok]], axis=1))
    pairs = np.sort(np.concatenate(picks), axis=1)
    return np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0)


def gap_frames(frags: Fragments, pairs: Int[np.ndarray, "P 2"]) -> Int[np.ndarray, "P 2"]:
    """(frame of i, frame of j) bounding the gap between two non-overlapping fragments."""
    i, j = pairs[:, 0], pairs[:, 1]
    i_first = (frags.stop[i] <= frags.start[j])[:, None]
    return np.where(
        i_first,
        np.stack([frags.stop[i] - 1, frags.start[j]], axis=1),
        np.stack([frags.start[i], frags.stop[j] - 1], axis=1),
    )


def search_steps(interval: int) -> Int[np.ndarray, " L"]:
    """Grid steps of the coarse-to-fine search, from interval/h down to one frame.

    The first level spans +-interval. A minimum found on a grid of step s lies
    within s/2 of a grid point, so the next level's span ``h s'`` need only
    reach s/2: the step shrinks by 2h per level.
    """
    steps, s = [], max(1, math.ceil(interval / _HALF_WIDTH))
    while s > 1:
        steps.append(s)
        s = max(1, math.ceil(s / (2 * _HALF_WIDTH)))
    steps.append(1)
    return np.asarray(steps, dtype=np.int32)


def rigid_weight(
    xf: Float[np.ndarray, "F K 3"],
    mf: Bool[np.ndarray, "F K"],
    xr: Float[np.ndarray, "F C 3"],
    mr: Bool[np.ndarray, "F C"],
    tolerance: float,
) -> Float[np.ndarray, "K C"]:
    """How rigidly each reference moves with each fragment: ``exp(-std^2 / (2 tol^2))``.

    ``std`` is the standard deviation over time of their distance (Kirk §3.1),
    taken on about _SPREAD_FRAMES evenly spaced frames. With fewer than
    _MIN_SHARED_FRAMES shared frames rigidity is unknown and the weight is
    ``exp(-1/2)``, as if ``std = tol``. At least _MIN_RIGID_WEIGHT.
    """
    every = max(1, xf.shape[0] // _SPREAD_FRAMES)
    spread, shared = distance_spread(
        jnp.asarray(xf[::every]), jnp.asarray(mf[::every]), jnp.asarray(xr[::every]), jnp.asarray(mr[::every])
    )
    spread, shared = np.asarray(spread), np.asarray(shared) * every
    rigid = np.where(shared >= _MIN_SHARED_FRAMES, np.exp(-0.5 * (spread / tolerance) ** 2), math.exp(-0.5))
    # Strictly positive: a zero weight is reserved for excluded references.
    return np.maximum(rigid, _MIN_RIGID_WEIGHT)


def pair_weights(
    rigid: Float[np.ndarray, "K C"], pairs: Int[np.ndarray, "P 2"], exclude: Int[np.ndarray, "P E"]
) -> Float[np.ndarray, "P C"]:
    """Per-pair reference weights ``rigid[i] * rigid[j]``, zero at the excluded references (-1: none)."""
    w = rigid[pairs[:, 0]] * rigid[pairs[:, 1]]
    rows = np.arange(pairs.shape[0])
    for col in range(exclude.shape[1]):
        ok = exclude[:, col] >= 0
        w[rows[ok], exclude[ok, col]] = 0.0
    return w


@dataclasses.dataclass(frozen=True)
class PairSearch:
    """The padded, device-resident inputs of the searches over one set of fragment pairs.

    Built once per recording; :meth:`search` runs the coarse-to-fine search
    (:func:`~jaxskel.relabel._distance.refine_min_distance`) and :meth:`at` the
    distance at given frames, both against a set of reference markers.
    """

    xq: Any  # (Fp, Kp, 3) jax array, the fragments
    mq: Any  # (Fp, Kp)
    n_frames: int
    n_columns: int  # Kp: fragments and references are both padded to this many columns
    steps: Any  # (L,)
    radius: Any  # ()
    floor: Any  # ()
    min_common: int

    @classmethod
    def build(
        cls, xf: np.ndarray, mf: np.ndarray, interval: int, radius: float, min_common: int
    ) -> PairSearch:
        fp, kp = bucket_size(xf.shape[0]), bucket_size(xf.shape[1], minimum=8)
        return cls(
            xq=jnp.asarray(_pad(xf, (fp, kp, 3))),
            mq=jnp.asarray(_pad(mf, (fp, kp))),
            n_frames=fp,
            n_columns=kp,
            steps=jnp.asarray(search_steps(interval)),
            radius=jnp.asarray(float(radius)),
            floor=jnp.asarray(_WEIGHT_FLOOR),
            min_common=min_common,
        )

    def _references(self, xr: np.ndarray, mr: np.ndarray):
        shape = (self.n_frames, self.n_columns)
        return jnp.asarray(_pad(xr, (*shape, 3))), jnp.asarray(_pad(mr, shape))

    def search(
        self,
        xr: Float[np.ndarray, "F C 3"],
        mr: Bool[np.ndarray, "F C"],
        weights: Float[np.ndarray, "P C"],
        pairs: Int[np.ndarray, "P 2"],
        seeds: Int[np.ndarray, "P 2"],
    ) -> tuple[Float[np.ndarray, " P"], Int[np.ndarray, "P 2"]]:
        """Minimum distance of each pair over a window around its seed frames, and where."""
        n = pairs.shape[0]
        rows = _padded_rows(n)
        xr, mr = self._references(xr, mr)
        best, frames = refine_min_distance(
            self.xq, self.mq, xr, mr,
            jnp.asarray(_pad(weights, (rows, self.n_columns))),
            jnp.asarray(_pad(pairs.astype(np.int32), (rows, 2))),
            jnp.asarray(_pad(seeds.astype(np.int32), (rows, 2))),
            self.steps, self.radius, self.floor,
            half_width=_HALF_WIDTH, n_nearest=min(_N_NEAREST, self.n_columns),
            min_common=self.min_common, chunk=_CHUNK,
        )  # fmt: skip
        return np.asarray(best)[:n], np.asarray(frames)[:n]

    def at(
        self,
        xr: Float[np.ndarray, "F C 3"],
        mr: Bool[np.ndarray, "F C"],
        weights: Float[np.ndarray, "P C"],
        pairs: Int[np.ndarray, "P 2"],
        frames: Int[np.ndarray, "P 2"],
    ) -> Float[np.ndarray, " P"]:
        """Distance of each pair at its given frames (inf where not comparable)."""
        n = pairs.shape[0]
        rows = _padded_rows(n)
        xr, mr = self._references(xr, mr)
        d = pair_distance_at(
            self.xq, self.mq, xr, mr,
            jnp.asarray(_pad(weights, (rows, self.n_columns))),
            jnp.asarray(_pad(pairs.astype(np.int32), (rows, 2))),
            jnp.asarray(_pad(frames.astype(np.int32), (rows, 2))),
            self.radius, self.floor,
            n_nearest=min(_N_NEAREST, self.n_columns), min_common=self.min_common,
        )  # fmt: skip
        return np.asarray(d)[:n]
