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
docs/bench/evidence_from_docstrings.md) among three or more: a group of two can only come
apart into lone markers, which a kept split never adds, so its two flagged markers (a thigh
left with a marker on the knee and one other, both held loosely) would only make the
segmentation start again elsewhere.

Two readings flag markers, and either can start a split:

* **the groups' scatter** (:func:`jaxskel.segment.marker_scatter`): each group posed on its
  own by Procrustes, from the segmentation alone. A joined group bends no other segment,
  so the median stays at the noise and a hinge that turns nearly about the child's own
  axis (distances varying by 2-5 mm) still stands out. It is the cheaper reading to
  judge by: a grown segmentation is read the same way before anything is fitted to it.
* **the rigid skeleton's residuals** (:attr:`jaxskel.skeleton.Skeleton.nonrigid_markers`),
  which also see a group that the scatter reads as rigid but no joint can hold.

Then:

1. segment again from scratch with one segment more (the paper's samplings and
   scoring, :func:`jaxskel.segment.segment_markers` given ``n``);
2. if the groups' scatter started it and the new segmentation's scatter flags fewer
   markers and leaves no more single-marker segments (a marker peeled off alone is always
   "rigid", and its joint is often untestable): fit the joints and the rigid skeleton
   again and keep that fit if it has a skeleton. Otherwise, if the rigid skeleton's
   residuals started it: fit again, and keep the fit if its rigid skeleton flags fewer
   markers and it leaves no more single-marker segments. A segmentation that neither
   reading improves is not fitted when only the scatter started it: soft tissue on real
   recordings flags whole groups (a head, a forearm) that no count mends;
3. while the kept fit still has a group with two or more markers flagged by either
   reading, try the next count (one more than the last one *tried*, kept or not), at most
   :data:`MAX_SPLITS` counts in all.

Warnings of the fits that are discarded are dropped; those of the kept one are
re-emitted. A given ``n_segments`` is never changed.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import numpy as np

from ..segment import Segmentation, count_singletons, crowded_flags, marker_scatter, scatter_flags

__all__ = ["MAX_SPLITS", "ScatterReading", "crowded_nonrigid", "keep_split", "read_scatter", "replay", "scatter_splits"]

#: Most segments added after the rigid fit (each one a further segmentation and fit).
MAX_SPLITS = 2


def crowded_nonrigid(skeleton: Any) -> tuple[str, ...]:
    """The flagged markers (``skeleton.nonrigid_markers``) that share a segment of three or
    more with another flagged marker (:func:`jaxskel.segment.crowded_flags`), in label
    order: a group of two can only split into lone markers, which a kept split never adds
    (:func:`keep_split`)."""
    if skeleton is None or not skeleton.nonrigid_markers:
        return ()
    labels = list(skeleton.marker_labels)
    flags = np.isin(labels, list(skeleton.nonrigid_markers))
    return tuple(labels[i] for i in crowded_flags(skeleton.marker_segment, flags))


def replay(caught: list[warnings.WarningMessage], stacklevel: int) -> None:
    """Re-emit recorded warnings ``stacklevel`` frames above the caller of this function, as
    :func:`warnings.warn` counts them (1: the caller, 2: its caller)."""
    for w in caught:
        warnings.warn(w.message, w.category, stacklevel=stacklevel + 1)


def keep_split(kept: Any, candidate: Any, base: Segmentation, grown: Segmentation) -> bool:
    """Whether a fit with one segment more replaces the kept one: its rigid skeleton flags
    fewer markers, and it leaves no more single-marker segments than the automatic count."""
    if candidate.skeleton is None:
        return False
    fewer = len(candidate.skeleton.nonrigid_markers) < len(kept.skeleton.nonrigid_markers)
    return fewer and count_singletons(grown.marker_segment) <= count_singletons(base.marker_segment)


class ScatterReading(NamedTuple):
    """What the groups' scatter flags on one segmentation (:func:`read_scatter`)."""

    #: the flagged markers that share a group of three or more with another, in label order
    crowded: tuple[str, ...]
    #: how many markers it flags in all
    flagged: int


def read_scatter(trial: Any, segmentation: Segmentation) -> ScatterReading:
    """The groups' scatter flags (:func:`jaxskel.segment.scatter_flags`) of ``segmentation``
    on ``trial``, read from the segmentation alone, before any fit."""
    flags = scatter_flags(marker_scatter(trial.positions, segmentation.marker_segment))
    crowded = crowded_flags(segmentation.marker_segment, flags)
    return ScatterReading(tuple(trial.labels[i] for i in crowded), int(flags.sum()))


def scatter_splits(kept: ScatterReading, grown: ScatterReading, grown_segmentation: Segmentation,
                   base: Segmentation) -> bool:
    """Whether a segmentation with one segment more mends what the groups' scatter flags:
    it flags fewer markers than the kept one and leaves no more single-marker segments
    than the automatic count."""
    if count_singletons(grown_segmentation.marker_segment) > count_singletons(base.marker_segment):
        return False
    return grown.flagged < kept.flagged
