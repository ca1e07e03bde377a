"""The joint of a one-marker segment steers its host's Procrustes pose by how still it sits there."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from wobble import wobbling_trial

import jaxskel
from jaxskel.skeleton._attachment_weights import FLOOR, attachment_points, attachment_weights


def _layout(sizes, edges):
    members, start = [], 0
    for n in sizes:
        members.append(np.arange(start, start + n))
        start += n
    edges = np.asarray(edges)
    seg_joints = [np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s)) for s in range(len(sizes))]
    width = max(len(m) + len(j) for m, j in zip(members, seg_joints))
    return edges, members, seg_joints, width


def test_attachment_points_are_the_hosts_joints_with_one_marker_segments():
    # 0 (3 markers) - 1 (2 markers) - 2 (1 marker); 1 - 3 (1 marker)
    edges, members, seg_joints, width = _layout([3, 2, 1, 1], [(0, 1), (1, 2), (1, 3)])
    hung = attachment_points(edges, members, seg_joints, width)
    # segment 1: markers in slots 0-1, then its joints 0, 1, 2: the last two lead to one-marker segments,
    # and it keeps its two markers and joint 0, three points of its own
    assert hung[1].tolist() == [False, False, False, True, True]
    assert not hung[[0, 2, 3]].any()  # a one-marker segment's own joint is not an attachment point on it


def test_a_host_short_of_three_points_of_its_own_keeps_its_attachment_joints():
    edges, members, seg_joints, width = _layout([3, 1, 1], [(0, 1), (1, 2)])
    # segment 1 has one marker: its joint with segment 2 is one of only three points
    assert not attachment_points(edges, members, seg_joints, width)[1].any()


def test_weights_are_inverse_variance_relative_to_the_hosts_own_points():
    hung = np.array([[False, False, False, True, True]])
    own = np.array([[0.002, 0.002, 0.004, 0.0, 0.0]])  # the hung points were not aligned: 0
    scatter = np.array([[np.nan, np.nan, np.nan, 0.002, 0.02]])
    w = attachment_weights(hung, own, scatter)
    assert w[0, :3].tolist() == [1.0, 1.0, 1.0]
    assert w[0, 3] == 1.0  # as still as the host's own points: a marker's weight
    assert w[0, 4] == pytest.approx((0.002 / 0.02) ** 2)
    # a host whose own points barely scatter is compared with the floor, not with zero
    still = attachment_weights(hung, np.array([[1e-5, 1e-5, 1e-5, 0.0, 0.0]]), scatter)
    assert still[0, 4] == pytest.approx((FLOOR / 0.02) ** 2)


def test_a_wobbling_cluster_marker_split_off_its_thigh_does_not_move_the_knee_by_centimetres():
    """Synthetic full body, the thigh marker LTHF moved by 30 mm RMS of soft tissue for 20 s (seed 1, a
    case of ``bench/wobbling_marker.py``): the segmentation hangs it from the thigh as a one-marker
    segment, and the centre of that joint, fixed by one distance, turns about the line of the thigh's
    two remaining markers with it. Aligned like a marker it turned the thigh, the knee was not
    recognised as a hinge, and it stayed 54 mm off along its axis; weighted by how still it sits in
    the thigh, it rides along, and the knee is placed in its limb plane."""
    trial, truth = wobbling_trial(seed=1, duration=20.0, amplitude=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial)
    labels = list(result.trial.labels)
    seg = np.asarray(result.segmentation.marker_segment)
    lone, thigh, shank = (int(seg[labels.index(m)]) for m in ("LTHF", "LTHI", "LTIB"))
    assert np.sum(seg == lone) == 1 and result.n_segments == truth.n_segments + 1
    edges = np.asarray(result.edges).tolist()
    hung = next(j for j, e in enumerate(edges) if set(e) == {thigh, lone})
    knee = next(j for j, e in enumerate(edges) if set(e) == {thigh, shank})
    diag = result.skeleton.diagnostics
    assert diag["attachment_weight"][hung] < 0.01 and diag["attachment_scatter"][hung] > 0.02
    assert [w for j, w in enumerate(diag["attachment_weight"]) if j != hung] == [1.0] * (len(edges) - 1)
    assert diag["hinge_placement"][knee] == "limb plane"
    true_knee = next(j for j, e in enumerate(np.asarray(truth.edges).tolist())
                     if set(e) == {int(truth.marker_segment[labels.index(m)]) for m in ("LTHI", "LTIB")})
    off = result.motion.joint_positions[:, knee] - truth.joint_positions[:, true_knee]
    assert np.sqrt(np.nanmean(np.sum(off**2, axis=-1))) < 0.025  # 14.8 mm (54.3 mm before)
    # reported: the lone marker is named with its host and its joint's weight there
    assert "alone on its segment, hung from" in result.summary() and "weight" in result.summary()
