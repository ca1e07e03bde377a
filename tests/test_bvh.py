"""BVH export and reader, checked against the independent `bvh` package and by forward kinematics.

The skeleton and motion are built directly from synthetic ground truth (no solver), so
these tests isolate the file format. The synthetic full body is Z up and faces +X (its
left is +Y); its anatomy here is the truth (tests/anatomy/truth.py). Blender's own
importer is tested on a fitted body in tests/result/test_named_export.py.
"""

from __future__ import annotations

import dataclasses

import bvh
import numpy as np
import pytest
from anatomy.truth import SYNTH_PART
from helpers import random_rotation, truth_motion, truth_skeleton
from scipy.spatial.transform import Rotation

from jaxskel import InputError, synth
from jaxskel.anatomy import Anatomy
from jaxskel.io import rotation_between_axes
from jaxskel.result import export_bvh, read_bvh
from jaxskel.result._bvh import bvh_frame
from jaxskel.result._export_names import MAX_NAME, ascii_names, part_names
from jaxskel.segment import names_from_markers

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
#: full_body's lab frame to the BVH's: left (+Y) -> +X, up (+Z) -> +Y, front (+X) -> +Z.
FACING = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def _truth_skeleton_and_motion(body, duration=1.0, seed=0):
    trial, truth = synth.simulate(body, "calibration", duration=duration, seed=seed)
    return truth_skeleton(trial, truth), truth_motion(trial, truth), truth


@pytest.fixture(scope="module")
def full_body():
    return _truth_skeleton_and_motion(synth.full_body(seed=0))


def _anatomy(truth, **changes):
    parts = tuple(SYNTH_PART.get(n, "") for n in truth.segment_names)
    fields = {"parts": parts, "confidence": np.ones(len(parts)), "humanoid": True, "up": (0, 0, 1),
              "front": (1, 0, 0), **changes}
    return Anatomy(**fields)


def _proximal(skeleton):
    prox = np.full(skeleton.n_segments, -1)
    prox[skeleton.edges[:, 1]] = np.arange(skeleton.n_joints)
    return prox


def _check_round_trip(skeleton, motion, names, data, scale, frame):
    """Every BVH joint, in every frame, at ``frame`` times the motion's joint (the root: its origin)."""
    world = data.world_positions() / scale
    assert data.n_frames == motion.n_frames
    prox = _proximal(skeleton)
    for s, name in enumerate(names):
        node = data.names.index(name)
        if s == skeleton.root:
            np.testing.assert_allclose(world[:, node], motion.root_position @ frame.T, atol=1e-6)
        else:
            np.testing.assert_allclose(world[:, node], motion.joint_positions[:, prox[s]] @ frame.T, atol=1e-6)


def _rest(data):
    """(K, 3) every joint's position in the BVH's rest pose (every channel zero)."""
    return dataclasses.replace(data, frames=np.zeros((1, data.frames.shape[1]))).world_positions()[0]


def test_round_trip_positions_and_independent_parser(tmp_path, full_body):
    skeleton, motion, truth = full_body
    names = truth.segment_names
    path = export_bvh(skeleton, motion, tmp_path / "body.bvh", labels=names)  # Z up -> Y up, centimetres
    data = read_bvh(path)
    _check_round_trip(skeleton, motion, names, data, 100.0, rotation_between_axes("z", "y"))
    # Hierarchy: parents follow the tree, leaves (and only leaves) end in an End Site.
    for s, name in enumerate(names):
        node = data.names.index(name)
        parent = data.parents[node]
        expected = skeleton.parent[s]
        assert (parent == -1) if expected < 0 else (data.names[parent] == names[expected])
        assert np.isfinite(data.end_sites[node]).all() == (s not in skeleton.edges[:, 0])

    with open(path) as handle:
        other = bvh.Bvh(handle.read())
    assert other.get_joints_names() == list(data.names)
    assert other.nframes == motion.n_frames
    assert other.frame_time == pytest.approx(1.0 / 120.0)
    root = names[skeleton.root]
    assert other.joint_channels(root) == [
        "Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation",
    ]
    for name in names:
        if name != root:
            assert other.joint_channels(name) == ["Zrotation", "Xrotation", "Yrotation"]
        np.testing.assert_allclose(other.joint_offset(name), data.offsets[data.names.index(name)], atol=1e-9)
    assert sum(other.get_joint_channels_index(n) >= 0 for n in other.get_joints_names()) == len(names)
    # Both parsers read the same channel values.
    start = np.cumsum([0] + [len(c) for c in data.channels])
    for node, name in enumerate(data.names):
        chans = list(data.channels[node])
        np.testing.assert_allclose(
            other.frame_joint_channels(5, name, chans), data.frames[5, start[node] : start[node + 1]]
        )


def test_without_an_anatomy_the_rest_is_the_default_pose_turned_y_up(tmp_path, full_body):
    """OFFSET = C times the joint in the parent frame (segment origins sit at their proximal
    joints), whatever frames the motion holds: the rest is the skeleton's, not a frame's."""
    skeleton, motion, truth = full_body
    names = truth.segment_names
    c = bvh_frame(None, "z")
    np.testing.assert_array_equal(c, [[1, 0, 0], [0, 0, 1], [0, -1, 0]])  # (x, y, z) -> (x, z, -y)
    data = read_bvh(export_bvh(skeleton, motion, tmp_path / "rest.bvh", labels=names, units="m"))
    for j, (p, ch) in enumerate(skeleton.edges):
        node = data.names.index(names[ch])
        np.testing.assert_allclose(data.offsets[node], c @ skeleton.joint_offsets[j, 0], atol=1e-9)
    np.testing.assert_array_equal(data.offsets[data.names.index(names[skeleton.root])], 0.0)
    later = dataclasses.replace(motion, **{f: getattr(motion, f)[10:] for f in (
        "root_position", "rotations", "segment_translations", "joint_positions", "fitted_markers", "marker_rms",
        "segment_observed", "steps", "result")})
    other = read_bvh(export_bvh(skeleton, later, tmp_path / "later.bvh", labels=names, units="m"))
    np.testing.assert_array_equal(other.offsets, data.offsets)
    np.testing.assert_allclose(other.frames, data.frames[10:], atol=1e-7)
    # a Y-up recording is written as it is, an unknown up axis too
    for up, expected in (("y", np.eye(3)), ("unknown", np.eye(3))):
        np.testing.assert_array_equal(bvh_frame(None, up), expected)


@pytest.mark.parametrize("up", UP_AXES)
def test_every_up_axis_is_turned_to_y_by_a_proper_rotation(up):
    c = bvh_frame(None, up)
    e = np.eye(3)["xyz".index(up[-1])] * (-1.0 if up[0] == "-" else 1.0)
    np.testing.assert_allclose(c @ e, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(c @ c.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c) == pytest.approx(1.0)


def test_an_anatomy_turns_up_to_y_front_to_z_and_left_to_x(full_body):
    _, _, truth = full_body
    np.testing.assert_allclose(bvh_frame(_anatomy(truth)), FACING, atol=1e-12)
    # a front that is not quite horizontal is made orthogonal to up; the frame stays proper
    tilted = bvh_frame(_anatomy(truth, up=(0.1, 0.0, 2.0), front=(1.0, 0.3, 0.2)))
    up = np.array([0.1, 0.0, 2.0]) / np.linalg.norm([0.1, 0.0, 2.0])
    np.testing.assert_allclose(tilted @ up, [0, 1, 0], atol=1e-12)
    assert (tilted @ [1.0, 0.3, 0.2])[0] == pytest.approx(0.0, abs=1e-12)
    assert np.linalg.det(tilted) == pytest.approx(1.0)
    with pytest.raises(InputError, match="parallel"):
        bvh_frame(_anatomy(truth, front=(0, 0, 3)))


def test_a_humanoid_is_written_as_a_named_t_pose_with_its_fitted_bones(tmp_path, full_body):
    """The T-pose rest: spine and head up, arms level sideways (left +X), legs straight down,
    feet forward (+Z), every bone as long as fitted; the frames still put every joint at
    C times the motion's."""
    skeleton, motion, truth = full_body
    anatomy = _anatomy(truth)
    data = read_bvh(export_bvh(skeleton, motion, tmp_path / "t.bvh", anatomy=anatomy))  # Mixamo names, cm
    mixamo = ["Hips", "Spine", "Head", "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm",
              "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot"]
    assert truth.segment_names[3] == "l_upperarm" and list(data.names) == mixamo  # full_body's order
    _check_round_trip(skeleton, motion, mixamo, data, 100.0, FACING)
    at = dict(zip(data.names, _rest(data)))
    assert at["Head"][1] > at["Spine"][1] > at["Hips"][1]
    np.testing.assert_allclose(at["Head"][[0, 2]], at["Spine"][[0, 2]], atol=1e-9)  # straight up
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        arm = np.array([at[f"{side}{b}"] for b in ("Arm", "ForeArm", "Hand")])
        np.testing.assert_allclose(arm[:, 1:], np.broadcast_to(arm[0, 1:], (3, 2)), atol=1e-9)
        assert sign * arm[0, 0] > 0 and (sign * np.diff(arm[:, 0]) > 20.0).all()
        leg = np.array([at[f"{side}{b}"] for b in ("UpLeg", "Leg", "Foot")])
        np.testing.assert_allclose(leg[:, [0, 2]], np.broadcast_to(leg[0, [0, 2]], (3, 2)), atol=1e-9)
        assert (np.diff(leg[:, 1]) < -30.0).all()
        foot = data.end_sites[data.names.index(f"{side}Foot")]
        assert foot[2] > 5.0 and foot[0] == pytest.approx(0.0, abs=1e-9)  # forward, not sideways
    # every bone keeps its fitted length: |OFFSET| = |joint - the parent's node origin|
    origin = np.zeros((skeleton.n_segments, 3))
    origin[skeleton.edges[:, 1]] = skeleton.joint_offsets[:, 1]
    for j, (p, ch) in enumerate(skeleton.edges.tolist()):
        length = np.linalg.norm(skeleton.joint_offsets[j, 0] - origin[p])
        assert np.linalg.norm(data.offsets[data.names.index(mixamo[ch])]) == pytest.approx(100.0 * length, abs=1e-6)


def _turned(skeleton, motion, q):
    """The same skeleton and motion in a lab frame turned by ``q`` (the rest frame's
    world-aligned segment frames turn with it: ``R_s -> q R_s q^T``)."""
    sk = dataclasses.replace(skeleton, joint_offsets=skeleton.joint_offsets @ q.T,
                             marker_offsets=skeleton.marker_offsets @ q.T)
    rot = Rotation.from_quat(motion.rotations.reshape(-1, 4), scalar_first=True).as_matrix()
    quats = Rotation.from_matrix(q @ rot @ q.T).as_quat(scalar_first=True).reshape(motion.rotations.shape)
    return sk, dataclasses.replace(
        motion, rotations=quats, root_position=motion.root_position @ q.T,
        segment_translations=motion.segment_translations @ q.T, joint_positions=motion.joint_positions @ q.T,
        fitted_markers=motion.fitted_markers @ q.T)


def test_the_t_posed_file_does_not_depend_on_the_lab_frame(tmp_path, full_body):
    """Turning the whole recording (and the anatomy's up and front with it) writes the same
    BVH: its axes are the body's."""
    skeleton, motion, truth = full_body
    anatomy = _anatomy(truth)
    q = random_rotation(3)
    sk, mo = _turned(skeleton, motion, q)
    np.testing.assert_allclose(mo.joint_positions[7], motion.joint_positions[7] @ q.T)
    turned = dataclasses.replace(anatomy, up=q @ anatomy.up, front=q @ anatomy.front)
    one = read_bvh(export_bvh(skeleton, motion, tmp_path / "a.bvh", anatomy=anatomy))
    two = read_bvh(export_bvh(sk, mo, tmp_path / "b.bvh", anatomy=turned))
    np.testing.assert_allclose(two.offsets, one.offsets, atol=1e-7)
    np.testing.assert_allclose(two.world_positions(), one.world_positions(), atol=1e-6)


def test_a_partial_body_t_poses_what_is_named(tmp_path, full_body):
    """Unnamed upper arms turn with the thorax; the named forearms and hands are still level,
    the legs straight down, and every frame still at the motion's joints."""
    skeleton, motion, truth = full_body
    parts = tuple("" if p.startswith("upper_arm") else p for p in _anatomy(truth).parts)
    anatomy = _anatomy(truth, parts=parts)
    data = read_bvh(export_bvh(skeleton, motion, tmp_path / "p.bvh", anatomy=anatomy, labels=truth.segment_names))
    assert "l_upperarm" in data.names and "LeftForeArm" in data.names
    names = ascii_names(part_names(anatomy, truth.segment_names, None))
    assert names[3] == "l_upperarm" and names[4] == "LeftForeArm"
    _check_round_trip(skeleton, motion, names, data, 100.0, FACING)
    at = dict(zip(data.names, _rest(data)))
    assert at["LeftForeArm"][1] == pytest.approx(at["LeftHand"][1], abs=1e-9)
    assert at["LeftHand"][0] - at["LeftForeArm"][0] > 20.0
    np.testing.assert_allclose(at["RightFoot"][[0, 2]], at["RightUpLeg"][[0, 2]], atol=1e-9)


def test_other_naming_conventions(tmp_path, full_body):
    skeleton, motion, truth = full_body
    anatomy = _anatomy(truth)
    parts = read_bvh(export_bvh(skeleton, motion, tmp_path / "p.bvh", anatomy=anatomy, names="jaxskel"))
    assert list(parts.names) == list(anatomy.parts)
    labels = [f"seg {i}" for i in range(skeleton.n_segments)]
    mapped = read_bvh(export_bvh(skeleton, motion, tmp_path / "m.bvh", anatomy=anatomy, labels=labels,
                                 names={"pelvis": "Root+Pelvis", "head": "Skull"}))
    assert mapped.names[0] == "Root_Pelvis" and "Skull" in mapped.names and "seg_3" in mapped.names
    # a body that is not human keeps its labels whatever the convention, still Y up
    other = dataclasses.replace(anatomy, humanoid=False)
    plain = read_bvh(export_bvh(skeleton, motion, tmp_path / "n.bvh", anatomy=other, labels=labels))
    assert list(plain.names) == [f"seg_{i}" for i in range(skeleton.n_segments)]
    np.testing.assert_allclose(plain.offsets[1], 100.0 * FACING @ skeleton.joint_offsets[0, 0], atol=1e-6)
    short = dataclasses.replace(anatomy, parts=anatomy.parts[:-1], confidence=anatomy.confidence[:-1])
    with pytest.raises(InputError, match="anatomy names 14 segments"):
        export_bvh(skeleton, motion, tmp_path / "s.bvh", anatomy=short)


def test_names_are_distinct_ascii_identifiers():
    assert ascii_names(["Kné€", "L+R", "LASI+RASI+3more", "  a b ", "3more", "", "Ω", "x", "x", "x_2"]) == (
        "Kne", "L_R", "LASI_RASI_3more", "a_b", "_3more", "segment", "segment_2", "x", "x_2", "x_2_2")
    long = ascii_names(["A" * 100, "A" * 100])
    assert len(long[0]) == MAX_NAME and long[1] == "A" * MAX_NAME + "_2"


def test_centimetres_and_other_rotation_order_on_a_random_tree(tmp_path):
    skeleton, motion, _ = _truth_skeleton_and_motion(synth.random_tree(8, seed=5), seed=5)
    names = [f"part {i}" for i in range(skeleton.n_segments)]  # spaces are not BVH-safe
    path = export_bvh(
        skeleton, motion, tmp_path / "tree.bvh", units="cm", rotation_order="XYZ", labels=names
    )
    data = read_bvh(path)
    safe = [n.replace(" ", "_") for n in names]
    assert set(data.names) == set(safe)
    assert data.channels[1] == ("Xrotation", "Yrotation", "Zrotation")
    _check_round_trip(skeleton, motion, safe, data, 100.0, bvh_frame(None, "z"))
    metres = read_bvh(export_bvh(skeleton, motion, tmp_path / "tree_m.bvh", labels=names, units="m"))
    np.testing.assert_allclose(data.offsets, 100.0 * metres.offsets, atol=1e-6)


def test_segments_are_named_from_their_markers_and_the_names_survive_the_round_trip(tmp_path, full_body):
    """Without labels the joints take the readable names of jaxskel.segment._names (subject prefixes
    read past), and the independent `bvh` package reads the same names back."""
    skeleton, motion, _ = full_body
    prefixed = dataclasses.replace(skeleton, marker_labels=tuple(f"Sam:{v}" for v in skeleton.marker_labels))
    raw = names_from_markers(skeleton.marker_labels, skeleton.marker_segment, skeleton.n_segments)
    assert raw[skeleton.root] == "LASI+RASI+LPSI+RPSI"  # the pelvis: no prefix beyond the side
    names = ascii_names(raw)
    assert names[skeleton.root] == "LASI_RASI_LPSI_RPSI"  # written without "+"
    for sk in (skeleton, prefixed):
        path = export_bvh(sk, motion, tmp_path / "named.bvh", overwrite=True)
        data = read_bvh(path)
        assert sorted(data.names) == sorted(names)
        _check_round_trip(sk, motion, names, data, 100.0, bvh_frame(None, "z"))
        with open(path) as handle:
            assert sorted(bvh.Bvh(handle.read()).get_joints_names()) == sorted(names)
    rods, rod_motion, _ = _truth_skeleton_and_motion(synth.linkage())
    data = read_bvh(export_bvh(rods, rod_motion, tmp_path / "rods.bvh"))
    assert sorted(data.names) == ["R1M", "R2M", "R3M"]  # R1M1, R1M2, R1M3: their common prefix


def test_write_is_atomic_and_refuses_to_overwrite(tmp_path, full_body):
    skeleton, motion, _ = full_body
    path = tmp_path / "a.bvh"
    path.write_text("keep me")
    with pytest.raises(InputError, match="exists"):
        export_bvh(skeleton, motion, path)
    assert path.read_text() == "keep me"
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind
    export_bvh(skeleton, motion, path, overwrite=True)
    assert read_bvh(path).n_frames == motion.n_frames


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"units": "mm"}, "units"),
        ({"rotation_order": "XXY"}, "permutation"),
        ({"labels": ["a"] * 15}, "distinct"),
        ({"rate": -1.0}, "rate"),
        ({"names": "vicon"}, "names must be"),
        ({"up_axis": "up"}, "up_axis"),
    ],
)
def test_export_rejects_bad_arguments(tmp_path, full_body, kwargs, message):
    skeleton, motion, _ = full_body
    with pytest.raises(InputError, match=message):
        export_bvh(skeleton, motion, tmp_path / "x.bvh", **kwargs)
    assert not (tmp_path / "x.bvh").exists()


def test_reader_rejects_malformed_files(tmp_path, full_body):
    skeleton, motion, _ = full_body
    good = export_bvh(skeleton, motion, tmp_path / "good.bvh").read_text()
    cases = {
        "no_motion.bvh": good.split("MOTION")[0],
        "truncated.bvh": good[: good.index("MOTION") - 40] + good[good.index("MOTION") :],
        "short_rows.bvh": good.rsplit("\n", 2)[0] + "\n",
        "not_bvh.bvh": "hello world",
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError):
            read_bvh(tmp_path / name)
