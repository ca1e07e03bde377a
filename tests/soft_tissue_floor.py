"""The soft-tissue floor: how well joint centres and bone lengths can be known from skin
markers that move with the joint angles, when everything else is given.

The oracle knows what the fit has to estimate (which segment each marker is on, its true
offset there, the true tree) and keeps only what the markers' motion alone decides:

* each segment's pose in every frame showing all its markers: Horn's alignment of the
  true offsets to the observed markers (no frame is smoothed, no joint constraint);
* each true joint's centre in both segment frames, by linear least squares over frames,
  ``R_p(t) c_p + t_p(t) = R_c(t) c_c + t_c(t)`` (SCoRE, Ehrig et al. 2006); a hinge's centre
  along its axis, which no marker data fixes, is pinned to the truth.

Soft tissue that moves with the joint angles moves each marker cluster's least-squares
pose with them; a centre shifted by ``d`` in a segment's frame changes its apparent
markers by a translation that is, to first order, also linear in the angles, so this part
of the artefact and the centre's position cannot be told apart from marker data. The
oracle's error is therefore an estimate of the floor a marker-only method reaches on a
given recording; a segment with fewer than three markers cannot be posed this way, so
its joints (and the bones ending at them) have no floor (NaN).
"""

from __future__ import annotations

import numpy as np
from helpers import off_axis_rmse, segment_map

import jaxskel


def _cluster_poses(positions, offsets):
    """Horn alignment per frame of (P, 3) ``offsets`` onto (F, P, 3) ``positions``: R (F, 3, 3), t (F, 3)."""
    oc = offsets - offsets.mean(axis=0)
    centroid = positions.mean(axis=1)
    h = np.einsum("pi,fpj->fij", oc, positions - centroid[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.ones((len(h), 3))
    d[:, 2] = np.sign(np.linalg.det(u @ vt))
    rot = np.einsum("fji,fj,fkj->fik", vt, d, u)  # V diag(d) U^T
    return rot, centroid - np.einsum("fij,j->fi", rot, offsets.mean(axis=0))


def floor_skeleton(trial, truth) -> dict[str, np.ndarray]:
    """The oracle's joint centres and errors on ``trial`` (columns = ``truth``'s physical markers).

    Returns ``joint_rmse`` (J,) m, RMS over frames of the distance to the true centre (a
    hinge: to its axis line), ``bone_error`` (B,) relative error of ``truth.bones``, and
    ``centres`` (J, 2, 3) in the parent and child frames; NaN where a segment has fewer
    than three non-collinear markers or no frame shows them all.
    """
    # One trajectory per physical marker (a relabelled marker is split over columns).
    n_frames, n_seg = trial.positions.shape[0], truth.n_segments
    x = np.full((n_frames, len(truth.physical_labels), 3), np.nan)
    column_segment = np.full(len(truth.physical_labels), -1)
    column_offset = np.zeros((len(truth.physical_labels), 3))
    for col in np.flatnonzero(truth.physical >= 0):
        k = truth.physical[col]
        seen = np.isfinite(trial.positions[:, col, 0])
        x[seen, k] = trial.positions[seen, col]
        column_segment[k], column_offset[k] = truth.marker_segment[col], truth.marker_offsets[col]
    rot = np.full((n_frames, n_seg, 3, 3), np.nan)
    trans = np.full((n_frames, n_seg, 3), np.nan)
    for s in range(n_seg):
        cols = np.flatnonzero(column_segment == s)
        offsets = column_offset[cols]
        if len(cols) < 3:
            continue
        sv = np.linalg.svd(offsets - offsets.mean(axis=0), compute_uv=False)
        if sv[1] < 1e-3 * sv[0]:
            continue
        seen = np.isfinite(x[:, cols]).all(axis=(1, 2))
        if seen.sum() >= 3:
            rot[seen, s], trans[seen, s] = _cluster_poses(x[seen][:, cols], offsets)

    centres = np.full((truth.n_joints, 2, 3), np.nan)
    joint_rmse = np.full(truth.n_joints, np.nan)
    for j, (p, c) in enumerate(truth.edges):
        both = np.isfinite(trans[:, p, 0]) & np.isfinite(trans[:, c, 0])
        if both.sum() < 3:
            continue
        lhs = np.concatenate([rot[both, p], -rot[both, c]], axis=2).reshape(-1, 6)
        rhs = (trans[both, c] - trans[both, p]).reshape(-1)
        if truth.joint_types[j] == "hinge":
            # The axis is fixed in the parent; pin the centre's component along it.
            axis = truth.body.joint_axes[j][0]
            row = np.concatenate([axis, np.zeros(3)]) * np.sqrt(both.sum())
            lhs = np.vstack([lhs, row])
            rhs = np.append(rhs, row[:3] @ truth.joint_offsets[j, 0])
        centres[j] = np.linalg.lstsq(lhs, rhs, rcond=None)[0].reshape(2, 3)
        world = np.einsum("fij,j->fi", rot[:, p], centres[j, 0]) + trans[:, p]  # NaN where not posed
        joint_rmse[j] = off_axis_rmse(np.where(both[:, None], world, np.nan), truth, j)

    bone_error = np.full(len(truth.bones), np.nan)
    for b, ((j0, j1), length, s) in enumerate(zip(truth.bones, truth.bone_lengths, truth.bone_segment)):
        ends = [centres[j, 0] if truth.edges[j, 0] == s else centres[j, 1] for j in (j0, j1)]
        bone_error[b] = abs(np.linalg.norm(ends[0] - ends[1]) - length) / length
    return {"joint_rmse": joint_rmse, "bone_error": bone_error, "centres": centres}


def fitted_errors(result, trial, truth) -> dict[str, np.ndarray]:
    """The same measures for a :func:`jaxskel.fit_skeleton` result (with its IK stage: the
    joints are ``result.motion.joint_positions``), indexed by the true joints and bones
    (NaN where the fitted tree lacks that joint or bone), and ``bone_bound``: the fit's
    own bound on each bone (:func:`jaxskel.joints.bone_uncertainty`), relative like the error."""
    seg_map = segment_map(result, trial, truth)
    true_joint = {frozenset(map(int, e)): j for j, e in enumerate(truth.edges)}
    joint_of = {
        j: true_joint.get(frozenset((seg_map[int(p)], seg_map[int(c)])), -1) for j, (p, c) in enumerate(result.edges)
    }
    joint_rmse = np.full(truth.n_joints, np.nan)
    positions = result.motion.joint_positions
    for j, tj in joint_of.items():
        if tj < 0:
            continue
        joint_rmse[tj] = off_axis_rmse(positions[:, j], truth, tj)
    bone_index = {frozenset(map(int, b)): k for k, b in enumerate(truth.bones)}
    bone_error = np.full(len(truth.bones), np.nan)
    bone_bound = np.full(len(truth.bones), np.nan)
    bounds = jaxskel.joints.bone_uncertainty(result.skeleton)
    for (j0, j1), length, bound in zip(result.skeleton.bones, result.skeleton.bone_lengths, bounds):
        k = bone_index.get(frozenset((joint_of[int(j0)], joint_of[int(j1)])))
        if k is not None:
            bone_error[k] = abs(length - truth.bone_lengths[k]) / truth.bone_lengths[k]
            bone_bound[k] = bound / truth.bone_lengths[k]
    return {"joint_rmse": joint_rmse, "bone_error": bone_error, "bone_bound": bone_bound}
