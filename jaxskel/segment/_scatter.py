"""How rigid each group of a segmentation is, marker by marker: its Procrustes scatter.

A group's markers, posed frame by frame onto their mean shape by generalised Procrustes
(:func:`jaxskel._math.procrustes.procrustes`, masked: a frame counts for a group when it
shows three or more of its markers), leave each marker an RMS distance from its place in
that mean shape. A rigid group leaves every marker at the noise level; two segments
clustered as one leave the markers of the smaller part several times further out,
because one rigid pose per frame cannot follow both parts. Unlike the rigid skeleton's
residuals, this reading is taken from the segmentation alone: no joint is fitted, so a
joined group does not bend the rest of the body and raise the median with it.

A marker is *flagged* when its scatter exceeds ``FLAG_FACTOR`` times the median scatter
of all markers in groups of three or more, and the median by ``FLAG_MARGIN`` metres (the
rule of :attr:`jaxskel.skeleton.Skeleton.nonrigid_markers`, read here on the groups).
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from .._math.outliers import above_median
from .._math.padding import bucket_size
from .._math.procrustes import procrustes
from .._runtime import program_cache as _program_cache

__all__ = ["FLAG_FACTOR", "FLAG_MARGIN", "crowded_flags", "marker_scatter", "scatter_flags"]

#: A marker's scatter over this many times the median is flagged ...
FLAG_FACTOR = 3.0
#: ... when it is also this far (m) over the median.
FLAG_MARGIN = 1e-3
#: Frames read, evenly spaced over the recording: the scatter is an RMS over frames, and
#: two thousand of them fix it to well under the noise.
MAX_FRAMES = 2048


def marker_scatter(positions: np.ndarray, marker_segment: np.ndarray, *, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Each marker's RMS distance (m) from its group's Procrustes mean shape.

    ``positions`` is ``(F, M, 3)`` with NaN where a marker is missing, ``marker_segment``
    ``(M,)`` the group of each marker (``-1``: left out). NaN for markers left out, in a
    group of fewer than three markers, or never seen with two more of their group.
    Groups are padded to bucketed shapes (:func:`jaxskel._math.padding.bucket_size`), so
    that segmentations of different counts reuse one compiled program.
    """
    positions = np.asarray(positions, dtype=float)
    segment = np.asarray(marker_segment)
    if positions.ndim != 3 or positions.shape[-1] != 3:
        raise InputError(f"positions must be (frames, markers, 3) in metres, got shape {positions.shape}")
    if segment.shape != positions.shape[1:2] or not np.issubdtype(segment.dtype, np.integer):
        raise InputError(f"marker_segment must hold one integer group per marker ({positions.shape[1]}), got "
                         f"{segment.dtype} of shape {segment.shape}; pass Segmentation.marker_segment")
    segment = segment.astype(int)
    scatter = np.full(segment.shape, np.nan)
    groups = [np.flatnonzero(segment == s) for s in range(int(segment.max(initial=-1)) + 1)]
    groups = [g for g in groups if g.size >= 3]
    if not groups or positions.shape[0] == 0:
        return scatter
    frames = np.unique(np.linspace(0, positions.shape[0] - 1, min(positions.shape[0], max_frames)).round().astype(int))
    n_f, n_s, n_p = bucket_size(frames.size), bucket_size(len(groups), minimum=8), bucket_size(
        max(g.size for g in groups), minimum=8)
    index = np.zeros((n_s, n_p), dtype=int)
    real = np.zeros((n_s, n_p), dtype=bool)
    for s, g in enumerate(groups):
        index[s, : g.size], real[s, : g.size] = g, True
    sub = positions[frames][:, index]  # (f, S, P, 3)
    seen = np.isfinite(sub).all(axis=-1) & real[None]
    seen &= seen.sum(axis=-1, keepdims=True) >= 3  # a frame poses a group with three of its markers
    pts = np.zeros((n_f, n_s, n_p, 3))
    weights = np.zeros((n_f, n_s, n_p))
    pts[: frames.size] = np.where(seen[..., None], sub, 0.0)
    weights[: frames.size] = seen
    first = np.argmax(weights.sum(axis=-1), axis=0)  # per group: its best-covered frame
    cols = np.arange(n_s)
    _, _, _, rms = _program_cache.call(procrustes, pts, weights, pts[first, cols], weights[first, cols])
    rms = np.asarray(rms)
    counted = weights.sum(axis=0) >= 3
    for s, g in enumerate(groups):
        scatter[g] = np.where(counted[s, : g.size], rms[s, : g.size], np.nan)
    return scatter


def scatter_flags(scatter: np.ndarray) -> np.ndarray:
    """The markers whose scatter is over ``FLAG_FACTOR`` x the median and the median +
    ``FLAG_MARGIN`` (boolean, ``False`` where the scatter is NaN)."""
    return above_median(scatter, FLAG_FACTOR, FLAG_MARGIN)


def crowded_flags(marker_segment: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """The flagged markers of groups of three or more markers that hold two or more flagged
    markers (indices, ascending): the groups that may be two segments clustered as one."""
    segment = np.asarray(marker_segment, dtype=int)
    flags = np.asarray(flags, dtype=bool) & (segment >= 0)
    if not flags.any():
        return np.zeros(0, dtype=int)
    sizes = np.bincount(segment[segment >= 0], minlength=segment.max() + 1)
    counts = np.bincount(segment[flags], minlength=segment.max() + 1)
    crowded = flags & (counts[np.maximum(segment, 0)] >= 2) & (sizes[np.maximum(segment, 0)] >= 3)
    return np.flatnonzero(crowded)
