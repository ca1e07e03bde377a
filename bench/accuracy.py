"""Accuracy of a fitted skeleton against the synthetic ground truth (``jaxskel.synth``).

The same measures for jaxskel and the reference, so a speed figure never comes from
cutting corners:

* ``segmentation_ari``: adjusted Rand index of the marker grouping (1 = exact);
* ``topology_correct``: the fitted tree, with each segment named by the true segment
  most of its markers belong to, has exactly the true joints;
* ``joint_error_mm``: per joint, the RMS over frames of the distance from the fitted
  joint centre to the true one; for hinges the distance to the true hinge *axis*
  (a hinge's centre along its axis is not determined by marker data). Median and
  max over joints;
* ``bone_error_pct``: relative error of every bone length (distance between two
  joints of one segment), median and max over bones; hinge joints are projected
  onto nothing, so bones ending at a hinge carry its axial uncertainty;
* ``ik_marker_rms_mm``: median per-frame marker residual of inverse kinematics;
  ``ik_joint_error_mm``: IK joint centres against the truth, median over joints
  (hinges: distance to the axis).
"""

from __future__ import annotations

import numpy as np

__all__ = ["segment_map", "evaluate", "same_topology"]


def segment_map(labels, marker_segment, truth) -> np.ndarray:
    """True segment of every fitted segment: the majority true segment of its markers (-1 if none)."""
    true_of = dict(zip(truth.physical_labels, truth.body.marker_segment))
    est = np.asarray(marker_segment)
    n = int(est.max()) + 1 if est.size else 0
    out = np.full(n, -1)
    for s in range(n):
        votes = [true_of[lab] for lab, e in zip(labels, est) if e == s and lab in true_of]
        if votes:
            out[s] = int(np.bincount(votes).argmax())
    return out


def _edge_set(edges, mapping=None) -> set[tuple[int, int]]:
    out = set()
    for a, b in np.asarray(edges).reshape(-1, 2):
        a, b = (int(a), int(b)) if mapping is None else (int(mapping[a]), int(mapping[b]))
        out.add((min(a, b), max(a, b)))
    return out


def same_topology(edges_a, map_a, edges_b, map_b) -> bool:
    """Whether two fitted trees join the same (true-named) segments."""
    return _edge_set(edges_a, map_a) == _edge_set(edges_b, map_b)


def _joint_index(edges, mapping, truth) -> np.ndarray:
    """True joint index of every fitted joint (-1 where the fitted edge is not a true joint)."""
    lookup = {(min(a, b), max(a, b)): j for j, (a, b) in enumerate(np.asarray(truth.edges))}
    return np.array(
        [lookup.get((min(mapping[a], mapping[b]), max(mapping[a], mapping[b])), -1) for a, b in np.asarray(edges)],
        int,
    ).reshape(-1)


def _joint_errors(positions, frames, true_index, truth) -> np.ndarray:
    """RMS error (m) per fitted joint that is a true joint; hinges against their axis line."""
    out = []
    for j, tj in enumerate(true_index):
        if tj < 0:
            continue
        est = positions[:, j]
        ref = np.asarray(truth.joint_positions)[frames, tj]
        diff = est - ref
        if truth.joint_types[tj] == "hinge":
            axis = np.asarray(truth.joint_axes_world[tj])[frames, 0]
            diff = diff - np.sum(diff * axis, -1, keepdims=True) * axis
        dist = np.linalg.norm(diff, axis=-1)
        dist = dist[np.isfinite(dist)]
        if dist.size:
            out.append(float(np.sqrt(np.mean(dist**2))))
    return np.asarray(out)


def _summary(values: np.ndarray, scale: float) -> dict[str, float | None]:
    if values.size == 0:
        return {"median": None, "max": None}
    return {"median": round(float(np.median(values)) * scale, 3), "max": round(float(np.max(values)) * scale, 3)}


def evaluate(
    truth,
    labels,
    marker_segment,
    edges=None,
    joint_positions=None,
    joint_frames=None,
    bones=None,
    bone_lengths=None,
    ik_joints=None,
    ik_frames=None,
    ik_marker_rms=None,
) -> dict:
    """Accuracy measures (module docstring) of whatever stages were run."""
    from sklearn.metrics import adjusted_rand_score

    true_of = dict(zip(truth.physical_labels, truth.body.marker_segment))
    known = [i for i, lab in enumerate(labels) if lab in true_of]
    est = np.asarray(marker_segment)
    out: dict = {
        "segmentation_ari": round(float(adjusted_rand_score([true_of[labels[i]] for i in known], est[known])), 4),
        "segments": int(est.max()) + 1,
        "segments_true": len(truth.segment_names),
    }
    if edges is None:
        return out
    mapping = segment_map(labels, est, truth)
    out["topology_correct"] = bool(
        len(set(mapping.tolist())) == len(mapping) and _edge_set(edges, mapping) == _edge_set(truth.edges)
    )
    true_index = _joint_index(edges, mapping, truth)
    out["joints_matched"] = int((true_index >= 0).sum())
    if joint_positions is not None:
        frames = np.arange(len(joint_positions)) if joint_frames is None else np.asarray(joint_frames)
        out["joint_error_mm"] = _summary(_joint_errors(joint_positions, frames, true_index, truth), 1e3)
    if bones is not None and len(bones):
        true_bones = {
            tuple(sorted((int(a), int(b)))): float(length)
            for (a, b), length in zip(np.asarray(truth.bones), truth.bone_lengths)
        }
        rel = []
        for (a, b), length in zip(np.asarray(bones), bone_lengths):
            key = tuple(sorted((int(true_index[a]), int(true_index[b]))))
            if key in true_bones:
                rel.append(abs(float(length) - true_bones[key]) / true_bones[key])
        out["bone_error_pct"] = _summary(np.asarray(rel), 100.0)
    if ik_joints is not None:
        frames = np.arange(len(ik_joints)) if ik_frames is None else np.asarray(ik_frames)
        out["ik_joint_error_mm"] = _summary(_joint_errors(ik_joints, frames, true_index, truth), 1e3)
    if ik_marker_rms is not None:
        rms = np.asarray(ik_marker_rms, float)
        out["ik_marker_rms_mm"] = round(float(np.nanmedian(rms)) * 1e3, 3)
    return out
