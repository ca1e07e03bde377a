"""Starting points of the joint solve (jaxskel.joints._cost_init): the consistency start for
pairs that never show five markers, where the algebraic start has nothing to solve."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from test_jointcost import _rotations, pair, rmse

from jaxskel.joints import solve_joint
from jaxskel.joints._cost_init import consistency_start

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


def _start(markers, mask=None):
    mask = np.ones(markers.shape[:2], bool) if mask is None else mask
    c, r, ok = consistency_start(jnp.asarray(markers), jnp.asarray(mask))
    return np.asarray(c), np.asarray(r), bool(ok)


def test_four_marker_pair_reaches_the_true_basin():
    """Two markers on each side of a ball joint, 1 mm noise. Started at the per-frame marker
    centroid the solve stops in a local minimum 3.3 times the cost of the solve started at
    the true joint, 32 mm from it; from the consistency start it reaches that cost and
    the joint (2.7 mm)."""
    markers, joint = pair("ball", n_parent=2, n_child=2, seed=3)
    c0, r0, ok = _start(markers)
    assert ok and rmse(c0, joint) < 0.01
    best = solve_joint(markers, alpha=0.0, c0=joint)
    from_start = solve_joint(markers, alpha=0.0, c0=c0, r0=r0)
    from_centroid = solve_joint(markers, alpha=0.0)
    assert float(from_start.cost) < 1.02 * float(best.cost)
    assert rmse(from_start.positions, joint) < 0.004
    assert float(from_centroid.cost) > 2.0 * float(best.cost)  # the failure the start exists for


def test_consistency_start_moves_with_the_data_and_ignores_marker_order():
    markers, _ = pair("ball", n_parent=2, n_child=2, seed=1)
    c, r, _ = _start(markers)
    rotation = _rotations(np.array([0.4, -1.1, 2.0]))
    shift = np.array([1.5, -2.0, 0.7])
    c_moved, r_moved, _ = _start(markers @ rotation.T + shift)
    np.testing.assert_allclose(c_moved, c @ rotation.T + shift, atol=1e-6)
    np.testing.assert_allclose(r_moved, r, atol=1e-6)
    order = np.array([3, 1, 0, 2])
    c_perm, r_perm, _ = _start(markers[:, order])
    np.testing.assert_allclose(c_perm, c, atol=1e-6)
    np.testing.assert_allclose(r_perm, r[order], atol=1e-6)


def test_padding_and_missing_markers():
    """A padded marker slot and gaps change nothing but the frames that lose a marker,
    which take their centroid (they cannot be solved with three markers)."""
    markers, joint = pair("ball", n_parent=2, n_child=2, seed=3)
    mask = np.ones(markers.shape[:2], bool)
    mask[100:120, 1] = False
    padded = np.concatenate([markers, np.zeros_like(markers[:, :1])], axis=1)
    padded_mask = np.concatenate([mask, np.zeros_like(mask[:, :1])], axis=1)
    c, r, ok = _start(np.where(mask[..., None], markers, 0.0), mask)
    c_pad, r_pad, _ = _start(np.where(padded_mask[..., None], padded, 0.0), padded_mask)
    assert ok
    np.testing.assert_allclose(c_pad, c, atol=1e-9)
    np.testing.assert_allclose(r_pad[:4], r, atol=1e-9)
    centroid = np.mean(markers[100:120][:, [0, 2, 3]], axis=1)
    np.testing.assert_allclose(c[100:120], centroid, atol=1e-12)
    keep = np.ones(len(c), bool)
    keep[100:120] = False
    assert rmse(c[keep], joint[keep]) < 0.01


def test_no_usable_frame_is_reported():
    """Three markers (or four in a plane) determine nothing: ``ok`` is False and the
    start is the centroid."""
    markers, _ = pair("ball", n_parent=2, n_child=2, seed=0)
    c, _, ok = _start(markers[:, :3])
    assert not ok
    np.testing.assert_allclose(c, markers[:, :3].mean(axis=1), atol=1e-12)
    flat = markers.copy()
    flat[..., 2] = 0.0
    assert not _start(flat)[2]
