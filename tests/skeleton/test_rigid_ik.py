"""Rigid skeleton (Kirk et al. §3.3) and inverse kinematics against synthetic ground truth.

One fit per seed is shared by the accuracy tests (module-scoped fixture): a full body,
calibration motion, 2 mm marker noise plus 3 mm soft-tissue artefact, with the true joint
centres (plus 2 mm noise, standing in for the joint solver) as input.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import horn_align, matrix_to_quat, random_rotation, segment_map
from scipy.spatial.transform import Rotation

import jaxskel
from jaxskel import ConvergenceWarning, DegenerateMotionError, InputError, synth
from jaxskel.segment import combine_trials
from jaxskel.skeleton import Skeleton, fit_rigid, forward_kinematics, ik_solve, inverse_kinematics
from jaxskel.skeleton import _ik as ik_module
from jaxskel.skeleton import _ik_batch as ik_batch
from jaxskel.skeleton import _rigid_sweeps as rigid_sweeps
from jaxskel.skeleton._ik import kinematic_chain
from jaxskel.skeleton._rigid_fit import SOLVED_JOINT_WEIGHT

NOISE = 0.002
SOFT = 0.003
DURATION = 10.0  # 1200 frames at 120 Hz
FIT_FRAMES = 300


def _fit(seed: int, trial=None, truth=None):
    if trial is None:
        body = synth.full_body(seed=seed)
        trial, truth = synth.simulate(
            body, "calibration", duration=DURATION, seed=seed, noise=NOISE, soft_tissue=SOFT
        )
    # The joint solver's output, simulated: true centres plus 2 mm noise.
    joints = truth.joint_positions + np.random.default_rng(seed).normal(0.0, 0.002, truth.joint_positions.shape)
    skeleton = fit_rigid(trial, truth.marker_segment, truth.edges, joints, max_frames=FIT_FRAMES)
    return trial, truth, joints, skeleton


def _fit_and_ik(seed: int):
    trial, truth, joints, skeleton = _fit(seed)
    return trial, truth, joints, skeleton, inverse_kinematics(skeleton, trial)


@pytest.fixture(scope="module")
def seed0():
    return _fit_and_ik(0)


@pytest.fixture(scope="module")
def seed1():
    return _fit_and_ik(1)


@pytest.fixture(params=["seed0", "seed1"])
def fitted(request):
    """Accuracy tests run on two subjects; the other tests on the first."""
    return request.getfixturevalue(request.param)


def _segment_points(offsets_m, offsets_j, marker_segment, edges, s):
    """Markers and joints of segment s in its frame (joint rows: parent side or child side)."""
    pts = [offsets_m[marker_segment == s]]
    pts += [offsets_j[j, 0][None] for j in np.flatnonzero(edges[:, 0] == s)]
    pts += [offsets_j[j, 1][None] for j in np.flatnonzero(edges[:, 1] == s)]
    return np.concatenate(pts)


# ------------------------------------------------------------------ rigid fit
@pytest.mark.usefixtures("float64")  # private JAX functions, as the public ones run them
def test_marker_offsets_match_truth_up_to_the_segment_frame(fitted):
    trial, truth, _, sk, _ = fitted
    assert np.array_equal(sk.edges, truth.edges) and sk.root == truth.root
    worst = 0.0
    for s in range(sk.n_segments):
        ours = _segment_points(sk.marker_offsets, sk.joint_offsets, sk.marker_segment, sk.edges, s)
        true = _segment_points(truth.marker_offsets, truth.joint_offsets, truth.marker_segment, truth.edges, s)
        # Frames differ by a rigid motion (our axes are world-aligned at the rest frame).
        rot, t = horn_align(jnp.asarray(ours), jnp.asarray(true))
        err = np.linalg.norm(ours @ np.asarray(rot).T + np.asarray(t) - true, axis=1)
        worst = max(worst, err.max())
    assert worst < 0.003


def test_marker_to_joint_distances_match_truth(fitted):
    _, truth, _, sk, _ = fitted
    for j, (p, c) in enumerate(sk.edges):
        for side, s in ((0, p), (1, c)):
            on = np.flatnonzero(sk.marker_segment == s)
            ours = np.linalg.norm(sk.marker_offsets[on] - sk.joint_offsets[j, side], axis=1)
            true = np.linalg.norm(truth.marker_offsets[on] - truth.joint_offsets[j, side], axis=1)
            np.testing.assert_allclose(ours, true, atol=0.003)


def test_bone_lengths_within_half_percent(fitted):
    _, truth, _, sk, _ = fitted
    true = {tuple(sorted(b)): length for b, length in zip(truth.bones.tolist(), truth.bone_lengths)}
    ours = {tuple(sorted(b)): length for b, length in zip(sk.bones.tolist(), sk.bone_lengths)}
    assert ours.keys() == true.keys()
    rel = np.array([abs(ours[k] - true[k]) / true[k] for k in true])
    assert rel.max() < 0.005
    # Segment length: the longest bone of the segment.
    for s, length in enumerate(sk.segment_lengths):
        on = sk.bone_segment == s
        if on.any():
            assert length == pytest.approx(sk.bone_lengths[on].max())
        else:
            assert np.isnan(length)


def test_residuals_at_noise_level_and_no_false_flags(fitted):
    trial, truth, _, sk, _ = fitted
    # What the skeleton cannot explain: noise plus soft tissue, per marker.
    present = trial.mask
    dev = np.linalg.norm(trial.positions - truth.clean_positions, axis=-1)
    actual = np.sqrt(np.nanmean(np.where(present, dev, np.nan) ** 2, axis=0))
    ratio = sk.marker_rms / actual
    # The fit absorbs part of the perturbation (3 + 3S pose unknowns per frame) but no more.
    assert 0.6 < np.median(ratio) < 1.05
    assert sk.nonrigid_markers == ()
    d = sk.diagnostics
    assert d["result"] == 0 and d["ik_failures"] == 0 and 1 <= d["sweeps"] < 30
    # stopped at a fixed point of the alternation, at its lowest cost (an accelerated
    # update may overshoot on the way and be restarted)
    assert len(d["cost_history"]) == len(d["offset_steps"]) == d["sweeps"]
    assert d["offset_steps"][-1] <= 1e-6
    assert d["cost_history"][-1] <= min(d["cost_history"]) * (1 + 1e-9)
    assert d["residual_rms"] == pytest.approx(np.sqrt(np.mean(actual**2)), rel=0.3)


def test_refinement_stops_at_the_optimum_with_lightly_weighted_joints():
    """With the joint centres weighted as fit_skeleton weighs its solved ones (0.1 of a
    marker) the pose/offset alternation creeps along the bone lengths. The default stop
    (no offset moved by more than 1 um) must be where a 10^4 times tighter run ends: bones
    and offsets within 0.1 mm. The relative-cost stop used before ended 0.3-0.9 mm away
    (seeds 0-2) and called that converged; accelerated, it is 0.01-0.03 mm."""
    body = synth.full_body(seed=1)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=1, noise=NOISE, soft_tissue=SOFT)
    joints = truth.joint_positions + np.random.default_rng(1).normal(0.0, 0.002, truth.joint_positions.shape)
    kw = dict(max_frames=FIT_FRAMES, joint_weight=SOLVED_JOINT_WEIGHT)
    sk = fit_rigid(trial, truth.marker_segment, truth.edges, joints, **kw)
    ref = fit_rigid(trial, truth.marker_segment, truth.edges, joints, xtol=1e-10, max_sweeps=1500, **kw)
    assert sk.diagnostics["result"] == ref.diagnostics["result"] == 0
    assert ref.diagnostics["sweeps"] > 2 * sk.diagnostics["sweeps"]
    np.testing.assert_allclose(sk.bone_lengths, ref.bone_lengths, rtol=0, atol=1e-4)
    np.testing.assert_allclose(sk.marker_offsets, ref.marker_offsets, rtol=0, atol=1e-4)


def test_refinement_that_runs_out_of_sweeps_says_so():
    body = synth.full_body(seed=1)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=1, noise=NOISE, soft_tissue=SOFT)
    with pytest.warns(ConvergenceWarning, match=r"max_sweeps=3 sweeps without meeting xtol"):
        sk = fit_rigid(trial, truth.marker_segment, truth.edges, truth.joint_positions, max_frames=FIT_FRAMES,
                       max_sweeps=3)
    d = sk.diagnostics
    assert d["result"] != 0 and d["sweeps"] == 3 and d["offset_steps"][-1] > 1e-6


def test_loose_marker_is_flagged():
    body = synth.full_body(seed=2)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=2, noise=NOISE)
    pos = trial.positions.copy()
    loose = trial.labels.index("LTHF")
    # The marker slides 2.5 cm back and forth on the skin, independently of the bone.
    pos[:, loose, 2] += 0.025 * np.sin(2 * np.pi * 0.7 * trial.times)
    _, _, _, sk = _fit(2, trial.replace(positions=pos), truth)
    assert sk.nonrigid_markers == ("LTHF",)
    assert sk.marker_rms[loose] > 3 * np.nanmedian(sk.marker_rms)


@pytest.mark.usefixtures("float64")  # private JAX functions, as the public ones run them
def test_segment_whose_markers_are_never_all_seen_together():
    """The paper aligns only frames showing all of a segment's markers. Here two thigh
    markers take turns (one hidden in the first half, the other in the second), so there
    is no such frame (this raised DegenerateMotionError); every frame with three points
    is used instead and each marker is placed from the frames that show it."""
    body = synth.full_body(seed=3)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=3, noise=NOISE)
    thigh = truth.segment_names.index("l_thigh")
    a, b = np.flatnonzero(truth.marker_segment == thigh)[:2]
    pos = trial.positions.copy()
    half = trial.n_frames // 2
    pos[:half, a] = np.nan
    pos[half:, b] = np.nan
    _, _, _, sk = _fit(3, trial.replace(positions=pos), truth)
    ours = _segment_points(sk.marker_offsets, sk.joint_offsets, sk.marker_segment, sk.edges, thigh)
    true = _segment_points(truth.marker_offsets, truth.joint_offsets, truth.marker_segment, truth.edges, thigh)
    rot, t = horn_align(jnp.asarray(ours), jnp.asarray(true))
    err = np.linalg.norm(ours @ np.asarray(rot).T + np.asarray(t) - true, axis=1)
    assert err.max() < 0.003, err


def test_marker_never_seen_with_its_segment_is_left_out_not_fatal():
    """A marker clustered with a segment but never in a frame with enough of that
    segment's points to place it (a sync light grouped with a hand, seen only while the
    hand's markers are hidden) used to stop the whole fit with DegenerateMotionError. It is
    left out of the skeleton with a warning, and the rest is the fit without it."""
    body = synth.full_body(seed=3)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=3, noise=NOISE)
    hand = truth.segment_names.index("l_hand")
    pos = trial.positions.copy()
    quarter = trial.n_frames // 4
    pos[-quarter:, truth.marker_segment == hand] = np.nan
    light = np.full((trial.n_frames, 1, 3), np.nan)
    light[-quarter:, 0] = [1.5, 0.2, 1.0]  # a fixed light, seen only while the hand is hidden
    with_light = trial.replace(positions=np.concatenate([pos, light], axis=1), labels=(*trial.labels, "SYNC"))
    segments = np.append(truth.marker_segment, hand)
    jp = truth.joint_positions
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="SYNC .* never seen in a frame together"):
        sk = fit_rigid(with_light, segments, truth.edges, jp, max_frames=FIT_FRAMES)
    assert sk.marker_segment[-1] == -1 and sk.diagnostics["unplaced_markers"] == ("SYNC",)
    assert np.isnan(sk.marker_offsets[-1]).all()
    without = fit_rigid(with_light, np.append(truth.marker_segment, -1), truth.edges, jp, max_frames=FIT_FRAMES)
    np.testing.assert_array_equal(sk.bone_lengths, without.bone_lengths)
    np.testing.assert_array_equal(sk.marker_offsets[:-1], without.marker_offsets[:-1])
    assert "unplaced_markers" not in without.diagnostics
    # the light as the hand's only marker, never seen with the wrist: leaving it out would
    # leave the hand no marker and one joint, so the fit still cannot place the hand
    only_light = np.append(np.where(truth.marker_segment == hand, -1, truth.marker_segment), hand)
    wrist = int(np.flatnonzero(truth.edges[:, 1] == hand)[0])
    no_wrist = jp.copy()
    no_wrist[-quarter:, wrist] = np.nan
    with pytest.raises(DegenerateMotionError, match="no frame shows enough of these points together"):
        fit_rigid(with_light, only_light, truth.edges, no_wrist, max_frames=FIT_FRAMES)


def test_fit_is_invariant_to_a_rigid_motion_of_the_data(seed0):
    trial, truth, joints, sk, _ = seed0
    rot = random_rotation(7)
    shift = np.array([0.4, -1.0, 0.25])
    moved = fit_rigid(
        trial.transformed(rot, shift), truth.marker_segment, truth.edges, joints @ rot.T + shift,
        max_frames=FIT_FRAMES,
    )
    np.testing.assert_allclose(moved.bone_lengths, sk.bone_lengths, atol=1e-7)
    np.testing.assert_allclose(moved.marker_rms, sk.marker_rms, atol=1e-7)
    # Offsets live in rest frames aligned with the world axes, so they turn with the data.
    np.testing.assert_allclose(moved.marker_offsets, sk.marker_offsets @ rot.T, atol=1e-6)
    assert moved.diagnostics["rest_frame"] == sk.diagnostics["rest_frame"]


def test_fit_rigid_rejects_bad_input(seed0):
    trial, truth, _, _, _ = seed0
    jp = truth.joint_positions
    with pytest.raises(InputError, match="marker_segment"):
        fit_rigid(trial, truth.marker_segment[:-1], truth.edges, jp)
    with pytest.raises(InputError, match="joint_positions"):
        fit_rigid(trial, truth.marker_segment, truth.edges, jp[:, :-1])
    cyclic = truth.edges.copy()
    cyclic[-1] = (cyclic[-1, 1], cyclic[0, 1])
    with pytest.raises(InputError, match="tree"):
        fit_rigid(trial, truth.marker_segment, cyclic, jp)
    for bad in (dict(xtol=0.0), dict(xtol=float("nan")), dict(xtol="1e-6"), dict(xtol=None), dict(max_sweeps=0),
                dict(max_sweeps="200"), dict(max_sweeps=2.5)):
        with pytest.raises(InputError, match="xtol must be a positive length"):
            fit_rigid(trial, truth.marker_segment, truth.edges, jp, **bad)
    for bad in (0.0, -1.0, float("inf"), "0.1", None, True):
        with pytest.raises(InputError, match="joint_weight must be a positive number"):
            fit_rigid(trial, truth.marker_segment, truth.edges, jp, joint_weight=bad)
    no_hand = truth.marker_segment.copy()
    hand = truth.segment_names.index("l_hand")
    no_hand[no_hand == hand] = -1
    with pytest.raises(DegenerateMotionError, match="no markers"):
        fit_rigid(trial, no_hand, truth.edges, jp)


# ------------------------------------------------------------------ kinematics


@pytest.mark.usefixtures("float64")  # JAX arrays and traces of the test's own, compared in float64
def test_forward_kinematics_reproduces_the_simulator():
    body = synth.random_tree(9, seed=3)
    _, truth = synth.simulate(body, "calibration", duration=0.5, seed=3)
    q = matrix_to_quat(jnp.asarray(truth.segment_rotations))
    trans, joints, markers = forward_kinematics(
        jnp.asarray(truth.segment_translations[:, truth.root]), q, jnp.asarray(truth.joint_offsets),
        jnp.asarray(truth.marker_offsets), jnp.asarray(truth.edges), jnp.asarray(truth.marker_segment),
    )
    np.testing.assert_allclose(trans, truth.segment_translations, atol=1e-12)
    np.testing.assert_allclose(joints, truth.joint_positions, atol=1e-12)
    np.testing.assert_allclose(markers, truth.clean_positions, atol=1e-12)
    chain = kinematic_chain(jnp.asarray(truth.edges))
    assert set(np.unique(np.asarray(chain.path))) <= {0.0, 1.0}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_offset_system_equals_the_per_frame_normal_equations(seed):
    """The offset update's normal equations, built from the segment pairs one observation
    joins only, equal sum_f sum_r w A^T A and A^T w (x - t_root) for the per-frame design
    ``A_fr = [coef[r, u] R_seg(u)(f)]_u`` (a random tree, markers and joints as fit_rigid
    lays them out)."""
    rng = np.random.default_rng(seed)
    n_seg = 6 + seed
    edges = np.array([[int(rng.integers(0, c)), c] for c in range(1, n_seg)])
    marker_seg = rng.integers(0, n_seg, size=2 * n_seg)
    path = kinematic_chain(edges).path  # (S, J): joints between the root and each segment
    n_m, n_j = len(marker_seg), len(edges)
    coef = np.zeros((n_m + n_j, n_m + n_j))
    coef[np.arange(n_m), np.arange(n_m)] = 1.0
    coef[:n_m, n_m:] = path[marker_seg]
    coef[n_m:, n_m:] = path[edges[:, 0]] + np.eye(n_j)
    useg = np.concatenate([marker_seg, edges[:, 0]]).astype(np.int32)
    n_f = 40
    rot = Rotation.random(n_f * n_seg, random_state=seed).as_matrix().reshape(n_f, n_seg, 3, 3)
    root = rng.normal(size=(n_f, 3))
    obs = rng.normal(size=(n_f, n_m + n_j, 3))
    w = rng.uniform(0.0, 1.0, size=(n_f, n_m + n_j)) * (rng.uniform(size=(n_f, n_m + n_j)) > 0.2)
    pairs, pair_index = rigid_sweeps.offset_pairs(coef, useg)
    assert len(pairs) < n_seg**2  # only segments on one root path meet
    with jax.enable_x64(True):
        normal, rhs, const = (np.asarray(a) for a in rigid_sweeps.offset_system(
            jnp.asarray(rot), jnp.asarray(root), jnp.asarray(obs), jnp.asarray(w), jnp.asarray(coef),
            jnp.asarray(useg), jnp.asarray(pairs), jnp.asarray(pair_index)))
    design = np.einsum("ru,fuab->fraub", coef, rot[:, useg]).reshape(n_f, n_m + n_j, 3, -1)
    want_normal = np.einsum("fr,frai,fraj->ij", w, design, design)
    want_rhs = np.einsum("fr,frai,fra->i", w, design, obs - root[:, None])
    np.testing.assert_allclose(normal, want_normal, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rhs, want_rhs, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(const, np.sum(w * np.sum((obs - root[:, None]) ** 2, -1)), rtol=1e-12)


@pytest.mark.parametrize("n_joints", [1, 2, 7, 30])
def test_host_kinematic_chain_equals_the_traced_one(n_joints):
    """numpy edges give the chain on the host (numpy arrays), equal to the jnp solve's."""
    rng = np.random.default_rng(n_joints)
    parent = [int(rng.integers(0, c)) for c in range(1, n_joints + 1)]
    edges = np.array([[p, c] for c, p in enumerate(parent, start=1)])[rng.permutation(n_joints)]
    host, traced = kinematic_chain(edges), kinematic_chain(jnp.asarray(edges))
    for field in ("edges", "parent", "path", "attach"):
        assert isinstance(getattr(host, field), np.ndarray), field
        np.testing.assert_array_equal(getattr(host, field), getattr(traced, field), err_msg=field)
    # each segment's path holds exactly the joints between it and the root
    depth = {0: 0}
    for c, p in enumerate(parent, start=1):
        depth[c] = depth[p] + 1
    np.testing.assert_array_equal(host.path.sum(axis=1), [depth[s] for s in range(n_joints + 1)])


# ------------------------------------------------------------------------ IK
def test_ik_fits_markers_to_noise_level_and_finds_the_joints(fitted):
    trial, truth, _, sk, motion = fitted
    assert motion.converged and (motion.result == 0).all()
    assert motion.rotations.shape == (trial.n_frames, sk.n_segments, 4)
    np.testing.assert_allclose(np.linalg.norm(motion.rotations, axis=-1), 1.0, atol=1e-12)
    # Per-frame residual close to the skeleton's fitting residual (same noise).
    assert np.median(motion.marker_rms) == pytest.approx(sk.diagnostics["residual_rms"], rel=0.1)
    joint_err = np.linalg.norm(motion.joint_positions - truth.joint_positions, axis=-1)
    assert np.median(joint_err) < 0.005 and joint_err.max() < 0.02
    # Joint positions are consistent with segment poses (the tree constraint).
    j = 3
    p, c = sk.edges[j]
    r_parent = Rotation.from_quat(motion.rotations[:, p], scalar_first=True).as_matrix()
    via_parent = np.einsum("fab,b->fa", r_parent, sk.joint_offsets[j, 0]) + motion.segment_translations[:, p]
    np.testing.assert_allclose(via_parent, motion.joint_positions[:, j], atol=1e-9)
    np.testing.assert_allclose(motion.segment_translations[:, c], motion.joint_positions[:, j], atol=1e-9)


def test_single_marker_gaps_are_reconstructed(seed0):
    trial, truth, _, sk, _ = seed0
    rng = np.random.default_rng(11)
    pos = trial.positions.copy()
    gap = np.zeros(trial.mask.shape, bool)
    one_second = int(trial.rate)
    for m in rng.choice(trial.n_markers, 12, replace=False):
        start = rng.integers(0, trial.n_frames - one_second)
        gap[start : start + one_second, m] = True
    pos[gap] = np.nan
    motion = inverse_kinematics(sk, trial.replace(positions=pos))
    err = np.linalg.norm(motion.fitted_markers - truth.clean_positions, axis=-1)
    for m in np.flatnonzero(gap.any(axis=0)):
        assert np.sqrt(np.mean(err[gap[:, m], m] ** 2)) < 0.010
    assert np.isfinite(motion.fitted_markers).all()


def test_gap_filling_never_trades_a_marker_fit_for_the_interpolation():
    """A 4 s take of the 3-segment linkage with overlapping gaps: the middle segment is not
    fully seen for 114 of 480 frames, its neighbours for 72 and 130, and the markers left
    still place it. Slerping across such gaps in fast motion can start the gap pass in a
    wrong basin; it used to be kept unconditionally (22 frames with a joint 86-89 mm off
    and 3-33 mm marker RMS, where the pose without gap filling fits to ~1 mm). Both poses
    are of the markers as measured (``ik_lowpass=None``: the filter is not under test)."""
    trial, truth = synth.simulate(synth.linkage(), duration=4.0, seed=35, noise=0.001, gaps=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial, ik_lowpass=None)
    filled = result.motion
    held = inverse_kinematics(result.skeleton, result.trial, fill_gaps=False)
    assert (~filled.segment_observed).sum(axis=0).min() > 50
    assert np.all(filled.marker_rms <= held.marker_rms + 2e-4)
    names = {frozenset(map(int, e)): j for j, e in enumerate(truth.edges)}
    seg = segment_map(result, trial, truth)
    for j, (p, c) in enumerate(result.edges):
        err = np.linalg.norm(filled.joint_positions[:, j] - truth.joint_positions[:, names[frozenset((seg[p], seg[c]))]], axis=-1)
        assert err.max() < 0.015, (j, err.max())


def test_whole_segment_gap_is_interpolated(seed0):
    trial, truth, _, sk, _ = seed0
    foot = truth.segment_names.index("r_foot")
    pos = trial.positions.copy()
    gap = np.zeros(trial.mask.shape, bool)
    gap[500:620, truth.marker_segment == foot] = True
    pos[gap] = np.nan
    filled = inverse_kinematics(sk, trial.replace(positions=pos))
    held = inverse_kinematics(sk, trial.replace(positions=pos), fill_gaps=False)
    assert not filled.segment_observed[500:620, foot].any() and filled.segment_observed[:500, foot].all()
    err_filled = np.linalg.norm(filled.fitted_markers - truth.clean_positions, axis=-1)[gap]
    err_held = np.linalg.norm(held.fitted_markers - truth.clean_positions, axis=-1)[gap]
    # Slerp between the gap's ends beats falling back to the rest-pose relative rotation.
    assert err_filled.max() < 0.7 * err_held.max()
    # No jump into or out of the gap: the frame-to-frame displacement of the foot markers
    # at both ends matches the true one up to noise.
    on_foot = truth.marker_segment == foot
    for f in (499, 619):
        step = filled.fitted_markers[f + 1, on_foot] - filled.fitted_markers[f, on_foot]
        true_step = truth.clean_positions[f + 1, on_foot] - truth.clean_positions[f, on_foot]
        assert np.linalg.norm(step - true_step, axis=-1).max() < 0.01


def test_gaps_at_a_junction_of_trials_fitted_together_are_filled_within_each_trial(seed0):
    """Two recordings concatenated (``combine_trials``; frames 0-599 and 900-1199) with the
    right foot hidden over the last 40 frames of the first and the first 40 of the second.
    Each side holds its own recording's nearest foot pose; before, the gap was slerped
    from one recording's pose to the other's, across a junction that is not motion."""
    trial, truth, _, sk, _ = seed0
    foot = truth.segment_names.index("r_foot")
    on_foot = truth.marker_segment == foot
    parts = []
    for frames, hidden in ((slice(0, 600), slice(560, 600)), (slice(900, 1200), slice(0, 40))):
        part = trial.select_frames(frames)
        pos = part.positions.copy()
        pos[hidden, on_foot] = np.nan
        parts.append(part.replace(positions=pos))
    frames = np.r_[0:600, 900:1200]
    both = combine_trials(parts)
    assert both.metadata["trial_bounds"] == ((0, 600), (600, 900))
    motion = inverse_kinematics(sk, both)
    gap = np.r_[560:640]
    assert not motion.segment_observed[gap, foot].any()
    # the foot's rotation relative to its parent: held at the last/first seen frame of its trial
    parent = int(np.asarray(sk.parent)[foot])
    rel = Rotation.from_quat(motion.rotations[:, parent], scalar_first=True).inv() * Rotation.from_quat(
        motion.rotations[:, foot], scalar_first=True
    )
    for side, seen in ((np.r_[560:600], 559), (np.r_[600:640], 640)):
        drift = np.degrees((rel[side] * rel[seen].inv()).magnitude())
        assert drift.max() < 0.5, drift.max()
    # the held pose is that trial's own: the first hidden frames of each side are close to the truth
    err = np.linalg.norm(motion.fitted_markers[:, on_foot] - truth.clean_positions[frames][:, on_foot], axis=-1)
    assert err[[560, 639]].max() < 0.02, err[[560, 639]]
    with pytest.raises(InputError, match="trial_bounds"):
        inverse_kinematics(sk, both, trial_bounds=[(0, 600), (601, 900)])


def test_ik_is_equivariant_and_ignores_marker_order(seed0):
    trial, _, _, sk, motion = seed0
    rot = random_rotation(5)
    shift = np.array([1.0, 2.0, -0.5])
    moved = inverse_kinematics(sk, trial.transformed(rot, shift))
    np.testing.assert_allclose(moved.joint_positions, motion.joint_positions @ rot.T + shift, atol=1e-6)
    np.testing.assert_allclose(moved.marker_rms, motion.marker_rms, atol=1e-8)
    order = np.random.default_rng(3).permutation(trial.n_markers)
    shuffled = inverse_kinematics(sk, trial.select_markers(order))
    np.testing.assert_allclose(shuffled.joint_positions, motion.joint_positions, atol=1e-9)
    assert shuffled.marker_labels == sk.marker_labels


def test_ik_batches_over_a_leading_trial_axis(seed0):
    trial, _, _, sk, motion = seed0
    x = trial.select_markers(list(sk.marker_labels)).positions
    half = x.shape[0] // 2
    both = inverse_kinematics(sk, np.stack([x[:half], x[half : 2 * half]]), rate=trial.rate)
    assert both.joint_positions.shape == (2, half, sk.n_joints, 3)
    # Frames are solved independently (no gaps here), so each half matches the whole-trial fit.
    np.testing.assert_allclose(both.joint_positions[0], motion.joint_positions[:half], atol=1e-8)
    np.testing.assert_allclose(both.joint_positions[1], motion.joint_positions[half : 2 * half], atol=1e-8)
    fitted_trial = motion.fitted_trial()
    assert fitted_trial.n_frames == trial.n_frames and fitted_trial.labels == sk.marker_labels
    np.testing.assert_array_equal(fitted_trial.positions, motion.fitted_markers)


def test_frames_in_a_wrong_basin_are_solved_again(monkeypatch):
    # Two markers per segment, posed on the true skeleton. Aligning each segment on its
    # two markers alone (one Horn pass) leaves its twist free, and some frames' solve
    # settles with a limb folded the wrong way; the start's later passes (the proximal
    # joint placed by the parent) avoid that, and re-solving from the neighbours'
    # pose repairs it.
    body = synth.full_body(seed=0, markers_per_segment=2)
    trial, truth = synth.simulate(body, "calibration", duration=DURATION, seed=0, noise=0.001)
    n_seg = len(truth.segment_names)
    skeleton = Skeleton(
        n_segments=n_seg, edges=truth.edges, root=truth.root, marker_labels=trial.labels,
        marker_segment=truth.marker_segment, marker_offsets=truth.marker_offsets,
        joint_offsets=truth.joint_offsets, bones=truth.bones, bone_lengths=truth.bone_lengths,
        bone_segment=truth.bone_segment, segment_lengths=np.full(n_seg, np.nan),
        marker_rms=np.zeros(trial.n_markers), nonrigid_markers=(), diagnostics={},
    )

    def worst_joint_error():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)  # wrong basins are also slow ones
            motion = inverse_kinematics(skeleton, trial)
        return np.linalg.norm(motion.joint_positions - truth.joint_positions, axis=-1).max()

    # Knocking out the two repairs (the later Horn passes of the start, the re-solve of
    # suspect frames) is the only way to show that each is needed: both are module
    # constants of this stage, not arguments of inverse_kinematics.
    monkeypatch.setattr(ik_module, "RESEED_FACTOR", np.inf)
    assert worst_joint_error() < 0.01  # the default start finds the right basin everywhere
    monkeypatch.setattr(ik_batch, "HORN_PASSES", 1)
    assert worst_joint_error() > 0.05  # markers-only start, no re-solving: limbs folded
    monkeypatch.setattr(ik_module, "RESEED_FACTOR", 2.0)
    assert worst_joint_error() < 0.01


def test_rigid_refinement_and_ik_use_one_slot_layout(monkeypatch):
    # fit_rigid's sweeps (joint centres as extra observed points, inside the refinement's
    # device program) and the IK of the fitted skeleton must hand solve_chunk one set of
    # shapes: the IK's reserved joint slot is what lets the final IK pose the skeleton in
    # the layout the refinement fitted it in (and keeps the IK's own program to one shape).
    body = synth.full_body(seed=2)
    trial, truth = synth.simulate(body, "calibration", duration=3.0, seed=2, noise=NOISE)
    shapes = set()
    real = ik_batch.solve_chunk

    def recording(model, *args, **kwargs):
        leaves = jax.tree.leaves((model, args))
        shapes.add(tuple((np.shape(a), np.result_type(a).str) for a in leaves) + (model.width,))
        return real(model, *args, **kwargs)

    # A spy (it records the shapes and calls through): the only way to see which shapes
    # the stage hands its one compiled solver, short of timing the compilations.
    monkeypatch.setattr(ik_batch, "solve_chunk", recording)
    # Segments with 2-4 markers, the root with 4 and a segment of 4 off the root:
    # the IK's reserved joint slot is what lets the shapes agree.
    counts = np.bincount(truth.marker_segment)
    assert counts[truth.root] == counts.max() and (np.delete(counts, truth.root) == counts.max()).any()
    skeleton = fit_rigid(trial, truth.marker_segment, truth.edges, truth.joint_positions, max_frames=100)
    assert len(shapes) == 1
    slots, _ = ik_batch.solver_shape(skeleton.marker_segment, skeleton.edges, skeleton.marker_segment.shape[0])
    inverse_kinematics(skeleton, trial, slots=slots)  # as fit_skeleton calls it
    assert len(shapes) == 1
    inverse_kinematics(skeleton, trial)  # on its own: no idle slot
    assert len(shapes) == 2


@pytest.mark.usefixtures("float64")  # private JAX functions, as the public ones run them
def test_joint_centres_observed_on_the_child_or_the_parent_give_the_same_poses(seed0):
    # The refinement observes a joint centre at its child's proximal end (marker offset 0
    # on the child); that is the point the parent's joint offset puts it at, so the IK
    # solution must be the one it had with the joint observed on the parent. Both start
    # from the IK's poses with their relative rotations as the prior (a Horn start
    # differs between the two layouts, and with it the prior's target).
    trial, truth, joints, sk, motion = seed0
    n_m, n_j = sk.marker_offsets.shape[0], sk.edges.shape[0]
    frames = slice(0, 64 * 3)
    obs = np.concatenate([trial.positions[frames], joints[frames]], axis=1)
    present = np.concatenate([trial.mask[frames], np.ones((obs.shape[0], n_j), bool)], axis=1)
    weight = np.concatenate([np.ones(n_m), np.full(n_j, 0.1**2)])
    j_th = sk.joint_offsets[:, 0]
    solutions = []
    for on_child in (False, True):
        side = sk.edges[:, 1] if on_child else sk.edges[:, 0]
        offsets = np.concatenate([sk.marker_offsets, np.zeros_like(j_th) if on_child else j_th])
        model = ik_batch.batch_model(
            sk.edges, np.stack([j_th, np.zeros_like(j_th)], axis=1), offsets,
            np.concatenate([sk.marker_segment, side]), weight,
        )
        q0 = motion.rotations[frames]
        solutions.append(ik_batch.solve(
            model, obs, present, motion.root_position[frames], q0, ik_module._host_relative(q0, np.asarray(sk.parent)),
            np.full(sk.n_segments, 0.01), max_steps=100, threads=1,
        ))
    on_parent, on_child = solutions
    assert on_parent["done"].all() and on_child["done"].all()
    np.testing.assert_allclose(on_child["rms"], on_parent["rms"], rtol=1e-6)
    np.testing.assert_allclose(on_child["joint_positions"], on_parent["joint_positions"], atol=1e-6)
    dots = np.abs(np.sum(on_child["rotations"] * on_parent["rotations"], axis=-1))
    assert dots.min() > 1.0 - 1e-10


def test_ik_warm_start_from_a_previous_motion(seed0):
    trial, _, _, sk, motion = seed0
    again = inverse_kinematics(sk, trial, init=motion)
    # Same optimum up to the stopping tolerance (micrometres, in weakly determined twists).
    np.testing.assert_allclose(again.joint_positions, motion.joint_positions, atol=1e-5)
    assert again.steps.mean() < motion.steps.mean()


def test_ik_rejects_wrong_markers(seed0):
    trial, _, _, sk, _ = seed0
    with pytest.raises(InputError, match="lacks"):
        inverse_kinematics(sk, trial.drop_markers(["LASI"]))
    with pytest.raises(InputError, match="markers"):
        inverse_kinematics(sk, trial.positions[:, :-1])
    for bad in (dict(batch_size=0), dict(max_steps=-1), dict(threads=0)):
        with pytest.raises(InputError, match=next(iter(bad))):
            inverse_kinematics(sk, trial, **bad)


@pytest.mark.usefixtures("float64")  # JAX arrays and traces of the test's own, compared in float64
def test_ik_gradients_match_finite_differences():
    body = synth.full_body(seed=4)
    trial, truth = synth.simulate(body, "calibration", duration=0.2, seed=4, noise=NOISE)
    x, mask = trial.to_arrays()
    f = 7
    xs, ms = jnp.asarray(x[f]), jnp.asarray(mask[f])
    edges, seg = jnp.asarray(truth.edges), jnp.asarray(truth.marker_segment)
    q_start = matrix_to_quat(jnp.asarray(truth.segment_rotations[f + 3]))  # a nearby pose
    t_start = jnp.asarray(truth.segment_translations[f + 3, truth.root])
    weights = jnp.asarray(np.random.default_rng(0).normal(size=(truth.edges.shape[0], 3)))

    def objective(xs, joint_offsets, marker_offsets):
        sol = ik_solve(xs, ms, joint_offsets, marker_offsets, edges, seg, t_start, q_start, prior_weight=0.01)
        _, joints, _ = forward_kinematics(sol.root_position, sol.rotations, joint_offsets, marker_offsets, edges, seg)
        return jnp.sum(weights * joints)

    args = (xs, jnp.asarray(truth.joint_offsets), jnp.asarray(truth.marker_offsets))
    value_and_grad = jax.jit(jax.value_and_grad(objective, argnums=(0, 1, 2)))
    value, grads = value_and_grad(*args)
    assert np.isfinite(value)
    rng = np.random.default_rng(1)
    eps = 1e-5
    for k in range(3):
        direction = rng.normal(size=args[k].shape)
        if k == 0:
            direction = direction * np.asarray(mask[f])[:, None]  # hidden markers do not count
        plus = list(args)
        minus = list(args)
        plus[k] = args[k] + eps * direction
        minus[k] = args[k] - eps * direction
        fd = (value_and_grad(*plus)[0] - value_and_grad(*minus)[0]) / (2 * eps)
        assert float(jnp.sum(grads[k] * direction)) == pytest.approx(float(fd), rel=1e-4, abs=1e-7)
    # A hidden marker has no influence.
    assert np.abs(np.asarray(grads[0])[~np.asarray(mask[f])]).max(initial=0.0) == 0.0
