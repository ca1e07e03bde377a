"""Motion parameterisation: joint axes, rest position, angles and twist (Sar Dessai et al. 2006, §4).

Samples. For joint j (parent limb p, child limb c) the relative limb rotation is
``Q_j(f) = L_p(f)^T L_c(f)`` (normalised limb frames, :mod:`jaxskel.sd06._normalize`)
and the sample is the child's unit long axis in the parent joint frame,
``p_j(f) = Q_j(f) m_c`` (``m_c`` = ``main_sign * e_main`` of the child): a point on
the unit joint sphere.

Calibration: the default pose, the movement filter, the axes and the axis
count come from the calibration frames only (a given window, a separate
calibration recording, every frame with "all", or by default each joint's
main-movement frames, found automatically: windows where the joint turns about
one fixed axis, on the circle through its default pose, an axis that many
frames share); the angles are computed for every frame.

Filtering and axes: :mod:`jaxskel.sd06._axes` (movement samples, direction joining /
PCA / EM). A joint has one axis when the rotations of its movement frames
relative to a reference frame all turn about one fixed axis, or when the
child's long axis swings about one fixed axis (any other rotation only twists
the limb: a foot whose heel -> toe axis is the ankle's inversion axis): the
off-axis RMS, with the estimated rotation noise removed
(:func:`_rotation_noise`, :func:`_one_axis_rms`, :func:`_one_swing_axis_rms`),
stays below ``hinge_tolerance``; else two. By default (``axis_count="anatomy"``) the
knees and elbows, found from the skeleton's shape (:mod:`jaxskel.sd06._anatomy`),
take one axis instead, as the paper takes the degrees of freedom from the anatomy;
``n_axes`` overrides both per joint.

Rest pose: the normalisation's default-pose frame ``d`` (``r = p_j(d)``,
``Q_rest = Q_j(d)``), so every angle is 0 in the default pose.

Angles. One axis ``A``: ``alpha`` is the signed angle from ``r`` to ``p`` about
``A`` (both projected on the plane orthogonal to ``A``). Two axes, ``p = R_B(beta)
R_A(alpha) r``: the circle reachable from ``r`` about ``A`` (plane ``A.x = A.r``) and
the circle reaching ``p`` about ``B`` (plane ``B.x = B.p``) meet on the line of the two
planes; its two intersections with the sphere give two angle pairs. Walking
from the rest frame forward and backward in time, the pair of least
``|wrap(d alpha)|^2 + |wrap(d beta)|^2 + w (alpha^2 + beta^2)`` is kept
(:func:`_two_axis_angles`): continuity with the previous frame, and near a
tangency (where the two solutions meet and continuity cannot tell them apart)
the one nearer the rest pose. Which extracted axis acts first: ``A`` moves with
the child and ``B`` stays in the parent, so ``B . (Q Q_rest^T A)`` keeps the
value ``A . B``; when one order keeps this clearly better (combined movement)
it is used, else (a protocol moves one axis at a time, which keeps both) the
order that keeps the calibration samples farthest from ``+-B``, where the
model is singular.

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
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._errors import ConvergenceWarning, DegenerateMotionWarning, InputError
from .._math.frames import cut_frames
from .._math.linalg import eigh3
from .._math.order import masked_median
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
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.compiler_options import jit
from .._runtime.precision import float64_scope
from . import _axes
from ._anatomy import AXIS_COUNTS, limb_hinges
from ._normalize import (
    FRAME_BUCKETS_PER_OCTAVE,
    Normalization,
    calibration_mask,
    freeze_fields,
    normalize,
    normalize_arrays,
    skeleton_leaf_axes,
    skeleton_leaf_lengths,
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
#: Weight of the rest-pose preference in the choice between the two circle intersections.
REST_PREFERENCE = 0.1


def _wrap(x: Array) -> Array:
    return jnp.mod(x + jnp.pi, 2 * jnp.pi) - jnp.pi


def _two_axis_angles(
    p: Float[Array, "F 3"],
    valid: Bool[Array, " F"],
    r: Float[Array, " 3"],
    a: Float[Array, " 3"],
    b: Float[Array, " 3"],
    start: Int[Array, ""],
    first: Bool[Array, " F"],
) -> tuple[Float[Array, " F"], Float[Array, " F"]]:
    """``(alpha, beta)`` per frame by circle intersection, the two solutions told apart by continuity.

    The circle reachable from ``r`` about ``a`` (plane ``a.x = a.r``) and the
    circle reaching ``p`` about ``b`` (plane ``b.x = b.p``) meet where their
    planes' line ``x0 + t (a x b)/|a x b|`` cuts the sphere: two candidates
    ``x+-`` with angles ``(alpha+-, beta+-)`` (``alpha`` takes ``r`` to ``x``
    about ``a``, ``beta`` takes ``x`` to ``p`` about ``b``), computed for all
    frames at once. The choice starts at frame ``start`` (the rest pose, angles
    0) and walks forward and backward in time (one scan, batched over the two
    directions), keeping at each frame the candidate of least

        |wrap(alpha - alpha_prev)|^2 + |wrap(beta - beta_prev)|^2 + w (alpha^2 + beta^2),

    continuity with the previous frame plus a small preference (``w`` =
    :data:`REST_PREFERENCE`) for the rest pose. Far from a tangency one candidate
    is a whole branch away and continuity decides; where the circles touch the
    candidates meet and swap, continuity cannot tell them apart and the
    solution nearer the rest pose is kept rather than the far one. Where a new
    take begins (``first``; walking backward: where one ends) the previous
    angles restart at 0. Padded frames keep the previous choice.
    """
    n = p.shape[0]
    c = a @ b
    h1 = a @ r
    h2 = p @ b
    denom = jnp.maximum(1.0 - c * c, 1e-12)
    x0 = ((h1 - c * h2)[:, None] * a + (h2 - c * h1)[:, None] * b) / denom
    line = _unit(jnp.cross(a, b))
    t = jnp.sqrt(jnp.maximum(1.0 - jnp.sum(x0 * x0, -1), 0.0))[:, None]
    cand = _unit(jnp.stack([x0 + t * line, x0 - t * line], axis=1))  # (F, 2, 3)
    alpha = _angle_about(a, r, cand)  # (F, 2)
    beta = _angle_about(b, cand, p[:, None])
    ab = jnp.stack([alpha, beta], axis=-1)  # (F, 2 candidates, 2 angles)

    steps = jnp.arange(n)
    index = jnp.stack([start + steps, start - steps])  # forward, backward from the rest frame
    inside = (index >= 0) & (index < n)
    index = jnp.clip(index, 0, n - 1)
    ok = inside & valid[index]
    last = jnp.concatenate([first[1:], jnp.ones(1, bool)])
    reset = jnp.stack([first[index[0]], last[index[1]]]) & (steps > 0)

    def choose(prev, x):
        ab, ok, reset = x  # (2 dirs, 2 cands, 2), (2,), (2,)
        prev = jnp.where(reset[:, None], 0.0, prev)
        cost = jnp.sum(_wrap(ab - prev[:, None]) ** 2, -1) + REST_PREFERENCE * jnp.sum(ab**2, -1)
        pick = jnp.where((cost[:, 0] <= cost[:, 1])[:, None], ab[:, 0], ab[:, 1])
        pick = jnp.where(ok[:, None], pick, prev)
        return pick, pick

    _, walked = jax.lax.scan(choose, jnp.zeros((2, 2), p.dtype), (jnp.swapaxes(ab[index], 0, 1), ok.T, reset.T))
    after = steps >= start
    out = jnp.where(
        after[:, None],
        walked[jnp.clip(steps - start, 0, n - 1), 0],
        walked[jnp.clip(start - steps, 0, n - 1), 1],
    )
    return out[:, 0], out[:, 1]


def swing_twist_angles(
    q: Float[Array, "F 4"],
    p: Float[Array, "F 3"],
    valid: Bool[Array, " F"],
    axes: Float[Array, "2 3"],
    n_axes: Int[Array, ""],
    rest_rotation: Float[Array, " 4"],
    rest_direction: Float[Array, " 3"],
    rest_frame: Int[Array, ""],
    first: Bool[Array, " F"] | None = None,
) -> tuple[Float[Array, "F 3"], Float[Array, " F"]]:
    """Angles ``(alpha, beta, tau)`` per frame of one joint and the direction residual (radians).

    ``rest_frame`` is the frame of the rest pose (``Q = Q_rest`` there, so all
    three angles are 0): the circle-intersection choice walks from it in both
    directions of time (:func:`_two_axis_angles`). Angles are in ``(-pi, pi]``.
    ``first`` (F,) marks frames that begin a new take (a separate calibration
    trial before the motion); default: frame 0 only.

    ``q`` are the relative limb rotations ``Q_j(f)`` as quaternions, ``p`` the
    samples; ``axes[0]`` acts first (``alpha``), ``axes[1]`` second (``beta``; unused
    with one axis). The twist is the rotation about ``d = S r`` closest to
    ``M = Q (S Q_rest)^T``: with ``M``'s quaternion ``(w, v)``, ``tau = 2 atan2(v . d, w)``
    (for unit quaternions ``tr(A^T B) = 4 (a . b)^2 - 1``, maximised over rotations
    about d). The residual is the angle between the re-posed and the sampled
    direction (0 when the model reaches the sample).
    """
    a, b = axes[0], axes[1]
    if first is None:
        first = jnp.arange(p.shape[0]) == 0
    alpha2, beta2 = _two_axis_angles(p, valid, rest_direction, a, b, rest_frame, first)
    two = (n_axes > 1) & (jnp.linalg.norm(jnp.cross(a, b)) > 1e-6)
    alpha = jnp.where(two, alpha2, _angle_about(a, rest_direction, p))
    beta = jnp.where(two, beta2, 0.0)
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


@jit
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


@jit
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
def _rotation_noise(
    q: Float[Array, "F 4"], defined: Bool[Array, " F"]
) -> tuple[Float[Array, "F 3"], Float[Array, ""], Float[Array, "3 3"]]:
    """Angular steps ``w_f = log(Q(f) Q(f-1)^T)`` (parent frame) and the noise of ``Q``: variance per component, covariance.

    Noise model: ``Q(f) = exp([e_f]) Q_true(f)`` with white ``e_f ~ N(0, C)``
    (``C`` need not be isotropic: a limb's rotation about its own long axis is
    usually the least well determined) and a motion that is smooth at the
    frame rate. The second difference of the steps ``dw_f = w_f - w_{f-1} ~ e_f
    - 2 e_{f-1} + e_{f-2}`` is then noise only, with covariance ``6 C``; so
    ``C = mean dw dw^T / 6`` over the frames whose ``|dw|^2`` is at most 9 times
    its median (the few frames where the motion itself jerks are left out), and
    ``s^2 = tr(C) / 3``.
    """
    step = quat_to_axis_angle(quat_multiply(q[1:], quat_conjugate(q[:-1])))
    w = jnp.concatenate([step[:1], step])
    dwv = w[1:] - w[:-1]
    dw = jnp.sum(dwv**2, -1)
    ok = defined[1:] & jnp.concatenate([defined[:1], defined[1:-1]])
    n_ok = jnp.sum(ok)
    median = masked_median(dw, ok)
    keep = (ok & (dw <= 9.0 * median)).astype(w.dtype)
    cov = jnp.einsum("f,fi,fj->ij", keep, dwv, dwv) / jnp.maximum(jnp.sum(keep), 1.0) / 6.0
    cov = jnp.where(n_ok > 0, cov, 0.0)
    return jnp.where(defined[:, None], w, 0.0), jnp.trace(cov) / 3.0, cov


def _off_line_rms(scatter: Float[Array, "3 3"], noise_cov: Float[Array, "3 3"]) -> Float[Array, ""]:
    """``sqrt(max(l_2 + l_3 - tr(V^T N V), 0))``: the RMS off the principal line of ``scatter`` with the noise ``N`` removed.

    ``V`` holds the two smaller eigenvectors of ``scatter`` (the off-line directions).
    """
    vals, vecs = jnp.linalg.eigh(scatter)
    off = vecs[:, :2]
    noise = jnp.trace(off.T @ noise_cov @ off)
    return jnp.sqrt(jnp.maximum(vals[0] + vals[1] - noise, 0.0))  # rounding can dip below 0


def _one_axis_rms(
    q: Float[Array, "F 4"],
    p: Float[Array, "F 3"],
    movement: Bool[Array, " F"],
    centroid: Float[Array, " 3"],
    noise_cov: Float[Array, "3 3"],
) -> Float[Array, ""]:
    """How far (RMS angle, noise removed) the movement frames' rotations leave a single fixed axis.

    About one axis ``A``, ``Q(f) Q(g)^T = R_A(theta_f - theta_g)`` for every pair
    of frames, so the rotation vectors ``w_f = log(Q(f) Q(ref)^T)`` lie on one line.
    The off-line variance is the sum of the two smaller eigenvalues of
    ``mean w w^T``; noise of covariance ``C`` (both frames carry it, so ``2 C``
    in ``w``) adds ``2 v^T C v`` along each off-line direction ``v``, which is
    removed (:func:`_off_line_rms`; ``4 s^2`` for isotropic noise). Whole limb rotations are used, not
    directions alone: a limb that is not orthogonal to its axis moves on a small
    circle, and a small circle can pass close to two short perpendicular arcs.
    """
    ref = jnp.argmin(jnp.where(movement, jnp.sum((p - centroid) ** 2, -1), jnp.inf))
    rotvec = quat_to_axis_angle(quat_multiply(q, quat_conjugate(q[ref])))
    w = movement.astype(p.dtype)
    scatter = jnp.einsum("f,fi,fj->ij", w, rotvec, rotvec) / jnp.maximum(jnp.sum(w), 1.0)
    return _off_line_rms(scatter, 2.0 * noise_cov)


def _one_swing_axis_rms(
    p: Float[Array, "F 3"],
    movement: Bool[Array, " F"],
    ref: Int[Array, ""],
    noise_cov: Float[Array, "3 3"],
) -> Float[Array, ""]:
    """How far (RMS angle, noise removed) the limb's swings leave one fixed axis, its twist ignored.

    The swing from the rest sample ``p_ref`` (the default-pose frame) to ``p_f`` is the rotation
    vector ``v_f = theta_f (p_ref x p_f) / |p_ref x p_f|`` (``theta_f`` the angle
    between them). When the long axis swings on one great circle about ``A``
    (a hinge orthogonal to the limb, or a universal joint whose second axis is
    the limb's long axis, which only twists it) every ``v_f`` lies on the line
    of ``A``. The off-line variance is the sum of the two smaller eigenvalues
    of ``mean v v^T`` over the movement frames that swing by more than three
    noise deviations (``theta_f > 3 sqrt(2) s``; still or only twisting frames
    would dilute it). Direction noise moves ``v`` across the line by the
    rotation noise about ``A x p`` (orthogonal to the axis and the limb), which
    over a circle about ``A`` adds ``tr(V^T C V)`` to the off-line variance (``V``
    the off-line directions, ``C`` the rotation noise covariance; ``2 s^2`` for
    isotropic noise); it is removed (:func:`_off_line_rms`).
    """
    cross = jnp.cross(p[ref][None], p)
    sin = jnp.linalg.norm(cross, axis=-1)
    angle = jnp.arctan2(sin, p @ p[ref])
    v = cross * (angle / jnp.where(sin > 1e-12, sin, 1.0))[:, None]
    # Only frames that swing clearly (beyond three noise deviations of a direction
    # difference): frames that hold still or only twist would dilute the RMS.
    noise_var = jnp.trace(noise_cov) / 3.0
    w = (movement & (angle > jnp.maximum(3.0 * jnp.sqrt(2.0 * noise_var), 1e-3))).astype(p.dtype)
    scatter = jnp.einsum("f,fi,fj->ij", w, v, v) / jnp.maximum(jnp.sum(w), 1.0)
    return _off_line_rms(scatter, noise_cov)


#: How far (along the axis, on the unit sphere: about 6 degrees) a main movement's sample may
#: leave the circle about its axis through the rest sample.
MAIN_CIRCLE_TOLERANCE = 0.1
#: Side of the grid cells (on the unit sphere of axes: about 3 degrees) within which windows
#: share a main movement's axis.
MAIN_AXIS_CELL = 0.05


def _main_movement_frames(
    w: Float[Array, "F 3"],
    p: Float[Array, "F 3"],
    rest: Float[Array, " 3"],
    movement: Bool[Array, " F"],
    noise_var: Float[Array, ""],
    window: int,
    purity: float,
    min_main: int,
) -> Bool[Array, " F"]:
    """Frames inside a main movement: the joint turns about one fixed axis (automatic calibration).

    The summed angular steps ``r_f = sum_{g <= f} w_g`` are the joint's rotation
    vector since the first frame where it turns about one fixed axis (``w_g`` all
    along it: ``r_f = theta_f A``), and the steps' noise telescopes (``w_g`` carries
    ``e_g - e_{g-1}``), so ``r`` has the noise of one frame, not of a step. Around
    every frame (evaluated once per block of an eighth of a window), the centred
    scatter ``S = sum (r - rbar)(r - rbar)^T`` over about ``window`` frames (block
    sums of ``r`` and ``r r^T``, then prefix sums over the blocks: one pass) has
    eigenvalues ``l_1 >= l_2 >= l_3``; noise adds about ``n s^2`` to each (n frames),
    which is removed. A frame belongs to a main movement when the joint moves
    there (``movement``), the noise-free excursion exceeds the noise
    (``l_1' > 9 n s^2``, three standard deviations) and one axis explains at least
    ``purity`` of it, ``l_1' / (l_1' + l_2' + l_3') >= purity``. A calibration
    protocol (one movement at a time) passes; free movement, where several degrees
    of freedom change together, mostly does not.

    A main movement starts from the default pose (§4: the calibration movements
    leave it one axis at a time), so the sample ``p`` stays on the circle about
    the window's axis ``u`` (the eigenvector of ``l_1``) through the rest sample:
    ``|u . (p - p_rest)| <=`` :data:`MAIN_CIRCLE_TOLERANCE`. Free movement that turns
    about one of the joint's axes from another posture (a small circle elsewhere)
    is left out: its samples would pull the axis planes. And a short stretch of
    free movement can turn about a mixture of the axes that drifts from stretch to
    stretch, while a main movement keeps its axis: a frame is kept only when its
    axis is shared, to within a grid cell of side :data:`MAIN_AXIS_CELL` on the sphere of axes,
    by at least ``min_main`` such frames of the recording (counts per cell of
    ``+-u``, on two grids half a cell apart, the larger count taken).
    """
    n = w.shape[0]
    r = jnp.cumsum(w, axis=0)
    # Windows overlap almost entirely from one frame to the next: they are evaluated
    # per block of ``stride`` frames (an eighth of a window), each window the
    # ``2 h + 1`` blocks around a frame's own block.
    stride = max(1, window // 8)
    n_blocks = -(-n // stride)
    h = max(1, (window // 2) // stride)
    filled = jnp.concatenate([jnp.ones(n, w.dtype), jnp.zeros(n_blocks * stride - n, w.dtype)])
    padded = jnp.concatenate([r, jnp.zeros((n_blocks * stride - n, 3), w.dtype)]).reshape(n_blocks, stride, 3)
    sums = [filled.reshape(n_blocks, stride).sum(1), padded.sum(1), jnp.einsum("bsi,bsj->bij", padded, padded)]
    cums = [jnp.concatenate([jnp.zeros((1, *x.shape[1:]), x.dtype), jnp.cumsum(x, axis=0)]) for x in sums]
    block = jnp.arange(n_blocks)
    lo, hi = jnp.clip(block - h, 0, n_blocks), jnp.clip(block + h + 1, 0, n_blocks)
    count, total_r, total_rr = (c[hi] - c[lo] for c in cums)
    count = jnp.maximum(count, 1.0)
    scatter = total_rr - jnp.einsum("bi,bj->bij", total_r, total_r) / count[:, None, None]
    vals, vecs = eigh3(scatter)
    vals = jnp.maximum(vals - (count * noise_var)[:, None], 0.0)
    total = jnp.sum(vals, -1)
    strong = vals[:, 2] > 9.0 * count * noise_var
    own = jnp.arange(n) // stride
    pure = (strong & (vals[:, 2] >= purity * jnp.maximum(total, 1e-300)) & (total > 0))[own] & movement
    axis = vecs[:, :, 2][own]  # the eigenvector of l_1
    # A main movement starts from the default pose: the sample stays on the circle
    # about the window's axis through the rest sample.
    pure = pure & (jnp.abs(jnp.sum(axis * (p - rest), -1)) <= MAIN_CIRCLE_TOLERANCE)
    weight = pure.astype(w.dtype)

    def shared(offset):
        key, n_cells = _axes.cell_keys(axis, MAIN_AXIS_CELL, offset)
        counts = jax.ops.segment_sum(weight, key, num_segments=n_cells)
        counts = counts + jax.ops.segment_sum(weight, _axes.cell_keys(-axis, MAIN_AXIS_CELL, offset)[0],
                                              num_segments=n_cells)
        return counts[key]

    return pure & (jnp.maximum(shared(0.0), shared(0.5)) >= min_main)


# Three jitted stages, joint-major inside (vmapped over joints); only the middle
# one depends on the axis-extraction method, so trying another method recompiles
# only that stage.
@jit(
    static_argnames=("n_bins", "min_prominence", "low_speed_fraction", "hinge_tolerance", "auto", "window", "purity",
                     "min_calibration", "min_main"),
)
def _filter_stage(
    limb: Float[Array, "F S 4"],
    edges: Int[Array, "J 2"],
    main: Float[Array, "S 3"],
    n_axes_given: Int[Array, " J"],
    valid: Bool[Array, " F"],
    calibration: Bool[Array, " F"],
    rest_frame: Int[Array, ""],
    *,
    n_bins: int,
    min_prominence: float,
    low_speed_fraction: float,
    hinge_tolerance: float,
    auto: bool,
    window: int,
    purity: float,
    min_calibration: int,
    min_main: int,
) -> dict[str, Array]:
    """Relative rotations, samples, calibration frames, movement filter (§4.1) and axes per joint.

    ``calibration`` (F,) are the frames the axes may come from (given, or all
    valid frames when ``auto``; then each joint keeps only its main-movement
    frames, :func:`_main_movement_frames` with ``min_main`` frames sharing an
    axis, or all frames when fewer than ``min_calibration`` are found; the axis
    count still comes from all of them).
    """
    q = jnp.swapaxes(quat_multiply(quat_conjugate(limb[:, edges[:, 0]]), limb[:, edges[:, 1]]), 0, 1)

    def one(q, main, given):
        p = quat_rotate(q, main)
        speed, defined = _axes.speeds(p, valid)
        w, noise_var, noise_cov = _rotation_noise(q, defined)
        in_cal = calibration & valid
        threshold, counts, top = _axes.speed_threshold(
            speed, defined & in_cal, n_bins, min_prominence, low_speed_fraction
        )
        moving = defined & (speed > threshold)

        def mean_sample(frames):
            weight = (valid & frames).astype(p.dtype)
            return jnp.sum(weight[:, None] * p, 0) / jnp.maximum(jnp.sum(weight), 1.0)

        # The axis count from every calibration frame: the automatic choice keeps
        # windows that turn about one axis, so a two-axis joint whose main movements
        # are found for one axis only would look like a hinge there.
        counted, counted_centroid = moving & in_cal, mean_sample(in_cal)
        if auto:
            found = _main_movement_frames(w, p, p[rest_frame], moving, noise_var, window, purity, min_main)
            found = found & in_cal
            in_cal = jnp.where(jnp.sum(found) >= min_calibration, found, in_cal)
        movement = moving & in_cal
        centroid = mean_sample(in_cal)
        hinge_rms = jnp.minimum(
            _one_axis_rms(q, p, counted, counted_centroid, noise_cov),
            _one_swing_axis_rms(p, counted, rest_frame, noise_cov),
        )
        n_axes = jnp.where(given > 0, given, jnp.where(hinge_rms > hinge_tolerance, 2, 1))
        return {
            "q": q,
            "samples": p,
            "speed": speed,
            "threshold": threshold,
            "histogram": counts,
            "top_speed": top,
            "movement": movement,
            "calibration": in_cal,
            "noise": jnp.sqrt(noise_var),
            "centroid": centroid,
            "hinge_rms": hinge_rms,
            "n_axes": n_axes,
        }

    return jax.vmap(one)(q, main[edges[:, 1]], n_axes_given)


@jit(static_argnames=("method", "cell", "delta", "max_groups", "max_em_steps"))
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


@jit
def _angles_stage(
    q: Float[Array, "J F 4"],
    samples: Float[Array, "J F 3"],
    movement: Bool[Array, "J F"],
    valid: Bool[Array, " F"],
    centroid: Float[Array, "J 3"],
    n_axes: Int[Array, " J"],
    axes: Float[Array, "J 2 3"],
    offsets: Float[Array, "J 2"],
    rest_frame: Int[Array, ""],
    first: Bool[Array, " F"],
    calibration: Bool[Array, "J F"],
    noise: Float[Array, " J"],
) -> dict[str, Array]:
    """Rest position (the default pose), axis order, angles and twist (§4.3-4.5), fit diagnostics."""

    def one(q, p, movement, centroid, n_axes, axes, offsets, calibration, noise):
        moving = movement.astype(p.dtype)
        axes = axes.at[1].set(jnp.where(n_axes > 1, axes[1], 0.0))
        rest_direction = p[rest_frame]
        rest_rotation = q[rest_frame]

        # Which axis acts first: it moves with the child while the second stays in the
        # parent, so B . (Q Q_rest^T A) stays A . B; keep the order where it varies less.
        carried = quat_rotate(quat_multiply(q, quat_conjugate(rest_rotation))[:, None], axes[None])  # (F, 2, 3)
        invariant = jnp.stack([carried[:, 0] @ axes[1], carried[:, 1] @ axes[0]], axis=1)
        mean = jnp.sum(moving[:, None] * invariant, 0) / jnp.maximum(jnp.sum(moving), 1.0)
        spread = jnp.sum(moving[:, None] * (invariant - mean) ** 2, 0) / jnp.maximum(jnp.sum(moving), 1.0)
        mean_sq = spread
        # A protocol moves one axis at a time, which keeps both invariants: then the
        # order is taken so that the limb stays far from the parent-fixed (second)
        # axis, where the two-axis model has its singularity (p = +-B: beta is lost).
        significant = jnp.max(mean_sq) > 9.0 * 2.0 * noise**2
        decisive = significant & (jnp.min(spread) < 0.1 * jnp.max(spread))
        close = jnp.max(jnp.where(calibration[:, None], jnp.abs(p @ axes.T), 0.0), axis=0)
        swap = (n_axes > 1) & jnp.where(decisive, spread[1] < spread[0], close[1] > close[0])
        axes = jnp.where(swap, axes[::-1], axes)
        offsets = jnp.where(swap, offsets[::-1], offsets)
        angles, residual = swing_twist_angles(
            q, p, valid, axes, n_axes, rest_rotation, rest_direction, rest_frame, first
        )

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

    return jax.vmap(one)(q, samples, movement, centroid, n_axes, axes, offsets, calibration, noise)


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
        reference frame), or the child's long-axis swings, leave one fixed
        axis, whichever is less: ~0 for a one-axis joint (the one-or-two-axes
        test, threshold ``hinge_tolerance_deg``).
    extent
        (J,) largest angle of any sample from the samples' mean direction.
    exercised
        (J,) False for joints that barely moved (``extent`` below ``min_extent``).
    steps, converged
        (J,) group merges (joining) or EM iterations, and whether EM settled
        (always True for joining and PCA).
    calibration
        (F, J) the frames each joint's axes, axis count and movement filter were
        taken from: the given calibration window, or (``calibration_source``
        "automatic", the default) the frames where the joint performs a main
        movement (it turns about one fixed axis, starting from the default pose,
        an axis many frames share; see ``_main_movement_frames``), or every frame
        when fewer than ``min_calibration_frames`` such frames exist; the automatic
        choice sets the axes and the movement filter, and the axis count comes from
        every frame. Angles are given for every frame.
    calibration_source
        "all", "given", "automatic" or "trial" (a separate calibration recording).
    noise
        (J,) estimated noise (radians, per rotation component and frame) of the
        joint's relative rotations, removed in the one-or-two-axes test.
    normalization
        The :class:`~jaxskel.sd06.Normalization` the samples were taken in.
    settings
        The options used (``n_axes`` as given, 0 = not given; ``axis_count``).
    axis_count_source
        (J,) where each joint's axis count came from: "given" (``n_axes``),
        "anatomy" (a knee or elbow, one axis: :mod:`jaxskel.sd06._anatomy`) or
        "data" (the one-or-two-axes test on ``hinge_rms``).
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
    calibration: np.ndarray
    calibration_source: str
    noise: np.ndarray
    normalization: Normalization
    settings: Mapping[str, Any]
    axis_count_source: np.ndarray | None = None

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
            to_device(pad(a)),
            to_device(self.axes),
            to_device(self.rest_direction),
            to_device(self.rest_rotation),
            to_device(pad(norm.limb_rotations[:, root]))
            if root_frames is None
            else matrix_to_quat(to_device(pad(frames_r))),
            to_device(pad(origins_r)),
            to_device(norm.joint_offsets),
            to_device(tree),
            to_device(root),
        )
        local = norm.limb_frames_local
        centre = np.zeros((norm.n_segments, 3)) if norm.origins_local is None else norm.origins_local
        frames, segment, translations = (
            np.asarray(v)[:n] for v in _segment_poses(limb, origins, to_device(local), to_device(centre))
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
        raise InputError(f"n_axes must be 1 or 2 per joint (0 or None: decided by axis_count), got {out.tolist()}")
    return out


def parameterize_normalized(
    normalization: Normalization,
    *,
    method: str = "joining",
    n_axes: int | Sequence[int] | Mapping[int, int] | None = None,
    axis_count: str = "anatomy",
    delta_deg: float = 15.0,
    cell: float = 0.05,
    max_groups: int = 32,
    n_bins: int = 100,
    min_prominence: float = 0.05,
    low_speed_fraction: float = 0.2,
    hinge_tolerance_deg: float = 4.0,
    min_extent_deg: float = 5.0,
    max_em_steps: int = 100,
    calibration: Any = None,
    rate: float | None = None,
    window_s: float = 1.0,
    purity: float = 0.97,
    main_s: float = 1.0,
    min_calibration_frames: int = 10,
    _first: np.ndarray | None = None,
) -> Parameterization:
    """Parameterise a normalised motion; see :func:`parameterize` for the options.

    ``calibration`` None uses the normalisation's calibration window when it has
    one, else chooses each joint's main-movement frames ("auto"); "all" takes every frame.
    """
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
    if axis_count not in AXIS_COUNTS:
        raise InputError(f"axis_count must be one of {AXIS_COUNTS}, got {axis_count!r}")
    user_given = _n_axes_array(n_axes, norm.n_joints)
    hinge = limb_hinges(norm) if axis_count == "anatomy" else np.zeros(norm.n_joints, bool)
    given = np.where((user_given == 0) & hinge, 1, user_given)
    source = np.where(user_given > 0, "given", np.where(hinge, "anatomy", "data"))
    if (not 0.5 <= float(purity) < 1.0 or not float(window_s) > 0 or not float(main_s) > 0
            or int(min_calibration_frames) < 3):
        raise InputError(
            f"purity must be in [0.5, 1), window_s > 0, main_s > 0 and min_calibration_frames >= 3; got {purity}, "
            f"{window_s}, {main_s}, {min_calibration_frames}"
        )
    if calibration is None and norm.calibration is not None and not norm.calibration.all():
        calibration = norm.calibration  # the normalisation's window
    every = isinstance(calibration, str) and calibration == "all"
    auto = calibration is None or (isinstance(calibration, str) and calibration == "auto")
    cal = None if auto else np.ones(n_frames, bool) if every else calibration_mask(calibration, n_frames, rate)
    if not auto and not cal[norm.default_frame]:
        raise InputError(
            f"the default pose (frame {norm.default_frame}) lies outside the calibration window; normalise "
            "with the same calibration= (parameterize does)"
        )
    window = round(window_s * rate) if rate else 30
    window = max(3, window | 1)
    first = np.zeros(n_frames, bool) if _first is None else np.asarray(_first, bool).copy()
    first[0] = True
    size = bucket_size(n_frames, steps_per_octave=FRAME_BUCKETS_PER_OCTAVE)
    max_groups = min(int(max_groups), size)
    limb = np.concatenate([norm.limb_rotations, np.repeat(norm.limb_rotations[-1:], size - n_frames, axis=0)])
    main = np.eye(3, dtype=limb.dtype)[norm.main_axis] * norm.main_sign[:, None]
    valid = to_device(np.arange(size) < n_frames)
    filter_options = {
        "n_bins": int(n_bins),
        "min_prominence": float(min_prominence),
        "low_speed_fraction": float(low_speed_fraction),
        "hinge_tolerance": math.radians(hinge_tolerance_deg),
        "auto": auto,
        "window": window,
        "purity": float(purity),
        "min_calibration": int(min_calibration_frames),
        "min_main": max(3, round(main_s * rate) if rate else 30),
    }
    axes_options = {
        "method": method,
        "cell": float(cell),
        "delta": math.radians(delta_deg),
        "max_groups": max_groups,
        "max_em_steps": int(max_em_steps),
    }
    pad_false = np.zeros(size - n_frames, bool)
    cal_frames = np.ones(n_frames, bool) if auto else cal
    filtered = _program_cache.call(
        _filter_stage,
        to_device(limb),
        to_device(norm.edges),
        to_device(main),
        to_device(given),
        valid,
        to_device(np.concatenate([cal_frames, pad_false])),
        to_device(norm.default_frame),
        **filter_options,
    )
    extracted = _program_cache.call(
        _axes_stage, filtered["samples"], filtered["movement"], filtered["n_axes"], **axes_options
    )
    posed = _program_cache.call(
        _angles_stage,
        filtered["q"],
        filtered["samples"],
        filtered["movement"],
        valid,
        filtered["centroid"],
        filtered["n_axes"],
        extracted["axes"],
        extracted["offsets"],
        to_device(norm.default_frame),
        to_device(np.concatenate([first, pad_false])),
        filtered["calibration"],
        filtered["noise"],
    )
    out = {k: np.asarray(v) for k, v in {**filtered, **extracted, **posed}.items() if k != "q"}
    # Per-frame outputs are joint-major inside the stages; frames first outside.
    for key in ("samples", "speed", "movement", "angles", "residual", "calibration"):
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
        calibration=out["calibration"].astype(bool),
        calibration_source="automatic" if auto else ("all" if every else "given"),
        noise=out["noise"],
        normalization=norm,
        axis_count_source=source,
        settings={
            **filter_options,
            **axes_options,
            "n_axes": user_given.tolist(),
            "axis_count": axis_count,
            "min_extent_deg": float(min_extent_deg),
        },
    )


def _is_motion(obj: Any) -> bool:
    return getattr(obj, "joint_positions", None) is not None and getattr(obj, "rotations", None) is not None


def _with_calibration_trial(
    calibration: Any, motion_arrays: tuple, skeleton_arrays: dict, up_axis: Any, options: dict, method: str, n_axes: Any,
    facing: Any = None,
) -> Parameterization:
    """Axes and default pose from a separate calibration recording, angles for the motion.

    The two recordings (same skeleton) are parameterised as two takes of one
    motion: the calibration take alone gives the default pose, the axes and
    the rest pose; the motion's take starts its circle-intersection walk from
    the rest pose again. The result holds the motion's frames only; its
    ``rest_frame`` and ``normalization.default_frame`` are -1 (the rest pose
    lies in the calibration recording).
    """
    joints, rotations, translations = motion_arrays
    cal_t = getattr(calibration, "segment_translations", None)
    if (cal_t is None) != (translations is None):
        raise InputError("the calibration motion and the motion must both have segment_translations, or neither")
    n_cal, n_mot = np.asarray(calibration.joint_positions).shape[0], np.asarray(joints).shape[0]
    try:
        cat = [np.concatenate([np.asarray(a), np.asarray(b)]) for a, b in (
            (calibration.joint_positions, joints), (calibration.rotations, rotations))]
        cat_t = None if translations is None else np.concatenate([np.asarray(cal_t), np.asarray(translations)])
    except ValueError as err:
        raise InputError(f"the calibration motion does not match the motion's skeleton: {err}") from None
    mask = np.arange(n_cal + n_mot) < n_cal
    norm = normalize_arrays(
        cat[0], skeleton_arrays["edges"], cat[1], root=skeleton_arrays["root"], up_axis=up_axis,
        segment_translations=cat_t, calibration=mask, facing=facing, leaf_axes=skeleton_arrays.get("leaf_axes"),
        leaf_lengths=skeleton_arrays.get("leaf_lengths"),
    )
    first = np.zeros(n_cal + n_mot, bool)
    first[n_cal] = True
    options = {k: v for k, v in options.items() if k != "rate"}
    param = parameterize_normalized(norm, method=method, n_axes=n_axes, calibration=mask, _first=first, **options)
    keep = slice(n_cal, None)
    n = n_cal + n_mot
    norm = cut_frames(param.normalization, n, keep, default_frame=-1)
    return cut_frames(
        param, n, keep, normalization=norm, rest_frame=np.full_like(param.rest_frame, -1), calibration_source="trial"
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
    calibration: Any = None,
    facing: Any = None,
    **options: Any,
) -> Parameterization:
    """Joint axes, rest positions and angles of a fitted motion (Sar Dessai et al. 2006, §4).

    Parameters
    ----------
    skeleton, motion
        Duck-typed: ``skeleton.edges`` (J, 2), ``skeleton.root``; ``motion.joint_positions``
        (F, J, 3), ``motion.rotations`` (F, S, 4) (w, x, y, z), optionally
        ``motion.segment_translations`` and ``motion.rate``. The motion (or the
        calibration recording) should contain a calibration phase: the default
        pose, then every joint's main movements one at a time.
    normalization
        From :func:`~jaxskel.sd06.normalize` (computed with ``up_axis`` and
        ``calibration`` when None).
    method
        "joining" (the paper's direction joining), or the baselines "pca" / "em".
    n_axes
        Movement axes per joint: None (decide), 1 or 2 for all, a sequence per
        joint or a mapping joint -> 1/2 (0 = decide). What is not given is decided
        by ``axis_count`` (an option below).
    calibration
        Which frames define the default pose, the axes and the axis count:
        None or "auto" (the default: each joint's main-movement frames, found as
        described in :func:`_main_movement_frames` and recorded in
        :attr:`Parameterization.calibration`; the default pose is sought in every
        frame), "all" (every frame), a ``slice`` or ``(start, stop)``
        of frames, ``(t0, t1)`` seconds (floats; uses ``motion.rate`` or
        ``rate=``), a boolean mask per frame, or a separate calibration
        recording of the same skeleton (an object like ``motion``). Angles are
        computed for every frame of ``motion``.
    facing
        The world direction the subject faces in the default pose, for the
        normalisation parameterize makes (``normalization=None``): see
        :func:`~jaxskel.sd06.normalize`; by default the body tells front from back.
    **options
        ``axis_count`` ("anatomy", the default: the knees and elbows, found from
        the skeleton's shape, get the one axis of a hinge, as the paper takes the
        degrees of freedom from the anatomy, and every other joint's count comes
        from the data; "data": every joint's count from the data; see
        :mod:`jaxskel.sd06._anatomy`), ``delta_deg`` (15, direction similarity), ``cell`` (0.05, stratification
        chord on the unit sphere), ``max_groups`` (32, largest groups clustered), ``n_bins`` (100, speed
        histogram), ``min_prominence`` (0.05 of the tallest bar), ``low_speed_fraction``
        (0.2), ``hinge_tolerance_deg`` (4, one axis when the movement frames' relative
        rotations, noise removed, stay this close to one axis), ``min_extent_deg`` (5,
        warn below), ``max_em_steps`` (100), ``rate`` (frames per second, default
        ``motion.rate``), ``window_s`` (1, window of the main-movement detector),
        ``purity`` (0.97, share of a window's rotation about one axis),
        ``main_s`` (1, seconds of frames that must share a main movement's axis),
        ``min_calibration_frames`` (10, fewer automatic frames: use all).
    """
    options.setdefault("rate", getattr(motion, "rate", None))
    if _is_motion(calibration):
        if normalization is not None:
            raise InputError("with a calibration recording, let parameterize normalise (normalization=None)")
        for obj, names in ((skeleton, ("edges", "root")), (motion, ("joint_positions", "rotations"))):
            missing = [n for n in names if getattr(obj, n, None) is None]
            if missing:
                raise InputError(f"{type(obj).__name__} has no {', '.join(missing)}")
        arrays = (motion.joint_positions, motion.rotations, getattr(motion, "segment_translations", None))
        skel = {"edges": skeleton.edges, "root": int(skeleton.root), "leaf_axes": skeleton_leaf_axes(skeleton),
                "leaf_lengths": skeleton_leaf_lengths(skeleton)}
        return _with_calibration_trial(calibration, arrays, skel, up_axis, options, method, n_axes, facing)
    if normalization is None:
        normalization = normalize(skeleton, motion, up_axis=up_axis, calibration=calibration, facing=facing)
    elif facing is not None:
        raise InputError("facing sets up the normalisation: give it to normalize, or pass normalization=None")
    elif not isinstance(normalization, Normalization):
        raise InputError(f"normalization must be a jaxskel.sd06.Normalization, got {type(normalization).__name__}")
    return parameterize_normalized(normalization, method=method, n_axes=n_axes, calibration=calibration, **options)


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
    calibration: Any = None,
    facing: Any = None,
    leaf_axes: Float[Any, "S 3"] | None = None,
    leaf_lengths: Float[Any, " S"] | None = None,
    **options: Any,
) -> Parameterization:
    """:func:`parameterize` from arrays (normalises first with :func:`~jaxskel.sd06._normalize.normalize_arrays`).

    ``calibration`` and ``facing`` as in :func:`parameterize`; a separate calibration recording
    is given as an object with ``joint_positions``, ``rotations`` (and
    ``segment_translations`` when the motion has them). ``leaf_axes`` and ``leaf_lengths``
    (a leaf's own long axis and its length, from its markers) as in ``normalize_arrays``;
    without ``leaf_lengths`` an elbow whose forearm is a leaf is not found as a hinge.
    """
    if _is_motion(calibration):
        skel = {"edges": edges, "root": root, "leaf_axes": leaf_axes, "leaf_lengths": leaf_lengths}
        arrays = (joint_positions, rotations, segment_translations)
        return _with_calibration_trial(calibration, arrays, skel, up_axis, options, method, n_axes, facing)
    norm = normalize_arrays(
        joint_positions, edges, rotations, root=root, up_axis=up_axis, segment_translations=segment_translations,
        calibration=calibration, rate=options.get("rate"), facing=facing, leaf_axes=leaf_axes,
        leaf_lengths=leaf_lengths,
    )
    return parameterize_normalized(norm, method=method, n_axes=n_axes, calibration=calibration, **options)


def write_parameters(group: Any, parameterization: Parameterization) -> None:
    """Write a :class:`Parameterization` into an h5py group (the result file's ``/parameters``).

    Datasets (J joints, F frames; joint-frame vectors in the parent limb's
    normalised frame): ``n_axes`` (J,), ``axes`` (J, 2, 3) (row 0 acts first; zero
    row for one-axis joints), ``rest_direction`` (J, 3), ``rest_frame`` (J,),
    ``rest_rotation`` (J, 4) quaternion, ``angles`` (F, J, 3) radians (axis 0, axis 1, twist),
    ``movement`` (F, J) bool, ``speed`` (F, J), ``speed_threshold`` (J,),
    ``residual`` (F, J) radians, ``axis_rms`` (J,), ``exercised`` (J,), ``steps`` (J,),
    ``converged`` (J,), ``calibration`` (F, J) bool (the frames each joint's axes
    came from), ``noise`` (J,) radians, ``hinge_rms`` (J,) radians, ``axis_count_source``
    (J,) strings ("given", "anatomy", "data"). Attributes: ``method``,
    ``calibration_source`` and the settings.
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
        "calibration",
        "noise",
        "hinge_rms",
    ):
        _put(group, name, np.asarray(getattr(p, name)))
    if p.axis_count_source is not None:
        _put(group, "axis_count_source", np.asarray(p.axis_count_source))
    group.attrs["method"] = p.method
    group.attrs["calibration_source"] = p.calibration_source
    group.attrs["angle_units"] = "rad"
    for key, value in p.settings.items():
        group.attrs[key] = value if not isinstance(value, list) else np.asarray(value)
