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
direction and none across it, which makes Gauss–Newton/LM crawl. Dropping negative
curvature keeps the model positive semi-definite, so every damped system is positive
definite.

Damping is two-level. A global Marquardt parameter ``lambda`` scales ``diag`` of the
whole model; each frame also has its own extra damping ``mu_f``. The trial radii
``r + dr`` are shared, but every frame keeps its old ``c_f`` when the step would raise
that frame's cost (and its ``mu_f`` grows). Frames in which the markers are nearly
collinear with the joint have an almost flat direction and propose steps of metres;
with a single damping parameter those few frames force every frame to crawl.

Each frame's problem can also have a second local minimum near the mirror image of
the joint in its markers. A frame that lands there is stuck far from the joint at a
much larger frame cost, and a run of such frames raises the pair's cost well above the
true minimum. So each trial also offers every frame the joints of the frames 1, 4 or
16 (in turn, one distance per step) before and after it, moved by the mean displacement
of the shared markers, and keeps whichever candidate is cheapest (the stepped, the kept,
or a neighbour's). Good branches spread into a bad run from both ends; with frames out
of time order the candidates are merely never taken. Every
choice is per frame at the same trial radii, so the cost still decreases
monotonically.

The iteration is :class:`jaxskel._math.lm.LevenbergMarquardt` (named state, Nielsen's
damping policy, result codes) around :class:`PairLM`'s proposal, which owns the
per-frame damping (:class:`FrameDamping`) and the reseeding. The (F, K) quantities are
coordinate planes with frames on the major axis, so the per-frame sums over the few
markers are short minor-axis reductions.

The step counts and costs behind these choices (on a synthetic hip) are in
docs/bench/evidence_from_docstrings.md.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._math.linalg import spd_solve
from .._math.lm import LevenbergMarquardt, LMState, Proposal
from .._math.planes import SYM, UPPER, sym_apply, sym_inverse

__all__ = ["FrameDamping", "PairLM", "PairProblem", "block_solve", "levenberg_marquardt", "inv3"]


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


# ------------------------------------------------------------ planar (SoA) kernels
# The hot loop keeps every 3-vector as three (F,) or (F, K) planes instead of a trailing
# axis of 3: XLA:CPU vectorises along the minor axis, and a minor axis of 3 wastes most
# of each SIMD register (timing: docs/bench/evidence_from_docstrings.md).
# A symmetric 3x3 block is its six upper-triangle planes (jaxskel._math.planes).


def _planes(x: Float[Array, "... 3"]) -> tuple[Array, Array, Array]:
    return x[..., 0], x[..., 1], x[..., 2]


def _sym_planes(a: Float[Array, "F 3 3"]) -> tuple[Array, ...]:
    return tuple(a[:, i, j] for i, j in UPPER)


def _sym_matrix(a6) -> Float[Array, "F 3 3"]:
    return jnp.stack([jnp.stack([a6[SYM[i][j]] for j in range(3)], -1) for i in range(3)], -2)


def _geometry(m, c):
    """Distances d (F, K), unit vectors u (3 planes (F, K)) and 1/d (0 where d = 0) for
    marker planes ``m`` (3 x (F, K)) and joint planes ``c`` (3 x (F,))."""
    v = tuple(ci[:, None] - mi for ci, mi in zip(c, m))
    d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    positive = d2 > 0
    # double-where keeps sqrt's derivative finite at coincident points
    d = jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1.0)), 0.0)
    inv_d = jnp.where(positive, 1.0 / jnp.where(positive, d, 1.0), 0.0)
    return d, tuple(vi * inv_d for vi in v), inv_d


def _frame_costs(m, beta, alpha, c, r):
    return _costs_at(_geometry(m, c)[0], beta, alpha, r)


def _costs_at(d, beta, alpha, r):
    """Per-frame costs from the distances ``d`` (F, K)."""
    e = d - r
    return 0.5 * jnp.sum(beta * (e * e + alpha * d), axis=1)


def _blocks(m, beta, alpha, c, r, curvature: str, geometry=None):
    """Planar :meth:`PairProblem.blocks`: ``(a6, b, c_diag, g_c, g_r)`` with ``a6`` the
    six planes of each frame's symmetric block, ``b`` and ``g_c`` three planes.
    ``geometry``: :func:`_geometry` at ``c``, where the caller has it already."""
    d, u, inv_d = _geometry(m, c) if geometry is None else geometry
    e = d - r
    # u u^T + s (I - u u^T) = (1 - s) u u^T + s I
    if curvature == "none":
        w_uu, w_eye = beta, jnp.zeros_like(d[:, 0])
    else:
        s = (e + 0.5 * alpha) * inv_d
        if curvature == "positive":
            s = jnp.maximum(s, 0.0)
        w_uu, w_eye = beta * (1.0 - s), jnp.sum(beta * s, axis=1)
    valid = jnp.any(beta > 0, axis=1)
    a6 = []
    for i, j in UPPER:
        entry = jnp.sum(w_uu * u[i] * u[j], axis=1) + (w_eye if i == j else 0.0)
        a6.append(jnp.where(valid, entry, 1.0 if i == j else 0.0))  # invalid frames: A = I
    b = tuple(-beta * ui for ui in u)
    c_diag = jnp.sum(beta, axis=0)
    c_diag = jnp.where(jnp.any(beta > 0, axis=0), c_diag, 1.0)
    we = beta * (e + 0.5 * alpha)
    g_c = tuple(jnp.sum(we * ui, axis=1) for ui in u)
    g_r = -jnp.sum(beta * e, axis=0)
    return tuple(a6), b, c_diag, g_c, g_r


def _sym_apply(a6, x):
    """``A x`` for symmetric blocks ``a6`` and planes ``x`` ((F,) or (F, K) each)."""
    lead = (slice(None),) + (None,) * (x[0].ndim - 1)  # frames first: broadcast over K
    return sym_apply(tuple(a[lead] for a in a6), x)


def _block_solve(a6, b, c_diag, rhs_c, rhs_r):
    """Planar :func:`block_solve` (symmetric blocks)."""
    a_inv = sym_inverse(a6)
    a_inv_b = _sym_apply(a_inv, b)  # 3 x (F, K)
    a_inv_rhs = _sym_apply(a_inv, rhs_c)  # 3 x (F,)
    hi = jax.lax.Precision.HIGHEST
    schur = jnp.diag(c_diag) - sum(jnp.dot(bi.T, gi, precision=hi) for bi, gi in zip(b, a_inv_b))
    # S is SPD (a Schur complement of the damped normal matrix); see jaxskel._math.linalg for why not jnp.linalg.
    x_r = spd_solve(schur, rhs_r - sum(jnp.dot(ri, bi, precision=hi) for ri, bi in zip(a_inv_rhs, b)))
    x_c = tuple(ri - jnp.dot(gi, x_r, precision=hi) for ri, gi in zip(a_inv_rhs, a_inv_b))
    return x_c, x_r


def block_solve(
    a: Float[Array, "F 3 3"],
    b: Float[Array, "F 3 K"],
    c_diag: Float[Array, " K"],
    rhs_c: Float[Array, "F 3"],
    rhs_r: Float[Array, " K"],
) -> tuple[Float[Array, "F 3"], Float[Array, " K"]]:
    """Solve ``[A B; B^T diag(c)] [x_c; x_r] = [rhs_c; rhs_r]`` for block-diagonal,
    symmetric A (its upper triangles are read).

    Schur complement onto the radii: ``S = diag(c) - sum_f B_f^T A_f^-1 B_f``,
    ``S x_r = rhs_r - sum_f B_f^T A_f^-1 rhs_c``, then ``x_c = A^-1 (rhs_c - B x_r)``.
    Linear in the right-hand side (JAX can transpose it for reverse-mode).
    """
    x_c, x_r = _block_solve(_sym_planes(a), tuple(b[:, i] for i in range(3)), c_diag, _planes(rhs_c), rhs_r)
    return jnp.stack(x_c, axis=-1), x_r


class PairProblem(eqx.Module):
    """One joint-cost problem: markers of a segment pair, weights and the prior weight.

    ``markers`` should be centred near the origin (the caller subtracts a reference
    point) so float32 keeps sub-micrometre resolution. The methods return the usual
    (F, K, 3) / (F, 3, 3) layouts; :func:`levenberg_marquardt` runs the same maths on
    coordinate planes.
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
        d, u, inv_d = _geometry(_planes(self.markers), _planes(c))
        return d, jnp.stack(u, axis=-1), inv_d

    def frame_costs(self, c: Float[Array, "F 3"], r: Float[Array, " K"]) -> Float[Array, " F"]:
        """Per-frame share of f: ``1/2 sum_k beta (e^2 + alpha d)``."""
        return _frame_costs(_planes(self.markers), self.beta, self.alpha, _planes(c), r)

    def gradient(self, c, r):
        # the gradient does not depend on the curvature model; jit drops the unused blocks
        _, _, _, g_c, g_r = _blocks(_planes(self.markers), self.beta, self.alpha, _planes(c), r, "none")
        return jnp.stack(g_c, axis=-1), g_r

    def blocks(self, c, r, *, curvature: str):
        """Hessian blocks (A, B, C-diagonal) and gradient at (c, r).

        ``curvature``: "exact" (true Hessian), "positive" (LM model, see module
        docstring) or "none" (Gauss–Newton of the distance residuals only: the
        data-only information matrix used for identifiability).
        Invalid frames get ``A = I`` and invalid markers ``C = 1`` so solves stay
        defined; their right-hand sides are zero, so their updates are zero.
        """
        a6, b, c_diag, g_c, g_r = _blocks(_planes(self.markers), self.beta, self.alpha, _planes(c), r, curvature)
        return _sym_matrix(a6), jnp.stack(b, axis=1), c_diag, jnp.stack(g_c, axis=-1), g_r


def _neighbour_shifts(m, beta, offsets) -> Float[Array, "n 3 F"]:
    """Shifts (n, 3, F) of the candidates ``roll(c, o) + shift`` for the signed offsets
    o = +o1, -o1, +o2, -o2, ...: the candidate offers frame f the joint of frame f - o
    (``m``: coordinate planes (F, K)).

    The shift is the mean displacement of the markers present in both frames, so the
    candidate follows the body. Frames without such a neighbour (edges, no shared
    markers) get a shift of a kilometre, and the candidate is never taken.
    """
    present = (beta > 0).astype(beta.dtype)
    frames = beta.shape[0]
    index = jnp.arange(frames)
    shifts = []
    for offset in offsets:
        for signed in (offset, -offset):
            shared = present * jnp.roll(present, signed, axis=0)
            count = jnp.maximum(jnp.sum(shared, axis=1), 1.0)
            source = index - signed
            usable = (jnp.sum(shared, axis=1) > 0) & (source >= 0) & (source < frames)
            shifts.append(jnp.stack([
                jnp.where(usable, jnp.sum(shared * (mi - jnp.roll(mi, signed, axis=0)), axis=1) / count, 1e3)
                for mi in m
            ]))
    return jnp.stack(shifts)


class FrameDamping(eqx.Module):
    """Per-frame damping ``mu_f`` added to the global ``lambda`` on each frame's block.

    A frame whose step is refused gets ``max(grow mu, bump)``; one whose step is taken
    ``mu / shrink``; values below ``zero_below`` drop to 0. A non-finite trial leaves mu
    as it was. The Marquardt scaling by the diagonal is floored at ``floor`` times the
    largest diagonal entry, so flat directions stay damped.
    """

    bump: float = 1e-3
    grow: float = 4.0
    shrink: float = 3.0
    zero_below: float = 1e-8
    floor: float = 1e-12

    def update(self, mu, take, finite):
        new = jnp.where(take, mu / self.shrink, jnp.maximum(self.grow * mu, self.bump))
        return jnp.where(finite, jnp.where(new < self.zero_below, 0.0, new), mu)


class PairLM(eqx.Module):
    """The pair problem's proposal for :class:`jaxskel._math.lm.LevenbergMarquardt`
    (module docstring): the Schur block-arrow step with per-frame damping, per-frame
    accept, and reseeding from the frames ``reseed_offsets`` before and after (one
    distance per step in turn, both directions).

    ``m`` (3 x (F, K)), ``beta`` (F, K), ``alpha``: the problem in planes; ``shifts``: the
    reseeding shifts (:func:`_neighbour_shifts`, computed once per solve by :meth:`of`).
    The solver's ``params`` are ``(c, r)`` (three (F,) planes, (K,)); ``aux`` is ``mu`` (F,).
    """

    m: tuple
    beta: Float[Array, "F K"]
    alpha: Float[Array, ""]
    shifts: Float[Array, "n 3 F"]
    frame_damping: FrameDamping = FrameDamping()
    reseed_offsets: tuple[int, ...] = eqx.field(static=True, default=(1, 4, 16))

    @classmethod
    def of(cls, problem: PairProblem, *, reseed_offsets: tuple[int, ...] = (1, 4, 16), **kw) -> PairLM:
        m = _planes(problem.markers)
        shifts = _neighbour_shifts(m, problem.beta, reseed_offsets)
        return cls(m, problem.beta, problem.alpha, shifts, reseed_offsets=reseed_offsets, **kw)

    def frame_costs(self, c, r) -> Float[Array, " F"]:
        return _frame_costs(self.m, self.beta, self.alpha, c, r)

    def init(self, solver: LevenbergMarquardt, c, r) -> LMState:
        """State at (c, r) (planes); nothing to fit when no frame has three markers."""
        frames = self.beta.shape[0]
        return solver.init(
            (c, r), jnp.sum(self.frame_costs(c, r)), jnp.zeros(frames, self.beta.dtype),
            done=~jnp.any(self.beta > 0),
        )

    def __call__(self, s: LMState) -> Proposal:
        (c, r), mu = s.params, s.aux
        hi = jax.lax.Precision.HIGHEST
        tiny = jnp.finfo(self.beta.dtype).tiny
        geometry = _geometry(self.m, c)  # at the current joints: the blocks and the kept joints' costs
        a6, b, c_diag, g_c, g_r = _blocks(self.m, self.beta, self.alpha, c, r, "positive", geometry)
        a_diag = (a6[0], a6[3], a6[5])
        # Marquardt scaling by the diagonal, floored so flat directions stay damped
        floor = self.frame_damping.floor * jnp.maximum(jnp.max(jnp.stack([jnp.max(x) for x in a_diag])), tiny)
        damping = s.lam + mu
        a_damped = list(a6)
        for k, diag in zip((0, 3, 5), a_diag):
            a_damped[k] = diag + damping * jnp.maximum(diag, floor)
        c_damped = c_diag * (1.0 + s.lam)
        dc, dr = _block_solve(tuple(a_damped), b, c_damped, tuple(-g for g in g_c), -g_r)
        model_c = tuple(ai + jnp.dot(bi, dr, precision=hi) for ai, bi in zip(_sym_apply(a6, dc), b))
        model_r = sum(jnp.dot(di, bi, precision=hi) for di, bi in zip(dc, b)) + c_diag * dr
        predicted = -(sum(jnp.sum(g * d) for g, d in zip(g_c, dc)) + jnp.sum(g_r * dr)) - 0.5 * (
            sum(jnp.sum(d * mc) for d, mc in zip(dc, model_c)) + jnp.sum(dr * model_r)
        )

        r_trial = r + dr
        stepped = tuple(ci + di for ci, di in zip(c, dc))
        moved = self.frame_costs(stepped, r_trial)
        kept = _costs_at(geometry[0], self.beta, self.alpha, r_trial)
        take = moved <= kept
        c_trial = tuple(jnp.where(take, x, y) for x, y in zip(stepped, c))
        c_trial, cost_frames = self._reseed(c, r_trial, c_trial, jnp.minimum(moved, kept), s.steps)
        cost_trial = jnp.sum(cost_frames)

        finite = jnp.isfinite(cost_trial) & jnp.all(jnp.isfinite(dr))
        for d in dc:
            finite = finite & jnp.all(jnp.isfinite(d))
        step = jnp.max(jnp.abs(dr))
        for ct, ci in zip(c_trial, c):
            step = jnp.maximum(step, jnp.max(jnp.abs(ct - ci)))
        return Proposal(
            params=(c_trial, r_trial), cost=cost_trial, predicted=predicted, step=step, finite=finite,
            aux=self.frame_damping.update(mu, take, finite),
        )

    def _reseed(self, c, r_trial, c_trial, cost_frames, steps):
        """Offer every frame a neighbour's joint (module docstring) and keep the cheapest:
        one distance per step in turn, both directions, so a step evaluates two candidates
        rather than ``2 len(reseed_offsets)`` (the frame costs dominate a step)."""
        turn = steps % len(self.reseed_offsets)
        for direction in (0, 1):

            def candidate_at(k, direction=direction):
                signed = self.reseed_offsets[k] * (1 if direction == 0 else -1)
                shift = self.shifts[2 * k + direction]
                return tuple(jnp.roll(ci, signed, axis=0) + shift[i] for i, ci in enumerate(c))

            candidate = candidate_at(0)
            for k in range(1, len(self.reseed_offsets)):
                candidate = tuple(jnp.where(turn == k, x, y) for x, y in zip(candidate_at(k), candidate))
            candidate_cost = self.frame_costs(candidate, r_trial)
            better = candidate_cost < cost_frames
            c_trial = tuple(jnp.where(better, x, y) for x, y in zip(candidate, c_trial))
            cost_frames = jnp.where(better, candidate_cost, cost_frames)
        return c_trial, cost_frames


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
    The controls may be traced, so changing them does not recompile. The iteration
    works on coordinate planes (see the planar kernels above).
    """
    solver = LevenbergMarquardt(rtol=rtol, atol=atol, max_steps=max_steps)
    pair = PairLM.of(problem)
    final = solver.run(pair, pair.init(solver, _planes(c0), r0))
    c, r = final.params
    return jnp.stack(c, axis=-1), r, final.steps, solver.result(final)
