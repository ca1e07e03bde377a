"""Grow an automatic segment count where the rigid skeleton cannot hold a group.

The automatic count (:func:`jaxskel.segment.segment_markers`: the eigengap, grown until every
group is rigid at ``rigid_ratio * sigma``) can join two segments whose joint moves
little: their markers' distances vary by a few millimetres, under the segmentation's
rigidity limit (``sigma`` is at least 3 mm, so that soft tissue on real data does not
split segments). The rigid skeleton sees such a group plainly: one rigid body cannot
follow both parts, and the markers of the smaller part keep residuals of several times
the median (:attr:`jaxskel.skeleton.Skeleton.nonrigid_markers`, ``> 3x`` the median RMS and
``> median + 1 mm``), and a joined group holds several such markers.

A single flagged marker on a segment is what soft tissue and markers on joints look
like on real data, so the count grows only where a segment holds **two or more**
flagged markers (the cases on synthetic trees and real recordings:
docs/bench/evidence_from_docstrings.md):

1. segment again from scratch with one segment more (the paper's samplings and
   scoring, :func:`jaxskel.segment.segment_markers` given ``n``), and fit the joints and the
   rigid skeleton again;
2. keep the new fit only if its rigid skeleton flags fewer markers *and* it leaves no
   more single-marker segments (a marker peeled off alone is always "rigid", and its
   joint is often untestable);
3. while the kept fit still has a segment with two or more flagged markers, try the
   next count (one more than the last one *tried*, kept or not), at most
   :data:`MAX_SPLITS` counts in all.

Warnings of the fits that are discarded are dropped; those of the kept one are
re-emitted. A given ``n_segments`` is never changed.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from .._errors import DegenerateMotionError
from ..joints import Topology
from ..result import SkeletonResult
from ..segment import count_singletons, segment_markers

if TYPE_CHECKING:
    from ._plan import PreparedFit, StagePlan

__all__ = ["crowded_nonrigid", "grow_count", "MAX_SPLITS"]

#: Most segments added after the rigid fit (each one a further segmentation and fit).
MAX_SPLITS = 2


def crowded_nonrigid(skeleton: Any) -> tuple[str, ...]:
    """The flagged markers (``skeleton.nonrigid_markers``) that share their segment with
    another flagged marker, in label order."""
    if skeleton is None or not skeleton.nonrigid_markers:
        return ()
    labels = list(skeleton.marker_labels)
    segments = np.asarray(skeleton.marker_segment)
    seg_of = {lab: int(segments[labels.index(lab)]) for lab in skeleton.nonrigid_markers}
    counts = np.bincount(list(seg_of.values()))
    return tuple(lab for lab in labels if lab in seg_of and counts[seg_of[lab]] >= 2)


def _replay(caught: list[warnings.WarningMessage], stacklevel: int) -> None:
    """Re-emit recorded warnings at ``stacklevel`` frames above the caller of this function."""
    for w in caught:
        warnings.warn(w.message, w.category, stacklevel=stacklevel + 1)


def grow_count(plan: StagePlan, prep: PreparedFit, topology: Topology | None = None, *,
               stacklevel: int = 2) -> SkeletonResult:
    """Fit a prepared fit, growing its automatic count while a segment holds two or more
    markers the rigid skeleton cannot hold (module docstring), then add the motion.

    The first fit is the plan's skeleton on ``topology`` (its joint stage solved already,
    by :func:`jaxskel.fit_batch`) or on the plan's own joint stage; each grown count is
    segmented and fitted again by the plan. The kept fit's warnings are re-emitted at
    ``stacklevel`` relative to the caller (2: the caller's caller).
    """
    options = plan.options
    growable = options.segment.n_segments is None and options.skeleton.enabled
    with warnings.catch_warnings(record=True) as caught:
        result = plan.skeleton(prep, topology if topology is not None else plan.joints(prep))
    kept_warnings = list(caught)
    base = result.segmentation
    n = base.n_segments
    for _ in range(MAX_SPLITS if growable else 0):
        # Each count is tried even when the one before was not kept: one more segment
        # can cut a joined group where it is not the pair the rigid fit flagged, and
        # the next count then cuts the flagged pair too.
        crowded = crowded_nonrigid(result.skeleton)
        n += 1
        if not crowded or n > min(base.max_segments, result.trial.n_markers):
            break
        with plan.stage(prep, "split"):
            grown = segment_markers(result.trial, n, seed=options.seed, **options.segment.kwargs())
        grown = dataclasses.replace(
            grown, count_rule="split", eigengap_segments=base.eigengap_segments, rigid_limit=base.rigid_limit,
            split_from=base.split_from or base.n_segments,
            split_markers=result.segmentation.split_markers + crowded,
        )
        with warnings.catch_warnings(record=True) as caught:
            try:
                candidate = plan.refit(dataclasses.replace(prep, trial=result.trial, segmentation=grown))
            except DegenerateMotionError:  # e.g. a split-off marker no joint can attach: not a candidate
                continue
        if candidate.skeleton is None:
            continue
        fewer = len(candidate.skeleton.nonrigid_markers) < len(result.skeleton.nonrigid_markers)
        if fewer and count_singletons(grown.marker_segment) <= count_singletons(base.marker_segment):
            result, kept_warnings = candidate, list(caught)
    _replay(kept_warnings, stacklevel + 1)
    return plan.motion(prep, result)
