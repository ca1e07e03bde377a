"""Reference inverse kinematics in numpy/scipy: one ``least_squares`` call per frame.

Unknowns per frame: the root position and a world-frame rotation vector per segment,
``R_s = exp([w_s]x) R0_s`` about the start ``R0`` (the previous frame's solution, or
for the first frame and after a failure a per-segment Kabsch fit). Every other
segment translation follows from the joints: ``t_c = t_p + R_p o_j0 - R_c o_j1``,
written with the root-to-segment path matrix so a pose is a few einsums. Residuals:
predicted minus observed markers (present ones), plus ``lambda w_s`` (a 1 mm/rad
prior that only decides what markers leave free, like jaxskel's pose prior; it pulls
towards the previous frame, which also fills gaps). The Jacobian is analytic
(``-[L]x J_l(w)`` with ``L`` the lever from the segment's proximal joint to the point
where the marker hangs on it), solved by MINPACK Levenberg-Marquardt
(``method="lm"``).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .rigid import RefSkeleton, kabsch

__all__ = ["inverse_kinematics", "forward_kinematics"]

PRIOR_WEIGHT = 1e-3  # metres per radian


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _expmap(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices exp([w]x) (..., 3, 3) and left Jacobians J_l(w) (..., 3, 3)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _skew(w)
    k2 = k @ k
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(t) / t)
    b = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    c = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    eye = np.eye(3)
    return eye + a * k + b * k2, eye + b * k + c * k2


class _Model:
    def __init__(self, sk: RefSkeleton):
        self.edges = sk.edges
        n_seg, n_j = sk.n_segments, len(sk.edges)
        self.n_seg = n_seg
        parent = np.full(n_seg, -1)
        parent[sk.edges[:, 1]] = sk.edges[:, 0]
        # path[s, j] = 1 if joint j lies between the root and segment s
        path = np.zeros((n_seg, n_j))
        child_joint = {int(c): j for j, (_, c) in enumerate(sk.edges)}
        for s in range(n_seg):
            u = s
            while parent[u] >= 0:
                path[s, child_joint[u]] = 1.0
                u = parent[u]
        self.path = path
        self.used = np.flatnonzero((sk.marker_segment >= 0) & np.isfinite(sk.marker_offsets).all(1))
        self.mseg = sk.marker_segment[self.used]
        self.moff = sk.marker_offsets[self.used]
        self.joff = sk.joint_offsets
        self.pm = path[self.mseg]  # (M, J)
        self.at_parent = (sk.edges[:, 0][:, None] == np.arange(n_seg)).astype(float)  # (J, S)
        self.at_child = (sk.edges[:, 1][:, None] == np.arange(n_seg)).astype(float)
        self.own = (self.mseg[:, None] == np.arange(n_seg)).astype(float)  # (M, S)

    def pose(self, t_root: np.ndarray, rot: np.ndarray):
        e = self.edges
        d = np.einsum("jab,jb->ja", rot[e[:, 0]], self.joff[:, 0]) - np.einsum("jab,jb->ja", rot[e[:, 1]], self.joff[:, 1])
        trans = t_root + self.path @ d
        markers = np.einsum("mab,mb->ma", rot[self.mseg], self.moff) + trans[self.mseg]
        joints = np.einsum("jab,jb->ja", rot[e[:, 0]], self.joff[:, 0]) + trans[e[:, 0]]
        return trans, markers, joints

    def levers(self, rot: np.ndarray) -> np.ndarray:
        """L (M, S, 3): d marker_m / d w_a = -[L_ma]x J_l(w_a)."""
        e = self.edges
        own = self.own[..., None] * np.einsum("mab,mb->ma", rot[self.mseg], self.moff)[:, None]
        jp = np.einsum("jab,jb->ja", rot[e[:, 0]], self.joff[:, 0])
        jc = np.einsum("jab,jb->ja", rot[e[:, 1]], self.joff[:, 1])
        via = np.einsum("mj,js,jx->msx", self.pm, self.at_parent, jp) - np.einsum("mj,js,jx->msx", self.pm, self.at_child, jc)
        return own + via


def _start(model: _Model, xf: np.ndarray, mf: np.ndarray, prev: np.ndarray | None) -> np.ndarray:
    """Per-segment Kabsch rotations where >= 3 markers are seen; else the parent's (or ``prev``)."""
    rot = np.tile(np.eye(3), (model.n_seg, 1, 1)) if prev is None else prev.copy()
    for s in range(model.n_seg):
        sel = (model.mseg == s) & mf
        if sel.sum() >= 3:
            rot[s] = kabsch(model.moff[sel], xf[sel], np.ones(sel.sum()))[0]
    return rot


def inverse_kinematics(
    sk: RefSkeleton, x: np.ndarray, mask: np.ndarray, *, prior_weight: float = PRIOR_WEIGHT
) -> dict[str, np.ndarray]:
    """Pose ``sk`` in every frame of ``x`` (F, M, 3) / ``mask`` (F, M), frame by frame in order."""
    model = _Model(sk)
    n_seg = model.n_seg
    xs, ms = x[:, model.used], mask[:, model.used]
    n_frames = x.shape[0]
    roots = np.zeros((n_frames, 3))
    rots = np.zeros((n_frames, n_seg, 3, 3))
    joints = np.zeros((n_frames, len(sk.edges), 3))
    rms = np.zeros(n_frames)
    nfev = np.zeros(n_frames, int)
    prev_rot, prev_t, typical = None, None, None
    for f in range(n_frames):
        xf, mf = xs[f], ms[f]
        if not mf.any():
            roots[f], rots[f], rms[f] = prev_t if prev_t is not None else 0.0, prev_rot if prev_rot is not None else np.eye(3), np.nan
            joints[f] = model.pose(roots[f], rots[f])[2]
            continue
        if prev_rot is None:
            r0 = _start(model, xf, mf, None)
        else:
            r0 = prev_rot
        obs = xf[mf]

        def fk(y):
            r_inc, jl = _expmap(y[3:].reshape(n_seg, 3))
            rot = r_inc @ r0
            return rot, jl, model.pose(y[:3], rot)

        def residuals(y):
            _, _, (_, pred, _) = fk(y)
            return np.concatenate([(pred[mf] - obs).ravel(), prior_weight * y[3:]])

        def jacobian(y):
            rot, jl, _ = fk(y)
            lev = model.levers(rot)[mf]  # (Mp, S, 3)
            blocks = -np.einsum("msab,sbc->msac", _skew(lev), jl)  # (Mp, S, 3, 3)
            n_obs = lev.shape[0]
            jac = np.zeros((3 * n_obs + 3 * n_seg, 3 + 3 * n_seg))
            jac[: 3 * n_obs, :3] = np.tile(np.eye(3), (n_obs, 1))
            jac[: 3 * n_obs, 3:] = blocks.transpose(0, 2, 1, 3).reshape(3 * n_obs, 3 * n_seg)
            jac[3 * n_obs :, 3:] = prior_weight * np.eye(3 * n_seg)
            return jac

        # root start: the translation that fits the markers best with the start rotations
        _, pred0, _ = model.pose(np.zeros(3), r0)
        t0 = (obs - pred0[mf]).mean(0)
        y0 = np.concatenate([t0, np.zeros(3 * n_seg)])
        n_res = 3 * int(mf.sum()) + 3 * n_seg
        method = "lm" if n_res >= y0.size else "trf"
        sol = least_squares(residuals, y0, jac=jacobian, method=method, xtol=1e-10, ftol=1e-10)
        rot, _, (_, pred, jts) = fk(sol.x)
        err = np.sqrt(np.mean(np.sum((pred[mf] - obs) ** 2, 1)))
        if typical is not None and err > 3 * typical and prev_rot is not None:
            # stuck after a fast move or a gap: restart from a fresh per-segment fit
            r0 = _start(model, xf, mf, prev_rot)
            _, pred0, _ = model.pose(np.zeros(3), r0)
            y0 = np.concatenate([(obs - pred0[mf]).mean(0), np.zeros(3 * n_seg)])
            again = least_squares(residuals, y0, jac=jacobian, method=method, xtol=1e-10, ftol=1e-10)
            rot2, _, (_, pred2, jts2) = fk(again.x)
            err2 = np.sqrt(np.mean(np.sum((pred2[mf] - obs) ** 2, 1)))
            nfev[f] += again.nfev
            if err2 < err:
                sol, rot, pred, jts, err = again, rot2, pred2, jts2, err2
        typical = err if typical is None else 0.9 * typical + 0.1 * err
        roots[f], rots[f], joints[f], rms[f] = sol.x[:3], rot, jts, err
        nfev[f] += sol.nfev
        prev_rot, prev_t = rot, sol.x[:3]
    return {"root": roots, "rotations": rots, "joints": joints, "marker_rms": rms, "nfev": nfev}


def forward_kinematics(sk: RefSkeleton, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(markers (F, M_used, 3), joints (F, J, 3)) of poses."""
    model = _Model(sk)
    out = [model.pose(t, r) for t, r in zip(root, rotations)]
    return np.stack([o[1] for o in out]), np.stack([o[2] for o in out])
