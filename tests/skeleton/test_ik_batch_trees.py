"""The batched IK's tree elimination on trees of every level structure, against known answers.

:mod:`jaxskel.skeleton._ik_batch` eliminates the step's unknowns level by level of a
breadth-first order (leaf to root, then back). A wrong level structure (a level's range,
a child's parent slot, the padding of a narrow level, the root's level) gives a wrong
step. Here every tree is posed by forward kinematics in random poses and marked without
noise, so with no prior the optimum is the true pose (energy 0) and the solver must
reach it from the Horn start in few Newton steps (a wrong step is at best a descent
direction: it takes many more). Segments are numbered out of breadth-first order so
that the internal reordering is exercised too.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._math.rotation import axis_angle_to_quat, quat_multiply
from jaxskel.skeleton import _ik_batch as ik_batch
from jaxskel.skeleton._ik import forward_kinematics

pytestmark = pytest.mark.usefixtures("float64")

FRAMES = 24
#: Newton from the Horn start on noise-free markers converges quadratically (these trees
#: pass with this bound); a wrong elimination (a descent direction, but not Newton's)
#: converges linearly at best and needs many more steps.
MAX_EXACT_STEPS = 8


def _tree(edges, seed, markers=3):
    """Joint offsets and ``markers`` markers per segment (a spread, non-planar set)."""
    rng = np.random.default_rng(seed)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    n_seg = edges.shape[0] + 1
    jo = rng.normal(size=(edges.shape[0], 2, 3)) * 0.15
    mo = rng.normal(size=(n_seg * markers, 3)) * 0.08
    ms = np.repeat(np.arange(n_seg), markers)
    return edges, jo, mo, ms


def _poses(edges, n_seg, seed, angle=0.5):
    """Root translations (F, 3) and global orientations (F, S, 4) from random relative turns."""
    rng = np.random.default_rng(seed + 100)
    rel = np.asarray(axis_angle_to_quat(jnp.asarray(rng.uniform(-angle, angle, (FRAMES, n_seg, 3)))))
    parent = np.full(n_seg, -1)
    parent[edges[:, 1]] = edges[:, 0]
    q = rel.copy()
    posed = {int(s) for s in np.flatnonzero(parent < 0)}
    while len(posed) < n_seg:
        for p, c in edges:
            if p in posed and c not in posed:
                q[:, c] = np.asarray(quat_multiply(jnp.asarray(q[:, p]), jnp.asarray(rel[:, c])))
                posed.add(int(c))
    t = rng.normal(size=(FRAMES, 3)) * 0.3
    return t, q


def _fk(tree, t, q):
    edges, jo, mo, ms = tree
    _, joints, markers = forward_kinematics(
        jnp.asarray(t), jnp.asarray(q), jnp.asarray(jo), jnp.asarray(mo), jnp.asarray(edges), jnp.asarray(ms)
    )
    return np.asarray(joints), np.asarray(markers)


#: name -> edges (parent, child), numbered out of breadth-first order.
TREES = {
    # one level per segment (width 1, padded)
    "chain": [[0, 3], [3, 1], [1, 5], [5, 2], [2, 4]],
    # levels of widths 1, 2, 1, 2: a narrow level between wide ones
    "mixed": [[2, 0], [2, 5], [0, 1], [1, 3], [1, 4]],
    # two levels: the root and one level of five children
    "star": [[1, 0], [1, 2], [1, 3], [1, 4], [1, 5]],
    # levels of widths 1, 3, 2, 1 with children of different parents side by side
    "bushy": [[4, 0], [4, 2], [4, 6], [0, 1], [6, 3], [3, 5]],
}


@pytest.mark.parametrize("name", sorted(TREES))
def test_exact_markers_give_the_true_pose_in_few_steps(name):
    tree = _tree(TREES[name], seed=len(name))
    n_seg = tree[0].shape[0] + 1
    t, q = _poses(tree[0], n_seg, seed=len(name))
    joints, x = _fk(tree, t, q)
    model = ik_batch.batch_model(*tree)
    out = ik_batch.solve(
        model, x, np.ones(x.shape[:2], bool), None, None, None, np.zeros(n_seg), max_steps=100, chunk=8, threads=1
    )
    assert out["done"].all()
    assert out["num_steps"].max() <= MAX_EXACT_STEPS
    assert out["rms"].max() < 1e-9
    np.testing.assert_allclose(out["joint_positions"], joints, atol=1e-9)
    np.testing.assert_allclose(out["root_position"], t, atol=1e-9)
    same = np.abs(np.sum(out["rotations"] * q, axis=-1))  # |<q_fit, q_true>| = 1: the same rotation
    np.testing.assert_allclose(same, 1.0, atol=1e-12)


def test_single_segment_is_its_rigid_alignment():
    """A forest of one segment: no joints, the root alone (no elimination level)."""
    tree = _tree(np.zeros((0, 2)), seed=3, markers=5)
    t, q = _poses(tree[0], 1, seed=3)
    _, x = _fk(tree, t, q)
    model = ik_batch.batch_model(*tree)
    out = ik_batch.solve(model, x, np.ones(x.shape[:2], bool), None, None, None, np.zeros(1), max_steps=100, chunk=8)
    assert out["done"].all() and out["num_steps"].max() <= MAX_EXACT_STEPS
    assert out["joint_positions"].shape == (FRAMES, 0, 3)
    np.testing.assert_allclose(out["root_position"], t, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(out["rotations"] * q, axis=-1)), 1.0, atol=1e-12)

