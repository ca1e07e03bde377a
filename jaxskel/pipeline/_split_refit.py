"""Grow an automatic segment count where the rigid skeleton cannot hold a group.

The automatic count (:func:`jaxskel.segment.segment_markers`: the eigengap, grown until every
group is rigid at ``rigid_ratio * sigma``) can join two segments whose joint moves
little: their markers' distances vary by a few millimetres, under the segmentation's
rigidity limit (``sigma`` is at least 3 mm, so that soft tissue on real data does not
split segments). The rigid skeleton sees such a group plainly: one rigid body cannot
follow both parts, and the markers of the smaller part keep residuals of several times
the median (:attr:`jaxskel.skeleton.Skeleton.nonrigid_markers`, ``> 3x`` the median RMS and
``> median + 1 mm``). Random 12-segment trees (1 mm noise): the eigengap joined two
segments twice in four seeds, and in both the joined group held 2-5 flagged markers.

A single flagged marker on a segment is what soft tissue and markers on joints look
like on real data (the bundled sample's right head marker, a forearm marker in HDM05
bd), so the count grows only where a segment holds **two or more** flagged markers:

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
from collections.abc import Callable
from typing import Any

import numpy as np

from .._errors import DegenerateMotionError
from ..segment import count_singletons, segment_markers

__all__ = ["crowded_nonrigid", "fit_growing_count", "MAX_SPLITS"]

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


def fit_growing_count(
    prep: Any,
    first: Callable[[Any], Any],
    refit: Callable[[Any], Any],
    add_motion: Callable[[Any, Any], Any],
    *,
    seed: int,
    segment_kwargs: dict[str, Any] | None,
    on_stage: Any = None,
    stacklevel: int = 2,
) -> Any:
    """Fit a prepared fit, growing its automatic count while a segment holds two or more
    markers the rigid skeleton cannot hold (module docstring).

    ``first(prep)`` and ``refit(prep)`` return a :class:`jaxskel.SkeletonResult` without
    inverse kinematics (they are given a ``prep`` whose settings say ``ik=False``);
    ``add_motion(prep, result)`` runs the IK on the kept result. The kept fit's warnings
    are re-emitted at ``stacklevel`` relative to the caller (2: the caller's caller).
    """
    settings = dict(prep.settings)
    growable = settings.get("n_segments") is None and settings.get("rigid", True)
    no_ik = dataclasses.replace(prep, settings={**settings, "ik": False})
    with warnings.catch_warnings(record=True) as caught:
        result = first(no_ik)
    kept_warnings = list(caught)
    base = result.segmentation
    n = base.n_segments
    for _ in range(MAX_SPLITS if growable else 0):
        # Each count is tried even when the one before was not kept: one more segment
        # can cut a joined group where it is not the pair the rigid fit flagged, and
        # the next count then cuts the flagged pair too (a random 10-segment tree, seed
        # 10: 8 -> 9 flags as many markers as before, 10 none).
        crowded = crowded_nonrigid(result.skeleton)
        n += 1
        if not crowded or n > min(base.max_segments, result.trial.n_markers):
            break
        with no_ik.stage("split", on_stage):
            grown = segment_markers(result.trial, n, seed=seed, **(segment_kwargs or {}))
        grown = dataclasses.replace(
            grown, count_rule="split", eigengap_segments=base.eigengap_segments, rigid_limit=base.rigid_limit,
            split_from=base.split_from or base.n_segments,
            split_markers=result.segmentation.split_markers + crowded,
        )
        with warnings.catch_warnings(record=True) as caught:
            try:
                candidate = refit(dataclasses.replace(no_ik, trial=result.trial, segmentation=grown))
            except DegenerateMotionError:  # e.g. a split-off marker no joint can attach: not a candidate
                continue
        if candidate.skeleton is None:
            continue
        fewer = len(candidate.skeleton.nonrigid_markers) < len(result.skeleton.nonrigid_markers)
        if fewer and count_singletons(grown.marker_segment) <= count_singletons(base.marker_segment):
            result, kept_warnings = candidate, list(caught)
    _replay(kept_warnings, stacklevel + 1)
    return add_motion(prep, dataclasses.replace(result, settings=settings))
