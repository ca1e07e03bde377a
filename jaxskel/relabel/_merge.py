"""Passive-marker correspondence: merge labels that are one physical marker (Kirk et al. 2005, §4).

A passive optical system cannot tell a re-found marker from a new one, so every
occlusion starts a new label and 40 physical markers can arrive as hundreds of
labels. :func:`merge_labels` recovers which labels are one marker.

Method
------
1. **Fragments.** Every label is cut into contiguous runs, and a run is cut
   again where it moves faster than ``max_speed`` between two frames. Trackers
   reuse label slots, so a label is not trusted across a gap or a jump: the
   fragments, not the labels, are merged. When no label needs cutting the
   fragments are the labels.
2. **Distance D (paper).** ``D_ij = min_{a in p_i, b in p_j} |m_{i,a} - A m_{j,b}|``
   with ``A`` the Horn alignment of frame b onto frame a over the markers seen
   in both. Frames are sampled every ``sample_interval_s`` (plus one frame of
   every fragment the grid misses) and every pair of samples is aligned once
   for all fragment pairs (:func:`~jaxskel.relabel._distance.sampled_min_distance`).
   For each fragment the ``n_candidates`` nearest fragments in D and in time
   are then searched coarse-to-fine around their best sample pair and around
   the frames bounding the gap between them
   (:func:`~jaxskel.relabel._distance.refine_min_distance`).
3. **Local alignment (beyond the paper).** In the search the alignment is
   weighted towards the markers that move with the pair: within
   ``neighbourhood_radius`` of it and keeping a constant distance to it
   (standard deviation of the distance, as in Kirk §3.1, against
   ``rigid_tolerance``). A whole-body alignment only matches frames where the
   whole pose repeats; a local one matches any two frames where the segment
   carrying the marker is seen, which on real data (non-repeating motion, fast
   limbs) is what separates neighbouring markers.
4. **Spectral clustering (paper).** Affinities ``exp(-D^2 / 2 s^2)``, zero
   between co-occurring fragments, clustered into n' groups, n' being the most
   fragments seen in one frame once short fragments with no match within
   ``max_link_distance`` (ghosts) are set aside. scikit-learn's spectral
   clustering has no repulsion term (the paper's [17]), so cannot-links are only
   soft there; its groups enter the next step as a prior: a link between two
   groups costs ``spectral_weight`` extra.
5. **Exact assignment.** Fragments are intervals in time, so one physical
   marker is a chain of non-overlapping fragments. A minimum-cost linear
   assignment links each fragment's end to at most one later start (cost D),
   starts as few chains as possible (at most the most fragments seen in one
   frame; exactly ``n_physical`` if given) and may drop fragments shorter than
   ``min_fragment_s`` as ghosts (cost ``max_link_distance``)
   (:class:`~jaxskel.relabel._assign.ChainProblem`). Links only go forward in
   time, so co-occurring labels are never merged -- exactly, not by penalty.
   Chains shorter than ``min_fragment_s`` in total are dropped (the paper
   ignores markers seen for less than half a second). The assignment also
   decides the number of physical markers and which short fragments are
   ghosts, so ghosts seen together with every real marker do not inflate n'.
6. **Kinematic confirmation and correction (beyond the paper).** The merged
   chains become the references: D is recomputed for the candidate pairs,
   aligning on the chains that move rigidly with the pair (except the chains
   under test), and the assignment is solved again, until it no longer changes
   (``max_iterations``). Markers lost together with their neighbours are then
   aligned on the neighbours' merged trajectories. For each final merge
   ``i -> j`` the lost marker is predicted across its gap from the rigid motion
   of its co-moving neighbours between the last frame of i and the first frame
   of j; that prediction error is reported (``link_error``).
7. **Confidence.** Every decision (a merge, or dropping a fragment) gets
   ``r / (r + c)``: c its cost in the final assignment and r its regret, the
   rise of the optimal total cost when that decision is forbidden (one more
   assignment per decision). A merge that nothing else can replace scores
   near 1; one with an equally good alternative near 0.

The method fails, as the paper says, when every marker is lost at once: no
frame before the loss shares a marker with a frame after it, so nothing can be
aligned across. :func:`merge_labels` then raises
:class:`~jaxskel.DegenerateMotionError` naming the frames.
"""

from __future__ import annotations

import dataclasses
import time
import types
from collections.abc import Mapping
from typing import Any

import numpy as np
from jaxtyping import Bool, Float, Int

from .._errors import DegenerateMotionError, InputError
from .._runtime.precision import float64_scope
from ..io import Trial
from ._assign import ChainProblem, Chains, spectral_clusters
from ._fragments import (
    Fragments,
    chain_arrays,
    check_continuity,
    fragment_arrays,
    split_fragments,
)
from ._search import (
    PairSearch,
    candidate_pairs,
    gap_frames,
    pair_weights,
    rigid_weight,
    sampled_distance,
)

__all__ = ["merge_labels", "LabelMapping", "needs_merging"]

# Cost of each chain (metres): far above any link, so the number of physical
# markers is minimised first and the links are chosen second.
_CHAIN_COST = 1.0


@dataclasses.dataclass(frozen=True, eq=False)
class LabelMapping:
    """Which input labels are one physical marker; returned by :func:`merge_labels`.

    Label-level attributes (M_in input labels):

    labels
        The input labels.
    physical
        (M_in,) physical marker index of each label (a column of the merged
        trial), -1 for labels dropped as ghosts. A label that had to be cut into
        fragments belonging to different markers maps to its longest fragment's
        marker; see the ``fragment_*`` attributes for the full account.
    confidence
        (M_in,) in [0, 1]: the lowest confidence of the label's fragments
        (NaN for a label never seen).
    physical_labels
        (n_physical,) label of each physical marker: its longest-lived input label.
    n_physical
        Number of physical markers.

    Fragment-level attributes (K fragments: contiguous runs of one label):

    fragment_label, fragment_start, fragment_stop
        (K,) input label index and frame range ``[start, stop)`` of each fragment.
    fragment_physical
        (K,) physical marker of each fragment, -1 if dropped.
    fragment_confidence
        (K,) the lowest confidence of the fragment's merges (1 if it was never
        merged); for a fragment dropped by the assignment, the confidence of
        that drop; for one dropped afterwards by the ``min_fragment_s`` rule, 1.
    distance
        (K, K) the final D matrix in metres (inf for co-occurring or never
        comparable fragments).
    spectral_cluster
        (K,) the spectral clustering of step 4 (the prior of the assignment).

    Merge-level attributes (L merges, ``link_from[l] -> link_to[l]`` consecutive
    fragments of one physical marker):

    link_from, link_to
        (L,) fragment indices.
    link_distance
        (L,) D of the merge in the final pass (metres).
    link_error
        (L,) kinematic prediction error across the gap (metres): the last
        position of ``link_from`` carried by the rigid motion of its co-moving
        neighbours to the first frame of ``link_to``, minus that position.
        NaN where fewer than four neighbours are seen on both sides.
    link_confidence
        (L,) ``r / (r + c)`` in [0, 1]: c the merge's cost in the assignment and
        r its regret, how much the optimal total cost rises without it.
    link_confirmed
        (L,) only after :func:`jaxskel.relabel.confirm_merges` (else ``None``): True where
        the marker-only assignment had made the merge too, False where the
        fitted skeleton corrected it. ``link_error`` then holds the skeleton's
        prediction error of the merge instead of the neighbours' one.

    diagnostics
        Read-only mapping: counts (fragments, sampled frames, candidate pairs),
        n' per pass, the affinity scale, stage timings, the settings.
    """

    labels: tuple[str, ...]
    physical: Int[np.ndarray, " M"]
    confidence: Float[np.ndarray, " M"]
    physical_labels: tuple[str, ...]
    n_physical: int
    fragment_label: Int[np.ndarray, " K"]
    fragment_start: Int[np.ndarray, " K"]
    fragment_stop: Int[np.ndarray, " K"]
    fragment_physical: Int[np.ndarray, " K"]
    fragment_confidence: Float[np.ndarray, " K"]
    distance: Float[np.ndarray, "K K"]
    spectral_cluster: Int[np.ndarray, " K"]
    link_from: Int[np.ndarray, " L"]
    link_to: Int[np.ndarray, " L"]
    link_distance: Float[np.ndarray, " L"]
    link_error: Float[np.ndarray, " L"]
    link_confidence: Float[np.ndarray, " L"]
    diagnostics: Mapping[str, Any]
    link_confirmed: Bool[np.ndarray, " L"] | None = None

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.ndarray):
                value = np.array(value, copy=True)
                value.setflags(write=False)
                object.__setattr__(self, field.name, value)
        object.__setattr__(self, "diagnostics", types.MappingProxyType(dict(self.diagnostics)))

    @property
    def n_labels(self) -> int:
        return len(self.labels)

    @property
    def n_fragments(self) -> int:
        return int(self.fragment_label.size)

    def members(self, physical: int) -> tuple[str, ...]:
        """Input labels merged into one physical marker (by fragment, in time order)."""
        order = np.flatnonzero(self.fragment_physical == physical)
        order = order[np.argsort(self.fragment_start[order], kind="stable")]
        return tuple(dict.fromkeys(self.labels[i] for i in self.fragment_label[order]))

    def summary(self) -> str:
        """A short human-readable account."""
        dropped = int((self.fragment_physical < 0).sum())
        low = int((self.link_confidence < 0.5).sum())
        return (
            f"merge_labels: {self.n_labels} labels -> {self.n_fragments} fragments -> "
            f"{self.n_physical} physical markers; {self.link_from.size} merges "
            f"({low} with confidence < 0.5), {dropped} fragments dropped as ghosts"
        )

    def __repr__(self) -> str:
        return f"LabelMapping({self.summary()})"


def needs_merging(trial: Trial) -> bool:
    """True when a trial has more labels than markers seen in any one frame.

    That is the paper's sign of passive relabelling (n > n'): the CLI and
    ``fit_skeleton(merge_labels="auto")`` merge exactly then.
    """
    present = trial.mask
    return bool(present.any(axis=0).sum() > present.sum(axis=1).max(initial=0))


@float64_scope
def merge_labels(
    trial: Trial,
    *,
    n_physical: int | None = None,
    sample_interval_s: float = 0.25,
    neighbourhood_radius: float = 0.08,
    rigid_tolerance: float = 0.01,
    max_link_distance: float = 0.03,
    min_fragment_s: float = 0.5,
    max_speed: float = 15.0,
    n_candidates: int = 6,
    spectral_weight: float = 0.005,
    max_iterations: int = 3,
    min_common: int = 4,
) -> tuple[Trial, LabelMapping]:
    """Merge the labels of a passive recording into one label per physical marker.

    See the module docstring for the method: Kirk et al. 2005 §4, plus a local
    alignment, an exact assignment and a kinematic correction.

    Parameters
    ----------
    trial
        The recording (metres). Ghosts and jumps may be present; running
        :func:`jaxskel.clean.clean` first (with ``min_run_s=0``, so that short
        relabelled runs survive) removes the worst jumps.
    n_physical
        Number of physical markers if known. By default as few as the data
        allow: the most fragments seen in one frame once short ones that match
        nothing (ghosts) are dropped.
    sample_interval_s
        Spacing of the sampled frames of the paper's coarse pass (seconds).
    neighbourhood_radius
        Radius (metres) of the proximity weights of the local alignment;
        ``math.inf`` weighs all shared markers alike, as the paper does.
    rigid_tolerance
        Standard deviation of distance (metres) below which two markers count
        as moving rigidly together.
    max_link_distance
        Cost (metres) of dropping a short fragment as a ghost: it is merged
        only if that is cheaper. Also the ghost threshold for the spectral n'.
    min_fragment_s
        Fragments shorter than this may be dropped as ghosts, and markers seen
        for less in total are dropped (the paper ignores markers seen for less
        than half a second).
    max_speed
        A label moving faster than this (m/s) between two frames is cut there.
    n_candidates
        Fragments searched per fragment: nearest in D, nearest before and after in time.
    spectral_weight
        Extra cost (metres) of a merge across two spectral clusters; 0 ignores them.
    max_iterations
        Kinematic correction passes after the first assignment.
    min_common
        Frames are only aligned on at least this many shared markers (>= 3).

    Returns
    -------
    (Trial, LabelMapping)
        The merged trial, one column per physical marker (ordered by the input
        position of its label; positions taken from its fragments, which never
        overlap in time), and the mapping with confidences and diagnostics.

    Raises
    ------
    InputError
        Bad arguments, a trial without samples, or ``n_physical`` below the
        number of long-lived fragments seen in one frame.
    DegenerateMotionError
        Every marker is lost at once (no frame before can be aligned with a frame
        after), or no pair of frames shares enough markers to align.
    """
    _check_arguments(
        trial, n_physical, sample_interval_s, neighbourhood_radius, rigid_tolerance,
        max_link_distance, min_fragment_s, max_speed, n_candidates, spectral_weight,
        max_iterations, min_common,
    )  # fmt: skip
    settings = dict(
        n_physical=n_physical, sample_interval_s=sample_interval_s,
        neighbourhood_radius=neighbourhood_radius, rigid_tolerance=rigid_tolerance,
        max_link_distance=max_link_distance, min_fragment_s=min_fragment_s, max_speed=max_speed,
        n_candidates=n_candidates, spectral_weight=spectral_weight,
        max_iterations=max_iterations, min_common=min_common,
    )  # fmt: skip
    clock = [time.perf_counter()]
    x, present = trial.to_arrays()
    frags = split_fragments(present, x, max_speed / trial.rate)
    if frags.size == 0:
        raise InputError("the trial has no marker samples at all; nothing to merge")
    xf, mf = fragment_arrays(x, frags)
    short = frags.length < min_fragment_s * trial.rate
    long_seen = mf[:, ~short].sum(axis=1)
    if n_physical is not None and n_physical < long_seen.max(initial=0):
        raise InputError(
            f"n_physical={n_physical} but {long_seen.max()} markers seen for at least min_fragment_s="
            f"{min_fragment_s} s are present together in frame {int(np.argmax(long_seen))}; give at "
            "least that many (or remove the extra markers first if they are spurious)"
        )
    cooccur = frags.cooccur()
    diagnostics: dict[str, Any] = dict(n_fragments=frags.size, most_seen=int(mf.sum(axis=1).max()))
    if cooccur.all():  # every fragment is seen with every other: nothing can merge
        k = frags.size
        identity = Chains(np.arange(k), np.full(k, -1), np.zeros(k, bool), n_chains=k, cost=0.0)
        diagnostics.update(passes=0, settings=types.MappingProxyType(settings))
        return _finish(
            trial, frags, identity, np.full((k, k), np.inf), identity.chain,
            np.zeros(0), np.zeros(0), np.zeros(0), np.ones(k), diagnostics,
        )  # fmt: skip
    check_continuity(mf, trial.rate, min_common)

    # The paper's pass: D over all pairs of sampled frames, whole-frame alignment.
    interval = max(1, round(sample_interval_s * trial.rate))
    d_coarse, frame_i, frame_j, n_samples = sampled_distance(xf, mf, frags, interval, min_common)
    d_coarse = np.where(cooccur, np.inf, d_coarse)
    clock.append(time.perf_counter())

    # Local searches around the best samples and across the gaps, on the fragments themselves.
    pairs = candidate_pairs(d_coarse, ~cooccur, frags, n_candidates)
    rows = np.concatenate([pairs, pairs])
    i, j = pairs[:, 0], pairs[:, 1]
    seeds = np.concatenate([np.stack([frame_i[i, j], frame_j[i, j]], axis=1), gap_frames(frags, pairs)])
    search = PairSearch.build(xf, mf, interval, neighbourhood_radius, min_common)
    rigid = rigid_weight(xf, mf, xf, mf, rigid_tolerance)
    distance, seeds = _searched_distance(search, d_coarse, xf, mf, rigid, rows, rows, seeds)
    clock.append(time.perf_counter())

    # Spectral clustering (the paper) as the prior of the exact assignment.
    nearest = np.where(cooccur, np.inf, distance).min(axis=1)
    if not np.isfinite(nearest).any():
        raise DegenerateMotionError(
            f"no two frames of different labels share {min_common} markers to be aligned on; "
            "labels cannot be compared. Is the subject in view?"
        )
    ghost = short & (nearest > max_link_distance)
    n_spectral = int(mf[:, ~ghost].sum(axis=1).max())
    scale = max(2.0 * float(np.median(nearest[np.isfinite(nearest)])), 1e-3)
    spectral = spectral_clusters(distance, cooccur, n_physical or n_spectral, scale)
    prior = spectral_weight * (spectral[:, None] != spectral[None, :])
    assign = dict(
        frags=frags, short=short, drop_cost=max_link_distance, n_physical=n_physical,
        n_max=n_physical or diagnostics["most_seen"], min_frames=min_fragment_s * trial.rate,
    )  # fmt: skip
    chains, problem = _assign(distance + prior, **assign)
    history = [chains.n_chains]

    # Kinematic correction: align on the merged markers that move with each pair.
    for _ in range(max_iterations):
        xr, mr, rigid = _merged_references(xf, mf, chains, search.n_columns, rigid_tolerance)
        distance, seeds = _searched_distance(search, d_coarse, xr, mr, rigid, rows, chains.chain[rows], seeds)
        corrected, problem = _assign(distance + prior, **assign)
        history.append(corrected.n_chains)
        converged = np.array_equal(corrected.chain, chains.chain)
        chains = corrected
        if converged:
            break
    else:
        xr, mr, rigid = _merged_references(xf, mf, chains, search.n_columns, rigid_tolerance)
    clock.append(time.perf_counter())

    # Each decision's confidence, and each merge's kinematic prediction across its gap.
    links = np.stack([np.flatnonzero(chains.successor >= 0), chains.successor[chains.successor >= 0]], 1)
    # Fragments the assignment dropped get the confidence of that choice; those dropped
    # afterwards (markers seen for less than min_fragment_s) follow a rule: 1.
    drops = np.flatnonzero(chains.dropped)
    confidence = problem.confidence(chains, np.concatenate([links, np.stack([drops, drops], 1)]))
    drop_confidence = np.ones(frags.size)
    drop_confidence[drops] = confidence[links.shape[0] :]
    error = np.zeros(0)
    if links.size:
        weights = pair_weights(rigid, links, chains.chain[links[:, :1]])
        error = search.at(xr, mr, weights, links, gap_frames(frags, links))
    clock.append(time.perf_counter())
    diagnostics.update(
        n_sampled_frames=n_samples,
        n_candidate_pairs=int(pairs.shape[0]),
        n_physical_spectral=n_spectral,
        affinity_scale=scale,
        passes=len(history),
        n_physical_per_pass=tuple(history),
        assignment_cost=chains.cost,
        seconds=types.MappingProxyType(
            dict(zip(("coarse", "search", "assign_and_correct", "confidence"), np.diff(clock).tolist()))
        ),
        settings=types.MappingProxyType(settings),
    )
    return _finish(
        trial, frags, chains, distance, spectral, distance[links[:, 0], links[:, 1]],
        np.where(np.isfinite(error), error, np.nan), confidence[: links.shape[0]], drop_confidence,
        diagnostics,
    )  # fmt: skip


def _merged_references(
    xf: Float[np.ndarray, "F K 3"],
    mf: Bool[np.ndarray, "F K"],
    chains: Chains,
    n_columns: int,
    tolerance: float,
) -> tuple[Float[np.ndarray, "F C 3"], Bool[np.ndarray, "F C"], Float[np.ndarray, "K C"]]:
    """The merged markers as references, and how rigidly each moves with each fragment."""
    xr, mr = chain_arrays(xf, mf, chains.chain, n_columns)
    return xr, mr, rigid_weight(xf, mf, xr, mr, tolerance)


def _searched_distance(
    search: PairSearch,
    d_coarse: Float[np.ndarray, "K K"],
    xr: Float[np.ndarray, "F C 3"],
    mr: Bool[np.ndarray, "F C"],
    rigid: Float[np.ndarray, "K C"],
    rows: Int[np.ndarray, "R 2"],
    exclude: Int[np.ndarray, "R 2"],
    seeds: Int[np.ndarray, "R 2"],
) -> tuple[Float[np.ndarray, "K K"], Int[np.ndarray, "R 2"]]:
    """D with each searched pair's entry lowered to its search result; and the new seeds.

    ``rows`` holds every candidate pair twice (two seeds each); the references
    ``exclude`` (the pair's own fragments or chains) get no weight.
    """
    best, seeds = search.search(xr, mr, pair_weights(rigid, rows, exclude), rows, seeds)
    half = rows.shape[0] // 2
    i, j = rows[:half, 0], rows[:half, 1]
    distance = d_coarse.copy()
    distance[i, j] = distance[j, i] = np.minimum(d_coarse[i, j], np.minimum(best[:half], best[half:]))
    return distance, seeds


def _assign(
    cost: Float[np.ndarray, "K K"],
    *,
    frags: Fragments,
    short: Bool[np.ndarray, " K"],
    drop_cost: float,
    n_physical: int | None,
    n_max: int,
    min_frames: float,
) -> tuple[Chains, ChainProblem]:
    """The exact assignment; then, unless n_physical is given, markers seen too briefly are dropped."""
    problem = ChainProblem.build(
        frags.start, frags.stop, cost, short, drop_cost,
        n_max=n_max, chain_cost=_CHAIN_COST, exact=n_physical is not None,
    )  # fmt: skip
    try:
        chains = problem.solve()
    except ValueError:
        raise DegenerateMotionError(
            f"cannot arrange the fragments into {n_max} physical markers without merging fragments "
            "that were never compared; the recording lacks frames with enough shared markers"
        ) from None
    if n_physical is not None:
        return chains, problem
    total = np.bincount(chains.chain[chains.chain >= 0], weights=frags.length[chains.chain >= 0],
                        minlength=chains.n_chains)  # fmt: skip
    keep = total >= min_frames
    renumber = np.where(keep, np.cumsum(keep) - 1, -1)
    chain = np.where(chains.chain >= 0, renumber[np.maximum(chains.chain, 0)], -1)
    successor = np.where(chain >= 0, chains.successor, -1)
    return dataclasses.replace(chains, chain=chain, successor=successor, n_chains=int(keep.sum())), problem


def _finish(
    trial: Trial,
    frags: Fragments,
    chains: Chains,
    distance: Float[np.ndarray, "K K"],
    spectral: Int[np.ndarray, " K"],
    link_distance: Float[np.ndarray, " L"],
    link_error: Float[np.ndarray, " L"],
    link_confidence: Float[np.ndarray, " L"],
    drop_confidence: Float[np.ndarray, " K"],
    diagnostics: Mapping[str, Any],
) -> tuple[Trial, LabelMapping]:
    """Build the merged trial and the mapping from the fragment-to-chain assignment."""
    labels, chain, n_chains = trial.labels, chains.chain, chains.n_chains
    # Name each chain after its longest-lived fragment's label (the next free one on a clash).
    order = np.lexsort((frags.start, -frags.length))
    names: list[str | None] = [None] * n_chains
    used: set[str] = set()
    for f in order[chain[order] >= 0]:  # host-side walk over the K fragments
        name = labels[frags.label[f]]
        if names[chain[f]] is None and name not in used:
            names[chain[f]] = name
            used.add(name)
    for c in range(n_chains):
        if names[c] is None:  # every member's label already names another chain
            base, k = labels[frags.label[order[chain[order] == c][0]]], 2
            while f"{base}#{k}" in used:
                k += 1
            names[c] = f"{base}#{k}"
            used.add(names[c])
    # Physical markers in the input order of their names.
    position = {lab: i for i, lab in enumerate(labels)}
    rank = np.argsort([position.get(str(n).split("#")[0], len(labels)) for n in names], kind="stable")
    renumber = np.empty(n_chains, dtype=int)
    renumber[rank] = np.arange(n_chains)
    physical = np.where(chain >= 0, renumber[np.maximum(chain, 0)], -1)
    physical_labels = tuple(str(names[c]) for c in rank)

    merged = merged_positions(trial, frags, physical, n_chains)

    # A fragment is as sure as its least sure merge; a dropped one as its drop.
    link_from = np.flatnonzero(chains.successor >= 0)
    link_to = chains.successor[link_from]
    frag_conf = np.ones(frags.size)
    np.minimum.at(frag_conf, link_from, link_confidence)
    np.minimum.at(frag_conf, link_to, link_confidence)
    frag_conf[physical < 0] = drop_confidence[physical < 0]
    # A label maps to its longest fragment's marker and is as sure as its least sure fragment.
    n_labels = len(labels)
    longest = np.lexsort((-frags.length, frags.label))
    first = longest[np.unique(frags.label[longest], return_index=True)[1]]
    label_physical = np.full(n_labels, -1)
    label_physical[frags.label[first]] = physical[first]
    label_conf = np.full(n_labels, np.nan)  # NaN: never seen
    label_conf[frags.label[first]] = 1.0
    np.minimum.at(label_conf, frags.label, frag_conf)

    merged_trial = trial.replace(
        positions=merged,
        labels=physical_labels,
        metadata={**dict(trial.metadata), "merged_labels_from": n_labels},
    )
    mapping = LabelMapping(
        labels=labels,
        physical=label_physical,
        confidence=label_conf,
        physical_labels=physical_labels,
        n_physical=n_chains,
        fragment_label=frags.label,
        fragment_start=frags.start,
        fragment_stop=frags.stop,
        fragment_physical=physical,
        fragment_confidence=frag_conf,
        distance=distance,
        spectral_cluster=spectral,
        link_from=link_from,
        link_to=link_to,
        link_distance=np.asarray(link_distance, dtype=float),
        link_error=np.asarray(link_error, dtype=float),
        link_confidence=np.asarray(link_confidence, dtype=float),
        diagnostics=diagnostics,
    )
    return merged_trial, mapping


def merged_positions(
    trial: Trial, frags: Fragments, physical: Int[np.ndarray, " K"], n_physical: int
) -> Float[np.ndarray, "F P 3"]:
    """Positions with one column per physical marker, from its fragments (NaN elsewhere)."""
    merged = np.full((trial.n_frames, n_physical, 3), np.nan, dtype=trial.positions.dtype)
    frame = np.arange(trial.n_frames)[:, None]
    frames, frag = np.nonzero((frame >= frags.start) & (frame < frags.stop) & (physical >= 0))
    merged[frames, physical[frag]] = trial.positions[frames, frags.label[frag]]
    return merged


def _check_arguments(
    trial, n_physical, sample_interval_s, neighbourhood_radius, rigid_tolerance, max_link_distance,
    min_fragment_s, max_speed, n_candidates, spectral_weight, max_iterations, min_common,
) -> None:  # fmt: skip
    if not isinstance(trial, Trial):
        raise InputError(f"merge_labels() takes a jaxskel.Trial, got {type(trial).__name__}")
    if trial.n_markers == 0 or trial.n_frames == 0:
        raise InputError(f"the trial is empty ({trial.n_frames} frames x {trial.n_markers} markers)")
    if n_physical is not None and (not isinstance(n_physical, (int, np.integer)) or n_physical < 1):
        raise InputError(f"n_physical must be a positive integer or None, got {n_physical!r}")
    positive = dict(  # name -> (value, may be inf)
        sample_interval_s=(sample_interval_s, False), neighbourhood_radius=(neighbourhood_radius, True),
        rigid_tolerance=(rigid_tolerance, False), max_link_distance=(max_link_distance, False),
        max_speed=(max_speed, True),
    )  # fmt: skip
    for name, (value, may_be_inf) in positive.items():
        if not (isinstance(value, (int, float, np.floating)) and value > 0 and (may_be_inf or value < np.inf)):
            raise InputError(f"{name} must be a positive number, got {value!r}")
    for name, value in dict(min_fragment_s=min_fragment_s, spectral_weight=spectral_weight).items():
        if not (isinstance(value, (int, float, np.floating)) and np.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a non-negative number, got {value!r}")
    counts = dict(n_candidates=(n_candidates, 1), max_iterations=(max_iterations, 0), min_common=(min_common, 3))
    for name, (value, low) in counts.items():
        if not isinstance(value, (int, np.integer)) or value < low:
            raise InputError(f"{name} must be an integer >= {low}, got {value!r}")
