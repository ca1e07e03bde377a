"""Tests of jaxskel.synth: the ground truth every other test relies on."""

from __future__ import annotations

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.io import rotation_between_axes
from scipy.spatial.transform import Rotation

RATE = 60.0
BODIES = {
    "linkage": synth.linkage,
    "full_body": lambda: synth.full_body(seed=3),
    "random_tree": lambda: synth.random_tree(9, seed=5),
}


def relative_rotvecs(truth: synth.GroundTruth, joint: int) -> np.ndarray:
    """(F, 3) rotation vector of the child relative to the parent, in the parent frame."""
    parent, child = truth.edges[joint]
    r_p = truth.segment_rotations[:, parent]
    r_c = truth.segment_rotations[:, child]
    return Rotation.from_matrix(np.swapaxes(r_p, -1, -2) @ r_c).as_rotvec()


@pytest.fixture(scope="module", params=list(BODIES))
def clean_calibration(request):
    body = BODIES[request.param]()
    return body, *synth.simulate(body, "calibration", duration=20.0, rate=RATE, seed=1)


# ------------------------------------------------------------------ bodies
def test_linkage_geometry():
    body = synth.linkage()
    assert body.joint_types == ("universal", "universal")
    assert body.n_markers == 9 and np.bincount(body.marker_segment).tolist() == [3, 3, 3]
    # The middle rod (the one with two joints) measures 0.341 m between its joints.
    np.testing.assert_allclose(body.bone_lengths, [0.341])
    for s in range(3):
        pts = body.marker_offsets[body.segment_markers(s)]
        # Non-degenerate marker set: the three markers span a plane, not a line.
        assert np.linalg.svd(pts - pts.mean(0), compute_uv=False)[1] > 0.01


def test_full_body_anatomy():
    body = synth.full_body(seed=0)
    assert 35 <= body.n_markers <= 50
    per_segment = np.bincount(body.marker_segment, minlength=body.n_segments)
    assert per_segment.min() >= 1 and per_segment.max() <= 4
    kind = dict(zip(body.joint_names, body.joint_types, strict=True))
    assert kind["l_knee"] == kind["r_elbow"] == "hinge"
    assert kind["l_hip"] == kind["r_shoulder"] == kind["spine"] == kind["neck"] == "ball"
    assert kind["l_wrist"] == kind["r_ankle"] == "universal"
    assert {"LKNE", "RANK", "LASI", "C7", "RFHD"} <= set(body.marker_labels)
    # Thigh and shank lengths of an adult (one bone each: hip-knee, knee-ankle).
    names = body.joint_names
    length = {
        (names[i], names[k]): d for (i, k), d in zip(body.bones, body.bone_lengths, strict=True)
    }
    assert 0.36 < length[("l_hip", "l_knee")] < 0.48
    assert 0.35 < length[("l_knee", "l_ankle")] < 0.47
    # Markers sit on the skin, off the bone line (segment frames start at the proximal joint).
    for m, s in enumerate(body.marker_segment):
        distal = [body.joint_offsets[j, 0] for j in np.flatnonzero(body.edges[:, 0] == s)]
        if s == body.root or len(distal) != 1:
            continue
        axis = distal[0] / np.linalg.norm(distal[0])
        off = body.marker_offsets[m]
        assert 0.02 < np.linalg.norm(off - (off @ axis) * axis) < 0.09, body.marker_labels[m]


def test_full_body_marker_selection_and_seeds():
    sparse = synth.full_body(markers_per_segment=1)
    assert sparse.n_markers == 15
    assert np.bincount(sparse.marker_segment).tolist() == [1] * 15
    few = synth.full_body(markers_per_segment={"l_hand": 1, "r_hand": 1})
    assert few.n_markers == 44
    chosen = synth.full_body(markers=["LKNE", "LANK"])
    assert chosen.marker_labels == ("LKNE", "LANK")
    a, b = synth.full_body(seed=1), synth.full_body(seed=2)
    assert not np.allclose(a.bone_lengths, b.bone_lengths)
    np.testing.assert_array_equal(a.marker_offsets, synth.full_body(seed=1).marker_offsets)
    with pytest.raises(jaxskel.InputError, match="no marker labelled"):
        synth.full_body(markers=["NOPE"])


def test_random_tree_structure():
    body = synth.random_tree(12, seed=4)
    assert body.n_segments == 12 and body.n_joints == 11
    assert set(body.joint_types) <= set(synth.JOINT_DOF)
    counts = np.bincount(body.marker_segment)
    assert counts.min() >= 2 and counts.max() <= 4
    assert np.all(body.bone_lengths > 0.01)
    # Every segment is reachable from the root (a single tree).
    assert sorted(body.edges[body.joint_order, 1].tolist()) == list(range(1, 12))


# --------------------------------------------------------- clean kinematics
def test_rigidity_of_markers_and_joints(clean_calibration):
    body, trial, truth = clean_calibration
    x = trial.positions
    np.testing.assert_array_equal(x, truth.clean_positions)
    seg = truth.marker_segment
    dist = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=-1)
    same = seg[:, None] == seg[None, :]
    assert np.abs(dist - dist[0])[:, same].max() < 1e-9
    # Joint-to-marker distances are constant for markers of both adjacent segments.
    for j, (parent, child) in enumerate(truth.edges):
        on_joint = (seg == parent) | (seg == child)
        d = np.linalg.norm(x[:, on_joint] - truth.joint_positions[:, j, None], axis=-1)
        assert np.abs(d - d[0]).max() < 1e-9
    # Bones (two joints on one segment) keep their length.
    bones = truth.bones
    length = np.linalg.norm(
        truth.joint_positions[:, bones[:, 0]] - truth.joint_positions[:, bones[:, 1]], axis=-1
    )
    np.testing.assert_allclose(length, np.broadcast_to(truth.bone_lengths, length.shape), atol=1e-9)
    # Marker offsets are the markers in their segment frame: x = R offset + t.
    rot = truth.segment_rotations[:, seg]
    local = np.einsum("fmji,fmj->fmi", rot, x - truth.segment_translations[:, seg])
    np.testing.assert_allclose(local, np.broadcast_to(truth.marker_offsets, local.shape), atol=1e-9)


def test_calibration_exercises_every_degree_of_freedom(clean_calibration):
    body, trial, truth = clean_calibration
    for j, kind in enumerate(truth.joint_types):
        rotvec = relative_rotvecs(truth, j)
        angles = truth.joint_angles[j]
        limits = truth.joint_limits[j]
        assert np.all(angles >= limits[:, 0]) and np.all(angles <= limits[:, 1])
        # Each angle sweeps most of its range of motion.
        swept = np.ptp(angles, axis=0) / (limits[:, 1] - limits[:, 0])
        assert swept.min() > 0.6, (truth.joint_names[j], swept)
        spread = np.linalg.svd(rotvec, compute_uv=False) / np.sqrt(len(rotvec))
        if kind == "hinge":
            axis = truth.joint_axes[j][0]
            off_axis = np.linalg.norm(np.cross(rotvec, axis), axis=-1)
            assert off_axis.max() < 1e-9
            assert np.ptp(rotvec @ axis) > 1.0
        else:
            assert spread[1] > 0.15, (truth.joint_names[j], spread)
        if kind == "ball":
            assert spread[2] > 0.1, (truth.joint_names[j], spread)
        if kind == "universal":
            # The parent-fixed and child-fixed axes keep their angle (the cross-piece).
            a0, a1 = truth.joint_axes[j]
            cosine = np.einsum("fi,fi->f", *np.moveaxis(truth.joint_axes_world[j], 1, 0))
            np.testing.assert_allclose(cosine, a0 @ a1, atol=1e-9)


def test_root_moves_and_turns(clean_calibration):
    body, trial, truth = clean_calibration
    root_t = truth.segment_translations[:, truth.root]
    assert np.ptp(root_t, axis=0)[:2].min() > 0.1
    turn = Rotation.from_matrix(truth.segment_rotations[:, truth.root]).as_rotvec()
    assert np.linalg.norm(turn, axis=-1).max() > 0.5


def test_walk_moves_legs_and_keeps_wrists_still():
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, "walk", duration=12.0, rate=RATE, seed=2)
    angle = {
        name: np.degrees(np.linalg.norm(relative_rotvecs(truth, j), axis=-1))
        for j, name in enumerate(truth.joint_names)
    }
    for name in ("l_wrist", "r_wrist", "neck"):
        assert angle[name].max() < 2.0, name
    for name in ("l_knee", "r_knee"):
        assert np.ptp(angle[name]) > 40.0
    assert np.ptp(angle["l_hip"]) > 20.0
    # Left and right knees are out of phase.
    corr = np.corrcoef(angle["l_knee"], angle["r_knee"])[0, 1]
    assert corr < -0.5
    # The pelvis travels (walking, not marching on the spot) at a walking speed.
    root = truth.segment_translations[:, truth.root]
    speed = np.linalg.norm(np.diff(root[:, :2], axis=0), axis=-1).mean() * RATE
    assert 0.9 < speed < 1.5
    # Feet meet the floor: the lowest foot marker touches down every stride and the
    # heel rests (near-zero vertical speed) during stance.
    heel = trial.positions[:, trial.labels.index("LHEE"), 2]
    toe = trial.positions[:, trial.labels.index("LTOE"), 2]
    assert -0.005 < min(heel.min(), toe.min()) < 0.04
    assert np.ptp(heel) > 0.15
    with pytest.raises(jaxskel.InputError, match="full_body"):
        synth.simulate(synth.linkage(), "walk", duration=1.0)


@pytest.mark.parametrize("motion", ["calibration", "walk"])
def test_joint_range_holds_a_joint_still(motion):
    body = synth.full_body(seed=1)
    kw = dict(duration=5.0, rate=RATE, seed=3)
    trial, truth = synth.simulate(body, motion, joint_range={"l_elbow": 0.0, "r_knee": 0.5}, **kw)
    _, free = synth.simulate(body, motion, **kw)
    elbow = truth.joint_names.index("l_elbow")
    knee = truth.joint_names.index("r_knee")
    assert np.ptp(relative_rotvecs(truth, elbow), axis=0).max() < 1e-12
    assert np.ptp(relative_rotvecs(free, elbow), axis=0).max() > 0.1
    excursion = np.ptp(truth.joint_angles[knee]) / np.ptp(free.joint_angles[knee])
    assert excursion == pytest.approx(0.5)
    with pytest.raises(jaxskel.InputError, match="unknown joint"):
        synth.simulate(body, motion, joint_range={"tail": 0.0}, **kw)


def test_seeds_are_reproducible_and_streams_independent():
    body = synth.random_tree(5, seed=0)
    kw = dict(duration=4.0, rate=RATE, noise=0.002, soft_tissue=0.004, gaps=2, jumps=4, ghosts=3)
    t1, g1 = synth.simulate(body, seed=7, **kw)
    t2, g2 = synth.simulate(body, seed=7, **kw)
    np.testing.assert_array_equal(t1.positions, t2.positions)
    assert t1.labels == t2.labels
    t3, _ = synth.simulate(body, seed=8, **kw)
    assert not np.allclose(np.nan_to_num(t1.positions), np.nan_to_num(t3.positions))
    # Turning noise off keeps the motion and the gaps of the same seed.
    t4, g4 = synth.simulate(body, seed=7, **{**kw, "noise": 0.0})
    np.testing.assert_array_equal(g4.clean_positions, g1.clean_positions)
    np.testing.assert_array_equal(t4.mask, t1.mask)


# ------------------------------------------------------------- corruptions
@pytest.fixture(scope="module")
def human():
    return synth.full_body(seed=0)


def test_noise_has_the_requested_std(human):
    trial, truth = synth.simulate(human, duration=10.0, rate=RATE, noise=0.002)
    err = trial.positions - truth.clean_positions
    assert abs(err.std() / 0.002 - 1) < 0.02
    assert abs(err.mean()) < 1e-4
    # Independent per coordinate: no correlation between x and y errors.
    assert abs(np.corrcoef(err[..., 0].ravel(), err[..., 1].ravel())[0, 1]) < 0.02


def test_soft_tissue_is_smooth_and_driven_by_joints(human):
    trial, truth = synth.simulate(human, duration=20.0, rate=RATE, soft_tissue=0.01)
    disp = trial.positions - truth.clean_positions
    np.testing.assert_allclose(disp, truth.soft_tissue_displacement, atol=1e-12)
    rms = np.sqrt((disp**2).sum(-1).mean(0))
    np.testing.assert_allclose(rms, 0.01, rtol=1e-6)
    # Smooth: frame-to-frame change is a small fraction of the amplitude.
    assert np.abs(np.diff(disp, axis=0)).max() < 0.1 * 0.01 * 10
    # Driven by the joints of the marker's segment: in the segment frame, a linear
    # function of those joint angles explains most of the displacement.
    lknee = truth.joint_names.index("l_knee")
    m = trial.labels.index("LTIB")  # on the shank: knee and ankle drive it
    seg = truth.marker_segment[m]
    local = np.einsum("fji,fj->fi", truth.segment_rotations[:, seg], disp[:, m])
    ankle = truth.joint_names.index("l_ankle")
    features = np.column_stack(
        [truth.joint_angles[lknee], truth.joint_angles[ankle], np.ones(trial.n_frames)]
    )
    coef, *_ = np.linalg.lstsq(features, local, rcond=None)
    explained = 1 - ((local - features @ coef) ** 2).sum() / ((local - local.mean(0)) ** 2).sum()
    assert explained > 0.7
    # The markers of one segment are no longer rigid.
    x = trial.positions
    a, b = (trial.labels.index(n) for n in ("LTIB", "LANK"))
    assert np.ptp(np.linalg.norm(x[:, a] - x[:, b], axis=-1)) > 0.005


def test_gaps_are_counted_and_bounded(human):
    gap_length = (0.1, 0.4)
    trial, truth = synth.simulate(
        human, duration=10.0, rate=RATE, gaps=3, gap_length=gap_length
    )
    missing = ~trial.mask
    assert missing[0].sum() == missing[-1].sum() == 0
    starts = missing[1:] & ~missing[:-1]
    assert (starts.sum(0) == 3).all()
    lengths = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], missing[:, 0], [0]]))))[::2]
    assert round(gap_length[0] * RATE) <= lengths.min()
    assert lengths.max() <= round(gap_length[1] * RATE)
    # Where visible, the trial is the clean data (no other corruption asked for).
    np.testing.assert_array_equal(trial.positions[~missing], truth.clean_positions[~missing])
    with pytest.raises(jaxskel.InputError, match="do not fit"):
        synth.simulate(human, duration=1.0, rate=RATE, gaps=5, gap_length=(0.5, 0.5))


def test_jumps_displace_a_few_samples_by_centimetres(human):
    trial, truth = synth.simulate(
        human, duration=10.0, rate=RATE, gaps=2, jumps=20, jump_size=(0.03, 0.08)
    )
    jumped = truth.jumped
    dist = np.linalg.norm(trial.positions - truth.clean_positions, axis=-1)
    assert 20 <= jumped.sum() <= 20 * 5 * 2  # events may overlap; two can stack on a sample
    assert dist[jumped].min() > 0.0 and np.nanmax(dist[jumped]) > 0.03
    np.testing.assert_array_equal(dist[trial.mask & ~jumped], 0.0)
    # Half of them sit right against an occlusion.
    missing = ~trial.mask
    near_gap = jumped & (np.roll(missing, 1, axis=0) | np.roll(missing, -1, axis=0))
    assert near_gap.any(axis=0).sum() >= 5


def test_ghosts_are_extra_short_lived_columns(human):
    trial, truth = synth.simulate(
        human, duration=5.0, rate=RATE, ghosts=6, ghost_length=(0.1, 0.3), gaps=3
    )
    ghost = np.array([lab.startswith("*ghost") for lab in trial.labels])
    assert ghost.sum() == 6 and trial.n_markers == human.n_markers + 6
    assert (truth.marker_segment[ghost] == -1).all() and (truth.physical[ghost] == -1).all()
    assert (truth.marker_segment[~ghost] >= 0).all()
    visible = trial.mask[:, ghost].sum(0)
    assert visible.min() >= round(0.1 * RATE) and visible.max() <= round(0.3 * RATE)
    assert np.isnan(truth.clean_positions[:, ghost]).all()


def test_relabel_gives_new_labels_after_every_gap(human):
    kw = dict(duration=8.0, rate=RATE, seed=3, noise=0.001, gaps=2, ghosts=2)
    plain, _ = synth.simulate(human, **kw)
    trial, truth = synth.simulate(human, relabel=True, **kw)
    n_phys = human.n_markers
    assert trial.n_markers == n_phys + 2 * n_phys + 2
    real = truth.physical >= 0
    assert np.bincount(truth.physical[real]).tolist() == [3] * n_phys
    # Labels of one physical marker never co-occur in a frame.
    present = trial.mask[:, real]
    owners = truth.physical[real]
    counts = np.zeros((trial.n_frames, n_phys), dtype=int)
    np.add.at(counts.T, owners, present.T)
    assert counts.max() == 1
    # Merging the labels of each physical marker gives back the unrelabelled trial.
    merged = np.full((trial.n_frames, n_phys, 3), np.nan)
    for col in np.flatnonzero(real):
        rows = trial.mask[:, col]
        merged[rows, truth.physical[col]] = trial.positions[rows, col]
    np.testing.assert_array_equal(merged, plain.positions[:, :n_phys])
    # New labels are numbered in order of appearance.
    first_seen = trial.mask[:, n_phys : 3 * n_phys].argmax(0)
    assert np.all(np.diff(first_seen) >= 0)
    np.testing.assert_array_equal(
        truth.clean_positions[:, real], truth.clean_positions[:, truth.physical[real]]
    )


def test_up_axis_matches_trial_conversion():
    body = synth.linkage()
    kw = dict(duration=2.0, rate=RATE, seed=4, noise=0.001, gaps=1)
    z_trial, z_truth = synth.simulate(body, **kw)
    for up in ("y", "-x"):
        trial, truth = synth.simulate(body, up_axis=up, **kw)
        assert trial.up_axis == up
        np.testing.assert_allclose(trial.to_up_axis("z").positions, z_trial.positions, atol=1e-12)
        back = truth.joint_positions @ rotation_between_axes(up, "z").T
        np.testing.assert_allclose(back, z_truth.joint_positions, atol=1e-12)
    with pytest.raises(jaxskel.InputError, match="up_axis"):
        synth.simulate(body, up_axis="up")


def test_bad_arguments_raise_input_errors():
    body = synth.linkage()
    with pytest.raises(jaxskel.InputError, match="unknown motion"):
        synth.simulate(body, "dance")
    with pytest.raises(jaxskel.InputError, match="noise"):
        synth.simulate(body, noise=-1.0)
    with pytest.raises(jaxskel.InputError, match="gaps"):
        synth.simulate(body, gaps=1.5)
    with pytest.raises(jaxskel.InputError, match="synth.Body"):
        synth.simulate("linkage")
    with pytest.raises(jaxskel.InputError, match="at least two frames"):
        synth.simulate(body, duration=0.0)
