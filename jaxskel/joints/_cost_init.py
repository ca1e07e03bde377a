"""Closed-form starting point for the joint solve: the algebraic (linearised) fit.

The joint-cost objective is non-convex; started from the marker centroid the
Levenberg–Marquardt iteration can settle in a local minimum away from the joint at
a multiple of the optimal cost (measured: docs/bench/evidence_from_docstrings.md). Squaring
the constant-distance condition makes it *linear*:

    |c_f - m_fk|^2 = s_k        (s_k = r_k^2)
    =>  -2 c_f . (m_fk - mbar_f) + (|m_fk|^2 - qbar_f) = s_k - sbar_f,

after subtracting each frame's mean over its present markers (bars), which
removes |c_f|^2. The unknowns are c_f (3 per frame) and s (K, defined up to a
common shift). Eliminating each frame's 3x3 block leaves a K x K system

    sum_f P_f^T (I - H_f) P_f s = sum_f P_f^T (I - H_f) b_f,

with U_f the (K, 3) rows -2 (m_fk - mbar_f), H_f = U_f (U_f^T U_f)^-1 U_f^T, P_f
the masked centring matrix and b_f the centred -|m_fk|^2. The shift of s is fixed
by a tiny ridge; c_f then follows frame by frame and r_k = mean_f |c_f - m_fk|.
This is the global minimiser of the algebraic residual: no local minima, one
linear solve, and a start from which the geometric problem converges to its
global minimum in practice. It needs >= 5 markers spanning 3-D in a frame (with
4 the radii drop out of the linear system); frames with fewer fall back to their
marker centroid, and so does a pair with no such frame.

Four markers: the consistency start
-----------------------------------
A pair of two-marker segments (or a three-marker segment and a lone marker) never
shows five markers. Keeping ``u_f = |c_f|^2`` as a fourth per-frame unknown, the
squared conditions are linear in ``(c_f, u_f)``,

    -2 m_fk . c_f + u_f = s_k - |m_fk|^2,

and four non-coplanar markers determine ``(c_f, u_f) = G_f (s - q_f)`` for *any*
radii: the algebraic residual is zero and says nothing. What the radii must satisfy
is the consistency the linearisation dropped,

    e_f(s) = u_f(s) - |c_f(s)|^2 = 0,

one quadratic equation per frame in the K radii. :func:`consistency_start` minimises
``sum_f e_f^2`` by Levenberg–Marquardt on ``s`` (K unknowns) from 54 starting joint
points -- a {-1, 0, 1}^3 grid along the principal axes of the markers of one
reference frame, at 0.5 and 1 times their span, so the set moves with the data and
does not depend on marker order -- and keeps the best. Started from the marker
centroid, the geometric solve of such a pair settles in local minima, at several times
the cost of the true joint, enough to joint the wrong segments; from the consistency
start it reaches the true joint's basin (measured on synthetic bodies with two markers
per segment: docs/bench/evidence_from_docstrings.md).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._math.linalg import eigh, eigvalsh, spd_solve
from ._cost_lm import inv3

__all__ = ["algebraic_start", "consistency_start"]

#: Starting joint points of :func:`consistency_start`: a {-1, 0, 1}^3 grid (symmetric
#: under sign flips and permutations of the principal axes) at these multiples of the
#: reference frame's marker span.
_GRID = np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=3)))
_GRID_SCALES = (0.5, 1.0)
#: Levenberg–Marquardt steps per starting point (K <= a few unknowns: converged well
#: before; the geometric solve refines what is left).
_CONSISTENCY_STEPS = 30


def algebraic_start(
    markers: Float[Array, "F K 3"], mask: Bool[Array, "F K"]
) -> tuple[Float[Array, "F 3"], Float[Array, " K"]]:
    """Linearised joint positions c (F, 3) and radii r (K,) (see the module docstring).

    Pure and vmappable over pairs; masked entries of ``markers`` are ignored.
    """
    dtype = markers.dtype
    w = mask.astype(dtype)  # (F, K)
    n = jnp.sum(w, axis=1, keepdims=True)  # (F, 1)
    safe_n = jnp.maximum(n, 1.0)
    mbar = jnp.sum(w[..., None] * markers, axis=1) / safe_n  # (F, 3)
    centroid = mbar
    q = jnp.sum(markers * markers, axis=-1)  # (F, K)
    qbar = jnp.sum(w * q, axis=1, keepdims=True) / safe_n
    u = -2.0 * (markers - mbar[:, None, :]) * w[..., None]  # (F, K, 3)
    b = -(q - qbar) * w  # (F, K)
    k = markers.shape[1]
    eye = jnp.eye(k, dtype=dtype)
    # P_f = diag(w) (I - 1 w^T / n): centred selection of s on present markers.
    p = w[:, :, None] * (eye[None] - w[:, None, :] / safe_n[:, :, None])  # (F, K, K)
    utu = jnp.einsum("fki,fkj->fij", u, u)
    # A frame informs s only with >= 5 markers spanning 3-D: with 4, the centred
    # rows of U_f span exactly the centred subspace, (I - H_f) P_f = 0 and s drops out.
    ev = jax.vmap(eigvalsh)(utu)  # plain XLA: no LAPACK kernel in the solver (see jaxskel._math.linalg)
    good = (n[:, 0] >= 5) & (ev[:, 0] > 1e-8 * jnp.maximum(ev[:, -1], 1e-300))
    utu_safe = jnp.where(good[:, None, None], utu, jnp.eye(3, dtype=dtype))
    inv = inv3(utu_safe)
    proj = jnp.einsum("fki,fij,flj->fkl", u, inv, u)  # H_f
    resid_op = (eye[None] - proj) * good[:, None, None]  # (I - H_f), zero for bad frames
    lhs = jnp.einsum("fki,fkl,flj->ij", p, resid_op, p)
    rhs = jnp.einsum("fki,fkl,fl->i", p, resid_op, b)
    any_good = jnp.any(good)
    scale = jnp.where(any_good, jnp.trace(lhs) / k, 1.0)
    present = (jnp.sum(w * good[:, None], axis=0) > 0).astype(dtype)
    # Ridge fixes the common shift of s and any marker never seen in a good frame.
    s = spd_solve(lhs + 1e-9 * scale * eye + jnp.diag(1.0 - present) * scale, rhs)  # SPD by the ridge
    s = jnp.where(any_good, s, 0.0)
    c = jnp.einsum("fij,fkj,fk->fi", inv, u, b - jnp.einsum("fkl,l->fk", p, s))
    c = jnp.where(good[:, None], c, centroid)
    d = jnp.sqrt(jnp.maximum(jnp.sum((c[:, None, :] - markers) ** 2, axis=-1), 1e-300))
    cnt = jnp.maximum(jnp.sum(w, axis=0), 1.0)
    r = jnp.sum(w * d, axis=0) / cnt
    return c, r


algebraic_start_batched = jax.jit(jax.vmap(algebraic_start))


def consistency_start(
    markers: Float[Array, "F K 3"], mask: Bool[Array, "F K"]
) -> tuple[Float[Array, "F 3"], Float[Array, " K"], Bool[Array, ""]]:
    """Joint positions (F, 3) and radii (K,) from the consistency of the squared
    distance conditions (module docstring, "Four markers"), and whether any frame could
    be used (four or more markers, not coplanar). Frames that cannot be used take their
    marker centroid. Pure and vmappable over pairs; masked entries are ignored.
    """
    dtype = markers.dtype
    w = mask.astype(dtype)  # (F, K)
    count = jnp.sum(w)
    origin = jnp.sum(w[..., None] * markers, axis=(0, 1)) / jnp.maximum(count, 1.0)
    # Work in units of the cloud's RMS radius: every quantity below is O(1).
    scale = jnp.sqrt(jnp.sum(w * jnp.sum((markers - origin) ** 2, axis=-1)) / jnp.maximum(count, 1.0))
    scale = jnp.where(scale > 0, scale, 1.0)
    y = jnp.where(mask[..., None], (markers - origin) / scale, 0.0)
    q = jnp.sum(y * y, axis=-1)  # (F, K)
    a = jnp.concatenate([-2.0 * y, jnp.ones_like(y[..., :1])], axis=-1) * w[..., None]  # (F, K, 4)
    normal = jnp.einsum("fki,fkj->fij", a, a)  # (F, 4, 4)
    ev = jax.vmap(eigvalsh)(normal)
    usable = (jnp.sum(w, axis=1) >= 4) & (ev[:, 0] > 1e-6 * jnp.maximum(ev[:, -1], 1e-300))
    safe = jnp.where(usable[:, None, None], normal, jnp.eye(4, dtype=dtype))
    gain = jax.vmap(spd_solve)(safe, jnp.swapaxes(a, 1, 2)) * usable[:, None, None]  # (F, 4, K): (c, u) = G (s - q)
    weight = usable.astype(dtype)

    def unknowns(s):
        return jnp.einsum("fik,fk->fi", gain, s[None] - q)  # (F, 4)

    def residual(s):
        v = unknowns(s)
        return weight * (v[:, 3] - jnp.sum(v[:, :3] ** 2, axis=-1)), v

    def cost(s):
        return jnp.sum(residual(s)[0] ** 2)

    def refine(s0):
        def step(_, state):
            s, lam, f = state
            e, v = residual(s)
            jac = weight[:, None] * (gain[:, 3] - 2.0 * jnp.einsum("fi,fik->fk", v[:, :3], gain[:, :3]))  # (F, K)
            jtj = jac.T @ jac
            ridge = 1e-12 * jnp.maximum(jnp.trace(jtj), 1e-300)
            damped = jtj + lam * jnp.diag(jnp.diagonal(jtj)) + ridge * jnp.eye(jtj.shape[0], dtype=dtype)
            trial = s - spd_solve(damped, jac.T @ e)
            f_trial = cost(trial)
            better = f_trial < f
            return (
                jnp.where(better, trial, s),
                jnp.where(better, lam / 3.0, lam * 4.0),
                jnp.where(better, f_trial, f),
            )

        s, _, f = jax.lax.fori_loop(0, _CONSISTENCY_STEPS, step, (s0, jnp.asarray(1e-3, dtype), cost(s0)))
        return s, jnp.where(jnp.isfinite(f), f, jnp.inf)

    # Starting points: a grid along the principal axes of the best-covered usable frame.
    reference = jnp.argmax(jnp.where(usable, jnp.sum(w, axis=1), -1.0))
    y0, w0 = y[reference], w[reference]
    centre = jnp.sum(w0[:, None] * y0, axis=0) / jnp.maximum(jnp.sum(w0), 1.0)
    spread = w0[:, None] * (y0 - centre)
    _, axes = eigh(spread.T @ spread)
    pairwise = jnp.sum((y0[:, None] - y0[None]) ** 2, axis=-1) * (w0[:, None] * w0[None])
    span = jnp.sqrt(jnp.max(pairwise))
    offsets = jnp.concatenate([f * jnp.asarray(_GRID, dtype) for f in _GRID_SCALES])  # (54, 3)
    points = centre + span * offsets @ axes.T
    s0 = jnp.sum((points[:, None] - y0[None]) ** 2, axis=-1)  # (54, K)
    s_all, f_all = jax.vmap(refine)(s0)
    best = s_all[jnp.argmin(f_all)]

    n = jnp.sum(w, axis=1, keepdims=True)
    centroid = jnp.sum(w[..., None] * y, axis=1) / jnp.maximum(n, 1.0)
    c = jnp.where(usable[:, None], unknowns(best)[:, :3], centroid)
    d = jnp.sqrt(jnp.maximum(jnp.sum((c[:, None, :] - y) ** 2, axis=-1), 1e-300))
    frames_used = w * usable[:, None]
    r = jnp.sum(frames_used * d, axis=0) / jnp.maximum(jnp.sum(frames_used, axis=0), 1.0)
    return c * scale + origin, r * scale, jnp.any(usable)


consistency_start_batched = jax.jit(jax.vmap(consistency_start))
