"""Synthetic motions for the Sar Dessai et al. (2006) stages, built on jaxskel.synth.

``synth.simulate(..., motion="calibration")`` moves every degree of freedom at
once; the paper's calibration instead performs each main movement separately
from the default pose. :func:`main_movements` builds that, and
:func:`with_default_pose` embeds a (perturbed) default pose in any motion.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from helpers import matrix_to_quat

from jaxskel import synth


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (scipy, independent of jaxskel)."""
    rotvec = np.asarray(rotvec, dtype=float)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*rotvec.shape[:-1], 3, 3)


def main_movements(
    body: synth.Body,
    *,
    rate: float = 60.0,
    period: float = 2.0,
    cycles: int = 2,
    hold: float = 0.5,
    amplitude: float = 0.8,
    seed: int = 0,
):
    """Default pose, then each degree of freedom k swung alone (all joints that have it).

    Angle k of a joint swings ``amplitude`` of the way to its upper limit and back,
    then to its lower limit and back if that is below -0.4 rad (``cycles`` times,
    ``period`` seconds each),
    with ``hold`` seconds of stillness between phases; the other angles stay 0.
    The root turns slowly about the vertical and drifts, so world frames change.
    Returns ``(angles, root_rotation, root_translation)`` for ``synth.forward_kinematics``.
    """
    n_swing = int(round(period * cycles * rate))
    n_hold = int(round(hold * rate))
    phase = np.sin(2 * np.pi * np.arange(n_swing) / (period * rate))
    n_dof = max(a.shape[0] for a in body.joint_axes)
    n_frames = n_hold + n_dof * (n_swing + n_hold)
    angles = [np.zeros((n_frames, a.shape[0])) for a in body.joint_axes]
    for k in range(n_dof):
        start = n_hold + k * (n_swing + n_hold)
        for j, lim in enumerate(body.joint_limits):
            if k < lim.shape[0]:
                lo, hi = lim[k]
                # A short range below zero (e.g. arm adduction into the body) is not
                # part of a main movement: those swing one way only, as an actor would.
                lo = lo if lo < -0.4 else 0.0
                swing = np.where(phase > 0, hi * phase, -lo * phase)
                angles[j][start : start + n_swing, k] = amplitude * swing
    rng = np.random.default_rng(seed)
    times = np.arange(n_frames) / rate
    yaw = rng.uniform(-np.pi, np.pi) + 0.3 * np.sin(2 * np.pi * times / (n_frames / rate))
    root_rot = rotvec_to_matrix(np.stack([0 * yaw, 0 * yaw, yaw], axis=1))
    root_trans = body.rest_translation + np.stack(
        [0.2 * np.sin(times / 3.0), 0.1 * np.cos(times / 4.0), 0 * times], axis=1
    )
    return tuple(angles), root_rot, root_trans


def with_default_pose(angles, root_rot, at: int, length: int, rng: np.random.Generator, noise_deg: float):
    """Blend a motion smoothly into a default pose around frame ``at`` and back out.

    Inside the window (``length`` frames, plus ramps of half that on each side)
    every joint angle goes to N(0, noise_deg) (an approximate default pose, as a
    person takes it) and the root keeps only its heading (the subject stands
    upright). Returns ``(angles, root_rotation, window)``, window = (start, stop).
    """
    n = angles[0].shape[0]
    f = np.arange(n)
    ramp = length // 2
    start, stop = at - length // 2, at + length // 2
    w = np.clip(np.minimum(f - (start - ramp), (stop + ramp) - f) / ramp, 0.0, 1.0)
    out = []
    for a in angles:
        target = rng.normal(0.0, np.radians(noise_deg), size=a.shape[1])
        out.append((1 - w[:, None]) * a + w[:, None] * target)
    heading = np.arctan2(root_rot[:, 1, 0], root_rot[:, 0, 0])
    upright = rotvec_to_matrix(np.stack([0 * heading, 0 * heading, heading], axis=1))
    tilt = Rotation.from_matrix(np.swapaxes(upright, 1, 2) @ root_rot).as_rotvec()
    blended = upright @ rotvec_to_matrix((1 - w[:, None]) * tilt)
    return tuple(out), blended, (start, stop)


def truth_arrays(body: synth.Body, angles, root_rot, root_trans):
    """(joint_positions, quaternions, rotations, translations) by forward kinematics."""
    rot, trans = synth.forward_kinematics(body, angles, root_rot, root_trans)
    parents = body.edges[:, 0]
    joints = np.einsum("fjik,jk->fji", rot[:, parents], body.joint_offsets[:, 0]) + trans[:, parents]
    quats = np.asarray(matrix_to_quat(rot))
    return joints, quats, rot, trans


def perturbed(body: synth.Body, rot, trans, rng: np.random.Generator, rotation_noise_deg: float):
    """IK-like noise: small random segment rotations, joints and translations kept consistent.

    Every segment orientation is turned by an independent random rotation vector
    (N(0, rotation_noise_deg) per component); the root keeps its translation and
    the tree constraint (each joint one point seen from both segments) places the
    rest, as an inverse-kinematics fit of a rigid skeleton would.
    Returns ``(joint_positions, quaternions, rotations, translations)``.
    """
    wobble = rotvec_to_matrix(rng.normal(0.0, np.radians(rotation_noise_deg), size=rot.shape[:-1]))
    noisy_rot = wobble @ rot
    noisy_trans = trans.copy()
    for j in body.joint_order:
        parent, child = body.edges[j]
        o_parent, o_child = body.joint_offsets[j]
        noisy_trans[:, child] = noisy_rot[:, parent] @ o_parent + noisy_trans[:, parent] - noisy_rot[:, child] @ o_child
    parents = body.edges[:, 0]
    joints = np.einsum("fjik,jk->fji", noisy_rot[:, parents], body.joint_offsets[:, 0]) + noisy_trans[:, parents]
    return joints, np.asarray(matrix_to_quat(noisy_rot)), noisy_rot, noisy_trans
