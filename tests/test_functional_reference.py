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
