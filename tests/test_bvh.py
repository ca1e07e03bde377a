"""BVH export and reader, checked against the independent `bvh` package and by forward kinematics.

The skeleton and motion are built directly from synthetic ground truth (no solver), so
these tests isolate the file format.
"""

from __future__ import annotations

import dataclasses

import bvh
import numpy as np
import pytest
from helpers import truth_motion, truth_skeleton

from jaxskel import InputError, synth
from jaxskel.result import export_bvh, read_bvh
from jaxskel.segment import names_from_markers


def _truth_skeleton_and_motion(body, duration=1.0, seed=0):
    trial, truth = synth.simulate(body, "calibration", duration=duration, seed=seed)
    return truth_skeleton(trial, truth), truth_motion(trial, truth), truth


@pytest.fixture(scope="module")
def full_body():
    return _truth_skeleton_and_motion(synth.full_body(seed=0))


def _proximal(skeleton):
    prox = np.full(skeleton.n_segments, -1)
    prox[skeleton.edges[:, 1]] = np.arange(skeleton.n_joints)
    return prox


def _check_round_trip(skeleton, motion, names, data, scale):
    world = data.world_positions() / scale
    assert data.n_frames == motion.n_frames
    prox = _proximal(skeleton)
    for s, name in enumerate(names):
        node = data.names.index(name)
        if s == skeleton.root:
            np.testing.assert_allclose(world[:, node], motion.root_position, atol=1e-6)
        else:
            np.testing.assert_allclose(world[:, node], motion.joint_positions[:, prox[s]], atol=1e-6)


def test_round_trip_positions_and_independent_parser(tmp_path, full_body):
    skeleton, motion, truth = full_body
    names = truth.segment_names
    path = export_bvh(skeleton, motion, tmp_path / "body.bvh", labels=names)
    data = read_bvh(path)
    _check_round_trip(skeleton, motion, names, data, 1.0)
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


def test_offsets_are_the_rest_pose_bones(tmp_path, full_body):
    skeleton, motion, truth = full_body
    names = truth.segment_names
    data = read_bvh(export_bvh(skeleton, motion, tmp_path / "rest.bvh", labels=names))
    for j, (p, c) in enumerate(skeleton.edges):
        node = data.names.index(names[c])
        # Full-body segment origins sit at their proximal joints: OFFSET = joint in parent frame.
        np.testing.assert_allclose(data.offsets[node], skeleton.joint_offsets[j, 0], atol=1e-9)
    np.testing.assert_array_equal(data.offsets[data.names.index(names[skeleton.root])], 0.0)


def test_centimetres_and_other_rotation_order_on_a_random_tree(tmp_path):
    skeleton, motion, truth = _truth_skeleton_and_motion(synth.random_tree(8, seed=5), seed=5)
    names = [f"part {i}" for i in range(skeleton.n_segments)]  # spaces are not BVH-safe
    path = export_bvh(
        skeleton, motion, tmp_path / "tree.bvh", units="cm", rotation_order="XYZ", labels=names
    )
    data = read_bvh(path)
    safe = [n.replace(" ", "_") for n in names]
    assert set(data.names) == set(safe)
    assert data.channels[1] == ("Xrotation", "Yrotation", "Zrotation")
    _check_round_trip(skeleton, motion, safe, data, 100.0)
    metres = read_bvh(export_bvh(skeleton, motion, tmp_path / "tree_m.bvh", labels=names))
    np.testing.assert_allclose(data.offsets, 100.0 * metres.offsets, atol=1e-6)


def test_segments_are_named_from_their_markers_and_the_names_survive_the_round_trip(tmp_path, full_body):
    """Without labels the joints take the readable names of jaxskel.segment._names (subject prefixes
    read past), and the independent `bvh` package reads the same names back."""
    skeleton, motion, _ = full_body
    prefixed = dataclasses.replace(skeleton, marker_labels=tuple(f"Sam:{v}" for v in skeleton.marker_labels))
    names = names_from_markers(skeleton.marker_labels, skeleton.marker_segment, skeleton.n_segments)
    assert names[skeleton.root] == "LASI+RASI+LPSI+RPSI"  # the pelvis: no prefix beyond the side
    for sk in (skeleton, prefixed):
        path = export_bvh(sk, motion, tmp_path / "named.bvh", overwrite=True)
        data = read_bvh(path)
        assert sorted(data.names) == sorted(names)
        _check_round_trip(sk, motion, names, data, 1.0)
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
