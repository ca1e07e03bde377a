"""Cleaning raw marker trajectories (Kirk et al. 2005, §3 opening paragraphs).

Optical systems report large errors just before they lose a marker and just
after they find it again, and markers sometimes jump by centimetres for a few
frames. Before any fitting, :func:`clean`

0. merges duplicate labels: two labels whose positions coincide (within
   ``duplicate_tolerance``) in every frame where both are seen, over at least
   ``duplicate_min_s`` of such frames, are one marker stored twice (some exports carry
   unnamed copies ``*N`` of named markers: docs/bench/evidence_from_docstrings.md).
   Two physical markers can never be that close (their centres are at least a marker diameter,
   >= 3 mm, apart), and a copy would otherwise count twice in every cost. The label
   kept is a named one over an unnamed ``*N``, then the one seen in more frames,
   then the first; it takes the copy's samples where it is itself missing;
1. rejects sporadic jumps: a sample further than ``jump_threshold`` from the
   robust local prediction from its own trajectory (window ``jump_window_s``) is marked
   missing. The threshold adapts to the marker: ``max(jump_threshold,
   median + jump_mad_factor * 1.4826 * MAD)`` of that marker's deviations, so fast
   but smooth motion (a running median follows it) is kept while a 3 cm blip is
   not. The prediction is velocity-compensated (see
   :func:`_running_median_deviation`), so steady fast motion is not mistaken
   for a jump; jumps lasting up to half the window (>= 2 frames) are caught;
2. trims ``trim_s`` seconds (at least one frame) at both ends of every
   contiguous run that borders a gap. Runs touching the first or last frame of
   the recording are not trimmed there: the marker was not lost, the recording
   merely started or stopped;
3. drops markers whose longest contiguous run is shorter than ``min_run_s``
   (0.5 s, as in the paper), including markers that are never present.

Everything is reported per marker in a :class:`CleaningReport` instead of printed.
This runs on the host (numpy): it is a cheap, one-off pass over the data.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .._errors import InputError
from ..io import Trial

__all__ = ["clean", "CleaningReport", "contiguous_runs", "find_duplicates"]


def contiguous_runs(present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start (inclusive) and stop (exclusive) indices of the True runs of a 1-D mask."""
    p = np.concatenate([[False], np.asarray(present, dtype=bool), [False]])
    d = np.diff(p.astype(np.int8))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


@dataclasses.dataclass(frozen=True)
class CleaningReport:
    """What :func:`clean` changed, per input marker.

    Attributes
    ----------
    labels
        Input marker labels (M,).
    present_before, present_after
        Present samples per marker before and after cleaning (after = 0 if dropped).
    jump_samples
        Samples rejected as jumps, per marker.
    trimmed_samples
        Samples removed at gap edges, per marker.
    longest_run_s
        Longest contiguous run per marker after jump rejection and trimming, seconds.
    dropped
        Labels of markers removed entirely, with the reason.
    settings
        The parameters used.
    duplicates
        Label of every duplicate merged away -> the label it was merged into (also in
        ``dropped``).
    """

    labels: tuple[str, ...]
    present_before: np.ndarray
    present_after: np.ndarray
    jump_samples: np.ndarray
    trimmed_samples: np.ndarray
    longest_run_s: np.ndarray
    dropped: dict[str, str]
    settings: dict[str, float]
    duplicates: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def kept_labels(self) -> tuple[str, ...]:
        return tuple(lab for lab in self.labels if lab not in self.dropped)

    def summary(self) -> str:
        """A short human-readable account."""
        n = len(self.labels)
        lines = [
            f"cleaning: {n} markers in, {n - len(self.dropped)} kept, {len(self.dropped)} dropped; "
            f"{int(self.jump_samples.sum())} jump samples rejected, "
            f"{int(self.trimmed_samples.sum())} gap-edge samples trimmed"
            + (f", {len(self.duplicates)} duplicate labels merged" if self.duplicates else "")
        ]
        for lab, why in self.dropped.items():
            lines.append(f"  dropped {lab}: {why}")
        return "\n".join(lines)

    __str__ = summary


def _nanmedian_last(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=-1)`` for short last axes, without numpy's per-call overhead.

    numpy's nanmedian goes through masked arrays per call (timing:
    docs/bench/evidence_from_docstrings.md); sorting sends NaNs to the end, so the
    median of the n finite values sits at (n - 1) // 2 and n // 2. All-NaN rows give
    NaN, as numpy's does.
    """
    ordered = np.sort(a, axis=-1)  # contiguous: counting NaNs here is cheaper than on a window view
    n = a.shape[-1] - np.count_nonzero(np.isnan(ordered), axis=-1)
    lo = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(ordered, (n // 2)[..., None].clip(max=a.shape[-1] - 1), axis=-1)[..., 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


@functools.lru_cache(maxsize=None)
def _sorting_network(width: int) -> tuple[tuple[int, int], ...]:
    """Comparators ``(i, j)``, ``i < j``, of Batcher's odd-even merge sort on ``width`` wires.

    Built for the next power of two and pruned to ``width``: the missing wires hold
    ``+inf``, so a comparator reaching one never moves a value and can be dropped.
    Applied in order (wire ``i`` takes the min, ``j`` the max) it sorts any input.
    """
    size = 1 << max(0, (width - 1).bit_length())
    out = []
    t = 1
    while t < size:
        k = t
        while k >= 1:
            for j in range(k % t, size - k, 2 * k):
                for i in range(min(k, size - j - k)):
                    a, b = i + j, i + j + k
                    if a // (2 * t) == b // (2 * t) and b < width:
                        out.append((a, b))
            k //= 2
        t *= 2
    return tuple(out)


@functools.lru_cache(maxsize=None)
def _selection_network(width: int, ranks: tuple[int, ...]) -> tuple[tuple[int, int, bool, bool], ...]:
    """The comparators of :func:`_sorting_network` that the values at ``ranks`` depend on, as
    ``(i, j, min needed, max needed)``: walked backwards from the wanted output wires, a
    comparator neither of whose outputs is needed is dropped, and of the others only the
    needed outputs are computed (both inputs then are needed)."""
    needed = set(ranks)
    kept = []
    for i, j in reversed(_sorting_network(width)):
        lo, hi = i in needed, j in needed
        if lo or hi:
            kept.append((i, j, lo, hi))
            needed |= {i, j}
    return tuple(reversed(kept))


def _nanmedian_columns(columns: list[np.ndarray]) -> np.ndarray:
    """``_nanmedian_last(np.stack(columns, axis=-1))``, exactly, without forming the windows.

    Elements whose W values are all finite (all but those next to gaps) take the median
    from :func:`_selection_network`: a comparator network outputs its inputs themselves
    in sorted order, so the values at ranks ``(W - 1) // 2`` and ``W // 2`` are the ones
    sorting finds, and their mean is computed as there. The others (some value NaN) are
    gathered and sorted by :func:`_nanmedian_last`.
    """
    width = len(columns)
    missing = np.zeros(columns[0].shape, dtype=np.int8)
    for c in columns:
        missing += np.isnan(c)
    lo_rank, hi_rank = (width - 1) // 2, width // 2
    wires: list[np.ndarray | None] = list(columns)
    owned = [False] * width  # a wire still holding an input column is not written in place
    for i, j, want_min, want_max in _selection_network(width, (lo_rank, hi_rank)):
        a, b = wires[i], wires[j]
        lo = np.minimum(a, b, out=a if owned[i] and not want_max else None) if want_min else a
        if want_max:
            wires[j] = np.maximum(a, b, out=b if owned[j] else None)
            owned[j] = True
        if want_min:
            wires[i], owned[i] = lo, True
    med = 0.5 * (wires[lo_rank] + wires[hi_rank])
    partial = np.nonzero(missing)
    if partial[0].size:
        med[partial] = _nanmedian_last(np.stack([c[partial] for c in columns], axis=-1))
    return med


def _running_median_deviation(x: np.ndarray, present: np.ndarray, half: int) -> np.ndarray:
    """Distance of each sample from a robust, velocity-compensated local prediction.

    Every neighbour ``x_{f+k}`` (|k| <= half, k != 0, present only) predicts
    ``x_f ~ x_{f+k} - k v - k^2 a / 2`` with ``v`` and ``a`` the median velocity
    (central first difference) and acceleration (second difference) in the window;
    the prediction is the median of those. Medians make a jump of up to ``half``
    frames unable to move the prediction; the velocity and acceleration terms
    remove the lag a plain running median has on fast or curving motion, leaving
    an error of order jerk * (k / rate)^3. Zero where one-sided (fewer than ``half // 2``
    present neighbours on a side), NaN where absent.

    ``x`` is ``(F, ..., 3)`` and ``present`` ``(F, ...)``: any number of trajectories
    along the middle axes, each on its own. A window's values are ``2 half + 1``
    shifted slices of the padded series (its columns), never a ``(F, ..., W)`` copy;
    the medians are :func:`_nanmedian_columns`.
    """
    xp = np.where(present[..., None], x, np.nan)
    nan_row = np.full((1,) + xp.shape[1:], np.nan)
    prev = np.concatenate([nan_row, xp[:-1]])
    nxt = np.concatenate([xp[1:], nan_row])
    vel = 0.5 * (nxt - prev)
    acc = nxt - 2.0 * xp + prev
    width = 2 * half + 1
    n_frames = xp.shape[0]
    pad = ((half, half),) + ((0, 0),) * (xp.ndim - 1)

    def columns(a: np.ndarray) -> list[np.ndarray]:  # column k + half of every frame's window
        padded = np.pad(a, pad, constant_values=np.nan)
        return [padded[j : j + n_frames] for j in range(width)]

    # All-NaN windows (inside gaps) give NaN medians; those frames are absent anyway.
    v = np.nan_to_num(_nanmedian_columns(columns(vel)))  # (F, ..., 3)
    a = np.nan_to_num(_nanmedian_columns(columns(acc)))
    k = np.arange(-half, half + 1, dtype=float)
    # a sample does not predict itself: its column is left out (a NaN there counts for nothing)
    pred = [c - k[j] * v - 0.5 * k[j] * k[j] * a for j, c in enumerate(columns(xp)) if j != half]
    med = _nanmedian_columns(pred)
    # One-sided windows (run ends) extrapolate and are not judged here; run ends
    # next to gaps are trimmed anyway.
    seen = [~np.isnan(c[..., 0]) for c in columns(xp)]
    need = max(1, half // 2)
    two_sided = (sum(seen[:half]) >= need) & (sum(seen[half + 1 :]) >= need)
    return np.where(two_sided, np.linalg.norm(xp - med, axis=-1), 0.0)


#: Trajectory values (frames x markers x 3) per block of :func:`_deviations`: a block's
#: window columns stay in cache.
_BLOCK_VALUES = 1 << 16


def _deviations(x: np.ndarray, present: np.ndarray, half: int) -> np.ndarray:
    """:func:`_running_median_deviation` of every marker of ``x`` (F, M, 3), in blocks of
    markers of about :data:`_BLOCK_VALUES` values (bounded memory), a thread per core
    (numpy's ufuncs release the GIL)."""
    per_block = max(1, _BLOCK_VALUES // max(1, 3 * x.shape[0]))
    blocks = [slice(lo, lo + per_block) for lo in range(0, x.shape[1], per_block)]
    with ThreadPoolExecutor(max(1, min(os.cpu_count() or 1, 4, len(blocks)))) as pool:
        parts = list(pool.map(lambda b: _running_median_deviation(x[:, b], present[:, b], half), blocks))
    return np.concatenate(parts, axis=1) if parts else np.zeros(present.shape)


_UNNAMED = re.compile(r"^\*\d+$")


def find_duplicates(
    positions: np.ndarray, present: np.ndarray, *, tolerance: float, min_frames: int
) -> list[tuple[int, ...]]:
    """Groups of markers that are one marker stored under several labels.

    Markers ``i`` and ``j`` are copies when they are both present in at least
    ``min_frames`` frames and no such frame puts them more than ``tolerance`` apart.
    Candidates come from every ``max(1, min_frames // 2)``-th frame (any overlap of
    ``min_frames`` consecutive frames holds two of them) and are then checked on all
    frames. Returns groups (sorted tuples of marker indices, two or more each).

    Parameters
    ----------
    positions
        (F, M, 3) positions, metres (anything where ``present`` is False).
    present
        (F, M) bool.
    """
    n_frames, n_markers = present.shape
    if n_markers < 2 or n_frames == 0:
        return []
    stride = max(1, int(min_frames) // 2)
    candidates = np.zeros((n_markers, n_markers), dtype=bool)
    sampled = np.arange(0, n_frames, stride)
    for lo in range(0, len(sampled), 256):  # (256, M, M) per block bounds memory
        rows = sampled[lo : lo + 256]
        x = np.where(present[rows, :, None], positions[rows], np.nan)
        d2 = sum((x[:, :, None, c] - x[:, None, :, c]) ** 2 for c in range(3))
        with np.errstate(invalid="ignore"):
            candidates |= (d2 <= tolerance**2).any(axis=0)
    parent = list(range(n_markers))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(candidates, 1))):
        both = present[:, i] & present[:, j]
        if both.sum() < max(int(min_frames), 1):
            continue
        gap = np.linalg.norm(positions[both, i] - positions[both, j], axis=-1)
        if np.all(gap <= tolerance):
            parent[root(int(j))] = root(int(i))
    groups: dict[int, list[int]] = {}
    for m in range(n_markers):
        groups.setdefault(root(m), []).append(m)
    return [tuple(g) for g in groups.values() if len(g) > 1]


def _merge_duplicates(
    labels: tuple[str, ...], pos: np.ndarray, present: np.ndarray, *, tolerance: float, min_frames: int
) -> dict[int, int]:
    """Merge copies in place (``pos``/``present``); return copy index -> kept index."""
    merged: dict[int, int] = {}
    for group in find_duplicates(pos, present, tolerance=tolerance, min_frames=min_frames):
        seen = present[:, list(group)].sum(axis=0)
        # the kept label takes every copy's samples, so its name matters most: a named
        # label over Vicon's unnamed "*N", then the one seen most, then the first
        keep = min(group, key=lambda m: (bool(_UNNAMED.match(labels[m])), -seen[group.index(m)], m))
        for m in group:
            if m == keep:
                continue
            fill = present[:, m] & ~present[:, keep]
            pos[fill, keep] = pos[fill, m]
            present[:, keep] |= present[:, m]
            present[:, m] = False
            merged[m] = keep
    return merged


def clean(
    trial: Trial,
    *,
    trim_s: float = 0.02,
    min_run_s: float = 0.5,
    reject_jumps: bool = True,
    jump_threshold: float = 0.02,
    jump_mad_factor: float = 8.0,
    jump_window_s: float = 0.1,
    duplicate_tolerance: float = 0.001,
    duplicate_min_s: float = 0.5,
) -> tuple[Trial, CleaningReport]:
    """Clean a trial: merge duplicate labels, reject jumps, trim gap edges, drop short-lived markers.

    Parameters
    ----------
    trial
        The raw recording (metres). Trials joined for a joint fit (``fit_skeleton([a, b])``
        records their frame ranges in ``metadata["trial_bounds"]``) are cleaned each on
        its own frames: a junction is neither a jump nor a gap edge, and no run spans it.
    trim_s
        Seconds trimmed at each gap-adjacent run end (at least one frame; 0 disables).
    min_run_s
        Markers whose longest contiguous run is shorter are dropped (paper: 0.5 s).
    reject_jumps, jump_threshold, jump_mad_factor, jump_window_s
        Jump rejection: a sample deviating from its trajectory's running median
        (window ``jump_window_s`` seconds, centred) by more than
        ``max(jump_threshold, median + jump_mad_factor * robust_std)`` metres of that
        marker's deviations is missing.
    duplicate_tolerance, duplicate_min_s
        Two labels both seen in at least ``duplicate_min_s`` seconds of frames, never
        further apart than ``duplicate_tolerance`` metres there, are one marker: the
        copy is merged into the kept label and dropped (``0`` disables).

    Returns
    -------
    (Trial, CleaningReport)
        The cleaned trial (a new object; the input is untouched) and the report.
    """
    if not isinstance(trial, Trial):
        raise InputError(f"clean() takes a jaxskel.Trial, got {type(trial).__name__}")
    for name, val in (("trim_s", trim_s), ("min_run_s", min_run_s), ("jump_window_s", jump_window_s),
                      ("duplicate_min_s", duplicate_min_s), ("duplicate_tolerance", duplicate_tolerance)):
        if not np.isfinite(val) or val < 0:
            raise InputError(f"{name} must be a non-negative number (seconds or metres), got {val!r}")
    rate = trial.rate
    pos = np.array(trial.positions, copy=True)
    present = trial.mask.copy()
    duplicates: dict[int, int] = {}
    if duplicate_tolerance > 0:
        duplicates = _merge_duplicates(
            trial.labels, pos, present, tolerance=duplicate_tolerance,
            min_frames=max(1, int(round(duplicate_min_s * rate))),
        )
    n_frames, n_markers = present.shape
    before = trial.mask.sum(axis=0)
    # Trials fitted together (combine_trials) are cleaned each on its own frames: the
    # junction between two recordings is not a jump, and a run ending there is not a gap edge.
    bounds = tuple(trial.metadata.get("trial_bounds", ((0, n_frames),)))

    jump = np.zeros_like(present)
    if reject_jumps and n_frames >= 3:
        # At least two frames each side, so jumps of up to two frames are always caught.
        half = max(2, int(round(0.5 * jump_window_s * rate)))
        seen = np.flatnonzero(present.any(axis=0))
        deviations = np.zeros(present.shape)
        for first, last in bounds:
            if last - first >= 3:
                deviations[first:last, seen] = _deviations(pos[first:last, seen], present[first:last, seen], half)
        for m in seen:
            dev = deviations[:, m]
            d = dev[present[:, m] & (dev > 0)]
            if d.size == 0:
                continue
            med = np.median(d)
            mad = np.median(np.abs(d - med))
            thresh = max(jump_threshold, med + jump_mad_factor * 1.4826 * mad)
            jump[:, m] = present[:, m] & (dev > thresh)
        present &= ~jump

    trim = max(1, int(round(trim_s * rate))) if trim_s > 0 else 0
    trimmed = np.zeros_like(present)
    longest = np.zeros(n_markers)
    for m in range(n_markers):
        for first, last in bounds:
            starts, stops = contiguous_runs(present[first:last, m])
            for a, b in zip(starts + first, stops + first):
                lo = a + trim if a > first else a
                hi = b - trim if b < last else b
                if hi <= lo:
                    trimmed[a:b, m] = True
                    continue
                trimmed[a:lo, m] = True
                trimmed[hi:b, m] = True
        present[:, m] &= ~trimmed[:, m]
        for first, last in bounds:
            starts, stops = contiguous_runs(present[first:last, m])
            if len(starts):
                longest[m] = max(longest[m], (stops - starts).max() / rate)

    dropped: dict[str, str] = {}
    for m, lab in enumerate(trial.labels):
        if m in duplicates:
            kept = trial.labels[duplicates[m]]
            both = trial.mask[:, m] & trial.mask[:, duplicates[m]]
            gap = np.linalg.norm(trial.positions[both, m] - trial.positions[both, duplicates[m]], axis=-1).max()
            dropped[lab] = (
                f"duplicate of {kept}: within {gap * 1000:.2f} mm of it in all {int(both.sum())} frames "
                f"both are seen (merged into {kept})"
            )
        elif before[m] == 0:
            dropped[lab] = "never present"
        elif longest[m] < min_run_s:
            dropped[lab] = f"longest contiguous run {longest[m]:.3f} s < min_run_s={min_run_s} s"
    keep = np.array([lab not in dropped for lab in trial.labels])
    pos[~present] = np.nan
    after = np.where(keep, present.sum(axis=0), 0)

    report = CleaningReport(
        labels=trial.labels,
        present_before=before,
        present_after=after,
        jump_samples=jump.sum(axis=0),
        trimmed_samples=trimmed.sum(axis=0) - (trimmed & jump).sum(axis=0),
        longest_run_s=longest,
        dropped=dropped,
        settings=dict(
            trim_s=trim_s,
            trim_frames=trim,
            min_run_s=min_run_s,
            reject_jumps=float(reject_jumps),
            jump_threshold=jump_threshold,
            jump_mad_factor=jump_mad_factor,
            jump_window_s=jump_window_s,
            duplicate_tolerance=duplicate_tolerance,
            duplicate_min_s=duplicate_min_s,
        ),
        duplicates={trial.labels[m]: trial.labels[k] for m, k in duplicates.items()},
    )
    cleaned = trial.replace(
        positions=pos[:, keep], labels=tuple(np.asarray(trial.labels, dtype=object)[keep])
    )
    return cleaned, report
