"""Block-arrow Levenberg–Marquardt for the Kirk et al. (2005, §3.2) joint-cost problem.

Unknowns ``z = (c, r)``: a joint position ``c_f`` per frame (F frames) and a radius
``r_k`` per marker (K markers). With fixed weights ``beta_fk >= 0`` (zero where a
marker is missing or the frame is invalid) the objective is

    f(c, r) = 1/2 sum_fk beta_fk [ (d_fk - r_k)^2 + alpha d_fk ],   d_fk = |c_f - m_fk|.

Minimising over ``r`` gives ``r_k`` = the weighted mean distance, so ``2 f`` is the
paper's mean distance variance plus ``alpha`` times the mean distance. With
``u = (c - m)/d`` and ``e = d - r`` its derivatives are

    g_c,f = sum_k beta (e + alpha/2) u                 g_r,k = -sum_f beta e
    A_f   = sum_k beta [u u^T + s (I - u u^T)],  s = (e + alpha/2) / d
    B_f[:, k] = -beta_fk u_fk                          C = diag(sum_f beta)

i.e. the Hessian is block-arrow: a 3x3 block per frame, coupled only to the K radii.
A step ``[A B; B^T C] [dc; dr] = -g`` is solved by eliminating every frame's 3x3 block
(Schur complement onto the K x K radii system), O(F K^2) work and memory.

The model Hessian keeps the Gauss–Newton part ``u u^T`` of the distance residuals
and the *positive part* ``max(s, 0)`` of the curvature term. For the prior this is its
exact Hessian ``alpha/(2d) (I - u u^T)``; the Gauss–Newton matrix of the usual
``sqrt(alpha beta d)`` residual instead puts curvature ``alpha/(4d)`` on the radial
direction and none across it, which made Gauss–Newton/LM crawl (measured: 20-60
inner steps per frame). Dropping negative curvature keeps the model positive
semi-definite, so every damped system is positive definite.

Damping is two-level. A global Marquardt parameter ``lambda`` scales ``diag`` of the
whole model; each frame also has its own extra damping ``mu_f``. The trial radii
``r + dr`` are shared, but every frame keeps its old ``c_f`` when the step would raise
that frame's cost (and its ``mu_f`` grows). Frames in which the markers are nearly
collinear with the joint have an almost flat direction and propose steps of metres;
with a single damping parameter those few frames forced every frame to crawl
(measured: 80-170 steps versus 20-45 with per-frame safeguarding).

Each frame's problem can also have a second local minimum near the mirror image of
the joint in its markers. A frame that lands there is stuck: on the synthetic hip,
12 of 1,200 frames (in runs of 2-6) sat 12-18 cm off with a 100x larger frame cost,
and the pair's cost was 6.6x the true minimum. So each trial also offers every
frame the joints of the frames 1, 4 or 16 (in turn, one distance per step) before and
after it, moved by the mean displacement of the shared markers, and keeps whichever
candidate is cheapest (the stepped, the kept, or a neighbour's). Good branches spread into a bad run from both
ends; with frames out of time order the candidates are merely never taken. Every
choice is per frame at the same trial radii, so the cost still decreases
monotonically.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._linalg import spd_solve

__all__ = ["PairProblem", "block_solve", "levenberg_marquardt", "inv3"]

# Per-frame damping: bumped to at least this when a frame's step is refused.
_MU_BUMP = 1e-3
# Global LM parameter above which no step can make progress: report divergence.
_LAMBDA_MAX = 1e30


def inv3(a: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3 3"]:
    """Inverse of (batches of) 3x3 matrices by cofactors.

    Much faster than a batched LU on CPU for tens of thousands of tiny blocks. The
    caller guarantees non-singular input.
    """
    c00 = a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1]
    c01 = a[..., 1, 2] * a[..., 2, 0] - a[..., 1, 0] * a[..., 2, 2]
    c02 = a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]
    c10 = a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2]
    c11 = a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0]
    c12 = a[..., 0, 1] * a[..., 2, 0] - a[..., 0, 0] * a[..., 2, 1]
    c20 = a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1]
    c21 = a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2]
    c22 = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    det = a[..., 0, 0] * c00 + a[..., 0, 1] * c01 + a[..., 0, 2] * c02
    adj = jnp.stack(
        [jnp.stack([c00, c10, c20], -1), jnp.stack([c01, c11, c21], -1), jnp.stack([c02, c12, c22], -1)],
        axis=-2,
    )
    return adj / det[..., None, None]


def block_solve(
    a: Float[Array, "F 3 3"],
    b: Float[Array, "F 3 K"],
    c_diag: Float[Array, " K"],
    rhs_c: Float[Array, "F 3"],
    rhs_r: Float[Array, " K"],
) -> tuple[Float[Array, "F 3"], Float[Array, " K"]]:
    """Solve ``[A B; B^T diag(c)] [x_c; x_r] = [rhs_c; rhs_r]`` for block-diagonal A.

    Schur complement onto the radii: ``S = diag(c) - sum_f B_f^T A_f^-1 B_f``,
    ``S x_r = rhs_r - sum_f B_f^T A_f^-1 rhs_c``, then ``x_c = A^-1 (rhs_c - B x_r)``.
    Linear in the right-hand side (JAX can transpose it for reverse-mode).
    """
    a_inv = inv3(a)
    a_inv_b = a_inv @ b
    a_inv_rhs = jnp.einsum("fij,fj->fi", a_inv, rhs_c)
    schur = jnp.diag(c_diag) - jnp.einsum("fik,fil->kl", b, a_inv_b)
    # S is SPD (a Schur complement of the damped normal matrix); see _linalg for why not jnp.linalg.
    x_r = spd_solve(schur, rhs_r - jnp.einsum("fik,fi->k", b, a_inv_rhs))
    x_c = a_inv_rhs - jnp.einsum("fik,k->fi", a_inv_b, x_r)
    return x_c, x_r


class PairProblem(eqx.Module):
    """One joint-cost problem: markers of a segment pair, weights and the prior weight.

    ``markers`` should be centred near the origin (the caller subtracts a reference
    point) so float32 keeps sub-micrometre resolution.
    """

    markers: Float[Array, "F K 3"]
    beta: Float[Array, "F K"]
    alpha: Float[Array, ""]

    @property
    def valid_frames(self) -> Bool[Array, " F"]:
        return jnp.any(self.beta > 0, axis=1)

    @property
    def valid_markers(self) -> Bool[Array, " K"]:
        return jnp.any(self.beta > 0, axis=0)

    def geometry(self, c: Float[Array, "F 3"]):
        """Distances d (F,K), unit vectors u (F,K,3) and 1/d (0 where d = 0)."""
        v = c[:, None, :] - self.markers
        d2 = jnp.sum(v * v, axis=-1)
        positive = d2 > 0
        # double-where keeps sqrt's derivative finite at coincident points
        d = jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1.0)), 0.0)
        inv_d = jnp.where(positive, 1.0 / jnp.where(positive, d, 1.0), 0.0)
        return d, v * inv_d[..., None], inv_d

    def frame_costs(self, c: Float[Array, "F 3"], r: Float[Array, " K"]) -> Float[Array, " F"]:
        """Per-frame share of f: ``1/2 sum_k beta (e^2 + alpha d)``."""
        d, _, _ = self.geometry(c)
        e = d - r
        return 0.5 * jnp.sum(self.beta * (e * e + self.alpha * d), axis=1)

    def gradient(self, c, r):
        d, u, _ = self.geometry(c)
        e = d - r
        g_c = jnp.einsum("fk,fki->fi", self.beta * (e + 0.5 * self.alpha), u)
        g_r = -jnp.sum(self.beta * e, axis=0)
        return g_c, g_r

    def blocks(self, c, r, *, curvature: str):
        """Hessian blocks (A, B, C-diagonal) and gradient at (c, r).

        ``curvature``: "exact" (true Hessian), "positive" (LM model, see module
        docstring) or "none" (Gauss–Newton of the distance residuals only: the
        data-only information matrix used for identifiability).
        Invalid frames get ``A = I`` and invalid markers ``C = 1`` so solves stay
        defined; their right-hand sides are zero, so their updates are zero.
        """
        d, u, inv_d = self.geometry(c)
        e = d - r
        uu = u[..., :, None] * u[..., None, :]
        eye = jnp.eye(3, dtype=c.dtype)
        if curvature == "none":
            terms = uu
        else:
            s = (e + 0.5 * self.alpha) * inv_d
            if curvature == "positive":
                s = jnp.maximum(s, 0.0)
            terms = uu + s[..., None, None] * (eye - uu)
        a = jnp.einsum("fk,fkij->fij", self.beta, terms)
        a = jnp.where(self.valid_frames[:, None, None], a, eye)
        b = -jnp.swapaxes(self.beta[..., None] * u, 1, 2)
        c_diag = jnp.sum(self.beta, axis=0)
        c_diag = jnp.where(self.valid_markers, c_diag, 1.0)
        g_c = jnp.einsum("fk,fki->fi", self.beta * (e + 0.5 * self.alpha), u)
        g_r = -jnp.sum(self.beta * e, axis=0)
        return a, b, c_diag, g_c, g_r


# Frame offsets from which a stuck frame may be reseeded (both directions, one offset per
# step in turn). Spreading over 1, 4 and 16 frames crosses a bad run of n frames in
# ~3n/32 steps instead of n/2.
_RESEED_OFFSETS = (1, 4, 16)


def _neighbour_candidates(problem: PairProblem) -> list[Callable[[Float[Array, "F 3"]], Float[Array, "F 3"]]]:
    """Candidate makers for o = +1, -1, +4, -4, +16, -16: ``candidate(c) = roll(c, o) + shift``
    offers frame f the joint of frame f - o.

    The shift is the mean displacement of the markers present in both frames, so the
    candidate follows the body. Frames without such a neighbour (edges, no shared
    markers) get a shift of a kilometre, and the candidate is never taken.
    """
    present = (problem.beta > 0).astype(problem.markers.dtype)
    frames = problem.markers.shape[0]
    index = jnp.arange(frames)
    candidates = []
    for offset in _RESEED_OFFSETS:
        for signed in (offset, -offset):
            shared = present * jnp.roll(present, signed, axis=0)
            count = jnp.sum(shared, axis=1)
            moved = problem.markers - jnp.roll(problem.markers, signed, axis=0)
            shift = jnp.sum(shared[..., None] * moved, axis=1) / jnp.maximum(count, 1.0)[:, None]
            source = index - signed
            usable = (count > 0) & (source >= 0) & (source < frames)
            shift = jnp.where(usable[:, None], shift, 1e3)
            candidates.append(lambda c, signed=signed, shift=shift: jnp.roll(c, signed, axis=0) + shift)
    return candidates


class _LMState(eqx.Module):
    c: Float[Array, "F 3"]
    r: Float[Array, " K"]
    cost: Float[Array, ""]
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    mu: Float[Array, " F"]
    steps: Int[Array, ""]
    done: Bool[Array, ""]
    failed: Bool[Array, ""]


def levenberg_marquardt(
    problem: PairProblem,
    c0: Float[Array, "F 3"],
    r0: Float[Array, " K"],
    *,
    max_steps: Int[Array, ""] | int,
    rtol: Float[Array, ""] | float,
    atol: Float[Array, ""] | float,
) -> tuple[Float[Array, "F 3"], Float[Array, " K"], Int[Array, ""], optx.RESULTS]:
    """Minimise f over (c, r) from (c0, r0); returns (c, r, steps, result).

    Converged when a step moves nothing by more than ``atol`` (metres), or when an
    accepted step lowered f by at most ``rtol * f`` and the model predicted no more.
    The controls may be traced, so changing them does not recompile.
    """
    dtype = c0.dtype
    tiny = jnp.finfo(dtype).tiny
    neighbour_candidates = _neighbour_candidates(problem)

    def body(s: _LMState) -> _LMState:
        a, b, c_diag, g_c, g_r = problem.blocks(s.c, s.r, curvature="positive")
        a_diag = jnp.diagonal(a, axis1=1, axis2=2)
        # Marquardt scaling by the diagonal, floored so flat directions stay damped
        floor = 1e-12 * jnp.maximum(jnp.max(a_diag), tiny)
        a_damped = a + ((s.lam + s.mu)[:, None] * jnp.maximum(a_diag, floor))[..., None] * jnp.eye(3, dtype=dtype)
        c_damped = c_diag * (1.0 + s.lam)
        dc, dr = block_solve(a_damped, b, c_damped, -g_c, -g_r)
        model_c = jnp.einsum("fij,fj->fi", a, dc) + jnp.einsum("fik,k->fi", b, dr)
        model_r = jnp.einsum("fik,fi->k", b, dc) + c_diag * dr
        predicted = -(jnp.sum(g_c * dc) + jnp.sum(g_r * dr)) - 0.5 * (jnp.sum(dc * model_c) + jnp.sum(dr * model_r))

        r_trial = s.r + dr
        moved = problem.frame_costs(s.c + dc, r_trial)
        kept = problem.frame_costs(s.c, r_trial)
        take = moved <= kept
        c_trial = jnp.where(take[:, None], s.c + dc, s.c)
        cost_frames = jnp.minimum(moved, kept)
        # A frame stuck on a wrong branch (mirror image) is reseeded from a neighbour:
        # one distance (1, 4, 16 frames) per step in turn, both directions, so a step
        # evaluates two candidates rather than six (the frame costs dominate a step).
        turn = s.steps % len(_RESEED_OFFSETS)
        for direction in (0, 1):
            options = neighbour_candidates[direction::2]
            candidate = options[0](s.c)
            for k, make in enumerate(options[1:], start=1):
                candidate = jnp.where(turn == k, make(s.c), candidate)
            candidate_cost = problem.frame_costs(candidate, r_trial)
            better = candidate_cost < cost_frames
            c_trial = jnp.where(better[:, None], candidate, c_trial)
            cost_frames = jnp.where(better, candidate_cost, cost_frames)
        cost_trial = jnp.sum(cost_frames)

        finite = jnp.isfinite(cost_trial) & jnp.all(jnp.isfinite(dc)) & jnp.all(jnp.isfinite(dr))
        actual = s.cost - cost_trial
        accept = finite & (actual > 0)
        rho = actual / jnp.where(predicted > 0, predicted, 1.0)
        # Nielsen's update of the LM parameter
        lam = jnp.where(accept, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu)
        nu = jnp.where(accept, 2.0, 2.0 * s.nu).astype(dtype)
        mu = jnp.where(take, s.mu / 3.0, jnp.maximum(4.0 * s.mu, _MU_BUMP))
        mu = jnp.where(finite, jnp.where(mu < 1e-8, 0.0, mu), s.mu)

        step = jnp.maximum(jnp.max(jnp.abs(c_trial - s.c)), jnp.max(jnp.abs(dr)))
        flat = accept & (actual <= rtol * s.cost) & (predicted <= rtol * s.cost)
        return _LMState(
            c=jnp.where(accept, c_trial, s.c),
            r=jnp.where(accept, r_trial, s.r),
            cost=jnp.where(accept, cost_trial, s.cost),
            lam=lam,
            nu=nu,
            mu=mu,
            steps=s.steps + 1,
            done=(finite & (step <= atol)) | flat,
            failed=lam > _LAMBDA_MAX,
        )

    def cond(s: _LMState):
        return (~s.done) & (~s.failed) & (s.steps < max_steps)

    init = _LMState(
        c=c0,
        r=r0,
        cost=jnp.sum(problem.frame_costs(c0, r0)),
        lam=jnp.asarray(1e-3, dtype),
        nu=jnp.asarray(2.0, dtype),
        mu=jnp.zeros(c0.shape[0], dtype),
        steps=jnp.asarray(0),
        # nothing to fit: no frame has three markers
        done=~jnp.any(problem.valid_frames),
        failed=jnp.asarray(False),
    )
    final = jax.lax.while_loop(cond, body, init)
    result = optx.RESULTS.where(
        final.done,
        optx.RESULTS.successful,
        optx.RESULTS.where(final.failed, optx.RESULTS.nonlinear_divergence, optx.RESULTS.nonlinear_max_steps_reached),
    )
    return final.c, final.r, final.steps, result
