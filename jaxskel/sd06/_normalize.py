"""Skeleton normalisation: body planes and skeleton-aligned limb frames (Sar Dessai et al. 2006, §3).

Frames are rotation matrices whose COLUMNS are the axes in world coordinates:
``L = [x | y | z]`` with, for the body frame, x = frontal-plane normal
(anterior), y = sagittal-plane normal (the subject's left), z = transverse-plane
normal (superior). A limb frame ``(L_s, o_s)`` maps limb coordinates to the
world, ``x_world = L_s @ x_limb + o_s``.

Default pose (§3). Per frame, from the joint positions ``X`` (J, 3) with centroid
``c``, covariance eigenvalues ``l_1 >= l_2 >= l_3`` and eigenvectors ``e_k``:

* ``plane``  = ``l_3``: mean squared distance to the best-fit plane;
* ``ratio``  = short / long edge of the bounding box of the joints projected on
  ``(e_1, e_2)`` (the best-fit plane): small for an elongated, upright pose;
* ``spread`` = mean ``|X_j - c|``: small for a compact pose (arms down).

They are made unit-free with the recording's scale ``L`` = median over frames of
``spread``, and the cost is ``w_plane plane / L^2 + w_ratio ratio + w_spread
spread / L`` (weights :data:`DEFAULT_POSE_WEIGHTS`, configurable). Standing with
the arms hanging makes all three terms small; a T-pose has ratio ~1, a crouch is
not planar, raised arms spread the joints. A subject lying down is planar and
elongated too, so only frames whose best-fit plane holds the up axis to within
:data:`UPRIGHT_TILT` (60 degrees) are searched, when there are any.

The cost only sees joints, so it cannot tell a frame of the held default pose
from one where only a leaf limb (hand, foot, head: no distal joint) moves, yet
the leaf's frame is taken from the chosen frame. Frames whose cost is within
``candidate_tolerance`` (cost units, default 0.02) of the least cost are
therefore all candidates; a default pose is held, so only the stillest fifth
of them (sum over joints of the relative rotation's angular step) can be chosen,
and the default-pose frame ``d`` is the one of those whose leaves are closest to their typical posture over the candidates (the
geometric median of the direction from the parent limb's origin to the leaf's
joint, seen in the leaf's frame); the cost breaks ties. With tolerance 0 this
is the paper's least-cost frame.

Body planes at frame ``d``: the frontal normal is ``e_3``; the transverse normal
is the up axis made orthogonal to it; the sagittal normal completes the frame.
The front/back sign is not visible in a planar pose, and with it left and right
(``y = z x x``): it comes from the body, never from the order of the joints.
With ``n`` the unsigned frontal normal, ``n_f`` the same normal carried by the
root through frame f, and "low" meaning below a quarter of the joints' height
range at frame d, the first conclusive cue of

1. ``facing``, a world direction given by the caller: ``sign(n . facing)``;
2. feet: the leaves with their own long axis (heel -> toe, ``leaf_axes``) whose
   proximal joint is low point forward: ``sum n . a_leaf`` (conclusive when
   above 0.3 per foot);
3. knees: for every low chain of joints (proximal, middle, distal; e.g. hip,
   knee, ankle) the middle joint's mean offset from the line of the two others
   along ``n_f``, over the recording: knees bend forward (conclusive when above
   0.02 body scales per chain);
4. walking: the distance the root travels along ``n_f`` (conclusive above 2
   body scales)

decides; without one the sign makes the largest world component of ``n``
positive (a convention, with a DegenerateMotionWarning).

Limb frames at frame ``d``: the root (hierarchical root segment) gets the body
frame. Every other segment's main orientation ``m`` runs from its proximal joint
to the centroid of its distal joints; a leaf (no distal joint) takes its own
long axis when its markers give one (``leaf_axes``: a foot's heel -> toe, a
hand's wrist -> marker centroid; :func:`leaf_axes_from_markers`), else the
direction from its parent limb's origin to its proximal joint. The body normal most parallel to
``m`` is replaced by ``+-m`` (sign kept, so the limb frame stays close to the body
frame); of the two others, the one closer to the plane orthogonal to ``m`` is
projected into that plane and the third axis completes a right-handed frame.
Origins ("midpoints"): the centroid of the root's joints; the midpoint between
proximal joint and distal centroid; a leaf's proximal joint.

Propagation: with the segment orientations ``R_s(f)``, the limb frame in segment
coordinates ``R_s(d)^T L_s(d)`` is constant, so ``L_s(f) = R_s(f) R_s(d)^T
L_s(d)``; origins follow from the joints of each frame (the same rigid points).
"""

from __future__ import annotations

import dataclasses
import math
import types
import warnings
from collections.abc import Iterator, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._errors import DegenerateMotionError, DegenerateMotionWarning, InputError
from .._math.linalg import eigh3
from .._math.order import kth_smallest, masked_median
from .._math.padding import bucket_size
from .._math.rotation import (
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.compiler_options import jit
from .._runtime.precision import float64_scope

__all__ = [
    "DEFAULT_POSE_WEIGHTS",
    "Normalization",
    "normalize",
    "normalize_arrays",
    "default_pose_terms",
    "tree_arrays",
    "freeze_fields",
    "write_normalized",
]

#: Frame-count buckets per octave of the padded SD06 programs: a recording is padded by at
#: most ~19 % (every stage's cost is proportional to the padded length), at the price of
#: one compiled program set per bucket.
FRAME_BUCKETS_PER_OCTAVE = 4

#: Default weights of the default-pose cost terms (see the module docstring).
#: ``plane`` is larger because ``l_3 / L^2`` is a squared, small quantity
#: (~0.001 for a standing pose, ~0.05 for a random one).
DEFAULT_POSE_WEIGHTS: Mapping[str, float] = {"plane": 10.0, "ratio": 1.0, "spread": 1.0}

_AXES = {"x": 0, "y": 1, "z": 2}


def _unit(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 1e-12, n, 1.0)


# ------------------------------------------------------------------ tree (host)
@dataclasses.dataclass(frozen=True)
class TreeArrays:
    """Host-side index/weight arrays of a rooted segment tree.

    Attributes
    ----------
    proximal
        (S,) joint whose child is the segment (-1 for the root).
    leaf
        (S,) True for segments without distal joints.
    origin_weights
        (S, J): limb origin ``o_s = origin_weights[s] @ X`` from joint positions.
    main_weights
        (S, J): main orientation ``m_s = main_weights[s] @ X`` for non-leaf,
        non-root segments (leaves and the root have zero rows).
    order
        (J,) joints in topological order (a parent's joint before its children's).
    chain_proximal, chain_distal, chain
        Per joint j as the middle of a chain of three joints: (J,) the proximal
        joint of j's parent segment (-1 at the root), (J, J) weights of the
        centroid of the child segment's distal joints, and (J,) whether both exist.
    """

    proximal: np.ndarray
    leaf: np.ndarray
    origin_weights: np.ndarray
    main_weights: np.ndarray
    order: np.ndarray
    chain_proximal: np.ndarray
    chain_distal: np.ndarray
    chain: np.ndarray


def tree_arrays(edges: Any, root: int) -> TreeArrays:
    """Validate a parent->child edge list and derive :class:`TreeArrays`."""
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2 or edges.shape[0] < 1 or not np.issubdtype(edges.dtype, np.integer):
        raise InputError(f"edges must be a (J, 2) integer array of parent->child segments, got shape {edges.shape}")
    n_joints = edges.shape[0]
    n_seg = n_joints + 1
    root = int(root)
    children = edges[:, 1]
    if edges.min() < 0 or edges.max() >= n_seg or len(set(children.tolist())) != n_joints or root in children:
        raise InputError(
            f"edges {edges.tolist()} with root {root} are not a rooted tree over {n_seg} segments: "
            "every segment except the root must be the child of exactly one joint"
        )
    proximal = np.full(n_seg, -1)
    proximal[children] = np.arange(n_joints)
    order, placed, pending = [], {root}, list(range(n_joints))
    while pending:
        ready = [j for j in pending if edges[j, 0] in placed]
        if not ready:
            raise InputError(f"edges {edges.tolist()} do not form a tree reachable from root {root}")
        for j in ready:
            order.append(j)
            placed.add(int(edges[j, 1]))
            pending.remove(j)
    distal = np.zeros((n_seg, n_joints))
    distal[edges[:, 0], np.arange(n_joints)] = 1.0
    n_distal = distal.sum(1)
    leaf = n_distal == 0
    distal_mean = distal / np.maximum(n_distal, 1)[:, None]
    prox = np.zeros((n_seg, n_joints))
    has_prox = proximal >= 0
    prox[np.flatnonzero(has_prox), proximal[has_prox]] = 1.0
    origin = np.where(leaf[:, None], prox, 0.5 * (prox + distal_mean))
    origin[root] = distal_mean[root]
    main = np.where(leaf[:, None], 0.0, distal_mean - prox)
    main[root] = 0.0
    chain_proximal = proximal[edges[:, 0]]
    chain_distal = distal_mean[edges[:, 1]]
    chain = (chain_proximal >= 0) & ~leaf[edges[:, 1]]
    return TreeArrays(
        proximal, leaf, origin, main, np.asarray(order, dtype=int), chain_proximal, chain_distal, chain
    )


def _leaf_clouds(
    edges: Any, root: int, marker_segment: Any, marker_offsets: Any, joint_offsets: Any
) -> tuple[int, Iterator[tuple[int, np.ndarray]]]:
    """The segment count, and for each leaf with finite markers ``(s, P - j)``: its markers
    relative to its proximal joint ``j`` (``joint_offsets[., 1]``, zero when not given), in
    segment coordinates."""
    tree = tree_arrays(np.asarray(edges), root)
    seg = np.asarray(marker_segment).reshape(-1)
    off = np.asarray(marker_offsets, dtype=float).reshape(-1, 3)
    if seg.shape[0] != off.shape[0]:
        raise InputError(f"marker_segment ({seg.shape[0]}) and marker_offsets ({off.shape[0]}) differ in length")
    joints = None if joint_offsets is None else np.asarray(joint_offsets, dtype=float)
    seen = np.all(np.isfinite(off), axis=1)

    def clouds() -> Iterator[tuple[int, np.ndarray]]:
        for s in np.flatnonzero(tree.leaf & (tree.proximal >= 0)):
            pts = off[(seg == s) & seen]
            if pts.shape[0]:
                yield int(s), pts - (np.zeros(3) if joints is None else joints[tree.proximal[s], 1])

    return tree.leaf.size, clouds()


def leaf_axes_from_markers(
    edges: Any, root: int, marker_segment: Any, marker_offsets: Any, joint_offsets: Any = None
) -> np.ndarray:
    """Each leaf segment's own long axis from its markers, in segment coordinates (S, 3).

    For a leaf (no distal joint) with markers at ``P_i`` (segment coordinates)
    and proximal joint ``j`` (``joint_offsets[., 1]``, the joint in the child
    frame; zero when not given), with ``c`` the mean of ``P_i - j`` and
    ``l_1 >= l_2`` the two largest eigenvalues (eigenvector ``e_1``) of their
    covariance: when the markers are elongated (``l_1 >= 4 l_2``) and longer
    along ``e_1`` than their distance from the joint (``ptp((P - j) e_1) >
    |c|``), as heel, metatarsal and toe markers on a foot are, the axis runs
    from the marker least to the one most advanced along ``e_1``, signed away
    from the joint (``c . e_1 > 0``: heel -> toe); otherwise
    (hand, head) it is the direction ``c`` from the joint to the markers. Rows
    of non-leaf segments and of leaves without markers are zero (the
    normalisation then uses the parent limb's direction).
    """
    n_segments, clouds = _leaf_clouds(edges, root, marker_segment, marker_offsets, joint_offsets)
    out = np.zeros((n_segments, 3))
    for s, rel in clouds:
        c = rel.mean(0)
        axis = c
        if rel.shape[0] >= 2:
            vals, vecs = np.linalg.eigh(np.cov(rel.T, bias=True))
            e1 = vecs[:, 2]
            along = rel @ e1
            if vals[2] >= 4.0 * vals[1] and np.ptp(along) > np.linalg.norm(c) and abs(c @ e1) > 1e-9:
                # From the rearmost to the foremost marker along e_1 (heel -> toe).
                axis = (rel[np.argmax(along)] - rel[np.argmin(along)]) * np.sign(c @ e1)
        n = np.linalg.norm(axis)
        if n > 1e-9:
            out[s] = axis / n
    return out


def leaf_lengths_from_markers(
    edges: Any, root: int, marker_segment: Any, marker_offsets: Any, joint_offsets: Any = None
) -> Float[np.ndarray, " S"]:
    """Each leaf segment's length: its farthest marker from its proximal joint (S,), 0 if unknown.

    ``marker_offsets`` and ``joint_offsets[:, 1]`` (the joint in the child segment) are in
    segment coordinates, so the distance is the same in every frame.
    """
    n_segments, clouds = _leaf_clouds(edges, root, marker_segment, marker_offsets, joint_offsets)
    out = np.zeros(n_segments)
    for s, rel in clouds:
        if np.all(np.isfinite(rel)):  # else the joint is unknown: length unknown (0)
            out[s] = float(np.max(np.linalg.norm(rel, axis=1)))
    return out


def up_vector(up_axis: Any) -> np.ndarray:
    """Unit up vector from an axis name ("z", "-y", ...) or a 3-vector."""
    if isinstance(up_axis, str):
        name = up_axis.strip().lower()
        sign = -1.0 if name.startswith("-") else 1.0
        if name.lstrip("+-") not in _AXES:
            raise InputError(
                f"up_axis must be one of x, y, z, -x, -y, -z or a 3-vector, got {up_axis!r}; "
                "the body planes need the recording's vertical (Trial.up_axis)"
            )
        return sign * np.eye(3)[_AXES[name.lstrip("+-")]]
    v = np.asarray(up_axis, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise InputError(f"up_axis must be an axis name or a non-zero 3-vector, got {up_axis!r}")
    return v / np.linalg.norm(v)


def calibration_mask(calibration: Any, n_frames: int, rate: float | None = None) -> np.ndarray | None:
    """Frames (F,) bool of a calibration window, or None when none is given.

    ``calibration`` is None, "auto" or "all" (no window: the default pose is sought
    in every frame; :func:`~jaxskel.sd06.parameterize` then chooses each joint's
    main movements, or takes every frame), a ``slice`` of frames, ``(start, stop)`` frame
    indices (integers, stop exclusive; negative counts from the end), ``(t0, t1)``
    seconds (floats; needs ``rate``) or a boolean mask of length F.
    """
    if calibration is None or (isinstance(calibration, str) and calibration in ("auto", "all")):
        return None
    if isinstance(calibration, slice):
        mask = np.zeros(n_frames, bool)
        mask[calibration] = True
    else:
        arr = np.asarray(calibration)
        if arr.dtype == bool:
            if arr.shape != (n_frames,):
                raise InputError(f"a calibration mask must have one entry per frame ({n_frames}), got shape {arr.shape}")
            mask = arr.copy()
        elif arr.shape == (2,) and np.issubdtype(arr.dtype, np.number):
            if np.issubdtype(arr.dtype, np.integer):
                start, stop = (int(v) for v in arr)
            else:
                if rate is None or not rate > 0:
                    raise InputError(
                        f"calibration={tuple(calibration)} is a time range in seconds, but the motion's frame rate "
                        "is unknown; give frames (integers) or pass rate="
                    )
                t0, t1 = (float(v) for v in arr)
                if not (np.isfinite(t0) and np.isfinite(t1)) or t0 < 0 or t1 <= t0:
                    raise InputError(f"calibration time range must be 0 <= t0 < t1 seconds, got {tuple(calibration)}")
                start, stop = int(np.floor(t0 * rate)), int(np.ceil(t1 * rate))
            mask = np.zeros(n_frames, bool)
            mask[slice(start, stop)] = True
        else:
            raise InputError(
                "calibration must be None or 'auto' (automatic), 'all' (every frame), a slice or (start, stop) of "
                "frames, (t0, t1) seconds, "
                f"a boolean mask per frame or a separate calibration motion; got {calibration!r}"
            )
    if mask.sum() < 3:
        raise InputError(
            f"the calibration window {calibration!r} holds {int(mask.sum())} of the motion's {n_frames} frames; "
            "it needs at least 3 (the default pose and the main movements)"
        )
    return mask


# ------------------------------------------------------------------ core (JAX)
#: The default pose is sought among frames whose best-fit body plane holds the up axis to
#: within this angle (radians; 60 degrees): standing, leaning or bowing, not lying (90).
UPRIGHT_TILT = math.radians(60.0)


def default_pose_terms(x: Float[Array, "J 3"]) -> tuple[Float[Array, " 3"], Float[Array, "3 3"]]:
    """``(plane, ratio, spread)`` of one frame's joints and the covariance eigenvectors (ascending)."""
    centred = x - jnp.mean(x, axis=0)
    cov = centred.T @ centred / x.shape[0]
    vals, vecs = eigh3(cov)
    extent = jnp.ptp(centred @ vecs[:, 1:], axis=0)
    ratio = jnp.min(extent) / jnp.maximum(jnp.max(extent), 1e-12)
    spread = jnp.mean(jnp.linalg.norm(centred, axis=-1))
    return jnp.stack([jnp.maximum(vals[0], 0.0), ratio, spread]), vecs


def _geometric_median(
    points: Float[Array, "F 3"], mask: Bool[Array, " F"], steps: int = 16
) -> Float[Array, " 3"]:
    """Geometric median of the masked points (Weiszfeld's iteration from their mean).

    Robust like a median (half the points may be far off) at the cost of a few
    elementwise passes, instead of sorting every frame.
    """
    w0 = mask.astype(points.dtype)

    def step(_, centre):
        w = w0 / jnp.maximum(jnp.linalg.norm(points - centre, axis=-1), 1e-9)
        return jnp.sum(w[:, None] * points, 0) / jnp.maximum(jnp.sum(w), 1e-300)

    mean = jnp.sum(w0[:, None] * points, 0) / jnp.maximum(jnp.sum(w0), 1.0)
    return jax.lax.fori_loop(0, steps, step, mean)


def _limb_frame(m: Float[Array, " 3"], body: Float[Array, "3 3"]) -> tuple[Float[Array, "3 3"], Int[Array, ""], Float[Array, ""]]:
    """Limb frame from its main orientation and the body normals (columns of ``body``).

    Returns the frame, the index of the column that holds the main axis and the
    sign with which it holds it (``m = sign * L[:, main]``).
    """
    m = _unit(m)
    cos = body.T @ m
    k = jnp.argmax(jnp.abs(cos))
    sign = jnp.where(cos[k] < 0, -1.0, 1.0).astype(m.dtype)
    axis_k = sign * m
    i, j = (k + 1) % 3, (k + 2) % 3
    # The body normal closer to the plane orthogonal to m is projected first.
    i_first = jnp.abs(cos[i]) <= jnp.abs(cos[j])
    first = jnp.where(i_first, i, j)
    proj = _unit(body[:, first] - (body[:, first] @ m) * m)
    # Cyclic (k, i, j): e_j = e_k x e_i and e_i = e_j x e_k.
    other = jnp.where(i_first, jnp.cross(axis_k, proj), jnp.cross(proj, axis_k))
    col_i = jnp.where(i_first, proj, other)
    col_j = jnp.where(i_first, other, proj)
    frame = jnp.zeros((3, 3), m.dtype).at[:, k].set(axis_k).at[:, i].set(col_i).at[:, j].set(col_j)
    return frame, k, sign


#: Names of the front/back cues, in the order they are tried (``Normalization.handedness``).
HANDEDNESS_CUES = ("facing", "feet", "knees", "walking", "none")


def _front_evidence(
    joints: Float[Array, "F J 3"],
    quats: Float[Array, "F S 4"],
    origins: Float[Array, "F S 3"],
    valid: Bool[Array, " F"],
    d: Int[Array, ""],
    root: Int[Array, ""],
    frontal: Float[Array, " 3"],
    up: Float[Array, " 3"],
    scale: Float[Array, ""],
    proximal: Int[Array, " S"],
    own_leaf: Bool[Array, " S"],
    leaf_d: Float[Array, "S 3"],
    chain_proximal: Int[Array, " J"],
    chain_distal: Float[Array, "J J"],
    chain: Bool[Array, " J"],
) -> tuple[Float[Array, " 3"], Bool[Array, " 3"]]:
    """Signed evidence that ``frontal`` points anterior, and whether it is conclusive, per body cue.

    Cues (see the module docstring): feet, knees, walking; each is a signed
    number along ``frontal`` (positive: anterior) and a flag.
    """
    heights = joints[d] @ up
    low = jnp.min(heights) + 0.25 * (jnp.max(heights) - jnp.min(heights))
    # Feet: leaves with their own long axis whose proximal joint is among the lowest.
    feet = own_leaf & (heights[jnp.maximum(proximal, 0)] < low) & (proximal >= 0)
    n_feet = jnp.sum(feet)
    feet_score = jnp.sum(jnp.where(feet, leaf_d @ frontal, 0.0))
    feet_ok = (n_feet > 0) & (jnp.abs(feet_score) > 0.3 * n_feet)
    # Knees: in the lower chains (proximal -> middle -> distal joints), the middle
    # joint's offset from the line of the two others, along the frontal normal as
    # the root carries it through the recording (knees bend forward).
    w = valid.astype(joints.dtype) / jnp.maximum(jnp.sum(valid), 1)
    carry = quat_multiply(quats[:, root], quat_conjugate(quats[d, root]))
    normal_f = quat_rotate(carry, frontal[None])  # (F, 3)
    x_prox = joints[:, jnp.maximum(chain_proximal, 0)]
    x_dist = jnp.einsum("jk,fkc->fjc", chain_distal, joints)
    u = x_dist - x_prox
    rel = joints - x_prox
    t = jnp.sum(rel * u, -1, keepdims=True) / jnp.maximum(jnp.sum(u * u, -1, keepdims=True), 1e-12)
    bulge = jnp.sum((rel - t * u) * normal_f[:, None], -1)  # (F, J)
    lower = chain & (x_dist[d] @ up < low)
    n_knees = jnp.sum(lower)
    knee_score = jnp.sum(jnp.where(lower, w @ bulge, 0.0)) / scale
    knee_ok = (n_knees > 0) & (jnp.abs(knee_score) > 0.02 * n_knees)
    # Walking: distance the root travels along its frontal normal, in body scales.
    step = origins[1:, root] - origins[:-1, root]
    pair = valid[1:] & valid[:-1]
    walk_score = jnp.sum(jnp.where(pair, jnp.sum(step * normal_f[1:], -1), 0.0)) / scale
    walk_ok = jnp.abs(walk_score) > 2.0
    return jnp.stack([feet_score, knee_score, walk_score]), jnp.stack([feet_ok, knee_ok, walk_ok])


@jit
def _normalize_core(
    joints: Float[Array, "F J 3"],
    quats: Float[Array, "F S 4"],
    translations: Float[Array, "F S 3"],
    valid: Bool[Array, " F"],
    edges: Int[Array, "J 2"],
    origin_weights: Float[Array, "S J"],
    main_weights: Float[Array, "S J"],
    proximal: Int[Array, " S"],
    parent: Int[Array, " S"],
    leaf: Bool[Array, " S"],
    leaves: Int[Array, " L"],
    root: Int[Array, ""],
    up: Float[Array, " 3"],
    facing: Float[Array, " 3"],
    weights: Float[Array, " 3"],
    candidate_tolerance: Float[Array, ""],
    search: Bool[Array, " F"],
    leaf_axes: Float[Array, "S 3"],
    has_leaf_axis: Bool[Array, " S"],
    chain_proximal: Int[Array, " J"],
    chain_distal: Float[Array, "J J"],
    chain: Bool[Array, " J"],
) -> dict[str, Array]:
    """Default-pose frame, body frame, limb frames and constant offsets (module docstring)."""
    terms, vecs = jax.vmap(default_pose_terms)(joints)
    scale = masked_median(terms[:, 2], valid)
    scaled = terms / jnp.stack([scale**2, jnp.ones_like(scale), scale])
    cost = jnp.where(valid, scaled @ weights, jnp.inf)
    origins = jnp.einsum("sj,fjk->fsk", origin_weights, joints)
    quats = quat_normalize(quats)

    # Default-pose candidates: frames within the tolerance of the least cost. Among
    # them, the leaves (invisible to the joint-based cost) decide: the frame whose
    # leaves sit closest to their typical posture over the candidates, with the cost
    # as a tie-breaker (it only matters when there are no leaves).
    # Only frames whose best-fit body plane stands (the up axis within UPRIGHT_TILT of the
    # plane): a subject lying down is planar and elongated too, but its plane cannot give
    # the transverse plane. Where no searched frame stands, every searched frame is taken
    # (and the normalisation reports the lying body plane).
    standing = jnp.abs(vecs[:, :, 0] @ up) <= jnp.sin(UPRIGHT_TILT)
    search = jnp.where(jnp.any(valid & search & standing), search & standing, search)
    least = jnp.min(jnp.where(search, cost, jnp.inf))
    candidate = valid & search & (cost <= least + candidate_tolerance)
    # A default pose is held: of the candidates keep the stillest fifth (joint
    # speeds), so a frame that only passes through the pose (a twist swinging
    # through zero moves no joint) does not stand in for it.
    rel = quat_multiply(quat_conjugate(quats[:, edges[:, 0]]), quats[:, edges[:, 1]])
    dot = jnp.abs(jnp.sum(rel[1:] * rel[:-1], -1))
    step = jnp.sum(2.0 * jnp.arccos(jnp.clip(dot, 0.0, 1.0)), -1)
    speed = jnp.concatenate([step[:1], step])
    slow = candidate & (speed <= kth_smallest(speed, candidate, (jnp.sum(candidate) - 1) // 5))
    proximal_x = joints[:, jnp.maximum(proximal, 0)]
    toward = _unit(proximal_x - origins[:, jnp.maximum(parent, 0)])
    seen = quat_rotate(quat_conjugate(quats[:, leaves]), toward[:, leaves])  # in each leaf's frame
    typical = _unit(jax.vmap(_geometric_median, (1, None))(seen, slow))
    leaf_off = jnp.sum((seen - typical) ** 2, axis=(1, 2))
    score = leaf_off + 1e-3 * (cost - least) / jnp.maximum(candidate_tolerance, 1e-12)
    d = jnp.argmin(jnp.where(slow, score, jnp.inf))

    # Body planes at the default frame.
    x_d = joints[d]
    frontal = vecs[d][:, 0]
    up_in_plane = up - (up @ frontal) * frontal
    transverse = _unit(up_in_plane)
    lateral0 = jnp.cross(transverse, frontal)
    leaf_d = quat_rotate(quats[d], leaf_axes)  # each leaf's own long axis at the default frame
    evidence, found = _front_evidence(
        joints, quats, origins, valid, d, root, frontal, up, scale, proximal, leaf & has_leaf_axis, leaf_d,
        chain_proximal, chain_distal, chain,
    )
    evidence = jnp.concatenate([jnp.stack([frontal @ facing]), evidence])
    found = jnp.concatenate([jnp.stack([jnp.any(facing != 0)]), found])
    cue = jnp.where(jnp.any(found), jnp.argmax(found), found.shape[0])
    # No cue: an arbitrary but order-independent convention (reported, see normalize_arrays).
    fallback = frontal[jnp.argmax(jnp.abs(frontal))]
    chosen = jnp.where(jnp.any(found), evidence[jnp.minimum(cue, found.shape[0] - 1)], fallback)
    sign = jnp.where(chosen < 0, -1.0, 1.0).astype(joints.dtype)
    body = jnp.stack([sign * frontal, sign * lateral0, transverse], axis=1)

    # Limb frames at the default frame.
    proximal_d = x_d[jnp.maximum(proximal, 0)]
    shank_like = proximal_d - origins[d][jnp.maximum(parent, 0)]
    leaf_main = jnp.where(has_leaf_axis[:, None], leaf_d, shank_like)
    main_d = jnp.where(leaf[:, None], leaf_main, main_weights @ x_d)
    frames_d, main_axis, main_sign = jax.vmap(_limb_frame, in_axes=(0, None))(main_d, body)
    is_root = jnp.arange(frames_d.shape[0]) == root
    frames_d = jnp.where(is_root[:, None, None], body, frames_d)

    local = jnp.einsum("sji,sjk->sik", quat_to_matrix(quats[d]), frames_d)
    limb = quat_multiply(quats, matrix_to_quat(local)[None])
    frames = quat_to_matrix(limb)

    # Constant offsets, averaged over the valid frames: joint j in the parent and in
    # the child limb frame, and each limb origin in its segment frame.
    w = valid.astype(joints.dtype)[:, None, None] / jnp.sum(valid)
    p, c = edges[:, 0], edges[:, 1]

    def in_limb(s, x):
        return jnp.sum(w * quat_rotate(quat_conjugate(limb[:, s]), x - origins[:, s]), axis=0)

    joint_offsets = jnp.stack([in_limb(p, joints), in_limb(c, joints)], axis=1)
    origins_local = jnp.sum(w * quat_rotate(quat_conjugate(quats), origins - translations), axis=0)
    return {
        "cost": cost,
        "candidate": candidate,
        "terms": terms,
        "scale": scale,
        "default_frame": d,
        "body_frame": body,
        "handedness": cue,
        "front_evidence": evidence,
        "up_in_plane": jnp.linalg.norm(up_in_plane),
        "main_length": jnp.linalg.norm(main_d, axis=-1),
        "main_axis": main_axis,
        "main_sign": main_sign,
        "local": local,
        "frames": frames,
        "limb": limb,
        "origins": origins,
        "joint_offsets": joint_offsets,
        "origins_local": origins_local,
    }


# ------------------------------------------------------------------ results
def freeze_fields(obj: Any) -> None:
    """Make a frozen dataclass deeply read-only: arrays unwritable, mappings read-only views."""
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if isinstance(value, np.ndarray):
            value = value.view()  # a view: the flag is ours to set, no copy of the data
            value.setflags(write=False)
            object.__setattr__(obj, field.name, value)
        elif isinstance(value, Mapping):
            object.__setattr__(obj, field.name, types.MappingProxyType(dict(value)))


@dataclasses.dataclass(frozen=True)
class Normalization:
    """Skeleton-aligned limb frames for a whole recording (Sar Dessai et al. 2006, §3).

    Frames are rotation matrices with the axes as columns (x anterior, y left,
    z superior for the body frame); ``x_world = limb_frames[f, s] @ x_limb +
    limb_origins[f, s]``. See :mod:`jaxskel.sd06._normalize` for the maths.

    Attributes
    ----------
    edges, root
        (J, 2) parent -> child segments and the root segment.
    default_frame
        Index of the frame chosen as the default pose.
    cost, cost_terms
        (F,) default-pose cost and (F, 3) its raw terms (plane [m^2], ratio, spread [m]).
    candidates
        (F,) frames within the candidate tolerance of the least cost.
    candidate_tolerance
        That tolerance (cost units).
    weights
        The cost weights used (``plane``, ``ratio``, ``spread``).
    scale
        Metres: the median spread that makes the terms unit-free.
    up
        (3,) the recording's up vector.
    body_frame
        (3, 3) body frame at the default frame (columns: frontal, sagittal and
        transverse plane normals).
    limb_frames, limb_origins
        (F, S, 3, 3) and (F, S, 3): every segment's limb frame in every frame.
    limb_rotations
        (F, S, 4) the same limb frames as quaternions (w, x, y, z).
    limb_frames_local
        (S, 3, 3): each limb frame in its segment's coordinates (constant).
    main_axis, main_sign
        (S,) which limb-frame column is the limb's long axis and its sign: the
        direction from the proximal joint along the limb is
        ``main_sign[s] * limb_frames[f, s][:, main_axis[s]]`` (root: unused).
    joint_offsets
        (J, 2, 3): joint j relative to the parent limb's origin in the parent
        limb frame, and relative to the child limb's origin in the child limb
        frame (means over frames).
    origins_local
        (S, 3) each limb origin in its segment's coordinates, or None when the
        segment translations were not given.
    calibration
        (F,) the frames the default pose was searched in (all, unless a
        calibration window was given).
    handedness
        The body cue that fixed front/back and so left/right (:data:`HANDEDNESS_CUES`):
        "facing" (given), "feet", "knees", "walking" or "none" (a convention).
    front_evidence
        (4,) each cue's signed evidence that the body frame's unsigned frontal
        normal points anterior: facing cosine, feet (sum of cosines), knees
        (summed mean bulge in body scales), walking (distance in body scales).
    leaf_axes
        (S, 3) the leaves' own long axes in segment coordinates (zero rows: none).
    leaf_lengths
        (S,) metres from each leaf's proximal joint to its farthest marker (0: unknown,
        or not a leaf), or None; it tells a limb's hinge (:mod:`jaxskel.sd06._anatomy`).
    """

    edges: np.ndarray
    root: int
    default_frame: int
    cost: np.ndarray
    candidates: np.ndarray
    candidate_tolerance: float
    cost_terms: np.ndarray
    weights: Mapping[str, float]
    scale: float
    up: np.ndarray
    body_frame: np.ndarray
    limb_frames: np.ndarray
    limb_rotations: np.ndarray
    limb_origins: np.ndarray
    limb_frames_local: np.ndarray
    main_axis: np.ndarray
    main_sign: np.ndarray
    joint_offsets: np.ndarray
    origins_local: np.ndarray | None = None
    calibration: np.ndarray | None = None
    handedness: str = "none"
    front_evidence: np.ndarray | None = None
    leaf_axes: np.ndarray | None = None
    leaf_lengths: np.ndarray | None = None

    def __post_init__(self) -> None:
        freeze_fields(self)

    @property
    def n_frames(self) -> int:
        return int(self.limb_frames.shape[0])

    @property
    def n_segments(self) -> int:
        return int(self.limb_frames.shape[1])

    @property
    def n_joints(self) -> int:
        return int(self.edges.shape[0])

    @property
    def body_frames(self) -> np.ndarray:
        """(F, 3, 3) the body (root limb) frame in every frame."""
        return self.limb_frames[:, self.root]

    @property
    def main_directions(self) -> np.ndarray:
        """(F, S, 3) unit long axis of every limb, pointing away from its proximal joint."""
        cols = np.take_along_axis(self.limb_frames, self.main_axis[None, :, None, None], axis=3)[..., 0]
        return cols * self.main_sign[None, :, None]

    def __repr__(self) -> str:
        return (
            f"Normalization({self.n_frames} frames, {self.n_segments} limbs, "
            f"default frame {self.default_frame})"
        )


def _weights(weights: Mapping[str, float] | None) -> dict[str, float]:
    out = dict(DEFAULT_POSE_WEIGHTS)
    if weights is not None:
        unknown = set(weights) - set(out)
        if unknown:
            raise InputError(f"unknown default-pose weight(s) {sorted(unknown)}; use {sorted(out)}")
        out.update({k: float(v) for k, v in weights.items()})
    if any(not np.isfinite(v) or v < 0 for v in out.values()) or sum(out.values()) == 0:
        raise InputError(f"default-pose weights must be finite, >= 0 and not all zero, got {out}")
    return out


@float64_scope
def normalize_arrays(
    joint_positions: Float[Any, "F J 3"],
    edges: Int[Any, "J 2"],
    rotations: Float[Any, "F S 4"],
    *,
    root: int = 0,
    up_axis: Any = "z",
    weights: Mapping[str, float] | None = None,
    facing: Any = None,
    segment_translations: Float[Any, "F S 3"] | None = None,
    candidate_tolerance: float = 0.02,
    calibration: Any = None,
    rate: float | None = None,
    leaf_axes: Float[Any, "S 3"] | None = None,
    leaf_lengths: Float[Any, " S"] | None = None,
) -> Normalization:
    """Normalisation from arrays: joint centres, parent->child edges, global segment quaternions.

    Parameters
    ----------
    joint_positions
        (F, J, 3) joint centres in metres; row j belongs to ``edges[j]``.
    edges
        (J, 2) parent -> child segment indices of a rooted tree.
    rotations
        (F, S, 4) global segment orientations, unit quaternions (w, x, y, z).
    root
        Root segment (receives the body frame).
    up_axis
        The recording's vertical: "x", "y", "z", "-x", "-y", "-z" or a 3-vector.
    weights
        Default-pose cost weights, keys ``plane``, ``ratio``, ``spread`` (missing keys
        keep :data:`DEFAULT_POSE_WEIGHTS`).
    facing
        Optional world direction the subject faces in the default pose (axis name
        or 3-vector); by default the front/back sign comes from the body itself
        (feet, knees, walking direction: the module docstring), never from the joint order.
    segment_translations
        Optional (F, S, 3) segment origins; with them the result also knows each
        limb origin in segment coordinates (for marker reconstruction).
    candidate_tolerance
        Frames whose cost exceeds the least cost by at most this much are
        default-pose candidates (see the module docstring); 0 keeps the least-cost frame.
    calibration
        Frames the default pose is searched in: None (all), a ``slice`` or
        ``(start, stop)`` of frames, ``(t0, t1)`` seconds (floats, with ``rate``)
        or a boolean mask (F,). Limb frames are still given for every frame.
    rate
        Frames per second (only needed for a calibration window in seconds).
    leaf_axes
        Optional (S, 3): each leaf segment's own long axis in its segment
        coordinates (e.g. heel -> toe, :func:`leaf_axes_from_markers`); zero rows
        (and every leaf when None) take the direction of the parent limb.
    leaf_lengths
        Optional (S,) metres: each leaf's length (:func:`leaf_lengths_from_markers`),
        kept in the result for :func:`jaxskel.sd06._anatomy.limb_hinges`.

    Warns
    -----
    DegenerateMotionWarning
        When no body cue tells front from back (module docstring): the sign is
        then a convention (``handedness`` "none"); pass ``facing``.
    """
    x = np.asarray(joint_positions)
    q = np.asarray(rotations)
    tree = tree_arrays(edges, root)
    n_joints = tree.order.size
    if x.ndim != 3 or x.shape[1:] != (n_joints, 3):
        raise InputError(f"joint_positions must be (F, {n_joints}, 3) for {n_joints} joints, got {x.shape}")
    if q.shape != (x.shape[0], n_joints + 1, 4):
        raise InputError(
            f"rotations must be (F, S, 4) = ({x.shape[0]}, {n_joints + 1}, 4) quaternions, got {q.shape}"
        )
    if n_joints < 3:
        raise InputError(
            f"the body planes need at least 3 joints; this skeleton has {n_joints}. Sar Dessai et al.'s "
            "normalisation needs a body (a trunk with limbs): fit a recording in which more segments move, or "
            "leave the parameterisation out"
        )
    if x.shape[0] < 1:
        raise InputError("the motion has no frames")
    for name, arr in (("joint_positions", x), ("rotations", q)):
        bad = ~np.all(np.isfinite(arr.reshape(arr.shape[0], -1)), axis=1)
        if bad.any():
            raise InputError(
                f"{name} is not finite in {bad.sum()} frame(s) (first: {np.flatnonzero(bad)[:5].tolist()}); "
                "normalise a complete motion (inverse_kinematics fills gaps)"
            )
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    dtype = x.dtype
    w = _weights(weights)
    if not 0.0 <= float(candidate_tolerance) < np.inf:
        raise InputError(f"candidate_tolerance must be a finite cost difference >= 0, got {candidate_tolerance}")
    up = up_vector(up_axis)
    face = np.zeros(3) if facing is None else up_vector(facing)

    edges_np = np.asarray(edges, dtype=int)
    n_frames = x.shape[0]
    if segment_translations is None:
        t = np.zeros((n_frames, n_joints + 1, 3), dtype)
    else:
        t = np.asarray(segment_translations, dtype=dtype)
        if t.shape != (n_frames, n_joints + 1, 3) or not np.all(np.isfinite(t)):
            raise InputError(
                f"segment_translations must be finite, shape {(n_frames, n_joints + 1, 3)}, got {t.shape}"
            )
    size = bucket_size(n_frames, steps_per_octave=FRAME_BUCKETS_PER_OCTAVE)
    search = calibration_mask(calibration, n_frames, rate)
    search = np.ones(n_frames, bool) if search is None else search

    def pad(a):
        return np.concatenate([a, np.repeat(a[-1:], size - n_frames, axis=0)]).astype(dtype)

    parent = np.full(n_joints + 1, -1)
    parent[edges_np[:, 1]] = edges_np[:, 0]
    if leaf_axes is None:
        own = np.zeros((n_joints + 1, 3))
    else:
        own = np.asarray(leaf_axes, dtype=float)
        if own.shape != (n_joints + 1, 3) or not np.all(np.isfinite(own)):
            raise InputError(f"leaf_axes must be finite, shape ({n_joints + 1}, 3) (one row per segment), got {own.shape}")
    lengths = None if leaf_lengths is None else np.asarray(leaf_lengths, dtype=float)
    if lengths is not None and (lengths.shape != (n_joints + 1,) or not np.all(np.isfinite(lengths) & (lengths >= 0))):
        raise InputError(
            f"leaf_lengths must be finite metres >= 0, one per segment: shape ({n_joints + 1},), got shape "
            f"{lengths.shape} with {int(np.sum(~(np.isfinite(lengths) & (lengths >= 0))))} bad value(s)"
        )
    own_norm = np.linalg.norm(own, axis=1)
    has_own = (own_norm > 1e-9) & tree.leaf
    own = np.where(has_own[:, None], own / np.maximum(own_norm, 1e-12)[:, None], 0.0)
    out = _program_cache.call(
        _normalize_core,
        to_device(pad(x)),
        to_device(pad(q)),
        to_device(pad(t)),
        to_device(np.arange(size) < n_frames),
        to_device(edges_np),
        to_device(tree.origin_weights, dtype),
        to_device(tree.main_weights, dtype),
        to_device(tree.proximal),
        to_device(parent),
        to_device(tree.leaf),
        to_device(np.flatnonzero(tree.leaf)),
        to_device(root),
        to_device(up, dtype),
        to_device(face, dtype),
        to_device([w["plane"], w["ratio"], w["spread"]], dtype),
        to_device(candidate_tolerance, dtype),
        to_device(np.concatenate([search, np.zeros(size - n_frames, bool)])),
        to_device(own, dtype),
        to_device(has_own),
        to_device(tree.chain_proximal),
        to_device(tree.chain_distal, dtype),
        to_device(tree.chain),
    )
    out = {k: np.asarray(v) for k, v in out.items()}
    d = int(out["default_frame"])
    handedness = HANDEDNESS_CUES[int(out["handedness"])]
    if handedness == "none":
        warnings.warn(
            "front and back (and so left and right) could not be told from the body: no foot points "
            "forward, no knee bends and the subject does not walk; the body frame's front is a "
            "convention. Pass facing= (the direction the subject faces) to fix it.",
            DegenerateMotionWarning,
            stacklevel=3,
        )
    if out["up_in_plane"] < 0.1:
        raise DegenerateMotionError(
            f"in the default-pose frame {d} the best-fit body plane is (nearly) horizontal, so the "
            f"up axis {up.tolist()} cannot orient the transverse plane; check up_axis, or pass "
            "weights that favour an upright frame"
        )
    short = np.flatnonzero((out["main_length"] < 1e-6) & (np.arange(n_joints + 1) != root))
    if short.size:
        raise DegenerateMotionError(
            f"segment(s) {short.tolist()} have no length in the default-pose frame {d} (their joints "
            "coincide), so their long axis is undefined; check the joint positions"
        )
    return Normalization(
        edges=edges_np,
        root=int(root),
        default_frame=d,
        cost=out["cost"][:n_frames],
        candidates=out["candidate"][:n_frames],
        candidate_tolerance=float(candidate_tolerance),
        cost_terms=out["terms"][:n_frames],
        weights=w,
        scale=float(out["scale"]),
        up=up,
        body_frame=out["body_frame"],
        limb_frames=out["frames"][:n_frames],
        limb_rotations=out["limb"][:n_frames],
        limb_origins=out["origins"][:n_frames],
        limb_frames_local=out["local"],
        main_axis=out["main_axis"].astype(int),
        main_sign=out["main_sign"],
        joint_offsets=out["joint_offsets"],
        origins_local=None if segment_translations is None else out["origins_local"],
        calibration=search,
        handedness=handedness,
        front_evidence=out["front_evidence"],
        leaf_axes=own,
        leaf_lengths=lengths,
    )


@float64_scope
def normalize(
    skeleton: Any,
    motion: Any,
    *,
    up_axis: Any = "z",
    weights: Mapping[str, float] | None = None,
    facing: Any = None,
    candidate_tolerance: float = 0.02,
    calibration: Any = None,
) -> Normalization:
    """Skeleton-aligned limb frames for a fitted motion (Sar Dessai et al. 2006, §3).

    ``skeleton`` needs ``.edges`` (J, 2) and ``.root`` (with ``.marker_segment``
    and ``.marker_offsets`` the leaves get their own long axes,
    :func:`leaf_axes_from_markers`); ``motion`` needs
    ``.joint_positions`` (F, J, 3), ``.rotations`` (F, S, 4) and, optionally,
    ``.segment_translations`` (F, S, 3). ``up_axis`` is the recording's vertical
    (``Trial.up_axis``); see :func:`normalize_arrays` for the other options
    (``motion.rate`` serves a calibration window in seconds).
    """
    for obj, names in ((skeleton, ("edges", "root")), (motion, ("joint_positions", "rotations"))):
        missing = [n for n in names if getattr(obj, n, None) is None]
        if missing:
            raise InputError(
                f"{type(obj).__name__} has no {', '.join(missing)}; pass the Skeleton and Motion "
                "from fit_rigid / inverse_kinematics (or use normalize_arrays)"
            )
    if isinstance(up_axis, str) and up_axis == "unknown":
        raise InputError(
            "the recording's up axis is unknown; pass up_axis='z' (or the axis that points up) "
            "so the transverse plane can be oriented"
        )
    return normalize_arrays(
        motion.joint_positions,
        skeleton.edges,
        motion.rotations,
        root=int(skeleton.root),
        up_axis=up_axis,
        weights=weights,
        facing=facing,
        segment_translations=getattr(motion, "segment_translations", None),
        candidate_tolerance=candidate_tolerance,
        calibration=calibration,
        rate=getattr(motion, "rate", None),
        leaf_axes=skeleton_leaf_axes(skeleton),
        leaf_lengths=skeleton_leaf_lengths(skeleton),
    )


def _skeleton_markers(skeleton: Any) -> tuple | None:
    """``(edges, root, marker_segment, marker_offsets, joint_offsets)`` of a skeleton that has markers, else None."""
    seg = getattr(skeleton, "marker_segment", None)
    off = getattr(skeleton, "marker_offsets", None)
    if seg is None or off is None:
        return None
    return skeleton.edges, int(skeleton.root), seg, off, getattr(skeleton, "joint_offsets", None)


def skeleton_leaf_lengths(skeleton: Any) -> np.ndarray | None:
    """:func:`leaf_lengths_from_markers` of a skeleton with ``marker_segment`` and ``marker_offsets``, else None."""
    markers = _skeleton_markers(skeleton)
    return None if markers is None else leaf_lengths_from_markers(*markers)


def skeleton_leaf_axes(skeleton: Any) -> np.ndarray | None:
    """:func:`leaf_axes_from_markers` of a skeleton with ``marker_segment`` and ``marker_offsets``, else None."""
    markers = _skeleton_markers(skeleton)
    return None if markers is None else leaf_axes_from_markers(*markers)


def write_normalized(group: Any, normalization: Normalization) -> None:
    """Write a :class:`Normalization` into an h5py group (the result file's ``/normalized``).

    Datasets: ``default_frame`` (), ``cost`` (F,), ``candidates`` (F,), ``cost_terms`` (F, 3)
    [plane m^2, ratio, spread m], ``body_frame`` (3, 3), ``up`` (3,),
    ``limb_frames`` (F, S, 3, 3) (columns are the axes), ``limb_origins`` (F, S, 3),
    ``limb_frames_local`` (S, 3, 3), ``main_axis`` (S,), ``main_sign`` (S,),
    ``joint_offsets`` (J, 2, 3) and, when known, ``origins_local`` (S, 3) and ``leaf_lengths`` (S,).
    Attributes: the cost ``weights`` and ``scale``, ``candidate_tolerance``, ``root``, ``convention``.
    """
    from ..io import put as _put

    n = normalization
    _put(group, "default_frame", np.int64(n.default_frame))
    for name in (
        "cost",
        "candidates",
        "cost_terms",
        "body_frame",
        "up",
        "limb_frames",
        "limb_origins",
        "limb_frames_local",
        "main_axis",
        "main_sign",
        "joint_offsets",
    ):
        _put(group, name, np.asarray(getattr(n, name)))
    if n.origins_local is not None:
        _put(group, "origins_local", n.origins_local)
    if n.leaf_lengths is not None:
        _put(group, "leaf_lengths", n.leaf_lengths)
    for key, value in n.weights.items():
        group.attrs[f"weight_{key}"] = float(value)
    group.attrs["scale"] = n.scale
    group.attrs["candidate_tolerance"] = n.candidate_tolerance
    group.attrs["root"] = n.root
    group.attrs["handedness"] = n.handedness
    group.attrs["convention"] = (
        "frames are rotation matrices with the axes as columns; x_world = limb_frames @ x_limb "
        "+ limb_origins; body frame columns: frontal (anterior), sagittal (left), transverse (up)"
    )
