"""The learning-pipeline API: jit/vmap-able, and gradients through the solves match
central finite differences (float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxskel
from jaxskel import synth

# Derivatives against finite differences need float64 in the caller's own traces (jit,
# grad, vmap), whose precision is the caller's: these tests run as a float64 user does.
pytestmark = pytest.mark.usefixtures("float64")


@pytest.fixture(scope="module")
def linkage():
    trial, truth = synth.simulate(synth.linkage(), duration=1.5, rate=60, seed=3, noise=0.0005)
    x, mask = trial.to_arrays()
    structure = jaxskel.learn.SkeletonStructure(truth.edges, truth.marker_segment)
    return x, mask, truth, structure


def directional_fd(f, args, directions, eps=1e-6):
    plus = f(*[a + eps * d for a, d in zip(args, directions)])
    minus = f(*[a - eps * d for a, d in zip(args, directions)])
    return (plus - minus) / (2 * eps)


def test_joint_cost_fn_grad_matches_fd_inside_jit_and_vmap(linkage):
    x, mask, _, _ = linkage
    pairs = np.asarray([[0, 1, 2, 3, 4, 5], [3, 4, 5, 6, 7, 8]])
    xs, ms = x[:, pairs].transpose(1, 0, 2, 3), mask[:, pairs].transpose(1, 0, 2)  # (2, F, 6, 3)
    weights = jnp.asarray(np.random.default_rng(0).normal(size=(xs.shape[1], 3)))
    tight = dict(rtol=1e-15, atol=1e-13, max_steps=500)  # FD needs the optimum to ~1e-13
    v = np.random.default_rng(1).normal(size=xs.shape) * ms[..., None]

    def solve(xs):
        return jax.vmap(lambda a, m: jaxskel.learn.joint_cost_fn(a, m, alpha=1e-3, **tight))(xs, ms)

    for name, out, eps, rel in (
        ("cost", lambda s: jnp.sum(s.cost), 1e-6, 1e-6),
        # positions converge to ~1e-11 m only, which limits the difference quotient itself
        ("positions", lambda s: jnp.sum(s.positions * weights), 1e-5, 3e-4),
    ):
        def loss(xs, out=out):
            return out(solve(xs))

        g = jax.jit(jax.grad(loss))(xs)
        fd = directional_fd(jax.jit(loss), [xs], [v], eps=eps)
        assert float(jnp.sum(g * v)) == pytest.approx(float(fd), rel=rel), name
    sol = jaxskel.learn.joint_cost_fn(xs, ms)
    assert sol.positions.shape == (2, x.shape[0], 3) and bool(jnp.all(sol.converged))


def test_rigid_fit_fn_bone_length_and_grad(linkage):
    x, mask, truth, structure = linkage
    jp = truth.joint_positions
    fit = jax.jit(jaxskel.learn.rigid_fit_fn)(structure, x, mask, jp)
    assert int(fit.result) == 0 and fit.marker_offsets.shape == (9, 3) and fit.joint_offsets.shape == (2, 2, 3)
    assert float(fit.bone_lengths[0]) == pytest.approx(truth.bone_lengths[0], abs=5e-4)
    assert float(jnp.max(fit.point_rms)) < 2e-3

    def bone(x, jp):
        return jaxskel.learn.rigid_fit_fn(structure, x, mask, jp).bone_lengths[0]

    gx, gj = jax.jit(jax.grad(bone, argnums=(0, 1)))(x, jp)
    rng = np.random.default_rng(2)
    vx, vj = rng.normal(size=x.shape) * mask[..., None], rng.normal(size=jp.shape)
    fd = directional_fd(jax.jit(bone), [x, jp], [vx, vj])
    assert float(jnp.sum(gx * vx) + jnp.sum(gj * vj)) == pytest.approx(float(fd), rel=1e-4)


def test_ik_fn_fits_and_grad_matches_fd(linkage):
    x, mask, truth, structure = linkage
    fit = jaxskel.learn.rigid_fit_fn(structure, x, mask, truth.joint_positions)
    sol = jax.jit(jaxskel.learn.ik_fn)(structure, x, mask, fit.joint_offsets, fit.marker_offsets)
    assert sol.rotations.shape == (x.shape[0], 3, 4) and float(jnp.median(sol.rms)) < 1.5e-3

    def loss(offsets, markers):
        return jnp.mean(jaxskel.learn.ik_fn(structure, markers, mask, fit.joint_offsets, offsets).rms ** 2)

    go, gx = jax.jit(jax.grad(loss, argnums=(0, 1)))(fit.marker_offsets, x)
    rng = np.random.default_rng(3)
    vo, vx = rng.normal(size=fit.marker_offsets.shape), rng.normal(size=x.shape) * mask[..., None]
    fd = directional_fd(jax.jit(loss), [fit.marker_offsets, x], [vo, vx])
    assert float(jnp.sum(go * vo) + jnp.sum(gx * vx)) == pytest.approx(float(fd), rel=1e-4)


def test_structure_is_static_and_checked():
    s = jaxskel.learn.SkeletonStructure([[0, 1], [1, 2]], [0, 0, 1, -1, 2])
    assert jax.tree_util.tree_leaves(s) == [] and hash(s) == hash(jaxskel.learn.SkeletonStructure([[0, 1], [1, 2]], [0, 0, 1, -1, 2]))
    assert s.root == 0 and s.segment_points().shape == (3, 3) and s.bones()[0].tolist() == [[0, 1]]
    with pytest.raises(jaxskel.InputError, match="tree"):
        jaxskel.learn.SkeletonStructure([[0, 1], [0, 1]], [0, 1, 2])
    with pytest.raises(jaxskel.InputError, match="marker_segment"):
        jaxskel.learn.SkeletonStructure([[0, 1]], [0, 5])
