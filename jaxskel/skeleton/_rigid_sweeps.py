"""The rigid refinement's pose/offset alternation as one device program.

The refinement of :mod:`jaxskel.skeleton._rigid_fit` minimises, over constant offsets
``theta`` (markers in their segment frames, joints in their parent frames) and per-frame
poses ``P_f`` (root translation, segment orientations)::

    E(theta, P) = sum_f sum_r w_fr |x_fr - t_root(f) - sum_u coef[r, u] R_seg(u)(f) theta_u|^2
                  + (IK pose prior)

Given ``theta`` the frames are independent IK problems (an *IK sweep*,
:func:`jaxskel.skeleton._ik_batch.solve_frames`, warm-started from the previous sweep's
poses with their relative rotations as the prior); given the poses ``E`` is a linear
least squares in ``theta`` (:func:`offset_update`, normal equations assembled from
per-frame rotation products). The alternation ``theta <- G(theta)`` (sweep, then exact
offsets) cannot raise the marker cost up to the weak pose prior, and converges linearly;
its updates are Anderson-accelerated (:func:`jaxskel._math.anderson.anderson_step_buffered`,
the last ``memory + 1`` pairs in a fixed buffer), the history restarted whenever the
cost rose. It stops at the first update that moves no offset by more than ``xtol``
without raising the cost (a fixed point of ``G``: a stationary point of ``E``), or after
``max_sweeps`` updates; every update is followed by a sweep, so the poses returned fit
the offsets returned.

:func:`alternate` runs all of it, IK sweeps included, in one ``lax.while_loop``: no
host round trip per sweep. The cost history, the offset steps and the sweep count come
back as the fields of :class:`Alternation`, the loop's named state.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._math.anderson import anderson_step_buffered
from .._math.linalg import spd_solve
from .._math.rotation import quat_to_matrix
from ._ik import _relative_rotations
from ._ik_batch import BatchModel, solve_frames, with_offsets

__all__ = ["Alternation", "SweepProblem", "alternate", "offset_pairs", "offset_system", "offset_update"]


# ------------------------------------------------------------ offset system
def offset_pairs(coef: np.ndarray, unknown_segment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ordered segment pairs ``(a, b)`` whose ``R_a^T R_b`` the offset system needs, and
    where each pair of unknowns finds its pair.

    Unknowns ``u`` and ``v`` meet in the normal equations only through an observation that
    depends on both (``coef[r, u] coef[r, v] != 0``): both lie on the path from the root to
    that observation's segment, so their segments are one another's ancestors. A tree of
    depth ``d`` needs about ``2 d S`` of the ``S^2`` pairs. Returns ``pairs`` (P, 2) and
    ``pair_index`` (U, U): the row of ``pairs`` of ``(seg u, seg v)``, or P where no
    observation joins ``u`` and ``v`` (a zero block).
    """
    used = np.asarray(coef) != 0  # (N, U)
    seg = np.asarray(unknown_segment)
    shared = (used[:, :, None] & used[:, None, :]).any(axis=0)  # (U, U)
    u, v = np.nonzero(shared)
    pairs = np.unique(np.stack([seg[u], seg[v]], axis=1), axis=0).reshape(-1, 2)
    row = np.full((seg.max(initial=0) + 1,) * 2, len(pairs), dtype=np.int32)  # segment pair -> its row
    row[pairs[:, 0], pairs[:, 1]] = np.arange(len(pairs))
    pair_index = np.where(shared, row[seg[:, None], seg[None, :]], len(pairs)).astype(np.int32)
    return pairs.astype(np.int32), pair_index


def offset_system(
    rot: Float[Array, "F S 3 3"],
    root_position: Float[Array, "F 3"],
    obs: Float[Array, "F N 3"],
    obs_weight: Float[Array, "F N"],
    coef: Float[Array, "N U"],
    unknown_segment: Int[Array, " U"],
    pairs: Int[Array, "P 2"],
    pair_index: Int[Array, "U U"],
) -> tuple[Float[Array, "3U 3U"], Float[Array, " 3U"], Float[Array, ""]]:
    """Normal equations of the offsets with the poses fixed (a linear least squares).

    Observation r (marker or joint) in frame f is modelled as
    ``t_root + sum_u coef[r, u] R_seg(u) theta_u``: a marker sums its own offset and the
    parent-side offsets of the joints above it; a joint its own and those above. So
    ``N[u, v] = sum_r coef[r, u] coef[r, v] T[r, seg u, seg v]`` with the per-observation
    segment-pair sums ``T[r, a, b] = sum_f w_fr R_a(f)^T R_b(f)``, for the pairs of
    :func:`offset_pairs` only (``pair_index``: where each pair of unknowns finds its sum):
    O(F N P), never a per-frame (U, U) product. Also returns ``sum w |x - t_root|^2`` for
    the cost.
    """
    n_frames = rot.shape[0]
    # R_a^T R_b as three broadcast products summed (fused elementwise loops) and the frame
    # sum as one matrix product: written as two einsums, XLA:CPU would run the first as a
    # tiny matrix product per frame and fuse it into the second; as one broadcast product
    # reduced over its middle axis, it runs the reduction as a slow loop.
    ra, rb = rot[:, pairs[:, 0]], rot[:, pairs[:, 1]]
    rtr = sum(ra[:, :, k, :, None] * rb[:, :, k, None, :] for k in range(3))  # (F, P, 3, 3)
    pair_sums = (obs_weight.T @ rtr.reshape(n_frames, -1)).reshape((-1,) + rtr.shape[1:])
    pair_sums = jnp.concatenate([pair_sums, jnp.zeros_like(pair_sums[:, :1])], axis=1)  # row P: no pair
    block = pair_sums[:, pair_index]  # (N, U, U, 3, 3)
    normal = jnp.einsum("ru,rv,ruvij->uivj", coef, coef, block)
    target = obs - root_position[:, None, :]
    weighted = jnp.einsum("ru,fra->fua", coef, obs_weight[..., None] * target)
    rhs = jnp.einsum("fuai,fua->ui", rot[:, unknown_segment], weighted)
    n_u = coef.shape[1]
    return normal.reshape(3 * n_u, 3 * n_u), rhs.reshape(-1), jnp.sum(obs_weight * jnp.sum(target * target, -1))


def offset_update(rotations, root_position, obs, weight, coef, unknown_segment, pairs, pair_index, theta_old):
    """Exact least-squares offsets ``theta`` (3U,) for fixed poses, and the mean cost
    they reach (weighted squared residual per unit weight)."""
    normal, rhs, const = offset_system(
        quat_to_matrix(rotations), root_position, obs, weight, coef, unknown_segment, pairs, pair_index
    )
    # A whisper of ridge towards the current offsets keeps directions that no frame
    # constrains (a joint with nothing below it ever seen) where they are.
    ridge = 1e-10 * jnp.trace(normal) / normal.shape[0]
    eye = jnp.eye(normal.shape[0], dtype=obs.dtype)
    # SPD (normal matrix plus a ridge): Cholesky in plain XLA (jaxskel._math.linalg), not
    # LAPACK's LU.
    theta = spd_solve(normal + ridge * eye, rhs + ridge * theta_old)
    cost = (const - 2 * theta @ rhs + theta @ normal @ theta) / jnp.maximum(jnp.sum(weight), 1.0)
    return theta, cost


# ------------------------------------------------------------------ records
class SweepProblem(eqx.Module):
    """The fixed inputs of the alternation, on the device.

    ``model``: the IK layout (:func:`jaxskel.skeleton._ik_batch.batch_model` of the
    starting offsets; joints observed at their child's origin, one slot each), whose
    offsets :func:`with_offsets` replaces each sweep. ``obs_in``/``observed`` (F, C, 3)/(F,
    C): the IK's padded observation columns (markers, then joint centres);
    ``prior_weight`` (S,); ``parent`` (S,) the tree in the original segment order (-1:
    root); ``max_steps`` per IK sweep; ``xtol`` (m). The offset system: ``obs`` (F, N, 3),
    ``weight`` (F, N) (mask times base weight), ``coef`` (N, U), ``unknown_segment`` (U,),
    ``pairs``/``pair_index`` (:func:`offset_pairs`).
    """

    model: BatchModel
    obs_in: Float[Array, "F C 3"]
    observed: Bool[Array, "F C"]
    prior_weight: Float[Array, " S"]
    parent: Int[Array, " S"]
    max_steps: Int[Array, ""]
    xtol: Float[Array, ""]
    obs: Float[Array, "F N 3"]
    weight: Float[Array, "F N"]
    coef: Float[Array, "N U"]
    unknown_segment: Int[Array, " U"]
    pairs: Int[Array, "P 2"]
    pair_index: Int[Array, "U U"]


class Alternation(eqx.Module):
    """The alternation's state, and its result.

    ``theta`` (U, 3) the offsets (markers, then joints); the last sweep's poses and IK
    report per frame (``root_position`` (F, 3), ``rotations`` (F, S, 4), ``num_steps``,
    ``done``, ``rms`` (F,)); ``cost_history`` and ``offset_steps`` (max_sweeps,): per
    update its mean cost (m^2) and largest offset move (m), valid up to ``sweeps``;
    ``met``: the last update met ``xtol``; ``swept``: a sweep has run;
    ``iterates``/``images`` (memory + 1, 3U) the Anderson history (newest last, ``count``
    rows valid).
    """

    theta: Float[Array, "U 3"]
    root_position: Float[Array, "F 3"]
    rotations: Float[Array, "F S 4"]
    num_steps: Int[Array, " F"]
    done: Bool[Array, " F"]
    rms: Float[Array, " F"]
    cost_history: Float[Array, " H"]
    offset_steps: Float[Array, " H"]
    sweeps: Int[Array, ""]
    met: Bool[Array, ""]
    swept: Bool[Array, ""]
    iterates: Float[Array, "A V"]
    images: Float[Array, "A V"]
    count: Int[Array, ""]


# -------------------------------------------------------------------- phases
def _sweep(problem: SweepProblem, theta, t0, q0, horn, chunk: int) -> dict[str, Array]:
    """One IK sweep over all frames with offsets ``theta``, from ``(t0, q0)`` (their
    relative rotations the prior) or, with ``horn``, from the Horn start."""
    n_joints = problem.model.joint_segment.shape[0]
    n_markers = theta.shape[0] - n_joints
    model = with_offsets(problem.model, theta[n_markers:], theta[:n_markers])
    rel = jax.vmap(_relative_rotations, (0, None))(q0, problem.parent)
    prior = jnp.where(rel[..., :1] < 0, -rel, rel)
    return solve_frames(
        model, problem.obs_in, problem.observed, t0, q0, prior, problem.prior_weight, horn, problem.max_steps,
        chunk=chunk,
    )


def _with_sweep(state: Alternation, theta, sol) -> Alternation:
    return eqx.tree_at(
        lambda s: (s.theta, s.root_position, s.rotations, s.num_steps, s.done, s.rms), state,
        (theta, sol["root_position"], sol["rotations"], sol["num_steps"], sol["done"], sol["rms"]),
    )


def _update(problem: SweepProblem, state: Alternation) -> tuple[Array, Alternation]:
    """One offset update and its bookkeeping and acceleration: the offsets to sweep with
    next, and the state with this update's cost, step and Anderson history."""
    theta_old = state.theta.reshape(-1)
    theta, cost = offset_update(
        state.rotations, state.root_position, problem.obs, problem.weight, problem.coef,
        problem.unknown_segment, problem.pairs, problem.pair_index, theta_old,
    )
    step = jnp.max(jnp.abs(theta - theta_old))
    k = state.sweeps
    started = k > 0
    rose = started & (cost > state.cost_history[jnp.maximum(k - 1, 0)])
    met = started & ~rose & (step <= problem.xtol)
    history = state.iterates.shape[0]
    count = jnp.minimum(jnp.where(rose, 0, state.count) + 1, history)  # the acceleration restarts on a rise
    iterates = jnp.roll(state.iterates, -1, axis=0).at[-1].set(theta_old)
    images = jnp.roll(state.images, -1, axis=0).at[-1].set(theta)
    theta_next = jnp.where(met, theta, anderson_step_buffered(iterates, images, count)).reshape(-1, 3)
    state = eqx.tree_at(
        lambda s: (s.cost_history, s.offset_steps, s.sweeps, s.met, s.iterates, s.images, s.count), state,
        (state.cost_history.at[k].set(cost), state.offset_steps.at[k].set(step), k + 1, met, iterates, images,
         count),
    )
    return theta_next, state


def _iteration(problem: SweepProblem, chunk: int, horn: Array, state: Alternation) -> Alternation:
    """The loop body: the first pass sweeps with the starting offsets (from the starting
    poses or, with ``horn``, the Horn start); every later one updates the offsets first.
    One IK call site, so the program holds one copy of the IK solver."""
    first = ~state.swept
    theta_next, state = jax.lax.cond(
        first, lambda s: (s.theta, s), functools.partial(_update, problem), state
    )
    sol = _sweep(problem, theta_next, state.root_position, state.rotations, horn & first, chunk)
    return _with_sweep(eqx.tree_at(lambda s: s.swept, state, jnp.asarray(True)), theta_next, sol)


@functools.partial(jax.jit, static_argnames=("max_sweeps", "memory", "chunk"))
def alternate(
    problem: SweepProblem,
    theta0: Float[Array, "U 3"],
    t0: Float[Array, "F 3"],
    q0: Float[Array, "F S 4"],
    horn: Bool[Array, ""],
    refine: Bool[Array, ""],
    *,
    max_sweeps: int,
    memory: int,
    chunk: int = 64,
) -> dict[str, Array]:
    """A sweep from ``(t0, q0)`` (or the Horn start) with the offsets ``theta0``; with
    ``refine``, then the accelerated alternation until ``xtol`` or ``max_sweeps`` (module
    docstring), all in one program. ``memory``: pairs beyond the newest that the
    acceleration combines.

    Returns the final :class:`Alternation`'s fields as a dict (field name -> array): a
    container that :mod:`jax.export` serializes, so the program can be saved
    (:func:`jaxskel._runtime.program_cache.call`)."""
    dtype = problem.obs.dtype
    n_frames = t0.shape[0]
    n_theta = theta0.size
    state = Alternation(
        theta=theta0.astype(dtype), root_position=t0.astype(dtype), rotations=q0.astype(dtype),
        num_steps=jnp.zeros(n_frames, jnp.int32), done=jnp.zeros(n_frames, bool), rms=jnp.zeros(n_frames, dtype),
        cost_history=jnp.zeros(max_sweeps, dtype), offset_steps=jnp.zeros(max_sweeps, dtype),
        sweeps=jnp.asarray(0, jnp.int32), met=jnp.asarray(False), swept=jnp.asarray(False),
        iterates=jnp.zeros((memory + 1, n_theta), dtype), images=jnp.zeros((memory + 1, n_theta), dtype),
        count=jnp.asarray(0, jnp.int32),
    )

    def cond(s: Alternation):
        return ~s.swept | (refine & (s.sweeps < max_sweeps) & ~s.met)

    final = jax.lax.while_loop(cond, functools.partial(_iteration, problem, chunk, horn), state)
    return {field.name: getattr(final, field.name) for field in dataclasses.fields(final)}
