"""Low-pass filtering of marker trajectories before inverse kinematics.

Inverse kinematics poses every frame on its own, so the white measurement noise of the
markers passes straight into the joint centres. The motion underneath is slow against
the capture rate, so a zero-lag Butterworth filter (``scipy.signal.filtfilt``: forwards
and backwards, no phase shift, twice the order) removes most of that noise; what it
leaves is soft tissue that moves with the joint angles, which no filter removes.

The cutoff is chosen per marker by Winter's residual analysis (Winter, *Biomechanics
and Motor Control of Human Movement*, 4th ed., §3.4.4.3), with the marker's own white
noise read from its time differences (:func:`jaxskel.segment._spectral.white_noise`). Filtering at
``f_c`` leaves a residual ``R(f_c)^2 = mean (x - x_filtered)^2`` per coordinate that is
the noise above the cutoff, about ``s^2 (1 - 2 f_c / f_s)``, plus the signal the filter
cut away. The cutoff taken is the lowest one with ``R(f_c) <= s``: there the signal
removed is at most ``sqrt(2 f_c / f_s) s``, no more than the noise the filter lets
through.

That reading of the noise holds only where the motion adds nothing to the differences.
A difference of order ``k`` damps a motion at angular frequency ``w`` per frame by
``w^k``, and white noise reads the same ``s`` at every order, so the 4th- and
5th-difference estimates agree for white noise and disagree where motion or coloured
noise (a recording filtered or interpolated already) is in them. There the 4th
difference's "noise" is partly motion, and a cutoff chosen against it would filter away
motion. A marker is filtered only where the two agree within 10 %, it has a micrometre
of noise or more (not synthetic data without noise) and 100 samples to read it from; and
only if some cutoff up to 0.8 of the Nyquist frequency passes. Everything else is left as
measured. (The ratios, cutoffs and the filter's effect measured on synthetic and real
recordings: docs/bench/evidence_from_docstrings.md.)

Gaps are not filled or bridged: every run of consecutive samples is filtered on its own
(runs of a concatenated trial's recordings, ``metadata["trial_bounds"]``, never join),
and runs too short for the filter's padding are left as measured.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import Bool, Float
from scipy.signal import butter, filtfilt

from .._errors import InputError
from ..io import Trial
from ..segment import white_noise
from ._clean import contiguous_runs

__all__ = ["Lowpassed", "check_cutoff", "lowpass_markers"]

#: Candidate cutoffs of the residual analysis: from 1 Hz to this fraction of the
#: Nyquist frequency, log-spaced.
_MAX_CUTOFF_OF_NYQUIST = 0.8
_N_CANDIDATES = 24
#: 5th differences a marker needs for its own noise estimate.
_MIN_NOISE_SAMPLES = 100
#: Least ratio of the 5th- to the 4th-difference noise estimate for the differences to be
#: read as white noise (1 for white noise; motion in the differences lowers it, the 5th
#: difference damping slow motion more than the 4th).
_WHITE_AGREEMENT = 0.9
#: White noise below this (metres) is none: what the 4th difference of a smooth noiseless
#: trajectory reads (a 1 Hz, 5 cm swing at 120 Hz: 0.05 um), far under any camera's.
_NOISE_FLOOR = 1e-6


class Lowpassed(NamedTuple):
    """What :func:`lowpass_markers` returns.

    ``trial`` holds the filtered positions (missing samples as before), ``cutoff_hz``
    (M,) the cutoff each marker was filtered at, NaN where it was left as measured.
    """

    trial: Trial
    cutoff_hz: Float[np.ndarray, " M"]


def check_cutoff(cutoff: object, *, rate: float | None = None, allow_none: bool = False) -> None:
    """Raise :class:`InputError` unless ``cutoff`` is ``"auto"``, a positive frequency
    (below the Nyquist frequency when ``rate`` is known) or, with ``allow_none``, None."""
    if cutoff is None and allow_none or isinstance(cutoff, str) and cutoff == "auto":
        return
    what = "'auto', None or a frequency in Hz" if allow_none else "'auto' or a frequency in Hz"
    if isinstance(cutoff, bool) or not isinstance(cutoff, (int, float, np.number)) or not float(cutoff) > 0:
        raise InputError(f"the low-pass cutoff must be {what}, got {cutoff!r}")
    if rate is not None and not float(cutoff) < 0.5 * rate:
        raise InputError(
            f"the low-pass cutoff must be below the Nyquist frequency, {0.5 * rate:g} Hz at {rate:g} Hz, "
            f"got {cutoff!r} Hz"
        )


def _runs(observed: Bool[np.ndarray, " F"], bounds: tuple[tuple[int, int], ...]) -> list[tuple[int, int]]:
    """``(start, stop)`` of every run of observed samples, split at the trial bounds."""
    out = []
    for first, last in bounds or ((0, len(observed)),):
        starts, stops = contiguous_runs(observed[first:last])
        out.extend(zip((starts + first).tolist(), (stops + first).tolist()))
    return out


def _filtered(
    x: Float[np.ndarray, "F 3"], runs: list[tuple[int, int]], rate: float, cutoff: float, order: int
) -> Float[np.ndarray, "F 3"]:
    """``x`` with each of ``runs`` filtered at ``cutoff``."""
    b, a = butter(order, cutoff / (0.5 * rate))
    out = x.copy()
    for start, stop in runs:
        out[start:stop] = filtfilt(b, a, x[start:stop], axis=0)
    return out


def _residual_cutoff(
    x: Float[np.ndarray, "F 3"], runs: list[tuple[int, int]], rate: float, noise: float, order: int
) -> tuple[Float[np.ndarray, "F 3"], float]:
    """Winter's choice (module docstring): the lowest candidate cutoff whose residual over
    ``runs`` is within ``noise``, found by bisection (the residual falls as the cutoff
    rises); ``(x, nan)`` when none is."""
    grid = np.geomspace(1.0, _MAX_CUTOFF_OF_NYQUIST * 0.5 * rate, _N_CANDIDATES)
    done = np.zeros(len(x), dtype=bool)
    for start, stop in runs:
        done[start:stop] = True
    best: tuple[Float[np.ndarray, "F 3"], float] = (x, float("nan"))
    lo, hi = 0, len(grid) - 1
    while lo <= hi:
        mid = (lo + hi) // 2
        y = _filtered(x, runs, rate, float(grid[mid]), order)
        residual = float(np.sqrt(np.mean((y[done] - x[done]) ** 2)))
        if residual <= noise:
            best, hi = (y, float(grid[mid])), mid - 1
        else:
            lo = mid + 1
    return best


def lowpass_markers(trial: Trial, cutoff: float | str = "auto", *, order: int = 2) -> Lowpassed:
    """Zero-lag Butterworth low-pass filter of every marker trajectory, gap by gap.

    Parameters
    ----------
    trial
        The recording.
    cutoff
        ``"auto"`` (default): each marker's own cutoff by residual analysis against its
        white noise (module docstring); a number: that cutoff in Hz for every marker
        (below the Nyquist frequency).
    order
        Butterworth order of each pass (filtered forwards and backwards: twice this
        overall, no phase lag).

    Returns
    -------
    :class:`Lowpassed`: the filtered trial (same labels, frames and missing samples) and
    the cutoff each marker got (NaN: left as measured).
    """
    if not isinstance(trial, Trial):
        raise InputError(f"lowpass_markers() takes a jaxskel.Trial, got {type(trial).__name__}")
    rate = float(trial.rate)  # a Trial's rate is validated positive
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise InputError(f"order must be a positive int, got {order!r}")
    check_cutoff(cutoff, rate=rate)
    automatic = isinstance(cutoff, str)
    x = np.asarray(trial.positions, dtype=float)
    mask = np.asarray(trial.mask)
    bounds = tuple((int(a), int(b)) for a, b in trial.metadata.get("trial_bounds", ()))
    out = x.copy()
    cutoff_hz = np.full(x.shape[1], np.nan)
    pad = 3 * (order + 1)  # filtfilt's padding: 3x the length of a Butterworth filter's coefficients
    for k in range(x.shape[1]):
        runs = [(start, stop) for start, stop in _runs(mask[:, k], bounds) if stop - start > pad]
        if not runs:  # no run long enough to filter
            continue
        if automatic:
            if np.isfinite(np.diff(x[:, k], n=5, axis=0)).all(axis=-1).sum() < _MIN_NOISE_SAMPLES:
                continue
            fourth, fifth = (white_noise(x[:, k : k + 1], order=n) for n in (4, 5))
            if not fourth > _NOISE_FLOOR or fifth < _WHITE_AGREEMENT * fourth:
                continue
            noise = min(fourth, fifth)
            out[:, k], cutoff_hz[k] = _residual_cutoff(x[:, k], runs, rate, noise, order)
        else:
            out[:, k], cutoff_hz[k] = _filtered(x[:, k], runs, rate, float(cutoff), order), float(cutoff)
    out[~mask] = np.nan
    return Lowpassed(trial.replace(positions=out), cutoff_hz)
