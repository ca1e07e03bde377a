"""A Levenberg–Marquardt solver object with the problem's linear algebra plugged in.

The solver owns what every LM iteration shares: the named state, the acceptance test,
the damping policy and the stopping rules. The problem owns its maths: it *proposes*
a trial point for the current state (building its model, solving the damped system
with whatever structure it has, evaluating the trial cost).

Interface
---------
A problem is a callable ``propose(state) -> Proposal``. From ``state.params``, the
problem's own per-iteration data ``state.aux`` (e.g. per-frame damping), the global
damping ``state.lam`` and ``state.steps``, it returns

* ``params``: the trial point (any pytree of the same structure as ``state.params``);
* ``cost``: the objective ``f`` at the trial point;
* ``predicted``: the decrease of ``f`` the undamped model predicts for the step
  (``-g^T dz - 1/2 dz^T H dz``), used for the gain ratio;
* ``step``: the largest absolute change of any unknown (for ``atol``);
* ``finite``: whether the step and trial cost are finite;
* ``aux``: the problem's data for the next iteration (taken whether or not the step
  is accepted; the problem decides what a refused step does to it).

The solver then accepts the trial when it is finite and lowers ``f`` (``actual > 0``),
updates ``lam`` by its damping policy from the gain ratio ``rho = actual / predicted``,
and stops with

* ``successful`` when a finite step moved nothing by more than ``atol``, or an accepted
  step lowered ``f`` by at most ``rtol f`` and the model predicted no more;
* ``nonlinear_divergence`` when the policy says the damping diverged (``lam > lam_max``:
  no step can make progress);
* ``nonlinear_max_steps_reached`` after ``max_steps`` steps.

``rtol``, ``atol`` and ``max_steps`` may be traced arrays, so changing them does not
recompile. :meth:`LevenbergMarquardt.run` iterates to the end in a device
``while_loop``; :meth:`LevenbergMarquardt.advance` runs a *static* number of
iterations (a ``fori_loop``) in which a finished state stays frozen, so a host can run
many problems in rounds and re-pack the unfinished ones between rounds: the iterates of
a problem do not depend on how its rounds were cut.

Plugging in other solvers (e.g. the inverse-kinematics LMs, whose damped systems are
eliminated along a kinematic tree): ``params`` are the pose parameters, ``aux`` can be
empty (``()``), and ``propose`` builds the tree's normal equations at ``state.params``,
solves them damped by ``state.lam`` (Marquardt scaling by the diagonal is the problem's
choice) and returns the trial. Per-frame problems batched with ``vmap`` get one state
per frame; a batch that must share one ``lam`` keeps its frames in ``params`` and sums
the costs. The damping policy is a separate object, so a different schedule (e.g.
multiply/divide by constants) is another policy with the same two methods.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

__all__ = ["LMState", "LevenbergMarquardt", "NielsenDamping", "Proposal"]


class NielsenDamping(eqx.Module):
    """Nielsen's (1999) update of the Marquardt parameter.

    Accepted step with gain ratio ``rho``: ``lam <- lam max(1/3, 1 - (2 rho - 1)^3)``,
    ``nu <- 2``; refused step: ``lam <- lam nu``, ``nu <- 2 nu``. ``lam`` starts at
    ``initial``; above ``lam_max`` no step can make progress (divergence).
    """

    initial: float = 1e-3
    lam_max: float = 1e30

    def start(self, dtype) -> tuple[Float[Array, ""], Float[Array, ""]]:
        return jnp.asarray(self.initial, dtype), jnp.asarray(2.0, dtype)

    def update(self, lam, nu, accept, rho) -> tuple[Float[Array, ""], Float[Array, ""]]:
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        new_lam = jnp.where(accept, lam * shrink, lam * nu)
        new_nu = jnp.where(accept, 2.0, 2.0 * nu).astype(nu.dtype)
        return new_lam, new_nu

    def diverged(self, lam) -> Bool[Array, ""]:
        return lam > self.lam_max


class Proposal(eqx.Module):
    """A trial point proposed by the problem for the current state (see the module docstring)."""

    params: Any
    cost: Float[Array, ""]
    predicted: Float[Array, ""]
    step: Float[Array, ""]
    finite: Bool[Array, ""]
    aux: Any


class LMState(eqx.Module):
    """The solver's named state: the iterate and its cost, the damping, the counters."""

    params: Any
    aux: Any
    cost: Float[Array, ""]
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    steps: Int[Array, ""]
    done: Bool[Array, ""]
    failed: Bool[Array, ""]

    @property
    def running(self) -> Bool[Array, ""]:
        return ~self.done & ~self.failed


class LevenbergMarquardt(eqx.Module):
    """Levenberg–Marquardt iteration around a problem's ``propose`` (module docstring).

    ``rtol``, ``atol`` and ``max_steps`` may be traced scalars.
    """

    rtol: Any
    atol: Any
    max_steps: Any
    damping: NielsenDamping = NielsenDamping()

    def init(self, params, cost, aux=(), *, done=False) -> LMState:
        """The state at ``params`` (cost ``cost``); ``done`` marks a problem with nothing to fit."""
        cost = jnp.asarray(cost)
        lam, nu = self.damping.start(cost.dtype)
        return LMState(
            params=params, aux=aux, cost=cost, lam=lam, nu=nu, steps=jnp.asarray(0, jnp.int32),
            done=jnp.asarray(done), failed=jnp.asarray(False),
        )

    def active(self, state: LMState) -> Bool[Array, ""]:
        """Whether ``state`` still iterates: not done, not failed, under the step cap."""
        return state.running & (state.steps < self.max_steps)

    def step(self, propose: Callable[[LMState], Proposal], state: LMState) -> LMState:
        """One iteration: propose, accept or refuse, update the damping, test convergence."""
        trial = propose(state)
        actual = state.cost - trial.cost
        accept = trial.finite & (actual > 0)
        rho = actual / jnp.where(trial.predicted > 0, trial.predicted, 1.0)
        lam, nu = self.damping.update(state.lam, state.nu, accept, rho)
        flat = accept & (actual <= self.rtol * state.cost) & (trial.predicted <= self.rtol * state.cost)
        params = jax.tree_util.tree_map(lambda t, p: jnp.where(accept, t, p), trial.params, state.params)
        return LMState(
            params=params,
            aux=trial.aux,
            cost=jnp.where(accept, trial.cost, state.cost),
            lam=lam,
            nu=nu,
            steps=state.steps + 1,
            done=(trial.finite & (trial.step <= self.atol)) | flat,
            failed=self.damping.diverged(lam),
        )

    def run(self, propose: Callable[[LMState], Proposal], state: LMState) -> LMState:
        """Iterate until done, failed or ``max_steps`` (a device ``while_loop``)."""
        return jax.lax.while_loop(lambda s: self.active(s), lambda s: self.step(propose, s), state)

    def advance(self, propose: Callable[[LMState], Proposal], state: LMState, rounds: int) -> LMState:
        """At most ``rounds`` (static) iterations; a state that is finished stays as it is.

        The same iterates as :meth:`run`, cut into pieces: ``advance`` repeated until
        :meth:`active` is False ends where ``run`` ends.
        """

        def body(_, s):
            nxt = self.step(propose, s)
            go = self.active(s)
            return jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), nxt, s)

        return jax.lax.fori_loop(0, rounds, body, state)

    def result(self, state: LMState) -> optx.RESULTS:
        """optimistix result code of a final state."""
        return optx.RESULTS.where(
            state.done,
            optx.RESULTS.successful,
            optx.RESULTS.where(state.failed, optx.RESULTS.nonlinear_divergence,
                               optx.RESULTS.nonlinear_max_steps_reached),
        )
