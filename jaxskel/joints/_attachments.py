"""Single-marker segments as attachments of the tree, never as hubs.

A segment of one marker tests a joint by one distance per frame: whether its marker
keeps a constant distance to a point of the other segment. Almost any neighbour passes
that test, so in the minimum spanning tree of the joint costs (Kirk et al. 2005, §3.2)
a one-marker segment becomes a hub. Real marker sets make such segments out of markers
placed on joints (acromion, ankle, wrist) and out of lone markers (a hand), and the tree
hangs whole segments from them (an example: docs/bench/evidence_from_docstrings.md).

The tree is therefore built in two layers:

1. Every one-marker segment ``s`` is an **attachment** of its *host*: the segment of two
   or more markers it is most rigid with, by the median over that segment's markers of
   the distance standard deviation ``A`` of segmentation (the statistic the segments
   were grouped by). It is a leaf of its host. Where the host has two markers the pair
   has three, too few for a joint cost (:func:`jaxskel.joints.joint_costs`): the joint is then
   solved with the distance prior alone (it places the centre near the markers, and
   the fit reports it undetermined), which keeps the tree right (a lone hand marker on
   its two-marker forearm, not on the upper arm a cost can be computed with).
2. The segments of two or more markers form the **core**, joined by the minimum
   spanning tree of their joint costs. A marker on a joint is nearly rigid with both
   of its neighbours, so an attachment also testifies to the joint between its host and
   its *second* most rigid segment ``x``: the core's cost of that pair is the lower of
   their own joint cost and the attachment's cost with ``x`` (only where the pair is
   feasible by itself; its joint is solved on its own markers). An acromion marker
   rigid with the upper arm, next with the thorax, so makes the shoulder joint cheap;
   its cheap joint with the head, which it is not rigid with, counts for nothing.

With no one-marker segment this is the minimum spanning tree of the paper. A one-marker
segment whose joint with its most rigid segment is infeasible for another reason (never
seen together, never moved) takes part in the core's tree like any other segment.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from ._tree import mst_edges

__all__ = ["Attachment", "attachment_tree", "core_costs"]


class Attachment(NamedTuple):
    """A one-marker segment ``segment`` hung from ``host`` (its most rigid segment of two
    or more markers, median distance std ``rigidity`` metres); ``bridge`` is its second
    most rigid such segment (or -1), whose joint with the host it testifies to."""

    segment: int
    host: int
    bridge: int
    rigidity: float


def _attachments(
    marker_segment: np.ndarray, distance_std: np.ndarray, cost: np.ndarray, too_few: np.ndarray
) -> list[Attachment]:
    n = cost.shape[0]
    sizes = np.bincount(marker_segment[marker_segment >= 0], minlength=n)
    out = []
    for s in np.flatnonzero(sizes == 1):
        marker = int(np.flatnonzero(marker_segment == s)[0])
        ranked = []
        for g in np.flatnonzero(sizes >= 2):
            a = distance_std[marker, marker_segment == g]
            if np.isfinite(a).any():
                ranked.append((float(np.nanmedian(a)), int(g)))
        ranked.sort()
        if ranked and (np.isfinite(cost[s, ranked[0][1]]) or too_few[s, ranked[0][1]]):
            bridge = ranked[1][1] if len(ranked) > 1 else -1
            out.append(Attachment(int(s), ranked[0][1], bridge, ranked[0][0]))
    return out


def attachment_tree(
    cost: np.ndarray, marker_segment: np.ndarray, distance_std: np.ndarray, too_few: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[Attachment, ...], np.ndarray]:
    """Undirected tree edges (E, 2), the attachments, and the core's cost matrix (module
    docstring). ``cost`` (S, S) is the joint cost (``inf``: infeasible), ``distance_std``
    (M, M) segmentation's ``A`` (NaN: unobserved), ``too_few`` (S, S) the pairs infeasible
    only for want of markers (:attr:`jaxskel.joints.PairCosts.too_few_markers`)."""
    cost = np.asarray(cost, dtype=float)
    marker_segment = np.asarray(marker_segment)
    too_few = np.zeros(cost.shape, bool) if too_few is None else np.asarray(too_few, bool)
    attachments = _attachments(marker_segment, np.asarray(distance_std, dtype=float), cost, too_few)
    core_cost = cost.copy()
    for att in attachments:
        core_cost[att.segment, :] = np.inf
        core_cost[:, att.segment] = np.inf
    for att in attachments:
        g, x = att.host, att.bridge
        if x >= 0 and np.isfinite(cost[g, x]):
            core_cost[g, x] = core_cost[x, g] = min(core_cost[g, x], cost[att.segment, x])
    core = mst_edges(core_cost)
    leaves = np.array([(a.host, a.segment) for a in attachments], dtype=int).reshape(-1, 2)
    edges = np.sort(np.concatenate([core, leaves]), axis=1)
    return edges[np.lexsort((edges[:, 1], edges[:, 0]))], tuple(attachments), core_cost


def core_costs(pair_costs: Any, segmentation: Any) -> np.ndarray:
    """The (S, S) costs the core's spanning tree is built on (:func:`attachment_tree`):
    ``inf`` to and from one-marker attachments, the pairs they bridge at their cost. The
    tree's rivals and near ties are judged on these: an attachment is hung by rigidity,
    and its cheap joint costs are what made it a hub."""
    return attachment_tree(
        pair_costs.cost, segmentation.marker_segment, segmentation.distance_std, pair_costs.too_few_markers
    )[2]
