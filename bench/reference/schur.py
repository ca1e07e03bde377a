"""Strong numpy reference of the joint stages: a batched Schur-complement Levenberg–Marquardt.

The same objective as :mod:`bench.reference.joints` (Kirk et al. 2005, §3.2), written as
in jaxskel with per-observation weights ``beta_fk = present_fk * n_max / n_k``:

    f(c, r) = 1/2 sum_fk beta_fk [ (d_fk - r_k)^2 + alpha d_fk ],   d_fk = |c_f - m_fk|,

over a joint position ``c_f`` per frame and a radius ``r_k`` per marker. ``2 f / (K n_max)``
is the paper's Q once the radii are at their optimum. The Hessian is block-arrow: a 3x3
block ``A_f`` per frame, coupled only to the K radii,

    A_f = sum_k beta [u u^T + s (I - u u^T)],  s = max((e + alpha/2) / d, 0),  e = d - r,
    B_f[:, k] = -beta u,   C = diag(sum_f beta),   u = (c_f - m_fk) / d,

(Gauss–Newton on the distance residuals plus the positive part of the curvature, which for
the prior is its exact Hessian). A damped step ``[A B; B^T C] [dc; dr] = -g`` is solved by
eliminating every frame's block: ``S = C - sum_f B_f^T A_f^-1 B_f`` (K x K),
``S dr = -g_r + sum_f B_f^T A_f^-1 g_f``, ``dc_f = -A_f^-1 (g_f + B_f dr)``. Per step and
pair that is ``O(F K)`` elementwise work plus one ``(K, 3F) x (3F, K)`` product.

The iteration is the one jaxskel runs (``jaxskel/joints/_cost_lm.py``), written
independently in numpy: Marquardt damping of the diagonal (floored at 1e-12 of the
largest entry) with Nielsen's update of ``lambda``; an extra per-frame damping ``mu_f``;
the trial radii are shared but each frame keeps its old joint when the step would raise
that frame's cost; every trial also offers each frame its neighbours' joints (1, 4 or 16
frames away in turn, both directions, moved by the mean displacement of the shared
markers) so frames stuck on the mirror branch are reseeded; the cost decreases
monotonically. The predicted decrease uses ``-g.d - d^T H d / 2 = (-g.d + d^T D d) / 2``
(``D`` the damping added to ``H``), which needs no extra product with ``H``. Stopping:
max step <= ``atol`` metres, or an accepted step lowered f by <= ``rtol f`` and the model
predicted no more (jaxskel's float64 defaults: ``1e-10``/``1e-9`` for the all-pairs costs,
``1e-7``/``1e-6`` for the full-frame tree joints).

What numpy can do that a vmapped while loop cannot: a batch of pairs (padded to a common
K, frames on the minor axis so every reduction over markers is a contiguous add) is
*compacted* as pairs converge, so no finished pair costs anything. Pairs are sorted by K
and cut into chunks, and the chunks (all-pairs pass) or joints (tree pass) are spread over
a thread pool (numpy releases the GIL inside its loops). Starts are those of
:mod:`bench.reference.joints` (its closed-form algebraic fit, or the consistency start
for pairs that never show five markers). Nothing here imports jaxskel.

Differences from jaxskel that remain: every tree joint keeps the prior ``alpha`` (as the
scipy reference does; jaxskel drops it for joints its identifiability test finds
determined), and there is no identifiability / uncertainty / pose check.
"""

from __future__ import annotations

import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import clean_and_segment, timed_output
from . import rigid as _rigid
from .joints import (
    MIN_FRAME_MARKERS,
    PairFit,
    algebraic_start,
    consistency_start,
    feasible_pairs,
    mst_topology,
    mst_weight,
    tree_start,
)

__all__ = [
    "LMResult",
    "lm_batch",
    "solve_pair",
    "solve_pairs",
    "all_pair_costs",
    "mst_topology",
    "tree_joints",
    "fit_strong",
    "PAIR_TOL",
    "TREE_TOL",
]

#: (rtol, atol) of the all-pairs pass and of the full-frame tree pass (jaxskel's float64 values).
PAIR_TOL = (1e-10, 1e-9)
TREE_TOL = (1e-7, 1e-6)
PAIR_STEPS, TREE_STEPS = 100, 500
_RESEED_OFFSETS = (1, 4, 16)
_MU_BUMP = 1e-3
_LAMBDA_MAX = 1e30
#: status codes of :class:`LMResult`
CONVERGED, MAX_STEPS, DIVERGED, NOTHING = 0, 1, 2, -1


def default_workers() -> int:
    """Threads for the pair/joint pool: the CPUs this process may use, at most 4."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    return max(1, min(n, 4))


@dataclasses.dataclass
class LMResult:
    """Batch solution: ``c`` (P, F, 3) joint positions (centred frame added back),
    ``r`` (P, K) radii, ``steps`` (P,), ``status`` (P,) (0 converged, 1 step cap, 2 diverged,
    -1 nothing to fit), ``valid`` (P, F) frames with >= 3 markers, and ``history`` (list of
    P arrays of the objective after every step) when asked for."""

    c: np.ndarray
    r: np.ndarray
    steps: np.ndarray
    status: np.ndarray
    valid: np.ndarray
    history: list | None = None


def _inv_sym3(a00, a01, a02, a11, a12, a22):
    """Inverse of symmetric 3x3 blocks given by their six upper entries (arrays), by cofactors."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv_det = 1.0 / det
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    return c00 * inv_det, c01 * inv_det, c02 * inv_det, c11 * inv_det, c12 * inv_det, c22 * inv_det


class _Batch:
    """The fixed data of P pairs in the solver's layout: markers (P, 3, K, F), weights (P, K, F)."""

    def __init__(self, m, beta, alpha, c, r):
        self.m, self.beta, self.alpha = m, beta, alpha  # alpha (P, 1, 1)
        self.c, self.r = c, r  # (P, 3, F), (P, K)
        present = beta > 0
        self.valid = present.any(1)  # (P, F)
        self.invalid = (~self.valid).astype(float)
        c_diag = beta.sum(2)
        self.c_diag = np.where(present.any(2), c_diag, 1.0)
        self.shifts = self._shifts(present)

    def _shifts(self, present):
        """Displacement of the shared markers from frame f - o to f, for each signed reseed offset o
        (P, 3, F); 1 km where there is no usable neighbour (never taken)."""
        pf = present.astype(float)
        n_frames = pf.shape[2]
        index = np.arange(n_frames)
        out = {}
        for offset in _RESEED_OFFSETS:
            for o in (offset, -offset):
                shared = pf * np.roll(pf, o, axis=2)
                count = shared.sum(1)  # (P, F)
                source = index - o
                usable = (count > 0) & (source >= 0) & (source < n_frames)
                disp = np.einsum("pkf,pikf->pif", shared, self.m - np.roll(self.m, o, axis=3))
                out[o] = np.where(usable[:, None, :], disp / np.maximum(count, 1.0)[:, None, :], 1e3)
        return out

    def take(self, keep):
        self.m, self.beta, self.alpha = self.m[keep], self.beta[keep], self.alpha[keep]
        self.c, self.r = self.c[keep], self.r[keep]
        self.valid, self.invalid, self.c_diag = self.valid[keep], self.invalid[keep], self.c_diag[keep]
        self.shifts = {o: s[keep] for o, s in self.shifts.items()}

    def distances(self, c):
        """d (P, K, F) of joints ``c`` (P, 3, F) and the differences v = c - m (P, 3, K, F)."""
        v = c[:, :, None] - self.m
        d2 = np.einsum("pikf,pikf->pkf", v, v)
        np.maximum(d2, 1e-300, out=d2)
        return np.sqrt(d2, out=d2), v

    def frame_costs(self, d, r):
        """1/2 sum_k beta [(d - r)^2 + alpha d] per frame (P, F), for distances ``d`` (..., P, K, F):
        ``(d - r)^2 + alpha d = (d - r + alpha/2)^2 + alpha (r - alpha/4)``, one fused product-sum."""
        shifted = (r - 0.5 * self.alpha[:, :, 0])[:, :, None]
        e = d - shifted
        const = np.einsum("pkf,pk->pf", self.beta, self.alpha[:, :, 0] * (r - 0.25 * self.alpha[:, :, 0]))
        lead = "c" if d.ndim == 4 else ""
        return 0.5 * (np.einsum(f"{lead}pkf,pkf,{lead}pkf->{lead}pf", e, self.beta, e) + const)

    def trial_distances(self, c):
        """d (C, P, K, F) of C candidate joint sets ``c`` (C, P, 3, F)."""
        v = c[:, :, :, None] - self.m
        d2 = np.einsum("cpikf,cpikf->cpkf", v, v)
        return np.sqrt(d2, out=d2)


def _step(b: _Batch, lam, nu, mu, cost, turn, rtol, atol):
    """One LM iteration of every pair in ``b`` (see the module docstring). Updates ``b.c``, ``b.r``;
    returns (lam, nu, mu, cost, done, failed)."""
    beta, alpha = b.beta, b.alpha
    c, r = b.c, b.r
    n_p, n_k, n_f = beta.shape
    d, v = b.distances(c)
    inv_d = 1.0 / d
    u = v
    u *= inv_d[:, None]  # unit vectors, in place of v
    e = d - r[:, :, None]
    we = e + 0.5 * alpha
    we *= beta  # beta (e + alpha/2)
    g_c = np.einsum("pkf,pikf->pif", we, u)  # (P, 3, F)
    g_r = -np.einsum("pkf,pkf->pk", beta, e)
    bs = we * inv_d
    np.maximum(bs, 0.0, out=bs)  # beta * positive part of the curvature
    w_eye = bs.sum(1)  # (P, F)
    w_uu = beta - bs
    q = beta[:, None] * u  # -B, (P, 3, K, F)
    t = w_uu[:, None] * u
    a00 = np.einsum("pkf,pkf->pf", t[:, 0], u[:, 0]) + w_eye + b.invalid
    a11 = np.einsum("pkf,pkf->pf", t[:, 1], u[:, 1]) + w_eye + b.invalid
    a22 = np.einsum("pkf,pkf->pf", t[:, 2], u[:, 2]) + w_eye + b.invalid
    a01 = np.einsum("pkf,pkf->pf", t[:, 0], u[:, 1])
    a02 = np.einsum("pkf,pkf->pf", t[:, 0], u[:, 2])
    a12 = np.einsum("pkf,pkf->pf", t[:, 1], u[:, 2])
    # Marquardt damping, floored so flat directions stay damped
    top = np.maximum(np.maximum(a00.max(1), a11.max(1)), a22.max(1))
    floor = (1e-12 * np.maximum(top, np.finfo(float).tiny))[:, None]
    damp = lam[:, None] + mu  # (P, F)
    d00 = damp * np.maximum(a00, floor)
    d11 = damp * np.maximum(a11, floor)
    d22 = damp * np.maximum(a22, floor)
    ainv = _inv_sym3(a00 + d00, a01, a02, a11 + d11, a12, a22 + d22)
    i00, i01, i02, i11, i12, i22 = ainv
    ainv_full = np.stack([np.stack(row, 1) for row in ((i00, i01, i02), (i01, i11, i12), (i02, i12, i22))], 1)
    z = np.einsum("pijf,pjkf->pikf", ainv_full, q)  # A^-1 (-B), (P, 3, K, F)
    h = np.einsum("pijf,pjf->pif", ainv_full, g_c)  # A^-1 g, (P, 3, F)
    c_damped = b.c_diag * (1.0 + lam[:, None])
    schur = -sum(q[:, i] @ z[:, i].transpose(0, 2, 1) for i in range(3))
    schur[:, np.arange(n_k), np.arange(n_k)] += c_damped
    rhs = -g_r - sum((q[:, i] @ h[:, i, :, None])[..., 0] for i in range(3))
    dr = np.linalg.solve(schur, rhs[..., None])[..., 0]
    dc = np.einsum("pikf,pk->pif", z, dr) - h
    # predicted decrease: (-g.d + d^T D d) / 2, D = the damping added to the model
    gd = np.einsum("pif,pif->p", g_c, dc) + np.einsum("pk,pk->p", g_r, dr)
    ddd = (
        np.einsum("pf,pf->p", d00, dc[:, 0] ** 2)
        + np.einsum("pf,pf->p", d11, dc[:, 1] ** 2)
        + np.einsum("pf,pf->p", d22, dc[:, 2] ** 2)
        + lam * np.einsum("pk,pk->p", b.c_diag, dr * dr)
    )
    predicted = 0.5 * (ddd - gd)

    r_trial = r + dr
    # trial joints: the step, and the neighbours' joints (one reseed distance per step, both directions)
    offset = _RESEED_OFFSETS[turn % len(_RESEED_OFFSETS)]
    trials = np.empty((3, n_p, 3, n_f))
    np.add(c, dc, out=trials[0])
    for slot, o in ((1, offset), (2, -offset)):
        trials[slot] = np.roll(c, o, axis=2)
        trials[slot] += b.shifts[o]
    costs = b.frame_costs(b.trial_distances(trials), r_trial)  # (3, P, F)
    moved = costs[0]
    kept = b.frame_costs(d, r_trial)
    take = moved <= kept
    c_trial = np.where(take[:, None], trials[0], c)
    cost_frames = np.minimum(moved, kept)
    for slot in (1, 2):
        better = costs[slot] < cost_frames
        c_trial = np.where(better[:, None], trials[slot], c_trial)
        np.minimum(costs[slot], cost_frames, out=cost_frames)
    cost_trial = cost_frames.sum(1)

    finite = np.isfinite(cost_trial) & np.isfinite(dr).all(1) & np.isfinite(dc).all((1, 2))
    actual = cost - cost_trial
    accept = finite & (actual > 0)
    rho = actual / np.where(predicted > 0, predicted, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        lam_new = np.where(accept, lam * np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), lam * nu)
    nu = np.where(accept, 2.0, 2.0 * nu)
    mu_new = np.where(take, mu / 3.0, np.maximum(4.0 * mu, _MU_BUMP))
    mu_new = np.where(mu_new < 1e-8, 0.0, mu_new)
    mu = np.where(finite[:, None], mu_new, mu)
    with np.errstate(invalid="ignore"):
        step = np.maximum(np.abs(dr).max(1), np.abs(c_trial - c).max((1, 2)))
    flat = accept & (actual <= rtol * cost) & (predicted <= rtol * cost)
    b.c = np.where(accept[:, None, None], c_trial, c)
    b.r = np.where(accept[:, None], r_trial, r)
    cost = np.where(accept, cost_trial, cost)
    done = (finite & (step <= atol)) | flat
    return lam_new, nu, mu, cost, done, lam_new > _LAMBDA_MAX


def lm_batch(
    x: np.ndarray,
    mask: np.ndarray,
    alpha,
    c0: np.ndarray,
    r0: np.ndarray,
    *,
    max_steps: int = PAIR_STEPS,
    rtol: float = PAIR_TOL[0],
    atol: float = PAIR_TOL[1],
    history: bool = False,
) -> LMResult:
    """Minimise f for P pairs at once: markers ``x`` (P, F, K, 3) present where ``mask`` (P, F, K)
    (padding: absent), prior weights ``alpha`` (scalar or (P,)), start ``c0`` (P, F, 3), ``r0`` (P, K).

    Frames with fewer than three present markers carry no weight and keep their start.
    Pairs leave the batch as they stop (compaction), so a finished pair costs nothing.
    """
    x = np.asarray(x, float)
    mask = np.asarray(mask, bool)
    n_p, n_f, n_k = mask.shape
    alpha = np.broadcast_to(np.asarray(alpha, float), (n_p,)).copy()
    present = mask & (mask.sum(2, keepdims=True) >= MIN_FRAME_MARKERS)
    n = present.sum(1)  # (P, K)
    n_max = np.maximum(n.max(1), 1)
    beta = present * (n_max[:, None] / np.where(n > 0, n, 1))[:, None, :]
    weight = mask[..., None].astype(float)
    ref = (x * weight).sum((1, 2)) / np.maximum(weight.sum((1, 2)), 1.0)  # (P, 3)
    centred = np.where(mask[..., None], x - ref[:, None, None], 0.0)
    m = np.ascontiguousarray(centred.transpose(0, 3, 2, 1))  # (P, 3, K, F)
    b = _Batch(
        m, np.ascontiguousarray(beta.transpose(0, 2, 1)), alpha[:, None, None],
        np.ascontiguousarray((np.asarray(c0, float) - ref[:, None]).transpose(0, 2, 1)), np.asarray(r0, float).copy(),
    )
    valid_out = b.valid.copy()
    out_c = b.c.copy()
    out_r = b.r.copy()
    out_steps = np.zeros(n_p, int)
    out_status = np.full(n_p, MAX_STEPS)
    hist = [[] for _ in range(n_p)] if history else None

    rows = np.arange(n_p)
    cost = b.frame_costs(b.distances(b.c)[0], b.r).sum(1)
    nothing = ~b.valid.any(1)
    if history:
        for i in range(n_p):
            hist[i].append(float(cost[i]))
    lam = np.full(n_p, 1e-3)
    nu = np.full(n_p, 2.0)
    mu = np.zeros((n_p, n_f))
    out_status[nothing] = NOTHING
    keep = ~nothing
    steps = 0
    while True:
        if not keep.all():
            rows = rows[keep]
            b.take(keep)
            lam, nu, mu, cost = lam[keep], nu[keep], mu[keep], cost[keep]
        if rows.size == 0 or steps >= max_steps:
            break
        lam, nu, mu, cost, done, failed = _step(b, lam, nu, mu, cost, steps, rtol, atol)
        steps += 1
        if history:
            for i, row in enumerate(rows):
                hist[row].append(float(cost[i]))
        stop = done | failed | (steps >= max_steps)
        if stop.any():
            out_c[rows[stop]] = b.c[stop]
            out_r[rows[stop]] = b.r[stop]
            out_steps[rows[stop]] = steps
            out_status[rows[stop]] = np.where(done[stop], CONVERGED, np.where(failed[stop], DIVERGED, MAX_STEPS))
        keep = ~stop
    c = out_c.transpose(0, 2, 1) + ref[:, None]
    return LMResult(c=c, r=out_r, steps=out_steps, status=out_status, valid=valid_out,
                    history=[np.asarray(h) for h in hist] if history else None)


# ----------------------------------------------------------------------------- pair API
def _q_cost(c, x, obs, alpha):
    """(Q, variance part, radii = mean distances) of joints ``c`` (F, 3) on markers ``x`` (F, K, 3)."""
    d = np.sqrt(np.where(obs, ((c[:, None] - x) ** 2).sum(-1), 0.0))
    n = obs.sum(0)
    ok = n > 0
    mean = np.where(ok, (d * obs).sum(0) / np.maximum(n, 1), 0.0)
    var = np.where(ok, (((d - mean) ** 2) * obs).sum(0) / np.maximum(n, 1), 0.0)
    k = max(int(ok.sum()), 1)
    return float(var.sum() / k + alpha * mean.sum() / k), float(var.sum() / k), mean


def pair_start(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scipy reference's start on all frames: algebraic fit, or the consistency start for
    pairs that never show five markers. Frames with < 3 markers are ignored (their joint is
    the start's fallback)."""
    obs = mask & (mask.sum(1, keepdims=True) >= MIN_FRAME_MARKERS)
    start = consistency_start(x, obs) if obs.sum(1).max() < 5 else None
    return start if start is not None else algebraic_start(x, obs)


@dataclasses.dataclass
class _Job:
    x: np.ndarray  # (F, K, 3)
    mask: np.ndarray  # (F, K)
    alpha: float
    c0: np.ndarray | None = None
    r0: np.ndarray | None = None


def _solve_chunk(jobs: list[_Job], max_steps, rtol, atol, history) -> list[PairFit]:
    n_f = jobs[0].mask.shape[0]
    k_pad = max(j.mask.shape[1] for j in jobs)
    xs = np.zeros((len(jobs), n_f, k_pad, 3))
    ms = np.zeros((len(jobs), n_f, k_pad), bool)
    c0 = np.zeros((len(jobs), n_f, 3))
    r0 = np.zeros((len(jobs), k_pad))
    for i, j in enumerate(jobs):
        k = j.mask.shape[1]
        xs[i, :, :k], ms[i, :, :k] = j.x, j.mask
        if j.c0 is None or j.r0 is None:
            ca, ra = pair_start(j.x, j.mask)
            j.c0 = ca if j.c0 is None else j.c0
            j.r0 = ra if j.r0 is None else j.r0
        c0[i], r0[i, :k] = j.c0, j.r0
    res = lm_batch(xs, ms, [j.alpha for j in jobs], c0, r0, max_steps=max_steps, rtol=rtol, atol=atol,
                   history=history)
    fits = []
    for i, j in enumerate(jobs):
        k = j.mask.shape[1]
        valid = res.valid[i]
        obs = j.mask & valid[:, None]
        if not valid.any():
            fits.append(PairFit(np.full((n_f, 3), np.nan), np.zeros(k), np.inf, np.inf, 0, -1))
            continue
        cost, variance, radii = _q_cost(res.c[i][valid], j.x[valid], obs[valid], j.alpha)
        positions = np.where(valid[:, None], res.c[i], np.nan)
        fit = PairFit(positions, radii, cost, variance, int(res.steps[i]), int(res.status[i]))
        if history:
            fit.history = res.history[i]
        fits.append(fit)
    return fits


def solve_pairs(
    xs: list[np.ndarray],
    masks: list[np.ndarray],
    alpha: float,
    *,
    c0s: list | None = None,
    r0s: list | None = None,
    max_steps: int = PAIR_STEPS,
    rtol: float = PAIR_TOL[0],
    atol: float = PAIR_TOL[1],
    chunk: int = 16,
    workers: int | None = None,
    history: bool = False,
) -> list[PairFit]:
    """Solve many pairs (``xs[i]`` (F, K_i, 3), same F) in chunks of ``chunk`` pairs of similar K,
    chunks spread over ``workers`` threads. Starts as :func:`pair_start` unless given."""
    jobs = [
        _Job(x, m, alpha, None if c0s is None else c0s[i], None if r0s is None else r0s[i])
        for i, (x, m) in enumerate(zip(xs, masks))
    ]
    order = sorted(range(len(jobs)), key=lambda i: jobs[i].mask.shape[1])
    chunks = [order[i : i + chunk] for i in range(0, len(order), chunk)]
    workers = default_workers() if workers is None else workers

    def run(idx):
        return _solve_chunk([jobs[i] for i in idx], max_steps, rtol, atol, history)

    if workers > 1 and len(chunks) > 1:
        # biggest chunks first so the pool ends together
        chunks.sort(key=lambda idx: -max(jobs[i].mask.shape[1] for i in idx))
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(run, chunks))
    else:
        results = [run(idx) for idx in chunks]
    out: list = [None] * len(jobs)
    for idx, fits in zip(chunks, results):
        for i, fit in zip(idx, fits):
            out[i] = fit
    return out


def solve_pair(
    x: np.ndarray,
    mask: np.ndarray,
    alpha: float,
    *,
    c0: np.ndarray | None = None,
    r0: np.ndarray | None = None,
    max_nfev: int | None = PAIR_STEPS,
    tol: tuple[float, float] = PAIR_TOL,
    history: bool = False,
) -> PairFit:
    """One pair, the contract of :func:`bench.reference.joints.solve_pair` (``nfev`` = LM steps;
    ``status`` 0 converged, 1 step cap, 2 diverged, -1 no frame with three markers).
    With ``history`` the fit also carries ``history``: the objective after every step."""
    return solve_pairs(
        [np.asarray(x, float)], [np.asarray(mask, bool)], alpha,
        c0s=None if c0 is None else [c0], r0s=None if r0 is None else [r0],
        max_steps=max_nfev or PAIR_STEPS, rtol=tol[0], atol=tol[1], workers=1, history=history,
    )[0]


def all_pair_costs(
    x: np.ndarray,
    mask: np.ndarray,
    seg: np.ndarray,
    n_segments: int,
    *,
    alpha: float = 1e-5,
    max_frames: int = 300,
    max_nfev: int = PAIR_STEPS,
    pairs: list[tuple[int, int]] | None = None,
    chunk: int = 16,
    workers: int | None = None,
) -> tuple[np.ndarray, dict, np.ndarray]:
    """As :func:`bench.reference.joints.all_pair_costs` (same frames, feasibility and MST
    weight Q / f), every pair solved by the batched Schur LM."""
    frames, feasible, xs, ms = feasible_pairs(x, mask, seg, n_segments, max_frames=max_frames, pairs=pairs)
    cost = np.full((n_segments, n_segments), np.inf)
    fitted = solve_pairs(xs, ms, alpha, max_steps=max_nfev, chunk=chunk, workers=workers)
    fits = {}
    for (a, b), m_pair, fit in zip(feasible, ms, fitted):
        fits[(a, b)] = fit
        cost[a, b] = cost[b, a] = mst_weight(fit.cost, m_pair)
    return cost, fits, frames


def tree_joints(
    x: np.ndarray,
    mask: np.ndarray,
    seg: np.ndarray,
    edges: np.ndarray,
    fits: dict,
    pair_frames: np.ndarray,
    *,
    alpha: float = 1e-5,
    max_nfev: int = TREE_STEPS,
    frames: np.ndarray | None = None,
    tol: tuple[float, float] = TREE_TOL,
    workers: int | None = None,
    info: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`bench.reference.joints.tree_joints`: each tree joint re-solved on all frames
    (or ``frames``) from the pair pass interpolated in time and its radii; one joint per
    task, joints spread over ``workers`` threads (most first-pass steps first).
    Returns ``(positions (F, J, 3), cost (J,))``; ``info`` (a dict) receives the LM ``steps``
    and marker counts ``ks`` per joint."""
    frames = np.arange(x.shape[0]) if frames is None else frames
    xf, mf = x[frames], mask[frames]
    jobs = []
    for p, c in edges:
        idx, c0, r0 = tree_start(seg, fits, pair_frames, frames, p, c)
        jobs.append((xf[:, idx], mf[:, idx], c0, r0, fits[(min(p, c), max(p, c))].nfev))
    workers = default_workers() if workers is None else workers

    def run(j):
        xj, mj, c0, r0, _ = jobs[j]
        return solve_pairs([xj], [mj], alpha, c0s=[c0], r0s=[r0], max_steps=max_nfev, rtol=tol[0], atol=tol[1],
                           workers=1)[0]

    order = sorted(range(len(jobs)), key=lambda j: -jobs[j][4])
    if workers > 1 and len(jobs) > 1:
        with ThreadPoolExecutor(workers) as pool:
            done = dict(zip(order, pool.map(run, order)))
    else:
        done = {j: run(j) for j in order}
    out = np.full((frames.size, len(edges), 3), np.nan)
    costs = np.full(len(edges), np.inf)
    steps = np.zeros(len(edges), int)
    for j, fit in done.items():
        out[:, j] = fit.positions
        costs[j] = fit.cost
        steps[j] = fit.nfev
    if info is not None:
        info["steps"], info["ks"] = steps, np.array([j[1].shape[1] for j in jobs])
    return out, costs


def fit_strong(
    positions: np.ndarray,
    rate: float,
    n_segments: int | None = None,
    *,
    alpha: float = 1e-5,
    topology_frames: int = 300,
    clean_data: bool = True,
    stages: tuple[str, ...] = ("clean", "segment", "joint_costs", "tree_joints", "rigid"),
    seed: int = 0,
    workers: int | None = None,
) -> dict:
    """The whole chain with the Schur LM joint stages (clean and segmentation from
    :mod:`bench.reference.segment`, all-pairs costs on ``topology_frames`` frames, MST, tree
    joints on all frames, Procrustes skeleton from :mod:`bench.reference.rigid`); the dict of
    :func:`bench.reference.fit_reference` (``timings`` and ``cpu`` per stage, outputs), plus the
    LM steps and marker counts of every pair (``pair_steps``, ``pair_ks``) and tree joint
    (``tree_steps``, ``tree_ks``)."""
    out, tick = timed_output()
    x, mask, seg = clean_and_segment(out, tick, positions, rate, n_segments, clean_data=clean_data, stages=stages,
                                     seed=seed)
    n_seg = int(seg.max()) + 1
    if "joint_costs" not in stages:
        return out

    t0, c0 = time.perf_counter(), time.process_time()
    cost, fits, pair_frames = all_pair_costs(x, mask, seg, n_seg, alpha=alpha, max_frames=topology_frames,
                                             workers=workers)
    tick("joint_costs", t0, c0)
    out["pair_cost"], out["pair_fits"] = cost, fits
    out["pair_steps"] = {k: f.nfev for k, f in fits.items()}
    out["pair_ks"] = {k: len(f.radii) for k, f in fits.items()}

    t0, c0 = time.perf_counter(), time.process_time()
    edges, root = mst_topology(cost)
    out["edges"], out["root"] = edges, root
    if "tree_joints" not in stages:
        return out
    info: dict = {}
    jp, jcost = tree_joints(x, mask, seg, edges, fits, pair_frames, alpha=alpha, workers=workers, info=info)
    tick("tree_joints", t0, c0)
    out["joint_cost"] = jcost
    out["tree_steps"], out["tree_ks"] = info["steps"].tolist(), info["ks"].tolist()
    out["joint_positions"], out["joint_frames"] = jp, np.arange(x.shape[0])
    if "rigid" not in stages:
        return out

    t0, c0 = time.perf_counter(), time.process_time()
    out["skeleton"] = _rigid.fit_rigid(x, mask, seg, edges, root, jp)
    tick("rigid", t0, c0)
    return out
