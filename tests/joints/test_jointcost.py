"""Joint cost (Kirk et al. 2005 §3.2): accuracy, invariances, identifiability, gradients.

A three-segment chain (parent -> child -> grandchild) is simulated here with a known
joint between parent and child: markers sit on rings 5-9 cm off each bone, the parent
moves rigidly and the child rotates about the joint (ball / universal / hinge / not
at all), 1 mm Gaussian noise. Most single-pair tests use 400 frames and 6 markers so
they share one compiled solver (padded to 512 frames x 8 markers).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxskel import DegenerateMotionError, InputError
from jaxskel.joints import solve_joint, solve_joints

# Private parts of the solver are checked against jax.hessian / jax.grad, and derivatives
# against finite differences, in the caller's own traces, whose precision is the caller's:
# these tests run in float64, as jaxskel's public functions and a float64 user do.
pytestmark = pytest.mark.usefixtures("float64")

NOISE = 1e-3
FRAMES = 400


def _rotations(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (scipy: an independent reference)."""
    rotvec = np.asarray(rotvec, float)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(rotvec.shape + (3,))


def chain(kind="ball", frames=FRAMES, n_parent=3, n_child=3, noise=NOISE, seed=0, amplitude=0.6):
    """Markers of parent, child, grandchild (F, n, 3) and the parent-child joint (F, 3)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)[:, None]

    def ring(n, near, far):
        angle = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n
        radius = rng.uniform(0.05, 0.09, n)
        return np.stack([radius * np.cos(angle), radius * np.sin(angle), -rng.uniform(near, far, n)], -1)

    parent_local = -ring(n_parent, 0.08, 0.22)  # above the joint, which is the parent origin
    child_local = ring(n_child, 0.08, 0.25)  # below it
    grand_local = ring(3, 0.08, 0.2)
    joint2_local = np.array([0.0, 0.0, -0.35])
    exercised = {"ball": [1, 1, 1], "universal": [1, 1, 0], "hinge": [1, 0, 0], "static": [0, 0, 0]}[kind]
    waves = amplitude * np.sin(2 * np.pi * rng.uniform(0.8, 2.0, 3) * t + rng.uniform(0, 2 * np.pi, 3))
    relative = _rotations(waves * np.asarray(exercised, float))
    grand_relative = _rotations(0.6 * np.sin(2 * np.pi * rng.uniform(0.8, 2.0, 3) * t + rng.uniform(0, 6, 3)))
    root = _rotations(0.5 * np.sin(2 * np.pi * 0.3 * t + np.array([0.0, 1.0, 2.0])))
    joint = np.concatenate([0.5 * np.sin(2 * np.pi * 0.2 * t), 0.3 * np.cos(2 * np.pi * 0.25 * t), 1.0 + 0 * t], -1)

    def world(rotation, origin, local):
        return np.einsum("fij,kj->fki", rotation, local) + origin[:, None, :]

    child_rotation = root @ relative
    joint2 = joint + np.einsum("fij,j->fi", child_rotation, joint2_local)
    markers = {
        "parent": world(root, joint, parent_local),
        "child": world(child_rotation, joint, child_local),
        "grand": world(child_rotation @ grand_relative, joint2, grand_local),
    }
    markers = {name: x + noise * rng.normal(size=x.shape) for name, x in markers.items()}
    return markers, joint


def pair(kind="ball", **kw):
    markers, joint = chain(kind, **kw)
    return np.concatenate([markers["parent"], markers["child"]], axis=1), joint


def rmse(positions, joint) -> float:
    return float(np.sqrt(np.mean(np.sum((np.asarray(positions) - joint) ** 2, axis=-1))))


@pytest.fixture(scope="module")
def ball():
    return pair("ball")


@pytest.fixture(scope="module")
def ball_solution(ball):
    return solve_joint(ball[0], alpha=0.0)


def test_ball_joint_recovered(ball, ball_solution):
    markers, joint = ball
    sol = ball_solution
    assert bool(sol.converged), sol.result_name
    assert sol.result_name == "successful"
    assert int(sol.steps) < 40
    assert rmse(sol.positions, joint) < 2.5e-3
    # distance spread is the noise level, and the cost is its square
    assert np.all((np.asarray(sol.distance_std) > 0.4 * NOISE) & (np.asarray(sol.distance_std) < 1.5 * NOISE))
    assert 0.2 * NOISE**2 < float(sol.cost) < 2.0 * NOISE**2
    np.testing.assert_allclose(float(sol.cost), float(sol.variance), rtol=1e-12)
    assert float(sol.residual) < 1e-6 * float(sol.cost)
    true_radii = np.linalg.norm(markers - joint[:, None], axis=-1).mean(0)
    np.testing.assert_allclose(np.asarray(sol.radii), true_radii, atol=2e-3)
    assert np.all(np.asarray(sol.valid_frames))


def test_universal_joint_recovered():
    markers, joint = pair("universal", seed=1)
    sol = solve_joint(markers, alpha=0.0)
    assert bool(sol.converged)
    assert rmse(sol.positions, joint) < 2.5e-3


def test_prior_biases_toward_markers(ball, ball_solution):
    markers, joint = ball
    biased = solve_joint(markers, alpha=0.01)
    assert bool(biased.converged)
    # centimetre-level pull toward the markers: lower mean distance, larger variance
    assert 5e-3 < rmse(biased.positions, joint) < 0.05
    assert float(np.mean(biased.radii)) < float(np.mean(ball_solution.radii))
    assert float(biased.variance) > float(ball_solution.variance)
    np.testing.assert_allclose(
        float(biased.cost), float(biased.variance) + 0.01 * float(np.mean(biased.radii)), rtol=1e-10
    )


def test_identifiability_separates_ball_hinge_and_rigid(ball_solution):
    universal = solve_joint(pair("universal", seed=1)[0], alpha=0.0)
    hinge = solve_joint(pair("hinge")[0], alpha=0.0)
    rigid = solve_joint(pair("static")[0], alpha=0.0)
    assert [int(s.undetermined_dims) for s in (ball_solution, universal, hinge, rigid)] == [0, 0, 1, 3]
    assert float(ball_solution.identifiability) > 100 and float(universal.identifiability) > 100
    assert float(hinge.identifiability) < 20 and float(rigid.identifiability) < 20
    assert float(ball_solution.uncertainty) < 0.03 and float(universal.uncertainty) < 0.03
    assert float(hinge.uncertainty) > 0.05
    assert float(rigid.uncertainty) > float(hinge.uncertainty)


def test_hinge_is_placed_on_its_axis():
    """A hinge's joint is undetermined only along the axis: the distance from the axis is right."""
    markers, joint = pair("hinge", seed=2)
    sol = solve_joint(markers, alpha=1e-4)
    assert int(sol.undetermined_dims) == 1
    # the hinge axis is the parent's x axis; the joint slides along it freely
    offset = np.asarray(sol.positions) - joint
    root = _rotations(0.5 * np.sin(2 * np.pi * 0.3 * np.linspace(0, 1, FRAMES)[:, None] + np.array([0.0, 1.0, 2.0])))
    across_axis = np.einsum("fji,fj->fi", root, offset)[:, 1:]
    assert float(np.sqrt(np.mean(np.sum(across_axis**2, -1)))) < 3e-3


def test_wrong_pair_costs_much_more():
    markers, _ = chain("ball", seed=3)
    cat = lambda a, b: np.concatenate([markers[a], markers[b]], axis=1)  # noqa: E731
    true_pairs = [solve_joint(cat("parent", "child"), alpha=0.0), solve_joint(cat("child", "grand"), alpha=0.0)]
    wrong = solve_joint(cat("parent", "grand"), alpha=0.0)
    assert float(wrong.cost) > 50 * max(float(s.cost) for s in true_pairs)
    # with the default prior the cost is dominated by alpha * distance; the variance still separates
    default = [solve_joint(cat(a, b)) for a, b in [("parent", "child"), ("child", "grand"), ("parent", "grand")]]
    assert float(default[2].cost) > max(float(s.cost) for s in default[:2])
    assert float(default[2].variance) > 8 * max(float(s.variance) for s in default[:2])


def test_missing_samples(ball, ball_solution):
    markers, joint = ball
    rng = np.random.default_rng(5)
    mask = rng.random(markers.shape[:2]) > 0.2
    holes = np.where(mask[..., None], markers, np.nan)
    sol = solve_joint(holes, alpha=0.0)  # mask taken from the NaNs
    explicit = solve_joint(markers, mask, alpha=0.0)
    np.testing.assert_allclose(float(sol.cost), float(explicit.cost), rtol=1e-12)
    # Frames missing markers leave fewer residual degrees of freedom per frame
    # (K_f - 3 of K_f), so the fitted variance drops by about a quarter at 20 % loss;
    # treating the holes as data would instead raise it by orders of magnitude.
    assert 0.6 * float(ball_solution.cost) < float(sol.cost) < 1.05 * float(ball_solution.cost)
    count = mask.sum(1)
    np.testing.assert_array_equal(np.asarray(sol.valid_frames), count >= 3)
    # three markers fix a joint only up to a mirror image; four or more place it
    placed = count >= 4
    assert rmse(np.asarray(sol.positions)[placed], joint[placed]) < 3e-3
    # frames with fewer than three markers keep the warm start
    start = joint + 0.01
    warm = solve_joint(markers, mask, alpha=0.0, c0=start)
    np.testing.assert_allclose(np.asarray(warm.positions)[count < 3], start[count < 3], atol=1e-12)
    np.testing.assert_allclose(float(warm.cost), float(sol.cost), rtol=1e-8)


def test_rigid_motion_invariance(ball, ball_solution):
    markers, _ = ball
    rotation = _rotations(np.array([0.3, -1.2, 0.7]))
    shift = np.array([2.0, -3.0, 0.5])
    moved = markers @ rotation.T + shift
    sol = solve_joint(moved, alpha=0.0)
    np.testing.assert_allclose(float(sol.cost), float(ball_solution.cost), rtol=1e-8)
    np.testing.assert_allclose(
        np.asarray(sol.positions), np.asarray(ball_solution.positions) @ rotation.T + shift, atol=1e-7
    )


def test_marker_order_invariance(ball, ball_solution):
    markers, _ = ball
    order = np.array([4, 0, 5, 2, 1, 3])
    sol = solve_joint(markers[:, order], alpha=0.0)
    np.testing.assert_allclose(float(sol.cost), float(ball_solution.cost), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(sol.radii), np.asarray(ball_solution.radii)[order], atol=1e-9)


def test_batch_padding_and_trial_vmap(ball, ball_solution):
    """Padding frames, markers and pairs changes nothing; vmap over a trial axis works."""
    a, _ = ball
    b, _ = pair("universal", n_parent=2, n_child=3, seed=5)
    unpadded = solve_joints(a[None], alpha=0.0)  # (1, 400, 6): no padding at all

    # frames 400 -> 512, markers -> 8, pairs 2 -> 4 (two fully masked pairs)
    padded = np.zeros((4, 512, 8, 3))
    padded[0, :FRAMES, :6], padded[1, :FRAMES, :5] = a, b
    padded_mask = np.zeros((4, 512, 8), bool)
    padded_mask[0, :FRAMES, :6], padded_mask[1, :FRAMES, :5] = True, True
    batch = solve_joints(padded, padded_mask, alpha=0.0)
    assert batch.cost.shape == (4,) and batch.positions.shape == (4, 512, 3)
    assert bool(batch.converged[0]) and bool(batch.converged[1])
    for reference in (unpadded, jax.tree_util.tree_map(lambda leaf: leaf[None], ball_solution)):
        np.testing.assert_allclose(float(batch.cost[0]), float(reference.cost[0]), rtol=1e-9)
        np.testing.assert_allclose(
            np.asarray(batch.positions[0, :FRAMES]), np.asarray(reference.positions[0]), atol=1e-8
        )
        np.testing.assert_allclose(np.asarray(batch.radii[0, :6]), np.asarray(reference.radii[0, :6]), atol=1e-9)
        assert int(batch.steps[0]) == int(reference.steps[0])
        assert int(batch.undetermined_dims[0]) == int(reference.undetermined_dims[0])
    np.testing.assert_allclose(float(batch.cost[1]), float(solve_joint(b, alpha=0.0).cost), rtol=1e-9)
    # one prior weight per pair (same compiled shape)
    mixed = solve_joints(padded, padded_mask, alpha=np.array([0.0, 1e-3, 0.0, 0.0]))
    np.testing.assert_allclose(float(mixed.cost[0]), float(batch.cost[0]), rtol=1e-12)
    np.testing.assert_allclose(float(mixed.cost[1]), float(solve_joint(b, alpha=1e-3).cost), rtol=1e-9)
    # the empty pairs: no NaN anywhere, nothing valid, no steps
    for leaf in jax.tree_util.tree_leaves(batch):
        assert np.all(np.isfinite(np.asarray(leaf, dtype=float)))
    assert np.all(np.asarray(batch.cost[2:]) == 0.0) and not np.asarray(batch.valid_frames[2:]).any()
    assert np.all(np.asarray(batch.converged[2:])) and np.all(np.asarray(batch.steps[2:]) == 0)

    # a leading trial axis: as extra batch axes (same compiled shape) and under jax.vmap
    trials, trial_mask = padded.reshape(2, 2, 512, 8, 3), padded_mask.reshape(2, 2, 512, 8)
    stacked = solve_joints(trials, trial_mask, alpha=0.0)
    assert stacked.cost.shape == (2, 2) and stacked.positions.shape == (2, 2, 512, 3)
    np.testing.assert_allclose(np.asarray(stacked.cost).ravel(), np.asarray(batch.cost), rtol=1e-12)
    mapped = jax.vmap(lambda x, m: solve_joints(x, m, alpha=0.0))(jnp.asarray(trials), jnp.asarray(trial_mask))
    np.testing.assert_allclose(np.asarray(mapped.cost), np.asarray(stacked.cost), rtol=1e-10)
    np.testing.assert_array_equal(np.asarray(mapped.steps), np.asarray(stacked.steps))


def test_warm_start(ball, ball_solution):
    markers, joint = ball
    warm = solve_joint(markers, alpha=0.0, c0=np.asarray(ball_solution.positions), r0=np.asarray(ball_solution.radii))
    assert int(warm.steps) <= 2
    np.testing.assert_allclose(float(warm.cost), float(ball_solution.cost), rtol=1e-10)
    near = solve_joint(markers, alpha=0.0, c0=joint + 0.01)
    assert int(near.steps) < int(ball_solution.steps) + 5
    np.testing.assert_allclose(float(near.cost), float(ball_solution.cost), rtol=1e-8)


def test_lm_and_ncg_agree():
    markers, joint = pair("ball", seed=6)
    lm = solve_joint(markers, alpha=1e-3)
    ncg = solve_joint(markers, alpha=1e-3, method="ncg", rtol=1e-12, atol=1e-12)
    assert bool(lm.converged) and bool(ncg.converged), ncg.result_name
    assert int(ncg.steps) > int(lm.steps)
    np.testing.assert_allclose(float(ncg.cost), float(lm.cost), rtol=1e-7)
    np.testing.assert_allclose(np.asarray(ncg.positions), np.asarray(lm.positions), atol=1e-4)
    assert float(ncg.residual) < 1e-6 * float(ncg.cost)
    # a step cap is reported, not hidden (LM's cap is traced: no recompilation)
    capped = solve_joint(markers, alpha=1e-3, max_steps=2)
    assert not bool(capped.converged) and capped.result_name == "nonlinear_max_steps_reached"
    assert int(capped.steps) == 2 and float(capped.cost) > float(lm.cost)
    assert float(capped.residual) > 1e-3 * float(capped.cost)


def test_gradients_match_finite_differences(ball):
    """Implicit derivatives of cost, a joint position and a radius vs central differences."""
    tight = dict(rtol=1e-15, atol=1e-13, max_steps=500)  # traced controls: no recompilation

    def outputs(x, alpha):
        sol = solve_joints(x[None], alpha=alpha, **tight)  # same (1, 400, 6) shape as above
        return jnp.stack([sol.cost[0], sol.positions[0, 30, 1], sol.radii[0, 2]])

    x0, alpha0 = jnp.asarray(ball[0]), 1e-3
    d_markers, d_alpha = jax.jacrev(outputs, argnums=(0, 1))(x0, alpha0)
    d_markers = np.asarray(d_markers)
    scale = np.max(np.abs(d_markers.reshape(3, -1)), axis=1)
    h = 1e-6
    for idx in [(30, 0, 0), (30, 4, 2), (31, 1, 1), (200, 3, 2)]:
        step = jnp.zeros_like(x0).at[idx].set(h)
        fd = (np.asarray(outputs(x0 + step, alpha0)) - np.asarray(outputs(x0 - step, alpha0))) / (2 * h)
        np.testing.assert_array_less(np.abs(d_markers[(slice(None),) + idx] - fd), 1e-5 * scale + 1e-12)
    fd_alpha = (np.asarray(outputs(x0, alpha0 + h)) - np.asarray(outputs(x0, alpha0 - h))) / (2 * h)
    np.testing.assert_allclose(np.asarray(d_alpha), fd_alpha, rtol=1e-4, atol=1e-9)
    # envelope theorem: d cost / d alpha is the mean marker distance
    sol = solve_joints(x0[None], alpha=alpha0, **tight)
    np.testing.assert_allclose(float(d_alpha[0]), float(jnp.mean(sol.radii[0])), rtol=1e-6)


def test_float32_follows_input(ball):
    markers, joint = ball
    sol = solve_joint(markers.astype(np.float32), alpha=0.0)
    assert sol.positions.dtype == jnp.float32 and sol.cost.dtype == jnp.float32
    assert bool(sol.converged)
    assert rmse(sol.positions, joint) < 3e-3


def test_bad_input_is_reported():
    markers, _ = pair("ball", frames=20)
    with pytest.raises(InputError, match="shaped"):
        solve_joint(markers[..., :2])
    with pytest.raises(InputError, match="mask"):
        solve_joint(markers, np.ones((20, 5), bool))
    nan = markers.copy()
    nan[3, 2] = np.nan
    with pytest.raises(InputError, match="NaN"):
        solve_joint(nan, np.ones(markers.shape[:2], bool))
    with pytest.raises(InputError, match="method"):
        solve_joint(markers, method="bfgs")
    with pytest.raises(InputError, match="alpha"):
        solve_joint(markers, alpha=-1.0)
    with pytest.raises(InputError, match="c0"):
        solve_joint(markers, c0=np.zeros((19, 3)))
    with pytest.raises(DegenerateMotionError, match="three|3"):
        solve_joint(markers[:, :2])


def test_pair_problem_blocks_match_autodiff_and_block_solve_the_dense_system():
    # The LM's planar kernels (coordinate planes, symmetric blocks as six planes) against
    # jax.hessian / jax.grad of f(c, r) = 1/2 sum beta [(d - r)^2 + alpha d], with a
    # missing marker and a frame without weight (A = I there, zero right-hand side).
    from jaxskel.joints._cost_lm import PairProblem, block_solve

    rng = np.random.default_rng(3)
    frames, k = 6, 4
    markers = jnp.asarray(rng.normal(0.0, 0.1, (frames, k, 3)))
    beta = rng.uniform(0.5, 1.5, (frames, k))
    beta[2, 1] = 0.0
    beta[4] = 0.0
    beta = jnp.asarray(beta)
    alpha = jnp.asarray(0.3)
    problem = PairProblem(markers, beta, alpha)
    c = jnp.asarray(rng.normal(0.0, 0.2, (frames, 3)))
    r = jnp.asarray(rng.uniform(0.1, 0.3, k))

    def objective(c, r):
        d = jnp.linalg.norm(c[:, None] - markers, axis=-1)
        return 0.5 * jnp.sum(beta * ((d - r) ** 2 + alpha * d))

    a, b, c_diag, g_c, g_r = problem.blocks(c, r, curvature="exact")
    grad_c, grad_r = jax.grad(objective, argnums=(0, 1))(c, r)
    np.testing.assert_allclose(g_c, grad_c, atol=1e-12)
    np.testing.assert_allclose(g_r, grad_r, atol=1e-12)
    np.testing.assert_allclose(jnp.sum(problem.frame_costs(c, r)), objective(c, r), rtol=1e-12)
    hess = jax.hessian(objective, argnums=(0, 1))(c, r)
    valid = np.asarray(problem.valid_frames)
    for f in range(frames):
        want = np.asarray(hess[0][0][f, :, f, :]) if valid[f] else np.eye(3)
        np.testing.assert_allclose(a[f], want, atol=1e-12)
        np.testing.assert_allclose(b[f], hess[0][1][f], atol=1e-12)
    np.testing.assert_allclose(c_diag, np.diag(hess[1][1]), atol=1e-12)
    # The LM model drops negative curvature only: "positive" minus "exact" is PSD.
    a_pos, *_ = problem.blocks(c, r, curvature="positive")
    assert np.linalg.eigvalsh(np.asarray(a_pos - a)).min() > -1e-12

    # block_solve against the assembled dense system.
    dense = np.zeros((3 * frames + k, 3 * frames + k))
    for f in range(frames):
        dense[3 * f : 3 * f + 3, 3 * f : 3 * f + 3] = a_pos[f]
    b_pos = np.asarray(problem.blocks(c, r, curvature="positive")[1])
    dense[: 3 * frames, 3 * frames :] = b_pos.reshape(3 * frames, k)
    dense[3 * frames :, : 3 * frames] = b_pos.reshape(3 * frames, k).T
    dense[3 * frames :, 3 * frames :] = np.diag(np.asarray(c_diag)) + 5.0 * np.eye(k)
    rhs_c, rhs_r = rng.normal(size=(frames, 3)), rng.normal(size=k)
    x_c, x_r = block_solve(a_pos, jnp.asarray(b_pos), c_diag + 5.0, jnp.asarray(rhs_c), jnp.asarray(rhs_r))
    want = np.linalg.solve(dense, np.concatenate([rhs_c.reshape(-1), rhs_r]))
    np.testing.assert_allclose(np.concatenate([np.asarray(x_c).reshape(-1), x_r]), want, rtol=1e-9, atol=1e-12)
