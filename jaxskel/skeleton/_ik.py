"""Forward and inverse kinematics of a rigid-segment tree (Kirk et al. 2005, §3.3).

Kinematic model
---------------
A skeleton is a tree of S rigid segments joined by J = S - 1 joints; joint ``j`` is
``edges[j] = (parent, child)``. Each segment ``s`` has a pose ``(R_s, t_s)`` mapping
its local frame to the world (``x_world = R_s @ x_local + t_s``). The constants are

* ``marker_offsets[m]``: marker ``m`` in the frame of its segment ``marker_segment[m]``;
* ``joint_offsets[j, 0]`` / ``joint_offsets[j, 1]``: joint ``j`` in the parent / child frame.

The unknowns of one frame are the root translation ``t_root`` and the global segment
orientations ``q_s`` (unit quaternions, w-x-y-z). Every other translation follows from
the tree constraint ``R_p o_j0 + t_p = R_c o_j1 + t_c`` (joint ``j`` is one point seen
from both segments), which therefore holds exactly::

    d_j = R_p(j) o_j0 - R_c(j) o_j1                     (J, 3)
    t   = t_root + P d,  P[s, j] = 1 if joint j lies between the root and s   (S, J)
    joint_j  = R_p(j) o_j0 + t_p(j)
    marker_m = R_s(m) o_m + t_s(m)

``P`` solves ``(I - Q) P = C`` (``Q`` the parent indicator, ``C[s, j] = [child(j) = s]``),
so a pose is a few small matrix products, with no loop over the tree.

Inverse kinematics
------------------
Per frame, minimise over ``t_root`` and the orientations ``q``::

    E = sum_m w_m |marker_m - x_m|^2  +  sum_s lambda_s^2 |log(p_s^-1 q_parent(s)^-1 q_s)|^2

The second term is a pose prior: ``p_s`` is a rotation of each segment relative to its
parent (the root: relative to the world) and ``lambda_s`` is in metres per radian, so a
rotation error of theta radians costs as much as a marker error of ``lambda_s * theta``
metres. With the default 1 mm/rad it only decides what the markers leave free: a segment
with one marker or none in a frame, the twist of a segment whose markers lie on a line.
:func:`inverse_kinematics` fills gaps by interpolating each segment's relative rotation
between the frames where the segment is fully seen and using that as the prior.

Solvers. Orientations are updated by rotation-vector increments,
``q_s <- exp(omega_s) q_s`` (singularity-free: the increment is re-based every step).

* :func:`solve_frame` is a Levenberg-Marquardt on the Gauss-Newton normal equations with
  the Jacobian written out analytically. A world-frame turn ``omega_a`` of segment ``a``
  moves every marker ``m`` below it by ``omega_a x u_ma``, where ``u_ma`` is the lever
  from ``t_a`` to the point where ``m`` hangs on ``a`` (the marker itself on ``a``, else
  the joint of ``a`` leading towards ``m``); all markers below one joint share a lever,
  so ``J^T J`` comes from per-subtree sums in O(S^2) (:func:`_normal_equations`). It is
  the single-frame reference solver (the rigid fit's global refinement uses it).
* :func:`jaxskel.skeleton._ik_batch.solve` is what :func:`inverse_kinematics` runs: the same
  energy and unknowns, frames on the last axis of structure-of-arrays tensors, an O(S)
  leaf-to-root elimination per step instead of dense normal equations, Newton steps near
  the optimum, and no LAPACK kernels, so chunks of frames run on several host threads.
  ``bench/bench_ik.py`` compares the solvers' speed and agreement.
* :func:`ik_solve` polishes that solution with ``optimistix.LevenbergMarquardt`` on the
  residual form, so that gradients of the solution with respect to the markers and the
  skeleton constants come from implicit differentiation (``optimistix.ImplicitAdjoint``).

Starting poses and robustness (:func:`inverse_kinematics`):

1. every frame starts from a Horn alignment of every segment on its visible markers,
   refined by passes that add the proximal joint placed by the parent
   (:func:`jaxskel.skeleton._ik_batch._horn_start`; no temporal dependence, so frames are solved
   in parallel);
2. a frame whose marker RMS exceeds :data:`RESEED_FACTOR` times the trial's median (a
   limb folded into a wrong basin) is solved again starting from the relative rotations
   interpolated between the neighbouring good frames, and keeps the better fit;
3. where a segment is not fully seen, a last pass uses the relative rotation interpolated
   (slerp) between the frames where it is as the prior (gap filling), started both from
   that interpolation and from the pose already found; each frame keeps the lower energy.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._errors import ConvergenceWarning, InputError
from .._math.lm import AcceptedSmall, LevenbergMarquardt, LMState, NielsenDamping, Proposal
from .._math.padding import bucket_size
from .._math.rotation import (
    axis_angle_to_quat,
    horn_align,
    inverse_right_jacobian,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_axis_angle,
    quat_to_matrix,
    skew,
    slerp,
)
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.precision import float64_scope

if TYPE_CHECKING:
    from ..io import Trial


class SkeletonLike(Protocol):
    """What inverse kinematics reads of a fitted :class:`jaxskel.skeleton.Skeleton`."""

    n_segments: int
    n_markers: int
    edges: np.ndarray
    parent: np.ndarray
    marker_labels: tuple[str, ...]
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    joint_offsets: np.ndarray

__all__ = [
    "Chain",
    "FrameSolution",
    "IKModel",
    "Motion",
    "forward_kinematics",
    "ik_initial_guess",
    "ik_model",
    "ik_solve",
    "inverse_kinematics",
    "kinematic_chain",
    "solve_frame",
    "tree_levels",
]

#: Default pose-prior weight, metres per radian (see the module docstring).
DEFAULT_PRIOR_WEIGHT = 1e-3
#: A frame whose marker RMS exceeds this multiple of the trial's median is re-solved
#: from its neighbours' pose (:func:`inverse_kinematics`).
RESEED_FACTOR = 2.0
#: optimistix result codes used in the diagnostics arrays.
RESULT_SUCCESSFUL = 0
RESULT_MAX_STEPS = 7  # optimistix.RESULTS.nonlinear_max_steps_reached
_IDENTITY = (1.0, 0.0, 0.0, 0.0)


# --------------------------------------------------------------------------- tree
class Chain(eqx.Module):
    """Index arrays of a rooted tree, derived once from ``edges`` (traced arrays).

    ``edges`` (J, 2) parent -> child; ``parent`` (S,) parent segment, -1 for the root;
    ``path`` (S, J) 1.0 where joint j lies between the root and segment s;
    ``attach`` (S, S, J) 1.0 where joint j is the joint of segment a that leads
    towards segment s (a a strict ancestor of s): ``attach[s, a, j]``.
    """

    edges: Int[Array, "J 2"]
    parent: Int[Array, " S"]
    path: Float[Array, "S J"]
    attach: Float[Array, "S S J"]


def kinematic_chain(edges: Int[Array, "J 2"], dtype: Any = jnp.float64) -> Chain:
    """:class:`Chain` of a parent->child edge list over ``J + 1`` segments (jit-able).

    ``path`` solves ``(I - Q) P = C`` with ``Q[s, s'] = [parent(s) = s']`` and
    ``C[s, j] = [child(j) = s]``: row s of P is C[s] plus the row of s's parent.

    A numpy ``edges`` gives a chain of numpy arrays, computed on the host (the same
    values; eager JAX would compile each operation for every tree size).
    """
    if isinstance(edges, np.ndarray):
        return _chain_np(edges, dtype)
    edges = jnp.asarray(edges)
    n_seg = edges.shape[0] + 1
    parent = jnp.full((n_seg,), -1, dtype=edges.dtype).at[edges[:, 1]].set(edges[:, 0])
    seg = jnp.arange(n_seg)
    q = (parent[:, None] == seg[None, :]).astype(dtype)
    c = (edges[None, :, 1] == seg[:, None]).astype(dtype)
    path = jnp.round(jnp.linalg.solve(jnp.eye(n_seg, dtype=dtype) - q, c))
    is_parent = (edges[None, :, 0] == seg[:, None]).astype(dtype)  # (S_a, J)
    attach = path[:, None, :] * is_parent[None, :, :]
    return Chain(edges=edges, parent=parent, path=path, attach=attach)


def _chain_np(edges: np.ndarray, dtype: Any) -> Chain:
    """:func:`kinematic_chain` of host ``edges``, by walking each segment up to the root."""
    edges = np.asarray(edges)
    n_seg = edges.shape[0] + 1
    parent = np.full(n_seg, -1, dtype=edges.dtype)
    parent[edges[:, 1]] = edges[:, 0]
    joint_of = np.full(n_seg, -1)
    joint_of[edges[:, 1]] = np.arange(edges.shape[0])
    path = np.zeros((n_seg, edges.shape[0]), dtype=np.dtype(dtype))
    for s in range(n_seg):
        u, seen = s, 0
        while joint_of[u] >= 0 and seen <= n_seg:
            path[s, joint_of[u]] = 1.0
            u, seen = parent[u], seen + 1
    is_parent = (edges[None, :, 0] == np.arange(n_seg)[:, None]).astype(path.dtype)
    return Chain(edges=edges, parent=parent, path=path, attach=path[:, None, :] * is_parent[None, :, :])


# ---------------------------------------------------------------- forward kinematics
def _poses(
    root_position: Float[Array, " 3"],
    rot: Float[Array, "S 3 3"],
    joint_offsets: Float[Array, "J 2 3"],
    chain: Chain,
) -> tuple[Float[Array, "S 3"], Float[Array, "J 3"]]:
    """Segment translations and joint centres from global rotation matrices."""
    rp = rot[chain.edges[:, 0]]
    rc = rot[chain.edges[:, 1]]
    joint_in_parent = jnp.einsum("jab,jb->ja", rp, joint_offsets[:, 0])
    d = joint_in_parent - jnp.einsum("jab,jb->ja", rc, joint_offsets[:, 1])
    trans = root_position[None, :] + chain.path @ d
    return trans, joint_in_parent + trans[chain.edges[:, 0]]


def _markers(
    rot: Float[Array, "S 3 3"],
    trans: Float[Array, "S 3"],
    marker_offsets: Float[Array, "M 3"],
    marker_segment: Int[Array, " M"],
) -> Float[Array, "M 3"]:
    return jnp.einsum("mab,mb->ma", rot[marker_segment], marker_offsets) + trans[marker_segment]


@float64_scope
def forward_kinematics(
    root_position: Float[Array, "*batch 3"],
    rotations: Float[Array, "*batch S 4"],
    joint_offsets: Float[Array, "J 2 3"],
    marker_offsets: Float[Array, "M 3"],
    edges: Int[Array, "J 2"],
    marker_segment: Int[Array, " M"],
) -> tuple[Float[Array, "*batch S 3"], Float[Array, "*batch J 3"], Float[Array, "*batch M 3"]]:
    """World segment translations, joint centres and markers of poses.

    Parameters
    ----------
    root_position
        (..., 3) translation of the root segment.
    rotations
        (..., S, 4) global segment orientations, quaternions (w, x, y, z); the scale is
        divided out.
    joint_offsets, marker_offsets
        Skeleton constants (module docstring).
    edges, marker_segment
        Tree and marker -> segment indices (every entry a valid segment).

    Returns
    -------
    ``(segment_translations (..., S, 3), joint_positions (..., J, 3), markers (..., M, 3))``.
    Pure; jit/vmap/grad-able in every float argument.
    """
    chain = kinematic_chain(edges, dtype=jnp.result_type(joint_offsets))
    marker_segment = jnp.asarray(marker_segment)

    def one(t, q):
        rot = quat_to_matrix(q)
        trans, joints = _poses(t, rot, joint_offsets, chain)
        return trans, joints, _markers(rot, trans, marker_offsets, marker_segment)

    batch = root_position.shape[:-1]
    flat = jax.vmap(one)(root_position.reshape(-1, 3), rotations.reshape(-1, *rotations.shape[-2:]))
    return tuple(a.reshape(*batch, *a.shape[1:]) for a in flat)  # type: ignore[return-value]


# --------------------------------------------------------------------- the model
class IKModel(eqx.Module):
    """Everything constant across the frames of one IK problem (a pytree of arrays).

    ``joint_offsets`` (J, 2, 3), ``marker_offsets`` (M, 3), ``marker_segment`` (M,)
    (entries >= 0; unused or padding markers get ``marker_weight`` 0), ``marker_weight``
    (M,) per-marker weight multiplying the visibility mask, ``chain``,
    ``segment_markers`` (S, K) each segment's markers (-1 = padding) and ``levels`` (static)
    the number of levels of the tree (root = 1). Build it with :func:`ik_model`.
    """

    joint_offsets: Float[Array, "J 2 3"]
    marker_offsets: Float[Array, "M 3"]
    marker_segment: Int[Array, " M"]
    marker_weight: Float[Array, " M"]
    chain: Chain
    segment_markers: Int[Array, "S K"]
    levels: int = eqx.field(static=True)


def tree_levels(edges: Int[np.ndarray, "J 2"]) -> int:
    """Number of levels of a rooted tree (1 for a single segment), on the host."""
    edges = np.asarray(edges).reshape(-1, 2)
    parent = np.full(edges.shape[0] + 1, -1)
    parent[edges[:, 1]] = edges[:, 0]
    deepest = 0
    for s in range(parent.size):
        depth, u = 0, s
        while parent[u] >= 0 and depth <= parent.size:
            u, depth = parent[u], depth + 1
        deepest = max(deepest, depth)
    return deepest + 1


def ik_model(
    edges: Int[np.ndarray, "J 2"],
    joint_offsets: Float[np.ndarray, "J 2 3"],
    marker_offsets: Float[np.ndarray, "M 3"],
    marker_segment: Int[np.ndarray, " M"],
    *,
    n_markers: int | None = None,
    marker_weight: Float[np.ndarray, " M"] | None = None,
    dtype: Any = np.float64,
) -> IKModel:
    """Host-side construction of an :class:`IKModel`, markers padded to ``n_markers``.

    Markers with ``marker_segment < 0`` (unused) or non-finite offsets get weight 0.
    """
    edges = np.asarray(edges, dtype=np.int32).reshape(-1, 2)
    n_seg = edges.shape[0] + 1
    seg = np.asarray(marker_segment, dtype=np.int32)
    n_real = seg.shape[0]
    m_pad = n_real if n_markers is None else int(n_markers)
    offsets = np.zeros((m_pad, 3), dtype)
    segment = np.zeros(m_pad, np.int32)
    weight = np.zeros(m_pad, dtype)
    given = np.asarray(marker_offsets, dtype)
    usable = (seg >= 0) & np.isfinite(given).all(axis=1)
    offsets[:n_real][usable] = given[usable]
    segment[:n_real][usable] = seg[usable]
    weight[:n_real] = usable * (1.0 if marker_weight is None else np.asarray(marker_weight, dtype))
    members = [np.flatnonzero((segment == s) & (weight > 0)) for s in range(n_seg)]
    width = max(1, max(len(m) for m in members))
    seg_markers = np.full((n_seg, width), -1, np.int32)
    for s, m in enumerate(members):
        seg_markers[s, : len(m)] = m
    return IKModel(
        joint_offsets=jnp.asarray(joint_offsets, dtype),
        marker_offsets=jnp.asarray(offsets),
        marker_segment=jnp.asarray(segment),
        marker_weight=jnp.asarray(weight),
        chain=kinematic_chain(jnp.asarray(edges), dtype),
        segment_markers=jnp.asarray(seg_markers),
        levels=tree_levels(edges),
    )


# ----------------------------------------------- relative rotations along the tree
def _identity(dtype: Any) -> Float[Array, " 4"]:
    return jnp.asarray(_IDENTITY, dtype)


def _relative_rotations(q: Float[Array, "S 4"], parent: Int[Array, " S"]) -> Float[Array, "S 4"]:
    """Each segment's rotation relative to its parent (the root's: relative to the world)."""
    qp = jnp.where((parent >= 0)[:, None], q[jnp.maximum(parent, 0)], _identity(q.dtype))
    return quat_multiply(quat_conjugate(qp), q)


def _compose_relative(rel: Float[Array, "S 4"], parent: Int[Array, " S"]) -> Float[Array, "S 4"]:
    """Global orientations from relative ones (inverse of :func:`_relative_rotations`).

    Iterates ``q = q[parent] rel``; S passes settle any tree depth (a fori_loop, so the
    traced graph does not grow with S).
    """

    def settle(_, q):
        qp = jnp.where((parent >= 0)[:, None], q[jnp.maximum(parent, 0)], _identity(rel.dtype))
        return quat_multiply(qp, rel)

    return jax.lax.fori_loop(0, rel.shape[0], settle, rel)


# --------------------------------------------------------------- the fast solver
class FrameSolution(eqx.Module):
    """One frame's IK result (leading axes added by vmap).

    ``root_position`` (3,), ``rotations`` (S, 4) unit quaternions (w >= 0),
    ``num_steps`` iterations taken, ``result`` an optimistix result code
    (0 successful, 7 maximum steps reached), ``rms`` the marker residual RMS in metres
    over the visible (weighted) markers.
    """

    root_position: Float[Array, " 3"]
    rotations: Float[Array, "S 4"]
    num_steps: Int[Array, ""]
    result: Int[Array, ""]
    rms: Float[Array, ""]


def _energy_terms(t_root, q, x, w, model, prior, prior_weight):
    rot = quat_to_matrix(q)
    trans, joints = _poses(t_root, rot, model.joint_offsets, model.chain)
    pred = _markers(rot, trans, model.marker_offsets, model.marker_segment)
    err = pred - x
    e_prior = quat_to_axis_angle(quat_multiply(quat_conjugate(prior), _relative_rotations(q, model.chain.parent)))
    energy = jnp.sum(w * jnp.sum(err * err, -1)) + jnp.sum(prior_weight**2 * jnp.sum(e_prior * e_prior, -1))
    return energy, rot, trans, joints, pred, err, e_prior


def _normal_equations(t_root, q, x, w, model, prior, prior_weight):
    """Energy, ``H = J^T J`` (3+3S square) and ``g = J^T r`` at a pose (module docstring).

    A turn ``omega_a`` moves marker m below segment a by ``omega_a x u_ma``; every marker
    below a's joint j = (a, c) shares the lever ``l_j = joint_j - t_a``. Hence with
    per-subtree sums (weight ``W_c``, residual ``E_c``, first moment ``f_a`` of the levers
    about ``t_a``, second moment ``K_aa``) the blocks are, for a an ancestor of b,
    ``K_ab = l_(a->b) f_b^T`` and ``H_ab = tr(K_ab) I - K_ab^T``: O(S^2) work, not O(M S^2).
    """
    energy, rot, trans, joints, pred, err, e_prior = _energy_terms(t_root, q, x, w, model, prior, prior_weight)
    chain = model.chain
    n_seg = q.shape[0]
    dtype = x.dtype
    eye = jnp.eye(3, dtype=dtype)
    seg = model.marker_segment
    rel = pred - trans[seg]  # marker levers on their own segment
    wr = w[:, None] * rel
    own_w = jax.ops.segment_sum(w, seg, n_seg)
    own_e = jax.ops.segment_sum(w[:, None] * err, seg, n_seg)
    own_f = jax.ops.segment_sum(wr, seg, n_seg)
    own_k = jax.ops.segment_sum(wr[:, :, None] * rel[:, None, :], seg, n_seg)
    own_g = jax.ops.segment_sum(jnp.cross(wr, err), seg, n_seg)
    # Subtree sums: subtree[a, s] = 1 if s is a or below a.
    below = jnp.sum(chain.attach, axis=-1)  # (S_s, S_a): a strict ancestor of s
    subtree = jnp.eye(n_seg, dtype=dtype) + below.T
    sub_w = subtree @ own_w
    sub_e = subtree @ own_e
    pa, ch = chain.edges[:, 0], chain.edges[:, 1]
    lever = joints - trans[pa]  # (J, 3) l_j
    at_parent = jax.nn.one_hot(pa, n_seg, dtype=dtype).T  # (S, J)
    f = own_f + at_parent @ (sub_w[ch, None] * lever)
    k_diag = own_k + jnp.tensordot(at_parent, (sub_w[ch, None] * lever)[:, :, None] * lever[:, None, :], axes=1)
    g_w = own_g + at_parent @ jnp.cross(lever, sub_e[ch])
    toward = jnp.einsum("baj,jk->bak", chain.attach, lever)  # (S_b, S_a, 3): l_(a->b)
    k_anc = jnp.einsum("bak,bl->abkl", toward, f)  # K_ab for a strict ancestor of b
    k_ab = k_anc + jnp.swapaxes(jnp.swapaxes(k_anc, 0, 1), 2, 3)
    k_ab = k_ab + jnp.eye(n_seg, dtype=dtype)[:, :, None, None] * k_diag[:, None, :, :]
    h_ww = jnp.trace(k_ab, axis1=2, axis2=3)[:, :, None, None] * eye - jnp.swapaxes(k_ab, 2, 3)
    h_tw = -skew(f)  # (S, 3, 3)
    g_t = jnp.sum(own_e, axis=0)
    # Prior: e_s depends on omega_s through D_s = Jr^-1(e_s) R_s^T and on omega_parent via -D_s,
    # so it adds lambda^2 D^T D to blocks (s, s) and (p, p) and subtracts it from (s, p), (p, s).
    d = inverse_right_jacobian(e_prior) @ jnp.swapaxes(rot, 1, 2)
    lam2 = prior_weight**2
    dtd = lam2[:, None, None] * jnp.einsum("sji,sjk->sik", d, d)
    to_parent = jax.nn.one_hot(chain.parent, n_seg, dtype=dtype)  # (S, S); root row is zero
    off = -to_parent[:, :, None, None] * dtd[:, None, :, :]  # block (s, parent(s))
    diag = dtd + jnp.tensordot(to_parent, dtd, axes=(0, 0))
    h_ww = h_ww + off + jnp.swapaxes(off, 0, 1) + jnp.eye(n_seg, dtype=dtype)[:, :, None, None] * diag[:, None]
    v = lam2[:, None] * jnp.einsum("sji,sj->si", d, e_prior)
    g_w = g_w + v - to_parent.T @ v
    h_tw_flat = jnp.transpose(h_tw, (1, 0, 2)).reshape(3, 3 * n_seg)
    top = jnp.concatenate([jnp.sum(own_w) * eye, h_tw_flat], axis=1)
    bottom = jnp.concatenate(
        [h_tw_flat.T, jnp.transpose(h_ww, (0, 2, 1, 3)).reshape(3 * n_seg, 3 * n_seg)], axis=1
    )
    return energy, jnp.concatenate([top, bottom], axis=0), jnp.concatenate([g_t, g_w.reshape(-1)])


def ik_solver(
    max_steps: Int[Array, ""] | int, energy_rtol: Float[Array, ""] | float, step_tol: Float[Array, ""] | float
) -> LevenbergMarquardt:
    """The Levenberg-Marquardt of both IKs (:func:`solve_frame` and
    :mod:`jaxskel.skeleton._ik_batch`): Nielsen's damping update on the gain ratio
    ``actual / max(predicted, 1e-300)``, ``mu`` starting at 1e-3 and never below 1e-15,
    and :class:`jaxskel._math.lm.AcceptedSmall` stopping: an accepted step that lowers the
    energy by at most ``energy_rtol E + 1e-24`` or moves every unknown by less than
    ``step_tol`` ends the iteration, and so does ``mu > 1e12`` (no step can lower the
    energy any more in floating point), as converged."""
    damping = NielsenDamping(initial=1e-3, lam_max=1e12, lam_min=1e-15, predicted_floor=1e-300)
    return LevenbergMarquardt(rtol=energy_rtol, atol=step_tol, max_steps=max_steps, damping=damping,
                              stopping=AcceptedSmall(drop_floor=1e-24))


class FrameStep(eqx.Module):
    """:func:`solve_frame`'s proposal for :class:`jaxskel._math.lm.LevenbergMarquardt`:
    ``params`` ``(t_root, q)``, no ``aux``; the trial solves ``(H + mu (diag(H) + 1e-12))
    delta = -g`` (``mu = state.lam``) by Cholesky and predicts the decrease
    ``-(2 g.delta + delta^T H delta)`` of the energy."""

    x: Float[Array, "M 3"]
    w: Float[Array, " M"]
    model: IKModel
    prior: Float[Array, "S 4"]
    prior_weight: Float[Array, " S"]

    def energy(self, t, q) -> Float[Array, ""]:
        return _energy_terms(t, q, self.x, self.w, self.model, self.prior, self.prior_weight)[0]

    def __call__(self, s: LMState) -> Proposal:
        t, q = s.params
        _, h, g = _normal_equations(t, q, self.x, self.w, self.model, self.prior, self.prior_weight)
        eye = jnp.eye(h.shape[0], dtype=h.dtype)
        damped = h + s.lam * (jnp.diag(jnp.diag(h)) + 1e-12 * eye)
        delta = -jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(damped, lower=True), g)
        t_new = t + delta[:3]
        q_new = quat_normalize(quat_multiply(axis_angle_to_quat(delta[3:].reshape(-1, 3)), q))
        energy_new = self.energy(t_new, q_new)
        # Gain ratio: actual over predicted decrease of E ~ E + 2 g.d + d^T H d.
        predicted = -(2.0 * g @ delta + delta @ h @ delta)
        return Proposal(params=(t_new, q_new), cost=energy_new, predicted=predicted,
                        step=jnp.max(jnp.abs(delta)), finite=jnp.isfinite(energy_new), aux=())


def solve_frame(
    x: Float[Array, "M 3"],
    mask: Bool[Array, " M"],
    model: IKModel,
    init_root: Float[Array, " 3"],
    init_rotations: Float[Array, "S 4"],
    prior_rotations: Float[Array, "S 4"],
    prior_weight: Float[Array, " S"],
    *,
    max_steps: int = 100,
    energy_rtol: float = 1e-8,
    step_tol: float = 1e-10,
) -> FrameSolution:
    """Fast IK of one frame: Levenberg-Marquardt on analytic normal equations.

    Solves ``(H + mu diag(H)) delta = -g`` for ``delta = (dt_root, omega)`` (module
    docstring), accepts the step if the energy drops, updates ``mu`` by Nielsen's rule
    from the ratio of actual to predicted decrease, and stops once an accepted step lowers the energy by less than
    ``energy_rtol`` relative or moves every unknown by less than ``step_tol`` (metres /
    radians), or once the damping has grown past any useful step (the energy cannot
    drop any more in floating point): :func:`ik_solver` around :class:`FrameStep`. The
    energy test matters: with noisy markers Gauss-Newton converges only linearly in
    directions the markers barely determine (the twist of a two-marker segment), where
    further steps change no marker by more than a nanometre. vmap over frames.
    """
    dtype = x.dtype
    w = mask.astype(dtype) * model.marker_weight
    problem = FrameStep(x, w, model, prior_rotations, prior_weight)
    solver = ik_solver(max_steps, energy_rtol, step_tol)
    t0, q0 = init_root.astype(dtype), quat_normalize(init_rotations.astype(dtype))
    final = solver.run(problem, solver.init((t0, q0), problem.energy(t0, q0)))
    t, q = final.params
    energy, rot, trans, joints, pred, err, _ = _energy_terms(t, q, x, w, model, prior_rotations, prior_weight)
    rms = jnp.sqrt(jnp.sum(w * jnp.sum(err * err, -1)) / jnp.maximum(jnp.sum(w), 1.0))
    result = jnp.where(final.done, RESULT_SUCCESSFUL, RESULT_MAX_STEPS).astype(jnp.int32)
    return FrameSolution(root_position=t, rotations=q, num_steps=final.steps, result=result, rms=rms)


def ik_initial_guess(
    x: Float[Array, "M 3"],
    mask: Bool[Array, " M"],
    model: IKModel,
    default_relative: Float[Array, "S 4"],
) -> tuple[Float[Array, " 3"], Float[Array, "S 4"]]:
    """Per-frame starting pose: Horn alignment of each segment, from the root down.

    Each segment is aligned (Horn) on its visible markers plus its proximal joint, placed
    where the parent's current pose puts it; a third set of points, the segment's
    markers where the *default pose* (parent orientation times ``default_relative``)
    would put them, enters with weight 1e-3, so it only decides what the data leave
    free: a segment with one visible marker swings onto it and keeps the default twist,
    one with none keeps the default. All segments are aligned together, ``levels``
    times, so every level sees its parent settled. The root translation then solves the
    marker fit with the rotations fixed (a weighted mean). Pure; vmap over frames.
    """
    dtype = x.dtype
    chain = model.chain
    n_seg = default_relative.shape[0]
    n_joints = chain.edges.shape[0]
    w = mask.astype(dtype) * model.marker_weight
    valid = model.segment_markers >= 0
    idx = jnp.maximum(model.segment_markers, 0)
    local_m = model.marker_offsets[idx]  # (S, K, 3)
    seen = jnp.where(valid, w[idx], 0.0)
    has_parent = chain.parent >= 0
    proximal = jnp.zeros(n_seg, jnp.int32).at[chain.edges[:, 1]].set(jnp.arange(n_joints, dtype=jnp.int32))
    local_j = jnp.where(has_parent[:, None], model.joint_offsets[proximal, 1], 0.0)  # (S, 3)
    root = jnp.argmin(chain.parent)
    identity = _identity(dtype)

    def settle(_, carry):
        q, t_root = carry
        rot = quat_to_matrix(q)
        trans, joints = _poses(t_root, rot, model.joint_offsets, chain)
        q_parent = jnp.where(has_parent[:, None], q[jnp.maximum(chain.parent, 0)], identity)
        r_default = quat_to_matrix(quat_multiply(q_parent, default_relative))
        joint_world = jnp.where(has_parent[:, None], joints[proximal], trans)
        t_default = joint_world - jnp.einsum("sab,sb->sa", r_default, local_j)
        guess = jnp.einsum("sab,skb->ska", r_default, local_m) + t_default[:, None, :]
        src = jnp.concatenate([local_m, local_j[:, None, :], local_m], axis=1)
        dst = jnp.concatenate([x[idx], joint_world[:, None, :], guess], axis=1)
        wts = jnp.concatenate([seen, has_parent[:, None].astype(dtype), 1e-3 * valid.astype(dtype)], axis=1)
        rot_new, t_new = jax.vmap(horn_align)(src, dst, wts)
        return matrix_to_quat(rot_new), t_new[root]

    q_start = _compose_relative(default_relative, chain.parent)
    q, _ = jax.lax.fori_loop(0, model.levels, settle, (q_start, jnp.zeros(3, dtype)))
    rot = quat_to_matrix(q)
    trans, _ = _poses(jnp.zeros(3, dtype), rot, model.joint_offsets, chain)
    pred = _markers(rot, trans, model.marker_offsets, model.marker_segment)
    t_root = jnp.sum((x - pred) * w[:, None], axis=0) / jnp.maximum(jnp.sum(w), 1.0)
    return t_root, q


# ------------------------------------------------- differentiable functional core
def _residuals(y, args):
    """Residual form of the energy for optimistix (y = (t_root, increments about q0))."""
    t_root, delta = y
    x, w, q0, joint_offsets, marker_offsets, chain, marker_segment, prior, prior_weight = args
    q = quat_multiply(axis_angle_to_quat(delta), q0)
    rot = quat_to_matrix(q)
    trans, _ = _poses(t_root, rot, joint_offsets, chain)
    pred = _markers(rot, trans, marker_offsets, marker_segment)
    # Millimetre units make optimistix' initial damping (lambda = 1) negligible.
    r_markers = (pred - x) * (jnp.sqrt(w) * 1e3)[:, None]
    e_prior = quat_to_axis_angle(quat_multiply(quat_conjugate(prior), _relative_rotations(q, chain.parent)))
    return r_markers, e_prior * (prior_weight * 1e3)[:, None]


@float64_scope
def ik_solve(
    x: Float[Array, "M 3"],
    mask: Bool[Array, " M"],
    joint_offsets: Float[Array, "J 2 3"],
    marker_offsets: Float[Array, "M 3"],
    edges: Int[Array, "J 2"],
    marker_segment: Int[Array, " M"],
    init_root: Float[Array, " 3"],
    init_rotations: Float[Array, "S 4"],
    prior_rotations: Float[Array, "S 4"] | None = None,
    prior_weight: float | Float[Array, " S"] = DEFAULT_PRIOR_WEIGHT,
    *,
    max_steps: int = 100,
) -> FrameSolution:
    """Differentiable inverse kinematics of one frame (pure; vmap over frames / trials).

    Parameters
    ----------
    x, mask
        (M, 3) marker positions (metres; anything where ``mask`` is False) and (M,) bool.
    joint_offsets, marker_offsets, edges, marker_segment
        The skeleton (module docstring); ``marker_segment`` entries must be >= 0.
    init_root, init_rotations
        Starting pose (3,), (S, 4); e.g. the previous frame or a Horn alignment.
    prior_rotations, prior_weight
        Relative-rotation prior (S, 4) (default: that of the starting pose) and its
        weight in metres per radian (scalar or (S,)).

    Returns a :class:`FrameSolution` (steps and result of :func:`solve_frame`). The solve
    runs :func:`solve_frame` to a tight tolerance and then ``optimistix.LevenbergMarquardt``
    from its answer (a few steps at most), so that
    ``jax.grad`` / ``jax.jvp`` through the solution use implicit differentiation
    (``optimistix.ImplicitAdjoint``) with respect to ``x``, ``joint_offsets``,
    ``marker_offsets`` and the prior; nothing is differentiated through the iterations.
    """
    dtype = jnp.result_type(x, joint_offsets, marker_offsets)
    chain = kinematic_chain(edges, dtype)
    q_init = quat_normalize(jnp.asarray(init_rotations, dtype))
    if prior_rotations is None:
        prior_rotations = _relative_rotations(q_init, chain.parent)
    n_seg = q_init.shape[0]
    weight = jnp.broadcast_to(jnp.asarray(prior_weight, dtype), (n_seg,))
    marker_segment = jnp.asarray(marker_segment)
    model = IKModel(
        joint_offsets=jnp.asarray(joint_offsets, dtype),
        marker_offsets=jnp.asarray(marker_offsets, dtype),
        marker_segment=marker_segment,
        marker_weight=jnp.ones(marker_segment.shape[0], dtype),
        chain=chain,
        segment_markers=jnp.full((n_seg, 1), -1, marker_segment.dtype),
        levels=0,
    )
    fast = solve_frame(
        jax.lax.stop_gradient(jnp.asarray(x, dtype)),
        mask,
        jax.lax.stop_gradient(model),
        jnp.asarray(init_root, dtype),
        q_init,
        jax.lax.stop_gradient(prior_rotations.astype(dtype)),
        jax.lax.stop_gradient(weight),
        max_steps=max_steps,
        energy_rtol=1e-14,
    )
    q0 = jax.lax.stop_gradient(fast.rotations)
    args = (
        jnp.asarray(x, dtype),
        mask.astype(dtype),
        q0,
        model.joint_offsets,
        model.marker_offsets,
        chain,
        marker_segment,
        prior_rotations.astype(dtype),
        weight,
    )
    y0 = (jax.lax.stop_gradient(fast.root_position), jnp.zeros((n_seg, 3), dtype))
    # The answer is already converged: the polish takes a step or two, and exists so that
    # the solution carries optimistix' implicit derivative (its result code is moot).
    solver = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-9)
    sol = optx.least_squares(_residuals, solver, y0, args, max_steps=4, throw=False)
    t_root, delta = sol.value
    q = quat_normalize(quat_multiply(axis_angle_to_quat(delta), q0))
    rot = quat_to_matrix(q)
    trans, _ = _poses(t_root, rot, model.joint_offsets, chain)
    err = jnp.sum((_markers(rot, trans, model.marker_offsets, marker_segment) - args[0]) ** 2, axis=-1)
    rms = jnp.sqrt(jnp.sum(err * args[1]) / jnp.maximum(jnp.sum(args[1]), 1.0))
    return FrameSolution(root_position=t_root, rotations=q, num_steps=fast.num_steps, result=fast.result, rms=rms)


# ------------------------------------------------------------- trial-level IK
@dataclasses.dataclass(frozen=True, eq=False)
class Motion:
    """Inverse-kinematics result: the skeleton's pose in every frame.

    Arrays have a leading trial axis when the input had one. Orientations are global
    (segment frame -> world, the convention of :class:`jaxskel.skeleton.Skeleton`).

    Attributes
    ----------
    root_position
        (F, 3) root segment translation, metres.
    rotations
        (F, S, 4) segment orientations, unit quaternions (w, x, y, z), w >= 0.
    segment_translations
        (F, S, 3) segment origins (proximal joints; the root's marker centroid).
    joint_positions
        (F, J, 3) joint centres.
    fitted_markers
        (F, M, 3) markers predicted by the skeleton in every frame, including where the
        input marker was missing (gap filling); NaN for markers not on the skeleton.
    marker_rms
        (F,) RMS distance between visible markers and their fitted positions.
    segment_observed
        (F, S) True where all of the segment's markers were visible; elsewhere the
        segment's relative rotation was also drawn towards the interpolation between
        neighbouring observed frames (when ``fill_gaps``).
    steps, result
        (F,) solver iterations (both passes) and optimistix result codes (0 successful,
        7 maximum steps reached).
    converged
        Every frame's solver succeeded.
    marker_labels, rate
        Labels of the marker axis and the frame rate (Hz; None if unknown).
    lowpass_hz
        (M,) the cutoff each marker was low-pass filtered at before the IK
        (:func:`jaxskel.clean.lowpass_markers`; NaN: as measured), ``None`` when none was
        (:func:`inverse_kinematics` itself never filters; :func:`jaxskel.fit_skeleton`
        does, and then reports ``marker_rms`` against the markers as measured).
    """

    root_position: np.ndarray
    rotations: np.ndarray
    segment_translations: np.ndarray
    joint_positions: np.ndarray
    fitted_markers: np.ndarray
    marker_rms: np.ndarray
    segment_observed: np.ndarray
    steps: np.ndarray
    result: np.ndarray
    converged: bool
    marker_labels: tuple[str, ...]
    rate: float | None = None
    lowpass_hz: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                a = np.array(value, copy=True)
                a.setflags(write=False)
                object.__setattr__(self, f.name, a)

    @property
    def n_frames(self) -> int:
        return int(self.root_position.shape[-2])

    def fitted_trial(self, *, source: str = "jaxskel inverse kinematics", up_axis: str = "unknown") -> Trial:
        """The fitted markers as a :class:`jaxskel.Trial` (e.g. to save as TRC or C3D)."""
        from ..io import Trial

        if self.rate is None:
            raise InputError("this motion has no frame rate; pass a Trial (or rate=) to inverse_kinematics")
        if self.fitted_markers.ndim != 3:
            raise InputError("fitted_trial works on one trial; index the motion's leading trial axis first")
        keep = np.isfinite(self.fitted_markers).all(axis=(0, 2))
        return Trial(
            positions=self.fitted_markers[:, keep],
            labels=tuple(lab for lab, k in zip(self.marker_labels, keep) if k),
            rate=self.rate,
            up_axis=up_axis,
            source=source,
        )

    def __repr__(self) -> str:
        return (
            f"Motion({self.n_frames} frames, {self.rotations.shape[-2]} segments, "
            f"median marker RMS {1e3 * float(np.median(self.marker_rms)):.2f} mm, converged={self.converged})"
        )


def segment_members(skeleton: SkeletonLike, n_rows: int | None = None) -> np.ndarray:
    """(n_rows, S) True where marker m sits on segment s (markers off the skeleton, and
    padding rows beyond its M markers, on none); ``n_rows`` defaults to M."""
    seg = np.asarray(skeleton.marker_segment)
    member = np.zeros((len(seg) if n_rows is None else n_rows, skeleton.n_segments), bool)
    on = np.flatnonzero((seg >= 0) & np.isfinite(np.asarray(skeleton.marker_offsets)).all(axis=1))
    member[on, seg[on]] = True
    return member


def measured_rms(fitted: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rms (F,), n (F,))``: per frame, the RMS distance between the ``fitted`` markers (F, M, 3)
    and the markers as ``measured`` (NaN missing) over the ``n`` markers both have; 0 where
    ``n`` is 0. The residual a motion reports when its IK posed filtered markers."""
    miss = np.sum((np.asarray(fitted) - np.asarray(measured)) ** 2, axis=-1)
    seen = np.isfinite(miss)
    n = seen.sum(1)
    return np.sqrt(np.where(seen, miss, 0.0).sum(1) / np.maximum(n, 1)), n


@jax.jit
def _gap_prior(
    rel: Float[Array, "T F S 4"], observed: Bool[Array, "T F S"], start: Int[Array, " F"], stop: Int[Array, " F"]
) -> Float[Array, "T F S 4"]:
    """Relative rotations interpolated (slerp) across each segment's unobserved frames.

    Observed frames keep their own value; a gap takes the slerp between the last observed
    frame before and the first after it by time fraction; a gap at either end holds the
    nearest observed value; a segment never observed keeps ``rel``. Frame ``f`` belongs to
    the recording ``[start[f], stop[f])`` (trials fitted together, concatenated): a gap
    never borrows a value from another recording, whose pose is unrelated.
    """
    n = rel.shape[1]
    idx = jnp.arange(n)[None, :, None]
    prev = jax.lax.cummax(jnp.where(observed, idx, -1), axis=1)
    nxt = jax.lax.cummin(jnp.where(observed, idx, n), axis=1, reverse=True)
    has_prev, has_next = prev >= start[None, :, None], nxt < stop[None, :, None]
    a = jnp.take_along_axis(rel, jnp.clip(prev, 0, n - 1)[..., None], axis=1)
    b = jnp.take_along_axis(rel, jnp.clip(nxt, 0, n - 1)[..., None], axis=1)
    frac = (idx - prev) / jnp.maximum(nxt - prev, 1)
    alpha = jnp.where(has_prev & has_next, frac, jnp.where(has_prev, 0.0, 1.0)).astype(rel.dtype)
    return jnp.where((has_prev | has_next)[..., None], slerp(a, b, alpha), rel)


@jax.jit
def _interpolated_start(
    rotations: Float[Array, "N S 4"], keep: Bool[Array, "T F S"], parent: Int[Array, " S"],
    start: Int[Array, " F"], stop: Int[Array, " F"],
) -> tuple[Float[Array, "N S 4"], Float[Array, "N S 4"]]:
    """Relative rotations interpolated over the frames not in ``keep`` (:func:`_gap_prior`)
    and the global orientations they compose to; N = T * F frames, trial-major."""
    rel = jax.vmap(_relative_rotations, (0, None))(rotations, parent)
    prior = _gap_prior(rel.reshape(*keep.shape, 4), keep, start, stop).reshape(rel.shape)
    return prior, jax.vmap(_compose_relative, (0, None))(prior, parent)


def _ik_input(
    skeleton: SkeletonLike, data: Trial | tuple[np.ndarray, np.ndarray] | np.ndarray
) -> tuple[np.ndarray, np.ndarray, float | None]:
    """(x (..., F, M, 3) zero-filled, mask (..., F, M), rate) in the skeleton's marker order."""
    from ..io import Trial

    if isinstance(data, Trial):
        missing = [lab for lab in skeleton.marker_labels if lab not in data.labels]
        if missing:
            raise InputError(
                f"the trial lacks {len(missing)} of the skeleton's markers ({', '.join(missing[:8])}); "
                "IK needs the marker set the skeleton was fitted with (absent markers may be all-NaN columns)"
            )
        x, mask = data.select_markers(list(skeleton.marker_labels)).to_arrays()
        return x, mask, data.rate
    if isinstance(data, tuple):
        if len(data) != 2:
            raise InputError("pass a Trial, positions with NaN for missing samples, or a tuple (x, mask)")
        x = np.asarray(data[0], dtype=float)
        mask = np.asarray(data[1], dtype=bool)
        if mask.shape != x.shape[:-1]:
            raise InputError(f"mask shape {mask.shape} does not match positions {x.shape}")
    else:
        x = np.asarray(data, dtype=float)
        mask = np.ones(x.shape[:-1], bool)
    if x.ndim not in (3, 4) or x.shape[-1] != 3:
        raise InputError(f"positions must be (F, M, 3) or (trials, F, M, 3); got {x.shape}")
    if x.shape[-2] != skeleton.n_markers:
        raise InputError(
            f"positions have {x.shape[-2]} markers but the skeleton has {skeleton.n_markers}; "
            "pass the markers in the skeleton's order (skeleton.marker_labels)"
        )
    mask = mask & np.isfinite(x).all(axis=-1)
    return np.where(mask[..., None], x, 0.0), mask, None


def _check_bounds(bounds: Sequence[tuple[int, int]], n_frames: int) -> tuple[tuple[int, int], ...]:
    """Validated ``(start, stop)`` ranges: consecutive, covering frames ``0 .. n_frames``."""
    try:
        out = tuple((int(lo), int(hi)) for lo, hi in bounds)
    except (TypeError, ValueError):
        raise InputError(f"trial_bounds must be (start, stop) pairs of frame indices, got {bounds!r}") from None
    if out and (out[0][0] != 0 or out[-1][1] != n_frames or any(lo >= hi for lo, hi in out)
                or any(a[1] != b[0] for a, b in zip(out, out[1:]))):
        raise InputError(
            f"trial_bounds {list(out)} must be consecutive non-empty (start, stop) ranges covering the "
            f"{n_frames} frames"
        )
    return out


# Compiled once per shape: run eagerly, the vmapped quaternion algebra would be dispatched
# op by op, and the rigid refinement calls it once per sweep.
_relative_batch = jax.jit(jax.vmap(_relative_rotations, (0, None)))


def _host_relative(q: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """:func:`_relative_rotations` of (N, S, 4) host arrays, with non-negative ``w``."""
    rel = np.asarray(_program_cache.call(_relative_batch, to_device(q), to_device(parent)))
    return np.where(rel[..., :1] < 0, -rel, rel)


def _interpolated(
    rotations: np.ndarray, keep: np.ndarray, parent: np.ndarray, bounds: Sequence[tuple[int, int]] = ()
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_interpolated_start` on (T, F, S, 4) host arrays, frames padded to a bucket
    size so that its compiled shapes are reused; ``bounds``: the frame ranges of
    recordings concatenated along F (default: one recording)."""
    n_trials, n_frames, n_seg = keep.shape
    f_pad = bucket_size(n_frames)
    rp = np.tile(np.asarray(_IDENTITY), (n_trials, f_pad, n_seg, 1))
    kp = np.zeros((n_trials, f_pad, n_seg), bool)
    rp[:, :n_frames] = rotations
    kp[:, :n_frames] = keep
    first, stop = np.zeros(f_pad, np.int32), np.full(f_pad, f_pad, np.int32)
    for lo, hi in bounds:
        first[lo:hi], stop[lo:hi] = lo, hi
    prior, start = _program_cache.call(
        _interpolated_start, to_device(rp.reshape(-1, n_seg, 4)), to_device(kp), to_device(parent), to_device(first),
        to_device(stop),
    )
    shape = (n_trials, f_pad, n_seg, 4)
    return (
        np.asarray(prior).reshape(shape)[:, :n_frames],
        np.asarray(start).reshape(shape)[:, :n_frames],
    )


@float64_scope
def inverse_kinematics(
    skeleton: SkeletonLike,
    data: Trial | tuple[np.ndarray, np.ndarray] | np.ndarray,
    *,
    init: Motion | None = None,
    prior_weight: float = DEFAULT_PRIOR_WEIGHT,
    fill_gaps: bool = True,
    max_steps: int = 100,
    batch_size: int = 64,
    rate: float | None = None,
    threads: int | None = None,
    trial_bounds: Sequence[tuple[int, int]] | None = None,
    slots: int | None = None,
) -> Motion:
    """Pose a rigid skeleton in every frame: root translation and segment rotations.

    Parameters
    ----------
    skeleton
        From :func:`jaxskel.skeleton.fit_rigid`.
    data
        A :class:`Trial` (markers matched by label), an array (F, M, 3) or
        (trials, F, M, 3) in the skeleton's marker order with NaN for missing samples,
        or a tuple ``(x, mask)``.
    init
        A previous :class:`Motion` of the same frames to start from (default: a Horn
        alignment of every segment, :func:`jaxskel.skeleton._ik_batch._horn_start`); its relative
        rotations are also the first pass's prior.
    prior_weight
        Pose-prior weight in metres per radian (:mod:`jaxskel.skeleton._ik`).
    fill_gaps
        Second pass for frames where a segment is not fully seen: its relative rotation
        is drawn towards the interpolation between the neighbouring observed frames.
    max_steps, batch_size
        Levenberg-Marquardt iterations per frame; frames solved together per compiled
        chunk (:func:`jaxskel.skeleton._ik_batch.solve`).
    rate
        Frame rate for array input (a Trial brings its own).
    threads
        Host threads that solve chunks concurrently (default: the CPU count, at most 4).
    trial_bounds
        ``(start, stop)`` frame ranges of recordings concatenated along the frame axis
        (default: a Trial's ``metadata["trial_bounds"]``, set when trials are fitted
        together). Gaps are filled from frames of their own recording only.
    slots
        Marker slots per segment in the solver's layout (default: as many as the fullest
        segment has). :func:`jaxskel.fit_skeleton` passes those of the rigid refinement
        (:func:`jaxskel.skeleton._ik_batch.solver_shape`, one more than the fullest non-root
        segment has markers), so that both run one compiled solver: one compilation
        less in a new process, for an idle slot per segment in the IK.

    Returns
    -------
    :class:`Motion`; a :class:`ConvergenceWarning` is issued if some frame hit ``max_steps``.

    The solver is :mod:`jaxskel.skeleton._ik_batch` (frames vectorised on the last axis, an O(S)
    tree elimination per step, Newton steps after the first); it minimises the same
    energy as :func:`solve_frame` / :func:`ik_solve`.
    """
    from ._ik_batch import batch_model, solve, solver_shape

    for name, value in (("max_steps", max_steps), ("batch_size", batch_size)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"{name} must be a positive int, got {value!r}")
    if slots is not None and (not isinstance(slots, (int, np.integer)) or slots < 1):
        raise InputError(f"slots must be a positive int or None, got {slots!r}")
    if threads is not None and (not isinstance(threads, (int, np.integer)) or threads < 1):
        raise InputError(f"threads must be a positive int or None (the CPU count, at most 4), got {threads!r}")
    x, mask, trial_rate = _ik_input(skeleton, data)
    lead = x.shape[:-3]
    n_trials = int(np.prod(lead)) if lead else 1
    n_frames, n_markers = x.shape[-3], x.shape[-2]
    if n_frames == 0:
        raise InputError("no frames to solve")
    if trial_bounds is None:
        trial_bounds = getattr(data, "metadata", {}).get("trial_bounds", ())
    bounds = _check_bounds(trial_bounds, n_frames)
    _, m_pad = solver_shape(skeleton.marker_segment, skeleton.edges, n_markers)  # padding columns is free
    n = n_trials * n_frames
    xf = np.zeros((n, m_pad, 3))
    mf = np.zeros((n, m_pad), bool)
    xf[:, :n_markers] = x.reshape(n, n_markers, 3)
    mf[:, :n_markers] = mask.reshape(n, n_markers)
    model = batch_model(
        skeleton.edges, skeleton.joint_offsets, skeleton.marker_offsets, skeleton.marker_segment, slots=slots or 1
    )
    n_seg = skeleton.n_segments
    parent = np.asarray(skeleton.parent)
    pw = np.full((n_seg,), float(prior_weight))
    kw = dict(max_steps=max_steps, chunk=int(batch_size), threads=threads)

    if init is None:
        sol = solve(model, xf, mf, None, None, None, pw, **kw)
    else:
        if init.rotations.shape[-2] != n_seg or init.root_position.shape[:-1] != lead + (n_frames,):
            raise InputError("init must be a Motion of this skeleton over the same frames")
        q0 = np.asarray(init.rotations, float).reshape(n, n_seg, 4)
        sol = solve(model, xf, mf, init.root_position.reshape(n, 3), q0, _host_relative(q0, parent), pw, **kw)
    steps = sol["num_steps"].astype(np.int64)
    real = mf.any(axis=1)

    def merge(rows: np.ndarray, again: dict[str, np.ndarray], take: np.ndarray) -> None:
        for key, value in again.items():
            if key != "num_steps":
                sol[key][rows[take]] = value[take]

    # Frames caught in a wrong basin (a limb folded the wrong way) fit far worse than
    # their neighbours: solve them again from the neighbours' pose and keep the better fit.
    rms = sol["rms"]
    suspect = real & (rms > RESEED_FACTOR * np.median(rms[real])) if real.any() else real
    if suspect.any() and (real & ~suspect).any():
        good = np.broadcast_to((real & ~suspect)[:, None], (n, n_seg)).reshape(n_trials, n_frames, n_seg)
        seed_rel, q_seed = _interpolated(
            sol["rotations"].reshape(n_trials, n_frames, n_seg, 4), good, parent, bounds
        )
        rows = np.flatnonzero(suspect)
        again = solve(
            model, xf[rows], mf[rows], sol["root_position"][rows],
            q_seed.reshape(n, n_seg, 4)[rows], seed_rel.reshape(n, n_seg, 4)[rows], pw, **kw,
        )
        merge(rows, again, again["rms"] < rms[rows])
        steps[rows] += again["num_steps"]

    # Observed: every marker of the segment visible (segments without markers count as seen).
    member = segment_members(skeleton, m_pad)
    observed = ~((~mf)[:, :, None] & member[None]).any(axis=1)  # (n, S)
    if fill_gaps and not observed.all():
        prior2, q_start = _interpolated(
            sol["rotations"].reshape(n_trials, n_frames, n_seg, 4), observed.reshape(n_trials, n_frames, n_seg),
            parent, bounds,
        )
        rows = np.flatnonzero(~observed.all(axis=1) & real)
        if rows.size:
            # Two starts for the same energy (markers + the interpolated prior): the
            # interpolation, and the pose already found. Across a long gap in fast motion
            # the interpolation can start in a wrong basin the markers would have ruled
            # out, so each frame keeps the lower energy.
            prior_rows = prior2.reshape(n, n_seg, 4)[rows]
            again = solve(
                model, xf[rows], mf[rows], sol["root_position"][rows],
                q_start.reshape(n, n_seg, 4)[rows], prior_rows, pw, **kw,
            )
            kept = solve(
                model, xf[rows], mf[rows], sol["root_position"][rows], sol["rotations"][rows], prior_rows, pw, **kw
            )
            better = kept["energy"] < again["energy"]
            for key in again:
                if key != "num_steps":
                    again[key][better] = kept[key][better]
            merge(rows, again, np.ones(rows.size, bool))
            steps[rows] += again["num_steps"] + kept["num_steps"]

    # Fitted markers back in the input's marker order (NaN for markers not on the skeleton).
    fitted = np.full((n, n_markers, 3), np.nan)
    index = np.asarray(model.marker_index)
    slot_used = np.asarray(model.marker_weight)[..., 0] > 0
    fitted[:, index[slot_used]] = sol["fitted"][:, slot_used]
    result = np.where(sol["done"], RESULT_SUCCESSFUL, RESULT_MAX_STEPS).astype(np.int32)
    failures = int((result != RESULT_SUCCESSFUL).sum())
    if failures:
        warnings.warn(
            f"inverse kinematics hit max_steps={max_steps} in {failures} frames (motion.result == 7); "
            "raise max_steps or check those frames for swapped or jumping markers",
            ConvergenceWarning,
            stacklevel=3,  # inverse_kinematics' caller (2 is float64_scope's wrapper)
        )

    def out(a: np.ndarray) -> np.ndarray:
        return a.reshape(lead + (n_frames,) + a.shape[1:])

    return Motion(
        root_position=out(sol["root_position"]),
        rotations=out(sol["rotations"]),
        segment_translations=out(sol["segment_translations"]),
        joint_positions=out(sol["joint_positions"]),
        fitted_markers=out(fitted),
        marker_rms=out(sol["rms"]),
        segment_observed=out(observed),
        steps=out(steps),
        result=out(result),
        converged=failures == 0,
        marker_labels=tuple(skeleton.marker_labels),
        rate=trial_rate if trial_rate is not None else rate,
    )
