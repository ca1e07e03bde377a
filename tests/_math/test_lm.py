"""The Levenberg–Marquardt solver object (jaxskel._math.lm) on problems with known minima."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxskel._math.lm import LevenbergMarquardt, NielsenDamping, Proposal

pytestmark = pytest.mark.usefixtures("float64")


def _rosenbrock(x):
    """Residuals of Rosenbrock's function: minimum 0 at (1, 1)."""
    return jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def _cost(x):
    return 0.5 * jnp.sum(_rosenbrock(x) ** 2)


def _propose(state):
    """Dense Gauss–Newton step damped by lam * diag(J^T J)."""
    x = state.params
    res, jac = _rosenbrock(x), jax.jacfwd(_rosenbrock)(x)
    jtj, g = jac.T @ jac, jac.T @ res
    dx = jnp.linalg.solve(jtj + state.lam * jnp.diag(jnp.diagonal(jtj)), -g)
    trial = x + dx
    predicted = -(g @ dx) - 0.5 * dx @ jtj @ dx
    cost = _cost(trial)
    return Proposal(params=trial, cost=cost, predicted=predicted, step=jnp.max(jnp.abs(dx)),
                    finite=jnp.isfinite(cost), aux=state.aux + 1)


def _solver(**kw):
    return LevenbergMarquardt(rtol=kw.pop("rtol", 1e-14), atol=kw.pop("atol", 1e-12), max_steps=kw.pop("max_steps", 200),
                              **kw)


def test_reaches_the_known_minimum_and_reports_steps_result_and_cost():
    solver = _solver()
    x0 = jnp.asarray([-1.2, 1.0])
    final = jax.jit(lambda x: solver.run(_propose, solver.init(x, _cost(x), jnp.asarray(0))))(x0)
    np.testing.assert_allclose(final.params, [1.0, 1.0], atol=1e-8)
    assert float(final.cost) < 1e-16
    assert 5 < int(final.steps) < 200
    assert int(final.aux) == int(final.steps)  # the problem's aux is carried from proposal to proposal
    assert solver.result(final) == optx.RESULTS.successful


def test_rounds_of_advance_end_where_run_ends():
    solver = _solver()
    x0 = jnp.asarray([-1.2, 1.0])
    start = solver.init(x0, _cost(x0), jnp.asarray(0))
    whole = solver.run(_propose, start)
    state = start
    for _ in range(100):  # 7 steps a round: the cut falls inside the iteration
        state = solver.advance(_propose, state, 7)
    assert int(state.steps) == int(whole.steps)
    np.testing.assert_array_equal(state.params, whole.params)
    np.testing.assert_array_equal(state.lam, whole.lam)


def test_step_cap_and_divergence_are_reported():
    x0 = jnp.asarray([-1.2, 1.0])
    capped = _solver(max_steps=3)
    final = capped.run(_propose, capped.init(x0, _cost(x0), jnp.asarray(0)))
    assert int(final.steps) == 3 and capped.result(final) == optx.RESULTS.nonlinear_max_steps_reached

    def never_finite(state):
        return Proposal(params=state.params, cost=jnp.asarray(jnp.nan), predicted=jnp.asarray(1.0),
                        step=jnp.asarray(jnp.nan), finite=jnp.asarray(False), aux=state.aux)

    failing = _solver(damping=NielsenDamping(initial=1.0, lam_max=1e6))
    final = failing.run(never_finite, failing.init(x0, _cost(x0), ()))
    # lam is multiplied by nu = 2, 4, 8, ...: 2^(k (k + 1) / 2) after k refusals, 2^15 after 5,
    # 2^21 > 1e6 after 6
    assert failing.result(final) == optx.RESULTS.nonlinear_divergence
    assert int(final.steps) == 6
    np.testing.assert_array_equal(final.params, x0)  # nothing refused is ever taken


def test_nielsen_update():
    damping = NielsenDamping()
    lam, nu = damping.start(jnp.float64)
    assert float(lam) == 1e-3 and float(nu) == 2.0
    # a perfect model (rho = 1) divides lam by 3; a refusal multiplies it by nu and doubles nu
    lam1, nu1 = damping.update(lam, nu, jnp.asarray(True), jnp.asarray(1.0))
    np.testing.assert_allclose([lam1, nu1], [1e-3 / 3, 2.0])
    lam2, nu2 = damping.update(lam, jnp.asarray(4.0), jnp.asarray(False), jnp.asarray(0.0))
    np.testing.assert_allclose([lam2, nu2], [4e-3, 8.0])
    # a poor model (rho = 0.25) shrinks lam by 1 - (2 rho - 1)^3 = 1.125: it grows
    lam3, _ = damping.update(lam, nu, jnp.asarray(True), jnp.asarray(0.25))
    np.testing.assert_allclose(lam3, 1.125e-3)
