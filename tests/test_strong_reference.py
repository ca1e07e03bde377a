"""The strong numpy reference (bench/reference/schur.py): its batched Schur-complement LM reaches
the scipy reference's cost and joint on synthetic data with a known joint, monotonically.

Synthetic three-segment chain (numpy only, no jaxskel): segment 0 moves freely, 1 hangs from 0
by a ball joint, 2 from 1; four markers per segment, 1 mm noise, some gaps.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.reference import joints as scipy_joints
from bench.reference import schur

ALPHA = 1e-5


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (F, 3, 3) of axis-angle vectors (F, 3) (Rodrigues)."""
    angle = np.linalg.norm(axis_angle, axis=1)[:, None, None]
    k = axis_angle / np.maximum(np.linalg.norm(axis_angle, axis=1, keepdims=True), 1e-12)
    cross = np.zeros((len(k), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    cross -= cross.transpose(0, 2, 1)
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _motion(frames: int, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    t = np.linspace(0, 1, frames)[:, None]
    freq = rng.uniform(0.7, 2.5, (1, 3))
    phase = rng.uniform(0, 2 * np.pi, (1, 3))
    return _rotation(amplitude * np.sin(2 * np.pi * freq * t + phase))


def _chain(frames: int = 240, seed: int = 0, noise: float = 0.001):
    """Markers (F, 12, 3), mask (F, 12), segment per marker (12,), true joints (F, 2, 3)."""
    rng = np.random.default_rng(seed)
    offsets = [rng.normal(0, 0.05, (4, 3)) + [0, 0, -0.15] for _ in range(3)]
    joint_in_parent = np.array([0.0, 0.0, -0.3])
    r0 = _motion(frames, rng, 0.6)
    p0 = np.stack([0.1 * np.sin(np.linspace(0, 3, frames)), np.zeros(frames), np.ones(frames)], 1)
    r1 = r0 @ _motion(frames, rng, 1.0)
    r2 = r1 @ _motion(frames, rng, 1.0)
    j1 = p0 + np.einsum("fij,j->fi", r0, joint_in_parent)
    j2 = j1 + np.einsum("fij,j->fi", r1, joint_in_parent)
    x = np.concatenate([
        p0[:, None] + np.einsum("fij,kj->fki", r0, offsets[0]),
        j1[:, None] + np.einsum("fij,kj->fki", r1, offsets[1]),
        j2[:, None] + np.einsum("fij,kj->fki", r2, offsets[2]),
    ], 1)
    x += rng.normal(0, noise, x.shape)
    mask = np.ones(x.shape[:2], bool)
    for m in rng.choice(12, 4, replace=False):  # a gap in four markers
        start = rng.integers(0, frames - 30)
        mask[start : start + 25, m] = False
    x = np.where(mask[..., None], x, 0.0)
    return x, mask, np.repeat(np.arange(3), 4), np.stack([j1, j2], 1)


@pytest.fixture(scope="module")
def chain():
    return _chain()


def _rms_mm(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    return float(np.sqrt(np.mean(np.sum((a[ok] - b[ok]) ** 2, -1))) * 1e3)


def test_pair_matches_scipy_and_truth_monotonically(chain):
    x, mask, seg, truth = chain
    idx = np.flatnonzero(seg <= 1)
    fit = schur.solve_pair(x[:, idx], mask[:, idx], ALPHA, history=True)
    ref = scipy_joints.solve_pair(x[:, idx], mask[:, idx], ALPHA)
    assert fit.status == schur.CONVERGED
    history = fit.history
    assert len(history) == fit.nfev + 1
    assert np.all(np.diff(history) <= 1e-12 * history[0]), "objective must never increase"
    assert history[-1] < history[0]
    # the same minimum: costs within 0.1 % (scipy's trust region stops on its own tolerances)
    assert fit.cost == pytest.approx(ref.cost, rel=1e-3)
    assert fit.cost <= ref.cost * (1 + 1e-6)
    assert _rms_mm(fit.positions, ref.positions) < 0.5
    assert np.allclose(fit.radii, ref.radii, atol=2e-4)
    # and the true joint, to within the noise
    assert _rms_mm(fit.positions, truth[:, 0]) < 3.0


def test_batch_equals_single_pairs(chain):
    """Pairs of different K solved together (padded, compacted as they finish) = solved alone."""
    x, mask, seg, _ = chain
    groups = [np.flatnonzero(seg <= 1), np.flatnonzero(seg >= 1), np.flatnonzero(seg != 1)[:7]]
    xs, ms = [x[:, g] for g in groups], [mask[:, g] for g in groups]
    together = schur.solve_pairs(xs, ms, ALPHA, chunk=8, workers=1)
    for xi, mi, fit in zip(xs, ms, together):
        alone = schur.solve_pair(xi, mi, ALPHA)
        assert fit.nfev == alone.nfev
        assert fit.cost == pytest.approx(alone.cost, rel=1e-9)
        np.testing.assert_allclose(fit.positions, alone.positions, atol=1e-9, equal_nan=True)


def test_topology_and_tree_joints_match_scipy(chain):
    x, mask, seg, truth = chain
    cost, fits, frames = schur.all_pair_costs(x, mask, seg, 3, alpha=ALPHA, max_frames=120, workers=2)
    cost_ref, fits_ref, frames_ref = scipy_joints.all_pair_costs(x, mask, seg, 3, alpha=ALPHA, max_frames=120)
    np.testing.assert_array_equal(frames, frames_ref)
    np.testing.assert_allclose(cost, cost_ref, rtol=1e-4)
    edges, root = schur.mst_topology(cost)
    assert {tuple(sorted(e)) for e in edges.tolist()} == {(0, 1), (1, 2)}
    info: dict = {}
    jp, jcost = schur.tree_joints(x, mask, seg, edges, fits, frames, alpha=ALPHA, workers=2, info=info)
    jp_ref, jcost_ref = scipy_joints.tree_joints(x, mask, seg, edges, fits_ref, frames_ref, alpha=ALPHA)
    assert jp.shape == jp_ref.shape == (x.shape[0], 2, 3)
    np.testing.assert_allclose(jcost, jcost_ref, rtol=1e-3)
    assert (info["steps"] > 0).all() and info["ks"].tolist() == [8, 8]
    for j, (p, c) in enumerate(edges.tolist()):
        true = truth[:, max(p, c) - 1]
        assert _rms_mm(jp[:, j], jp_ref[:, j]) < 0.5
        assert _rms_mm(jp[:, j], true) < 3.0
