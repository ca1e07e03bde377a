"""How much the joint of a one-marker segment may steer its host's Procrustes pose.

The per-segment Procrustes step of the rigid fit (:mod:`jaxskel.skeleton._rigid_fit`) aligns
each segment's markers *and the centres of its joints*. A one-marker segment hangs from
its host (:mod:`jaxskel.joints._attachments`), and the centre of their joint is fixed by
that one marker's distance: where the pair has three markers, any distances fit and the
distance prior places it. When the lone marker is a cluster marker that soft tissue moves
by centimetres (split off its cluster for that reason) and its host keeps two markers,
this centre keeps its distances to all three and so turns about the line of the host's
two markers with the lone one; aligned like a marker, it turns the host's pose, and the
host then no longer turns as a hinge against its neighbour (a knee 54 mm off along its
axis, measured: docs/bench/decisions.md).

So the host is aligned twice. First on its own points alone (its markers and its other
joints). In that pose each attachment joint ``a`` has a mean position and an RMS scatter
``s_a`` about it; the host's own points scatter by ``s_0`` (their median, at least
``FLOOR``). Then again with each attachment joint weighted by its inverse variance
relative to the host's own points,

    w_a = min(1, (s_0 / s_a)^2),

the weight a point of scatter ``s_a`` has in a weighted least-squares fit whose other
points scatter by ``s_0``. A joint that sits as still in its host as the host's own
points keeps weight 1, as before (the bundled sample's lone acromion, hand and ankle
markers: 0.1-0.7); one that wanders with its marker weighs next to nothing (0.001-0.025
for a thigh marker moved 15-30 mm by soft tissue) and rides along: its position in the
host is its mean there. Only hosts that keep three points of their own are treated so (a
host needs three to be posed).
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

__all__ = ["FLOOR", "attachment_points", "attachment_weights", "scatter_about_mean"]

#: Least scatter (metres) of a host's own points in the weights: marker noise of a good system.
FLOOR = 1e-3


def attachment_points(
    edges: Int[np.ndarray, "J 2"], members: list[np.ndarray], seg_joints: list[np.ndarray], width: int
) -> Bool[np.ndarray, "S P"]:
    """(S, P) the Procrustes points (markers first, then joints, as the rigid fit lays them
    out) that are a host's joint with a one-marker segment, on hosts that keep at least
    three points of their own."""
    n_seg = len(members)
    hung = np.zeros((n_seg, width), bool)
    for s in range(n_seg):
        for k, j in enumerate(seg_joints[s]):
            other = int(edges[j, 1] if edges[j, 0] == s else edges[j, 0])
            if len(members[other]) == 1 and len(members[s]) > 0:
                hung[s, len(members[s]) + k] = True
        if len(members[s]) + len(seg_joints[s]) - hung[s].sum() < 3:
            hung[s] = False
    return hung


def scatter_about_mean(
    points: Float[np.ndarray, "F S P 3"],
    weights: Float[np.ndarray, "F S P"],
    rot: Float[np.ndarray, "F S 3 3"],
    trans: Float[np.ndarray, "F S 3"],
) -> tuple[Float[np.ndarray, "S P 3"], Float[np.ndarray, "S P"]]:
    """Each point's weighted mean in its segment's aligned frame (``R x + t``) and its RMS
    scatter about that mean (NaN where never weighted)."""
    cloud = np.einsum("fsij,fspj->fspi", rot, points) + trans[:, :, None, :]
    total = weights.sum(axis=0)
    safe = np.maximum(total, 1e-300)
    mean = np.einsum("fsp,fspi->spi", weights, cloud) / safe[..., None]
    spread = np.sqrt(np.einsum("fsp,fsp->sp", weights, np.sum((cloud - mean[None]) ** 2, axis=-1)) / safe)
    return mean, np.where(total > 0, spread, np.nan)


def attachment_weights(
    hung: Bool[np.ndarray, "S P"], own_scatter: Float[np.ndarray, "S P"], hung_scatter: Float[np.ndarray, "S P"]
) -> Float[np.ndarray, "S P"]:
    """(S, P) each point's weight in its segment's alignment (module docstring): 1 for the
    segment's own points, ``min(1, (s_0 / s_a)^2)`` for the attachment joints ``hung``.
    ``own_scatter`` is the scatter of every point in the first alignment (NaN where the
    point was not aligned), ``hung_scatter`` the attachment joints' scatter in it."""
    own = np.where(~hung & (own_scatter > 0), own_scatter, np.nan)
    typical = np.full(own.shape[0], FLOOR)
    some = np.isfinite(own).any(axis=1)  # a segment without scattered own points keeps the floor
    typical[some] = np.maximum(np.nanmedian(own[some], axis=1), FLOOR)
    scatter = np.nan_to_num(hung_scatter, nan=0.0)
    # own points, and attachment joints as still as the host's own points: a marker's weight
    still = ~hung | (scatter <= typical[:, None])
    return np.where(still, 1.0, (typical[:, None] / np.where(still, 1.0, scatter)) ** 2)
