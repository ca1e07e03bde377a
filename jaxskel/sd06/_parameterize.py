"""Motion parameterisation: joint axes, rest position, angles and twist (Sar Dessai et al. 2006, §4).

Samples. For joint j (parent limb p, child limb c) the relative limb rotation is
``Q_j(f) = L_p(f)^T L_c(f)`` (normalised limb frames, :mod:`jaxskel.sd06._normalize`)
and the sample is the child's unit long axis in the parent joint frame,
``p_j(f) = Q_j(f) m_c`` (``m_c`` = ``main_sign * e_main`` of the child): a point on
the unit joint sphere.

Filtering and axes: :mod:`jaxskel.sd06._axes` (movement samples, direction joining /
PCA / EM, rest direction ``r``, rest frame and ``Q_rest = Q_j(rest frame)``). A joint
has one axis when the rotations of its movement frames relative to a reference
frame all turn about one fixed axis (RMS deviation below ``hinge_tolerance``),
else two; ``n_axes`` overrides this per joint.

Angles. One axis ``A``: ``alpha`` is the signed angle from ``r`` to ``p`` about
``A`` (both projected on the plane orthogonal to ``A``). Two axes, ``p = R_B(beta)
R_A(alpha) r``: the circle reachable from ``r`` about ``A`` (plane ``A.x = A.r``) and
the circle reaching ``p`` about ``B`` (plane ``B.x = B.p``) meet on the line of the two
planes; its intersections with the sphere are the candidates for the intermediate
``x``, and the one closer to the previous frame's keeps the trajectory smooth (a
scan over frames, starting from ``x = r``). Then ``alpha`` takes ``r`` to ``x`` about
``A`` and ``beta`` takes ``x`` to ``p`` about ``B``. Which extracted axis acts first is
decided per joint from the data: ``A`` moves with the child and ``B`` stays in the
parent, so ``B . (Q Q_rest^T A)`` keeps the value ``A . B``; the order in which this
varies less over the movement frames is kept (for a universal joint the right
order then needs no twist).

Twist, in closed form (the paper sampled it). With the swing ``S = R_B(beta)
R_A(alpha)`` and ``d = S r``, the twist ``tau`` minimising ``|R_d(tau) S Q_rest - Q|_F``
is the rotation about ``d`` closest to ``M = Q (S Q_rest)^T``: for unit quaternions
``tr(A^T B) = 4 (a . b)^2 - 1``, so with ``M``'s quaternion ``(w, v)`` (``w >= 0``)
``tau = 2 atan2(v . d, w)``. When the swing reaches the sample, ``M`` turns about
``d`` only and this is exact.

Inverse (pose editing): ``Q_j = S R_r(tau) Q_rest`` (= ``R_d(tau) S Q_rest``), composed
down the tree from the root's limb frame, ``L_c = L_p Q_j``, with joints and
origins placed by the normalisation's constant ``joint_offsets``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._errors import ConvergenceWarning, DegenerateMotionWarning, InputError
from .._math.padding import bucket_size
from .._math.rotation import (
    axis_angle_to_quat,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_axis_angle,
    quat_to_matrix,
    quat_twist_angle,
)
from .._runtime.precision import float64_scope
from . import _axes
from ._normalize import (
    Normalization,
    freeze_fields,
    normalize,
    normalize_arrays,
    tree_arrays,
)

__all__ = [
    "METHODS",
    "Parameterization",
    "Pose",
    "parameterize",
    "parameterize_arrays",
    "parameterize_normalized",
    "pose_from_angles",
    "swing_twist_angles",
    "write_parameters",
]

#: Axis-extraction methods: the paper's direction joining and its two baselines.
METHODS = ("joining", "pca", "em")


def _unit(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 1e-12, n, 1.0)


def _angle_about(a: Float[Array, "... 3"], u: Float[Array, "... 3"], v: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Signed angle about unit ``a`` from ``u`` to ``v`` (both projected on the plane orthogonal to ``a``)."""
    au = jnp.sum(a * u, -1)
    av = jnp.sum(a * v, -1)
    return jnp.arctan2(jnp.sum(a * jnp.cross(u, v), -1), jnp.sum(u * v, -1) - au * av)


# ------------------------------------------------------------------ angles
def _intermediates(
    p: Float[Array, "F 3"], valid: Bool[Array, " F"], r: Float[Array, " 3"], a: Float[Array, " 3"], b: Float[Array, " 3"]
) -> Float[Array, "F 3"]:
    """The intermediate ``x`` of every frame: circle intersection, smooth choice of the two candidates.

    The candidates are computed for all frames at once; a scan then keeps, frame
    by frame, the one closer to the previous choice (frame 0: closer to ``r``).
    Padded frames keep the previous choice.
    """
    c = a @ b
    h1 = a @ r
    h2 = p @ b
    denom = jnp.maximum(1.0 - c * c, 1e-12)
    x0 = ((h1 - c * h2)[:, None] * a + (h2 - c * h1)[:, None] * b) / denom
    line = _unit(jnp.cross(a, b))
    t = jnp.sqrt(jnp.maximum(1.0 - jnp.sum(x0 * x0, -1), 0.0))[:, None]

    def choose(prev, cand):
        plus, minus, ok = cand
        x = jnp.where(jnp.sum((plus - prev) ** 2) <= jnp.sum((minus - prev) ** 2), plus, minus)
        x = jnp.where(ok, x, prev)
        return x, x

    _, x = jax.lax.scan(choose, r, (x0 + t * line, x0 - t * line, valid))
    return _unit(x)


def swing_twist_angles(
    q: Float[Array, "F 4"],
    p: Float[Array, "F 3"],
    valid: Bool[Array, " F"],
    axes: Float[Array, "2 3"],
    n_axes: Int[Array, ""],
    rest_rotation: Float[Array, " 4"],
    rest_direction: Float[Array, " 3"],
) -> tuple[Float[Array, "F 3"], Float[Array, " F"]]:
    """Angles ``(alpha, beta, tau)`` per frame of one joint and the direction residual (radians).

    ``q`` are the relative limb rotations ``Q_j(f)`` as quaternions, ``p`` the
    samples; ``axes[0]`` acts first (``alpha``), ``axes[1]`` second (``beta``; unused
    with one axis). The twist is the rotation about ``d = S r`` closest to
    ``M = Q (S Q_rest)^T``: with ``M``'s quaternion ``(w, v)``, ``tau = 2 atan2(v . d, w)``
    (for unit quaternions ``tr(A^T B) = 4 (a . b)^2 - 1``, maximised over rotations
    about d). The residual is the angle between the re-posed and the sampled
    direction (0 when the model reaches the sample).
    """
    a, b = axes[0], axes[1]
    x = _intermediates(p, valid, rest_direction, a, b)
    two = (n_axes > 1) & (jnp.linalg.norm(jnp.cross(a, b)) > 1e-6)
    alpha = jnp.where(two, _angle_about(a, rest_direction, x), _angle_about(a, rest_direction, p))
    beta = jnp.where(two, _angle_about(b, x, p), 0.0)
    swing = quat_multiply(axis_angle_to_quat(b * beta[..., None]), axis_angle_to_quat(a * alpha[..., None]))
    d = quat_rotate(swing, rest_direction)
    tau = quat_twist_angle(quat_multiply(q, quat_conjugate(quat_multiply(swing, rest_rotation))), d)
    residual = jnp.arccos(jnp.clip(jnp.sum(d * p, -1), -1.0, 1.0))
    return jnp.stack([alpha, beta, tau], -1), jnp.where(valid, residual, 0.0)


def _joint_rotations(
    angles: Float[Array, "F J 3"],
    axes: Float[Array, "J 2 3"],
    rest_direction: Float[Array, "J 3"],
    rest_rotation: Float[Array, "J 4"],
) -> Float[Array, "F J 4"]:
    """``Q_j = R_B(beta) R_A(alpha) R_r(tau) Q_rest`` (quaternions) for every frame and joint."""
    swing = quat_multiply(
        axis_angle_to_quat(axes[None, :, 1] * angles[..., 1, None]),
        axis_angle_to_quat(axes[None, :, 0] * angles[..., 0, None]),
    )
    twist = axis_angle_to_quat(rest_direction[None] * angles[..., 2, None])
    return quat_multiply(quat_multiply(swing, twist), rest_rotation[None])


@jax.jit
def pose_from_angles(
    angles: Float[Array, "F J 3"],
    axes: Float[Array, "J 2 3"],
    rest_direction: Float[Array, "J 3"],
    rest_rotation: Float[Array, "J 4"],
    root_rotation: Float[Array, "F 4"],
    root_origin: Float[Array, "F 3"],
    joint_offsets: Float[Array, "J 2 3"],
    tree: Int[Array, "J 3"],
    root: Int[Array, ""],
) -> tuple[Float[Array, "F S 4"], Float[Array, "F S 3"], Float[Array, "F J 3"]]:
    """Forward kinematics of the parameterisation: limb rotations (quaternions), limb origins, joint centres.

    ``tree`` rows are ``(joint, parent, child)`` in topological order. For each
    joint ``x_j = o_p + L_p u_j``, ``L_c = L_p Q_j``, ``o_c = x_j - L_c w_j`` with
    ``(u_j, w_j) = joint_offsets[j]``; a ``fori_loop`` walks the tree (one compiled
    body for any skeleton size), every step vectorised over frames.
    """
    n_frames, n_joints = angles.shape[:2]
    q = _joint_rotations(angles, axes, rest_direction, rest_rotation)
    rotation = jnp.zeros((n_joints + 1, n_frames, 4), angles.dtype).at[root].set(root_rotation)
    origin = jnp.zeros((n_joints + 1, n_frames, 3), angles.dtype).at[root].set(root_origin)
    joints = jnp.zeros((n_joints, n_frames, 3), angles.dtype)

    def place(i, state):
        rotation, origin, joints = state
        j, parent, child = tree[i, 0], tree[i, 1], tree[i, 2]
        x = origin[parent] + quat_rotate(rotation[parent], joint_offsets[j, 0])
        r_child = quat_multiply(rotation[parent], q[:, j])
        o_child = x - quat_rotate(r_child, joint_offsets[j, 1])
        return rotation.at[child].set(r_child), origin.at[child].set(o_child), joints.at[j].set(x)

    rotation, origin, joints = jax.lax.fori_loop(0, n_joints, place, (rotation, origin, joints))
    return jnp.swapaxes(rotation, 0, 1), jnp.swapaxes(origin, 0, 1), jnp.swapaxes(joints, 0, 1)


@jax.jit
def _segment_poses(
    limb: Float[Array, "F S 4"],
    origins: Float[Array, "F S 3"],
    limb_frames_local: Float[Array, "S 3 3"],
    origins_local: Float[Array, "S 3"],
) -> tuple[Float[Array, "F S 3 3"], Float[Array, "F S 4"], Float[Array, "F S 3"]]:
    """Limb frames as matrices, segment orientations ``R_s = L_s L_loc^T`` and translations ``o_s - R_s c_s``."""
    segment = quat_multiply(limb, quat_conjugate(matrix_to_quat(limb_frames_local))[None])
    return quat_to_matrix(limb), segment, origins - quat_rotate(segment, origins_local[None])


# ------------------------------------------------------------------ core
def _one_axis_rms(
    q: Float[Array, "F 4"], p: Float[Array, "F 3"], movement: Bool[Array, " F"], centroid: Float[Array, " 3"]
) -> Float[Array, ""]:
    """How far (RMS angle) the movement frames' rotations leave a single fixed axis.

    About one axis ``A``, ``Q(f) Q(g)^T = R_A(theta_f - theta_g)`` for every pair
    of frames, so the rotation vectors ``w_f = log(Q(f) Q(ref)^T)`` lie on one line.
    The test uses whole limb rotations, not directions alone: a limb that is not
    orthogonal to its axis moves on a small circle, and a small circle can pass
    close to two short perpendicular arcs (two axes exercised one way each).
    """
    ref = jnp.argmin(jnp.where(movement, jnp.sum((p - centroid) ** 2, -1), jnp.inf))
    rotvec = quat_to_axis_angle(quat_multiply(q, quat_conjugate(q[ref])))
    w = movement.astype(p.dtype)
    _, vecs = jnp.linalg.eigh(jnp.einsum("f,fi,fj->ij", w, rotvec, rotvec))
    along = rotvec @ vecs[:, 2]
    off = jnp.maximum(jnp.sum(rotvec**2, -1) - along**2, 0.0)  # rounding can dip below 0
    return jnp.sqrt(jnp.sum(w * off) / jnp.maximum(jnp.sum(w), 1.0))


# Three jitted stages, joint-major inside (vmapped over joints); only the middle
# one depends on the axis-extraction method, so trying another method recompiles
# only that stage.
@functools.partial(jax.jit, static_argnames=("n_bins", "min_prominence", "low_speed_fraction", "hinge_tolerance"))
def _filter_stage(
    limb: Float[Array, "F S 4"],
    edges: Int[Array, "J 2"],
    main: Float[Array, "S 3"],
    n_axes_given: Int[Array, " J"],
    valid: Bool[Array, " F"],
    *,
    n_bins: int,
    min_prominence: float,
    low_speed_fraction: float,
    hinge_tolerance: float,
) -> dict[str, Array]:
    """Relative rotations, samples, movement filter (§4.1) and the number of axes per joint."""
    q = jnp.swapaxes(quat_multiply(quat_conjugate(limb[:, edges[:, 0]]), limb[:, edges[:, 1]]), 0, 1)

    def one(q, main, given):
        p = quat_rotate(q, main)
        speed, defined = _axes.speeds(p, valid)
        threshold, counts, top = _axes.speed_threshold(speed, defined, n_bins, min_prominence, low_speed_fraction)
        movement = defined & (speed > threshold)
        weight = valid.astype(p.dtype)
        centroid = jnp.sum(weight[:, None] * p, 0) / jnp.maximum(jnp.sum(weight), 1.0)
        hinge_rms = _one_axis_rms(q, p, movement, centroid)
        n_axes = jnp.where(given > 0, given, jnp.where(hinge_rms > hinge_tolerance, 2, 1))
        return {
            "q": q,
            "samples": p,
            "speed": speed,
            "threshold": threshold,
            "histogram": counts,
            "top_speed": top,
            "movement": movement,
            "centroid": centroid,
            "hinge_rms": hinge_rms,
            "n_axes": n_axes,
        }

    return jax.vmap(one)(q, main[edges[:, 1]], n_axes_given)


@functools.partial(jax.jit, static_argnames=("method", "cell", "delta", "max_groups", "max_em_steps"))
def _axes_stage(
    samples: Float[Array, "J F 3"],
    movement: Bool[Array, "J F"],
    n_axes: Int[Array, " J"],
    *,
    method: str,
    cell: float,
    delta: float,
    max_groups: int,
    max_em_steps: int,
) -> dict[str, Array]:
    """Two axis planes ``n . p = h`` per joint (§4.2; the baselines' planes pass through the joint centre)."""

    def one(p, movement, n_axes):
        offsets = jnp.zeros(2, p.dtype)
        if method == "joining":
            axes, offsets, steps = _axes.join_directions(
                p, movement, n_axes, cell=cell, delta=delta, max_groups=max_groups
            )
            converged = jnp.asarray(True)
        elif method == "pca":
            axes = _axes.pca_axes(p, movement, cell=cell)
            steps, converged = jnp.asarray(0), jnp.asarray(True)
        else:
            axes, steps, converged = _axes.em_axes(p, movement, n_axes, cell=cell, max_steps=max_em_steps)
        axes, offsets = _axes.orient_axes(axes, offsets)
        return {"axes": axes, "offsets": offsets, "steps": steps, "converged": converged}

    return jax.vmap(one)(samples, movement, n_axes)


@jax.jit
def _angles_stage(
    q: Float[Array, "J F 4"],
    samples: Float[Array, "J F 3"],
    movement: Bool[Array, "J F"],
    valid: Bool[Array, " F"],
    centroid: Float[Array, "J 3"],
    n_axes: Int[Array, " J"],
    axes: Float[Array, "J 2 3"],
    offsets: Float[Array, "J 2"],
) -> dict[str, Array]:
    """Rest position (§4.3), axis order, angles and twist (§4.4-4.5), fit diagnostics."""

    def one(q, p, movement, centroid, n_axes, axes, offsets):
        moving = movement.astype(p.dtype)
        axes = axes.at[1].set(jnp.where(n_axes > 1, axes[1], 0.0))
        target = _axes.rest_target(axes, n_axes, centroid)
        rest_frame = jnp.argmin(jnp.where(valid, jnp.sum((p - target) ** 2, -1), jnp.inf))
        rest_direction = p[rest_frame]
        rest_rotation = q[rest_frame]

        # Which axis acts first: it moves with the child while the second stays in the
        # parent, so B . (Q Q_rest^T A) stays A . B; keep the order where it varies less.
        carried = quat_rotate(quat_multiply(q, quat_conjugate(rest_rotation))[:, None], axes[None])  # (F, 2, 3)
        invariant = jnp.stack([carried[:, 0] @ axes[1], carried[:, 1] @ axes[0]], axis=1)
        mean = jnp.sum(moving[:, None] * invariant, 0) / jnp.maximum(jnp.sum(moving), 1.0)
        spread = jnp.sum(moving[:, None] * (invariant - mean) ** 2, 0)
        swap = (n_axes > 1) & (spread[1] < spread[0])
        axes = jnp.where(swap, axes[::-1], axes)
        offsets = jnp.where(swap, offsets[::-1], offsets)
        angles, residual = swing_twist_angles(q, p, valid, axes, n_axes, rest_rotation, rest_direction)

        off = jax.vmap(_axes.circle_distance, in_axes=(None, 0, 0), out_axes=1)(p, axes, offsets)
        off = jnp.where(n_axes > 1, jnp.min(off, axis=1), off[:, 0])
        axis_rms = jnp.sqrt(jnp.sum(moving * off**2) / jnp.maximum(jnp.sum(moving), 1.0))
        extent = jnp.max(jnp.where(valid, jnp.arccos(jnp.clip(p @ _unit(centroid), -1.0, 1.0)), 0.0))
        return {
            "axes": axes,
            "rest_frame": rest_frame,
            "rest_direction": rest_direction,
            "rest_rotation": rest_rotation,
            "angles": angles,
            "residual": residual,
            "axis_rms": axis_rms,
            "extent": extent,
        }

    return jax.vmap(one)(q, samples, movement, centroid, n_axes, axes, offsets)


# ------------------------------------------------------------------ results
@dataclasses.dataclass(frozen=True)
class Pose:
    """A skeleton pose per frame from joint angles (:meth:`Parameterization.pose`).

    Attributes
    ----------
    joint_positions
        (F, J, 3) joint centres, metres.
    limb_frames, limb_origins
        (F, S, 3, 3) normalised limb frames (axes as columns) and (F, S, 3) origins.
    rotations
        (F, S, 4) global segment orientations, quaternions (w, x, y, z), in the
        convention of the input motion.
    segment_translations
        (F, S, 3) segment origins (with the input motion's segment frames), or None
        when the normalisation was made without segment translations. Markers are
        then ``quat_rotate(rotations[:, seg], marker_offsets) + segment_translations[:, seg]``.
    """

    joint_positions: np.ndarray
    limb_frames: np.ndarray
    limb_origins: np.ndarray
    rotations: np.ndarray
    segment_translations: np.ndarray | None

    def __post_init__(self) -> None:
        freeze_fields(self)


@dataclasses.dataclass(frozen=True)
class Parameterization:
    """Joint axes, rest positions and per-frame angles (Sar Dessai et al. 2006, §4).

    Joint-frame quantities are in the parent limb's normalised frame. See
    :mod:`jaxskel.sd06._parameterize` for the maths.

    Attributes
    ----------
    method
        Axis extraction used: "joining", "pca" or "em".
    n_axes
        (J,) 1 or 2 movement axes per joint.
    axes
        (J, 2, 3) unit axes in the parent joint frame; ``axes[j, 0]`` acts first
        (angle 0), ``axes[j, 1]`` second (angle 1; zero vector for one-axis joints).
    rest_direction, rest_frame, rest_rotation
        (J, 3) rest direction of each child limb, (J,) the frame it was taken from,
        (J, 4) the child limb frame relative to the parent's there (quaternion w, x, y, z).
    angles
        (F, J, 3) radians: the angles about ``axes[j, 0]``, ``axes[j, 1]`` (0 for
        one-axis joints) and the twist about the limb's long axis.
    samples
        (F, J, 3) the child limb's unit direction in the parent joint frame.
    speed, speed_threshold, movement
        (F, J) sample speed per frame, (J,) the threshold found in the speed
        histogram (``histogram`` (J, n_bins) over ``[0, top_speed]``) and the
        movement mask ``speed > speed_threshold``.
    residual
        (F, J) angle (radians) between the re-posed and the sampled limb direction.
    axis_rms
        (J,) RMS angle of the movement samples from the nearest of their axes' circles.
    hinge_rms
        (J,) RMS angle by which the movement frames' rotations (relative to a
        reference frame) leave one fixed axis: ~0 for a one-axis joint (the
        one-or-two-axes test, threshold ``hinge_tolerance_deg``).
    extent
        (J,) largest angle of any sample from the samples' mean direction.
    exercised
        (J,) False for joints that barely moved (``extent`` below ``min_extent``).
    steps, converged
        (J,) group merges (joining) or EM iterations, and whether EM settled
        (always True for joining and PCA).
    normalization
        The :class:`~jaxskel.sd06.Normalization` the samples were taken in.
    """

    method: str
    n_axes: np.ndarray
    axes: np.ndarray
    rest_direction: np.ndarray
    rest_frame: np.ndarray
    rest_rotation: np.ndarray
    angles: np.ndarray
    samples: np.ndarray
    speed: np.ndarray
    speed_threshold: np.ndarray
    histogram: np.ndarray
    top_speed: np.ndarray
    movement: np.ndarray
    residual: np.ndarray
    axis_rms: np.ndarray
    hinge_rms: np.ndarray
    extent: np.ndarray
    exercised: np.ndarray
    steps: np.ndarray
    converged: np.ndarray
    normalization: Normalization
    settings: Mapping[str, Any]

    def __post_init__(self) -> None:
        freeze_fields(self)

    @property
    def n_frames(self) -> int:
        return int(self.angles.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.angles.shape[1])

    @float64_scope
    def pose(
        self,
        angles: Float[Any, "F J 3"] | None = None,
        *,
        root_frames: Float[Any, "F 3 3"] | None = None,
        root_origins: Float[Any, "F 3"] | None = None,
    ) -> Pose:
        """Skeleton pose from joint angles (the inverse of the parameterisation).

        ``angles`` (F, J, 3) radians, e.g. an edited copy of :attr:`angles`; the
        root limb keeps the recording's frames and origins unless ``root_frames``
        (F, 3, 3) and ``root_origins`` (F, 3) are given. The frame count F may
        differ from the recording's when both root arguments are given.
        """
        norm = self.normalization
        a = self.angles if angles is None else np.asarray(angles, dtype=self.angles.dtype)
        if a.ndim != 3 or a.shape[1:] != self.angles.shape[1:]:
            raise InputError(f"angles must be (F, {self.n_joints}, 3) radians, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError("angles contain NaN or inf; give finite radians for every frame and joint")
        root = norm.root
        frames_r = norm.limb_frames[:, root] if root_frames is None else np.asarray(root_frames, a.dtype)
        if frames_r.shape == (a.shape[0], 3, 3) and not np.allclose(
            np.einsum("fji,fjk->fik", frames_r, frames_r), np.eye(3), atol=1e-6
        ):
            raise InputError("root_frames must be rotation matrices (orthonormal columns)")
        origins_r = norm.limb_origins[:, root] if root_origins is None else np.asarray(root_origins, a.dtype)
        if frames_r.shape != (a.shape[0], 3, 3) or origins_r.shape != (a.shape[0], 3):
            raise InputError(
                f"for {a.shape[0]} frames of angles the root needs frames ({a.shape[0]}, 3, 3) and origins "
                f"({a.shape[0]}, 3), got {frames_r.shape} and {origins_r.shape}; pass root_frames and "
                "root_origins when the frame count changes"
            )
        n = a.shape[0]
        size = bucket_size(n)

        def pad(x):
            return np.concatenate([x, np.repeat(x[-1:], size - n, axis=0)])

        order = tree_arrays(norm.edges, root).order
        tree = np.stack([order, norm.edges[order, 0], norm.edges[order, 1]], axis=1)
        limb, origins, joints = pose_from_angles(
            jnp.asarray(pad(a)),
            jnp.asarray(self.axes),
            jnp.asarray(self.rest_direction),
            jnp.asarray(self.rest_rotation),
            jnp.asarray(pad(norm.limb_rotations[:, root]))
            if root_frames is None
            else matrix_to_quat(jnp.asarray(pad(frames_r))),
            jnp.asarray(pad(origins_r)),
            jnp.asarray(norm.joint_offsets),
            jnp.asarray(tree),
            jnp.asarray(root),
        )
        local = norm.limb_frames_local
        centre = np.zeros((norm.n_segments, 3)) if norm.origins_local is None else norm.origins_local
        frames, segment, translations = (
            np.asarray(v)[:n] for v in _segment_poses(limb, origins, jnp.asarray(local), jnp.asarray(centre))
        )
        return Pose(
            joint_positions=np.asarray(joints)[:n],
            limb_frames=frames,
            limb_origins=np.asarray(origins)[:n],
            rotations=segment,
            segment_translations=None if norm.origins_local is None else translations,
        )

    def __repr__(self) -> str:
        return (
            f"Parameterization({self.method}: {self.n_frames} frames, {self.n_joints} joints, "
            f"axes per joint {self.n_axes.tolist()})"
        )


# ------------------------------------------------------------------ entry points
def _n_axes_array(n_axes: Any, n_joints: int) -> np.ndarray:
    if n_axes is None:
        return np.zeros(n_joints, dtype=int)
    if isinstance(n_axes, Mapping):
        out = np.zeros(n_joints, dtype=int)
        for j, k in n_axes.items():
            if not 0 <= int(j) < n_joints:
                raise InputError(f"n_axes names joint {j}; joints are 0..{n_joints - 1}")
            out[int(j)] = int(k)
    elif np.ndim(n_axes) == 0:
        out = np.full(n_joints, int(n_axes))
    else:
        out = np.asarray(n_axes, dtype=int).reshape(-1)
        if out.size != n_joints:
            raise InputError(f"n_axes has {out.size} entries for {n_joints} joints")
    if not np.all(np.isin(out, (0, 1, 2))):
        raise InputError(f"n_axes must be 1 or 2 per joint (0 or None: decide from the data), got {out.tolist()}")
    return out


def parameterize_normalized(
    normalization: Normalization,
    *,
    method: str = "joining",
    n_axes: int | Sequence[int] | Mapping[int, int] | None = None,
    delta_deg: float = 15.0,
    cell: float = 0.05,
    max_groups: int = 32,
    n_bins: int = 100,
    min_prominence: float = 0.05,
    low_speed_fraction: float = 0.2,
    hinge_tolerance_deg: float = 4.0,
    min_extent_deg: float = 5.0,
    max_em_steps: int = 100,
) -> Parameterization:
    """Parameterise a normalised motion; see :func:`parameterize` for the options."""
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if not 0.0 < delta_deg < 90.0:
        raise InputError(f"delta_deg must be in (0, 90) degrees, got {delta_deg}")
    if not 0.0 < cell < 0.5:
        raise InputError(f"cell is a chord length on the unit joint sphere, in (0, 0.5); got {cell}")
    if int(n_bins) < 4 or int(max_groups) < 2:
        raise InputError(f"n_bins must be >= 4 and max_groups >= 2, got {n_bins} and {max_groups}")
    norm = normalization
    n_frames = norm.n_frames
    if n_frames < 3:
        raise InputError(f"parameterisation needs a motion of several frames, got {n_frames}")
    given = _n_axes_array(n_axes, norm.n_joints)
    max_groups = min(int(max_groups), bucket_size(n_frames))
    size = bucket_size(n_frames)
    limb = np.concatenate([norm.limb_rotations, np.repeat(norm.limb_rotations[-1:], size - n_frames, axis=0)])
    main = np.eye(3, dtype=limb.dtype)[norm.main_axis] * norm.main_sign[:, None]
    valid = jnp.asarray(np.arange(size) < n_frames)
    filter_options = {
        "n_bins": int(n_bins),
        "min_prominence": float(min_prominence),
        "low_speed_fraction": float(low_speed_fraction),
        "hinge_tolerance": math.radians(hinge_tolerance_deg),
    }
    axes_options = {
        "method": method,
        "cell": float(cell),
        "delta": math.radians(delta_deg),
        "max_groups": max_groups,
        "max_em_steps": int(max_em_steps),
    }
    filtered = _filter_stage(
        jnp.asarray(limb), jnp.asarray(norm.edges), jnp.asarray(main), jnp.asarray(given), valid, **filter_options
    )
    extracted = _axes_stage(filtered["samples"], filtered["movement"], filtered["n_axes"], **axes_options)
    posed = _angles_stage(
        filtered["q"],
        filtered["samples"],
        filtered["movement"],
        valid,
        filtered["centroid"],
        filtered["n_axes"],
        extracted["axes"],
        extracted["offsets"],
    )
    out = {k: np.asarray(v) for k, v in {**filtered, **extracted, **posed}.items() if k != "q"}
    # Per-frame outputs are joint-major inside the stages; frames first outside.
    for key in ("samples", "speed", "movement", "angles", "residual"):
        out[key] = np.swapaxes(out[key], 0, 1)[:n_frames]
    if not out["converged"].all():
        warnings.warn(
            f"EM axis extraction stopped after {max_em_steps} steps without settling for joint(s) "
            f"{np.flatnonzero(~out['converged']).tolist()}; raise max_em_steps or use method='joining'",
            ConvergenceWarning,
            stacklevel=4,  # parameterize's caller (3 is float64_scope's wrapper)
        )
    exercised = out["extent"] >= math.radians(min_extent_deg)
    if not exercised.all():
        warnings.warn(
            f"joint(s) {np.flatnonzero(~exercised).tolist()} barely move (largest excursion "
            f"{np.degrees(out['extent'][~exercised]).round(1).tolist()} degrees < {min_extent_deg}); "
            "their axes are not meaningful. Record a calibration phase that moves every joint "
            "through its main movements.",
            DegenerateMotionWarning,
            stacklevel=4,  # parameterize's caller (3 is float64_scope's wrapper)
        )
    return Parameterization(
        method=method,
        n_axes=out["n_axes"].astype(int),
        axes=out["axes"],
        rest_direction=out["rest_direction"],
        rest_frame=out["rest_frame"].astype(int),
        rest_rotation=out["rest_rotation"],
        angles=out["angles"],
        samples=out["samples"],
        speed=out["speed"],
        speed_threshold=out["threshold"],
        histogram=out["histogram"],
        top_speed=out["top_speed"],
        movement=out["movement"],
        residual=out["residual"],
        axis_rms=out["axis_rms"],
        hinge_rms=out["hinge_rms"],
        extent=out["extent"],
        exercised=exercised,
        steps=out["steps"].astype(int),
        converged=out["converged"].astype(bool),
        normalization=norm,
        settings={
            **filter_options,
            **axes_options,
            "n_axes": given.tolist(),
            "min_extent_deg": float(min_extent_deg),
        },
    )


@float64_scope
def parameterize(
    skeleton: Any,
    motion: Any,
    normalization: Normalization | None = None,
    *,
    up_axis: Any = "z",
    method: str = "joining",
    n_axes: int | Sequence[int] | Mapping[int, int] | None = None,
    **options: Any,
) -> Parameterization:
    """Joint axes, rest positions and angles of a fitted motion (Sar Dessai et al. 2006, §4).

    Parameters
    ----------
    skeleton, motion
        Duck-typed: ``skeleton.edges`` (J, 2), ``skeleton.root``; ``motion.joint_positions``
        (F, J, 3), ``motion.rotations`` (F, S, 4) (w, x, y, z), optionally
        ``motion.segment_translations``. The motion should contain a calibration
        phase in which every joint performs its main movements one at a time.
    normalization
        From :func:`~jaxskel.sd06.normalize` (computed with ``up_axis`` when None).
    method
        "joining" (the paper's direction joining), or the baselines "pca" / "em".
    n_axes
        Movement axes per joint: None (decide from the data), 1 or 2 for all, a
        sequence per joint or a mapping joint -> 1/2 (0 = decide).
    **options
        ``delta_deg`` (15, direction similarity), ``cell`` (0.05, stratification
        chord on the unit sphere), ``max_groups`` (32, largest groups clustered), ``n_bins`` (100, speed
        histogram), ``min_prominence`` (0.05 of the tallest bar), ``low_speed_fraction``
        (0.2), ``hinge_tolerance_deg`` (4, one axis when the movement frames' relative
        rotations stay this close to one axis), ``min_extent_deg`` (5, warn below), ``max_em_steps`` (100).
    """
    if normalization is None:
        normalization = normalize(skeleton, motion, up_axis=up_axis)
    elif not isinstance(normalization, Normalization):
        raise InputError(f"normalization must be a jaxskel.sd06.Normalization, got {type(normalization).__name__}")
    return parameterize_normalized(normalization, method=method, n_axes=n_axes, **options)


@float64_scope
def parameterize_arrays(
    joint_positions: Float[Any, "F J 3"],
    edges: Int[Any, "J 2"],
    rotations: Float[Any, "F S 4"],
    *,
    root: int = 0,
    up_axis: Any = "z",
    method: str = "joining",
    n_axes: int | Sequence[int] | Mapping[int, int] | None = None,
    segment_translations: Float[Any, "F S 3"] | None = None,
    **options: Any,
) -> Parameterization:
    """:func:`parameterize` from arrays (normalises first with :func:`~jaxskel.sd06._normalize.normalize_arrays`)."""
    norm = normalize_arrays(
        joint_positions, edges, rotations, root=root, up_axis=up_axis, segment_translations=segment_translations
    )
    return parameterize_normalized(norm, method=method, n_axes=n_axes, **options)


def write_parameters(group: Any, parameterization: Parameterization) -> None:
    """Write a :class:`Parameterization` into an h5py group (the result file's ``/parameters``).

    Datasets (J joints, F frames; joint-frame vectors in the parent limb's
    normalised frame): ``n_axes`` (J,), ``axes`` (J, 2, 3) (row 0 acts first; zero
    row for one-axis joints), ``rest_direction`` (J, 3), ``rest_frame`` (J,),
    ``rest_rotation`` (J, 4) quaternion, ``angles`` (F, J, 3) radians (axis 0, axis 1, twist),
    ``movement`` (F, J) bool, ``speed`` (F, J), ``speed_threshold`` (J,),
    ``residual`` (F, J) radians, ``axis_rms`` (J,), ``exercised`` (J,), ``steps`` (J,),
    ``converged`` (J,). Attributes: ``method`` and the settings.
    """
    from ..io import put as _put

    p = parameterization
    for name in (
        "n_axes",
        "axes",
        "rest_direction",
        "rest_frame",
        "rest_rotation",
        "angles",
        "movement",
        "speed",
        "speed_threshold",
        "residual",
        "axis_rms",
        "exercised",
        "steps",
        "converged",
    ):
        _put(group, name, np.asarray(getattr(p, name)))
    group.attrs["method"] = p.method
    group.attrs["angle_units"] = "rad"
    for key, value in p.settings.items():
        group.attrs[key] = value if not isinstance(value, list) else np.asarray(value)
