"""Skeleton-based confirmation and correction of label merges (beyond Kirk et al. §4).

:func:`jaxskel.relabel.merge_labels` decides which fragments are one physical marker
from marker data alone. Once a skeleton has been fitted to the merged trial,
its inverse-kinematics motion poses every segment in *every* frame, including
the frames where a marker was lost. That gives a sharper test of a merge than
the marker-only distance: a physical marker is rigid on one segment, so two
fragments of it must sit at the same place in that segment's frame.

The test
--------
Let ``(R_ts, p_ts)`` be segment s's pose in frame t (``x = R_ts o + p_ts``). A
fragment k seen in frames ``T_k`` has, on segment s, the least-squares
constant offset and its mean squared residual

    o_ks = mean_{t in T_k} R_ts^T (x_tk - p_ts),
    v_ks = mean_{t in T_k} |R_ts^T (x_tk - p_ts) - o_ks|^2

(one GEMM over frames for all K fragments and S segments at once). The
**skeleton link cost** of fragments i and j is

    S_ij = min_s sqrt(|o_is - o_js|^2 + (v_is - v_i*) + (v_js - v_j*)),

with ``v_k*`` the residual on k's best segment: metres, the distance between
the two fragments' places on their common segment when both fit it, and large
when one of them moves with another segment. It compares where the skeleton
puts the lost marker with where the new fragment is over both fragments'
frames, not only at the gap's ends, so noise and soft-tissue wobble average
out.

A fragment is *explained* when ``sqrt(v_k*)`` is below ``rigid_tolerance``.
Between two explained fragments the link cost becomes ``min(D_ij, S_ij)``: the
skeleton can vouch for a link the marker-only distance D found doubtful (two
fragments far apart in time, seen in poses that never repeat), but never break
one D found sure: where the subject leaves the capture volume the poses are
extrapolated, and the skeleton alone would undo good merges. The exact chain assignment of
:func:`jaxskel.relabel.merge_labels` is then solved again (same drop cost for short
ghosts, same marker-count rule). Links it keeps are *confirmed*; new ones are
*corrections*; every decision again gets the regret confidence ``r / (r + c)``.
A skeleton that explains too few samples (wrong segmentation) is not used.
"""

from __future__ import annotations

import dataclasses
import time
import types
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._errors import DegenerateMotionWarning, InputError
from .._math.rotation import quat_to_matrix
from .._runtime.precision import float64_scope
from ..io import Trial
from ._fragments import Fragments, fragment_arrays

__all__ = ["confirm_merges", "fragment_offsets", "skeleton_link_cost"]


@jax.jit
def fragment_offsets(
    x: Float[Array, "F K 3"],
    present: Bool[Array, "F K"],
    rotations: Float[Array, "F S 4"],
    translations: Float[Array, "F S 3"],
    posed: Bool[Array, "F S"],
) -> tuple[Float[Array, "K S"], Float[Array, "K S 3"], Float[Array, "K S"]]:
    """Frame counts ``n_ks``, offsets ``o_ks`` and mean squared residuals ``v_ks``.

    Only frames where the fragment is seen and the segment is ``posed`` count:
    ``w_tks = m_tk posed_ts``. ``x`` is zero where ``present`` is False. With
    ``y_tks = R_ts^T (x_tk - p_ts)``: ``n_ks = sum_t w_tks``,
    ``o_ks = sum_t w_tks y_tks / n_ks`` and
    ``v_ks = sum_t w_tks |y_tks|^2 / n_ks - |o_ks|^2`` (``|y| = |x - p|`` since R is
    a rotation; ``inf`` where ``n_ks = 0``). Every sum over frames is one
    contraction, so no (F, K, S, 3) array is formed.
    """
    m = present.astype(x.dtype)
    w = posed.astype(x.dtype)
    rot = quat_to_matrix(rotations) * w[..., None, None]  # (F, S, 3, 3), zero where not posed
    xm = x * m[..., None]
    n = m.T @ w
    sum_y = jnp.einsum("tsji,tkj->ksi", rot, xm) - jnp.einsum("tk,tsi->ksi", m, jnp.einsum("tsji,tsj->tsi", rot, translations))
    sum_sq = (
        jnp.einsum("tk,ts->ks", jnp.sum(xm * x, axis=-1), w)
        - 2.0 * jnp.einsum("tkj,tsj->ks", xm, translations * w[..., None])
        + jnp.einsum("tk,ts->ks", m, jnp.sum(translations**2, axis=-1) * w)
    )
    safe_n = jnp.maximum(n, 1.0)
    offset = sum_y / safe_n[..., None]
    mean_sq = jnp.maximum(sum_sq / safe_n - jnp.sum(offset * offset, axis=-1), 0.0)
    return n, offset, jnp.where(n > 0, mean_sq, jnp.inf)


def skeleton_link_cost(
    offset: Float[np.ndarray, "K S 3"], mean_sq: Float[np.ndarray, "K S"]
) -> Float[np.ndarray, "K K"]:
    """The skeleton link cost (metres) of every pair of fragments (module docstring).

    ``min_s sqrt(|o_is - o_js|^2 + (v_is - v_i*) + (v_js - v_j*))`` with ``v_k*`` the
    mean squared residual of fragment k on its best segment.
    """
    excess = mean_sq - mean_sq.min(axis=1, keepdims=True)  # inf where never posed together
    k, s = mean_sq.shape
    cost = np.full((k, k), np.inf)
    for seg in range(s):  # host loop over S segments; each step is a (K, K) array
        diff = offset[:, None, seg] - offset[None, :, seg]
        cost = np.minimum(cost, np.sum(diff * diff, axis=-1) + excess[:, None, seg] + excess[None, :, seg])
    return np.sqrt(cost)


@float64_scope
def confirm_merges(
    trial: Trial,
    mapping: Any,
    fit: Any,
    *,
    rigid_tolerance: float = 0.02,
    min_posed_markers: int = 0,
    min_explained: float = 0.5,
    max_link_distance: float | None = None,
) -> tuple[Trial, Any]:
    """Confirm or correct the merges of :func:`jaxskel.relabel.merge_labels` with a fitted skeleton.

    Parameters
    ----------
    trial
        The recording that was given to :func:`jaxskel.relabel.merge_labels` (before merging).
    mapping
        Its :class:`jaxskel.relabel.LabelMapping`.
    fit
        The :class:`jaxskel.SkeletonResult` of fitting the merged recording (same
        frames, with inverse kinematics): its segment poses predict where each
        lost marker is.
    rigid_tolerance
        A fragment is *explained* by the skeleton when its RMS distance to a
        constant offset on its best segment is below this (metres): a marker on
        a body moves at most a centimetre or two against its segment (soft
        tissue). Links between two explained fragments may be vouched for by the
        skeleton; a link touching an unexplained fragment (a marker the skeleton
        does not model well, e.g. on segments a short recording could not
        separate) keeps the marker-only distance of ``merge_labels``.
    min_posed_markers
        Trust a segment's pose only in frames where at least this many of its
        own markers are seen (default 0: every frame, the inverse-kinematics
        gap filling included). Raising it keeps fragments seen only while their
        segment is extrapolated (e.g. the subject leaving the capture volume)
        to the marker-only distance.
    min_explained
        The skeleton is trusted only if it explains at least this fraction of
        the marker samples (seen where their segment is posed). A skeleton fitted to a recording that could not
        separate all segments (e.g. a few seconds of walking) models many
        markers badly; judging merges by it would undo good ones. Below the
        fraction the mapping is returned unchanged (``link_confirmed`` all
        False) with a :class:`~jaxskel.DegenerateMotionWarning`.
    max_link_distance
        Cost (metres) of dropping a short fragment as a ghost; default the one
        ``merge_labels`` used.

    Returns
    -------
    (Trial, LabelMapping)
        The re-merged trial and a mapping whose links come from the skeleton
        test: ``link_error`` is the skeleton link cost of each merge (metres),
        ``link_confirmed`` says whether ``merge_labels`` had made it too,
        ``link_confidence`` is its regret confidence in the new assignment, and
        ``diagnostics["skeleton"]`` counts confirmed and corrected decisions.
    """
    from ._merge import _assign, _finish

    if not isinstance(trial, Trial):
        raise InputError(f"confirm_merges() takes the jaxskel.Trial given to merge_labels, got {type(trial).__name__}")
    if tuple(mapping.labels) != tuple(trial.labels):
        raise InputError("the mapping was not made from this trial (its labels differ); pass the trial given to merge_labels")
    motion, skeleton = getattr(fit, "motion", None), getattr(fit, "skeleton", None)
    if motion is None or skeleton is None:
        raise InputError("confirm_merges() needs a fit with a skeleton and inverse kinematics (fit_skeleton(..., rigid=True, ik=True))")
    rotations = np.asarray(motion.rotations)
    if rotations.ndim != 3 or rotations.shape[0] != trial.n_frames:
        raise InputError(
            f"the fit has poses of shape {rotations.shape}, expected ({trial.n_frames}, S, 4): "
            "one trial's fit over the same frames as the trial"
        )
    clock = time.perf_counter()
    settings = dict(mapping.diagnostics.get("settings", {}))
    drop_cost = float(max_link_distance if max_link_distance is not None else settings.get("max_link_distance", 0.03))
    min_fragment_s = float(settings.get("min_fragment_s", 0.5))
    n_physical = settings.get("n_physical")
    frags = Fragments(
        label=np.asarray(mapping.fragment_label), start=np.asarray(mapping.fragment_start),
        stop=np.asarray(mapping.fragment_stop),
    )  # fmt: skip
    x, present = trial.to_arrays()
    xf, mf = fragment_arrays(x, frags)
    # Frames where each segment is posed by its own markers.
    on_segment = np.asarray(skeleton.marker_segment)[None, :, None] == np.arange(rotations.shape[1])
    posed = (np.asarray(fit.trial.mask)[..., None] & on_segment).sum(axis=1) >= min_posed_markers
    n, offset, mean_sq = (
        np.asarray(a)
        for a in fragment_offsets(
            jnp.asarray(xf), jnp.asarray(mf), jnp.asarray(rotations),
            jnp.asarray(np.asarray(motion.segment_translations)), jnp.asarray(posed),
        )  # fmt: skip
    )
    skeleton_cost = skeleton_link_cost(offset, mean_sq)
    best = np.argmin(mean_sq, axis=1)
    n_best = n[np.arange(frags.size), best]
    explained = np.sqrt(mean_sq[np.arange(frags.size), best]) < rigid_tolerance
    explained_fraction = float(n_best[explained].sum() / max(n_best.sum(), 1.0))
    if explained_fraction < min_explained:
        warnings.warn(
            f"the fitted skeleton explains only {100 * explained_fraction:.0f} % of the marker samples "
            f"(within {1e3 * rigid_tolerance:.0f} mm of a rigid place on a segment); label merges were "
            "not checked against it. Fit a recording with more range of motion, or give n_segments.",
            DegenerateMotionWarning,
            stacklevel=3,  # confirm_merges' caller (2 is float64_scope's wrapper)
        )
        diagnostics = dict(mapping.diagnostics)
        diagnostics["skeleton"] = types.MappingProxyType(
            dict(applied=False, explained_fraction=explained_fraction, seconds=time.perf_counter() - clock)
        )
        unchanged = dataclasses.replace(
            mapping, diagnostics=diagnostics, link_confirmed=np.zeros(np.asarray(mapping.link_from).size, bool)
        )
        return _merged_trial(trial, mapping), unchanged
    judged = explained[:, None] & explained[None, :]
    # The skeleton may vouch for a link the markers alone found doubtful, never break one they
    # found sure: where its poses are extrapolated (or posed on first-pass mistakes) its
    # prediction is worse than the local marker alignment.
    cost = np.where(judged, np.minimum(skeleton_cost, np.asarray(mapping.distance)), np.asarray(mapping.distance))
    cooccur = frags.cooccur()
    cost[cooccur] = np.inf

    short = frags.length < min_fragment_s * trial.rate
    chains, problem = _assign(
        cost, frags=frags, short=short, drop_cost=drop_cost, n_physical=n_physical,
        n_max=n_physical or int(mapping.diagnostics.get("most_seen", mf.sum(axis=1).max())),
        min_frames=min_fragment_s * trial.rate,
    )  # fmt: skip
    links = np.stack([np.flatnonzero(chains.successor >= 0), chains.successor[chains.successor >= 0]], 1)
    drops = np.flatnonzero(chains.dropped)
    confidence = problem.confidence(chains, np.concatenate([links, np.stack([drops, drops], 1)]))
    drop_confidence = np.ones(frags.size)
    drop_confidence[drops] = confidence[links.shape[0] :]

    before = set(zip(np.asarray(mapping.link_from).tolist(), np.asarray(mapping.link_to).tolist()))
    after = set(map(tuple, links.tolist()))
    confirmed = np.array([tuple(link) in before for link in links.tolist()], dtype=bool)
    moved = _changed_fragments(np.asarray(mapping.fragment_physical), chains.chain)
    diagnostics = dict(mapping.diagnostics)
    diagnostics["skeleton"] = types.MappingProxyType(
        dict(
            applied=True,
            explained_fraction=explained_fraction,
            links_confirmed=int(confirmed.sum()),
            links_added=int(len(after - before)),
            links_removed=int(len(before - after)),
            fragments_moved=int(moved.sum()),
            fragments_explained=int(explained.sum()),
            n_physical_before=int(mapping.n_physical),
            links_judged=int(judged[links[:, 0], links[:, 1]].sum()) if links.size else 0,
            seconds=time.perf_counter() - clock,
        )
    )
    merged, out = _finish(
        trial, frags, chains, np.asarray(mapping.distance), np.asarray(mapping.spectral_cluster),
        np.asarray(mapping.distance)[links[:, 0], links[:, 1]] if links.size else np.zeros(0),
        np.where(judged, skeleton_cost, np.nan)[links[:, 0], links[:, 1]] if links.size else np.zeros(0),
        confidence[: links.shape[0]], drop_confidence, diagnostics,
    )  # fmt: skip
    return merged, dataclasses.replace(out, link_confirmed=confirmed)


def _changed_fragments(before: Int[np.ndarray, " K"], chain: Int[np.ndarray, " K"]) -> Bool[np.ndarray, " K"]:
    """Fragments whose marker changed, up to a renumbering of markers.

    Old and new markers are matched by the most shared fragments; a fragment
    counts as moved if its new marker is not matched to its old one (a dropped
    fragment matches only a dropped one).
    """
    from scipy.optimize import linear_sum_assignment

    old_ids, new_ids = np.unique(before[before >= 0]), np.unique(chain[chain >= 0])
    overlap = (before[:, None] == old_ids[None, :]).astype(int).T @ (chain[:, None] == new_ids[None, :]).astype(int)
    rows, cols = linear_sum_assignment(-overlap)
    match = dict(zip(old_ids[rows].tolist(), new_ids[cols].tolist()))
    expected = np.array([match.get(int(b), -2) if b >= 0 else -1 for b in before])
    return expected != chain



def _merged_trial(trial: Trial, mapping: Any) -> Trial:
    """The trial merged by an existing mapping (one column per physical marker)."""
    from ._merge import merged_positions

    frags = Fragments(
        label=np.asarray(mapping.fragment_label), start=np.asarray(mapping.fragment_start),
        stop=np.asarray(mapping.fragment_stop),
    )  # fmt: skip
    return trial.replace(
        positions=merged_positions(trial, frags, np.asarray(mapping.fragment_physical), mapping.n_physical),
        labels=tuple(mapping.physical_labels),
        metadata={**dict(trial.metadata), "merged_labels_from": trial.n_markers},
    )
