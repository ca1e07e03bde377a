"""Body parts named without marker names: synthetic bodies with shuffled, meaningless labels,
their mirror image and a turned lab, partial bodies, bodies that are not human, and the
real recordings of ``bench/real_trees.py`` judged with the body-part maps."""

from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.anatomy import AnatomyOptions, identify, identify_result, mirror

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers import REAL, truth_motion, truth_skeleton  # noqa: E402
from truth import result_truth, score, synth_truth  # noqa: E402

LEGS = {"pelvis", "thigh_l", "thigh_r", "shank_l", "shank_r", "foot_l", "foot_r"}


def anonymous(trial, seed: int):
    """The trial with its markers shuffled and labelled ``M0..Mn``, and the original label of each."""
    order = np.random.default_rng(seed).permutation(trial.n_markers)
    shuffled = trial.select_markers(order)
    return shuffled.replace(labels=tuple(f"M{i}" for i in range(shuffled.n_markers))), shuffled.labels


def fit(trial):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jaxskel.fit_skeleton(trial)


def truth_of(result, body, original):
    """Per fitted segment, its true part (labels mapped back to the body's own)."""
    name = dict(zip((f"M{i}" for i in range(len(original))), original))
    return synth_truth(body, [name[lab] for lab in result.trial.labels], result.segmentation.marker_segment)


@pytest.fixture(scope="module")
def full_fit():
    body = synth.full_body(3)
    trial, truth = synth.simulate(body, motion="calibration", duration=4, noise=0.0005, seed=1)
    trial, original = anonymous(trial, 0)
    result = fit(trial)
    # the body's forward (the pelvis's +X) at the skeleton's rest frame
    forward = truth.segment_rotations[result.skeleton.diagnostics["rest_frame"], body.root][:, 0]
    return body, original, result, forward


def _transformed(result, matrix: np.ndarray):
    """The fitted skeleton and motion in a lab frame changed by ``matrix`` (a rotation, or a
    reflection: the mirror image of the recording, whose segment rotations ``P R P`` stay proper)."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(matrix, float)
    sk, mo = result.skeleton, result.motion
    skeleton = dataclasses.replace(
        sk, marker_offsets=sk.marker_offsets @ p.T, joint_offsets=sk.joint_offsets @ p.T,
        diagnostics=dict(sk.diagnostics),
    )  # fmt: skip
    q = np.asarray(mo.rotations, float)
    r = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix()
    r = p @ r @ p.T if np.linalg.det(p) > 0 else p @ r @ p
    quats = Rotation.from_matrix(r).as_quat(scalar_first=True).reshape(q.shape)
    motion = dataclasses.replace(
        mo, rotations=quats, segment_translations=np.asarray(mo.segment_translations) @ p.T,
        joint_positions=np.asarray(mo.joint_positions) @ p.T, root_position=np.asarray(mo.root_position) @ p.T,
        fitted_markers=np.asarray(mo.fitted_markers) @ p.T,
    )  # fmt: skip
    return skeleton, motion


def test_a_full_body_with_meaningless_labels_is_named(full_fit):
    body, original, result, forward = full_fit
    anatomy = identify_result(result)
    right, scored, swapped = score(anatomy.parts, truth_of(result, body, original))
    assert anatomy.humanoid
    assert scored >= 13 and right >= 0.95 * scored and swapped == 0, (anatomy.parts, anatomy.notes)
    assert np.allclose(anatomy.up, [0, 0, 1])  # the trial's Z up
    assert anatomy.front @ forward > 0.9
    named = [c for p, c in zip(anatomy.parts, anatomy.confidence) if p]
    assert min(named) > 0.3 and max(anatomy.confidence) <= 1.0
    assert all(c == 0 for p, c in zip(anatomy.parts, anatomy.confidence) if not p)


def test_the_vertical_is_found_from_the_body(full_fit):
    result = full_fit[2]
    anatomy = identify(result.skeleton, result.motion, up_axis="auto")
    assert np.allclose(anatomy.up, [0, 0, 1])
    assert anatomy.parts == identify_result(result).parts


def test_a_mirrored_recording_swaps_every_side(full_fit):
    result = full_fit[2]
    parts = identify_result(result).parts
    skeleton, motion = _transformed(result, np.diag([1.0, -1.0, 1.0]))
    mirrored = identify(skeleton, motion, up_axis="z")
    assert mirrored.parts == tuple(mirror(p) for p in parts)
    assert sum(p != mirror(p) for p in parts) >= 10


def test_a_turned_lab_frame_gives_the_same_parts(full_fit):
    result = full_fit[2]
    parts = identify_result(result).parts
    z_to_y = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # the lab's Z becomes Y
    skeleton, motion = _transformed(result, z_to_y)
    for up_axis in ("y", "auto"):
        turned = identify(skeleton, motion, up_axis=up_axis)
        assert turned.parts == parts
        assert np.allclose(turned.up, [0, 1, 0])


def test_the_rest_pose_alone_names_the_body(full_fit):
    body, original, result, _ = full_fit
    anatomy = identify(result.skeleton, None, up_axis="z")
    right, scored, swapped = score(anatomy.parts, truth_of(result, body, original))
    assert swapped == 0 and right >= 0.9 * scored, (anatomy.parts, anatomy.notes)


def test_a_lower_limb_set_is_named_as_far_as_it_goes():
    body = synth.full_body(5)
    keep = [lab for lab, s in zip(body.marker_labels, body.marker_segment) if "pelvis" in body.segment_names[s]
            or any(k in body.segment_names[s] for k in ("thigh", "shank", "foot"))]  # fmt: skip
    body = body.select_markers(keep)
    trial, _ = synth.simulate(body, motion="calibration", duration=4, noise=0.0005, seed=2)
    trial, original = anonymous(trial, 1)
    result = fit(trial)
    anatomy = identify_result(result)
    truth = truth_of(result, body, original)
    right, scored, swapped = score(anatomy.parts, truth)
    assert anatomy.humanoid and swapped == 0 and right >= 0.95 * scored, (anatomy.parts, truth)
    assert set(anatomy.parts) - {""} <= LEGS and {"thigh_l", "thigh_r", "shank_l", "shank_r"} <= set(anatomy.parts)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_random_tree_is_not_human(seed):
    body = synth.random_tree(12, seed)
    trial, truth = synth.simulate(body, duration=4, noise=0.0, seed=seed)
    anatomy = identify(truth_skeleton(trial, truth), truth_motion(trial, truth))
    assert not anatomy.humanoid and set(anatomy.parts) == {""} and not anatomy.confidence.any()
    assert anatomy.notes


def test_the_linkage_is_not_human():
    body = synth.linkage()
    trial, truth = synth.simulate(body, duration=4, noise=0.0, seed=0)
    anatomy = identify(truth_skeleton(trial, truth), truth_motion(trial, truth), up_axis="z")
    assert not anatomy.humanoid and set(anatomy.parts) == {""} and not anatomy.confidence.any()
    assert "not a human" in anatomy.notes[0]


def test_the_true_full_body_is_named_exactly():
    body = synth.full_body(1)
    trial, truth = synth.simulate(body, motion="calibration", duration=4, noise=0.0, seed=0)
    anatomy = identify(truth_skeleton(trial, truth), truth_motion(trial, truth), up_axis="z")
    expected = tuple(synth_truth(body, body.marker_labels, body.marker_segment))
    assert anatomy.parts == expected


def _long_feet_uneven_thighs(seed: int):
    """A full body whose left thigh is 10 % longer than its right and whose toe markers sit
    26 cm ahead of the ankle: the two legs' shank + foot spans agree better than their
    thigh + shank spans."""
    body = synth.full_body(seed)
    joints = np.array(body.joint_offsets)
    joints[body.joint_names.index("l_knee"), 0] *= 1.1
    markers = np.array(body.marker_offsets)
    markers[[lab.endswith("TOE") for lab in body.marker_labels], 0] = 0.26
    return dataclasses.replace(body, joint_offsets=joints, marker_offsets=markers)


@pytest.mark.parametrize("motion", ["walk", "calibration", None])
def test_the_knee_is_the_hinge_that_straightens_not_the_ankle(motion):
    """The hinge of a leg is chosen among the knee and the ankle (both could pair the legs'
    spans): the knee straightens, the ankle never does. Matching the spans alone took the
    ankles here (thigh_l named on the shank)."""
    body = _long_feet_uneven_thighs(0)
    trial, truth = synth.simulate(body, motion=motion or "walk", duration=4, noise=0.0, seed=0)
    anatomy = identify(truth_skeleton(trial, truth), truth_motion(trial, truth) if motion else None, up_axis="z")
    assert anatomy.parts == tuple(synth_truth(body, body.marker_labels, body.marker_segment)), anatomy.notes


@pytest.mark.parametrize("bad", [
    {"limb_match": -0.1}, {"limb_match": float("nan")}, {"min_side_evidence": 2.0}, {"min_leg_span": "long"},
    {"clavicle_ratio": 1.5}, {"axis_snap_deg": 120.0}, {"max_frames": 0}, {"max_frames": 2.5},
])  # fmt: skip
def test_bad_options_raise_input_error(bad):
    with pytest.raises(jaxskel.InputError):
        AnatomyOptions(**bad)


def test_bad_arguments_raise_input_error(full_fit):
    result = full_fit[2]
    with pytest.raises(jaxskel.InputError, match="up_axis"):
        identify(result.skeleton, result.motion, up_axis="w")
    with pytest.raises(jaxskel.InputError, match="AnatomyOptions"):
        identify(result.skeleton, result.motion, options={"limb_match": 0.1})


# --------------------------------------------------------------------------- real recordings
def _judge_real(path: Path, **settings) -> tuple[int, int, int]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(jaxskel.load(path), **settings)
    anatomy = identify_result(result)
    return score(anatomy.parts, result_truth(result))


@pytest.fixture(scope="module")
def demo_rest_fit():
    """The bundled demo (Clouthier's 62-marker cluster set, kneel to prone), default settings
    without IK: one fit (about a minute on 2 cores) for the two tests below."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jaxskel.fit_skeleton(jaxskel.load(Path(jaxskel.__file__).parent / "data" / "KneeltoProne01.c3d"),
                                    None, ik=False)


def test_the_bundled_demo_is_named_from_its_rest_pose(demo_rest_fit):
    # without IK (fast): the rest pose is the only frame
    right, scored, swapped = score(identify_result(demo_rest_fit).parts, result_truth(demo_rest_fit))
    assert scored >= 15 and swapped == 0 and right >= 0.95 * scored, (right, scored)


def test_bundled_sample_tree_is_anatomical_with_default_settings(demo_rest_fit):
    """The demo's recording, default settings: every joint joins adjacent body parts and no
    marker sits with a body part it is not on. The acromion, hand and ankle markers are
    one-marker segments; before they were attachments (jaxskel.joints._attachments) the right
    acromion marker was a hub jointed to the thorax, the head and the right upper arm, and the
    head hung from it (head-acromion 7.1 against head-thorax 13.0 mm^2: one marker tests one
    distance). (Moved from tests/test_real_skeleton.py to share this fit.)"""
    from human_markers import implausible_edges, misplaced_markers, segment_parts

    result = demo_rest_fit
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    assert implausible_edges(labels, seg, result.edges) == []
    assert misplaced_markers(labels, seg, result.segmentation.distance_std, result.segmentation.rigid_limit) == []
    parts = segment_parts(labels, seg)
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    assert {frozenset(("thorax", "head")), frozenset(("thorax", "pelvis"))} <= edges
    hosts = {result.trial.labels[int(np.flatnonzero(seg == a.segment)[0])]: parts[a.host]
             for a in result.topology.attachments}
    assert hosts["RHAND"] == "R forearm" and hosts["LHAND"] == "L forearm"
    for a in result.topology.attachments:  # every one-marker segment is a leaf
        assert sum(a.segment in e for e in result.edges.tolist()) == 1


#: Measured levels below the target: recording -> reason (strict xfail).
BELOW_TARGET: dict[str, str] = {
    "auto_marker_label/PronetoRun01.c3d": "15/16 right, 0 swapped (the head hangs in an arm chain)",
    "nimblephysics/cmu_02_05.c3d": "13/14 right, 0 swapped (a shoulder segment named clavicle, truth thorax)",
    "numediart/HDM_bd_05-01_01_120.c3d": "0/17 right, 0 swapped (not named)",
    "nimblephysics/squat.c3d": "0/11 right, 0 swapped (not named)",
    "pycgm/Movement_trial.c3d": "6/11 right, 0 swapped",
    "kineticstoolkit/kinematics_tennis_serve.c3d": "0/16 right, 0 swapped (not named)",
    "kineticstoolkit/kinematics_basket_sprint.c3d": "0/1 right, 0 swapped (not named)",
}

RECORDINGS = (
    "auto_marker_label/PronetoRun01.c3d", "nimblephysics/cmu_02_05.c3d", "c3d_to_xyz_cmu/01_01.c3d",
    "numediart/85_12.c3d", "numediart/HDM_bd_05-01_01_120.c3d", "dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d",
    "nimblephysics/squat.c3d", "pycgm/Movement_trial.c3d", "kineticstoolkit/kinematics_tennis_serve.c3d",
    "kineticstoolkit/kinematics_basket_sprint.c3d", "numediart/03_rolling.c3d",
)  # fmt: skip


@pytest.mark.extended
@pytest.mark.parametrize("rel", [
    pytest.param(r, marks=pytest.mark.xfail(strict=True, reason=BELOW_TARGET[r])) if r in BELOW_TARGET else r
    for r in RECORDINGS
])  # fmt: skip
def test_a_real_recording_is_named(rel):
    right, scored, swapped = _judge_real(REAL / rel)
    assert swapped == 0 and right >= 0.95 * scored, (right, scored, swapped)
