"""Parameterisation (Sar Dessai et al. 2006, §4) against synthetic joints with known axes."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from calibration_motions import main_movements, perturbed, rotvec_to_matrix, truth_arrays
from helpers import matrix_to_quat
from matplotlib.figure import Figure

from jaxskel import DegenerateMotionWarning, InputError, synth

from jaxskel.plots import plot_angles, plot_joint_spheres, plot_speed_histograms
from jaxskel.sd06 import Normalization, Parameterization, normalize_arrays, parameterize, parameterize_arrays
from jaxskel._runtime.precision import float64_scope
from jaxskel.sd06._parameterize import parameterize_normalized as _parameterize_normalized
from jaxskel.sd06._parameterize import write_parameters

# private: it runs inside the float64 scope of parameterize(), which calls it
parameterize_normalized = float64_scope(_parameterize_normalized)

RATE = 30.0  # main_movements at 30 Hz: 420 frames, the bucket of tests/sd06/test_normalize.py
BODY = synth.full_body(seed=0)
KIND = np.array(BODY.joint_types)
HINGES = np.flatnonzero(KIND == "hinge")
UNIVERSALS = np.flatnonzero(KIND == "universal")
NAMES = BODY.joint_names


def calibration(noise_deg: float, seed: int = 0, body: synth.Body = BODY):
    angles, root_rot, root_trans = main_movements(body, rate=RATE, seed=seed)
    joints, quats, rot, trans = truth_arrays(body, angles, root_rot, root_trans)
    if noise_deg:
        joints, quats, rot, trans = perturbed(body, rot, trans, np.random.default_rng(seed), noise_deg)
    norm = normalize_arrays(joints, body.edges, quats, root=body.root, segment_translations=trans)
    return SimpleNamespace(angles=angles, joints=joints, quats=quats, rot=rot, trans=trans, norm=norm)


def true_axes(norm: Normalization, j: int, body: synth.Body = BODY) -> np.ndarray:
    """The generator's axes of joint j in the parent joint (limb) frame."""
    return body.joint_axes[j] @ norm.limb_frames_local[body.edges[j, 0]]


def axis_errors_deg(param: Parameterization, j: int, body: synth.Body = BODY) -> np.ndarray:
    """Angle from each true axis to the nearest extracted axis (axes have no sign)."""
    est = param.axes[j, : param.n_axes[j]]
    cos = np.abs(true_axes(param.normalization, j, body) @ est.T).max(axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def frame_axis_deviation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("...ij,...ij->...j", a, b), -1.0, 1.0)))


@pytest.fixture(scope="module")
def clean():
    rec = calibration(0.0)
    rec.param = parameterize_normalized(rec.norm)
    return rec


@pytest.fixture(scope="module")
def noisy():
    """IK-like noise: 0.3 deg random rotation on every segment, joints kept consistent; three seeds."""
    recs = [calibration(0.3, seed) for seed in (1, 2, 3)]
    for rec in recs:
        rec.params = {m: parameterize_normalized(rec.norm, method=m) for m in ("joining", "pca", "em")}
    return recs


# ------------------------------------------------------------------ axes
def test_one_axis_for_hinges_two_otherwise(clean, noisy):
    expected = np.where(KIND == "hinge", 1, 2)
    for param in [clean.param] + [rec.params["joining"] for rec in noisy]:
        np.testing.assert_array_equal(param.n_axes, expected)
        assert np.all(np.linalg.norm(param.axes[HINGES, 1], axis=-1) == 0)


def test_axes_of_hinge_and_universal_joints(clean, noisy):
    """Extracted axes within 3 degrees of the generator's (exact on clean data)."""
    for j in [*HINGES, *UNIVERSALS]:
        assert axis_errors_deg(clean.param, j).max() < 0.01, NAMES[j]
    errors = np.array([[axis_errors_deg(rec.params["joining"], j).max() for j in [*HINGES, *UNIVERSALS]] for rec in noisy])
    print(f"joining, 0.3 deg noise: axis error mean {errors.mean():.2f}, max {errors.max():.2f} deg")
    assert errors.max() < 3.0


def test_direction_joining_compared_with_pca_and_em(noisy):
    """The paper's comparison (§4.2) on noisy calibrations: PCA misses one-sided movements."""
    joints = [*HINGES, *UNIVERSALS]
    table = {
        m: np.array([[axis_errors_deg(rec.params[m], j).max() for j in joints] for rec in noisy])
        for m in ("joining", "pca", "em")
    }
    print("\nmax axis error per joint over 3 seeds (deg)")
    print("method   " + " ".join(f"{NAMES[j]:>8}" for j in joints))
    for m, err in table.items():
        print(f"{m:8} " + " ".join(f"{e:8.2f}" for e in err.max(axis=0)))
    assert table["joining"].max() < 3.0
    # PCA's orthogonal principal directions miss the ankle's two movements from rest,
    # each performed one way only; EM, started from PCA, usually repairs it here.
    assert table["pca"].max() > 10.0
    assert table["joining"].mean() < table["pca"].mean()
    for rec in noisy:
        em = rec.params["em"]
        assert em.converged.all() and np.all(em.steps >= 1)


# ------------------------------------------------------------------ angles
def test_angles_match_the_generator(clean):
    """Hinge: the angle up to sign and rest offset; universal: (child-fixed, parent-fixed) angles."""
    param = clean.param
    for j in HINGES:
        sign = np.sign(param.axes[j, 0] @ true_axes(param.normalization, j)[0])
        theta = clean.angles[j][:, 0]
        expected = sign * (theta - theta[param.rest_frame[j]])
        np.testing.assert_allclose(param.angles[:, j, 0], expected, atol=1e-7)
    for j in UNIVERSALS:
        # The calibration moves one axis at a time from the default pose, so the angle
        # about each extracted axis is the generator's angle about the matching true axis
        # (and the order of the two is unobservable: either is exact).
        axes = true_axes(param.normalization, j)
        np.testing.assert_allclose(clean.angles[j][param.rest_frame[j]], 0.0, atol=1e-12)
        for k in range(2):
            match = np.argmax(np.abs(axes @ param.axes[j, k]))
            sign = np.sign(axes[match] @ param.axes[j, k])
            np.testing.assert_allclose(param.angles[:, j, k], sign * clean.angles[j][:, match], atol=1e-7)
    np.testing.assert_allclose(param.angles[:, [*HINGES, *UNIVERSALS], 2], 0.0, atol=1e-7)  # no twist
    assert param.residual.max() < 1e-7


def test_reposing_reproduces_the_motion(clean, noisy):
    """Paper §5: 1.3 mm mean position deviation, 18.7 deg twist (axis) deviation."""
    pose = clean.param.pose()
    np.testing.assert_allclose(pose.joint_positions, clean.joints, atol=1e-9)
    np.testing.assert_allclose(pose.limb_frames, clean.norm.limb_frames, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum("fsi,fsi->fs", pose.rotations, clean.quats)), 1.0, atol=1e-9)
    np.testing.assert_allclose(pose.segment_translations, clean.trans, atol=1e-9)
    for rec in noisy:
        param = rec.params["joining"]
        pose = param.pose()
        position = np.linalg.norm(pose.joint_positions - rec.joints, axis=-1)
        axes = frame_axis_deviation_deg(pose.limb_frames, rec.norm.limb_frames)
        print(f"re-posed: positions {1000 * position.mean():.2f} mm mean, axes {axes.mean():.2f} deg mean")
        assert position.mean() < 1e-3
        assert axes.mean() < 5.0
        # What is lost is the off-axis part of hinge motion (noise): the residual says so.
        assert np.degrees(param.residual[:, HINGES].mean()) < 1.0
        np.testing.assert_allclose(param.residual[:, UNIVERSALS], 0.0, atol=1e-7)


def test_editing_an_angle_poses_the_skeleton(clean):
    """Editing the elbow's angle or the wrist's second angle = the generator with that angle changed."""
    param = clean.param
    elbow, wrist = NAMES.index("l_elbow"), NAMES.index("l_wrist")
    edited = param.angles.copy()
    edited[:, elbow, 0] += 0.3
    edited[:, wrist, 1] -= 0.2
    pose = param.pose(edited)
    angles = [a.copy() for a in clean.angles]
    norm = param.normalization
    angles[elbow][:, 0] += 0.3 * np.sign(param.axes[elbow, 0] @ true_axes(norm, elbow)[0])
    angles[wrist][:, 0] -= 0.2 * np.sign(param.axes[wrist, 1] @ true_axes(norm, wrist)[0])
    root_rot, root_trans = clean.rot[:, BODY.root], clean.trans[:, BODY.root]
    joints, _, _, trans = truth_arrays(BODY, tuple(angles), root_rot, root_trans)
    np.testing.assert_allclose(pose.joint_positions, joints, atol=1e-9)
    np.testing.assert_allclose(pose.segment_translations, trans, atol=1e-9)
    # Only the arm below the elbow moved.
    moved = np.linalg.norm(pose.joint_positions - clean.joints, axis=-1).max(axis=0) > 1e-9
    assert set(np.flatnonzero(moved)) == {wrist}


def test_pose_with_a_new_root_and_frame_count(clean):
    param = clean.param
    angles = param.angles[:50]
    turn = rotvec_to_matrix(np.array([0.0, 0.0, 0.5]))
    pose = param.pose(angles, root_frames=turn @ param.normalization.body_frames[:50], root_origins=np.zeros((50, 3)))
    base = param.pose()
    centred = base.joint_positions[:50] - param.normalization.limb_origins[:50, BODY.root, None]
    np.testing.assert_allclose(pose.joint_positions, centred @ turn.T, atol=1e-9)
    with pytest.raises(InputError, match="root_frames"):
        param.pose(angles)
    with pytest.raises(InputError, match="rotation matrices"):
        param.pose(angles, root_frames=np.ones((50, 3, 3)), root_origins=np.zeros((50, 3)))
    with pytest.raises(InputError, match="angles must be"):
        param.pose(angles[:, :3])
    with pytest.raises(InputError, match="finite"):
        param.pose(np.full_like(param.angles, np.nan))


def test_movement_filter_finds_the_swings(clean):
    """The elbow moves only in its swing phase; the filter agrees with the generator frame by frame."""
    param = clean.param
    elbow = NAMES.index("l_elbow")
    theta = clean.angles[elbow][:, 0]
    truly_moving = np.abs(np.gradient(theta)) > 1e-9
    agreement = np.mean(param.movement[:, elbow] == truly_moving)
    assert agreement > 0.9
    assert 0 < param.speed_threshold[elbow] < 0.2 * param.top_speed[elbow]
    assert param.histogram.shape == (BODY.n_joints, 100)
    np.testing.assert_array_equal(param.histogram.sum(axis=1), param.n_frames)


# ------------------------------------------------------------------ any motion
def test_any_motion_is_reposed_up_to_the_reported_residual():
    """synth's calibration moves every angle at once, not one main movement at a time.

    The two-axis swing model then cannot reach every direction (the axes come from
    arbitrary clusters); the residual reports exactly what is lost, and hinges,
    whose motion has one axis, are still exact.
    """
    _, truth = synth.simulate(BODY, "calibration", duration=14.0, rate=RATE, seed=4)
    quats = np.asarray(matrix_to_quat(truth.segment_rotations))
    param = parameterize_arrays(truth.joint_positions, truth.edges, quats, root=truth.root)
    np.testing.assert_array_equal(param.n_axes, np.where(KIND == "hinge", 1, 2))
    pose = param.pose()
    norm = param.normalization
    children = BODY.edges[:, 1]
    reposed = np.einsum("fjik,jk->fji", pose.limb_frames[:, children], _main(norm)[children])
    actual = np.einsum("fjik,jk->fji", norm.limb_frames[:, children], _main(norm)[children])
    # Direction error of each child limb relative to its parent: exactly the residual.
    parents = BODY.edges[:, 0]
    rel_pose = np.einsum("fjki,fjk->fji", pose.limb_frames[:, parents], reposed)
    rel_true = np.einsum("fjki,fjk->fji", norm.limb_frames[:, parents], actual)
    angle = np.arccos(np.clip(np.sum(rel_pose * rel_true, -1), -1.0, 1.0))
    np.testing.assert_allclose(angle, param.residual, atol=1e-6)
    np.testing.assert_allclose(param.residual[:, HINGES], 0.0, atol=1e-7)
    print(f"mean residual of two-axis joints: {np.degrees(param.residual[:, param.n_axes == 2].mean()):.2f} deg")


def test_angles_do_not_depend_on_the_world_frame(noisy):
    rec = noisy[0]
    turn = rotvec_to_matrix(np.array([1.0, 0.3, -0.4]))
    moved = parameterize_arrays(
        rec.joints @ turn.T + 2.0,
        BODY.edges,
        np.asarray(matrix_to_quat(turn @ rec.rot)),
        up_axis=turn[:, 2],
    )
    np.testing.assert_allclose(moved.angles, rec.params["joining"].angles, atol=1e-9)
    np.testing.assert_allclose(moved.axes, rec.params["joining"].axes, atol=1e-9)


def _main(norm: Normalization) -> np.ndarray:
    """(S, 3) each limb's long axis in its own limb frame."""
    return np.eye(3)[norm.main_axis] * norm.main_sign[:, None]


def test_a_joint_that_never_moves_is_flagged():
    angles, root_rot, root_trans = main_movements(BODY, rate=RATE, seed=0)
    wrist = NAMES.index("l_wrist")
    angles = tuple(np.zeros_like(a) if j == wrist else a for j, a in enumerate(angles))
    joints, quats, _, _ = truth_arrays(BODY, angles, root_rot, root_trans)
    with pytest.warns(DegenerateMotionWarning, match=rf"joint\(s\) \[{wrist}\] barely move"):
        param = parameterize_arrays(joints, BODY.edges, quats)
    assert not param.exercised[wrist] and param.exercised.sum() == BODY.n_joints - 1
    assert np.all(np.isfinite(param.angles)) and np.all(np.isfinite(param.axes))
    np.testing.assert_allclose(param.pose().joint_positions, joints, atol=1e-9)


def test_bad_options_are_reported(clean):
    norm = clean.norm
    with pytest.raises(InputError, match="method"):
        parameterize_normalized(norm, method="ica")
    with pytest.raises(InputError, match="n_axes"):
        parameterize_normalized(norm, n_axes=3)
    with pytest.raises(InputError, match="entries"):
        parameterize_normalized(norm, n_axes=[1, 2])
    with pytest.raises(InputError, match="delta_deg"):
        parameterize_normalized(norm, delta_deg=120.0)
    with pytest.raises(InputError, match="Normalization"):
        parameterize(None, None, normalization="not one")


def test_n_axes_override_and_duck_typed_entry(clean):
    skeleton = SimpleNamespace(edges=BODY.edges, root=BODY.root)
    motion = SimpleNamespace(joint_positions=clean.joints, rotations=clean.quats, segment_translations=clean.trans)
    elbow = NAMES.index("l_elbow")
    param = parameterize(skeleton, motion, n_axes={elbow: 2})
    assert param.n_axes[elbow] == 2
    np.testing.assert_array_equal(np.delete(param.n_axes, elbow), np.delete(clean.param.n_axes, elbow))
    np.testing.assert_allclose(param.pose().joint_positions, clean.joints, atol=1e-9)


# ------------------------------------------------------------------ outputs
def test_results_are_immutable(clean):
    param = clean.param
    with pytest.raises(ValueError, match="read-only"):
        param.angles[0, 0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        param.normalization.limb_frames[0, 0, 0, 0] = 1.0
    with pytest.raises(TypeError):
        param.settings["cell"] = 1.0  # type: ignore[index]
    with pytest.raises(dataclasses.FrozenInstanceError):
        param.method = "pca"  # type: ignore[misc]


def test_write_parameters_round_trip(clean, tmp_path):
    param = clean.param
    with h5py.File(tmp_path / "r.h5", "w") as f:
        write_parameters(f.create_group("parameters"), param)
    with h5py.File(tmp_path / "r.h5", "r") as f:
        g = f["parameters"]
        np.testing.assert_array_equal(g["angles"][()], param.angles)
        np.testing.assert_array_equal(g["axes"][()], param.axes)
        np.testing.assert_array_equal(g["movement"][()], param.movement)
        np.testing.assert_array_equal(g["n_axes"][()], param.n_axes)
        assert g.attrs["method"] == "joining" and g.attrs["angle_units"] == "rad"


def test_figures(clean, tmp_path):
    param = clean.param
    joints = [NAMES.index(n) for n in ("l_shoulder", "l_elbow", "l_wrist")]
    for plot, name in ((plot_joint_spheres, "spheres"), (plot_speed_histograms, "speeds"), (plot_angles, "angles")):
        path = tmp_path / f"{name}.png"
        fig = plot(param, joints, names=NAMES, path=path)
        assert isinstance(fig, Figure) and len(fig.axes) >= len(joints)
        assert path.stat().st_size > 10_000
    with pytest.raises(InputError, match="joints"):
        plot_angles(param, [99])
