"""Synthetic recordings for the SD06 stages with exactly known joint angles.

:func:`protocol_and_free` is what a real session looks like: the paper's
calibration protocol (default pose, then every main movement alone, from
``calibration_motions.main_movements``) followed by free movement in which every
degree of freedom moves at once (``synth``'s "calibration" motion), blended in
over one second. :func:`reference_angles` is an independent NumPy/SciPy
implementation of the SD06 angle model evaluated with the TRUE axes and the
TRUE rest pose (all generator angles 0), so estimated angles can be compared
with what the generator did.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from calibration_motions import main_movements, perturbed, rotvec_to_matrix, truth_arrays
from scipy.spatial.transform import Rotation

from jaxskel import synth


def protocol_and_free(
    body: synth.Body,
    *,
    rate: float = 30.0,
    free_seconds: float = 20.0,
    seed: int = 0,
    noise_deg: float = 0.0,
    free_amount: float = 1.0,
):
    """Protocol (main movements) then ``free_seconds`` of free movement.

    Returns a namespace with ``angles`` (J arrays (F, k)), ``joints``, ``quats``,
    ``rot``, ``trans`` and ``protocol`` = (start, stop) frames of the protocol.
    """
    p_angles, p_root, _ = main_movements(body, rate=rate, seed=seed)
    n_p = p_angles[0].shape[0]
    _, free = synth.simulate(
        body, "calibration", duration=free_seconds, rate=rate, seed=seed + 100,
        joint_range={n: free_amount for n in body.joint_names},
    )
    n_f = free.joint_angles[0].shape[0]
    ramp = np.clip(np.arange(n_f) / rate, 0.0, 1.0)[:, None]
    angles = tuple(np.concatenate([a, ramp * f]) for a, f in zip(p_angles, free.joint_angles, strict=True))
    # Root: keep turning slowly about the vertical and drifting after the protocol.
    n = n_p + n_f
    t = np.arange(n) / rate
    yaw0 = np.arctan2(p_root[0, 1, 0], p_root[0, 0, 0])
    yaw = yaw0 + 0.3 * np.sin(2 * np.pi * t / (n / rate))
    root_rot = rotvec_to_matrix(np.stack([0 * yaw, 0 * yaw, yaw], axis=1))
    root_trans = body.rest_translation + np.stack([0.2 * np.sin(t / 3.0), 0.1 * np.cos(t / 4.0), 0 * t], axis=1)
    joints, quats, rot, trans = truth_arrays(body, angles, root_rot, root_trans)
    if noise_deg:
        joints, quats, rot, trans = perturbed(body, rot, trans, np.random.default_rng(seed), noise_deg)
    return SimpleNamespace(angles=angles, joints=joints, quats=quats, rot=rot, trans=trans, protocol=(0, n_p), rate=rate)


def _rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(angle)[:, None] * axis[None]).as_matrix()


def _angle_about(a, u, v):
    au, av = u @ a, v @ a
    return np.arctan2(np.cross(u, v) @ a, np.sum(u * v, -1) - au * av)


def reference_angles(
    rel: np.ndarray, first: np.ndarray, second: np.ndarray | None, rest_rel: np.ndarray, main: np.ndarray,
    start: int = 0,
):
    """SD06 angles ``(alpha, beta, tau)`` of relative rotations (NumPy/SciPy; the branch by a plain loop).

    ``rel`` (F, 3, 3) relative limb rotations ``Q(f)``, ``first`` the axis that
    moves with the child (acts first), ``second`` the parent-fixed axis (None:
    one axis), ``rest_rel`` the rest rotation, ``main`` the child's long axis in
    its limb frame. Swing ``S = R_second(beta) R_first(alpha)`` takes the rest
    direction ``r`` to the sample ``p``; of the two circle intersections the one
    whose angles are nearest the previous frame's (plus 0.1 times their squared
    size: near the rest pose where continuity cannot tell) is kept, walking
    from frame ``start`` (the rest pose, angles 0) forward and then backward; the
    twist is the angle about ``d = S r`` of ``Q (S Q_rest)^T``. Vectorised over
    frames but for the walk, a scalar loop (also ``bench/sd06_speed.py``'s reference).
    """
    r = rest_rel @ main
    p = rel @ main
    n = len(rel)
    if second is None:
        alpha = _angle_about(first, r, p)
        beta = np.zeros(n)
        swing = _rot(first, alpha)
    else:
        a, b = first, second
        c = a @ b
        h1, h2 = a @ r, p @ b
        x0 = ((h1 - c * h2)[:, None] * a + (h2 - c * h1)[:, None] * b) / (1 - c * c)
        line = np.cross(a, b) / np.linalg.norm(np.cross(a, b))
        t = np.sqrt(np.maximum(1 - np.sum(x0 * x0, -1), 0.0))[:, None]
        cands = []
        for x in (x0 + t * line, x0 - t * line):
            x = x / np.linalg.norm(x, axis=-1, keepdims=True)
            cands.append(np.stack([_angle_about(a, r, x), _angle_about(b, x, p)], -1))
        cands = np.stack(cands, 1).tolist()  # (F, 2 candidates, 2 angles) as Python floats for the walk
        out = np.zeros((n, 2))
        for frames in (range(start, n), range(start - 1, -1, -1)):
            prev_a = prev_b = 0.0
            for f in frames:
                best, least = None, math.inf
                for ca, cb in cands[f]:
                    da, db = math.remainder(ca - prev_a, math.tau), math.remainder(cb - prev_b, math.tau)
                    cost = da * da + db * db + 0.1 * (ca * ca + cb * cb)
                    if cost < least:
                        best, least = (ca, cb), cost
                prev_a, prev_b = out[f] = best
        alpha, beta = out[:, 0], out[:, 1]
        swing = _rot(b, beta) @ _rot(a, alpha)
    d = swing @ r
    m = rel @ np.swapaxes(swing @ rest_rel, -1, -2)
    q = Rotation.from_matrix(m).as_quat()  # x, y, z, w
    q = np.where(q[:, 3:] < 0, -q, q)
    tau = 2 * np.arctan2(np.sum(q[:, :3] * d, -1), q[:, 3])
    return np.stack([alpha, beta, tau], axis=1)


def true_axes_in_limb(body: synth.Body, norm, j: int) -> np.ndarray:
    """Generator axes of joint j in the parent limb frame (rows)."""
    return body.joint_axes[j] @ norm.limb_frames_local[body.edges[j, 0]]


def compare(param, rec, body: synth.Body):
    """Per joint: axis errors (deg) and RMS angle errors (deg) against the true-axis reference.

    The reference uses the estimate's own relative rotations (so only the model
    matters), the generator's axes (matched to the estimate's by |cos|, with the
    estimate's order and signs) and the generator's rest pose. Returns a dict
    with arrays ``axis_err`` (J,), ``angle_rms`` (J, 3), ``default`` (J, 3) the
    angles at the default-pose frame.
    """
    norm = param.normalization
    e = body.edges
    L = norm.limb_frames
    rel = np.einsum("fji,fjk->fik", L[:, e[:, 0]].reshape(-1, 3, 3), L[:, e[:, 1]].reshape(-1, 3, 3)).reshape(
        L.shape[0], len(e), 3, 3
    )
    main = np.eye(3)[norm.main_axis] * norm.main_sign[:, None]
    frames_local = norm.limb_frames_local
    n_j = len(e)
    axis_err = np.zeros(n_j)
    angle_rms = np.zeros((n_j, 3))
    for j in range(n_j):
        true = true_axes_in_limb(body, norm, j)
        k = param.n_axes[j]
        est = param.axes[j, :k]
        # Match each estimated axis to a distinct true swing axis.
        cos = np.abs(est @ true[: max(k, min(2, len(true)))].T)
        order = [int(np.argmax(cos[0]))] if k == 1 else ([0, 1] if cos[0, 0] + cos[1, 1] >= cos[0, 1] + cos[1, 0] else [1, 0])
        matched = true[order]
        signs = np.sign(np.sum(est * matched, -1))
        axis_err[j] = np.degrees(np.arccos(np.clip(np.abs(np.sum(est * matched, -1)), -1, 1))).max()
        ref_axes = signs[:, None] * matched
        # True rest: generator angles 0, where the child segment is parallel to the parent.
        rest_rel = frames_local[e[j, 0]].T @ frames_local[e[j, 1]]
        ref = reference_angles(rel[:, j], ref_axes[0], ref_axes[1] if k == 2 else None, rest_rel, main[e[j, 1]])
        diff = np.angle(np.exp(1j * (param.angles[:, j] - ref)))
        angle_rms[j] = np.degrees(np.sqrt(np.mean(diff**2, axis=0)))
    return SimpleNamespace(axis_err=axis_err, angle_rms=angle_rms, default=np.degrees(param.angles[norm.default_frame]))
