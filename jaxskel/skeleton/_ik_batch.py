"""Batched inverse kinematics: frames on the last axis, O(S) tree solve per step.

This is the fast path of :func:`jaxskel.skeleton.inverse_kinematics`. It minimises the energy of
:mod:`jaxskel.skeleton._ik` (markers plus the relative-rotation prior) over the same unknowns
(root translation, global segment orientations), from the same kind of Horn start, but
is organised for a CPU:

* **Layout.** Every quantity is a tuple of scalar components (structure of arrays), each
  an array whose *last* axis is the frames: a 3x3 matrix is nine arrays (the algebra of
  :mod:`jaxskel._math.planes` and :mod:`jaxskel._math.rotation_planes`). All arithmetic
  is then elementwise over frames, which XLA fuses into few vectorised loops, with no
  small matrix products, concatenations or batched linear algebra. Markers live in the
  padded ``(segment, slot)`` layout, so a segment's sums run over its few slots, and
  segments are stored in breadth-first order, so a tree level is a contiguous range and
  a segment's children are contiguous.
* **Tree elimination instead of dense normal equations.** Linearising the joint
  constraint, a step is a quadratic in each segment's *maximal* coordinates
  ``(omega_s, v_s)`` (a world-frame turn, and the velocity of the segment's reference
  point: its proximal joint, or the root's origin) with ``v_c = v_p + omega_p x (J_c -
  ref_p)`` fixed by the parent. Eliminating ``omega_c`` leaf to root (a 3x3 solve per
  segment, a 6x6 Schur complement carried to the parent) and solving the root's 6x6
  system gives exactly the step of the dense ``3 + 3S`` normal equations of
  :func:`jaxskel.skeleton._ik._normal_equations`, in O(S) work. The pose prior couples a
  segment's turn with its parent's only, so it stays inside the elimination.
* **Newton, not only Gauss-Newton.** With markers a few millimetres off the model,
  Gauss-Newton converges only linearly (the residuals' curvature is left out). The exact
  Hessian adds, for every segment ``a``, the residual curvature of its turn
  ``sum w [sym(r l^T) - (r . l) I]`` over the markers below ``a`` (``r`` residual, ``l``
  the lever on ``a``: a segment's rotation enters every marker position through one
  term, so the second derivatives are block diagonal). It costs a few products per
  segment and converges quadratically; the first step, far from the optimum, stays
  Gauss-Newton.
* **Levenberg-Marquardt control.** The iteration is :class:`jaxskel._math.lm.LevenbergMarquardt`
  with the IK policies of :func:`jaxskel.skeleton._ik.ik_solver` (Nielsen's damping update
  on the gain ratio, as :func:`jaxskel.skeleton._ik.solve_frame`) around :class:`TreeStep`'s
  proposal; damping adds ``mu * |diag|`` to each eliminated block, which changes the
  path, not the optimum. The Newton switch (:class:`NewtonSwitch`) is the proposal's
  ``aux``, set from the solver's decision on each step.
* **Batch-wide loop.** A chunk of frames is one batch state of the solver (per-frame
  damping, step count and convergence) in one ``while_loop``; converged frames are
  frozen and the loop stops when all are done or after ``max_steps``.

The tree shape is static (:class:`TreePlan`, hashable): one compilation per topology
and padded shape; offsets and marker assignment are traced.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._math.lm import Decision, LMState, Proposal
from .._math.padding import bucket_size
from .._math.planes import (
    UPPER,
    cross_left,
    cross_right,
    mmul,
    mtmul_sym,
    mtvec,
    mvec,
    sym_apply,
    sym_full,
    sym_inverse,
    sym_mul,
    vadd,
    vcross,
    vdot,
    vscale,
    vsub,
)
from .._math.rotation_planes import (
    axis_angle_to_quat,
    horn_quat,
    inverse_right_jacobian,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_axis_angle,
    unit_quat_to_matrix,
)
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.precision import float64_scope
from ._ik import ik_solver

__all__ = ["BatchModel", "TreePlan", "batch_model", "solve", "solve_chunk", "solve_frames", "solver_shape", "with_offsets"]

#: Weight of the default-pose pull in the Horn start, per point (as in ik_initial_guess).
HORN_DEFAULT_WEIGHT = 1e-3
#: Repeated squarings of Horn's 4x4 matrix (its spectrum raised to 2**HORN_SQUARINGS).
HORN_SQUARINGS = 10
#: Horn passes of the start (capped by the tree depth): the first aligns each segment on
#: its markers, each later one adds the proximal joint placed by the parent.
HORN_PASSES = 3


# ------------------------------------------------------------------ the tree plan
@dataclasses.dataclass(frozen=True)
class TreePlan:
    """Static tree layout (hashable): segments in breadth-first order.

    ``order[i]`` is the original segment of internal segment ``i``; ``parent[i]`` its
    internal parent (-1 for the root, internal index 0); ``joint[i]`` the original joint
    leading to ``i`` (-1 for the root); ``levels`` the internal ranges ``(start, stop)``
    of the tree levels, root level first. Children of one parent are contiguous.
    """

    order: tuple[int, ...]
    parent: tuple[int, ...]
    joint: tuple[int, ...]
    levels: tuple[tuple[int, int], ...]

    @property
    def n_seg(self) -> int:
        return len(self.order)

    @staticmethod
    def from_edges(edges: np.ndarray) -> TreePlan:
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        n_seg = edges.shape[0] + 1
        parent = np.full(n_seg, -1)
        joint = np.full(n_seg, -1)
        parent[edges[:, 1]] = edges[:, 0]
        joint[edges[:, 1]] = np.arange(edges.shape[0])
        roots = np.flatnonzero(parent < 0)
        if len(roots) != 1:
            raise ValueError("edges do not form a rooted tree")
        order, levels, frontier = [], [], [int(roots[0])]
        while frontier:
            levels.append((len(order), len(order) + len(frontier)))
            order.extend(frontier)
            frontier = [int(c) for p in frontier for c in edges[edges[:, 0] == p, 1]]
        if len(order) != n_seg:
            raise ValueError("edges do not form a rooted tree")
        where = np.empty(n_seg, np.int64)
        where[order] = np.arange(n_seg)
        return TreePlan(
            order=tuple(order),
            parent=tuple(int(where[parent[s]]) if parent[s] >= 0 else -1 for s in order),
            joint=tuple(int(joint[s]) for s in order),
            levels=tuple(levels),
        )

    def parent_slots(self, lev: int) -> np.ndarray:
        """Parent of each segment of level ``lev`` as a slot of level ``lev - 1``."""
        s, e = self.levels[lev]
        return np.asarray(self.parent[s:e]) - self.levels[lev - 1][0]


class BatchModel(eqx.Module):
    """Skeleton constants in the solver's layout: internal (breadth-first) segment order,
    vectors as tuples of components with a trailing unit axis that broadcasts over frames.

    ``joint_parent`` / ``joint_child``: each segment's proximal joint in its parent's /
    its own frame (3 x (S, 1); zero for the root); ``marker_offsets`` (3 x (S, K, 1)) the
    segment's markers in its frame; ``marker_index`` (S, K) their input column (0 for
    padding); ``marker_weight`` (S, K, 1) (0 for padding); ``shape_moment`` (6 x (S, 1)):
    the symmetric ``sum v v^T`` of the segment's points (markers and proximal joint)
    about their mean, for the default-pose pull of the Horn start.

    The tree is data, not code, so one compilation serves every tree with the same
    segment count and level width: ``parent`` (S,) (the root points to itself),
    ``has_parent`` (S, 1), ``path`` (S, S) (``path[s, c] = 1`` where the joint into
    ``c`` lies between the root and ``s``), ``level_start`` (S,) and ``n_levels``, the
    levels as ranges of the internal order, ``level_parent`` (S, W, W) one-hot: child
    slot ``c`` of level ``l`` hangs on slot ``p`` of level ``l - 1``, ``level_valid``
    (S, W, 1). ``order`` (S,): original segment of each internal one;
    ``joint_segment`` (J,): internal segment that each original joint leads into.
    ``width`` (static) is the widest level, padded.
    """

    joint_parent: tuple
    joint_child: tuple
    marker_offsets: tuple
    marker_index: Int[Array, "S K"]
    marker_weight: Float[Array, "S K 1"]
    shape_moment: tuple
    parent: Int[Array, " S"]
    has_parent: Float[Array, "S 1"]
    path: Float[Array, "S S"]
    level_start: Int[Array, " S"]
    n_levels: Int[Array, ""]
    level_parent: Float[Array, "S W W"]
    level_valid: Float[Array, "S W 1"]
    order: Int[Array, " S"]
    joint_segment: Int[Array, " J"]
    unit: Float[Array, ""]
    width: int = eqx.field(static=True)


def batch_model(
    edges: np.ndarray,
    joint_offsets: np.ndarray,
    marker_offsets: np.ndarray,
    marker_segment: np.ndarray,
    marker_weight: np.ndarray | None = None,
    *,
    slots: int = 1,
    dtype: Any = np.float64,
) -> BatchModel:
    """Host-side :class:`BatchModel`; markers with ``marker_segment < 0``, non-finite
    offsets or zero weight are left out. Each segment gets at least ``slots`` slots
    (see :func:`solver_shape`)."""
    plan = TreePlan.from_edges(edges)
    n_seg = plan.n_seg
    seg = np.asarray(marker_segment, dtype=np.int64)
    offsets = np.asarray(marker_offsets, dtype=np.float64)
    weight = np.ones(seg.shape[0]) if marker_weight is None else np.asarray(marker_weight, np.float64)
    usable = (seg >= 0) & np.isfinite(offsets).all(axis=1) & (weight > 0)
    members = [np.flatnonzero(usable & (seg == s)) for s in plan.order]
    slots = max(1, int(slots), max(len(m) for m in members))
    index = np.zeros((n_seg, slots), np.int32)
    w = np.zeros((n_seg, slots, 1))
    off = np.zeros((3, n_seg, slots, 1))
    jo = np.asarray(joint_offsets, dtype=np.float64).reshape(-1, 2, 3)
    jp = np.zeros((3, n_seg, 1))
    jc = np.zeros((3, n_seg, 1))
    moment = np.zeros((6, n_seg, 1))
    for i, m in enumerate(members):
        index[i, : len(m)] = m
        w[i, : len(m), 0] = weight[m]
        off[:, i, : len(m), 0] = offsets[m].T
        pts = [offsets[m]]
        if plan.joint[i] >= 0:
            jp[:, i, 0] = jo[plan.joint[i], 0]
            jc[:, i, 0] = jo[plan.joint[i], 1]
            pts.append(jc[:, i, 0][None])
        pts = np.concatenate(pts)
        if len(pts):
            v = pts - pts.mean(axis=0)
            c = v.T @ v
            moment[:, i, 0] = [c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2]]
    parent = np.asarray(plan.parent)
    path = np.zeros((n_seg, n_seg))
    for s in range(n_seg):
        u = s
        while parent[u] >= 0:
            path[s, u] = 1.0
            u = parent[u]
    sizes = [e - b for b, e in plan.levels]
    width = 2 * ((max(sizes) + 1) // 2)  # even: fewer distinct compiled shapes
    start = np.zeros(n_seg, np.int32)
    lp = np.zeros((n_seg, width, width))
    valid = np.zeros((n_seg, width, 1))
    for lev, (b, e) in enumerate(plan.levels):
        start[lev] = b
        valid[lev, : e - b] = 1.0
        if lev:
            lp[lev, plan.parent_slots(lev), np.arange(e - b)] = 1.0
    joint_of = np.asarray(plan.joint)
    joint_segment = np.argsort(np.where(joint_of < 0, -1, joint_of))[1:]

    def tup(a):
        return tuple(to_device(c, dtype) for c in a)

    return BatchModel(
        joint_parent=tup(jp),
        joint_child=tup(jc),
        marker_offsets=tup(off),
        marker_index=to_device(index),
        marker_weight=to_device(w, dtype),
        shape_moment=tup(moment),
        parent=to_device(np.maximum(parent, 0), np.int32),
        has_parent=to_device((parent >= 0)[:, None], dtype),
        path=to_device(path, dtype),
        level_start=to_device(start),
        n_levels=to_device(len(plan.levels), np.int32),
        level_parent=to_device(lp, dtype),
        level_valid=to_device(valid, dtype),
        order=to_device(plan.order, np.int32),
        joint_segment=to_device(joint_segment, np.int32),
        unit=to_device(np.ones((), dtype)),
        width=int(width),
    )


def solver_shape(marker_segment: np.ndarray, edges: np.ndarray, n_markers: int) -> tuple[int, int]:
    """``(slots, columns)`` that the IK of a skeleton and its rigid refinement share.

    The refinement (:mod:`jaxskel.skeleton._rigid_fit`) solves the IK with each joint centre as one
    more observed point, fixed at the proximal end of the joint's child segment, so each
    non-root segment needs one slot more than it has markers and the input one column
    per joint more. :func:`jaxskel.skeleton.inverse_kinematics` pads its columns the same way (free)
    and, given ``slots`` (as :func:`jaxskel.fit_skeleton` does), reserves that slot too,
    so both run *one* compiled :func:`solve_chunk` (one compilation instead of two, for
    an idle slot per segment in the IK). Returns the slot count per segment and the
    padded width of the marker axis for ``n_markers`` markers.
    """
    seg = np.asarray(marker_segment, dtype=np.int64)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    n_seg = edges.shape[0] + 1
    count = np.bincount(seg[seg >= 0], minlength=n_seg)[:n_seg]
    count[edges[:, 1]] += 1
    return max(1, int(count.max())), bucket_size(int(n_markers) + edges.shape[0], minimum=8)


def _barrier(model: BatchModel, x):
    """Materialise ``x``: a division by the runtime 1.0 ``model.unit`` is an 'expensive'
    operation, which XLA does not duplicate into every consumer; without it XLA fuses
    (and recomputes) long shared chains of cheap operations several times over.
    (``optimization_barrier`` is dropped by XLA's CPU pipeline.)"""
    return jax.tree_util.tree_map(lambda a: a / model.unit, x)


# ------------------------------------------------------------ tree helpers
def _rows(comps, idx):
    """Rows ``idx`` (traced) of each component (S, ...)."""
    return tuple(jnp.take(c, idx, axis=0) for c in comps)


def _parent_values(model: BatchModel, comps, root_value):
    """Each segment's parent's components; ``root_value`` for the root."""
    got = _rows(comps, model.parent)
    return tuple(jnp.where(model.has_parent > 0, g, v) for g, v in zip(got, root_value))


def _slice(comps, start, width):
    return tuple(jax.lax.dynamic_slice_in_dim(c, start, width, axis=0) for c in comps)


def _put(comps, values, start):
    return tuple(jax.lax.dynamic_update_slice_in_dim(c, v, start, axis=0) for c, v in zip(comps, values))


def _pad_rows(comps, extra):
    return tuple(jnp.concatenate([c, jnp.zeros((extra, *c.shape[1:]), c.dtype)]) for c in comps)


def _sum_slots(a):
    """Sum over the marker slots (axis 1) of (S, K, B)."""
    total = a[:, 0]
    for k in range(1, a.shape[1]):
        total = total + a[:, k]
    return total


# ------------------------------------------------------------- evaluation
class Evaluation(eqx.Module):
    """A pose evaluated on a batch (components; segment arrays (S, B), markers (S, K, B))."""

    rot: tuple  # 9
    trans: tuple  # 3
    ref: tuple  # 3: proximal joint (root: its origin)
    err: tuple  # 3: fitted - observed
    lever: tuple  # 3: fitted - ref
    e_prior: tuple  # 3
    energy: Float[Array, " B"]


def _forward(model: BatchModel, t_root, rot):
    """Segment translations and reference points (proximal joints; the root's origin)
    from the root translation (3 x (B,)) and rotations (9 x (S, B)):
    ``t = t_root + path @ d`` with ``d_c = R_parent(c) o_c0 - R_c o_c1``."""
    rp = _rows(rot, model.parent)
    d = vsub(mvec(rp, model.joint_parent), mvec(rot, model.joint_child))
    d = tuple(model.has_parent * c for c in d)
    trans = tuple(t[None] + jnp.dot(model.path, c, precision=jax.lax.Precision.HIGHEST) for t, c in zip(t_root, d))
    ref = vadd(trans, mvec(rot, model.joint_child))
    return trans, ref


def _markers(model: BatchModel, rot, trans):
    o = model.marker_offsets
    return tuple(
        rot[3 * i][:, None] * o[0] + rot[3 * i + 1][:, None] * o[1] + rot[3 * i + 2][:, None] * o[2] + trans[i][:, None]
        for i in range(3)
    )


def _evaluate(model: BatchModel, x, w, t_root, q, prior, lam2) -> Evaluation:
    rot = _barrier(model, unit_quat_to_matrix(q))
    trans, ref = _barrier(model, _forward(model, t_root, rot))
    fitted = _barrier(model, _markers(model, rot, trans))
    err = vsub(fitted, x)
    lever = tuple(f - r[:, None] for f, r in zip(fitted, ref))
    rel = quat_multiply(quat_conjugate(_parent_values(model, q, (1.0, 0.0, 0.0, 0.0))), q)
    e_prior = quat_to_axis_angle(quat_multiply(quat_conjugate(prior), rel))
    energy = jnp.sum(_sum_slots(w * vdot(err, err)), axis=0) + jnp.sum(lam2 * vdot(e_prior, e_prior), axis=0)
    rot, trans, ref, err, lever, e_prior, energy = _barrier(model, (rot, trans, ref, err, lever, e_prior, energy))
    return Evaluation(rot=rot, trans=trans, ref=ref, err=err, lever=lever, e_prior=e_prior, energy=energy)


# --------------------------------------------------------------- one LM step
def _step(model: BatchModel, ev: Evaluation, w, lam2, mu, newton):
    """Damped (Gauss-)Newton step: ``(omega, v, predicted decrease)``; ``omega`` (3 x (S, B))
    the turn of each segment, ``v`` the velocity of its reference point (for the root
    the translation increment); ``newton`` 1.0 adds the residual curvature."""
    u, r = ev.lever, ev.err
    wu, wr = _barrier(model, (vscale(w, u), vscale(w, r)))
    weight = _sum_slots(w)
    f = tuple(_sum_slots(c) for c in wu)
    kmat = [_sum_slots(wu[i] * u[j]) for i, j in UPPER]  # sum w u u^T
    g_w = tuple(_sum_slots(c) for c in vcross(wu, r))
    g_v = tuple(_sum_slots(c) for c in wr)
    tr = kmat[0] + kmat[3] + kmat[5]
    # |w x u|^2 = w^T (|u|^2 I - u u^T) w; residual curvature sym(r u^T) - (r.u) I.
    kr = [_sum_slots(wr[i] * u[j]) for i in range(3) for j in range(3)]
    tr_r = kr[0] + kr[4] + kr[8]
    sym_r = [0.5 * (kr[3 * i + j] + kr[3 * j + i]) for i, j in UPPER]
    h_ww = [-kmat[k] + newton * sym_r[k] for k in range(6)]
    for k in (0, 3, 5):
        h_ww[k] = h_ww[k] + tr - newton * tr_r
    zero = jnp.zeros_like(weight)
    h_wv = (zero, -f[2], f[1], f[2], zero, -f[0], -f[1], f[0], zero)  # [f]x
    h_vv = (weight, zero, zero, weight, zero, weight)
    # Prior: e_s moves by D_s (omega_s - omega_parent), D = Jr^-1(e) R^T.
    jr = _barrier(model, inverse_right_jacobian(ev.e_prior))
    d = mmul(jr, tuple(ev.rot[3 * j + i] for i in range(3) for j in range(3)))
    p_mat = tuple(lam2 * c for c in mtmul_sym(d, d))
    b = tuple(lam2 * c for c in mtvec(d, ev.e_prior))
    h_ww, h_wv, h_vv, g_w, g_v, p_mat, b, d = _barrier(model, (tuple(h_ww), h_wv, h_vv, g_w, g_v, p_mat, b, d))

    width = model.width
    n_seg = weight.shape[0]
    dtype = weight.dtype

    # Leaf-to-root elimination, one tree level per iteration (levels are ranges of the
    # breadth-first order; rows past the end are padding). acc: the quadratic of every
    # segment in its maximal coordinates, children's Schur complements added in.
    acc = _pad_rows((*h_ww, *h_wv, *h_vv, *g_w, *g_v, *g_v), width)  # 6 + 9 + 6 + 3 + 3 + 3 (es)
    keep = _pad_rows(tuple(jnp.zeros_like(weight) for _ in range(24)), width)  # y 9, z 3, zz 9, rr 3
    p_pad, b_pad, ref_pad = _pad_rows(p_mat, width), _pad_rows(b, width), _pad_rows(ev.ref, width)
    parent_pad = jnp.concatenate([model.parent, jnp.zeros(width, model.parent.dtype)])
    eye6 = (1.0, 0.0, 0.0, 1.0, 0.0, 1.0)

    def eliminate(i, carry):
        acc, keep = carry
        lev = model.n_levels - 1 - i
        start, pstart = model.level_start[lev], model.level_start[lev - 1]
        valid = model.level_valid[lev]  # (W, 1)
        here = _slice(acc, start, width)
        hww, hwv, hvv, gw, gv, es = here[0:6], here[6:15], here[15:21], here[21:24], here[24:27], here[27:30]
        p, bb = _slice(p_pad, start, width), _slice(b_pad, start, width)
        m = list(vadd(hww, p))
        for k in (0, 3, 5):
            m[k] = m[k] + mu * jnp.abs(m[k]) + 1e-12
        m = tuple(jnp.where(valid > 0, c, e) for c, e in zip(m, eye6))
        minv, p, hwv = _barrier(model, (sym_inverse(m), p, hwv))
        gh = vadd(gw, bb)
        y = sym_mul(minv, hwv)
        z = sym_apply(minv, gh)
        zz = sym_mul(minv, sym_full(p))
        y, z, zz = _barrier(model, (y, z, zz))
        qa = vsub(p, mtmul_sym(sym_full(p), zz))
        qb = sym_mul(p, y)
        qc = vsub(hvv, mtmul_sym(hwv, y))
        ga = vsub(sym_apply(p, z), bb)
        gc = vsub(gv, mtvec(hwv, z))
        pidx = jax.lax.dynamic_slice_in_dim(parent_pad, start, width)
        rr = vsub(_slice(ref_pad, start, width), _rows(ref_pad, pidx))
        qa, qb, qc, ga, gc, rr = _barrier(model, (qa, qb, qc, ga, gc, rr))
        qbx = cross_right(qb, rr)  # Qb X with X = -[rr]x
        xqcx = cross_left(rr, cross_right(sym_full(qc), rr))  # X^T Qc X
        to_ww = [qa[k] + qbx[3 * i + j] + qbx[3 * j + i] + xqcx[3 * i + j] for k, (i, j) in enumerate(UPPER)]
        er = vdot(es, rr)
        for k, (i, j) in enumerate(UPPER):
            to_ww[k] = to_ww[k] + newton * (0.5 * (es[i] * rr[j] + es[j] * rr[i]) - (er if i == j else 0.0))
        to_wv = vadd(qb, cross_left(rr, sym_full(qc)))
        to_gw = vadd(ga, vcross(rr, gc))
        up = (*to_ww, *to_wv, *qc, *to_gw, *gc, *es)
        one_hot = model.level_parent[lev][:, :, None]  # (W parent, W child, 1)
        up = _barrier(model, tuple(jnp.sum(one_hot * (valid * c)[None], axis=1) for c in up))
        acc = _put(acc, vadd(_slice(acc, pstart, width), up), pstart)
        old = _slice(keep, start, width)
        new = tuple(jnp.where(valid > 0, n, o) for n, o in zip((*y, *z, *zz, *rr), old))
        keep = _put(keep, new, start)
        return acc, keep

    acc, keep = jax.lax.fori_loop(0, model.n_levels - 1, eliminate, (acc, keep))

    # Root: the 6x6 system [[A, H], [H^T, C]] (omega, v) = -(g_w, g_v), by its Schur
    # complement on v.
    root = tuple(c[0] for c in acc)
    a_mat = list(vadd(root[0:6], tuple(c[0] for c in p_mat)))
    hwv, c_mat = root[6:15], list(root[15:21])
    g_w = vadd(root[21:24], tuple(c[0] for c in b))
    g_v = root[24:27]
    for k in (0, 3, 5):
        a_mat[k] = a_mat[k] + mu * jnp.abs(a_mat[k]) + 1e-12
        c_mat[k] = c_mat[k] + mu * jnp.abs(c_mat[k]) + 1e-12
    a_inv = _barrier(model, sym_inverse(a_mat))
    ah = _barrier(model, sym_mul(a_inv, hwv))  # A^-1 H
    ag = sym_apply(a_inv, g_w)
    schur = vsub(c_mat, mtmul_sym(hwv, ah))
    v_root = sym_apply(sym_inverse(schur), vsub(mtvec(hwv, ag), g_v))
    w_root = tuple(-c for c in vadd(ag, mvec(ah, v_root)))
    xv = _barrier(model, (*w_root, *v_root))

    # Root-to-leaf back substitution, one level per iteration.
    zeros = jnp.zeros((n_seg + width, weight.shape[1]), dtype)
    sol = tuple(zeros.at[0].set(c) for c in xv)  # omega 3, v 3

    def substitute(lev, sol):
        start = model.level_start[lev]
        valid = model.level_valid[lev]
        kp = _slice(keep, start, width)
        y, z, zz, rr = kp[0:9], kp[9:12], kp[12:21], kp[21:24]
        pidx = jax.lax.dynamic_slice_in_dim(parent_pad, start, width)
        par = _rows(sol, pidx)
        wp, vp = par[0:3], par[3:6]
        v = vadd(vp, vcross(wp, rr))
        om = tuple(-c for c in vsub(vadd(z, mvec(y, v)), mvec(zz, wp)))
        old = _slice(sol, start, width)
        new = tuple(jnp.where(valid > 0, n, o) for n, o in zip((*om, *v), old))
        return _barrier(model, _put(sol, new, start))

    sol = jax.lax.fori_loop(1, model.n_levels, substitute, sol)
    omega = tuple(c[:n_seg] for c in sol[0:3])
    vel = tuple(c[:n_seg] for c in sol[3:6])

    # Predicted decrease of the energy by the Gauss-Newton model.
    dp = vadd(vcross(tuple(c[:, None] for c in omega), u), tuple(c[:, None] for c in vel))
    de = mvec(d, vsub(omega, _parent_values(model, omega, (0.0, 0.0, 0.0))))
    lin = jnp.sum(_sum_slots(w * (2.0 * vdot(r, dp) + vdot(dp, dp))), axis=0)
    lin = lin + jnp.sum(lam2 * (2.0 * vdot(ev.e_prior, de) + vdot(de, de)), axis=0)
    return omega, vel, -lin


# ------------------------------------------------------------------ Horn start
def _compose(model: BatchModel, rel):
    """Global orientations from relative ones: ``q = q_parent rel``, settled once per level."""

    def settle(_, q):
        return quat_multiply(_parent_values(model, q, (1.0, 0.0, 0.0, 0.0)), rel)

    return jax.lax.fori_loop(0, model.n_levels, settle, rel)


def _horn_pass(model: BatchModel, x, w, q_def, joint, joint_w):
    """Horn alignment of every segment on its visible markers and (weight ``joint_w``) its
    proximal joint at ``joint``, pulled towards ``q_def``; returns ``(q, rot, t, seen)``."""
    off = model.marker_offsets
    jl = model.joint_child
    wsum = _sum_slots(w) + joint_w
    inv = 1.0 / jnp.where(wsum > 0, wsum, 1.0)
    mu_s = tuple((_sum_slots(w * o) + joint_w * j) * inv for o, j in zip(off, jl))
    mu_d = tuple((_sum_slots(w * c) + joint_w * j) * inv for c, j in zip(x, joint))
    src = tuple(o - m[:, None] for o, m in zip(off, mu_s))
    dst = tuple(c - m[:, None] for c, m in zip(x, mu_d))
    js, jd = vsub(jl, mu_s), vsub(joint, mu_d)
    wsrc, dst = _barrier(model, (vscale(w, src), dst))
    jws = vscale(joint_w, js)
    rdef = unit_quat_to_matrix(q_def)
    # Pull towards the default pose: sum_k v_k (R_def v_k)^T = C R_def^T.
    crt = sym_mul(model.shape_moment, tuple(rdef[3 * j + i] for i in range(3) for j in range(3)))
    mcov = tuple(
        _sum_slots(wsrc[a] * dst[b]) + jws[a] * jd[b] + HORN_DEFAULT_WEIGHT * crt[3 * a + b]
        for a in range(3)
        for b in range(3)
    )
    mcov = _barrier(model, mcov)
    q = _barrier(model, horn_quat(mcov, q_def, HORN_SQUARINGS))
    rot = unit_quat_to_matrix(q)
    t = vsub(mu_d, mvec(rot, mu_s))
    return q, rot, t, wsum > 0


def _horn_start(model: BatchModel, x, w, default_relative, passes):
    """Starting pose: :data:`HORN_PASSES` Horn alignments of all segments at once.

    The first aligns each segment on its visible markers alone; each later pass adds its
    proximal joint (weight 1), placed by the parent's pose of the previous pass, which
    poses segments with fewer than three markers. Every alignment is pulled towards the
    default pose (parent orientation times ``default_relative``) with weight
    :data:`HORN_DEFAULT_WEIGHT` per point, so the default decides only what the data
    leave free. Returns ``(t_root, q)``, the root translation fitting the markers given
    the rotations.
    """
    zero = jnp.zeros_like(w[:, 0])
    q, rot, t, seen = _horn_pass(model, x, w, _compose(model, default_relative), (zero, zero, zero), zero)

    def again(_, carry):
        q, rot, t, seen = carry
        rp = _parent_values(model, rot, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
        tp = _parent_values(model, t, (0.0, 0.0, 0.0))
        joint = vadd(tp, mvec(rp, model.joint_parent))
        jw = model.has_parent * _parent_values(model, (seen.astype(w.dtype),), (0.0,))[0]
        q_def = quat_multiply(_parent_values(model, q, (1.0, 0.0, 0.0, 0.0)), default_relative)
        return _horn_pass(model, x, w, q_def, joint, jw)

    q, rot, _, _ = jax.lax.fori_loop(1, jnp.minimum(passes, model.n_levels), again, (q, rot, t, seen))
    # Root translation: the weighted mean marker fit with the rotations fixed.
    trans0, _ = _forward(model, (zero[0], zero[0], zero[0]), rot)
    fitted = _markers(model, rot, trans0)
    wtot = jnp.maximum(jnp.sum(_sum_slots(w), axis=0), 1.0)
    t_root = tuple(jnp.sum(_sum_slots(w * (xc - fc)), axis=0) / wtot for xc, fc in zip(x, fitted))
    return t_root, q


# ------------------------------------------------------------------ the solver
class BatchSolution(eqx.Module):
    """Per-frame results (components, frames last)."""

    root_position: tuple
    rotations: tuple
    num_steps: Int[Array, " B"]
    done: Bool[Array, " B"]
    rms: Float[Array, " B"]
    evaluation: Evaluation


class NewtonSwitch(eqx.Module):
    """When the batched IK takes Newton steps, and when a Newton step ends it.

    A step is followed by a Newton step (the residual curvature added) only if it was
    accepted, its gain ratio lies in ``gain < rho < 2 - gain`` and
    it lowered the energy by less than the fraction ``drop``: far from the optimum the
    residual curvature can be indefinite and lead into a wrong basin, so the first step
    is Gauss-Newton. An accepted Newton step ends the iteration when it lowered the
    energy by at most the fraction ``rtol`` with ``rho > stop_gain`` and damping below
    ``stop_lam``: quadratic convergence leaves an error of about its square.
    """

    rtol: float = 1e-5
    gain: float = 0.75
    drop: float = 0.5
    stop_gain: float = 0.5
    stop_lam: float = 1e-2


class TreeStep(eqx.Module):
    """The batched IK's proposal for :class:`jaxskel._math.lm.LevenbergMarquardt`: a
    batch of frames (frames on the last axis of every leaf).

    ``params`` are ``(t_root, q, evaluation)`` (the evaluation of the pose is accepted
    with it), ``aux`` the per-frame Newton switch (:class:`NewtonSwitch`, set in
    :meth:`settle` from the solver's decision); the step is :func:`_step`'s damped tree
    solve with ``mu = state.lam``.
    """

    model: BatchModel
    x: tuple
    w: Float[Array, "S K B"]
    lam2: Float[Array, "S 1"]
    prior: tuple
    newton: NewtonSwitch = NewtonSwitch()

    def __call__(self, s: LMState) -> Proposal:
        t, q, ev = s.params
        omega, vel, predicted = _step(self.model, ev, self.w, self.lam2, s.lam, s.aux.astype(ev.energy.dtype))
        t_new = vadd(t, tuple(c[0] for c in vel))
        q_new = quat_normalize(quat_multiply(axis_angle_to_quat(omega), q))
        ev_new = _evaluate(self.model, self.x, self.w, t_new, q_new, self.prior, self.lam2)
        step = jnp.max(jnp.maximum(jnp.maximum(jnp.abs(omega[0]), jnp.abs(omega[1])), jnp.abs(omega[2])), axis=0)
        step = jnp.maximum(step, jnp.maximum(jnp.maximum(jnp.abs(vel[0][0]), jnp.abs(vel[1][0])), jnp.abs(vel[2][0])))
        return Proposal(params=(t_new, q_new, ev_new), cost=ev_new.energy, predicted=predicted, step=step,
                        finite=jnp.isfinite(ev_new.energy), aux=s.aux)

    def settle(self, s: LMState, trial: Proposal, d: Decision) -> Proposal:
        nw, drop, rho = self.newton, d.actual, d.rho
        converged = s.aux & (drop <= nw.rtol * s.cost) & (rho > nw.stop_gain) & (s.lam < nw.stop_lam)
        newton_next = d.accept & (rho > nw.gain) & (rho < 2.0 - nw.gain) & (drop < nw.drop * s.cost)
        return dataclasses.replace(trial, aux=newton_next, converged=converged)


def _lm(model, x, w, lam2, t0, q0, prior, max_steps, energy_rtol, step_tol):
    ev0 = _evaluate(model, x, w, t0, q0, prior, lam2)
    solver = ik_solver(max_steps, energy_rtol, step_tol)
    problem = TreeStep(model, x, w, lam2, prior)
    # nothing to fit (no markers, prior met): done at once
    state = solver.init((t0, q0, ev0), ev0.energy, jnp.zeros(ev0.energy.shape, bool), done=ev0.energy <= 1e-30)
    final = solver.run(problem, state)
    t, q, ev = final.params
    wsum = jnp.maximum(jnp.sum(_sum_slots(w), axis=0), 1.0)
    rms = jnp.sqrt(jnp.sum(_sum_slots(w * vdot(ev.err, ev.err)), axis=0) / wsum)
    return BatchSolution(root_position=t, rotations=q, num_steps=final.steps, done=final.done, rms=rms, evaluation=ev)


@functools.partial(jax.jit, static_argnames=("energy_rtol", "step_tol"))
def solve_chunk(
    model: BatchModel,
    x: Float[Array, "B M 3"],
    mask: Bool[Array, "B M"],
    t0: Float[Array, "B 3"],
    q0: Float[Array, "B S 4"],
    prior: Float[Array, "B S 4"],
    prior_weight: Float[Array, " S"],
    horn: Bool[Array, ""],
    max_steps: Int[Array, ""],
    horn_passes: Int[Array, ""],
    *,
    energy_rtol: float = 1e-8,
    step_tol: float = 1e-10,
) -> dict[str, Array]:
    """IK of a chunk of B frames; segments and joints in the *original* order.

    With ``horn`` each frame starts from :func:`_horn_start` and its prior is that
    start's relative rotations (``t0``, ``q0`` and ``prior`` are then ignored). Returns
    frame-major arrays: ``root_position`` (B, 3), ``rotations`` (B, S, 4), ``num_steps``,
    ``done``, ``rms`` (B,), ``energy`` (B,: markers plus prior, what the solver
    minimised), ``segment_translations`` (B, S, 3), ``joint_positions`` (B, J, 3) and
    ``fitted`` (B, S, K, 3) (the model's slot layout).
    """
    order = model.order
    dtype = x.dtype
    lam2 = (prior_weight[order] ** 2)[:, None].astype(dtype)
    xs = jnp.transpose(x[:, model.marker_index], (3, 1, 2, 0))
    xs = (xs[0], xs[1], xs[2])
    ws = jnp.transpose(mask[:, model.marker_index], (1, 2, 0)).astype(dtype) * model.marker_weight
    q_in = tuple(jnp.transpose(q0[:, order], (2, 1, 0)).astype(dtype))
    p_in = tuple(jnp.transpose(prior[:, order], (2, 1, 0)).astype(dtype))
    t_in = tuple(t0.T.astype(dtype))

    def from_horn(_):
        ident = tuple(jnp.full_like(q_in[0], v) for v in (1.0, 0.0, 0.0, 0.0))
        th, qh = _horn_start(model, xs, ws, ident, horn_passes)
        rel = quat_multiply(quat_conjugate(_parent_values(model, qh, (1.0, 0.0, 0.0, 0.0))), qh)
        return th, qh, rel

    def given(_):
        return t_in, quat_normalize(q_in), p_in

    t_s, q_s, p_s = jax.lax.cond(horn, from_horn, given, None)
    sol = _lm(model, xs, ws, lam2, t_s, q_s, p_s, max_steps, energy_rtol, step_tol)
    ev = sol.evaluation
    fitted = vadd(ev.err, xs)
    inverse = jnp.argsort(order)
    child_of_joint = model.joint_segment
    return dict(
        root_position=jnp.stack(sol.root_position, axis=-1),
        rotations=jnp.stack(sol.rotations, axis=-1).transpose(1, 0, 2)[:, inverse],
        num_steps=sol.num_steps,
        done=sol.done,
        rms=sol.rms,
        energy=ev.energy,
        segment_translations=jnp.stack(ev.trans, axis=-1).transpose(1, 0, 2)[:, inverse],
        joint_positions=jnp.stack(ev.ref, axis=-1).transpose(1, 0, 2)[:, child_of_joint],
        fitted=jnp.stack(fitted, axis=-1).transpose(2, 0, 1, 3),
    )


def solve(
    model: BatchModel,
    x: np.ndarray,
    mask: np.ndarray,
    t0: np.ndarray | None,
    q0: np.ndarray | None,
    prior: np.ndarray | None,
    prior_weight: np.ndarray,
    *,
    max_steps: int,
    chunk: int = 64,
    threads: int | None = None,
) -> dict[str, np.ndarray]:
    """IK of N frames on the host: chunks of ``chunk`` frames through one compiled
    :func:`solve_chunk`, spread over ``threads`` host threads (default: the CPU count,
    at most 4). ``t0 is None``: Horn start. Returns numpy arrays (see solve_chunk)."""
    n = x.shape[0]
    n_seg = model.order.shape[0]
    horn = t0 is None
    pad = (-n) % chunk
    dtype = np.dtype(model.marker_weight.dtype)

    def padded(a, fill):
        a = np.asarray(a)
        if pad:
            a = np.concatenate([a, np.broadcast_to(np.asarray(fill, a.dtype), (pad, *a.shape[1:]))])
        return a

    ident = np.array([1.0, 0.0, 0.0, 0.0], dtype)
    xp = padded(np.asarray(x, dtype), 0.0)
    mp = padded(np.asarray(mask, bool), False)
    if horn:
        tp = np.zeros((n + pad, 3), dtype)
        qp = pp = np.broadcast_to(ident, (n + pad, n_seg, 4))
    else:
        tp = padded(np.asarray(t0, dtype), 0.0)
        qp = padded(np.asarray(q0, dtype), ident)
        pp = padded(np.asarray(prior, dtype), ident)
    pw = to_device(prior_weight, dtype)
    flag = to_device(horn, bool)
    limit = to_device(max_steps, np.int32)
    passes = to_device(HORN_PASSES, np.int32)

    @float64_scope  # run in the pool's threads too, which do not inherit the caller's mode
    def run(k):
        sl = slice(k * chunk, (k + 1) * chunk)
        out = _program_cache.call(
            solve_chunk, model, xp[sl], mp[sl], tp[sl], qp[sl], pp[sl], pw, flag, limit, passes
        )
        return {key: np.asarray(val) for key, val in out.items()}

    n_chunks = (n + pad) // chunk
    if threads is None:
        threads = min(os.cpu_count() or 1, 4)
    if threads > 1 and n_chunks > 1:
        # The first chunk compiles (once, outside the pool). Concurrent executions are
        # safe here because the solver has no LAPACK custom calls (see jaxskel._math.linalg;
        # a test checks the lowered HLO).
        first = run(0)
        with ThreadPoolExecutor(threads) as pool:
            parts = [first, *pool.map(run, range(1, n_chunks))]
    else:
        parts = [run(k) for k in range(n_chunks)]
    return {key: np.concatenate([p[key] for p in parts])[:n] for key in parts[0]}


# ------------------------------------------------------- device-side helpers
def with_offsets(
    model: BatchModel, joint_parent: Float[Array, "J 3"], marker_offsets: Float[Array, "N 3"]
) -> BatchModel:
    """``model`` with its offset-dependent fields rebuilt from traced offsets (jittable).

    The layout (slots, tree, weights) stays ``model``'s; ``marker_offsets`` (N, 3) is
    indexed by the model's input columns (``marker_index``; slots of columns past N are
    points at the segment's origin, as the rigid refinement's joint centres are),
    ``joint_parent`` (J, 3) gives each joint in its parent's frame, and every joint sits
    at its child's origin (``joint_child`` zero). This is :func:`batch_model` with
    ``joint_offsets[:, 1] == 0`` for the offsets, so the rigid refinement can update the
    skeleton on the device between IK sweeps. ``shape_moment`` is recomputed as there:
    ``sum v v^T`` of the slots in use and the proximal joint, about their mean.
    """
    dtype = model.marker_weight.dtype
    n_rows = marker_offsets.shape[0]
    index = model.marker_index
    in_use = model.marker_weight[..., 0] > 0  # (S, K)
    inside = (index < n_rows) & in_use
    off = jnp.where(inside[..., None], jnp.asarray(marker_offsets, dtype)[jnp.minimum(index, n_rows - 1)], 0.0)
    n_seg = index.shape[0]
    jp = jnp.zeros((n_seg, 3), dtype).at[model.joint_segment].set(jnp.asarray(joint_parent, dtype))
    has = model.has_parent  # (S, 1); the proximal joint is a point at the origin (joint_child 0)
    w = in_use.astype(dtype)
    count = jnp.sum(w, axis=1) + has[:, 0]
    mean = jnp.sum(w[..., None] * off, axis=1) / jnp.maximum(count, 1.0)[:, None]  # (S, 3)
    v = off - mean[:, None]
    cov = jnp.einsum("sk,ska,skb->sab", w, v, v) + has[:, 0, None, None] * mean[:, :, None] * mean[:, None, :]
    moment = tuple(cov[:, a, b][:, None] for a, b in UPPER)
    return dataclasses.replace(
        model,
        joint_parent=tuple(jp[:, a][:, None] for a in range(3)),
        joint_child=tuple(jnp.zeros((n_seg, 1), dtype) for _ in range(3)),
        marker_offsets=tuple(off[..., a][..., None] for a in range(3)),
        shape_moment=moment,
    )


def solve_frames(
    model: BatchModel,
    x: Float[Array, "N M 3"],
    mask: Bool[Array, "N M"],
    t0: Float[Array, "N 3"],
    q0: Float[Array, "N S 4"],
    prior: Float[Array, "N S 4"],
    prior_weight: Float[Array, " S"],
    horn: Bool[Array, ""],
    max_steps: Int[Array, ""],
    *,
    chunk: int = 64,
) -> dict[str, Array]:
    """:func:`solve_chunk` over all N frames inside a traced program (jittable): the
    frames are padded to a multiple of ``chunk`` (absent markers, identity poses: done
    at once) and the chunks run one after another (``lax.map``), each with its own
    iteration count, as :func:`solve` runs them from the host. Same outputs as
    :func:`solve` (frame-major, N rows)."""
    n = x.shape[0]
    pad = (-n) % chunk
    dtype = x.dtype
    ident = jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype)

    def padded(a, fill):
        a = jnp.asarray(a)
        if not pad:
            return a
        return jnp.concatenate([a, jnp.broadcast_to(jnp.asarray(fill, a.dtype), (pad, *a.shape[1:]))])

    def chunks(a):
        return a.reshape(-1, chunk, *a.shape[1:])

    parts = tuple(chunks(a) for a in (
        padded(x.astype(dtype), 0.0), padded(mask, False), padded(t0.astype(dtype), 0.0),
        padded(q0.astype(dtype), ident), padded(prior.astype(dtype), ident),
    ))
    passes = jnp.asarray(HORN_PASSES, jnp.int32)

    def one(args):
        xc, mc, tc, qc, pc = args
        return solve_chunk(model, xc, mc, tc, qc, pc, prior_weight, horn, max_steps, passes)

    out = jax.lax.map(one, parts)
    return {key: val.reshape(-1, *val.shape[2:])[:n] for key, val in out.items()}
