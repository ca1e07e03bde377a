"""A Levenberg–Marquardt solver object with the problem's linear algebra plugged in.

The solver owns what every LM iteration shares: the named state, the acceptance test,
the damping policy and the stopping rules. The problem owns its maths: it *proposes*
a trial point for the current state (building its model, solving the damped system
with whatever structure it has, evaluating the trial cost).

Interface
---------
A problem is a callable ``propose(state) -> Proposal``. From ``state.params``, the
problem's own per-iteration data ``state.aux`` (e.g. per-frame damping), the damping
``state.lam`` and ``state.steps``, it returns

* ``params``: the trial point (any pytree of the same structure as ``state.params``;
  it may carry the problem's evaluation of the point, which is accepted with it);
* ``cost``: the objective ``f`` at the trial point;
* ``predicted``: the decrease of ``f`` the undamped model predicts for the step
  (``-g^T dz - 1/2 dz^T H dz``), used for the gain ratio;
* ``step``: the largest absolute change of any unknown (for ``atol``);
* ``finite``: whether the step and trial cost are finite;
* ``aux``: the problem's data for the next iteration (taken whether or not the step
  is accepted; the problem decides what a refused step does to it);
* ``converged`` (default False): the problem's own test that an accepted step ends the
  iteration (read by :class:`AcceptedSmall`).

The solver accepts the trial when it is finite and lowers ``f`` (``actual = f - f_trial
> 0``) and forms the gain ratio ``rho = actual / predicted`` (:meth:`NielsenDamping.gain`).
A problem that also has a method ``settle(state, trial, decision) -> Proposal`` sees
that :class:`Decision` before anything else uses the trial and may rewrite the trial's
``aux`` and ``converged`` (e.g. a switch to Newton steps after a well-predicted
accepted step). The damping policy then updates ``lam`` from ``accept`` and ``rho``, and
the stopping policy decides ``done`` (converged) and ``failed`` (diverged):

* :class:`FlatOrStill` (the default): ``successful`` when a finite step moved nothing by
  more than ``atol``, or an accepted step lowered ``f`` by at most ``rtol f`` and the
  model predicted no more; ``nonlinear_divergence`` when the damping diverged
  (``lam > lam_max``: no step can make progress);
* :class:`AcceptedSmall`: ``successful`` when an accepted step moved nothing by ``atol``
  or more, lowered ``f`` by at most ``rtol f + drop_floor``, or the problem says it
  converged; damping past ``lam_max`` also counts as converged (``f`` cannot drop any
  more in floating point), never as divergence.

A member that has reached ``max_steps`` stops with ``nonlinear_max_steps_reached``.
``rtol``, ``atol`` and ``max_steps`` may be traced arrays, so changing them does not
recompile.

Batches
-------
One state can hold a *batch* of independent problems: ``cost`` has the batch's shape
(``()`` for one problem, ``(B,)`` for B), and so do ``lam``, ``nu``, ``steps``, ``done``
and ``failed``, which :meth:`LevenbergMarquardt.init` shapes from ``cost``. Every leaf
of ``params`` holds the batch on its trailing axes (it broadcasts against ``cost``:
``(3, B)`` or ``(S, K, B)`` for ``(B,)``), and ``propose`` returns per-member ``cost``,
``predicted``, ``step``, ``finite`` and ``converged``. Each member is accepted, damped and
stopped on its own; :meth:`LevenbergMarquardt.step` leaves a member that is no longer
:meth:`~LevenbergMarquardt.active` exactly as it is, so a member's iterates do not
depend on the others. :meth:`LevenbergMarquardt.run` iterates in a device
``while_loop`` while any member is active; :meth:`LevenbergMarquardt.advance` runs a
*static* number of iterations (a ``fori_loop``), so a host can run many problems in
rounds and re-pack the unfinished ones between rounds: the iterates of a problem do not
depend on how its rounds were cut.

Plugging in other solvers
-------------------------
The joint-cost LM (:class:`jaxskel.joints._cost_lm.PairLM`) is one problem whose
``params`` are the planes of every frame's joint and the radii, with one shared ``lam``
(per-frame damping in ``aux``) and the default policies. The inverse-kinematics LMs run
on this object too: the batched IK (:mod:`jaxskel.skeleton._ik_batch`) is a batch of
frames (``params`` the root translation, the segment orientations and their evaluation,
frames on the last axis; ``aux`` the Newton switch, set by ``settle``), and the
one-frame IK (:func:`jaxskel.skeleton._ik.solve_frame`, vmapped) a single problem; both
take their solver from :func:`jaxskel.skeleton._ik.ik_solver`: :class:`AcceptedSmall` and
a :class:`NielsenDamping` with ``lam_min`` (the damping never falls below it),
``lam_max`` (past it the iteration counts as converged) and ``predicted_floor``. A different schedule (e.g. multiply/divide by constants) is another
damping policy with the same methods.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "AcceptedSmall",
    "Decision",
    "FlatOrStill",
    "LMState",
    "LevenbergMarquardt",
    "NielsenDamping",
    "Proposal",
]


class NielsenDamping(eqx.Module):
    """Nielsen's (1999) update of the Marquardt parameter.

    Accepted step with gain ratio ``rho``: ``lam <- lam max(1/3, 1 - (2 rho - 1)^3)``,
    ``nu <- 2``; refused step: ``lam <- lam nu``, ``nu <- 2 nu``; then ``lam <- max(lam,
    lam_min)``. ``lam`` starts at ``initial``; above ``lam_max`` no step can make progress.
    The gain ratio is ``actual / predicted``; with ``predicted_floor`` None a
    non-positive prediction counts as 1, otherwise the prediction is floored at
    ``predicted_floor``.
    """

    initial: float = 1e-3
    lam_max: float = 1e30
    lam_min: float = 0.0
    predicted_floor: float | None = None

    def start(self, dtype, shape=()) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
        return jnp.full(shape, self.initial, dtype), jnp.full(shape, 2.0, dtype)

    def gain(self, actual, predicted) -> Float[Array, "*b"]:
        if self.predicted_floor is None:
            return actual / jnp.where(predicted > 0, predicted, 1.0)
        return actual / jnp.maximum(predicted, self.predicted_floor)

    def update(self, lam, nu, accept, rho) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        new_lam = jnp.where(accept, lam * shrink, lam * nu)
        new_nu = jnp.where(accept, 2.0, 2.0 * nu).astype(nu.dtype)
        if self.lam_min > 0:
            new_lam = jnp.maximum(new_lam, self.lam_min)
        return new_lam, new_nu

    def diverged(self, lam) -> Bool[Array, "*b"]:
        return lam > self.lam_max


class Proposal(eqx.Module):
    """A trial point proposed by the problem for the current state (see the module docstring)."""

    params: Any
    cost: Float[Array, "*b"]
    predicted: Float[Array, "*b"]
    step: Float[Array, "*b"]
    finite: Bool[Array, "*b"]
    aux: Any
    converged: Any = False


class Decision(eqx.Module):
    """The solver's verdict on a trial: ``accept``, ``actual = f - f_trial``, the gain ratio ``rho``."""

    accept: Bool[Array, "*b"]
    actual: Float[Array, "*b"]
    rho: Float[Array, "*b"]


class LMState(eqx.Module):
    """The solver's named state: the iterate and its cost, the damping, the counters
    (per member of a batch: module docstring)."""

    params: Any
    aux: Any
    cost: Float[Array, "*b"]
    lam: Float[Array, "*b"]
    nu: Float[Array, "*b"]
    steps: Int[Array, "*b"]
    done: Bool[Array, "*b"]
    failed: Bool[Array, "*b"]

    @property
    def running(self) -> Bool[Array, "*b"]:
        return ~self.done & ~self.failed


class FlatOrStill(eqx.Module):
    """Stop when a finite step moved nothing by more than ``atol``, or an accepted step
    lowered ``f`` by at most ``rtol f`` and the model predicted no more; fail when the
    damping diverged."""

    def __call__(self, solver, state, trial, decision, lam) -> tuple[Bool[Array, "*b"], Bool[Array, "*b"]]:
        flat = decision.accept & (decision.actual <= solver.rtol * state.cost) & (
            trial.predicted <= solver.rtol * state.cost
        )
        return (trial.finite & (trial.step <= solver.atol)) | flat, solver.damping.diverged(lam)


class AcceptedSmall(eqx.Module):
    """Stop when an accepted step is small: it moved every unknown by less than ``atol``,
    lowered ``f`` by at most ``rtol f + drop_floor``, or the problem's ``converged`` holds;
    damping past ``lam_max`` also stops, as converged. Never fails."""

    drop_floor: float = 1e-24

    def __call__(self, solver, state, trial, decision, lam) -> tuple[Bool[Array, "*b"], Bool[Array, "*b"]]:
        small = (trial.step < solver.atol) | (decision.actual <= solver.rtol * state.cost + self.drop_floor)
        small = small | trial.converged
        done = (decision.accept & small) | solver.damping.diverged(lam)
        return done, jnp.zeros_like(done)


def _keep(go, new, old):
    """``new`` where ``go`` (broadcast against each leaf's trailing axes), else ``old``."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), new, old)


class LevenbergMarquardt(eqx.Module):
    """Levenberg–Marquardt iteration around a problem's ``propose`` (module docstring).

    ``rtol``, ``atol`` and ``max_steps`` may be traced scalars; ``damping`` and
    ``stopping`` are the policies.
    """

    rtol: Any
    atol: Any
    max_steps: Any
    damping: NielsenDamping = NielsenDamping()
    stopping: FlatOrStill | AcceptedSmall = FlatOrStill()

    def init(self, params, cost, aux=(), *, done=False) -> LMState:
        """The state at ``params`` (cost ``cost``, one per member); ``done`` marks members with nothing to fit."""
        cost = jnp.asarray(cost)
        lam, nu = self.damping.start(cost.dtype, cost.shape)
        return LMState(
            params=params, aux=aux, cost=cost, lam=lam, nu=nu, steps=jnp.zeros(cost.shape, jnp.int32),
            done=jnp.broadcast_to(jnp.asarray(done), cost.shape), failed=jnp.zeros(cost.shape, bool),
        )

    def active(self, state: LMState) -> Bool[Array, "*b"]:
        """Which members still iterate: not done, not failed, under the step cap."""
        return state.running & (state.steps < self.max_steps)

    def step(self, propose: Callable[[LMState], Proposal], state: LMState) -> LMState:
        """One iteration of every active member: propose, accept or refuse, settle, update
        the damping, test convergence. Inactive members are returned unchanged."""
        trial = propose(state)
        actual = state.cost - trial.cost
        accept = trial.finite & (actual > 0)
        decision = Decision(accept=accept, actual=actual, rho=self.damping.gain(actual, trial.predicted))
        settle = getattr(propose, "settle", None)
        if settle is not None:
            trial = settle(state, trial, decision)
        lam, nu = self.damping.update(state.lam, state.nu, accept, decision.rho)
        done, failed = self.stopping(self, state, trial, decision, lam)
        go = self.active(state)
        take = accept & go
        counters = _keep(go, (trial.aux, lam, nu, state.steps + 1, done, failed),
                         (state.aux, state.lam, state.nu, state.steps, state.done, state.failed))
        aux, lam, nu, steps, done, failed = counters
        return LMState(
            params=_keep(take, trial.params, state.params),
            aux=aux,
            cost=jnp.where(take, trial.cost, state.cost),
            lam=lam,
            nu=nu,
            steps=steps,
            done=done,
            failed=failed,
        )

    def run(self, propose: Callable[[LMState], Proposal], state: LMState) -> LMState:
        """Iterate until no member is active (a device ``while_loop``)."""
        return jax.lax.while_loop(lambda s: jnp.any(self.active(s)), lambda s: self.step(propose, s), state)

    def advance(self, propose: Callable[[LMState], Proposal], state: LMState, rounds: int) -> LMState:
        """``rounds`` (static) iterations; finished members stay as they are.

        The same iterates as :meth:`run`, cut into pieces: ``advance`` repeated until
        :meth:`active` is False everywhere ends where ``run`` ends.
        """
        return jax.lax.fori_loop(0, rounds, lambda _, s: self.step(propose, s), state)

    def result(self, state: LMState) -> optx.RESULTS:
        """optimistix result code of a final state (one per member of a batch)."""

        def one(done, failed):
            return optx.RESULTS.where(
                done,
                optx.RESULTS.successful,
                optx.RESULTS.where(failed, optx.RESULTS.nonlinear_divergence, optx.RESULTS.nonlinear_max_steps_reached),
            )

        for _ in range(jnp.ndim(state.done)):
            one = jax.vmap(one)
        return one(state.done, state.failed)
