"""The tree's joints checked against the segments' poses: points fixed in both frames.

Kirk et al.'s joint cost (§3.2) gives the joint its own position ``j_f`` in every frame
and asks only that marker-joint distances stay constant. The relaxation is what lets the
method test a joint on segments of one or two markers, but it lets ``j_f`` wander with
whatever the distances do not pin down, and it charges a segment's own non-rigidity to
every joint the segment is tried with: a thorax group that bends with the spine makes
the head's true joint expensive, and a neighbour that barely turns can then come out
cheaper.

A joint is a point fixed in both segments. Where each segment of a pair carries three
or more non-collinear markers, their marker-only poses (``R x + t`` maps a frame's
markers onto the segment's mean cloud; :func:`jaxskel.joints._anchored_centres._segment_poses`)
test that directly. The pair's *fixed-centre misfit* is

    m(a, b) = min_{c_a, c_b} mean_f |R_a(f)^T (c_a - t_a(f)) - R_b(f)^T (c_b - t_b(f))|^2,

the mean squared distance (m^2) between where the two segments put the joint, over the
frames that pose both: a linear least-squares problem in six unknowns (SCoRE, Ehrig et
al. 2006), solved for every pair at once from its 6 x 6 normal equations
(pseudo-inverse: along a hinge's axis the centre is free and the misfit does not
depend on it). Each pose averages over its segment's markers, so a segment that flexes
moves its pose, not the test.

The check overrules the joint costs only where the poses reject a tree joint clearly.
Removing tree edge ``(p, c)`` cuts the tree in two; the lowest-misfit pair across the
cut (of finite joint cost) is its rival. Where the rival's misfit is below the edge's
divided by :data:`MISFIT_FACTOR` (2: the factor by which jaxskel calls a misfit changed;
a centre's resolution is the distance over which its misfit doubles), the tree takes the
rival instead; the worst-fitting edge first, until no edge has such a rival. Edges to a
segment with fewer than three markers, or between segments posed together in too few
frames, are never judged. Each exchange is reported (:class:`PoseExchange`, the
summary, ``/topology/pose_exchanges``), and the near-tie test
(:mod:`jaxskel.joints._near_ties`) does not count a rival the poses have rejected.

Segments of one or two markers have no pose, and the check above never judges their
joints; the joint costs made such a segment a hub where its one or two distances fitted
several neighbours about equally well. A second pass judges exactly those edges, with
the *anchored sphere misfit* (:func:`sphere_misfit`): how far the sparse segment's
markers are from keeping constant distances to one centre fixed in the other segment's
pose. Rivals across the cut are judged by the same statistic (the better of a pair's
two directions), with the same factor, and
one-marker attachments (:mod:`jaxskel.joints._attachments`) take no part. A third pass
judges the edges between posed segments by the same statistic, against the rivals across
their cut that the first pass could not pose (a pair with a segment of one or two
markers): where the costs made a neighbour's neighbour the parent of a segment and left a
two-marker hub out, only this comparison sees it. Exchanges are labelled
``test="sphere"``. Its effect on synthetic and real trees is measured in
docs/bench/sweep_bodies.md and docs/bench/real_trees.md.

The factor of two is a margin for joints the costs chose clearly. Where they did not, a
third pass lets the poses decide with less: a tree edge between posed segments whose
rival across the cut is a *near tie* (its cost within the costs' sampling noise,
:mod:`jaxskel.joints._near_ties`) is exchanged for the near tie of lowest fixed-centre
misfit when that misfit is lower by ``TIE_Z`` (2) standard errors (:func:`misfit_drop_z`:
the per-frame difference of the two pairs' errors, its error from the means of
``MISFIT_BLOCKS`` stretches of time, whose frames are correlated). Exchanges are
labelled ``test="near_tie"``. (PronetoRun01, running: the thighs turn about nearly one
axis, so L thigh-R thigh cost 7 % less than the pelvis-R thigh hip, but its misfit is
1.97x the hip's, 3.2 standard errors; head-R upper arm against thorax-R upper arm,
1.34x but 1.3 standard errors, stays, a near tie the summary names.)

Why a margin, and not simply a spanning tree of the misfit: where two segments barely
turn against each other, any point is nearly fixed in both and the misfit is small
whatever the joint: segments that move alike (both thighs in a symmetric squat) fit
each other better than their true joints, and a minimum spanning tree of the misfit
joints them.

The fixed-centre check's measured effect on real and synthetic trees, and the misfits of
the cases above, are in docs/bench/evidence_from_docstrings.md.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._tree import _adjacency, _bfs

__all__ = [
    "MISFIT_FACTOR", "PoseExchange", "segment_poses", "fixed_centre_errors", "fixed_centre_misfit", "misfit_drop_z",
    "misfit_from_errors", "sphere_misfit", "pose_checked_edges",
]

#: The poses overrule the joint costs only where the rival's misfit is below the tree
#: edge's divided by this: the factor by which jaxskel calls a misfit changed (a centre's
#: resolution is the distance over which its misfit doubles, :mod:`jaxskel.joints._determination`).
MISFIT_FACTOR = 2.0
#: Standard errors of the costs' sampling noise within which a rival is a near tie
#: (:func:`jaxskel.joints._near_ties.near_ties`' default ``z``).
TIE_Z = 2.0
#: Stretches of time the near-tie pass's standard error is read from (:func:`misfit_drop_z`).
MISFIT_BLOCKS = 10
#: Gauss-Newton steps of the anchored sphere misfit's centre from its algebraic start.
SPHERE_STEPS = 8


class PoseExchange(NamedTuple):
    """A joint-cost MST edge the pose check replaced (:func:`pose_checked_edges`).

    ``removed`` is the MST's pair, ``added`` the pair the tree joints instead; ``misfit``
    is their misfits under ``test`` and ``cost`` their joint costs (both m^2, removed
    first). ``test`` is ``"fixed"`` (a centre fixed in both poses, :func:`fixed_centre_misfit`)
    or ``"sphere"`` (an edge to a segment of one or two markers: those markers about a
    centre fixed in the other's pose, :func:`sphere_misfit`).
    """

    removed: tuple[int, int]
    added: tuple[int, int]
    misfit: tuple[float, float]
    cost: tuple[float, float]
    test: str = "fixed"


def segment_poses(
    x: np.ndarray, mask: np.ndarray, marker_segment: np.ndarray, n_segments: int, frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``R`` (F, S, 3, 3), ``t`` (F, S, 3), ``posed`` (F, S) on ``frames``: the anchored
    refit's marker-only poses (``R x + t`` is a marker in its segment's frame: the mean
    clouds of the whole recording, each of ``frames`` aligned to them alone), identity
    where not posed."""
    from ._anchored_centres import MAX_FRAMES, _segment_poses

    rot, t, posed = _segment_poses(x, mask, marker_segment, n_segments, MAX_FRAMES, frames=frames)
    rot = np.where(posed[..., None, None], rot, np.eye(3))
    t = np.where(posed[..., None], t, 0.0)
    return rot, t, posed


def sphere_misfit(
    x: np.ndarray, mask: np.ndarray, marker_segment: np.ndarray, n_segments: int, frames: np.ndarray,
    min_frames: int, poses: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(S, S) anchored sphere misfit (m^2): ``m[a, b]`` is how far ``b``'s markers are from
    keeping constant distances to one centre fixed in ``a``'s pose,

        m[a, b] = mean_{k in b} var_f |p_kf - c|,   p_kf = R_a(f) x_kf + t_a(f),

    with ``c`` the shared centre that minimises it: started at the algebraic sphere fit
    (|p|^2 = 2 p.c + d_k is linear; with each ``d_k`` eliminated it is the 3 x 3 system
    sum_k sum_f p~ p~^T c = 1/2 sum_k sum_f p~ (|p|^2 - mean |p|^2), p~ = p - mean p,
    pseudo-inverse: a hinge leaves the centre free along its axis, which changes no
    variance), then :data:`SPHERE_STEPS` Gauss-Newton steps on the variance (residuals
    ``|p_kf - c| - mean_f |p_kf - c|``, pseudo-inverse again), each pair keeping its
    lowest misfit. The algebraic centre alone lies off on a short arc (its error weighs
    points by ``|p|``) and reads a true joint at several times the noise there
    (docs/bench/decisions.md). It needs a pose
    of ``a`` only, so it judges joints of segments of one or two markers, which
    :func:`fixed_centre_misfit` cannot. Directed; ``inf`` where ``a`` has no pose, where
    a marker of ``b`` is seen with ``a`` posed in fewer than ``min_frames`` of ``frames``,
    and on the diagonal.
    """
    rot, t, posed = poses if poses is not None else segment_poses(x, mask, marker_segment, n_segments, frames)
    x, mask = x[frames], mask[frames]
    s = n_segments
    seg = np.asarray(marker_segment)
    onehot = (seg[:, None] == np.arange(s)[None]).astype(float)  # (M, S)
    # Sums over frames are batched matrix products over (a, m): frames last, axes (S, M, F, ...).
    xw = np.where(mask[..., None], x, 0.0)  # (F, M, 3)
    p = np.matmul(xw[:, None], rot.transpose(0, 1, 3, 2)) + t[:, :, None, :]  # (F, S, M, 3)
    p = np.ascontiguousarray(p.transpose(1, 2, 0, 3))  # (S, M, F, 3)
    w = np.ascontiguousarray((posed.T[:, None, :] & mask.T[None, :, :]).astype(float))  # (S, M, F)
    n = w.sum(axis=-1)  # (S, M)
    inv_n = 1.0 / np.maximum(n, 1)

    def mean_f(v: np.ndarray) -> np.ndarray:
        """sum_f w v / n over the frames (last axis) of ``v`` (S, M, F)."""
        return np.matmul(w[:, :, None, :], v[..., None])[..., 0, 0] * inv_n

    def moments(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sum_f w u u^T (S, M, 3, 3) and sum_f w u v (S, M, 3) of ``u`` (S, M, F, 3), ``v`` (S, M, F)."""
        wu = w[..., None] * u
        return np.matmul(wu.transpose(0, 1, 3, 2), u), np.matmul(wu.transpose(0, 1, 3, 2), v[..., None])[..., 0]

    def per_pair(a_m: np.ndarray) -> np.ndarray:
        """(S_a, M, ...) summed over each segment b's markers: (S_a, S_b, ...)."""
        return np.moveaxis(np.tensordot(a_m, onehot, axes=([1], [0])), -1, 1)

    mean_p = np.matmul(w[:, :, None, :], p)[:, :, 0] * inv_n[..., None]  # (S, M, 3)
    sq = np.sum(p * p, axis=-1)  # (S, M, F)
    pc = p - mean_p[:, :, None]
    cov, g = moments(pc, sq - mean_f(sq)[..., None])
    centre = 0.5 * np.matmul(np.linalg.pinv(per_pair(cov)), per_pair(g)[..., None])[..., 0]  # (S_a, S_b, 3)
    counts = np.maximum(onehot.sum(axis=0), 1)

    def about(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The misfit (S_a, S_b) about centres ``c`` (S_a, S_b, 3), each marker's offsets
        from its centre (S, M, F, 3) and distances less their means (S, M, F)."""
        off = p - c[:, seg][:, :, None]  # marker m about c[a, seg[m]]
        dist = np.sqrt(np.sum(off * off, axis=-1))
        resid = dist - mean_f(dist)[..., None]
        var = mean_f(resid * resid)
        return (var @ onehot) / counts[None], off / np.maximum(dist, 1e-12)[..., None], resid

    # The algebraic centre minimises the algebraic error, not the distances' variance: on a
    # short arc it lies off the centre that does (a true joint read at 10 mm^2 instead of
    # 3). Gauss-Newton on the variance from there, each pair keeping its best centre.
    misfit, unit, resid = about(centre)
    for _ in range(SPHERE_STEPS):
        jac = unit - (np.matmul(w[:, :, None, :], unit)[:, :, 0] * inv_n[..., None])[:, :, None]  # -d resid / d c
        normal, rhs = moments(jac, resid)
        step = np.matmul(np.linalg.pinv(per_pair(normal)), per_pair(rhs)[..., None])[..., 0]
        trial_misfit, trial_unit, trial_resid = about(centre + step)
        better = trial_misfit < misfit
        if not better.any():
            break
        centre = np.where(better[..., None], centre + step, centre)
        misfit = np.where(better, trial_misfit, misfit)
        keep = better[:, seg][:, :, None]  # (S, M, 1): each marker follows its pair's centre
        unit = np.where(keep[..., None], trial_unit, unit)
        resid = np.where(keep, trial_resid, resid)
    enough = ((n < min_frames).astype(float) @ onehot) == 0
    posed_any = posed.any(axis=0)
    ok = enough & posed_any[:, None] & ~np.eye(s, dtype=bool) & (onehot.sum(axis=0) > 0)[None]
    return np.where(ok, misfit, np.inf)


def fixed_centre_misfit(
    x: np.ndarray, mask: np.ndarray, marker_segment: np.ndarray, n_segments: int, frames: np.ndarray,
    min_frames: int, poses: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(S, S) fixed-centre misfit (m^2, module docstring) of every pair of posed segments.

    ``x`` (F, M, 3) and ``mask`` (F, M) are the whole recording, posed as the anchored
    refit poses it (the same compiled alignment); the misfit uses the ``frames`` given
    (the all-pairs pass's subsample). ``inf`` where either segment has no pose (fewer
    than three non-collinear markers) or fewer than ``min_frames`` of those frames pose
    both, and on the diagonal.
    """
    return misfit_from_errors(*fixed_centre_errors(x, mask, marker_segment, n_segments, frames, poses=poses),
                              min_frames)


def misfit_from_errors(errors: np.ndarray, both: np.ndarray, min_frames: int) -> np.ndarray:
    """(S, S) :func:`fixed_centre_misfit` from the per-frame :func:`fixed_centre_errors`."""
    n = both.sum(axis=0)
    misfit = np.einsum("fab,fab->ab", both, errors) / np.maximum(n, 1.0)
    misfit = np.where((n >= min_frames) & ~np.eye(n.shape[0], dtype=bool), misfit, np.inf)
    return np.minimum(misfit, misfit.T)  # symmetric up to rounding


def misfit_drop_z(errors: np.ndarray, both: np.ndarray, edge: tuple[int, int], rival: tuple[int, int],
                  blocks: int = MISFIT_BLOCKS) -> float:
    """How many standard errors the fixed-centre misfit of ``rival`` lies below ``edge``'s.

    The paired difference ``e_f = errors[f, edge] - errors[f, rival]`` over the frames that
    pose all the segments of both, whose mean is the misfits' difference; its standard
    error from ``blocks`` contiguous stretches of time (batch means: the frames of a
    stretch are correlated, the stretches nearly not), ``std(block means) / sqrt(blocks)``.
    0 where fewer than two frames per block pose both pairs.
    """
    seen = (both[:, edge[0], edge[1]] > 0) & (both[:, rival[0], rival[1]] > 0)
    diff = (errors[:, edge[0], edge[1]] - errors[:, rival[0], rival[1]])[seen]
    if len(diff) < 2 * blocks:
        return 0.0
    means = np.array([part.mean() for part in np.array_split(diff, blocks)])
    spread = means.std(ddof=1) / np.sqrt(blocks)
    return float(diff.mean() / spread) if spread > 0 else float(np.sign(diff.mean()) * np.inf)


def fixed_centre_errors(
    x: np.ndarray, mask: np.ndarray, marker_segment: np.ndarray, n_segments: int, frames: np.ndarray,
    poses: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, what :func:`fixed_centre_misfit` averages: ``errors`` (F, S, S), the squared
    distance (m^2) between where the two segments put the pair's best fixed centre, and
    ``both`` (F, S, S), 1.0 where both segments are posed in that frame of ``frames``."""
    rot, t, posed = poses if poses is not None else segment_poses(x, mask, marker_segment, n_segments, frames)
    w = posed.astype(float)  # (F, S)
    n = np.einsum("fa,fb->ab", w, w)
    # World from segment frame: p = R^T (c - t). For a pair, A [c_a; c_b] = q_a - q_b with
    # A = [R_a^T, -R_b^T] and q = R^T t; the normal equations' blocks per pair:
    cross = np.einsum("fa,fb,faij,fbkj->abik", w, w, rot, rot)  # sum_f R_a R_b^T
    rt_b = np.einsum("faij,fbkj,fbk->fabi", rot, rot, t)  # R_a R_b^T t_b
    # A^T (q_a - q_b) = [t_a - R_a R_b^T t_b; t_b - R_b R_a^T t_a]
    rhs_a = np.einsum("fa,fb,fabi->abi", w, w, t[:, :, None, :] - rt_b)
    rhs_b = np.einsum("fa,fb,fabi->abi", w, w, t[:, None, :, :] - rt_b.transpose(0, 2, 1, 3))
    s = n_segments
    eye = np.eye(3) * n[..., None, None]
    normal = np.zeros((s, s, 6, 6))
    normal[..., :3, :3] = eye
    normal[..., 3:, 3:] = eye
    normal[..., :3, 3:] = -cross
    normal[..., 3:, :3] = -cross.transpose(0, 1, 3, 2)
    rhs = np.concatenate([rhs_a, rhs_b], axis=-1)
    centres = np.einsum("abij,abj->abi", np.linalg.pinv(normal), rhs)
    world = np.einsum("faji,abj->fabi", rot, centres[..., :3]) - np.einsum("faji,faj->fai", rot, t)[:, :, None]
    other = np.einsum("fbji,abj->fabi", rot, centres[..., 3:]) - np.einsum("fbji,fbj->fbi", rot, t)[:, None]
    both = w[:, :, None] * w[:, None, :]
    return np.einsum("fabi,fabi->fab", world - other, world - other), both


def pose_checked_edges(
    edges: np.ndarray, misfit: np.ndarray, cost: np.ndarray, *, factor: float = MISFIT_FACTOR,
    judged: np.ndarray | None = None, test: str = "fixed", tie_noise: np.ndarray | None = None,
    errors: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, tuple[PoseExchange, ...]]:
    """The MST ``edges`` (E, 2) with the joints the poses reject exchanged (module docstring).

    A tree edge with a finite ``judged`` misfit (default ``misfit``) is replaced by the
    lowest-``misfit`` pair across the cut it makes (finite ``cost``, not the edge itself)
    where that pair's misfit is below the edge's divided by ``factor``; the worst edge
    first, until none is. Returns the undirected edges (sorted) and the exchanges made,
    labelled ``test``.

    With ``tie_noise`` (S, S), the squared relative sampling error of each pair's cost
    (:func:`jaxskel.joints._near_ties.cost_variance`: ``2 / d``, ``inf`` where ``d`` is 0),
    only the pairs whose cost the edge's does not beat by more than the costs' sampling
    noise take part:
    ``cost[r] / cost[e] - 1 < TIE_Z * sqrt(tie_noise[e] + tie_noise[r])``, the near ties
    of :mod:`jaxskel.joints._near_ties`, and the lowest-misfit one replaces the edge where
    its misfit is lower by ``TIE_Z`` standard errors (:func:`misfit_drop_z` on ``errors``,
    the per-frame :func:`fixed_centre_errors`): where the costs cannot tell the two joints
    apart, the poses decide, if they can.
    """
    tree = [tuple(sorted(map(int, e))) for e in np.asarray(edges, dtype=int).reshape(-1, 2)]
    n = misfit.shape[0]
    judged_misfit = misfit if judged is None else judged
    usable = np.where(np.isfinite(cost), misfit, np.inf)
    exchanges: list[PoseExchange] = []
    # Each exchange divides one edge's misfit by more than ``factor``, so the product of
    # the judged edges' misfits falls geometrically and the loop ends; the cap only
    # guards against misfits of exactly zero (noise-free input).
    for _ in range(len(tree) * n + 1):
        order = sorted((e for e in tree if np.isfinite(judged_misfit[e])), key=lambda e: -judged_misfit[e])
        for e in order:
            adj = _adjacency(n, np.array([f for f in tree if f != e], dtype=int).reshape(-1, 2))
            # the two sides of the cut (within the component: a forest stays a forest)
            side_a, side_b = np.zeros(n, bool), np.zeros(n, bool)
            side_a[list(_bfs(adj, e[0])[0])] = True
            side_b[list(_bfs(adj, e[1])[0])] = True
            crossing = np.where(side_a[:, None] & side_b[None, :], usable, np.inf)
            crossing[e[0], e[1]] = np.inf
            if tie_noise is not None:  # only the rivals the costs cannot tell from the edge
                noise = tie_noise[e] + tie_noise
                with np.errstate(divide="ignore", invalid="ignore"):  # a free edge (cost 0): no tie
                    tie = np.isfinite(noise) & (cost / cost[e] - 1.0 < TIE_Z * np.sqrt(noise))
                crossing = np.where(tie, crossing, np.inf)
            a, b = np.unravel_index(np.argmin(crossing), crossing.shape)
            new = tuple(sorted((int(a), int(b))))
            if crossing[a, b] * factor < judged_misfit[e] and (
                errors is None or misfit_drop_z(*errors, e, new) > TIE_Z
            ):
                tree[tree.index(e)] = new
                exchanges.append(PoseExchange(e, new, (float(judged_misfit[e]), float(misfit[new])),
                                              (float(cost[e]), float(cost[new])), test))
                break
        else:
            break
    return np.array(sorted(tree), dtype=int).reshape(-1, 2), tuple(exchanges)
