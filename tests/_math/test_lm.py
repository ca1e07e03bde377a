"""The Levenberg–Marquardt solver object (jaxskel._math.lm) on problems with known minima."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxskel._math.lm import AcceptedSmall, FlatOrStill, LevenbergMarquardt, LMState, NielsenDamping, Proposal

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
    # 7 steps a round: the cut falls inside the iteration; the rounds go two past the last
    # step run takes (each round runs eagerly, so not 100 of them), and stay where run ended
    for _ in range(int(whole.steps) // 7 + 3):
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


# ------------------------------------------------------------------ batches and policies
def _rosenbrock_step(x, lam):
    """One damped Gauss–Newton step of Rosenbrock at x (2, *b), closed-form 2x2 solve (elementwise over b)."""
    res = _rosenbrock(x)
    # J = [[-20 x0, 10], [-1, 0]]
    j00, j01, j10, j11 = -20.0 * x[0], jnp.full_like(x[0], 10.0), jnp.full_like(x[0], -1.0), jnp.zeros_like(x[0])
    a, b, d = j00 * j00 + j10 * j10, j00 * j01 + j10 * j11, j01 * j01 + j11 * j11
    g0, g1 = j00 * res[0] + j10 * res[1], j01 * res[0] + j11 * res[1]
    ad, dd = a * (1.0 + lam), d * (1.0 + lam)
    det = ad * dd - b * b
    dx = jnp.stack([-(dd * g0 - b * g1) / det, -(ad * g1 - b * g0) / det])
    predicted = -(g0 * dx[0] + g1 * dx[1]) - 0.5 * (a * dx[0] ** 2 + 2 * b * dx[0] * dx[1] + d * dx[1] ** 2)
    trial = x + dx
    cost = 0.5 * jnp.sum(_rosenbrock(trial) ** 2, axis=0)
    return trial, cost, predicted, jnp.max(jnp.abs(dx), axis=0)


def _propose_elementwise(state):
    trial, cost, predicted, step = _rosenbrock_step(state.params, state.lam)
    return Proposal(params=trial, cost=cost, predicted=predicted, step=step, finite=jnp.isfinite(cost),
                    aux=state.aux + 1)


@pytest.mark.parametrize("stopping", [FlatOrStill(), AcceptedSmall()])
def test_a_batch_runs_each_member_as_its_own_scalar_run(stopping):
    """Members (batch on the last axis of params) converge, are damped and stop on their own:
    every member ends exactly where its own scalar run ends, though they take different
    step counts (finished members are frozen while the others go on)."""
    solver = _solver(stopping=stopping, max_steps=40)
    starts = jnp.asarray([[-1.2, 1.0], [0.5, 0.5], [2.0, -1.0], [1.0, 1.0]]).T  # (2, B)
    cost0 = 0.5 * jnp.sum(_rosenbrock(starts) ** 2, axis=0)
    batch = jax.jit(lambda s: solver.run(_propose_elementwise, s))(
        solver.init(starts, cost0, jnp.zeros(4, jnp.int32), done=cost0 <= 0.0))
    assert len(set(np.asarray(batch.steps).tolist())) > 2  # members stop at different steps
    for b in range(4):
        x0 = starts[:, b]
        one = jax.jit(lambda s: solver.run(_propose_elementwise, s))(
            solver.init(x0, cost0[b], jnp.asarray(0), done=cost0[b] <= 0.0))
        # the same iterates; XLA may round a vectorised loop differently from a scalar one
        np.testing.assert_allclose(batch.params[:, b], one.params, rtol=1e-10, atol=1e-14)
        for name in ("cost", "lam"):
            np.testing.assert_allclose(getattr(batch, name)[b], getattr(one, name), rtol=1e-10, atol=1e-30,
                                       err_msg=name)
        for name in ("nu", "steps", "done", "failed", "aux"):
            np.testing.assert_array_equal(getattr(batch, name)[b], getattr(one, name), err_msg=name)
    assert int(batch.steps[3]) == 0 and bool(batch.done[3])  # at the minimum: nothing to fit
    np.testing.assert_array_equal(batch.aux, batch.steps)  # a frozen member's aux is frozen too
    codes = solver.result(batch)
    for b in range(4):
        one = solver.init(starts[:, b], cost0[b])
        one = LMState(**{**{f: getattr(one, f) for f in ("params", "aux", "cost", "lam", "nu", "steps")},
                         "done": batch.done[b], "failed": batch.failed[b]})
        assert int(codes._value[b]) == int(solver.result(one)._value)


def _fixed(cost, predicted, step, finite=True, converged=False):
    """A problem that always proposes the same trial (as given)."""

    def propose(state):
        return Proposal(params=state.params + 1.0, cost=jnp.asarray(cost), predicted=jnp.asarray(predicted),
                        step=jnp.asarray(step), finite=jnp.asarray(finite), aux=(), converged=jnp.asarray(converged))

    return propose


def test_accepted_small_stops_on_accepted_small_steps_only():
    solver = _solver(rtol=1e-8, atol=1e-10, stopping=AcceptedSmall(drop_floor=1e-24))
    start = solver.init(jnp.asarray(0.0), jnp.asarray(1.0))
    cases = [
        # (trial cost, predicted, step, converged) -> done after one step
        ((0.5, 0.5, 1e-11, False), True),  # accepted, step below atol
        ((0.5, 0.5, 1e-10, False), False),  # accepted, step not below atol (strict), large drop
        ((1.0 - 1e-9, 1e-9, 1.0, False), True),  # accepted, drop <= rtol f
        ((2.0, 0.5, 1e-11, False), False),  # refused: a small step ends nothing
        ((0.5, 0.5, 1.0, True), True),  # accepted and the problem says converged
        ((2.0, 0.5, 1.0, True), False),  # refused, though the problem says converged
    ]
    for (cost, predicted, step, converged), done in cases:
        after = solver.step(_fixed(cost, predicted, step, converged=converged), start)
        assert bool(after.done) == done, (cost, predicted, step, converged)
        assert not bool(after.failed)
        assert float(after.params) == (1.0 if cost < 1.0 else 0.0)  # accepted trials only
    # The pair rule (FlatOrStill) stops on a finite small step even when it is refused.
    pair = _solver(rtol=1e-8, atol=1e-10)
    assert bool(pair.step(_fixed(2.0, 0.5, 1e-11), pair.init(jnp.asarray(0.0), jnp.asarray(1.0))).done)


def test_saturated_damping_is_success_for_accepted_small_and_divergence_for_flat_or_still():
    damping = NielsenDamping(initial=1.0, lam_max=1e6)
    refused = _fixed(2.0, 1.0, 1.0)  # never lowers f
    x0 = jnp.asarray(0.0)
    for stopping, code in ((AcceptedSmall(), optx.RESULTS.successful),
                           (FlatOrStill(), optx.RESULTS.nonlinear_divergence)):
        solver = _solver(damping=damping, stopping=stopping)
        final = solver.run(refused, solver.init(x0, jnp.asarray(1.0)))
        assert int(final.steps) == 6  # 2^21 > 1e6 after 6 refusals (test_step_cap_and_divergence_are_reported)
        assert solver.result(final) == code
        assert float(final.params) == 0.0


def test_damping_floor_and_gain_policies():
    lam, nu = NielsenDamping(initial=1e-14).start(jnp.float64, (3,))
    assert lam.shape == nu.shape == (3,)
    accept = jnp.asarray([True, True, False])
    rho = jnp.asarray([1.0, 1.0, 0.0])
    # rho = 1 divides by 3: 1e-14 / 3 stays above a 1e-15 floor, falls below a 1e-14 floor
    np.testing.assert_allclose(NielsenDamping(lam_min=1e-15).update(lam, nu, accept, rho)[0],
                               [1e-14 / 3, 1e-14 / 3, 2e-14])
    np.testing.assert_array_equal(NielsenDamping(lam_min=1e-14).update(lam, nu, accept, rho)[0], [1e-14, 1e-14, 2e-14])
    actual = jnp.asarray([1.0, 1.0, 1.0])
    predicted = jnp.asarray([2.0, 0.0, -1.0])
    # default: a non-positive prediction counts as 1; with a floor it is floored (rho huge)
    np.testing.assert_array_equal(NielsenDamping().gain(actual, predicted), [0.5, 1.0, 1.0])
    np.testing.assert_allclose(NielsenDamping(predicted_floor=1e-300).gain(actual, predicted), [0.5, 1e300, 1e300],
                               rtol=1e-15)


def test_settle_sees_the_decision_and_rewrites_aux_and_converged():
    """A problem's ``settle`` runs after the accept test and the gain ratio: it sets the next
    aux from the decision, and its ``converged`` ends the iteration under AcceptedSmall."""

    class Recording(eqx.Module):
        def __call__(self, state):
            return _fixed(0.5, 1.0, 1.0)(state)

        def settle(self, state, trial, decision):
            aux = (decision.accept, decision.actual, decision.rho)
            return dataclasses.replace(trial, aux=aux, converged=decision.rho > 0.4)

    solver = _solver(stopping=AcceptedSmall(), damping=NielsenDamping(predicted_floor=1e-300))
    start = solver.init(jnp.asarray(0.0), jnp.asarray(1.0), (jnp.asarray(False), jnp.asarray(0.0), jnp.asarray(0.0)))
    after = solver.step(Recording(), start)
    accept, actual, rho = after.aux
    assert bool(accept) and float(actual) == 0.5 and float(rho) == 0.5
    assert bool(after.done) and solver.result(after) == optx.RESULTS.successful
