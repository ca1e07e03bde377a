"""Anatomical joint angles against synthetic truth: every joint kind's signs, hinge flexion
exact on the true skeleton, invariance to the lab frame, the OpenSim storage file.

The fitted case (knee and elbow flexion within 2 degrees RMS after the whole fit) is in
``test_named_fit.py``, on its fit."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxskel import InputError, synth
from jaxskel.anatomy import AngleOptions, Anatomy, JointAngles, anatomical_frames, joint_angles
from jaxskel.result import read_sto, write_angles_sto
from jaxskel.skeleton import Motion

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers import truth_motion, truth_skeleton  # noqa: E402
from truth import SYNTH_PART  # noqa: E402

DEG = np.pi / 180


@pytest.fixture(scope="module")
def body():
    return synth.full_body(seed=1)


@pytest.fixture(scope="module")
def calibration(body):
    trial, truth = synth.simulate(body, motion="calibration", duration=4.0, seed=1)
    return truth_skeleton(trial, truth), truth_motion(trial, truth), truth


def named(body) -> Anatomy:
    """The synthetic body's true parts; it stands facing +X, Z up, in its segment frames."""
    parts = [SYNTH_PART[n] for n in body.segment_names]
    return Anatomy(parts, np.ones(len(parts)), True, up=[0.0, 0.0, 1.0], front=[1.0, 0.0, 0.0])


def posed(body, skeleton, joint: str, axis: int, theta: np.ndarray) -> Motion:
    """The body standing still but for one angle of one joint, ``theta`` (F,) radians."""
    n = len(theta)
    angles = [np.zeros((n, a.shape[0])) for a in body.joint_axes]
    angles[body.joint_names.index(joint)][:, axis] = theta
    rot, trans = synth.forward_kinematics(body, tuple(angles), np.broadcast_to(np.eye(3), (n, 3, 3)),
                                          np.zeros((n, 3)))
    quats = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(n, -1, 4)
    m = len(skeleton.marker_labels)
    return Motion(root_position=trans[:, 0], rotations=quats, segment_translations=trans,
                  joint_positions=np.zeros((n, len(body.joint_names), 3)), fitted_markers=np.zeros((n, m, 3)),
                  marker_rms=np.zeros(n), segment_observed=np.ones(rot.shape[:2], bool), steps=np.zeros(n, int),
                  result=np.zeros(n, int), converged=True, marker_labels=skeleton.marker_labels, rate=100.0)


# The synthetic body's angle (joint, axis index, its sign of motion: ``synth._bodies``) and the
# clinical angle it is, with the sign that angle must read: a positive synthetic hip angle 0 is
# abduction, so hip adduction reads -theta.
SIGNS = [
    ("hip", 1, "hip_{s}_flexion", 1), ("hip", 0, "hip_{s}_adduction", -1),
    ("hip", 2, "hip_{s}_internal_rotation", -1),
    ("knee", 0, "knee_{s}_flexion", 1),
    ("ankle", 0, "ankle_{s}_dorsiflexion", -1), ("ankle", 1, "ankle_{s}_inversion", -1),
    ("shoulder", 1, "shoulder_{s}_flexion", 1), ("shoulder", 0, "shoulder_{s}_abduction", 1),
    ("shoulder", 2, "shoulder_{s}_internal_rotation", -1),
    ("elbow", 0, "elbow_{s}_flexion", 1),
    ("wrist", 0, "wrist_{s}_flexion", 1), ("wrist", 1, "wrist_{s}_ulnar_deviation", -1),
]


@pytest.mark.parametrize("side", ["l", "r"])
@pytest.mark.parametrize("joint, axis, angle, sign", SIGNS)
def test_each_angle_reads_its_own_motion_with_the_clinical_sign_on_both_sides(body, calibration, side, joint,
                                                                              axis, angle, sign):
    """From the standing pose, the angle moves by exactly +-theta and no other angle moves.
    A hand's and a foot's frame come from their markers (a constant offset from the
    synthetic frame), so at the wrist and ankle the sign and the size are checked, to 10 %."""
    skeleton = calibration[0]
    theta = np.linspace(0.0, 0.6, 7)
    angles = joint_angles(skeleton, posed(body, skeleton, f"{side}_{joint}", axis, theta), named(body))
    moved = angles.values - angles.values[0]
    column = angles.names.index(angle.format(s=side))
    if joint in ("wrist", "ankle"):
        np.testing.assert_allclose(moved[:, column], sign * theta, rtol=0.1, atol=1e-9)
        return
    np.testing.assert_allclose(moved[:, column], sign * theta, atol=1e-9)
    np.testing.assert_allclose(np.delete(moved, column, axis=1), 0.0, atol=1e-9)


def test_the_standing_pose_is_zero_but_at_the_ends_of_the_limbs(body, calibration):
    """Thigh, shank, arm and forearm frames are the synthetic ones: every angle between them
    is 0 standing; a hand's and a foot's frames sit on their markers, within 25 degrees."""
    skeleton = calibration[0]
    angles = joint_angles(skeleton, posed(body, skeleton, "l_knee", 0, np.zeros(2)), named(body))
    for name, value in zip(angles.names, angles.values[0]):
        limit = 25 * DEG if name.startswith(("wrist", "ankle", "neck")) else 1e-9
        assert abs(value) <= limit, name


@pytest.mark.parametrize("axis, angle, sign", [(0, "lateral_bending", 1), (1, "flexion", -1),
                                               (2, "axial_rotation", -1)])
def test_trunk_and_neck_angles_are_signed_towards_flexion_and_the_right(body, calibration, axis, angle, sign):
    skeleton = calibration[0]
    theta = np.linspace(0.0, 0.4, 5)
    for joint, ours in (("spine", "thoracic"), ("neck", "neck")):
        angles = joint_angles(skeleton, posed(body, skeleton, joint, axis, theta), named(body))
        moved = angles[f"{ours}_{angle}"] - angles[f"{ours}_{angle}"][0]
        np.testing.assert_allclose(moved, sign * theta, atol=1e-9 if joint == "spine" else 0.02)


def test_hinge_flexion_equals_the_true_angle_in_every_frame(body, calibration):
    skeleton, motion, truth = calibration
    angles = joint_angles(skeleton, motion, named(body))
    for side in "lr":
        for joint in ("knee", "elbow"):
            true = truth.joint_angles[truth.joint_names.index(f"{side}_{joint}")][:, 0]
            assert np.ptp(true) > 60 * DEG  # the calibration motion exercises it
            np.testing.assert_allclose(angles[f"{joint}_{side}_flexion"], true, atol=1e-8)
            assert angles.lateral[f"{joint}_{side}"] == "functional"
            assert angles.of(f"{joint}_{side}").shape == (motion.rotations.shape[0], 1)  # a hinge: one angle


def test_a_hinge_turned_about_a_tilted_axis_is_still_all_flexion(calibration):
    """The knee's functional axis, not the body's right, is its flexion axis: a knee axis 15
    degrees off the lateral (a varus-valgus tilt) gives the true flexion, no crosstalk."""
    body = synth.full_body(seed=1)
    j = body.joint_names.index("l_knee")
    tilted = list(body.joint_axes)
    tilted[j] = np.array(tilted[j]) @ Rotation.from_rotvec([15 * DEG, 0, 0]).as_matrix().T
    body = dataclasses.replace(body, joint_axes=tuple(tilted))
    trial, truth = synth.simulate(body, motion="calibration", duration=4.0, seed=3)
    skeleton, motion = truth_skeleton(trial, truth), truth_motion(trial, truth)
    three = joint_angles(skeleton, motion, named(body), options=AngleOptions(hinges=()))
    true = truth.joint_angles[j][:, 0]
    np.testing.assert_allclose(three["knee_l_flexion"], true, atol=1e-6)
    np.testing.assert_allclose(three["knee_l_adduction"], 0.0, atol=1e-6)
    body_axis = joint_angles(skeleton, motion, named(body), options=AngleOptions(hinges=(), axis_range_deg=89.0))
    assert body_axis.lateral["knee_l"] == "body"
    assert np.abs(body_axis["knee_l_adduction"]).max() > 5 * DEG  # the body's right would see crosstalk


def test_angles_do_not_depend_on_the_lab_frame(body, calibration):
    skeleton, motion, _ = calibration
    turn = Rotation.from_rotvec([0.3, -1.1, 2.0])
    q = Rotation.from_quat(motion.rotations.reshape(-1, 4), scalar_first=True)
    moved = (turn * q).as_quat(scalar_first=True).reshape(motion.rotations.shape)

    a = joint_angles(skeleton, motion, named(body))
    b = joint_angles(skeleton, dataclasses.replace(motion, rotations=moved), named(body))
    np.testing.assert_allclose(a.values, b.values, atol=1e-9)


def test_frames_are_right_handed_with_the_long_axis_along_the_bone(body, calibration):
    skeleton, motion, _ = calibration
    frames, _ = anatomical_frames(skeleton, motion, named(body))
    for s, part in enumerate(named(body).parts):
        np.testing.assert_allclose(frames[s].T @ frames[s], np.eye(3), atol=1e-9)
        assert np.linalg.det(frames[s]) == pytest.approx(1.0)
        if part.startswith(("thigh", "shank", "upper_arm", "forearm")):
            np.testing.assert_allclose(frames[s][:, 1], [0, 0, 1], atol=0.08)  # the bone, pointing up
            assert frames[s][2, 2] == pytest.approx(0.0, abs=0.08)  # lateral axis horizontal
            assert frames[s][1, 2] < -0.99  # ... and to the right (-Y of the synthetic body)


def test_a_body_that_is_not_human_has_no_joint_angles(body, calibration):
    skeleton, motion, _ = calibration
    plain = Anatomy([""] * skeleton.n_segments, np.zeros(skeleton.n_segments), False, [0, 0, 1.0], [1.0, 0, 0])
    with pytest.raises(InputError, match="human"):
        joint_angles(skeleton, motion, plain)
    with pytest.raises(InputError, match="segments"):
        joint_angles(skeleton, motion, Anatomy(["pelvis"], [1.0], True, [0, 0, 1.0], [1.0, 0, 0]))
    with pytest.raises(InputError, match="hinges"):
        AngleOptions(hinges=("knees",))
    with pytest.raises(InputError, match="axis_range_deg"):
        AngleOptions(axis_range_deg=0)


def test_the_storage_file_is_what_opensim_reads(body, calibration, tmp_path):
    import opensim

    skeleton, motion, _ = calibration
    angles = joint_angles(skeleton, motion, named(body))
    path = write_angles_sto(angles, tmp_path / "angles.sto")
    table = read_sto(path)
    assert table.labels == angles.names and table.in_degrees
    np.testing.assert_allclose(table.values, angles.degrees, atol=1e-7)
    np.testing.assert_allclose(table.time, angles.time, atol=1e-8)

    storage = opensim.Storage(str(path))
    labels = storage.getColumnLabels()
    assert [labels.get(i) for i in range(labels.getSize())] == ["time", *angles.names]
    assert storage.getSize() == angles.n_frames and storage.isInDegrees()
    sto = opensim.TimeSeriesTable(str(path))
    knee = sto.getDependentColumn("knee_l_flexion").to_numpy()
    np.testing.assert_allclose(knee, angles.degrees[:, angles.names.index("knee_l_flexion")], atol=1e-7)

    with pytest.raises(InputError, match="exists"):
        write_angles_sto(angles, path)
    with pytest.raises(InputError, match=r"\.sto"):
        write_angles_sto(angles, tmp_path / "angles.csv")
    (tmp_path / "bad.sto").write_text("not a table\n")
    with pytest.raises(InputError, match="endheader"):
        read_sto(tmp_path / "bad.sto")


def test_joint_angles_record_reads_by_name(body, calibration):
    skeleton, motion, _ = calibration
    angles = joint_angles(skeleton, motion, named(body))
    assert isinstance(angles, JointAngles)
    assert angles.of("hip_l").shape[1] == 3
    np.testing.assert_allclose(angles.degrees, np.rad2deg(angles.values))
    with pytest.raises(InputError, match="no angle"):
        angles["knee_flexion"]
    with pytest.raises(InputError, match="no joint"):
        angles.of("knee")


def test_a_partial_body_has_the_angles_of_the_joints_it_names(body, calibration):
    """Legs without their pelvis (left unnamed): no hip angles, the knees all the same."""
    skeleton, motion, truth = calibration
    parts = [p if p.startswith(("thigh", "shank", "foot")) else "" for p in named(body).parts]
    legs = Anatomy(parts, np.ones(len(parts)), True, up=[0.0, 0.0, 1.0], front=[1.0, 0.0, 0.0])
    angles = joint_angles(skeleton, motion, legs)
    assert set(angles.joints) == {"knee_l", "knee_r", "ankle_l", "ankle_r"}
    true = truth.joint_angles[truth.joint_names.index("r_knee")][:, 0]
    np.testing.assert_allclose(angles["knee_r_flexion"], true, atol=1e-8)
