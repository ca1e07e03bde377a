"""Joint centres refitted fixed in a segment's frame (jaxskel.joints._anchored_centres).

Two segments with known geometry: ``A`` carries four nearly coplanar markers (a pelvis's
waist markers), the joint lies 12 cm off their plane, ``B`` carries three markers. The
per-frame centres handed in are wrong in known ways; the refit must correct what the
motion determines and leave alone what it does not.
"""

import numpy as np
import pytest
from helpers import random_rotation, rotvec_to_matrix

import jaxskel
from jaxskel import synth
from jaxskel.joints._anchored_centres import MIN_EXERCISE_DEG, anchored_centres

A_MARKERS = np.array([[0.12, 0.08, 0.0], [-0.12, 0.08, 0.003], [0.12, -0.08, -0.002], [-0.12, -0.08, 0.0]])
JOINT_IN_A = np.array([0.08, 0.0, -0.12])
B_MARKERS = np.array([[0.03, 0.02, -0.22], [-0.04, 0.05, -0.40], [0.05, -0.03, -0.12]])  # relative to the joint


def _recording(rel_rotvecs, *, noise=0.001, seed=0):
    """World markers (F, 7, 3), true joint (F, 3), A's rotations (F, 3, 3)."""
    rng = np.random.default_rng(seed)
    n = len(rel_rotvecs)
    t = np.linspace(0.0, 1.0, n)
    # A turns slowly about a drifting axis and walks; B turns relative to A
    rot_a = np.stack([rotvec_to_matrix(np.array([0.3 * np.sin(3 * s), 0.2 * np.cos(2 * s), 2.0 * s])) for s in t])
    trans_a = np.stack([2.0 * t, 0.5 * np.sin(4 * t), 0.9 + 0.02 * np.sin(9 * t)], axis=1)
    rot_b = rot_a @ np.stack([rotvec_to_matrix(v) for v in rel_rotvecs])
    joint = np.einsum("fij,j->fi", rot_a, JOINT_IN_A) + trans_a
    xa = np.einsum("fij,kj->fki", rot_a, A_MARKERS) + trans_a[:, None]
    xb = np.einsum("fij,kj->fki", rot_b, B_MARKERS) + joint[:, None]
    x = np.concatenate([xa, xb], axis=1) + rng.normal(0.0, noise, (n, 7, 3))
    return x, joint, rot_a


def _refit(x, centres):
    seg = np.array([0, 0, 0, 0, 1, 1, 1])
    return anchored_centres(x, np.ones(x.shape[:2], bool), seg, np.array([[0, 1]]), centres[:, None])


def _ball(n, amplitude, seed):
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 3)
    s = np.linspace(0, 6 * np.pi, n)[:, None]
    return amplitude * np.sin(s * np.array([1.0, 1.7, 0.6]) + phase)


@pytest.mark.parametrize("seed", [0, 1])
def test_ball_joint_off_the_anchor_plane_is_recovered(seed):
    """Per-frame centres lying in the plane of A's markers (12 cm off, the CMU hips'
    failure) move back to the true centre."""
    x, joint, rot_a = _recording(_ball(600, 0.5, seed), seed=seed)
    biased = joint + np.einsum("fij,j->fi", rot_a, [0.0, 0.0, 0.12])
    out = _refit(x, biased)
    assert out.moved[0]
    assert out.shift[0] == pytest.approx(0.12, abs=0.01)
    err = np.linalg.norm(out.joint_positions[:, 0] - joint, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.003
    assert out.result[0] == 0 and out.steps[0] > 0
    k = np.argmax(np.abs(out.displacement[0]))  # the 12 cm move is resolved many times over
    assert abs(out.displacement[0, k]) > 5 * out.resolution[0, k]


def test_hinge_axis_direction_is_left_alone():
    """About a hinge the centre is free along the axis: the refit corrects the error
    across the axis and keeps the per-frame estimate along it."""
    axis = np.array([0.0, 1.0, 0.2]) / np.linalg.norm([0.0, 1.0, 0.2])
    angles = 0.8 * np.sin(np.linspace(0, 8 * np.pi, 600)) + 0.6
    x, joint, rot_a = _recording(angles[:, None] * axis)
    across = np.cross(axis, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    bias_local = 0.05 * axis + 0.03 * across
    out = _refit(x, joint + np.einsum("fij,j->fi", rot_a, bias_local))
    assert out.moved[0]
    err_local = np.einsum("fji,fj->fi", rot_a, out.joint_positions[:, 0] - joint)
    # along the axis: unchanged (up to the per-frame noise of A's marker-only pose)
    assert abs(np.median(err_local @ axis) - 0.05) < 0.001
    off_axis = err_local - np.outer(err_local @ axis, axis)
    assert np.sqrt(np.mean(np.sum(off_axis**2, axis=1))) < 0.003  # across: corrected


def test_the_weakest_direction_is_read_against_the_markers():
    """radial_cosines: a hinge leaves its centre loose along its axis, across the lines to
    B's markers (measured 0.25); a short arc about every axis leaves it loose along them,
    their distance from the centre (0.96)."""
    axis = np.array([0.0, 1.0, 0.2]) / np.linalg.norm([0.0, 1.0, 0.2])
    angles = 0.8 * np.sin(np.linspace(0, 8 * np.pi, 600)) + 0.6
    x, joint, _ = _recording(angles[:, None] * axis)
    hinge = _refit(x, joint)
    x, joint, _ = _recording(_ball(600, 0.1, 3), noise=0.002, seed=3)
    arc = _refit(x, joint)
    for out in (hinge, arc):
        assert out.resolution[0, 0] > 0.1 and np.all((out.radial_cosines >= 0) & (out.radial_cosines <= 1))
    assert hinge.radial_cosines[0, 0] < 0.4 and arc.radial_cosines[0, 0] > 0.9


def test_barely_exercised_joint_is_not_moved():
    """A joint turning 1 degree RMS with 3 mm noise: the fixed-centre minimum is not
    localised, and the per-frame centres (here the truth plus 5 mm) are kept."""
    x, joint, rot_a = _recording(_ball(600, 0.025, 3), noise=0.003, seed=3)
    given = joint + np.einsum("fij,j->fi", rot_a, [0.005, 0.0, 0.0])
    out = _refit(x, given)
    assert not out.moved[0]
    np.testing.assert_allclose(out.joint_positions[:, 0], given)
    assert np.any(np.abs(out.displacement[0]) < out.resolution[0])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_joint_without_relative_motion_is_not_moved_by_skin_sway(seed):
    """A standing trial: the segments turn 0.3-0.6 degrees relative to each other and B's
    markers sway 3 mm on the skin. The fixed-centre minimum then lies 6-24 cm away,
    several resolutions out (Hamner's static trial: 1023 mm), because the misfit is
    0.5 mm noise. The sweep angle flags the joint as not
    exercised and the per-frame centres are kept."""
    x, joint, rot_a = _recording(_ball(300, 0.005, seed), noise=0.0005, seed=seed)
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, (1, 3, 3))
    x[:, 4:] += 0.003 * np.sin(np.linspace(0, 2 * np.pi, 300)[:, None, None] + phase)
    out = _refit(x, joint)
    assert 0.1 < out.exercise[0] < MIN_EXERCISE_DEG, out.exercise
    assert np.any(np.abs(out.displacement[0]) > 2 * out.resolution[0])  # what the guard overrules
    assert not out.moved[0] and out.shift[0] == 0.0
    np.testing.assert_allclose(out.joint_positions[:, 0], joint)
    # the same recording with the joint exercised (0.5 rad) is refitted, sway and all
    x, joint, rot_a = _recording(_ball(300, 0.5, seed), noise=0.0005, seed=seed)
    out = _refit(x, joint + np.einsum("fij,j->fi", rot_a, [0.0, 0.0, 0.05]))
    assert out.exercise[0] > 10.0 and out.moved[0]
    assert np.sqrt(np.mean(np.sum((out.joint_positions[:, 0] - joint) ** 2, axis=1))) < 0.003


def test_refit_is_invariant_to_a_rigid_motion_of_the_recording():
    x, joint, rot_a = _recording(_ball(600, 0.5, 0))
    biased = joint + np.einsum("fij,j->fi", rot_a, [0.0, 0.0, 0.12])
    rot, shift = random_rotation(7), np.array([3.0, -1.0, 0.5])
    out = _refit(x, biased)
    moved = _refit(x @ rot.T + shift, biased @ rot.T + shift)
    np.testing.assert_allclose(moved.joint_positions[:, 0], out.joint_positions[:, 0] @ rot.T + shift, atol=1e-4)
    np.testing.assert_allclose(moved.shift, out.shift, atol=1e-4)


def test_segments_without_a_frame_keep_the_per_frame_centres():
    """With two markers on each side neither segment has a pose: nothing is refitted."""
    x, joint, _ = _recording(_ball(300, 0.5, 0))
    seg = np.array([0, 0, -1, -1, 1, 1, -1])
    out = anchored_centres(x, np.ones(x.shape[:2], bool), seg, np.array([[0, 1]]), joint[:, None] + 0.1)
    assert out.anchor[0] == -1 and not out.moved[0]
    np.testing.assert_allclose(out.joint_positions[:, 0], joint + 0.1)


def test_fit_skeleton_reports_the_refit_and_accepts_the_paper_mode():
    """The pipeline's default refits the joints (reported per joint); ``"per_frame"`` is
    the paper's and reports nothing; both give the 3-link chain's rods to 0.3 %."""
    trial, truth = synth.simulate(synth.linkage(), duration=10.0, seed=1, noise=0.001)
    lengths = {}
    for mode in ("anchored", "per_frame"):
        result = jaxskel.fit_skeleton(trial, 3, ik=False, joint_centres=mode)
        lengths[mode] = result.skeleton.bone_lengths
        report = result.skeleton.diagnostics.get("anchored")
        if mode == "per_frame":
            assert report is None
            continue
        assert report["anchor"].shape == (2,) and np.all(report["anchor"] >= 0)
        assert np.all(report["result"] == 0) and report["resolution"].shape == (2, 3)
    middle = truth.bone_lengths[np.argmax(truth.bone_lengths)]  # compare the longest bone
    for mode, got in lengths.items():
        assert abs(np.max(got) - middle) / middle < 0.003, (mode, got, truth.bone_lengths)
    with pytest.raises(jaxskel.InputError, match="joint_centres"):
        jaxskel.fit_skeleton(trial, 3, joint_centres="fixed")


@pytest.mark.usefixtures("float64")  # private JAX functions, as anchored_centres runs them
def test_one_problem_per_call_gives_the_batched_answers(monkeypatch):
    """On a CPU each (joint, anchor) problem is its own call, since a vmapped while loop
    charges every member its slowest member's steps; the answers must be the batched
    call's (what an accelerator runs)."""
    import jaxskel.joints._anchored_centres as module

    trial, truth = synth.simulate(synth.full_body(seed=0), duration=8.0, seed=0, noise=0.002, soft_tissue=0.002)
    seen = []
    solve_all = module._solve_all
    # A spy, kept because it is the only way to get the problems anchored_centres builds
    # (inline, from its inputs) without copying that code here: it records them and calls
    # through, so the refit itself is unchanged.
    monkeypatch.setattr(
        module, "_solve_all", lambda problems, one_per_call=None: seen.append(problems) or solve_all(problems)
    )
    x, mask = trial.to_arrays()
    jp = truth.joint_positions + np.random.default_rng(0).normal(0.0, 0.003, truth.joint_positions.shape)
    anchored_centres(x, mask, truth.marker_segment, truth.edges, jp)
    (problems,) = seen
    alone = solve_all(problems, one_per_call=True)
    together = solve_all(problems, one_per_call=False)
    assert all(a.shape == b.shape and a.shape[0] == len(problems) for a, b in zip(alone, together))
    assert len(problems) >= truth.n_joints  # every joint has an anchor with three markers
    ok = (alone[4] == 0) & (together[4] == 0)
    assert ok.all()
    np.testing.assert_allclose(alone[0], together[0], rtol=0, atol=1e-6)  # c*, metres
    np.testing.assert_allclose(alone[2], together[2], rtol=1e-6, atol=1e-12)  # C(c*)
    np.testing.assert_allclose(alone[5], together[5], rtol=1e-4)  # Hessian eigenvalues
