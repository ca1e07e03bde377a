"""Marker segmentation: group markers into rigid segments (Kirk et al. 2005, §3.1).

Markers on one rigid segment keep constant mutual distances, so the standard
deviation over time of the distance between markers i and j,

    A_ij = std_t |x_i(t) - x_j(t)|,

is ~0 (noise, skin motion) within a segment and large across a moving joint.
Following the paper:

* ``A`` is computed on a *jittered uniform sampling* of frames (every
  ``interval_s`` seconds, +/- ``jitter_s``), only over frames where both markers
  are present. Pairs seen together in fewer than ``min_cooccur`` sampled frames
  have no estimate: they get zero affinity (no evidence either way) and are
  listed in :attr:`Segmentation.unobserved_pairs`, never treated as rigid (A = 0).
* Spectral clustering (scikit-learn) on the Gaussian affinity
  ``W_ij = exp(-A_ij^2 / (2 sigma^2))`` groups the markers. ``sigma`` adapts to
  the data's noise floor: ``sigma_factor`` times the median over markers of the
  std-dev to their most rigid partner, but at least ``sigma_min`` metres.
* RANSAC-style robustness to sporadic jumps: ``n_samplings`` different jittered
  samplings are clustered; the clustering kept is the one with the smallest
  score ``sum_g (sum_{i<j in g} A_ij) / |g|``, evaluated on the element-wise
  median of A over all samplings so that every candidate is judged on the same,
  jump-robust matrix.
* Beyond the paper, each sampling's clustering is mended before it is scored: a
  marker plainly non-rigid with its group (or far less rigid with it than with
  another) and plainly rigid with another moves there when that lowers the score
  (:func:`_mend`). Spectral clustering follows chains of affinity, and labels seen
  only while the body held still are falsely rigid with everything around them.
* The number of segments is given, or chosen at the largest gap of the
  normalised-affinity spectrum (the eigengap); the spectrum is kept in the
  result so a user can see why.
* Beyond the paper, white measurement noise is taken out of A before any of this:
  noise of std ``s`` per coordinate on both markers adds ``2 s^2`` to the variance of
  their distance, whatever the motion, so ``A_ij`` becomes ``sqrt(max(A_ij^2 - 2 s^2,
  0))``, with ``s`` read from the recording itself (:func:`white_noise`). Without it the
  affinity scale, which follows the noise floor, grows with the noise while the joints'
  motion does not, until joints that move little (a wrist, an ankle) look rigid and
  their segments are joined. Where the noise is small against the affinity scale, an
  ``A`` at that scale or above changes by about ``s^2 / A``, a negligible amount.
* Beyond the paper, a chosen count must give rigid groups: while some group holds two
  markers whose A_ij exceeds ``rigid_ratio * sigma`` (an affinity below e^-4.5 = 1 %:
  the affinity itself calls them unrelated), the count grows by one, up to
  ``max_segments``. The eigengap reads chains of affinity as one cluster: markers placed
  on joints (a knee marker rigid with both thigh and shank) link whole limbs into one
  group, which the grown count separates. A knee marker can then go to either side and
  leave its neighbour's only other marker alone: a lone marker first takes the marker on
  the joint next to it, one about as rigid with it as with its own group
  (:func:`_pair_lone_markers`). When no count up to ``max_segments`` is rigid (a marker
  that moves against every neighbour), or the first rigid one still leaves more
  single-marker groups than the eigengap's, that count is passed over; the count taken is
  then, of those on the way that leave no more lone markers, the one whose least rigid
  group is the most rigid, or the eigengap's if none is more rigid (:func:`grow_count`).
  A short take in which some joints barely move gives such a spectrum: its eigengap
  joins whole limbs, and the first rigid count splits a lone marker off a segment of
  two.
* Beyond the paper, whatever automatic count is taken, a lone marker whose joint marker
  sits in a group of two takes it when the group's other marker joins a third group as
  rigidly (:func:`_pass_joint_marker`): an elbow marker clustered with the forearm marker
  leaves the upper-arm marker alone, and one segment of one marker cannot carry a joint
  on each side.

The measurements behind these departures (noise levels, counts on real recordings) are in
docs/bench/evidence_from_docstrings.md.

The pairwise statistic is one jit-compiled JAX function, vmapped over samplings,
on padded (bucketed) arrays with masks.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._errors import DegenerateMotionError, InputError
from .._math.order import nanquantiles_np
from .._math.padding import bucket_size
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.precision import float64_scope
from ..io import Trial

__all__ = ["Segmentation", "segment_markers", "combine_trials", "count_singletons", "distance_std", "sample_frames", "white_noise"]


@float64_scope
@jax.jit
def distance_std(
    x: Float[Array, "T M 3"], mask: Bool[Array, "T M"]
) -> tuple[Float[Array, "M M"], Float[Array, "M M"]]:
    """Std-dev over frames of every pairwise marker distance, masked.

    Returns ``(A, n)``: A_ij over the frames where both i and j are present, and
    n_ij the number of such frames (A is 0 where n < 2; callers check n).
    """
    diff = x[:, :, None, :] - x[:, None, :, :]
    d2 = jnp.sum(diff * diff, axis=-1)
    # Safe sqrt: the diagonal and absent pairs have d2 = 0.
    d = jnp.where(d2 > 0, jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)), 0.0)
    w = (mask[:, :, None] & mask[:, None, :]).astype(x.dtype)
    n = jnp.sum(w, axis=0)
    safe_n = jnp.maximum(n, 1.0)
    mean = jnp.sum(w * d, axis=0) / safe_n
    var = jnp.sum(w * (d - mean) ** 2, axis=0) / safe_n
    return jnp.sqrt(jnp.maximum(var, 0.0)), n


_distance_std_batched = jax.jit(jax.vmap(distance_std))


#: Order of the time difference :func:`white_noise` reads: the k-th difference of white
#: noise has variance C(2k, k) s^2, while a smooth trajectory's shrinks as dt^k, so a
#: higher order keeps fast motion at a low frame rate out of the estimate (4 against 2:
#: docs/bench/evidence_from_docstrings.md).
_NOISE_DIFFERENCE_ORDER = 4
#: Median of the chi-square distribution with 3 degrees of freedom.
_CHI2_3_MEDIAN = 2.365974


def white_noise(x: np.ndarray, *, order: int = _NOISE_DIFFERENCE_ORDER) -> float:
    """Std-dev (per coordinate, input units) of the white measurement noise in a recording.

    With ``D = Delta^k x_i`` the k-th difference along time of a marker's position
    (k = 4, frames where all k + 1 are present), isotropic white noise of std ``s`` gives
    ``D ~ N(0, C(2k, k) s^2 I_3)`` with ``C(8, 4) = 70``, and a smooth motion almost
    nothing at capture rates. ``|D|^2 / (70 s^2)`` is then chi-square with 3 degrees of
    freedom, whose median is 2.366, so ``s = median|D| / sqrt(70 * 2.366)``: read from
    the median, jumps and the ends of gaps do not count, and from the length of ``D``,
    rotating the recording does not change it.

    Parameters
    ----------
    x
        (T, M, 3) positions, NaN where missing.
    order
        ``k``, the order of the time difference (``C(2k, k)`` in place of 70). Motion
        fast against the frame rate adds to a low order's estimate more than to a higher
        one's; for white noise every order reads the same ``s``.

    Returns
    -------
    float
        ``s``; 0 when no marker is present on k + 1 consecutive frames.

    Raises
    ------
    InputError
        When ``x`` is not of shape (T, M, 3).
    """
    k = int(order)
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise InputError(f"white_noise() takes positions of shape (T, M, 3), got shape {x.shape}")
    if x.shape[0] <= k:
        return 0.0
    d = np.linalg.norm(np.diff(x, n=k, axis=0), axis=-1)
    d = d[np.isfinite(d)]
    if not d.size:
        return 0.0
    return float(np.median(d) / np.sqrt(math.comb(2 * k, k) * _CHI2_3_MEDIAN))


def affinity_scale(noise_floor: float, *, sigma: float | None, sigma_min: float, sigma_factor: float) -> float:
    """The affinity scale (metres): ``sigma`` when given, else ``max(sigma_min, sigma_factor *
    noise_floor)`` (``noise_floor``: the median over markers of their smallest distance std,
    white noise taken out). The rigidity limit is ``rigid_ratio`` times it."""
    return float(sigma) if sigma is not None else max(float(sigma_min), float(sigma_factor) * float(noise_floor))


def _without_noise(a: np.ndarray, noise: float) -> np.ndarray:
    """Distance std-devs with ``noise`` (per coordinate, on both markers) taken out."""
    return np.sqrt(np.maximum(a * a - 2.0 * noise * noise, 0.0))


def sample_frames(
    n_frames: int,
    rate: float,
    rng: np.random.Generator,
    *,
    interval_s: float = 0.5,
    jitter_s: float = 0.1,
    min_samples: int = 40,
) -> np.ndarray:
    """Jittered uniform frame sample: every ``interval_s`` seconds +/- ``jitter_s``.

    Short recordings would give too few samples for a stable std-dev, so the
    interval shrinks until at least ``min_samples`` frames (or all frames) are used.
    """
    step = interval_s * rate
    if n_frames / step < min_samples:
        step = max(1.0, n_frames / min_samples)
    base = np.arange(0.5 * step, n_frames, step)
    jitter = min(jitter_s * rate, 0.45 * step)
    frames = np.rint(base + rng.uniform(-jitter, jitter, size=base.shape)).astype(int)
    return np.unique(np.clip(frames, 0, n_frames - 1))


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """Markers grouped into rigid segments.

    Attributes
    ----------
    labels
        Marker labels (M,), as in the trial that was segmented.
    marker_segment
        (M,) int segment index of each marker, segments numbered 0..S-1 in order
        of their first marker.
    n_segments
        S.
    distance_std
        (M, M) median over samplings of A_ij (metres), as measured; NaN where
        unobserved. The clustering works on it with :attr:`white_noise` taken out.
    affinity
        (M, M) the affinity the kept clustering used.
    eigenvalues
        Leading eigenvalues of the normalised affinity, descending (the spectrum
        behind the eigengap choice).
    eigengap_segments
        Number of segments the eigengap suggests (equal to ``n_segments`` unless
        the user fixed it).
    scores
        Score of each sampling's clustering (lower is better).
    best_sampling
        Index of the kept sampling.
    sigma
        Affinity scale used (metres), on A with the white noise taken out.
    unobserved_pairs
        (i, j) marker pairs never seen together often enough to estimate A.
    count_rule
        How ``n_segments`` was decided: ``"given"``, ``"eigengap"`` (the paper),
        ``"rigid"`` (grown from the eigengap's count until every group is rigid; 1 when
        every pair of markers is rigid, a recording that exercises no joint), ``"most
        rigid"`` (grown short of ``rigid_count``, or with no rigid count up to
        ``max_segments``, to the count whose least rigid group is the most rigid:
        :func:`grow_count`), or
        ``"split"`` (grown past ``split_from`` because one rigid body could not hold
        ``split_markers`` with the rest of their groups: :func:`jaxskel.fit_skeleton`).
    max_segments
        The upper bound of the eigengap search and of the growth.
    rigid_limit
        Largest A_ij (metres, as in :attr:`distance_std`) two markers of one group may
        show: ``rigid_ratio * sigma`` once the white noise is taken out, i.e.
        ``sqrt((rigid_ratio * sigma)^2 + 2 white_noise^2)``; ``inf`` when the check is off.
    split_from
        With ``count_rule == "split"``: the automatic count (eigengap or rigid) the
        fit started from; 0 otherwise.
    split_markers
        With ``count_rule == "split"``: the markers flagged two or more in one group, by
        the group's Procrustes scatter (:func:`marker_scatter`) or by the rigid skeleton,
        that made the count grow.
    rigid_count
        With ``count_rule`` ``"eigengap"`` or ``"most rigid"``: the first larger count whose
        groups were all rigid, passed over because it leaves more markers alone in a group
        (a count to compare when :meth:`nonrigid_groups` is not empty); 0 when there is none.
    white_noise
        Std-dev per coordinate (metres) of the recording's white measurement noise
        (:func:`white_noise`), taken out of A before clustering.
    left_out
        Markers left out of the grouping because the motion cannot place them, label ->
        reason (:func:`jaxskel.segment.left_out_markers`); they are not in :attr:`labels`.
    still_spans
        Frame ranges ``(start, stop)`` of trials fitted together in which no two segments
        move relative to each other (:func:`jaxskel.segment.still_trials`: a static pose);
        the joint stages leave them out, the skeleton and the motion use them.
    passed_joint_markers
        With an automatic count: ``(joint marker, lone marker, partner)`` labels for each
        joint marker that left its group of two for a lone marker while its partner joined
        a third group (:func:`_pass_joint_marker`); each makes one segment fewer than
        :attr:`count_rule`'s count.
    """

    labels: tuple[str, ...]
    marker_segment: np.ndarray
    n_segments: int
    distance_std: np.ndarray
    affinity: np.ndarray
    eigenvalues: np.ndarray
    eigengap_segments: int
    scores: np.ndarray
    best_sampling: int
    sigma: float
    unobserved_pairs: tuple[tuple[int, int], ...]
    count_rule: str = "eigengap"
    max_segments: int = 30
    rigid_limit: float = float("inf")
    split_from: int = 0
    split_markers: tuple[str, ...] = ()
    rigid_count: int = 0
    white_noise: float = 0.0
    left_out: dict[str, str] = dataclasses.field(default_factory=dict)
    still_spans: tuple[tuple[int, int], ...] = ()
    passed_joint_markers: tuple[tuple[str, str, str], ...] = ()

    @property
    def groups(self) -> list[tuple[str, ...]]:
        """Labels of each segment's markers."""
        return [
            tuple(lab for lab, s in zip(self.labels, self.marker_segment) if s == g)
            for g in range(self.n_segments)
        ]

    @property
    def segment_sizes(self) -> np.ndarray:
        return np.bincount(self.marker_segment[self.marker_segment >= 0], minlength=self.n_segments)

    def count_candidates(self, n: int = 3) -> list[tuple[int, float]]:
        """The ``n`` segment counts k with the largest eigengaps ``lambda_k - lambda_{k+1}``
        (k >= 2, largest first): the eigengap's choice and its runners-up. Close gaps
        mean the spectrum does not settle the count; pass ``n_segments`` then."""
        ev = np.asarray(self.eigenvalues)
        gaps = _eigengaps(ev, min(self.max_segments, len(ev) - 1))
        order = np.argsort(-gaps, kind="stable")[:n]
        return [(int(i) + 2, float(gaps[i])) for i in order]

    def nonrigid_groups(self) -> list[tuple[int, str, str, float]]:
        """Groups holding two markers that move relative to each other: ``(segment,
        label, label, A_ij)`` of each group's least rigid pair with ``A_ij`` above
        ``rigid_limit``."""
        return [
            (g, self.labels[i], self.labels[j], a)
            for g, (i, j, a) in enumerate(_least_rigid_pairs(self.marker_segment, self.distance_std))
            if a > self.rigid_limit
        ]

    def within_std(self) -> np.ndarray:
        """Mean within-segment distance std-dev per segment (NaN for 1-marker segments and
        for groups none of whose pairs is ever seen together)."""
        out = np.full(self.n_segments, np.nan)
        for g in range(self.n_segments):
            idx = np.flatnonzero(self.marker_segment == g)
            if len(idx) > 1:
                pairs = self.distance_std[np.ix_(idx, idx)][np.triu_indices(len(idx), 1)]
                pairs = pairs[np.isfinite(pairs)]
                if pairs.size:
                    out[g] = pairs.mean()
        return out


def _normalised_spectrum(w: np.ndarray, k: int) -> np.ndarray:
    deg = w.sum(axis=1)
    dinv = 1.0 / np.sqrt(np.maximum(deg, 1e-300))
    lap = dinv[:, None] * w * dinv[None, :]
    ev = np.linalg.eigvalsh(lap)[::-1]
    return ev[:k]


def _eigengaps(ev: np.ndarray, kmax: int) -> np.ndarray:
    """Gaps lambda_k - lambda_{k+1} after the k-th eigenvalue, k = 2..kmax."""
    return ev[1:kmax] - ev[2 : kmax + 1]


def _eigengap(ev: np.ndarray, max_segments: int) -> int:
    """Number of clusters at the largest gap lambda_k - lambda_{k+1}, k >= 2."""
    kmax = min(max_segments, len(ev) - 1)
    if kmax < 2:
        return max(1, kmax)
    return int(np.argmax(_eigengaps(ev, kmax))) + 2


#: :func:`_mend` moves a marker rigid with its group at the affinity's scale when its
#: distance std to its group is this many times its largest one to another group.
MEND_RATIO = 1.5


def _score(labels: np.ndarray, a: np.ndarray) -> float:
    total = 0.0
    for g in np.unique(labels):
        idx = np.flatnonzero(labels == g)
        if len(idx) > 1:
            block = a[np.ix_(idx, idx)]
            total += np.nansum(block[np.triu_indices(len(idx), 1)]) / len(idx)
    return float(total)


def _least_rigid_pairs(labels: np.ndarray, a: np.ndarray) -> list[tuple[int, int, float]]:
    """Per group ``g = 0..max(labels)``: ``(i, j, A_ij)`` of its largest observed A_ij
    (``(-1, -1, 0)`` when the group has fewer than two markers seen together)."""
    out = []
    for g in range(int(labels.max()) + 1):
        idx = np.flatnonzero(labels == g)
        block = np.nan_to_num(a[np.ix_(idx, idx)], nan=-np.inf)
        if len(idx) < 2 or not np.isfinite(block.max()):
            out.append((-1, -1, 0.0))
            continue
        i, j = np.unravel_index(np.argmax(block), block.shape)
        out.append((int(idx[i]), int(idx[j]), float(block[i, j])))
    return out


def _least_rigidity(labels: np.ndarray, a: np.ndarray) -> float:
    """The largest A_ij of two markers in one group."""
    return max(a_ij for _, _, a_ij in _least_rigid_pairs(labels, a))


def count_singletons(labels: np.ndarray) -> int:
    return int(np.sum(np.bincount(labels) == 1))


Clustering = tuple[np.ndarray, list[float], int]


def grow_count(
    gap_choice: int,
    cluster: Callable[[int], Clustering],
    a: np.ndarray,
    limit: float,
    n_max: int,
) -> tuple[str, np.ndarray, list[float], int, int]:
    """The automatic count, grown from the eigengap's until every group is rigid.

    ``cluster(n)`` gives n groups (labels, every sampling's score, the best sampling);
    ``a`` the distance stds the groups are judged on, ``limit`` the largest one a rigid
    group may hold. The eigengap's count is kept when its groups are rigid. Otherwise
    the count grows, one at a time up to ``n_max``, to the first whose groups are all
    rigid (``"rigid"``), its lone markers first paired with the marker on the joint next
    to them (:func:`_pair_lone_markers`). A new single-marker group has no partner for a
    joint among its neighbours when they carry few markers (a joint needs 4 in all): it
    is then jointed anywhere. So when that count still leaves more lone markers than the
    eigengap's, it is passed over (returned as ``rigid_count``; 0 when no count up to
    ``n_max`` is rigid). The count taken then is, of the counts on the way that leave no
    more lone markers than the eigengap's, the one whose least rigid group is the most
    rigid (``"most rigid"``; the smaller count on a tie), if it is more rigid than the
    eigengap's; else the eigengap's (``"eigengap"``). (Examples, and the rules
    tried and not adopted: docs/bench/evidence_from_docstrings.md.)

    Returns ``(rule, labels, scores, best, rigid_count)``.
    """
    labels, scores, best = cluster(gap_choice)
    least = _least_rigidity(labels, a)
    if least <= limit:
        return "eigengap", labels, scores, best, 0
    lone = count_singletons(labels)
    rule, chosen, rigid_count = "eigengap", (labels, scores, best), 0
    for n in range(gap_choice + 1, n_max + 1):
        grown = cluster(n)
        grown_least = _least_rigidity(grown[0], a)
        if grown_least <= limit:
            paired = _pair_lone_markers(grown[0], a, limit)
            if count_singletons(paired) <= lone:
                return "rigid", _canonical(paired), grown[1], grown[2], 0
            rigid_count = n
            break
        if grown_least < least and count_singletons(grown[0]) <= lone:
            rule, chosen, least = "most rigid", grown, grown_least
    return rule, *chosen, rigid_count


def _lone_partners(labels: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The costs ``a`` with NaN (unobserved) and the diagonal at infinity, and each lone marker
    of ``labels`` with its most rigid partner, ``(i, p)``, the most rigid pair first."""
    off = np.where(np.isnan(a), np.inf, a)
    np.fill_diagonal(off, np.inf)
    lone = np.flatnonzero(np.bincount(labels)[labels] == 1)
    return off, [(int(i), int(np.argmin(off[i]))) for i in sorted(lone, key=lambda i: off[i].min())]


def _pair_lone_markers(labels: np.ndarray, a: np.ndarray, limit: float, ratio: float = MEND_RATIO) -> np.ndarray:
    """Give a one-marker group the marker on the joint next to it, where there is one.

    A grown count separates the groups the eigengap chained together, but a marker placed
    on a joint (a knee marker, rigid with thigh and shank) can go to either side and leave
    its neighbour's only other marker alone. Lone marker ``i`` takes marker ``p``, its most
    rigid partner, from ``p``'s group when

    * ``A_ip <= limit``: the new pair is rigid;
    * ``p``'s group keeps two markers or more;
    * ``p`` is about as rigid with ``i`` as with its own group: ``A_ip`` is at most ``ratio``
      times the median ``A_pj`` over its group mates ``j`` (:data:`MEND_RATIO`, the
      sampling noise of a ratio of two distance stds, as in :func:`_mend`). A marker of a
      cluster, far more rigid with its cluster than with anything else, is never taken.

    Lone markers are served from the most rigid pair up; a group that has received or
    lost a marker is not touched again. Every group stays rigid (``a``: the (M, M) cost,
    NaN where unobserved).
    """
    labels = labels.copy()
    off, candidates = _lone_partners(labels, a)
    touched: set[int] = set()
    for i, p in candidates:
        own, theirs = int(labels[i]), int(labels[p])
        mates = np.flatnonzero(labels == theirs)
        mates = mates[mates != p]
        if not (off[i, p] <= limit and len(mates) >= 2) or {own, theirs} & touched:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            with_mates = np.nanmedian(a[p, mates])
        if off[i, p] <= ratio * with_mates:
            labels[p] = own
            touched |= {own, theirs}
    return labels


def _pass_joint_marker(
    labels: np.ndarray, a: np.ndarray, limit: float, ratio: float = MEND_RATIO
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Give a one-marker group the joint marker of a two-marker group whose other marker
    fits a third group.

    :func:`_pair_lone_markers` never empties a group of two: its other marker would be left
    alone. Here it is not: lone marker ``i`` takes ``p``, its most rigid partner, from the
    group ``{p, q}``, and ``q`` joins group ``r``, when

    * ``A_ip <= limit`` and ``A_ip <= ratio A_pq``: ``p`` is about as rigid with ``i`` as
      with ``q`` (a marker on the joint);
    * ``A_qj <= limit`` for every ``j`` of ``r``, and the median of ``A_qj`` over ``r`` is at
      most ``ratio A_pq``: ``q`` is about as rigid with ``r`` as it was with ``p``. Of the
      groups that qualify, ``r`` is the one with the smallest median.

    Two groups of one and two markers become one of two, and ``r`` grows by one: one lone
    marker fewer, one segment fewer, every group rigid. Lone markers are served from the
    most rigid pair up; a group that has received or lost a marker is not touched again
    (``a``: the (M, M) cost, NaN where unobserved). Returns the labels, renumbered
    (:func:`_canonical`) where a marker moved and as given otherwise, and the moves
    ``(p, i, q)``.
    """
    given = labels
    labels = labels.copy()
    off, candidates = _lone_partners(labels, a)
    touched: set[int] = set()
    moves: list[tuple[int, int, int]] = []
    for i, p in candidates:
        own, theirs = int(labels[i]), int(labels[p])
        mates = np.flatnonzero(labels == theirs)
        if len(mates) != 2 or {own, theirs} & touched:
            continue
        q = int(mates[mates != p][0])
        if not (off[i, p] <= limit and off[i, p] <= ratio * off[p, q]):
            continue
        fits = {
            int(r): float(np.median(off[q, labels == r]))
            for r in np.unique(labels)
            if int(r) not in {own, theirs} | touched and off[q, labels == r].max() <= limit
        }
        if not fits:
            continue
        r = min(fits, key=fits.__getitem__)
        if fits[r] <= ratio * off[p, q]:
            labels[p], labels[q] = own, r
            touched |= {own, theirs, r}
            moves.append((p, int(i), q))
    return (_canonical(labels) if moves else given), moves


#: The lower and upper quartiles and the largest value of a marker's costs to a group (:func:`_mend`).
_MEND_QUANTILES = np.array([0.25, 0.75, 1.0])


def _mend(labels: np.ndarray, a: np.ndarray, sigma: float, ratio: float = MEND_RATIO) -> np.ndarray:
    """Move markers out of groups they plainly do not belong to, lowering the score.

    Spectral clustering follows chains of high affinity. A marker seen with a few others
    only in a stretch where they happen not to move relative to each other (a label
    present for a short part of a take) is falsely rigid with all of them and can tie a
    marker from elsewhere on the body into their group, which then gets jointed where no
    joint is. Spectral cuts also run through a segment now and then, leaving a marker
    with the neighbouring segment (cases on real and synthetic recordings:
    docs/bench/evidence_from_docstrings.md). Marker i of group g moves to group h only when

    * it is not rigid with its own group: the lower quartile of ``A_ij`` over the other
      members j of g exceeds ``sigma`` (the affinity's scale), or ``ratio`` times the
      largest ``A_ij`` over h. The second reading catches a marker near a joint that
      spectral clustering put on the wrong side: rigid with its group mates at the
      affinity's scale (under ``sigma``), but at the noise floor with every marker of its
      own segment, ``ratio`` times closer. ``ratio`` = 1.5
      is about 2.6 standard errors of the log of a ratio of two distance stds over the
      fewest frames a sampling has (40: ``1/sqrt(40)`` = 0.16), before the quartile and
      the median over samplings. The largest ``A_ij`` over h, not a quartile: with the
      upper quartile, markers move into groups they are rigid with on most pairs only,
      and can leave a recording with no rigid count at all;
    * it is more rigid with h than with g as distributions, not by a few pairs: the
      upper quartile of ``A_ij`` over h is below that lower quartile over g (a marker on
      a joint, about as rigid with either side, never passes);
    * the move lowers the paper's score ``sum_g P_g / n_g`` (``P_g = sum_{i<j in g}
      A_ij``); moving i from g to h changes it by

          (P_g - s_ig) / (n_g - 1) - P_g / n_g + (P_h + s_ih) / (n_h + 1) - P_h / n_h,

      ``s_ig = sum_{j in g, j != i} A_ij``.

    The qualifying move lowering the score most is applied until none is left. Groups
    are never emptied, so the count stays, and a clustering of rigid groups is a fixed
    point (a marker of a rigid group sits at the noise floor with its group mates, and
    no other group is ``ratio`` times more rigid with it than that). ``a`` is the
    (M, M) cost with NaN for unobserved pairs: they count as 0 in the score (as in
    :func:`_score`) and are left out of the quartiles.
    """
    labels = labels.copy()
    m, k = len(labels), int(labels.max()) + 1
    a_obs = a.copy()
    np.fill_diagonal(a_obs, np.nan)
    cost = np.nan_to_num(a_obs)
    rows = np.arange(m)
    for _ in range(2 * m):
        onehot = np.eye(k, dtype=bool)[labels]  # (M, k)
        s = cost @ onehot  # (M, k): summed cost of marker i to group g
        n = onehot.sum(axis=0).astype(float)
        p = 0.5 * np.sum(onehot * s, axis=0)  # (k,) within-group sums over pairs
        n_own = n[labels]
        with np.errstate(divide="ignore", invalid="ignore"):
            leave = np.where(n_own > 1, (p[labels] - s[rows, labels]) / (n_own - 1) - p[labels] / n_own, np.inf)
        join = (p[None, :] + s) / (n[None, :] + 1) - p[None, :] / n[None, :]
        # lower quartile, upper quartile and largest A_ij of each marker to each group (NaN: no evidence)
        q = np.stack([nanquantiles_np(a_obs[:, labels == g], _MEND_QUANTILES) for g in range(k)], axis=-1)
        own_low = q[0, rows, labels]  # (M,) NaN: nothing observed with its own group
        other_high, other_max = np.where(np.isnan(q[1:]), np.inf, q[1:])  # (M, k) each
        loose = (own_low > sigma)[:, None] | (ratio * other_max < own_low[:, None])  # (M, k)
        allowed = loose & (other_high < own_low[:, None])
        delta = np.where(allowed, leave[:, None] + join, np.inf)
        delta[rows, labels] = np.inf
        i, g = np.unravel_index(np.argmin(delta), delta.shape)
        if not delta[i, g] < -1e-12 * max(float(p.sum()), 1e-300):
            break
        labels[i] = g
    return labels


def _canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber clusters in order of their first marker (stable across runs)."""
    order = {}
    for lab in labels:
        order.setdefault(int(lab), len(order))
    return np.array([order[int(lab)] for lab in labels], dtype=int)


def _affinity(a: np.ndarray, observed: np.ndarray, sigma: float) -> np.ndarray:
    w = np.where(observed, np.exp(-0.5 * (a / sigma) ** 2), 0.0)
    np.fill_diagonal(w, 1.0)
    # A whisper of connectivity keeps the graph connected (scikit-learn's spectral
    # embedding needs it) without creating evidence for any grouping.
    return w + 1e-9


def _spectral(w: np.ndarray, n: int, seed: int) -> np.ndarray:
    from sklearn.cluster import SpectralClustering

    if n == 1:
        return np.zeros(len(w), dtype=int)
    if n >= len(w):
        return np.arange(len(w))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        model = SpectralClustering(
            n_clusters=n, affinity="precomputed", assign_labels="cluster_qr", random_state=seed
        )
        return _canonical(model.fit_predict(w))


@float64_scope
def segment_markers(
    trial: Trial,
    n_segments: int | None = None,
    *,
    n_samplings: int = 8,
    interval_s: float = 0.5,
    jitter_s: float = 0.1,
    min_samples: int = 40,
    min_cooccur: int = 5,
    sigma: float | None = None,
    sigma_factor: float = 2.0,
    sigma_min: float = 0.003,
    max_segments: int = 30,
    rigid_ratio: float | None = 3.0,
    mend: bool = True,
    seed: int = 0,
) -> Segmentation:
    """Group a trial's markers into rigid segments (Kirk et al. 2005, §3.1).

    Parameters
    ----------
    trial
        A cleaned trial (metres).
    n_segments
        Number of segments; ``None`` chooses it by the eigengap.
    n_samplings
        Number of jittered frame samplings clustered (RANSAC-style).
    interval_s, jitter_s, min_samples
        Sampling: one frame every ``interval_s`` s +/- ``jitter_s`` (paper: 0.5 s
        +/- a few 1/30 s); short recordings use at least ``min_samples`` frames.
    min_cooccur
        Minimum sampled frames two markers must share for A_ij to count.
    sigma, sigma_factor, sigma_min
        Affinity scale in metres, or (default) ``max(sigma_min, sigma_factor *
        noise floor)`` where the noise floor is the median over markers of their
        smallest A_ij.
    max_segments
        Upper bound for the eigengap search and the rigidity growth.
    rigid_ratio
        With ``n_segments=None``: the count grows from the eigengap's choice until no
        group holds two markers with ``A_ij > rigid_ratio * sigma``. When no count up to
        ``max_segments`` achieves that, or the first that does leaves more single-marker
        groups once each lone marker has taken the marker on the joint next to it, the
        count is the most rigid one on the way that adds no lone marker, or the
        eigengap's (:func:`grow_count`). When every pair of
        markers is within that limit the count is 1 (one rigid body: the motion
        exercises no joint, and :func:`jaxskel.fit_skeleton` says so).
        ``None``: the eigengap alone (the paper).
    mend
        Move markers that are plainly in the wrong group out of each sampling's spectral
        clustering before it is scored (:func:`_mend`); ``False`` keeps the paper's
        clustering as is.
    seed
        Seeds the samplings and the clustering.
    """
    if not isinstance(trial, Trial):
        raise InputError(f"segment_markers() takes a jaxskel.Trial, got {type(trial).__name__}")
    m = trial.n_markers
    if m < 2:
        raise InputError(f"segmentation needs at least 2 markers, the trial has {m}")
    if n_segments is not None:
        n_segments = int(n_segments)
        if not 1 <= n_segments <= m:
            raise InputError(
                f"n_segments={n_segments} is impossible with {m} markers; choose 1..{m} or None (eigengap)"
            )
    if n_samplings < 1:
        raise InputError("n_samplings must be >= 1")
    if rigid_ratio is not None and not (isinstance(rigid_ratio, (int, float)) and rigid_ratio > 0):
        raise InputError(f"rigid_ratio must be a positive number or None, got {rigid_ratio!r}")
    rng = np.random.default_rng(seed)
    samplings = [
        sample_frames(trial.n_frames, trial.rate, rng, interval_s=interval_s, jitter_s=jitter_s, min_samples=min_samples)
        for _ in range(n_samplings)
    ]
    t_pad = bucket_size(max(len(s) for s in samplings))
    m_pad = bucket_size(m, minimum=8)
    x_all, mask_all = trial.to_arrays()
    xs = np.zeros((n_samplings, t_pad, m_pad, 3))
    ms = np.zeros((n_samplings, t_pad, m_pad), dtype=bool)
    for r, frames in enumerate(samplings):
        xs[r, : len(frames), :m] = x_all[frames]
        ms[r, : len(frames), :m] = mask_all[frames]
    a_all, n_all = _program_cache.call(_distance_std_batched, to_device(xs), to_device(ms))
    a_all = np.asarray(a_all)[:, :m, :m]
    n_all = np.asarray(n_all)[:, :m, :m]
    observed_all = n_all >= min_cooccur
    a_nan = np.where(observed_all, a_all, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a_med = np.nanmedian(a_nan, axis=0)
    observed = ~np.isnan(a_med)
    np.fill_diagonal(observed, True)
    np.fill_diagonal(a_med, 0.0)
    if not observed[~np.eye(m, dtype=bool)].any():
        raise DegenerateMotionError(
            "no two markers are present together in enough sampled frames to measure their distance; "
            "check the recording for gaps or lower min_cooccur"
        )

    def noise_floor(a: np.ndarray, obs: np.ndarray) -> float:
        off = np.where(obs & ~np.eye(m, dtype=bool), a, np.inf)
        nearest = off.min(axis=1)
        nearest = nearest[np.isfinite(nearest)]
        return float(np.median(nearest)) if nearest.size else sigma_min

    # Everything below judges A with the white noise taken out (module docstring); the
    # result keeps A as measured, with a limit restated in its terms.
    noise = white_noise(trial.positions)
    a_med_c = _without_noise(a_med, noise)
    sig = affinity_scale(noise_floor(a_med_c, observed), sigma=sigma, sigma_min=sigma_min, sigma_factor=sigma_factor)
    w_med = _affinity(np.nan_to_num(a_med_c), observed, sig)
    spectrum = _normalised_spectrum(w_med, min(m, max_segments + 2))
    gap_choice = _eigengap(spectrum, max_segments)
    a_observed = np.where(observed, a_med_c, np.nan)  # what every candidate is mended and judged on
    affinities = []
    for r in range(n_samplings):
        obs_r = observed_all[r].copy()
        np.fill_diagonal(obs_r, True)
        affinities.append(_affinity(np.where(obs_r, _without_noise(a_all[r], noise), 0.0), obs_r, sig))

    def cluster(n: int) -> tuple[np.ndarray, list[float], int]:
        """Each sampling's (mended) clustering into n groups; the best one, all scores."""
        candidates, scores = [], []
        for r, w_r in enumerate(affinities):
            labels = _spectral(w_r, n, seed + r)
            if mend:
                labels = _canonical(_mend(labels, a_observed, sig))
            candidates.append(labels)
            scores.append(_score(labels, a_observed))
        best = int(np.argmin(scores))
        return candidates[best], scores, best

    limit = float(rigid_ratio) * sig if rigid_ratio is not None else np.inf
    rigid_count = 0
    passed: tuple[tuple[str, str, str], ...] = ()
    one_group = np.zeros(m, dtype=int)
    if n_segments is not None:
        rule, (labels, scores, best) = "given", cluster(n_segments)
    elif rigid_ratio is not None and _least_rigidity(one_group, a_observed) <= limit:
        # Every marker keeps its distance to every other (the growth's test below, on
        # all markers as one group): one rigid body, and the eigengap (k >= 2) would
        # split it anywhere (a static trial: flat spectrum, two arbitrary halves and no
        # feasible joint between them).
        rule, labels, scores, best = "rigid", one_group, [_score(one_group, a_observed)], 0
    else:
        rule, labels, scores, best, rigid_count = grow_count(
            gap_choice, cluster, a_observed, limit, min(max_segments, m)
        )
        labels, moves = _pass_joint_marker(labels, a_observed, limit)
        passed = tuple((trial.labels[p], trial.labels[i], trial.labels[q]) for p, i, q in moves)
    unobserved = tuple(
        (int(i), int(j)) for i, j in zip(*np.nonzero(~observed)) if i < j
    )
    return Segmentation(
        labels=trial.labels,
        marker_segment=labels,
        n_segments=int(labels.max()) + 1,
        distance_std=np.where(observed, a_med, np.nan),
        affinity=w_med,
        eigenvalues=spectrum,
        eigengap_segments=gap_choice,
        scores=np.asarray(scores),
        best_sampling=best,
        sigma=sig,
        unobserved_pairs=unobserved,
        count_rule=rule,
        max_segments=int(max_segments),
        rigid_limit=float(np.sqrt(limit**2 + 2.0 * noise**2)),
        rigid_count=rigid_count,
        white_noise=noise,
        passed_joint_markers=passed,
    )


def combine_trials(trials: Sequence[Trial]) -> Trial:
    """Concatenate trials of one subject and marker set along time.

    Labels are the union in order of first appearance (a marker absent from a
    trial is missing there). Frame rates must agree. The frame range of each
    input is kept in ``metadata['trial_bounds']`` so results can be split again.
    """
    trials = list(trials)
    if not trials:
        raise InputError("no trials given")
    if len(trials) == 1:
        return trials[0]
    rates = {round(t.rate, 6) for t in trials}
    if len(rates) > 1:
        raise InputError(
            f"trials fitted together must share a frame rate, got {sorted(rates)} Hz; resample first"
        )
    labels: list[str] = []
    for t in trials:
        labels.extend(lab for lab in t.labels if lab not in labels)
    index = {lab: i for i, lab in enumerate(labels)}
    total = sum(t.n_frames for t in trials)
    pos = np.full((total, len(labels), 3), np.nan)
    bounds, start = [], 0
    for t in trials:
        cols = [index[lab] for lab in t.labels]
        pos[start : start + t.n_frames, cols] = t.positions
        bounds.append((start, start + t.n_frames))
        start += t.n_frames
    ups = {t.up_axis for t in trials}
    return Trial(
        positions=pos,
        labels=tuple(labels),
        rate=trials[0].rate,
        up_axis=ups.pop() if len(ups) == 1 else "unknown",
        source=" + ".join(t.source or "<array>" for t in trials),
        metadata={"trial_bounds": tuple(bounds), "sources": tuple(t.source for t in trials),
                  "files": tuple(t.metadata.get("file", "") for t in trials)},
    )
