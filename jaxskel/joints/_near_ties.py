"""Tree joints the joint costs cannot tell from a rival: near ties of the spanning tree.

The minimum spanning tree takes, for every joint it keeps, the cheapest pair of
segments across the cut that joint makes: removing tree edge ``(p, c)`` splits the
segments in two, and the cheapest *other* pair reconnecting them, the rival, is the edge
the tree would hold instead had ``(p, c)`` cost a little more. So a joint is only as
certain as its margin over its rival, ``cost(rival) / cost(p, c) - 1``.

Both costs are estimates. A joint cost is a variance of marker-joint distances over
the sampled frames plus the distance prior, both divided by the pair's residual
fraction (:class:`jaxskel.joints.PairCosts`). The prior is not small: the variance can be
well under half of a tree joint's cost. The allowance below applies the variance's
relative error to the whole cost, so it is wider than the variance's own noise where
the prior weighs most. A variance from ``d`` residual degrees
of freedom has a relative standard error of about ``sqrt(2 / d)`` (Gaussian residuals),
with ``d = sum_t max(K_t - 3, 0)``: the ``K_t`` markers of the pair seen in frame ``t``
less the 3 coordinates of that frame's joint. The margin is within the sampling noise
when

    cost(rival) / cost(p, c) - 1 < z * sqrt(2 / d_joint + 2 / d_rival),

``z = 2`` by default (the difference of the two estimates is within two standard
errors). The tree could then be either way, and the data do not say which; the fit
names such joints (:attr:`jaxskel.SkeletonResult.near_ties`, the summary, a
:class:`jaxskel.AmbiguousTreeWarning`) and leaves the tree as the MST made it. (The
margins and allowances measured on real and synthetic trees, and the share of the prior
in the costs: docs/bench/evidence_from_docstrings.md.)

However wide, the smallest margin of any joint is the runner-up tree's: of the trees that
differ from the fit's in one joint, the one whose swapped pair costs the least more
relative to the joint it replaces (:func:`runner_up`, stated in the summary).

A rival the pose check replaced (:mod:`jaxskel.joints._pose_check`: a centre fixed in both
segments fits the tree's pair better) is not a near tie: the poses settled it, and the
summary reports the exchange (and neither is it the runner-up).

Tried and not used: the same test on the variance parts alone (the prior taken out),
which asks whether the data, not the prior, chose the joint. It names wrong joints
where the rival fits the distances as well or better and only the prior decided, but
also right joints on synthetic and real trees, and it misses a wrong joint that wins
on the variance too (measured: docs/bench/evidence_from_docstrings.md).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from ._attachments import core_costs
from ._pose_check import MISFIT_FACTOR, TIE_Z
from ._tree import _adjacency, _bfs

__all__ = [
    "NearTie", "RivalMargin", "cost_variance", "near_ties", "residual_dof", "rival_edges", "rival_margins", "runner_up",
]


class NearTie(NamedTuple):
    """A tree joint whose cost is within the sampling noise of its rival's (:func:`near_ties`).

    ``joint`` indexes ``topology.edges``; ``edge`` is that (parent, child) pair and
    ``rival`` the pair the tree would joint instead. ``cost`` and ``rival_cost`` are the
    MST weights (m^2), ``margin`` = ``rival_cost / cost - 1`` and ``noise`` the margin the
    sampling noise allows (``z`` standard errors).
    """

    joint: int
    edge: tuple[int, int]
    rival: tuple[int, int]
    cost: float
    rival_cost: float
    margin: float
    noise: float


def rival_edges(
    cost: np.ndarray, edges: np.ndarray, exclude: Any = ()
) -> list[tuple[int, int] | None]:
    """For each tree edge, the cheapest other finite pair reconnecting the tree without it
    (``None`` where no finite pair crosses the cut); the pairs in ``exclude`` (an iterable
    of pairs, either order) are never rivals."""
    cost = np.array(cost, dtype=float)
    for a, b in exclude:
        cost[a, b] = cost[b, a] = np.inf
    n = cost.shape[0]
    edges = np.asarray(edges, dtype=int).reshape(-1, 2)
    out: list[tuple[int, int] | None] = []
    for e, (a, b) in enumerate(edges):
        # the side of the cut holding a: what the other tree edges reach from a
        side = np.zeros(n, dtype=bool)
        side[list(_bfs(_adjacency(n, np.delete(edges, e, axis=0)), int(a))[0])] = True
        crossing = np.where(side[:, None] & ~side[None, :], cost, np.inf)
        crossing[a, b] = crossing[b, a] = np.inf
        i, j = np.unravel_index(np.argmin(crossing), crossing.shape)
        out.append((int(i), int(j)) if np.isfinite(crossing[i, j]) else None)
    return out


class RivalMargin(NamedTuple):
    """A tree joint against its rival (:func:`rival_margins`): ``joint`` indexes
    ``topology.edges``, ``edge`` is its pair and ``rival`` the cheapest other pair across its
    cut; ``cost``, ``rival_cost`` their MST weights (m^2), ``margin`` = ``rival_cost / cost - 1``."""

    joint: int
    edge: tuple[int, int]
    rival: tuple[int, int]
    cost: float
    rival_cost: float
    margin: float


def rival_margins(topology: Any, cost: np.ndarray | None = None) -> list[RivalMargin]:
    """Every tree joint's margin over its rival, in the order of ``topology.edges``, by the
    (S, S) ``cost`` (default the joint costs, ``topology.pair_costs.cost``).

    A pair the pose check took out of the tree (:mod:`jaxskel.joints._pose_check`: the poses
    settled it) is never a rival; the next cheapest pair across the cut is. Left out:
    joints with no finite rival or no finite positive cost.
    """
    pc = topology.pair_costs
    if pc is None or not len(topology.edges):
        return []
    weight = np.asarray(pc.cost if cost is None else cost, dtype=float)
    overruled = [e.removed for e in topology.pose_exchanges]
    out = []
    for j, ((p, c), rival) in enumerate(zip(topology.edges.tolist(), rival_edges(weight, topology.edges, overruled))):
        if rival is None:
            continue
        cost_pc, rival_cost = float(weight[p, c]), float(weight[rival])
        if np.isfinite(cost_pc) and cost_pc > 0:
            out.append(RivalMargin(j, (int(p), int(c)), rival, cost_pc, rival_cost, rival_cost / cost_pc - 1.0))
    return out


def runner_up(topology: Any, cost: np.ndarray | None = None) -> RivalMargin | None:
    """The runner-up tree: of the trees that differ from ``topology``'s in one joint, the one
    whose swapped pair costs the least more by ``cost``, relative to the joint it replaces
    (the smallest :func:`rival_margins`); ``None`` where no joint has a rival.

    Given the core's costs of :func:`jaxskel.joints._attachments.attachment_tree` (``inf`` to and
    from a one-marker segment), the attachments, hung by rigidity and not by cost, neither
    have a runner-up nor are one."""
    return min(rival_margins(topology, cost), key=lambda m: m.margin, default=None)


def residual_dof(mask: np.ndarray, marker_segment: np.ndarray, n_segments: int) -> np.ndarray:
    """(S, S) residual degrees of freedom of every pair's joint cost on the frames of
    ``mask`` (F, M): ``d = sum_t max(K_t - 3, 0)``, ``K_t`` the pair's markers seen in frame
    ``t`` (module docstring)."""
    seg = np.asarray(marker_segment)
    onehot = (seg[:, None] == np.arange(n_segments)[None]).astype(float)  # (M, S); left-out markers: -1
    seen = np.asarray(mask, dtype=float) @ onehot  # (F, S)
    return np.maximum(seen[:, :, None] + seen[:, None, :] - 3.0, 0.0).sum(axis=0)


def cost_variance(dof: np.ndarray) -> np.ndarray:
    """Squared relative sampling error of joint costs with ``dof`` residual degrees of
    freedom (:func:`residual_dof`): ``2 / d``, ``inf`` where ``d`` is 0 (no estimate).
    Two costs are a near tie when ``cost_b / cost_a - 1 < z sqrt(var_a + var_b)``."""
    dof = np.asarray(dof, dtype=float)
    return np.where(dof > 0, 2.0 / np.maximum(dof, 1.0), np.inf)


def near_ties(trial: Any, segmentation: Any, topology: Any, *, z: float = TIE_Z) -> list[NearTie]:
    """Tree joints whose margin over their rival is within ``z`` standard errors of the
    costs' sampling noise (module docstring), in the order of ``topology.edges``.

    ``trial`` is the trial the joint costs were computed on (``result.trial``).
    """
    pc = topology.pair_costs
    if pc is None or not len(topology.edges):
        return []
    mask = np.asarray(trial.mask)[np.asarray(pc.frames)]
    var = cost_variance(residual_dof(mask, segmentation.marker_segment, segmentation.n_segments))
    out = []
    # on the core's costs: a one-marker attachment neither has a near tie nor is one
    misfit = getattr(topology, "fixed_misfit", None)
    for m in rival_margins(topology, core_costs(pc, segmentation)):
        if misfit is not None and misfit[m.rival] > MISFIT_FACTOR * misfit[m.edge]:
            continue  # the poses settle it: a centre fixed in both fits the tree's pair far better
        if not np.isfinite(var[m.edge] + var[m.rival]):
            continue
        noise = z * float(np.sqrt(var[m.edge] + var[m.rival]))
        if m.margin < noise:
            out.append(NearTie(m.joint, m.edge, m.rival, m.cost, m.rival_cost, m.margin, noise))
    return out
