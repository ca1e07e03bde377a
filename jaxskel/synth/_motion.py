"""Joint-space motions and forward kinematics for synthetic bodies.

A motion is a set of joint-angle trajectories theta_j(t) (F, k_j) plus a root
pose (R_0(t), t_0(t)). Forward kinematics composes, in topological order,

    R_child = R_parent @ R_rel(theta_j),
    t_child = R_parent @ o_parent + t_parent - R_child @ o_child,

with ``(o_parent, o_child) = joint_offsets[j]``; this makes the joint centre the
same world point seen from both segments at every frame. Everything is
vectorised over frames; the only Python loop runs over the joints of the tree.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from jaxtyping import Float

from .._errors import InputError
from .._math.rotation import axis_angle_to_matrix_np
from ._bodies import Body

__all__ = [
    "MOTIONS",
    "smooth_signal",
    "relative_rotation",
    "forward_kinematics",
    "calibration_motion",
    "walk_motion",
]


def smooth_signal(
    times: Float[np.ndarray, " F"],
    n_channels: int,
    rng: np.random.Generator,
    frequency: tuple[float, float] = (0.08, 0.5),
    n_terms: int = 3,
) -> Float[np.ndarray, "F C"]:
    """Smooth random signals in (-1, 1): ``tanh(u(t))``.

    ``u(t) = sum_k a_k sin(2 pi f_k t + phi_k) / sqrt(sum_k a_k^2 / 2)`` has unit
    variance; frequencies are drawn uniformly from ``frequency`` (Hz), so they are
    incommensurate with probability one and the trajectory does not repeat. The
    tanh keeps the signal bounded while it still visits values close to +-1.
    """
    amp = rng.uniform(0.5, 1.0, size=(n_channels, n_terms))
    freq = rng.uniform(*frequency, size=(n_channels, n_terms))
    phase = rng.uniform(0.0, 2 * np.pi, size=(n_channels, n_terms))
    waves = amp * np.sin(2 * np.pi * freq * times[:, None, None] + phase)
    u = waves.sum(-1) / np.sqrt((amp**2).sum(-1) / 2.0)
    return np.tanh(u)


def relative_rotation(
    kind: str, axes: Float[np.ndarray, "k 3"], angles: Float[np.ndarray, "F k"]
) -> Float[np.ndarray, "F 3 3"]:
    """``R_rel(theta)`` of a joint (see :mod:`jaxskel.synth._bodies` for the convention)."""
    if kind == "ball":
        return axis_angle_to_matrix_np(angles @ axes)
    # hinge: one factor; universal: parent-fixed axis first, then the child-fixed axis.
    factors = axis_angle_to_matrix_np(angles[:, :, None] * axes[None])  # (F, k, 3, 3)
    out = factors[:, 0]
    for k in range(1, factors.shape[1]):
        out = out @ factors[:, k]
    return out


def forward_kinematics(
    body: Body,
    angles: tuple[Float[np.ndarray, "F k"], ...],
    root_rotation: Float[np.ndarray, "F 3 3"],
    root_translation: Float[np.ndarray, "F 3"],
) -> tuple[Float[np.ndarray, "F S 3 3"], Float[np.ndarray, "F S 3"]]:
    """Segment poses (R, t) per frame from joint angles and the root pose.

    ``angles[j]`` (F, k_j) are joint j's angles (one column per axis of
    ``body.joint_axes[j]``); the root pose is (F, 3, 3) rotations and (F, 3) translations.
    """
    if len(angles) != body.n_joints:
        raise InputError(f"got angles for {len(angles)} joints; this body has {body.n_joints}")
    n_frames = root_rotation.shape[0]
    for j, a in enumerate(angles):
        if a.shape != (n_frames, body.joint_axes[j].shape[0]):
            raise InputError(
                f"angles[{j}] has shape {a.shape}; joint {body.joint_names[j]!r} "
                f"({body.joint_types[j]}) needs ({n_frames}, {body.joint_axes[j].shape[0]})"
            )
    rot = np.zeros((n_frames, body.n_segments, 3, 3))
    trans = np.zeros((n_frames, body.n_segments, 3))
    rot[:, body.root] = root_rotation
    trans[:, body.root] = root_translation
    for j in body.joint_order:
        parent, child = body.edges[j]
        r_child = rot[:, parent] @ relative_rotation(
            body.joint_types[j], body.joint_axes[j], angles[j]
        )
        o_parent, o_child = body.joint_offsets[j]
        rot[:, child] = r_child
        trans[:, child] = rot[:, parent] @ o_parent + trans[:, parent] - r_child @ o_child
    return rot, trans


# ----------------------------------------------------------------- motions
RootPose = tuple[Float[np.ndarray, "F 3 3"], Float[np.ndarray, "F 3"]]
JointMotion = tuple[tuple[Float[np.ndarray, "F k"], ...], RootPose]


def calibration_motion(
    body: Body,
    times: Float[np.ndarray, " F"],
    rng: np.random.Generator,
    amount: Float[np.ndarray, " J"],
) -> JointMotion:
    """Every joint exercised through all its degrees of freedom at once.

    Each angle is ``mid + 0.95 amount_j half_range s(t)`` with ``s`` a
    :func:`smooth_signal`, so with ``amount_j = 1`` it sweeps most of its range of
    motion and stays strictly inside the limits (``amount_j = 0`` holds joint j still).
    Joint frequencies are 0.08-0.5 Hz, raised for short trials so that the slowest
    term still completes ~1.5 cycles (a few-second trial is still a full calibration).
    The root wanders by ~0.25 m and turns: an upright body turns about the vertical
    by up to +-90 degrees and tilts a little; other bodies tumble about all axes.
    """
    duration = times[-1] - times[0] + (times[1] - times[0])
    frequency = (max(0.08, 1.5 / duration), max(0.5, 3.0 / duration))
    angles = []
    for lim, scale in zip(body.joint_limits, amount, strict=True):
        mid = lim.mean(axis=1)
        half = 0.5 * (lim[:, 1] - lim[:, 0])
        wave = smooth_signal(times, lim.shape[0], rng, frequency=frequency)
        angles.append(mid + 0.95 * scale * half * wave)
    wander = smooth_signal(times, 6, rng, frequency=(0.03, 0.2))
    if body.upright:
        rotvec = wander[:, :3] * np.array([0.15, 0.15, 0.5 * np.pi])
        translation = wander[:, 3:] * np.array([0.3, 0.3, 0.03])
    else:
        rotvec = wander[:, :3] * 1.2
        translation = wander[:, 3:] * 0.25
    return tuple(angles), (axis_angle_to_matrix_np(rotvec), translation + body.rest_translation)


# Walking pattern per joint name (without side prefix): per degree of freedom,
# (offset, [(amplitude, harmonic, phase), ...]) of the gait phase phi; radians.
# Hip flexion peaks at phi = pi/2 (heel strike), the knee's swing flexion at
# phi ~ -0.2 (mid-swing); the ankle (toe down > 0) plantarflexes ~17 degrees at
# toe-off and dorsiflexes ~9 degrees in late stance. Left and right are half a
# cycle apart; arms swing against the legs. Wrists and neck barely move
# (< 2 degrees) as in real walking.
_GAIT: dict[str, list[tuple[float, list[tuple[float, int, float]]]]] = {
    "hip": [(0.0, [(0.05, 1, 0.0)]), (0.15, [(0.35, 1, 0.0)]), (0.0, [(0.05, 1, 1.0)])],
    "knee": [(0.45, [(0.45, 1, 1.77), (0.12, 2, 0.5 * np.pi)])],
    "ankle": [(0.04, [(0.106, 1, 1.72), (0.157, 2, 2.96)]), (0.0, [(0.03, 1, 0.0)])],
    "shoulder": [(0.08, [(0.02, 2, 0.0)]), (0.1, [(-0.3, 1, 0.0)]), (0.0, [(0.03, 1, 0.5)])],
    "elbow": [(0.35, [(-0.15, 1, 0.0)])],
    "wrist": [(0.0, [(0.012, 1, 0.3)]), (0.0, [(0.008, 1, 1.1)])],
    "spine": [(0.0, [(0.03, 1, 0.0)]), (0.05, [(0.02, 2, 0.0)]), (0.0, [(-0.08, 1, 0.0)])],
    "neck": [(0.0, [(0.01, 1, 0.0)]), (0.0, [(0.01, 2, 0.0)]), (0.0, [(0.015, 1, np.pi)])],
}


def walk_motion(
    body: Body,
    times: Float[np.ndarray, " F"],
    rng: np.random.Generator,
    amount: Float[np.ndarray, " J"],
) -> JointMotion:
    """Walking on a circle of 2.5 m radius at ~1.2 m/s, ~0.9 strides per second.

    Joint angles follow the :data:`_GAIT` pattern of the gait phase, with 10 %
    smooth stride-to-stride variability; ``amount_j`` scales joint j's excursion
    around its pattern offset (0 holds it still). Hips, knees, ankles and shoulders move a
    lot; wrists and neck stay within ~1.5 degrees. The pelvis sways and rotates
    with the stride, and its height keeps the lower foot on the floor (z = 0).
    Requires a :func:`~jaxskel.synth.full_body` body.
    """
    pattern_names = [name.split("_", 1)[-1] for name in body.joint_names]
    if body.name != "full_body" or any(n not in _GAIT for n in pattern_names):
        raise InputError(
            f"motion='walk' needs a human body from synth.full_body(); this is a {body.name!r} "
            "body. Use motion='calibration' for linkages and random trees."
        )
    stride_hz = rng.uniform(0.85, 0.95)
    drift = 0.1 * smooth_signal(times, 1, rng, frequency=(0.05, 0.15))[:, 0]
    phase = 2 * np.pi * stride_hz * times + drift
    angles = []
    for name, pattern, scale_j in zip(body.joint_names, pattern_names, amount, strict=True):
        side_shift = np.pi if name.startswith("r_") else 0.0
        dof = []
        jitter = smooth_signal(times, len(_GAIT[pattern]), rng, frequency=(0.2, 1.0))
        for k, (offset, terms) in enumerate(_GAIT[pattern]):
            wave = sum(a * np.sin(h * (phase + side_shift) + p) for a, h, p in terms)
            scale = max(abs(a) for a, _, _ in terms)
            dof.append(offset + scale_j * (wave + 0.1 * scale * jitter[:, k]))
        angles.append(np.stack(dof, axis=1))

    radius, speed = 2.5, rng.uniform(1.1, 1.3)
    heading = speed * times / radius
    gait = np.stack(
        [0.04 * np.sin(phase), 0.03 * np.sin(2 * phase), 0.08 * np.sin(phase)], axis=1
    )
    # Face along the circle's tangent: yaw = heading + 90 degrees, then the pelvis
    # oscillations (roll, pitch, yaw) in the pelvis frame.
    yaw = axis_angle_to_matrix_np(np.stack([0 * heading, 0 * heading, heading + 0.5 * np.pi], axis=1))
    rotation = yaw @ axis_angle_to_matrix_np(gait)
    translation = np.stack(
        [radius * np.cos(heading), radius * np.sin(heading), 0.0 * heading], axis=1
    )
    translation[:, 2] = _floor_height(body, tuple(angles), rotation)
    return tuple(angles), (rotation, translation)


def _floor_height(
    body: Body,
    angles: tuple[Float[np.ndarray, "F k"], ...],
    root_rotation: Float[np.ndarray, "F 3 3"],
) -> Float[np.ndarray, " F"]:
    """Pelvis height that keeps the lower foot on the floor (z = 0) at every frame.

    Each sole is modelled by a heel and a toe point below the ankle, at the ankle's
    rest height h (heel 0.6 h behind, toe 1.9 h ahead, ~5 and ~15 cm for an adult).
    The vertical bob of the pelvis then follows from the leg geometry, as in gait.
    """
    feet = [body.segment_names.index(name) for name in ("l_foot", "r_foot")]
    zero = tuple(np.zeros((1, lim.shape[0])) for lim in body.joint_limits)
    _, rest = forward_kinematics(body, zero, np.eye(3)[None], body.rest_translation[None])
    ankle_height = rest[0, feet[0], 2]
    sole = ankle_height * np.array([[-0.6, 0.0, -1.0], [1.9, 0.0, -1.0]])
    rot, trans = forward_kinematics(body, angles, root_rotation, np.zeros((len(root_rotation), 3)))
    sole_z = np.einsum("fsj,pj->fsp", rot[:, feet, 2, :], sole) + trans[:, feet, 2, None]
    return -sole_z.min(axis=(1, 2))


#: Named motions accepted by :func:`jaxskel.synth.simulate`.
MOTIONS: dict[str, Callable[[Body, np.ndarray, np.random.Generator, np.ndarray], JointMotion]] = {
    "calibration": calibration_motion,
    "walk": walk_motion,
}
