"""OpenSim model export: the XML alone (no OpenSim needed), then the model in OpenSim 4
(it loads, its default pose puts the markers where jaxskel's motion does, and OpenSim's
inverse kinematics fits the trial as well as jaxskel's own).

Two skeletons: the synthetic full body's ground truth (no solver; its knees and elbows
turn about their hinge axes exactly, so their pin joints reproduce the motion exactly),
and a skeleton fitted to a short trial of it (jaxskel finds hinge axes for the knees and
elbows; its inverse kinematics poses every joint as a ball). The fitted skeleton's cases
need a minute-long fit and run with ``pytest -m extended``; OpenSim's IK on a fitted real
skeleton is checked by default in tests/test_real_ik.py.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from anatomy.truth import SYNTH_PART
from helpers import opensim_ik_rms, true_joint_index, truth_motion, truth_skeleton
from scipy.spatial.transform import Rotation

import jaxskel
from jaxskel import InputError, synth
from jaxskel.anatomy import Anatomy
from jaxskel.result import export_osim, opensim_frame, opensim_names, to_opensim_frame

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


@pytest.fixture(scope="module")
def osim():
    """The ``opensim`` module; a test needing it is skipped, saying why, only where it cannot be imported."""
    reason = "OpenSim's Python package 'opensim' (the dev extra) cannot be imported"
    try:
        import opensim  # noqa: F401
    except ImportError as err:  # the message says why (not installed, a library missing, ...)
        reason += f": {type(err).__name__}: {err}"
    module = pytest.importorskip("opensim", reason=reason, exc_type=ImportError)
    module.Logger.setLevelString("Warn")  # no line per IK frame
    return module


# ----------------------------------------------------------------------------- skeletons
def _truth_skeleton_and_motion(body, duration=1.0, seed=0):
    """The synthetic ground truth as a Skeleton (its hinge joints given their axes) and Motion."""
    trial, truth = synth.simulate(body, "calibration", duration=duration, seed=seed)
    hinge = np.full((truth.n_joints, 3), np.nan)
    for j, kind in enumerate(truth.joint_types):
        if kind == "hinge":
            hinge[j] = truth.joint_axes[j][0]
    skeleton = dataclasses.replace(truth_skeleton(trial, truth), diagnostics={"hinge_axis": hinge.tolist()})
    return skeleton, truth_motion(trial, truth), truth


@pytest.fixture(scope="module")
def truth_body():
    return _truth_skeleton_and_motion(synth.full_body(seed=0))


@pytest.fixture(scope="module")
def fitted(osim):
    """A skeleton fitted to 4 s of the full body's calibration motion (200 frames); only the
    tests in OpenSim use it (``osim``: no fit where they are skipped)."""
    trial, truth = synth.simulate(
        synth.full_body(seed=0), motion="calibration", duration=4.0, rate=50.0, noise=0.0005, seed=0
    )
    return trial, truth, jaxskel.fit_skeleton(trial, len(truth.segment_names))


def _ball_only(skeleton):
    return dataclasses.replace(
        skeleton, diagnostics={**skeleton.diagnostics, "hinge_axis": np.full((skeleton.n_joints, 3), np.nan).tolist()}
    )


def _pins(skeleton):
    axes = np.asarray(skeleton.diagnostics["hinge_axis"], dtype=float)
    unmoved = set(skeleton.diagnostics.get("hinges_unmoved", []))
    return {j for j in range(skeleton.n_joints) if np.isfinite(axes[j]).all() and j not in unmoved}


def _exported_pins(path):
    """The tree joints (edge order) a model file makes PinJoints."""
    kinds = [el.tag for el in ET.parse(path).getroot().find("Model/JointSet/objects")][1:]
    return {j for j, kind in enumerate(kinds) if kind == "PinJoint"}


# ----------------------------------------------------------------------------- the XML alone
@pytest.mark.parametrize("up", UP_AXES)
def test_lab_to_opensim_is_a_proper_rotation_taking_up_to_y(up):
    c = opensim_frame(up)
    assert np.allclose(c @ c.T, np.eye(3)) and np.isclose(np.linalg.det(c), 1.0)
    e_up = np.eye(3)["xyz".index(up[-1])] * (-1.0 if up[0] == "-" else 1.0)
    np.testing.assert_allclose(c @ e_up, [0.0, 1.0, 0.0], atol=1e-15)
    points = np.random.default_rng(0).normal(size=(5, 4, 3))
    points[1, 2] = np.nan
    moved = to_opensim_frame(points, up)
    np.testing.assert_allclose(moved, points @ c.T)
    assert np.isnan(moved[1, 2]).all() and np.isfinite(np.delete(moved.reshape(-1, 3), 6, axis=0)).all()


def test_z_up_keeps_lab_x():
    np.testing.assert_array_equal(to_opensim_frame(np.array([1.0, 2.0, 3.0]), "z"), [1.0, 3.0, -2.0])


def test_names_are_made_valid_and_distinct():
    assert opensim_names(["LASI+RASI", "a b", "C7", "C7", "a_b", "/", ""], reserved=["ground"]) == (
        "LASI_RASI", "a_b", "C7", "C7_2", "a_b_2", "unnamed", "unnamed_2",
    )
    assert opensim_names(["ground"], reserved=["ground"]) == ("ground_2",)


def _floats(text):
    return np.array([float(v) for v in text.split()])


def test_the_xml_holds_one_body_per_segment_joints_and_markers(truth_body, tmp_path):
    skeleton, motion, truth = truth_body
    path = export_osim(skeleton, tmp_path / "body.osim", motion=motion, frame=3, model_name="synth body")
    root = ET.parse(path).getroot()
    assert root.tag == "OpenSimDocument" and root.get("Version") == "40000"
    model = root.find("Model")
    assert model.get("name") == "synth_body"
    assert _floats(model.findtext("gravity")).tolist() == [0.0, -9.80665, 0.0]
    text = model.findtext("credits") + model.findtext("publications")
    assert "up axis z" in text and "PLACEHOLDERS" in text and "1 0 0; 0 0 1; 0 -1 0" in text
    names = opensim_names(skeleton.names())
    bodies = model.find("BodySet/objects")
    assert [b.get("name") for b in bodies] == list(names)
    assert all(b.findtext("mass") == "1" for b in bodies)
    joints = model.find("JointSet/objects")
    kinds = [j.tag for j in joints]
    assert kinds[0] == "FreeJoint" and joints[0].get("name") == f"ground-{names[skeleton.root]}"
    expected = ["PinJoint" if t == "hinge" else "BallJoint" for t in truth.joint_types]
    assert kinds[1:] == expected and "PinJoint" in kinds
    c = opensim_frame("z")
    for j, (el, (p, ch)) in enumerate(zip(joints[1:], skeleton.edges)):
        assert el.get("name") == f"{names[p]}-{names[ch]}"
        coords = [x.get("name") for x in el.find("coordinates")]
        suffixes = ["angle"] if el.tag == "PinJoint" else ["rx", "ry", "rz"]
        assert coords == [f"{el.get('name')}_{s}" for s in suffixes]
        parent, child = el.find("frames")
        assert parent.findtext("socket_parent") == f"/bodyset/{names[p]}"
        np.testing.assert_allclose(_floats(parent.findtext("translation")), c @ skeleton.joint_offsets[j, 0], atol=1e-15)
        if el.tag == "PinJoint":  # the joint frames' Z is the hinge axis, in the OpenSim frame
            q = Rotation.from_euler("XYZ", _floats(parent.findtext("orientation"))).as_matrix()
            np.testing.assert_allclose(q[:, 2], c @ truth.joint_axes[j][0], atol=1e-12)
            assert child.findtext("orientation") == parent.findtext("orientation")
    free = [x.get("name") for x in joints[0].find("coordinates")]
    assert [n.rsplit("_", 1)[1] for n in free] == ["rx", "ry", "rz", "tx", "ty", "tz"]
    np.testing.assert_allclose(
        [float(x.findtext("default_value")) for x in joints[0].find("coordinates")][3:],
        c @ motion.root_position[3], atol=1e-12,
    )
    for x in model.iter("Coordinate"):
        assert x.findtext("clamped") == "false" and x.findtext("locked") == "false"
    markers = model.find("MarkerSet/objects")
    assert [m.get("name") for m in markers] == list(skeleton.marker_labels)
    for m, el in enumerate(markers):
        assert el.findtext("socket_parent_frame") == f"/bodyset/{names[skeleton.marker_segment[m]]}"
        np.testing.assert_allclose(_floats(el.findtext("location")), c @ skeleton.marker_offsets[m], atol=1e-15)


def test_unused_markers_are_left_out_and_the_rest_pose_is_all_zero(truth_body, tmp_path):
    skeleton, _, _ = truth_body
    seg = skeleton.marker_segment.copy()
    seg[0] = -1
    off = skeleton.marker_offsets.copy()
    off[0] = np.nan
    partial = dataclasses.replace(skeleton, marker_segment=seg, marker_offsets=off)
    model = ET.parse(export_osim(partial, tmp_path / "rest.osim")).getroot().find("Model")
    assert [m.get("name") for m in model.iter("Marker")] == list(skeleton.marker_labels[1:])
    assert all(float(x.findtext("default_value")) == 0.0 for x in model.iter("Coordinate"))
    assert "rest pose" in model.findtext("credits")


def test_bodies_are_named_by_the_skeleton_or_by_segment_names(truth_body, tmp_path):
    skeleton, _, truth = truth_body
    named = dataclasses.replace(skeleton, segment_names=truth.segment_names)
    model = ET.parse(export_osim(named, tmp_path / "named.osim")).getroot().find("Model")
    assert tuple(b.get("name") for b in model.iter("Body")) == truth.segment_names
    assert model.find("JointSet/objects")[0].get("name") == "ground-pelvis"
    given = [f"part {i}" for i in range(skeleton.n_segments)]
    model = ET.parse(export_osim(named, tmp_path / "given.osim", segment_names=given)).getroot().find("Model")
    assert [b.get("name") for b in model.iter("Body")] == [f"part_{i}" for i in range(skeleton.n_segments)]


def test_a_frame_from_the_end_is_recorded_as_its_index(truth_body, tmp_path):
    skeleton, motion, _ = truth_body
    last = ET.parse(export_osim(skeleton, tmp_path / "last.osim", motion=motion, frame=-1)).getroot()
    same = ET.parse(export_osim(skeleton, tmp_path / "same.osim", motion=motion, frame=motion.n_frames - 1)).getroot()
    assert f"frame {motion.n_frames - 1} of the fitted motion" in last.findtext("Model/credits")
    assert ET.tostring(last) == ET.tostring(same)


def test_a_joint_that_turned_about_more_than_one_axis_is_a_ball(truth_body, tmp_path):
    skeleton, _, truth = truth_body
    knee = truth.joint_names.index("l_knee")
    unmoved = dataclasses.replace(skeleton, diagnostics={**skeleton.diagnostics, "hinges_unmoved": [knee]})
    joints = ET.parse(export_osim(unmoved, tmp_path / "u.osim")).getroot().find("Model/JointSet/objects")
    assert joints[1 + knee].tag == "BallJoint"
    assert sum(el.tag == "PinJoint" for el in joints) == truth.joint_types.count("hinge") - 1


def test_bad_input_is_refused_clearly(truth_body, tmp_path):
    skeleton, motion, _ = truth_body
    with pytest.raises(InputError, match=r"up_axis must be the lab's up axis, one of x, y, z, -x, -y, -z; got 'up'"):
        export_osim(skeleton, tmp_path / "a.osim", up_axis="up")
    with pytest.raises(InputError, match=r"an OpenSim model must end in \.osim, not '\.xml'"):
        export_osim(skeleton, tmp_path / "a.xml")
    with pytest.raises(InputError, match="it is a folder"):
        export_osim(skeleton, tmp_path)
    path = export_osim(skeleton, tmp_path / "a.osim")
    with pytest.raises(InputError, match="exists"):
        export_osim(skeleton, path)
    export_osim(skeleton, path, overwrite=True)
    with pytest.raises(InputError, match="frame 120 is out of range for a motion of 120 frames"):
        export_osim(skeleton, path, motion=motion, frame=120, overwrite=True)
    with pytest.raises(InputError, match="segment_names must be 15 distinct names"):
        export_osim(skeleton, path, segment_names=["a"] * 15, overwrite=True)
    with pytest.raises(InputError, match="up_axis"):
        to_opensim_frame(np.zeros((2, 3)), "unknown")


# ----------------------------------------------------------------------------- in OpenSim
def _vec(v):
    return np.array([v.get(i) for i in range(3)])


def _markers_in_ground(osim, path, labels):
    model = osim.Model(str(path))
    state = model.initSystem()
    model.realizePosition(state)
    markers = model.getMarkerSet()
    return model, np.array([_vec(markers.get(name).getLocationInGround(state)) for name in labels])


def _anatomy(truth, humanoid=True):
    """The synthetic full body's true parts (tests/anatomy/truth.py); it is Z up, facing +X."""
    parts = tuple(SYNTH_PART.get(n, "") for n in truth.segment_names)
    return Anatomy(parts=parts, confidence=np.ones(len(parts)), humanoid=humanoid, up=(0, 0, 1), front=(1, 0, 0))


OPENSIM_BODIES = ("pelvis", "torso", "head", "humerus_l", "radius_l", "hand_l", "humerus_r", "radius_r", "hand_r",
                  "femur_l", "tibia_l", "calcn_l", "femur_r", "tibia_r", "calcn_r")


def test_a_humanoid_takes_opensim_body_and_joint_names(truth_body, tmp_path):
    """gait2392 / Rajagopal body names, joints named after the joint (hip_r, knee_r, ...), in
    the full body's segment order; a body that is not human keeps its segment names."""
    skeleton, _, truth = truth_body
    assert truth.segment_names[:4] == ("pelvis", "torso", "head", "l_upperarm")
    named = dataclasses.replace(skeleton, segment_names=truth.segment_names)
    model = ET.parse(export_osim(named, tmp_path / "h.osim", anatomy=_anatomy(truth))).getroot().find("Model")
    assert tuple(b.get("name") for b in model.iter("Body")) == OPENSIM_BODIES
    joints = [j.get("name") for j in model.find("JointSet/objects")]
    child = {j.get("name"): j.find("frames")[1].find("socket_parent").text for j in model.find("JointSet/objects")}
    assert joints[0] == "ground-pelvis"
    for joint, body in (("hip_r", "femur_r"), ("knee_l", "tibia_l"), ("ankle_r", "calcn_r"),
                        ("shoulder_l", "humerus_l"), ("elbow_r", "radius_r"), ("wrist_l", "hand_l"), ("neck", "head"),
                        ("thoracic", "torso")):
        assert child[joint] == f"/bodyset/{body}"
    parents = {m.find("socket_parent_frame").text for m in model.iter("Marker")}
    assert parents == {f"/bodyset/{b}" for b in OPENSIM_BODIES}
    plain = ET.parse(export_osim(named, tmp_path / "n.osim", anatomy=_anatomy(truth, humanoid=False))).getroot()
    assert tuple(b.get("name") for b in plain.find("Model").iter("Body")) == truth.segment_names
    with pytest.raises(InputError, match="anatomy names"):
        export_osim(named, tmp_path / "x.osim", anatomy=dataclasses.replace(
            _anatomy(truth), parts=("pelvis",), confidence=np.ones(1)))


def test_the_named_model_loads_and_poses_the_markers_as_the_unnamed_one(osim, truth_body, tmp_path):
    skeleton, motion, truth = truth_body
    path = export_osim(skeleton, tmp_path / "named.osim", motion=motion, frame=30, anatomy=_anatomy(truth))
    model, where = _markers_in_ground(osim, path, skeleton.marker_labels)
    assert [model.getBodySet().get(b).getName() for b in range(model.getNumBodies())] == list(OPENSIM_BODIES)
    assert model.getCoordinateSet().contains("knee_r_angle") and model.getCoordinateSet().contains("hip_l_rx")
    np.testing.assert_allclose(where, to_opensim_frame(motion.fitted_markers[30], "z"), atol=1e-6)


@pytest.mark.extended  # a full-body fit (about a minute on 2 cores); the true skeleton's cases run by default
def test_the_model_loads_in_opensim(osim, fitted, tmp_path):
    trial, truth, result = fitted
    skeleton = result.skeleton
    path = export_osim(skeleton, tmp_path / "fit.osim", motion=result.motion, frame=10)
    pins = _exported_pins(path)
    # jaxskel finds the knees' and elbows' hinge axes on this trial, and slides a universal
    # wrist's centre like a hinge's, but the motion turns the wrist far off that axis: a ball
    kind = [truth.joint_types[true_joint_index(result, trial, truth, j)] for j in range(skeleton.n_joints)]
    hinge_joints = {j for j, k in enumerate(kind) if k == "hinge"}
    assert hinge_joints <= pins <= _pins(skeleton), (hinge_joints, pins)
    assert not any(kind[j] == "universal" for j in pins)
    assert _pins(skeleton) - pins, "the case of a hinge axis the motion rules out is gone: test it another way"
    model = osim.Model(str(path))
    model.initSystem()
    assert model.getNumBodies() == skeleton.n_segments == len(truth.segment_names)
    assert model.getNumJoints() == skeleton.n_joints + 1
    kinds = [model.getJointSet().get(j).getConcreteClassName() for j in range(model.getNumJoints())]
    assert kinds[0] == "FreeJoint"
    assert [k for k in kinds[1:]] == ["PinJoint" if j in pins else "BallJoint" for j in range(skeleton.n_joints)]
    assert model.getNumCoordinates() == 6 + len(pins) + 3 * (skeleton.n_joints - len(pins))
    names = [model.getMarkerSet().get(m).getName() for m in range(model.getMarkerSet().getSize())]
    assert names == list(trial.labels)
    np.testing.assert_allclose(_vec(model.getGravity()), [0.0, -9.80665, 0.0])


@pytest.mark.parametrize("up", ["z", "-y", "x"])
def test_default_pose_puts_the_markers_where_the_motion_does(osim, truth_body, tmp_path, up):
    """Ground truth with exact hinges: every joint's default coordinates (FreeJoint,
    BallJoint and PinJoint conventions) and offsets reproduce the frame to 1e-6 m."""
    skeleton, motion, _ = truth_body
    frame = 57
    path = export_osim(skeleton, tmp_path / "truth.osim", motion=motion, frame=frame, up_axis=up)
    model, where = _markers_in_ground(osim, path, skeleton.marker_labels)
    kinds = {model.getJointSet().get(j).getConcreteClassName() for j in range(model.getNumJoints())}
    assert kinds == {"FreeJoint", "BallJoint", "PinJoint"}
    np.testing.assert_allclose(where, to_opensim_frame(motion.fitted_markers[frame], up), atol=1e-6)


@pytest.mark.extended  # a full-body fit (about a minute on 2 cores); the true skeleton's cases run by default
def test_default_pose_of_a_fitted_motion(osim, fitted, tmp_path):
    """jaxskel's inverse kinematics poses every joint as a ball: exported with ball joints
    only, the default pose is its frame to 1e-6 m. With pins, so are the markers of every
    body above the pins; below them the pins drop the small off-axis part of each turn."""
    trial, _, result = fitted
    skeleton, frame = result.skeleton, 120
    used = skeleton.marker_segment >= 0
    labels = [lab for lab, u in zip(trial.labels, used) if u]
    expected = to_opensim_frame(result.motion.fitted_markers[frame][used], "z")
    balls = export_osim(_ball_only(skeleton), tmp_path / "ball.osim", motion=result.motion, frame=frame)
    np.testing.assert_allclose(_markers_in_ground(osim, balls, labels)[1], expected, atol=1e-6)
    with_pins = export_osim(skeleton, tmp_path / "pin.osim", motion=result.motion, frame=frame)
    below, pins = set(), _exported_pins(with_pins)  # the segments below a pin joint
    for _ in range(skeleton.n_joints):
        below |= {int(c) for j, (p, c) in enumerate(skeleton.edges) if j in pins or p in below}
    assert below
    off = np.linalg.norm(_markers_in_ground(osim, with_pins, labels)[1] - expected, axis=-1)
    under = np.isin(skeleton.marker_segment[used], sorted(below))
    assert off[~under].max() < 1e-6 and off[under].max() < 0.03, (off[~under].max(), off[under].max())


def _opensim_ik_rms(osim, model_path, trial, tmp_path):
    """OpenSim's per-frame marker RMS for ``trial`` (its markers turned into the OpenSim frame)."""
    take = trial.replace(positions=to_opensim_frame(trial.positions, trial.up_axis))
    return opensim_ik_rms(osim, model_path, take, tmp_path)


def test_opensim_inverse_kinematics_agrees_with_jaxskel_on_the_true_skeleton(osim, tmp_path):
    """The acceptance test on the body's own skeleton (pins at its hinges): OpenSim's inverse
    kinematics of a noisy trial with the exported model leaves the marker error jaxskel's
    inverse kinematics leaves, within 2 mm on average and frame by frame."""
    body = synth.full_body(seed=0)
    trial, _ = synth.simulate(body, "calibration", duration=2.0, rate=50.0, noise=0.001, seed=4)
    skeleton, _, _ = _truth_skeleton_and_motion(body, duration=2.0, seed=4)
    motion = jaxskel.skeleton.inverse_kinematics(skeleton, trial)
    model_path = export_osim(skeleton, tmp_path / "truth.osim", motion=motion, frame=0)
    assert _exported_pins(model_path)  # the hinges are pins
    rms = _opensim_ik_rms(osim, model_path, trial, tmp_path)
    ours = np.asarray(motion.marker_rms)
    print(f"\nOpenSim IK mean marker RMS {1e3 * rms.mean():.2f} mm, jaxskel IK {1e3 * ours.mean():.2f} mm")
    assert abs(rms.mean() - ours.mean()) < 0.002 and np.percentile(np.abs(rms - ours), 95) < 0.002


@pytest.mark.extended  # a full-body fit (about a minute on 2 cores); the true skeleton's cases run by default
def test_opensim_inverse_kinematics_agrees_with_jaxskel(osim, fitted, tmp_path):
    """The acceptance test: OpenSim's inverse kinematics of the trial (its markers turned
    into the OpenSim frame) with the exported model leaves a mean RMS marker error within
    2 mm of jaxskel's own inverse kinematics residual."""
    trial, _, result = fitted
    model_path = export_osim(result.skeleton, tmp_path / "fit.osim", motion=result.motion, frame=0)
    rms = _opensim_ik_rms(osim, model_path, trial, tmp_path)
    ours = float(np.mean(result.motion.marker_rms))
    print(f"\nOpenSim IK mean marker RMS {1e3 * float(np.mean(rms)):.2f} mm, jaxskel IK {1e3 * ours:.2f} mm")
    assert abs(float(np.mean(rms)) - ours) < 0.002, (float(np.mean(rms)), ours)
