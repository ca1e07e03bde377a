"""Body frame handedness from the body, and the foot's own limb frame (issue 47, items 4 and 5).

Ground truth: ``synth.full_body`` stands facing its pelvis' +x with its left
along the pelvis' +y; the foot's heel -> toe axis is the foot segment's +x.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from calibration_motions import main_movements, perturbed, truth_arrays

from jaxskel import DegenerateMotionWarning, synth
from jaxskel.sd06 import normalize, parameterize
from jaxskel.sd06._normalize import leaf_axes_from_markers

RATE = 30.0


def recording(seed: int, *, straight_knees: bool = False):
    """A subject (``full_body(seed)``) doing the protocol (main movements), facing a random direction."""
    body = synth.full_body(seed=seed)
    angles, root_rot, root_trans = main_movements(body, rate=RATE, seed=seed)
    if straight_knees:
        angles = tuple(np.zeros_like(a) if "knee" in n else a for a, n in zip(angles, body.joint_names, strict=True))
    _, _, rot, trans = truth_arrays(body, angles, root_rot, root_trans)
    joints, quats, rot, trans = perturbed(body, rot, trans, np.random.default_rng(seed), 0.2)
    return SimpleNamespace(body=body, angles=angles, joints=joints, quats=quats, rot=rot, trans=trans)


def skeleton_of(body: synth.Body, markers: bool):
    s = SimpleNamespace(edges=np.asarray(body.edges), root=body.root)
    if markers:
        s.marker_segment, s.marker_offsets = np.asarray(body.marker_segment), np.asarray(body.marker_offsets)
        s.joint_offsets = np.asarray(body.joint_offsets)
    return s


def permuted(rec, skeleton, rng: np.random.Generator):
    """The same recording with the skeleton's segments and joints renumbered at random."""
    n_seg, n_joint = rec.quats.shape[1], rec.joints.shape[1]
    seg = rng.permutation(n_seg)  # old segment s becomes seg[s]
    jnt = rng.permutation(n_joint)  # old joint j becomes jnt[j]
    edges = np.zeros_like(skeleton.edges)
    edges[jnt] = seg[skeleton.edges]
    out = SimpleNamespace(edges=edges, root=int(seg[skeleton.root]))
    if hasattr(skeleton, "marker_segment"):
        out.marker_segment, out.marker_offsets = seg[skeleton.marker_segment], skeleton.marker_offsets
        out.joint_offsets = np.zeros_like(skeleton.joint_offsets)
        out.joint_offsets[jnt] = skeleton.joint_offsets
    joints = np.zeros_like(rec.joints)
    joints[:, jnt] = rec.joints
    quats, trans = np.zeros_like(rec.quats), np.zeros_like(rec.trans)
    quats[:, seg], trans[:, seg] = rec.quats, rec.trans
    motion = SimpleNamespace(joint_positions=joints, rotations=quats, segment_translations=trans, rate=RATE)
    return out, motion, seg, jnt


@pytest.mark.parametrize("markers", [False, True], ids=["knees", "feet"])
def test_one_handedness_over_15_recordings_with_permuted_joint_orders(markers):
    """Front, left and up agree with the body in 15 subjects x permuted segment/joint orders.

    The old rule (left = the side of the first lateral joint in joint order)
    mirrors the frame whenever a right limb comes first.
    """
    cue = "feet" if markers else "knees"
    rng = np.random.default_rng(47)
    for seed in range(15):
        rec = recording(seed)
        skeleton = skeleton_of(rec.body, markers)
        motion = SimpleNamespace(joint_positions=rec.joints, rotations=rec.quats, segment_translations=rec.trans)
        ref = normalize(skeleton, motion)
        skel_p, motion_p, seg, jnt = permuted(rec, skeleton, rng)
        norm = normalize(skel_p, motion_p)
        assert ref.handedness == norm.handedness == cue, (seed, ref.handedness, norm.handedness)
        np.testing.assert_allclose(norm.body_frame, ref.body_frame, atol=1e-9)
        d = norm.default_frame
        pelvis = rec.rot[d, rec.body.root]
        cos = np.sum(norm.body_frame * pelvis, axis=0)  # body axes against the pelvis' x (front), y (left), z (up)
        assert np.all(cos > np.cos(np.radians(10.0))), (seed, np.degrees(np.arccos(np.clip(cos, -1, 1))))
        # Left limbs on the left: every l_* joint has y > 0 from the pelvis origin, r_* y < 0.
        origin = norm.limb_origins[d, norm.root]
        side = (motion_p.joint_positions[d] - origin) @ norm.body_frame[:, 1]
        for j, name in enumerate(rec.body.joint_names):
            if name[:2] in ("l_", "r_"):
                assert np.sign(side[jnt[j]]) == (1 if name[0] == "l" else -1), (seed, name, side[jnt[j]])


def test_without_a_body_cue_the_front_is_a_reported_convention():
    """Straight knees, no foot markers, no walking: nothing tells front from back."""
    rec = recording(3, straight_knees=True)
    motion = SimpleNamespace(joint_positions=rec.joints, rotations=rec.quats, segment_translations=rec.trans)
    with pytest.warns(DegenerateMotionWarning, match="front and back"):
        norm = normalize(skeleton_of(rec.body, False), motion)
    assert norm.handedness == "none"
    # The same recording with its foot markers is oriented by the feet, and facing= overrides both.
    with warnings.catch_warnings():
        warnings.simplefilter("error", DegenerateMotionWarning)
        feet = normalize(skeleton_of(rec.body, True), motion)
        facing = normalize(skeleton_of(rec.body, True), motion, facing=-feet.body_frame[:, 0])
    assert feet.handedness == "feet" and facing.handedness == "facing"
    assert feet.body_frame[:, 0] @ rec.rot[feet.default_frame, 0, :, 0] > 0.98
    np.testing.assert_allclose(facing.body_frame[:, :2], -feet.body_frame[:, :2], atol=1e-12)


# ------------------------------------------------------------------ item 5: the foot's own frame
def test_leaf_axes_from_markers_follow_each_leafs_geometry():
    body = synth.full_body(seed=0)
    axes = leaf_axes_from_markers(body.edges, body.root, body.marker_segment, body.marker_offsets, body.joint_offsets)
    names = body.segment_names
    for foot in ("l_foot", "r_foot"):  # heel -> toe: the foot's +x
        assert axes[names.index(foot)] @ [1.0, 0.0, 0.0] > np.cos(np.radians(5.0))
    for hand in ("l_hand", "r_hand"):  # wrist -> hand markers: down the hand
        assert axes[names.index(hand)] @ [0.0, 0.0, -1.0] > np.cos(np.radians(30.0))
    assert axes[names.index("head")] @ [0.0, 0.0, 1.0] > np.cos(np.radians(30.0))
    non_leaf = [names.index(s) for s in ("pelvis", "torso", "l_thigh", "r_shank", "l_upperarm")]
    np.testing.assert_array_equal(axes[non_leaf], 0.0)


@pytest.fixture(scope="module")
def foot_session():
    rec = recording(0)
    skeleton = skeleton_of(rec.body, True)
    motion = SimpleNamespace(joint_positions=rec.joints, rotations=rec.quats, segment_translations=rec.trans, rate=RATE)
    return rec, skeleton, motion


def test_foot_limb_frame_runs_heel_to_toe(foot_session):
    """In every frame the foot's limb long axis is the true heel -> toe direction (the foot's +x), not the shank's."""
    rec, skeleton, motion = foot_session
    norm = normalize(skeleton, motion)
    for foot in ("l_foot", "r_foot"):
        s = rec.body.segment_names.index(foot)
        toe = rec.rot[:, s, :, 0]
        err = np.degrees(np.arccos(np.clip(np.sum(norm.main_directions[:, s] * toe, -1), -1, 1)))
        assert err.max() < 6.0, (foot, err.max())
        d = norm.default_frame  # at rest the shank's long axis (its +z) is some 90 degrees away
        assert abs(norm.main_directions[d, s] @ rec.rot[d, s - 1, :, 2]) < 0.2


def test_ankle_is_flexion_plus_twist_with_the_foot_frame(foot_session):
    """The ankle's inversion axis is the foot's long axis: one swing axis (flexion), inversion is the twist."""
    rec, skeleton, motion = foot_session
    param = parameterize(skeleton, motion)
    norm = param.normalization
    for side in ("l", "r"):
        j = rec.body.joint_names.index(f"{side}_ankle")
        assert param.n_axes[j] == 1
        parent = rec.body.edges[j, 0]
        true_flexion = rec.body.joint_axes[j][0] @ norm.limb_frames_local[parent]
        assert abs(param.axes[j, 0] @ true_flexion) > np.cos(np.radians(3.0))
        flex_sign = np.sign(param.axes[j, 0] @ true_flexion)
        err_flex = np.degrees(param.angles[:, j, 0] - flex_sign * rec.angles[j][:, 0])
        inversion = rec.angles[j][:, 1]
        tw_sign = np.sign(np.sum(param.angles[:, j, 2] * inversion))
        err_inv = np.degrees(param.angles[:, j, 2] - tw_sign * inversion)
        assert np.sqrt(np.mean(err_flex**2)) < 2.0 and np.sqrt(np.mean(err_inv**2)) < 4.0, (
            side, np.sqrt(np.mean(err_flex**2)), np.sqrt(np.mean(err_inv**2)))
