"""The functional reference of bench/joint_centres.py: SCoRE (Ehrig et al. 2006) finds the
centre of a synthetic ball joint from the two segments' markers alone."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bench.joint_centres import score_centres


def _ball_joint(frames: int = 300, seed: int = 0, noise: float = 0.0):
    """Markers (F, 7, 3) of a 4-marker and a 3-marker segment turning about a joint that
    moves with ``centre`` (F, 3); both segments' markers 10 cm apart, 20-25 cm from it."""
    rng = np.random.default_rng(seed)
    local_a = rng.normal(size=(4, 3)) * 0.1 + np.array([0.0, 0.0, 0.2])
    local_b = rng.normal(size=(3, 3)) * 0.1 + np.array([0.0, 0.0, -0.25])
    rot_a = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.2).as_matrix()
    rot_b = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.6).as_matrix()
    centre = np.cumsum(rng.normal(size=(frames, 3)) * 0.01, axis=0) + np.array([0.1, 0.2, 0.9])
    x = np.concatenate([centre[:, None] + np.einsum("fij,kj->fki", rot_a, local_a),
                        centre[:, None] + np.einsum("fij,kj->fki", rot_b, local_b)], axis=1)
    return x + rng.normal(size=x.shape) * noise, centre


def test_score_finds_a_ball_joint_and_leaves_unposed_frames_empty():
    x, centre = _ball_joint()
    x[5, 0] = np.nan
    found = score_centres(x, np.arange(4), np.arange(4, 7))
    assert np.isnan(found[5]).all()
    assert np.nanmax(np.abs(found - centre)) < 1e-9
    noisy, centre = _ball_joint(seed=1, noise=0.0005)
    found = score_centres(noisy, np.arange(4), np.arange(4, 7))
    assert np.sqrt(np.mean(np.sum((found - centre) ** 2, axis=-1))) < 0.003  # 0.5 mm marker noise, 10 cm clusters


def test_score_needs_three_markers_on_each_segment():
    x, _ = _ball_joint()
    assert score_centres(x, np.arange(4), np.arange(4, 6)) is None


def test_reference_drift_is_the_least_error_of_a_centre_fixed_in_the_group():
    from bench.joint_centres import _marker_poses, reference_drift

    x, centre = _ball_joint(seed=2)
    group = np.arange(4, 7)
    assert reference_drift(x, group, centre) < 1e-6  # the true joint is fixed in the group
    # a reference 3 cm off in the world frame: it moves in the group's frame as the group turns
    reference = centre + np.array([0.03, 0.0, 0.0])
    drift = reference_drift(x, group, reference)
    rot, t = _marker_poses(x[:, group])
    local = np.einsum("fji,fj->fi", rot, reference - t)

    def rms_error(c):  # a centre fixed at c in the group's frame, against the reference (mm)
        return 1e3 * np.sqrt(np.mean(np.sum((np.einsum("fij,j->fi", rot, c) + t - reference) ** 2, axis=1)))

    assert 5.0 < drift < 30.0
    assert abs(rms_error(local.mean(axis=0)) - drift) < 1e-9  # attained at the mean place
    rng = np.random.default_rng(0)
    assert all(rms_error(local.mean(axis=0) + rng.normal(size=3) * 0.01) > drift for _ in range(20))
    assert reference_drift(x, np.arange(4, 6), centre) is None


def test_score_misfit_is_zero_at_a_true_joint_and_grows_at_a_displaced_reference():
    from bench.joint_centres import score_misfits

    x, centre = _ball_joint(seed=3)
    best, at_true = score_misfits(x, np.arange(4), np.arange(4, 7), centre)
    assert best < 1e-6 and at_true < 1e-6
    best, at_shifted = score_misfits(x, np.arange(4), np.arange(4, 7), centre + np.array([0.0, 0.02, 0.0]))
    assert best < 1e-6 and at_shifted > 5.0  # 2 cm off the joint, both segments turning
    assert score_misfits(x, np.arange(4), np.arange(4, 6), centre) is None
