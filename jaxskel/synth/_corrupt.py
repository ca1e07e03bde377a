"""Realistic corruptions of clean marker trajectories, each seeded and switchable.

Applied by :func:`jaxskel.synth.simulate` in this order: soft-tissue artefact
(moves markers on their segment), measurement noise, jumps (placed knowing where
the gaps will be), gaps (NaN), ghost markers (extra columns), and passive-system
relabelling (a new label after every gap). All functions are vectorised over
frames; loops run only over a handful of events (jumps, ghosts).
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

from .._errors import InputError
from ._bodies import Body
from ._motion import smooth_signal

__all__ = [
    "soft_tissue_displacement",
    "gap_mask",
    "jump_offsets",
    "ghost_trajectories",
    "relabel_after_gaps",
]


def soft_tissue_displacement(
    body: Body,
    angles: tuple[Float[np.ndarray, "F k"], ...],
    times: Float[np.ndarray, " F"],
    amplitude: float,
    rng: np.random.Generator,
) -> Float[np.ndarray, "F M 3"]:
    """Skin-marker displacement in each marker's segment frame, RMS norm ``amplitude``.

    Real soft-tissue artefact is driven by the neighbouring joints: muscles bulge
    and skin slides as the joints of the segment move. For marker m on segment s

        d_m(t) = c_m (phi_s(t) W_m + 0.3 n_m(t)) - mean_t,

    where phi_s stacks the normalised angles ``(theta - mid) / half_range`` of every
    joint touching s, W_m is a random (K, 3) Gaussian matrix, n_m a smooth
    low-frequency (0.1-0.7 Hz) random signal, and c_m scales the zero-mean
    displacement to an RMS length of ``amplitude`` metres.
    """
    features = np.concatenate(
        [
            (a - lim.mean(axis=1)) / np.maximum(0.5 * (lim[:, 1] - lim[:, 0]), 1e-9)
            for a, lim in zip(angles, body.joint_limits, strict=True)
        ],
        axis=1,
    )  # (F, K)
    # Which angle columns belong to a joint touching each marker's segment.
    joint_of_column = np.repeat(np.arange(body.n_joints), [a.shape[1] for a in angles])
    seg = body.marker_segment
    touches = (body.edges[joint_of_column, 0][None, :] == seg[:, None]) | (
        body.edges[joint_of_column, 1][None, :] == seg[:, None]
    )  # (M, K)
    weights = rng.normal(size=(body.n_markers, features.shape[1], 3)) * touches[..., None]
    wobble = smooth_signal(times, 3 * body.n_markers, rng, frequency=(0.1, 0.7))
    disp = np.einsum("fk,mkc->fmc", features, weights) + 0.3 * wobble.reshape(-1, body.n_markers, 3)
    disp -= disp.mean(axis=0)
    rms = np.sqrt((disp**2).sum(-1).mean(axis=0))
    return disp * (amplitude / np.maximum(rms, 1e-12))[None, :, None]


def gap_mask(
    n_frames: int,
    n_markers: int,
    gaps_per_marker: int,
    length_frames: tuple[int, int],
    rng: np.random.Generator,
) -> Bool[np.ndarray, "F M"]:
    """(F, M) True where a marker is occluded: exactly ``gaps_per_marker`` gaps each.

    Gap lengths are uniform integers in ``length_frames``. Gaps never touch the
    first or last frame and are separated by at least two visible frames, so each
    gap has a visible sample on both sides (a marker reappears after every gap).
    Starts are placed uniformly by "stars and bars": sorted uniform draws over the
    free frames, shifted by the lengths (plus separations) of the earlier gaps.
    """
    n_gaps = int(gaps_per_marker)
    if n_gaps == 0:
        return np.zeros((n_frames, n_markers), dtype=bool)
    lo, hi = length_frames
    lengths = rng.integers(lo, hi + 1, size=(n_markers, n_gaps))
    separation = 2
    free = n_frames - lengths.sum(axis=1) - separation * (n_gaps + 1)
    if free.min() < 0:
        raise InputError(
            f"{n_gaps} gaps of up to {hi} frames do not fit in {n_frames} frames; "
            "use fewer gaps, a shorter gap_length or a longer duration"
        )
    draws = np.sort(rng.uniform(0.0, 1.0, size=(n_markers, n_gaps)), axis=1)
    slack = np.floor(draws * (free[:, None] + 1)).astype(int)
    before = np.cumsum(lengths + separation, axis=1) - (lengths + separation)
    starts = separation + slack + before
    frames = np.arange(n_frames)[:, None, None]
    inside = (frames >= starts[None]) & (frames < (starts + lengths)[None])
    return inside.any(axis=-1)


def jump_offsets(
    missing: Bool[np.ndarray, "F M"],
    n_jumps: int,
    size: tuple[float, float],
    length_frames: tuple[int, int],
    rng: np.random.Generator,
) -> tuple[Float[np.ndarray, "F M 3"], Bool[np.ndarray, "F M"]]:
    """Sporadic jumps: a marker displaced by ``size`` metres for a few frames.

    Reconstruction is worst right next to an occlusion, so when there are gaps
    half of the ``n_jumps`` events sit against a gap edge (just before it starts
    or just after it ends); the others are anywhere. Each event moves one marker by
    a constant offset of random direction and length uniform in ``size`` for a
    length uniform in ``length_frames``. Returns the offsets (F, M, 3), zero
    outside jumps, and the (F, M) mask of jumped visible samples.
    """
    n_frames, n_markers = missing.shape
    offsets = np.zeros((n_frames, n_markers, 3))
    edge_f, edge_m = np.nonzero(missing[1:] != missing[:-1])  # change between f and f + 1
    for event in range(int(n_jumps)):
        length = int(rng.integers(length_frames[0], length_frames[1] + 1))
        if edge_f.size and event % 2 == 0:
            k = int(rng.integers(edge_f.size))
            marker = int(edge_m[k])
            # Visible run ends at edge_f[k] (gap starts after it) or starts at edge_f[k] + 1.
            start = edge_f[k] - length + 1 if missing[edge_f[k] + 1, marker] else edge_f[k] + 1
        else:
            marker = int(rng.integers(n_markers))
            start = int(rng.integers(0, max(n_frames - length, 0) + 1))
        direction = rng.normal(size=3)
        step = direction / np.linalg.norm(direction) * rng.uniform(*size)
        start = max(int(start), 0)
        offsets[start : start + length, marker] += step
    jumped = (np.abs(offsets).sum(-1) > 0) & ~missing
    return offsets, jumped


def ghost_trajectories(
    positions: Float[np.ndarray, "F M 3"],
    n_ghosts: int,
    length_frames: tuple[int, int],
    rng: np.random.Generator,
) -> Float[np.ndarray, "F G 3"]:
    """Short-lived spurious markers (reflections, merged camera rays), NaN elsewhere.

    Half of them shadow a real marker at a fixed 3-15 cm offset (a reflection off
    the body); the others hang still at a random point of the markers' bounding box
    at the time they appear (a stray reflection in the room). Lifetimes are uniform
    in ``length_frames``.
    """
    n_frames, n_markers, _ = positions.shape
    out = np.full((n_frames, int(n_ghosts), 3), np.nan)
    for g in range(int(n_ghosts)):
        length = int(rng.integers(length_frames[0], length_frames[1] + 1))
        start = int(rng.integers(0, max(n_frames - length, 0) + 1))
        span = slice(start, start + length)
        if g % 2 == 0:
            direction = rng.normal(size=3)
            offset = direction / np.linalg.norm(direction) * rng.uniform(0.03, 0.15)
            out[span, g] = positions[span, int(rng.integers(n_markers))] + offset
        else:
            frame = positions[start]
            visible = frame[~np.isnan(frame[:, 0])]
            box = visible if visible.size else np.zeros((1, 3))
            out[span, g] = rng.uniform(box.min(axis=0) - 0.1, box.max(axis=0) + 0.1)
    return out


def relabel_after_gaps(
    present: Bool[np.ndarray, "F M"],
) -> tuple[Int[np.ndarray, "F M"], Int[np.ndarray, " N"]]:
    """Passive-system labelling: every visible run after a gap gets a new label.

    Returns ``column`` (F, M): the output column of each visible sample (-1 where
    missing), and ``physical`` (N,): the marker behind each output column. The
    first visible run of marker m keeps column m; later runs get columns M, M + 1,
    ... numbered in order of appearance (as a tracker would number new trajectories).
    """
    n_frames, n_markers = present.shape
    begins = present & ~np.vstack([np.zeros((1, n_markers), bool), present[:-1]])
    run = np.cumsum(begins, axis=0) * present  # 1-based run index, 0 where missing
    later_f, later_m = np.nonzero(begins & (run > 1))
    order = np.lexsort((later_m, later_f))  # by start frame, then marker
    new_column = np.empty(order.size, dtype=int)
    new_column[order] = n_markers + np.arange(order.size)
    # Map (marker, run) -> column through a dense table (runs per marker are few).
    table = np.tile(np.arange(n_markers), (int(run.max(initial=1)) + 1, 1))
    table[run[later_f, later_m], later_m] = new_column
    column = np.where(present, table[run, np.arange(n_markers)[None, :]], -1)
    physical = np.concatenate([np.arange(n_markers), later_m[order]])
    return column, physical
