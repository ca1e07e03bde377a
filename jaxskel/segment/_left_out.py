"""Markers the motion cannot place on the body: left out of the grouping, with the reason.

Kirk et al. (2005, §3.1) group markers by how much their distances vary. Two kinds of
marker defeat that statistic, and each is left out of the skeleton and reported:

* **Seen only while the body held still.** A marker present only in frames in which no
  two markers move relative to each other beyond the rigidity limit (a static calibration
  trial fitted together with a dynamic one; the medial knee and ankle markers of a lab's
  static pose) keeps a constant distance to *every* marker, so it is rigid with every
  segment at once and the clustering puts it anywhere. Those frames say nothing about
  which segment it is on.
* **Stationary objects.** A marker that does not move in the lab while the body moves
  (a calibration frame, markers on the floor or on a wall), together with every stationary
  marker linked to it, when none of them is linked to a moving marker. Two markers are
  *linked* when they stay within a body's marker spacing of each other (the 90th
  percentile over the frames both are seen of their distance is at most
  :data:`LINK_SPACINGS` times the median nearest-neighbour distance of the markers). A
  planted foot is stationary too, but it is linked to its shank's markers (the ankle
  marker sits next to the heel), and the chain reaches a moving marker.

Both tests use the segmentation's own rigidity limit (:func:`rigidity_limit`: the same
noise-aware limit that :func:`jaxskel.segment.segment_markers` grows its count by), so a
marker counts as moving or a pair as moving apart only beyond what the recording's noise
and soft tissue do to one rigid segment. A recording in which nothing moves relative to
anything else (one static trial alone) leaves nothing out: the segmentation then finds
one rigid body and the fit says so.

Maths. With ``d_kl(f)`` the distance of markers k and l at frame f and ``F_i`` the frames
marker i is seen in, the relative motion while i is seen is ``A^i_kl = std_{f in F_i}
d_kl(f)`` (white noise taken out). Of the pairs that move apart beyond the limit over the
whole recording (those that can tell segments apart), marker i is left out when fewer than
:data:`MOVING_PAIR_FRACTION` of the ones seen in ``F_i`` do so there; where ``F_i`` shows none
of them (only one rigid group in view), it is kept. The
moments ``sum_f v_i(f) w_kl(f) d_kl(f)^p`` (p = 0, 1, 2; ``v``, ``w`` presence) are one
matrix product over frames for all markers at once.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..io import Trial
from ._spectral import affinity_scale

__all__ = ["LeftOut", "left_out_markers", "rigidity_limit", "still_trials"]

#: At most this many frames (evenly spaced over the recording) are read: the tests are
#: about minutes-long stillness or motion, not single frames.
MAX_FRAMES = 600
#: A marker carries grouping evidence when at least this fraction of the marker pairs
#: seen with it move apart beyond the rigidity limit while it is seen. One moving hand of a
#: 41-marker set moves 2 x 39 of 820 pairs (10 %); a still body moves none.
MOVING_PAIR_FRACTION = 0.05
#: Two markers are linked (the same object or the same body) when they stay within this
#: many median nearest-neighbour distances of each other.
LINK_SPACINGS = 3.0
#: Fewest frames two markers must share for their distance to count (as the segmentation's
#: ``min_cooccur``).
MIN_SHARED_FRAMES = 5


@dataclasses.dataclass(frozen=True)
class LeftOut:
    """Markers left out of the grouping: ``reasons`` maps each label to why."""

    reasons: dict[str, str]

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(self.reasons)

    def __bool__(self) -> bool:
        return bool(self.reasons)


def rigidity_limit(
    noise_floor: float, *, sigma: float | None = None, sigma_min: float, sigma_factor: float, rigid_ratio: float
) -> float:
    """The largest distance std (noise taken out) two markers of one segment may show:
    ``rigid_ratio`` times the segmentation's affinity scale (:func:`affinity_scale`)."""
    return float(rigid_ratio) * affinity_scale(noise_floor, sigma=sigma, sigma_min=sigma_min, sigma_factor=sigma_factor)


def _pair_distances(x: np.ndarray) -> np.ndarray:
    """(T, M, M) distances ``|x_k - x_l|`` of the markers of ``x`` (T, M, 3), one coordinate
    at a time: ``sqrt((dx^2 + dy^2) + dz^2)``, the sum in ``np.linalg.norm``'s order (the
    same bits), without a (T, M, M, 3) difference array."""
    total = None
    for c in np.moveaxis(x, -1, 0):
        diff = c[:, :, None] - c[:, None, :]
        diff *= diff
        total = diff if total is None else np.add(total, diff, out=total)
    return np.sqrt(total, out=total)


class _RelativeMotion:
    """Pairwise distances of a recording's markers and their std over chosen frames."""

    def __init__(self, x: np.ndarray, seen: np.ndarray, white_noise: float) -> None:
        t, m = seen.shape
        x0 = np.where(seen[..., None], x, 0.0)
        self.both = seen[:, :, None] & seen[:, None, :]  # (T, M, M)
        self.d = _pair_distances(x0) * self.both
        self.w = self.both.reshape(t, m * m).astype(float)
        self.dd = self.d.reshape(t, m * m)
        self.m = m
        self.noise2 = 2.0 * float(white_noise) ** 2
        self.off_diag = ~np.eye(m, dtype=bool)
        a, n = self.std(np.ones((1, t)))
        #: (M, M) the recording's own distance stds over all frames (inf: not measured)
        self.a_all = np.where((n[0] >= MIN_SHARED_FRAMES) & self.off_diag, a[0], np.inf)

    def std(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(A, n)``: for each row of ``weights`` (G, T), the (M, M) distance std over those
        frames (white noise taken out) and the number of frames each pair is seen in."""
        g, m = weights.shape[0], self.m
        s0 = (weights @ self.w).reshape(g, m, m)
        s1 = (weights @ self.dd).reshape(g, m, m)
        s2 = (weights @ (self.dd * self.dd)).reshape(g, m, m)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / s0
            var = np.maximum(s2 / s0 - mean * mean - self.noise2, 0.0)
        return np.sqrt(var), s0

    def limit(self, *, sigma: float | None, sigma_min: float, sigma_factor: float,
              rigid_ratio: float) -> float | None:
        """The segmentation's rigidity limit on this recording (``None``: no pair measured)."""
        nearest = self.a_all.min(axis=1)
        nearest = nearest[np.isfinite(nearest)]
        if not nearest.size:
            return None
        return rigidity_limit(float(np.median(nearest)), sigma=sigma, sigma_min=sigma_min, sigma_factor=sigma_factor,
                              rigid_ratio=rigid_ratio)

    def moving_pairs(self, weights: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """For each row of ``weights``: of the marker pairs that move apart beyond ``limit``
        somewhere in the recording (the pairs that *can* tell segments apart), how many do
        over those frames, and how many are measured there."""
        a, n = self.std(weights)
        movable = np.isfinite(self.a_all) & (self.a_all > limit)
        pairs = (n >= MIN_SHARED_FRAMES) & movable[None]
        return (pairs & (a > limit)).sum(axis=(1, 2)), pairs.sum(axis=(1, 2))


def still_trials(
    trial: Trial,
    bounds: tuple[tuple[int, int], ...],
    *,
    white_noise: float,
    sigma: float | None = None,
    sigma_min: float = 0.003,
    sigma_factor: float = 2.0,
    rigid_ratio: float = 3.0,
) -> tuple[int, ...]:
    """The trials (``bounds``: frame ranges of trials fitted together) in which no two
    segments move relative to each other: fewer than :data:`MOVING_PAIR_FRACTION` of the
    marker pairs move apart beyond the rigidity limit. Such a trial (a static pose) places
    markers on segments but says nothing about joints. Empty when every trial moves, or
    none does."""
    if len(bounds) < 2:
        return ()
    frames = _frames(trial)
    x = np.asarray(trial.positions, dtype=float)[frames]
    seen = np.isfinite(x).all(axis=-1)
    if x.shape[1] < 3:
        return ()
    motion = _RelativeMotion(x, seen, white_noise)
    limit = motion.limit(sigma=sigma, sigma_min=sigma_min, sigma_factor=sigma_factor, rigid_ratio=rigid_ratio)
    if limit is None:
        return ()
    weights = np.stack([((frames >= a) & (frames < b)).astype(float) for a, b in bounds])
    moving, n = motion.moving_pairs(weights, limit)
    still = tuple(i for i in range(len(bounds)) if n[i] > 0 and moving[i] < MOVING_PAIR_FRACTION * n[i])
    return still if len(still) < len(bounds) else ()


def _frames(trial: Trial) -> np.ndarray:
    n = trial.n_frames
    if n <= MAX_FRAMES:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, MAX_FRAMES).round().astype(int))


def left_out_markers(
    trial: Trial,
    *,
    white_noise: float,
    sigma: float | None = None,
    sigma_min: float = 0.003,
    sigma_factor: float = 2.0,
    rigid_ratio: float = 3.0,
) -> LeftOut:
    """The markers of ``trial`` (metres) that the motion cannot place, with the reason.

    ``white_noise`` is the recording's white measurement noise (per coordinate, metres:
    :func:`jaxskel.segment.white_noise`); ``sigma``, ``sigma_min``, ``sigma_factor`` and
    ``rigid_ratio`` are the segmentation's settings, which fix the rigidity limit. Returns an empty
    :class:`LeftOut` when every marker can be grouped, or when nothing in the recording
    moves relative to anything else.
    """
    frames = _frames(trial)
    x = np.asarray(trial.positions, dtype=float)[frames]
    seen = np.isfinite(x).all(axis=-1)  # (T, M)
    m = x.shape[1]
    if m < 3:
        return LeftOut({})
    motion = _RelativeMotion(x, seen, white_noise)
    limit = motion.limit(sigma=sigma, sigma_min=sigma_min, sigma_factor=sigma_factor, rigid_ratio=rigid_ratio)
    if limit is None:
        return LeftOut({})
    moving_pairs, n_pairs = motion.moving_pairs(seen.T.astype(float), limit)  # over each marker's frames
    d, both = motion.d, motion.both
    off_diag = ~np.eye(m, dtype=bool)
    # A marker whose frames show no pair that moves elsewhere (the only markers then in view
    # are one rigid group, or the recording moves nothing) is not judged: it is kept.
    has_evidence = (n_pairs == 0) | (moving_pairs >= MOVING_PAIR_FRACTION * np.maximum(n_pairs, 1))
    reasons: dict[str, str] = {}
    if not has_evidence.any():
        return LeftOut({})
    times = np.asarray(trial.times)[frames]
    for i in np.flatnonzero(~has_evidence):
        t = times[seen[:, i]]
        span = f"{t.min():.2f}-{t.max():.2f} s" if t.size else "no frame"
        reasons[trial.labels[i]] = (
            f"seen only while no two segments moved relative to each other ({span}; "
            f"{moving_pairs[i]} of the {n_pairs[i]} marker pairs that move apart elsewhere did so there, beyond the "
            f"rigidity limit {1000 * limit:.1f} mm): the motion cannot tell which segment it is on; "
            "fit it with a trial in which it moves"
        )

    # Stationary objects, among the markers with evidence.
    centre = np.array([np.nanmedian(np.where(seen[:, i, None], x[:, i], np.nan), axis=0)
                       if seen[:, i].any() else np.full(3, np.nan) for i in range(m)])
    spread = np.array([np.percentile(np.linalg.norm(x[seen[:, i], i] - centre[i], axis=-1), 90)
                       if seen[:, i].any() else np.inf for i in range(m)])
    judged = has_evidence & (seen.sum(axis=0) >= MIN_SHARED_FRAMES)  # a marker seen a moment is not judged
    still = (spread <= limit) & judged
    moving = (spread > limit) & judged
    if not still.any() or not moving.any():
        return LeftOut(reasons)
    d_p90 = np.full((m, m), np.inf)
    dd = np.where(both, d, np.nan)
    shared = both.sum(0) >= MIN_SHARED_FRAMES
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pairs never seen together: all-NaN
        p90 = np.nanpercentile(dd, 90, axis=0)
        med = np.nanmedian(dd, axis=0)
    d_p90[shared] = p90[shared]
    med = np.where(shared & off_diag, med, np.inf)
    spacing = float(np.median(med.min(axis=1)[np.isfinite(med.min(axis=1))]))
    linked = (d_p90 <= LINK_SPACINGS * spacing) & off_diag & has_evidence[:, None] & has_evidence[None, :]
    # Components of the link graph: a still marker is on the body when its component holds a
    # moving marker.
    component = np.arange(m)
    changed = True
    while changed:
        nxt = np.where(linked, component[None, :], m).min(axis=1)
        nxt = np.minimum(component, nxt)
        changed = bool((nxt != component).any())
        component = nxt
    on_body = {int(c) for c in component[moving]}
    for i in np.flatnonzero(still):
        if int(component[i]) in on_body:
            continue
        group = [trial.labels[k] for k in np.flatnonzero((component == component[i]) & still)]
        reasons[trial.labels[i]] = (
            f"a stationary object: it moves at most {1000 * spread[i]:.1f} mm while the body moves, and "
            f"neither it nor the still markers with it ({', '.join(group)}) stay within "
            f"{1000 * LINK_SPACINGS * spacing:.0f} mm of a moving marker"
        )
    return LeftOut(reasons)
