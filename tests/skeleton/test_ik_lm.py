"""The IKs' Levenberg–Marquardt policies on the solver object (jaxskel._math.lm).

The batched IK runs a chunk of frames as one batch state of the solver: each frame is
accepted, damped and stopped on its own and frozen once done, so a frame's fit must not
depend on the other frames of its chunk (they change how long the loop runs). The
Newton switch is the tree proposal's ``aux``, set by its ``settle`` hook from the
solver's decision.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel import synth
from jaxskel._math.lm import Decision, LMState, Proposal
from jaxskel.skeleton import _ik_batch as ik_batch
from jaxskel.skeleton._ik import ik_solver

pytestmark = pytest.mark.usefixtures("float64")

CHUNK = 16


def _chunk(truth, x, mask, rows):
    slots, m_pad = ik_batch.solver_shape(truth.marker_segment, truth.edges, x.shape[1])
    model = ik_batch.batch_model(truth.edges, truth.joint_offsets, truth.marker_offsets, truth.marker_segment,
                                 slots=slots)
    n_seg = truth.edges.shape[0] + 1
    xs = np.zeros((CHUNK, m_pad, 3))
    ms = np.zeros((CHUNK, m_pad), bool)
    xs[:, : x.shape[1]] = x[rows]
    ms[:, : x.shape[1]] = mask[rows]
    ident = np.broadcast_to([1.0, 0.0, 0.0, 0.0], (CHUNK, n_seg, 4))
    return ik_batch.solve_chunk(
        model, jnp.asarray(xs), jnp.asarray(ms), jnp.zeros((CHUNK, 3)), jnp.asarray(ident), jnp.asarray(ident),
        jnp.full((n_seg,), 1e-3), jnp.asarray(True), jnp.asarray(60, jnp.int32), jnp.asarray(3, jnp.int32),
    )


def test_a_frame_fits_the_same_whatever_else_is_in_its_chunk():
    body = synth.random_tree(6, seed=2)
    trial, truth = synth.simulate(body, duration=1.0, seed=2, noise=0.002)
    x = np.asarray(trial.positions, float)
    mask = np.isfinite(x).all(-1) & (np.random.default_rng(0).random(x.shape[:2]) > 0.15)
    x = np.where(mask[..., None], x, 0.0)
    first = np.arange(CHUNK)
    other = np.concatenate([np.arange(8), 60 + np.arange(8)])  # the same first 8 frames, other company
    a, b = _chunk(truth, x, mask, first), _chunk(truth, x, mask, other)
    assert bool(np.all(a["done"])) and bool(np.all(b["done"]))
    assert int(np.max(a["num_steps"])) != int(np.max(b["num_steps"]))  # the loops run for different lengths
    for key in a:
        np.testing.assert_array_equal(np.asarray(a[key])[:8], np.asarray(b[key])[:8], err_msg=key)
    # and the fits are the optimum's: markers within a few noise levels
    assert float(np.max(a["rms"])) < 0.01


def test_newton_switch_follows_the_solver_decision():
    tree = ik_batch.TreeStep(None, None, None, None, None)  # settle reads only the switch policy
    energy = jnp.asarray([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    newton_now = jnp.asarray([True, True, True, False, True, True])
    lam = jnp.asarray([1e-3, 1e-3, 1e-3, 1e-3, 0.1, 1e-3])
    state = LMState(params=(), aux=newton_now, cost=energy, lam=lam, nu=jnp.full(6, 2.0), steps=jnp.zeros(6, int),
                    done=jnp.zeros(6, bool), failed=jnp.zeros(6, bool))
    trial = Proposal(params=(), cost=energy, predicted=energy, step=energy, finite=jnp.ones(6, bool), aux=newton_now)
    decision = Decision(
        accept=jnp.asarray([True, True, False, True, True, True]),
        actual=jnp.asarray([1e-6, 0.4, 1e-6, 1e-6, 1e-6, 0.6]),
        rho=jnp.asarray([1.0, 0.8, 1.0, 1.0, 1.0, 1.0]),
    )
    out = tree.settle(state, trial, decision)
    # Newton next: accepted, 0.75 < rho < 1.25, dropped by less than half the energy
    np.testing.assert_array_equal(out.aux, [True, True, False, True, True, False])
    # a Newton step ends the iteration: it was one, dropped by <= 1e-5 E, rho > 0.5, lam < 1e-2
    # (the stopping rule also requires it to be accepted)
    np.testing.assert_array_equal(out.converged, [True, False, True, False, False, False])


def test_ik_solver_policies():
    solver = ik_solver(50, 1e-8, 1e-10)
    lam, _ = solver.damping.update(jnp.asarray(1e-15), jnp.asarray(2.0), jnp.asarray(True), jnp.asarray(1.0))
    assert float(lam) == 1e-15  # floored
    assert bool(solver.damping.diverged(jnp.asarray(2e12))) and not bool(solver.damping.diverged(jnp.asarray(1e12)))

    def refused(state):  # never lowers the energy: mu grows by nu = 2, 4, 8, ...
        return Proposal(params=state.params + 1.0, cost=jnp.asarray(2.0), predicted=jnp.asarray(1.0),
                        step=jnp.asarray(1.0), finite=jnp.asarray(True), aux=())

    final = solver.run(refused, solver.init(jnp.asarray(0.0), jnp.asarray(1.0)))
    # 1e-3 2^(k (k + 1) / 2) > 1e12 first after k = 10 refusals: converged (the energy cannot
    # drop in floating point), not diverged, and nothing refused was taken
    assert int(final.steps) == 10 and bool(final.done) and not bool(final.failed)
    assert int(solver.result(final)._value) == 0 and float(final.params) == 0.0
