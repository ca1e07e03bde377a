"""The learning-pipeline API: pure, jit/vmap/grad-able fits with documented shapes.

Three stages of Kirk et al. (2005) as pure JAX functions of arrays, usable inside a
user's ``jax.jit`` training step, under ``jax.vmap`` (over trials, noise draws,
...) and under ``jax.grad``. Gradients through every solve come from the implicit
function theorem at the optimum, never from unrolled iterations:

=================  ======================================  ==============================
function           solves                                  derivative
=================  ======================================  ==============================
`joint_cost_fn`    min over (c_f, r_k) of the joint cost   custom JVP, block-arrow Hessian
                   Q (one pair of segments)                 solve (:mod:`jaxskel.joints._cost`)
`rigid_fit_fn`     generalised Procrustes per segment       ``optimistix.fixed_point`` with
                   (constant marker / joint offsets)       ``ImplicitAdjoint``
`ik_fn`            per-frame inverse kinematics            ``optimistix.least_squares`` with
                                                           ``ImplicitAdjoint`` (:func:`ik_solve`)
=================  ======================================  ==============================

The *structure* (which marker is on which segment, the tree) is discrete and static:
:class:`SkeletonStructure` holds it as hashable static fields, so it can be passed
to ``jax.jit`` as an ordinary argument or closed over; only arrays are traced.
Shapes: F frames, M markers, S segments, J = S - 1 joints, K markers of a segment
pair, P points (markers + joints) of a segment, B bones. Missing samples are given by
masks, never NaN (put any finite value, e.g. 0, where the mask is False).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._errors import InputError
from .._math.rotation import horn_align
from .._runtime.precision import float64_scope
from ..joints import JointSolution, solve_joints
from ..skeleton import (
    DEFAULT_PRIOR_WEIGHT,
    FrameSolution,
    IKModel,
    ik_initial_guess,
    ik_solve,
    kinematic_chain,
    tree_levels,
)

__all__ = ["SkeletonStructure", "RigidFit", "joint_cost_fn", "rigid_fit_fn", "ik_fn"]


# ----------------------------------------------------------------------- structure
class SkeletonStructure(eqx.Module):
    """The discrete part of a skeleton: tree and marker assignment (static, hashable).

    Attributes
    ----------
    edges
        J (parent, child) segment pairs of a tree over S = J + 1 segments.
    marker_segment
        M segment indices, -1 for a marker that belongs to no segment (ignored).
    root
        Root segment (the one that is never a child).

    Build it with ``SkeletonStructure(edges, marker_segment)`` or
    :meth:`from_result` (a :class:`jaxskel.SkeletonResult` or :class:`jaxskel.skeleton.Skeleton`).
    """

    edges: tuple[tuple[int, int], ...] = eqx.field(static=True)
    marker_segment: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, edges: Any, marker_segment: Any):
        edges_np = np.asarray(edges, dtype=int).reshape(-1, 2)
        seg = np.asarray(marker_segment, dtype=int).reshape(-1)
        n_seg = len(edges_np) + 1
        if seg.size and (seg.max() >= n_seg or seg.min() < -1):
            raise InputError(f"marker_segment entries must be -1 or 0..{n_seg - 1}")
        children = set(edges_np[:, 1].tolist())
        if len(children) != len(edges_np) or sum(s not in children for s in range(n_seg)) != 1:
            raise InputError("edges must be (parent, child) pairs of a rooted tree (every segment but one a child)")
        self.edges = tuple((int(a), int(b)) for a, b in edges_np)
        self.marker_segment = tuple(int(v) for v in seg)

    @classmethod
    def from_result(cls, result: Any) -> SkeletonStructure:
        """From a :class:`jaxskel.SkeletonResult` (its rigid skeleton) or a :class:`jaxskel.skeleton.Skeleton`."""
        skeleton = getattr(result, "skeleton", result)
        if skeleton is None or not hasattr(skeleton, "marker_segment"):
            raise InputError("the result has no rigid skeleton (fit with rigid=True)")
        return cls(skeleton.edges, skeleton.marker_segment)

    # ------------------------------------------------------------ derived (numpy)
    @property
    def n_segments(self) -> int:
        return len(self.edges) + 1

    @property
    def n_joints(self) -> int:
        return len(self.edges)

    @property
    def n_markers(self) -> int:
        return len(self.marker_segment)

    @property
    def root(self) -> int:
        children = {c for _, c in self.edges}
        return next(s for s in range(self.n_segments) if s not in children)

    def segment_points(self) -> np.ndarray:
        """(S, P) indices into ``concat(markers (M), joints (J))`` of each segment's points, -1 padding.

        A segment's points are its markers, then the joints it takes part in.
        """
        seg = np.asarray(self.marker_segment)
        edges = np.asarray(self.edges, dtype=int).reshape(-1, 2)
        rows = []
        for s in range(self.n_segments):
            joints = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
            rows.append(np.concatenate([np.flatnonzero(seg == s), self.n_markers + joints]))
        width = max(len(r) for r in rows)
        out = np.full((self.n_segments, width), -1, dtype=int)
        for s, r in enumerate(rows):
            out[s, : len(r)] = r
        return out

    def bones(self) -> tuple[np.ndarray, np.ndarray]:
        """``(bones (B, 2) joint pairs, bone_segment (B,))``: every pair of joints on one segment."""
        edges = np.asarray(self.edges, dtype=int).reshape(-1, 2)
        pairs, segs = [], []
        for s in range(self.n_segments):
            joints = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
            for i in range(len(joints)):
                for k in range(i + 1, len(joints)):
                    pairs.append((joints[i], joints[k]))
                    segs.append(s)
        return np.asarray(pairs, dtype=int).reshape(-1, 2), np.asarray(segs, dtype=int)


# ----------------------------------------------------------------------- joint cost
@float64_scope
def joint_cost_fn(
    markers: Float[ArrayLike, "*batch F K 3"],
    mask: Bool[ArrayLike, "*batch F K"],
    *,
    alpha: float | Float[ArrayLike, "*batch"] = 1e-5,
    max_steps: int = 256,
    rtol: float | None = None,
    atol: float | None = None,
    c0: Float[ArrayLike, "*batch F 3"] | None = None,
    r0: Float[ArrayLike, "*batch K"] | None = None,
) -> JointSolution:
    """Joint between two marker groups: ``argmin_c Q(c)``, Kirk et al.'s joint cost.

    ``Q(c) = 1/K sum_k [ var_f |c_f - m_fk| + alpha mean_f |c_f - m_fk| ]`` over the
    frames where marker k is present (``mask``). ``markers`` (..., F, K, 3) holds the
    markers of both segments; leading axes are solved together (one vmapped solve).

    Returns a :class:`jaxskel.joints.JointSolution`: ``positions`` (..., F, 3) the joint per
    frame, ``radii`` (..., K), ``cost`` (...) = Q at the optimum (m^2), plus solver
    diagnostics. ``jax.grad`` of ``cost``, ``positions`` or ``radii`` with respect to
    ``markers`` and ``alpha`` is the implicit derivative at the optimum, as exact as the
    optimum is (``rtol``/``atol``, default 1e-10/1e-9 in float64; tighten them to
    compare with finite differences). ``alpha > 0`` keeps the derivative finite for a
    hinge, whose centre can otherwise slide along its axis. ``c0``/``r0`` warm-start
    the solve (default: per-frame marker centroid). Pure: jit, vmap and grad it freely.
    """
    return solve_joints(markers, mask, alpha=alpha, max_steps=max_steps, rtol=rtol, atol=atol, c0=c0, r0=r0)


# ------------------------------------------------------------------------- rigid fit
class RigidFit(eqx.Module):
    """Output of :func:`rigid_fit_fn`.

    Attributes
    ----------
    marker_offsets
        (M, 3) each marker in its segment frame (0 for markers with segment -1).
    joint_offsets
        (J, 2, 3) joint j in its parent frame and in its child frame (the latter 0:
        a segment's origin is its proximal joint; the root's is its markers' centroid).
    bone_lengths
        (B,) distance between the two joints of each bone
        (:meth:`SkeletonStructure.bones`).
    clouds
        (S, P, 3) each segment's mean point cloud (:meth:`SkeletonStructure.segment_points`)
        in the world pose of its reference frame; segment axes are world axes there.
    reference_frames
        (S,) that frame (the first with the most points of the segment present).
    point_rms
        (S, P) RMS distance of each point from its place on the rigid segment.
    steps, result
        Fixed-point iterations and optimistix result code (0 = converged).
    """

    marker_offsets: Float[Array, "M 3"]
    joint_offsets: Float[Array, "J 2 3"]
    bone_lengths: Float[Array, " B"]
    clouds: Float[Array, "S P 3"]
    reference_frames: Int[Array, " S"]
    point_rms: Float[Array, "S P"]
    steps: Int[Array, ""]
    result: Int[Array, ""]


def _gpa_step(y, args):
    """One generalised-Procrustes update, gauge-fixed onto the reference frame.

    Align every frame's cloud to ``y`` (Horn), average the aligned clouds, then align
    that mean onto the reference frame's observed points. The last step removes the
    rotation/translation freedom of the mean (G(Q y) = G(y) for any rigid Q), so the
    fixed point is isolated and I - dG/dy is invertible: implicit differentiation works.
    """
    points, weights, ref_points, ref_weights, fallback = args
    align = jax.vmap(jax.vmap(horn_align))  # over frames, then segments
    known = (jnp.sum(weights, axis=0) > 0).astype(weights.dtype)  # points seen in some frame
    rot, t = align(points, jnp.broadcast_to(y, points.shape), weights * known[None])
    aligned = jnp.einsum("fsij,fspj->fspi", rot, points) + t[:, :, None, :]
    total = jnp.sum(weights, axis=0)
    mean = jnp.sum(weights[..., None] * aligned, axis=0) / jnp.where(total > 0, total, 1.0)[..., None]
    mean = jnp.where((total > 0)[..., None], mean, fallback)
    rot0, t0 = jax.vmap(horn_align)(mean, ref_points, ref_weights)
    return jnp.einsum("sij,spj->spi", rot0, mean) + t0[:, None, :]


@float64_scope
def rigid_fit_fn(
    structure: SkeletonStructure,
    markers: Float[ArrayLike, "F M 3"],
    mask: Bool[ArrayLike, "F M"],
    joints: Float[ArrayLike, "F J 3"],
    joint_mask: Bool[ArrayLike, "F J"] | None = None,
    *,
    max_steps: int = 100,
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> RigidFit:
    """Rigid segments from markers and joint centres: generalised Procrustes (Kirk §3.3).

    For each segment s with points p (its markers and its joints), find the constant
    cloud ``Y_s`` (P, 3) and per-frame poses minimising
    ``sum_f sum_p w_fsp |R_fs x_fsp + t_fs - Y_sp|^2`` (``w`` = presence; a frame
    counts for a segment only with >= 3 of its points present). Solved as the fixed
    point of the gauge-fixed Procrustes update (:func:`_gpa_step`) with
    ``optimistix.fixed_point``; derivatives by ``optimistix.ImplicitAdjoint``.

    Each segment needs >= 3 non-collinear points (markers + joints) in some frame.
    ``joints`` are e.g. the joint positions of :func:`joint_cost_fn` or of a fit.
    Pure; jit/vmap/grad-able in ``markers`` and ``joints``.
    """
    markers = jnp.asarray(markers)
    dtype = markers.dtype if jnp.issubdtype(markers.dtype, jnp.floating) else jnp.float64
    markers = markers.astype(dtype)
    joints = jnp.asarray(joints, dtype)
    n_markers = markers.shape[1]
    if n_markers != structure.n_markers or joints.shape[1:] != (structure.n_joints, 3):
        raise InputError(
            f"markers (F, {structure.n_markers}, 3) and joints (F, {structure.n_joints}, 3) must match the "
            f"structure; got {markers.shape} and {joints.shape}"
        )
    mask = jnp.asarray(mask, bool) & (jnp.asarray(structure.marker_segment) >= 0)[None]
    jmask = jnp.ones(joints.shape[:2], bool) if joint_mask is None else jnp.asarray(joint_mask, bool)
    index = structure.segment_points()  # (S, P) static
    valid = jnp.asarray(index >= 0)
    idx = jnp.asarray(np.maximum(index, 0))
    all_points = jnp.concatenate([markers, joints], axis=1)  # (F, M + J, 3)
    all_mask = jnp.concatenate([mask, jmask], axis=1)
    points = all_points[:, idx]  # (F, S, P, 3)
    present = all_mask[:, idx] & valid[None]
    usable = jnp.sum(present, axis=-1) >= 3  # (F, S)
    weights = (present & usable[..., None]).astype(dtype)
    points = jnp.where(present[..., None], points, 0.0)

    ref = jnp.argmax(jnp.sum(weights, axis=-1), axis=0)  # (S,) first frame with the most points
    seg = jnp.arange(index.shape[0])
    ref_points = points[ref, seg]
    ref_weights = weights[ref, seg]
    fallback = jax.lax.stop_gradient(ref_points)
    args = (points, weights, ref_points, ref_weights, fallback)
    sol = optx.fixed_point(
        _gpa_step, optx.FixedPointIteration(rtol=rtol, atol=atol), ref_points, args,
        max_steps=max_steps, throw=False, adjoint=optx.ImplicitAdjoint(),
    )
    clouds = sol.value

    # residual scatter of each point about its place on the rigid segment
    align = jax.vmap(jax.vmap(horn_align))
    wsum = jnp.sum(weights, axis=0)
    rot, t = align(points, jnp.broadcast_to(clouds, points.shape), weights * (wsum > 0)[None])
    aligned = jnp.einsum("fsij,fspj->fspi", rot, points) + t[:, :, None, :]
    sq = jnp.sum((aligned - clouds[None]) ** 2, axis=-1)
    point_rms = jnp.sqrt(jnp.sum(weights * sq, axis=0) / jnp.maximum(wsum, 1.0))

    # offsets: segment origin at the proximal joint (root: centroid of its markers)
    n_seg, n_mark, n_joint = structure.n_segments, structure.n_markers, structure.n_joints
    edges = np.asarray(structure.edges, dtype=int).reshape(-1, 2)
    slot = {(s, int(p)): k for s in range(n_seg) for k, p in enumerate(index[s]) if p >= 0}
    seg_of = np.asarray(structure.marker_segment)
    root_slots = [slot[(structure.root, m)] for m in np.flatnonzero(seg_of == structure.root)]
    if not root_slots:
        raise InputError("the root segment has no markers; rigid_fit_fn places the root's origin at their centroid")
    origins = []
    for s in range(n_seg):
        if s == structure.root:
            origins.append(jnp.mean(clouds[s, jnp.asarray(root_slots)], axis=0))
        else:
            j = int(np.flatnonzero(edges[:, 1] == s)[0])
            origins.append(clouds[s, slot[(s, n_mark + j)]])
    origin = jnp.stack(origins)
    m_rows = [(int(seg_of[m]), slot[(int(seg_of[m]), m)]) if seg_of[m] >= 0 else (0, -1) for m in range(n_mark)]
    marker_offsets = jnp.stack([
        clouds[s, k] - origin[s] if k >= 0 else jnp.zeros(3, dtype) for s, k in m_rows
    ]) if n_mark else jnp.zeros((0, 3), dtype)
    parent_side = jnp.stack([
        clouds[int(p), slot[(int(p), n_mark + j)]] - origin[int(p)] for j, (p, _) in enumerate(edges)
    ]) if n_joint else jnp.zeros((0, 3), dtype)
    joint_offsets = jnp.stack([parent_side, jnp.zeros_like(parent_side)], axis=1)
    bones, bone_seg = structure.bones()
    bone_lengths = jnp.stack([
        jnp.linalg.norm(clouds[s, slot[(s, n_mark + a)]] - clouds[s, slot[(s, n_mark + b)]])
        for (a, b), s in zip(bones.tolist(), bone_seg.tolist())
    ]) if len(bones) else jnp.zeros((0,), dtype)
    return RigidFit(
        marker_offsets=marker_offsets,
        joint_offsets=joint_offsets,
        bone_lengths=bone_lengths,
        clouds=clouds,
        reference_frames=ref,
        point_rms=point_rms,
        steps=jnp.asarray(sol.stats["num_steps"]),
        result=jnp.asarray(sol.result._value, jnp.int32),
    )


# ------------------------------------------------------------------------------- IK
def _ik_model(structure: SkeletonStructure, joint_offsets, marker_offsets, dtype) -> IKModel:
    seg = np.asarray(structure.marker_segment)
    members = [np.flatnonzero(seg == s) for s in range(structure.n_segments)]
    width = max(1, max(len(m) for m in members))
    seg_markers = np.full((structure.n_segments, width), -1, np.int32)
    for s, m in enumerate(members):
        seg_markers[s, : len(m)] = m
    return IKModel(
        joint_offsets=joint_offsets,
        marker_offsets=marker_offsets,
        marker_segment=jnp.asarray(np.maximum(seg, 0), jnp.int32),
        marker_weight=jnp.asarray(seg >= 0, dtype),
        chain=kinematic_chain(jnp.asarray(structure.edges, jnp.int32).reshape(-1, 2), dtype),
        segment_markers=jnp.asarray(seg_markers),
        levels=tree_levels(np.asarray(structure.edges, dtype=int)),
    )


@float64_scope
def ik_fn(
    structure: SkeletonStructure,
    markers: Float[ArrayLike, "F M 3"],
    mask: Bool[ArrayLike, "F M"],
    joint_offsets: Float[ArrayLike, "J 2 3"],
    marker_offsets: Float[ArrayLike, "M 3"],
    *,
    init_root: Float[ArrayLike, "F 3"] | None = None,
    init_rotations: Float[ArrayLike, "F S 4"] | None = None,
    prior_weight: float | Float[ArrayLike, " S"] = DEFAULT_PRIOR_WEIGHT,
    max_steps: int = 100,
) -> FrameSolution:
    """Inverse kinematics of every frame: root position and segment orientations.

    Per frame, minimises ``sum_m w_m |FK(t, q)_m - x_m|^2`` plus a weak pose prior
    (``prior_weight`` metres per radian, toward the starting pose) over the root
    translation t and the segment quaternions q (w, x, y, z), frames in parallel
    (vmapped :func:`jaxskel.skeleton.ik_solve`). The start is a root-down Horn alignment of each
    segment (:func:`jaxskel.skeleton._ik.ik_initial_guess`) unless ``init_*`` are given.

    Returns a :class:`jaxskel.skeleton._ik.FrameSolution` with leading axis F:
    ``root_position`` (F, 3), ``rotations`` (F, S, 4), ``rms`` (F,) marker residual
    (m), ``num_steps`` and ``result`` (F,). Gradients with respect to ``markers``,
    ``joint_offsets`` and ``marker_offsets`` are implicit (``optimistix.ImplicitAdjoint``);
    the start is not differentiated (it does not change the optimum).
    """
    markers = jnp.asarray(markers)
    dtype = jnp.result_type(markers, joint_offsets, marker_offsets, jnp.float32)
    markers = markers.astype(dtype)
    joint_offsets = jnp.asarray(joint_offsets, dtype)
    marker_offsets = jnp.asarray(marker_offsets, dtype)
    seg = np.asarray(structure.marker_segment)
    mask = jnp.asarray(mask, bool) & jnp.asarray(seg >= 0)[None]
    marker_offsets = jnp.where(jnp.asarray(seg >= 0)[:, None], marker_offsets, 0.0)
    if init_root is None or init_rotations is None:
        model = jax.lax.stop_gradient(_ik_model(structure, joint_offsets, marker_offsets, dtype))
        identity = jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype), (structure.n_segments, 1))
        guess_root, guess_rot = jax.vmap(ik_initial_guess, in_axes=(0, 0, None, None))(
            jax.lax.stop_gradient(markers), mask, model, identity
        )
        init_root = guess_root if init_root is None else init_root
        init_rotations = guess_rot if init_rotations is None else init_rotations
    edges = jnp.asarray(structure.edges, jnp.int32).reshape(-1, 2)
    segment = jnp.asarray(np.maximum(seg, 0), jnp.int32)

    def one(x, m, t0, q0):
        return ik_solve(x, m, joint_offsets, marker_offsets, edges, segment, t0, q0,
                        prior_weight=prior_weight, max_steps=max_steps)

    return jax.vmap(one)(markers, mask, jnp.asarray(init_root, dtype), jnp.asarray(init_rotations, dtype))
