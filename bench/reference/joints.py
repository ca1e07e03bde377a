"""Reference joint costs, MST topology and tree joints (Kirk et al. 2005, §3.2) in numpy/scipy.

The same objective as :mod:`jaxskel.joints._cost`: for two marker groups (K markers, F
frames) and a joint trajectory ``c_f``,

    Q = 1/K sum_k [ var_f |c_f - m_fk| + alpha mean_f |c_f - m_fk| ],

written as least squares over ``z = (c_1..c_F, r_1..r_K)`` with residuals

    e_fk = sqrt(w_k) (|c_f - m_fk| - r_k),     p_fk = sqrt(alpha w_k |c_f - m_fk|),

``w_k = 1/n_k`` (frames where marker k is present in a frame with >= 3 of the pair's
markers). Solved per pair with ``scipy.optimize.least_squares`` (trust-region
reflective) on a sparse Jacobian: each residual touches its frame's three joint
coordinates and its marker's radius. By default the Jacobian is analytic (a fixed
CSR pattern whose values are refilled each call, the fastest of the variants
measured); ``jac="sparsity"`` gives scipy the pattern (``jac_sparsity``) and lets it
difference. Frames with fewer than three present markers carry no information and
are left out of the unknowns (their joint is NaN).

The start is the same closed-form algebraic fit jaxskel uses
(:mod:`jaxskel.joints._cost_init`), ported to numpy: squaring |c - m|^2 = s_k makes
the problem linear and eliminating each frame's 3x3 block leaves a K x K system.
Pairs that never show five markers take jaxskel's consistency start instead (the
same 54 starting points, ``u_f = |c_f|^2`` solved for the radii by
``scipy.optimize.least_squares``).

A competent day's work, not a strawman: vectorised numpy inside a pair, sparse
Jacobians, the same start, tolerances matched to the accuracy the answer needs.
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.sparse.csgraph import minimum_spanning_tree

__all__ = [
    "PairFit",
    "algebraic_start",
    "consistency_start",
    "solve_pair",
    "all_pair_costs",
    "mst_topology",
    "tree_joints",
]

MIN_FRAME_MARKERS = 3
MIN_PAIR_MARKERS = 4
MIN_PAIR_FRAMES = 10


@dataclasses.dataclass
class PairFit:
    """One pair's joint: ``positions`` (F, 3) NaN where undefined, ``radii`` (K,), cost Q (m^2)."""

    positions: np.ndarray
    radii: np.ndarray
    cost: float
    variance: float
    nfev: int
    status: int


def algebraic_start(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linearised joint positions (F, 3) and radii (K,), numpy port of jaxskel's start."""
    w = mask.astype(float)
    n = w.sum(1, keepdims=True)
    safe_n = np.maximum(n, 1.0)
    mbar = (w[..., None] * x).sum(1) / safe_n
    q = (x * x).sum(-1)
    qbar = (w * q).sum(1, keepdims=True) / safe_n
    u = -2.0 * (x - mbar[:, None]) * w[..., None]
    b = -(q - qbar) * w
    k = x.shape[1]
    eye = np.eye(k)
    p = w[:, :, None] * (eye[None] - w[:, None, :] / safe_n[:, :, None])
    utu = np.einsum("fki,fkj->fij", u, u)
    ev = np.linalg.eigvalsh(utu)
    good = (n[:, 0] >= 5) & (ev[:, 0] > 1e-8 * np.maximum(ev[:, -1], 1e-300))
    inv = np.linalg.inv(np.where(good[:, None, None], utu, np.eye(3)))
    proj = np.einsum("fki,fij,flj->fkl", u, inv, u)
    resid = (eye[None] - proj) * good[:, None, None]
    lhs = np.einsum("fki,fkl,flj->ij", p, resid, p)
    rhs = np.einsum("fki,fkl,fl->i", p, resid, b)
    if good.any():
        scale = np.trace(lhs) / k
        present = ((w * good[:, None]).sum(0) > 0).astype(float)
        s = np.linalg.solve(lhs + 1e-9 * scale * eye + np.diag(1.0 - present) * scale, rhs)
    else:
        s = np.zeros(k)
    c = np.einsum("fij,fkj,fk->fi", inv, u, b - np.einsum("fkl,l->fk", p, s))
    c = np.where(good[:, None], c, mbar)
    d = np.sqrt(np.maximum(((c[:, None] - x) ** 2).sum(-1), 1e-300))
    r = (w * d).sum(0) / np.maximum(w.sum(0), 1.0)
    return c, r


def consistency_start(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """jaxskel's start for pairs without five markers in a frame, in numpy/scipy:
    ``(c_f, u_f) = G_f (s - q_f)`` from the linear squared-distance conditions, the radii
    ``s`` minimising ``sum_f (u_f - |c_f|^2)^2`` from 54 starting joint points (a
    {-1, 0, 1}^3 grid along the principal axes of the best-covered frame, at 0.5 and 1
    times its marker span). ``None`` when no frame has four non-coplanar markers."""
    w = mask.astype(float)
    origin = (w[..., None] * x).sum((0, 1)) / max(w.sum(), 1.0)
    scale = np.sqrt((w * ((x - origin) ** 2).sum(-1)).sum() / max(w.sum(), 1.0)) or 1.0
    y = np.where(mask[..., None], (x - origin) / scale, 0.0)
    q = (y * y).sum(-1)
    a = np.concatenate([-2.0 * y, np.ones_like(y[..., :1])], -1) * w[..., None]
    normal = np.einsum("fki,fkj->fij", a, a)
    ev = np.linalg.eigvalsh(normal)
    usable = (w.sum(1) >= 4) & (ev[:, 0] > 1e-6 * np.maximum(ev[:, -1], 1e-300))
    if not usable.any():
        return None
    gain = np.einsum("fij,fkj->fik", np.linalg.inv(normal[usable]), a[usable])  # (U, 4, K)
    qu = q[usable]

    def unknowns(s):
        return np.einsum("fik,fk->fi", gain, s[None] - qu)

    def residual(s):
        v = unknowns(s)
        return v[:, 3] - (v[:, :3] ** 2).sum(-1)

    ref = int(np.argmax(np.where(usable, w.sum(1), -1.0)))
    seen = mask[ref]
    y0 = y[ref]
    centre = y0[seen].mean(0)
    _, axes = np.linalg.eigh((y0[seen] - centre).T @ (y0[seen] - centre))
    span = np.sqrt(((y0[seen][:, None] - y0[seen][None]) ** 2).sum(-1).max())
    grid = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], float)
    best = None
    for factor in (0.5, 1.0):
        for g in grid:
            point = centre + factor * span * axes @ g
            sol = least_squares(residual, ((point - y0) ** 2).sum(-1), method="lm", max_nfev=200)
            if best is None or sol.cost < best.cost:
                best = sol
    c = np.where(usable[:, None], 0.0, (w[..., None] * y).sum(1) / np.maximum(w.sum(1), 1.0)[:, None])
    c[usable] = unknowns(best.x)[:, :3]
    used = w * usable[:, None]
    d = np.sqrt(((c[:, None] - y) ** 2).sum(-1))
    r = (used * d).sum(0) / np.maximum(used.sum(0), 1.0)
    return c * scale + origin, r * scale


def _pair_cost(c: np.ndarray, x: np.ndarray, obs: np.ndarray, alpha: float) -> tuple[float, float, np.ndarray]:
    """(Q, variance part, radii = mean distances) of joint positions ``c`` (F, 3)."""
    d = np.linalg.norm(np.where(obs[..., None], c[:, None] - x, 0.0), axis=-1)
    n = obs.sum(0)
    ok = n > 0
    mean = np.where(ok, (d * obs).sum(0) / np.maximum(n, 1), 0.0)
    var = np.where(ok, (((d - mean) ** 2) * obs).sum(0) / np.maximum(n, 1), 0.0)
    k = max(int(ok.sum()), 1)
    return float(var.sum() / k + alpha * mean.sum() / k), float(var.sum() / k), mean


def solve_pair(
    x: np.ndarray,
    mask: np.ndarray,
    alpha: float,
    *,
    c0: np.ndarray | None = None,
    r0: np.ndarray | None = None,
    max_nfev: int | None = 100,
    tol: float = 1e-8,
    jac: str = "analytic",
) -> PairFit:
    """Joint between the markers ``x`` (F, K, 3) present where ``mask`` (F, K), least squares."""
    f_all, k = mask.shape
    frame_ok = mask.sum(1) >= MIN_FRAME_MARKERS
    obs = mask & frame_ok[:, None]
    frames = np.flatnonzero(frame_ok)
    if frames.size == 0:
        return PairFit(np.full((f_all, 3), np.nan), np.zeros(k), np.inf, np.inf, 0, -1)
    xs, ob = x[frames], obs[frames]
    if c0 is None or r0 is None:
        start = consistency_start(xs, ob) if ob.sum(1).max() < 5 else None
        ca, ra = start if start is not None else algebraic_start(xs, ob)
        c0 = ca if c0 is None else c0[frames]
        r0 = ra if r0 is None else r0
    else:
        c0 = c0[frames]
    f = frames.size
    fi, ki = np.nonzero(ob)  # observations, frame-major
    n_obs = fi.size
    n_k = np.maximum(ob.sum(0), 1)
    sw = np.sqrt(1.0 / n_k[ki])
    sa = np.sqrt(alpha / n_k[ki])
    xo = xs[fi, ki]
    use_prior = alpha > 0
    n_res = n_obs * (2 if use_prior else 1)

    def unpack(z):
        return z[: 3 * f].reshape(f, 3), z[3 * f :]

    def geometry(z):
        c, r = unpack(z)
        diff = c[fi] - xo
        d = np.sqrt(np.maximum((diff * diff).sum(1), 1e-30))
        return diff, d, r

    def residuals(z):
        _, d, r = geometry(z)
        e = sw * (d - r[ki])
        return np.concatenate([e, sa * np.sqrt(d)]) if use_prior else e

    # Fixed sparsity pattern: rows of e touch (c_f, r_k); rows of p touch c_f.
    rows_e = np.repeat(np.arange(n_obs), 4)
    cols_e = np.stack([3 * fi, 3 * fi + 1, 3 * fi + 2, 3 * f + ki], 1).ravel()
    rows, cols = [rows_e], [cols_e]
    if use_prior:
        rows.append(n_obs + np.repeat(np.arange(n_obs), 3))
        cols.append(np.stack([3 * fi, 3 * fi + 1, 3 * fi + 2], 1).ravel())
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    shape = (n_res, 3 * f + k)
    pattern = sp.csr_matrix((np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=shape)
    order = pattern.data.astype(int) - 1  # where each (row, col) entry landed in CSR storage

    def jacobian(z):
        diff, d, _ = geometry(z)
        u = diff / d[:, None]
        vals_e = np.concatenate([sw[:, None] * u, -sw[:, None]], 1).ravel()
        vals = [vals_e]
        if use_prior:
            vals.append(((0.5 * sa / np.sqrt(d))[:, None] * u).ravel())
        vals = np.concatenate(vals)
        return sp.csr_matrix((vals[order], pattern.indices, pattern.indptr), shape=shape)

    z0 = np.concatenate([c0.ravel(), r0])
    if jac == "analytic":
        kwargs = dict(jac=jacobian)
    elif jac == "sparsity":
        kwargs = dict(jac="2-point", jac_sparsity=pattern)
    else:
        raise ValueError(f"jac must be 'analytic' or 'sparsity', got {jac!r}")
    sol = least_squares(
        residuals, z0, method="trf", tr_solver="lsmr",
        ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev, **kwargs,
    )
    c = unpack(sol.x)[0]
    cost, variance, radii = _pair_cost(c, xs, ob, alpha)
    positions = np.full((f_all, 3), np.nan)
    positions[frames] = c
    return PairFit(positions, radii, cost, variance, int(sol.nfev), int(sol.status))


def _pair_members(seg: np.ndarray, a: int, b: int) -> np.ndarray:
    return np.flatnonzero((seg == a) | (seg == b))


def all_pair_costs(
    x: np.ndarray,
    mask: np.ndarray,
    seg: np.ndarray,
    n_segments: int,
    *,
    alpha: float = 1e-5,
    max_frames: int = 300,
    max_nfev: int = 100,
    pairs: list[tuple[int, int]] | None = None,
) -> tuple[np.ndarray, dict, np.ndarray]:
    """Joint cost (S, S) of every segment pair on ``max_frames`` evenly spaced frames:
    Kirk's Q divided by the fraction of residual degrees of freedom (the MST weight).

    Pairs with fewer than four markers or fewer than ten frames with three of them
    present are infeasible (``inf``). ``pairs`` restricts the solve to a subset (for
    timing; the rest stay ``inf``). Returns ``(cost, fits, frames)``.
    """
    frames, feasible, xs, ms = feasible_pairs(x, mask, seg, n_segments, max_frames=max_frames, pairs=pairs)
    cost = np.full((n_segments, n_segments), np.inf)
    fits: dict[tuple[int, int], PairFit] = {}
    for (a, b), x_pair, m_pair in zip(feasible, xs, ms):
        fit = solve_pair(x_pair, m_pair, alpha, max_nfev=max_nfev)
        fits[(a, b)] = fit
        cost[a, b] = cost[b, a] = mst_weight(fit.cost, m_pair)
    return cost, fits, frames


def feasible_pairs(
    x: np.ndarray, mask: np.ndarray, seg: np.ndarray, n_segments: int, *, max_frames: int,
    pairs: list[tuple[int, int]] | None = None,
) -> tuple[np.ndarray, list[tuple[int, int]], list[np.ndarray], list[np.ndarray]]:
    """The all-pairs pass's problems: ``max_frames`` evenly spaced frames, and of the segment
    pairs (all, or ``pairs``) those with four markers or more and ten frames or more with three
    of them present, each with its markers' positions (F, K, 3) and mask (F, K) on those frames.
    Returns ``(frames, pairs, xs, masks)``."""
    stride = max(1, int(np.ceil(x.shape[0] / max_frames)))
    frames = np.arange(0, x.shape[0], stride)
    xf, mf = x[frames], mask[frames]
    todo = pairs if pairs is not None else [(a, b) for a in range(n_segments) for b in range(a + 1, n_segments)]
    feasible, xs, ms = [], [], []
    for a, b in todo:
        idx = _pair_members(seg, a, b)
        if idx.size < MIN_PAIR_MARKERS or (mf[:, idx].sum(1) >= MIN_FRAME_MARKERS).sum() < MIN_PAIR_FRAMES:
            continue
        feasible.append((a, b))
        xs.append(xf[:, idx])
        ms.append(mf[:, idx])
    return frames, feasible, xs, ms


def mst_weight(objective: float, pair_mask: np.ndarray) -> float:
    """The MST weight of a pair: its cost per residual degree of freedom, Q / f with
    f = sum_t (K_t - 3) / sum_t K_t over frames with >= 3 markers (as jaxskel); inf where f = 0."""
    k_t = pair_mask.sum(1)
    k_t = k_t[k_t >= MIN_FRAME_MARKERS]
    f = (k_t - 3).sum() / max(k_t.sum(), 1)
    return objective / f if f > 0 else np.inf


def _centre(n: int, edges: np.ndarray) -> int:
    """Tree centre (smallest eccentricity in hops, then the lowest index)."""
    adj = [[] for _ in range(n)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)

    def ecc(s):
        dist = {s: 0}
        queue = deque([s])
        while queue:
            u = queue.popleft()
            for v in adj[u]:
                if v not in dist:
                    dist[v] = dist[u] + 1
                    queue.append(v)
        return max(dist.values()) if len(dist) == n else np.inf

    return int(np.argmin([ecc(s) for s in range(n)]))


def mst_topology(cost: np.ndarray, root: int | None = None) -> tuple[np.ndarray, int]:
    """``scipy.sparse.csgraph.minimum_spanning_tree`` on the costs, edges (parent, child) from the root."""
    n = cost.shape[0]
    finite = np.isfinite(cost) & ~np.eye(n, dtype=bool)
    shift = 1.0 + (np.abs(cost[finite]).max() if finite.any() else 0.0)  # 0 means "no edge" to scipy
    tree = minimum_spanning_tree(np.triu(np.where(finite, cost + shift, 0.0), 1)).tocoo()
    undirected = np.stack([tree.row, tree.col], 1).astype(int)
    root = _centre(n, undirected) if root is None else int(root)
    adj = [[] for _ in range(n)]
    for a, b in undirected:
        adj[a].append(b)
        adj[b].append(a)
    edges, seen, queue = [], {root}, deque([root])
    while queue:
        u = queue.popleft()
        for v in sorted(adj[u]):
            if v not in seen:
                seen.add(v)
                edges.append((u, v))
                queue.append(v)
    return np.asarray(edges, int).reshape(-1, 2), root


def tree_start(seg: np.ndarray, fits: dict, pair_frames: np.ndarray, frames: np.ndarray, p: int, c: int):
    """Tree joint ``(p, c)``'s markers and start: the pair-pass joint interpolated in time to
    ``frames`` (from the frames the pair pass placed) and its radii."""
    key = (min(p, c), max(p, c))
    first = fits[key]
    ok = np.isfinite(first.positions).all(1)
    c0 = np.stack([np.interp(frames, pair_frames[ok], first.positions[ok, d]) for d in range(3)], 1)
    return _pair_members(seg, *key), c0, first.radii


def tree_joints(
    x: np.ndarray,
    mask: np.ndarray,
    seg: np.ndarray,
    edges: np.ndarray,
    fits: dict,
    pair_frames: np.ndarray,
    *,
    alpha: float = 1e-5,
    max_nfev: int = 200,
    frames: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each tree joint re-solved on all frames (or ``frames``), warm-started from the pair pass.

    The start is the pair-pass joint interpolated in time and its radii. Every joint
    keeps the small distance prior ``alpha`` (jaxskel drops it for joints its
    identifiability test finds determined). Returns ``(positions (F, J, 3), cost (J,))``.
    """
    frames = np.arange(x.shape[0]) if frames is None else frames
    out = np.full((frames.size, len(edges), 3), np.nan)
    costs = np.full(len(edges), np.inf)
    for j, (p, c) in enumerate(edges):
        idx, c0, r0 = tree_start(seg, fits, pair_frames, frames, p, c)
        fit = solve_pair(x[frames][:, idx], mask[frames][:, idx], alpha, c0=c0, r0=r0, max_nfev=max_nfev)
        out[:, j] = fit.positions
        costs[j] = fit.cost
    return out, costs
