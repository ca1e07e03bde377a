"""Joint centres held fixed in a segment's frame (a functional sphere fit).

Kirk et al. (2005, §3.2) give every frame its own joint position ``j_f`` and ask only
that the marker-to-joint distances stay constant. A rigid segment also keeps the joint
fixed in its own frame, and the per-frame freedom can exploit what distances do not
see: four nearly coplanar markers (a pelvis: waist markers front and back) pin a point
in their plane only to second order along the plane's normal, so ``j_f`` may slide
along that normal frame by frame and absorb the motion of the other segment's markers:
a hip next to four waist markers then sits in their plane, away from the centre a
sphere fit of each thigh marker in the pelvis frame finds, and the thigh comes out long.

This module solves the paper's cost, without the distance prior, with the joint fixed in
an *anchor* segment ``A`` (either side of the joint, with at least three non-collinear
markers)::

    j_f = R_A(f)^T (c - t_A(f))          (R_A, t_A: marker-only Procrustes pose of A)
    C(c) = mean_k var_f |x_kf - j_f|     (markers k of both segments)

3 unknowns, BFGS from ``c_0``, the per-frame centres' median in A's frame. Of the two
anchors the one with the lower minimum ``C*`` is used. The minimum ``c*`` is only
trusted along the directions the data localise it in. A short arc (a joint barely
exercised, a hinge turning about one axis) leaves a valley along which the cost falls
slowly for metres, and soft-tissue artefact, which repeats with the joint angle, tilts
that valley the same way in every part of the recording, so neither the size of the
cost drop nor a split-half test exposes it. The *resolution* along an eigenvector
``v_k`` of the Hessian ``H`` at ``c*`` (eigenvalue ``lambda_k``),

    r_k = sqrt(2 C* / lambda_k),

is the distance over which the quadratic model raises the cost by the whole remaining
``C*``. The centre moves by ``m_k = v_k . (c* - c_0)`` along ``v_k`` only where
``|m_k| >= r_k``: where the fit separates the two positions by more than its own
misfit. Elsewhere it keeps the per-frame estimate.

The resolution test trusts the misfit ``C*`` to measure what the valley's tilt could be
made of. When the two segments hardly turn relative to each other that fails: ``C*`` is
then marker noise, while a few millimetres of skin sway (or a "segment" that is not
rigid) tilts an almost flat cost, and its minimum lands decimetres away with ``|m_k|``
several ``r_k``. So a joint is refitted only where it is *exercised*: the other
segment's markers, seen in the anchor's frame, sweep an RMS angle about ``c_0`` (median
over markers of ``rms_f |y_kf - mean_f y_k| / median_f |y_kf - c_0|``; the smaller of
the two anchors' readings, as a wobbling non-rigid anchor inflates it) of at least
``MIN_EXERCISE_DEG``. A 2 degree sweep moves a marker 30 cm from the joint by 10 mm,
the size of soft-tissue artefact; below it the skin, not the joint, shapes the cost.
Static trials sweep less than that, the joints of moving takes more.

The measurements behind this (per-frame and anchored hips on a real recording, a static
trial's drift, the sweeps of static and moving takes, examples of the resolution test)
are in docs/bench/evidence_from_docstrings.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._math.padding import bucket_size
from .._math.procrustes import align_to_reference, closed_form_align, procrustes
from .._runtime import program_cache as _program_cache
from .._runtime.backend import uses_cpu
from .._runtime.precision import float64_scope

__all__ = ["AnchoredCentres", "anchored_centres"]

#: One alignment pass of every frame to a fixed reference, compiled once per shape.
_align = jax.jit(align_to_reference)

#: Rows of (frame, segment) clouds, each aligned to its own segment's reference.
_align_rows = jax.jit(jax.vmap(closed_form_align))

#: At most this many frames enter the generalised Procrustes of the segment poses (the
#: pose check's, :mod:`jaxskel.joints._pose_check`, too) and each joint's fit.
MAX_FRAMES = 2000

#: The anchored refit poses the (segment, frame) rows its fits read in blocks of this many.
POSE_ROWS = 8192

#: A move along a Hessian eigenvector is kept where it is at least this many
#: resolutions long (module docstring).
MIN_RESOLUTIONS = 1.0

#: A joint is refitted only where the other segment's markers sweep at least this RMS
#: angle (degrees) about it in the anchor's frame (module docstring).
MIN_EXERCISE_DEG = 2.0


@dataclasses.dataclass(frozen=True, eq=False)
class AnchoredCentres:
    """Joint centres after the fixed-in-a-segment refit.

    Attributes
    ----------
    joint_positions
        (F, J, 3) centres per frame: the anchored ones for moved joints (NaN where the
        anchor has no pose), the input elsewhere.
    anchor
        (J,) segment each joint was fitted in (-1: neither segment has three markers).
    moved
        (J,) True where the anchored centre replaced the per-frame one.
    shift
        (J,) metres the centre moved (0 where it did not).
    exercise
        (J,) degrees the other segment's markers sweep about the centre in the anchor's
        frame (RMS, median over markers); below ``MIN_EXERCISE_DEG`` nothing moves. NaN:
        no anchor.
    displacement, resolution
        (J, 3) ``m_k`` and ``r_k`` (metres) along the Hessian's eigenvectors, weakest
        first; a direction moved where ``|m_k| >= MIN_RESOLUTIONS r_k``. NaN: no anchor.
    bone_cosines
        (J, J, 3) ``|v_k . u|``: how much of eigenvector ``k`` of joint ``j``'s fit (same
        order as ``resolution``) lies along the bone ``u`` from joint ``j`` to joint ``i``
        on a segment they share (median over the anchor's posed frames, returned centres);
        NaN where ``j`` has no anchor or ``i`` shares no segment with it. Row ``j``, column
        ``i``. :mod:`jaxskel.joints._determination` turns it into bone-length uncertainties.
    radial_cosines
        (J, 3) how much of each eigenvector (same order as ``resolution``) points from
        the returned centre to the other segment's markers: ``|v_k . u_m|``, RMS over
        those markers ``m`` (their median positions in the anchor's frame). Near 1, the
        direction is the markers' distance from the centre, which a short arc leaves
        loose; near 0, it runs across them, as the axis of a motion about one axis does.
        NaN where ``j`` has no anchor.
    cost_per_frame, cost
        (J,) the fixed-centre cost ``C`` (m^2) at the per-frame centres' median and at
        the minimum.
    steps, result
        (J,) BFGS steps and ``optimistix.RESULTS`` code (0: converged) of the fit.
    """

    joint_positions: Float[np.ndarray, "F J 3"]
    anchor: Int[np.ndarray, " J"]
    moved: Bool[np.ndarray, " J"]
    shift: Float[np.ndarray, " J"]
    exercise: Float[np.ndarray, " J"]
    displacement: Float[np.ndarray, "J 3"]
    resolution: Float[np.ndarray, "J 3"]
    cost_per_frame: Float[np.ndarray, " J"]
    cost: Float[np.ndarray, " J"]
    steps: Int[np.ndarray, " J"]
    result: Int[np.ndarray, " J"]
    bone_cosines: Float[np.ndarray, "J J 3"]
    radial_cosines: Float[np.ndarray, "J 3"]


@dataclasses.dataclass(frozen=True, eq=False)
class _Clouds:
    """Each segment's mean marker cloud, what poses a frame against it.

    ``index`` (S, P): the markers of each segment (-1: padding); ``ref`` (S, P, 3) the
    mean clouds of the generalised Procrustes, ``ref_weight`` (S, P) 1 where a point of
    it exists; ``framed`` (S,): the segment has a frame at all (three or more markers,
    three frames that see them all, a cloud that is not (nearly) collinear)."""

    index: Int[np.ndarray, "S P"]
    ref: Float[np.ndarray, "S P 3"]
    ref_weight: Float[np.ndarray, "S P"]
    framed: Bool[np.ndarray, " S"]


def _gather(
    x: np.ndarray, mask: np.ndarray, index: np.ndarray, frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The clouds ``(Fb, S, P, 3)`` and their weights ``(Fb, S, P)`` of ``frames``, padded
    to a bucket of frames (weight 0) so that recordings share compiles."""
    padded = np.concatenate([frames, np.zeros(bucket_size(frames.size) - frames.size, int)])
    real = np.arange(padded.size) < frames.size
    seen = mask[padded][:, np.maximum(index, 0)] & (index >= 0)[None] & real[:, None, None]
    return np.where(seen[..., None], x[padded][:, np.maximum(index, 0)], 0.0), seen.astype(float)


def _mean_clouds(x: np.ndarray, mask: np.ndarray, seg: np.ndarray, n_seg: int, max_frames: int) -> _Clouds:
    """The rigid stage's generalised Procrustes (passes until the mean cloud settles, at
    most eight) on at most ``max_frames`` evenly spaced frames."""
    n_frames = x.shape[0]
    members = [np.flatnonzero(seg == s) for s in range(n_seg)]
    index = np.full((n_seg, max(max((m.size for m in members), default=1), 1)), -1)
    for s, m in enumerate(members):
        index[s, : m.size] = m
    sub_frames = np.unique(np.linspace(0, n_frames - 1, min(max_frames, n_frames)).astype(int))
    sub_pts, sub_w = _gather(x, mask, index, sub_frames)
    first = np.argmax(sub_w.sum(axis=-1), axis=0)  # per segment: best-covered frame
    ref = np.asarray(
        _program_cache.call(
            procrustes, sub_pts, sub_w, sub_pts[first, np.arange(n_seg)], sub_w[first, np.arange(n_seg)]
        )[0]
    )
    framed = np.zeros(n_seg, bool)
    for s, m in enumerate(members):
        if m.size >= 3 and mask[:, m].all(axis=1).sum() >= 3:
            sv = np.linalg.svd(ref[s, : m.size] - ref[s, : m.size].mean(axis=0), compute_uv=False)
            framed[s] = sv[1] > 1e-3 * max(sv[0], 1e-12)
    return _Clouds(index=index, ref=ref, ref_weight=(sub_w.sum(axis=0) > 0).astype(float), framed=framed)


def _posed(clouds: _Clouds, mask: np.ndarray) -> Bool[np.ndarray, "F S"]:
    """(F, S): the frame sees three of the segment's markers and the segment has a frame."""
    seen = mask[:, np.maximum(clouds.index, 0)] & (clouds.index >= 0)[None]
    return (seen.sum(axis=-1) >= 3) & clouds.framed[None]


def _pose_frames(
    clouds: _Clouds, x: np.ndarray, mask: np.ndarray, frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (F, S, 3, 3) and ``t`` (F, S, 3) of ``frames`` (F indices), ``R x + t``
    mapping a frame's markers onto the mean clouds: every frame aligned on its own, in
    one pass."""
    pts, weights = _gather(x, mask, clouds.index, np.asarray(frames, dtype=int))
    rot, t = (np.asarray(a) for a in _program_cache.call(_align, pts, weights, clouds.ref, clouds.ref_weight))
    return rot[: len(frames)], t[: len(frames)]


def _segment_poses(
    x: np.ndarray, mask: np.ndarray, seg: np.ndarray, n_seg: int, max_frames: int, frames: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker-only poses of every segment in every frame (or only in ``frames``).

    The mean cloud of each segment comes from :func:`_mean_clouds`; every frame is then
    aligned to it once, in one pass (timing: docs/bench/evidence_from_docstrings.md).
    Frames are padded to bucket sizes so trials share compiles.

    Returns ``R`` (F, S, 3, 3) and ``t`` (F, S, 3), ``R x + t`` mapping a frame's markers
    onto their mean cloud, and ``posed`` (F, S) (:func:`_posed`). With ``frames``
    (indices), F is ``len(frames)``: the mean clouds and which segments have a frame are
    still the whole recording's, and each frame's alignment is its own, so these rows are
    the whole recording's rows ``frames``.
    """
    clouds = _mean_clouds(x, mask, seg, n_seg, max_frames)
    posed_frames = np.arange(x.shape[0]) if frames is None else np.asarray(frames, dtype=int)
    rot, t = _pose_frames(clouds, x, mask, posed_frames)
    return rot, t, _posed(clouds, mask[posed_frames])


def _pose_rows(
    clouds: _Clouds, x: np.ndarray, mask: np.ndarray, segments: np.ndarray, frames: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (N, 3, 3) and ``t`` (N, 3) of segment ``segments[n]`` in frame ``frames[n]``:
    the rows of :func:`_pose_frames`, only those asked for, in blocks of ``POSE_ROWS``
    (one compiled shape for every recording)."""
    n = segments.size
    pad = -n % POSE_ROWS
    segments, frames = np.concatenate([segments, np.zeros(pad, int)]), np.concatenate([frames, np.zeros(pad, int)])
    index = clouds.index[segments]  # (N, P)
    seen = mask[frames[:, None], np.maximum(index, 0)] & (index >= 0) & (np.arange(n + pad) < n)[:, None]
    pts = np.where(seen[..., None], x[frames[:, None], np.maximum(index, 0)], 0.0)
    weights, ref = seen * clouds.ref_weight[segments], clouds.ref[segments]
    block = [slice(lo, lo + POSE_ROWS) for lo in range(0, n + pad, POSE_ROWS)]
    blocks = [_program_cache.call(_align_rows, pts[b], ref[b], weights[b]) for b in block]
    return (np.concatenate([np.asarray(b[k]) for b in blocks])[:n] for k in range(2))


class _PoseRows:
    """The poses asked for so far, each (segment, frame) posed once, in as few passes as
    there are requests: rows of :func:`_segment_poses` on the whole recording (the same
    mean clouds, each frame aligned on its own)."""

    def __init__(self, clouds: _Clouds, x: np.ndarray, mask: np.ndarray) -> None:
        self._clouds, self._x, self._mask = clouds, x, mask
        self._keys = np.zeros(0, np.int64)  # segment * F + frame, sorted
        self._rot, self._t = np.zeros((0, 3, 3)), np.zeros((0, 3))

    def _key(self, segment: int | np.ndarray, frames: np.ndarray) -> np.ndarray:
        return np.asarray(segment, np.int64) * self._x.shape[0] + np.asarray(frames, np.int64)

    def need(self, requests: list[tuple[int, np.ndarray]]) -> None:
        """Pose ``(segment, frames)`` of every request not posed yet, in one pass."""
        if not requests:
            return
        keys = np.unique(np.concatenate([self._key(s, f) for s, f in requests]))
        missing = keys[~np.isin(keys, self._keys)]
        if missing.size:
            rot, t = _pose_rows(self._clouds, self._x, self._mask, missing // self._x.shape[0],
                                missing % self._x.shape[0])
            order = np.argsort(np.concatenate([self._keys, missing]), kind="stable")
            self._keys = np.concatenate([self._keys, missing])[order]
            self._rot, self._t = np.concatenate([self._rot, rot])[order], np.concatenate([self._t, t])[order]

    def take(self, frames: np.ndarray, segment: int) -> tuple[np.ndarray, np.ndarray]:
        """``R`` (F, 3, 3), ``t`` (F, 3) of ``segment`` on ``frames`` (posed first if needed)."""
        keys = self._key(segment, frames)
        row = np.searchsorted(self._keys, keys)
        if not np.array_equal(self._keys[np.minimum(row, max(self._keys.size - 1, 0))], keys):
            self.need([(segment, frames)])
            row = np.searchsorted(self._keys, keys)
        return self._rot[row], self._t[row]


def _sweep_deg(
    x: Float[np.ndarray, "F K 3"], mask: Bool[np.ndarray, "F K"], rot: Float[np.ndarray, "F 3 3"],
    t: Float[np.ndarray, "F 3"], centre: Float[np.ndarray, " 3"],
) -> float:
    """RMS angle (degrees) markers ``x`` sweep about ``centre`` in the frame ``R x + t``:
    per marker seen in ten or more frames ``rms_f |y_f - mean y| / median_f |y_f - centre|``,
    the median over markers (NaN: none seen that often)."""
    y = np.einsum("fij,fkj->fki", rot, x) + t[:, None]
    angles = []
    for k in range(y.shape[1]):
        yk = y[mask[:, k], k]
        if len(yk) >= 10:
            radius = np.median(np.linalg.norm(yk - centre, axis=1))
            spread = np.sqrt(np.mean(np.sum((yk - yk.mean(axis=0)) ** 2, axis=1)))
            angles.append(np.degrees(spread / max(radius, 1e-9)))
    return float(np.median(angles)) if angles else float("nan")


def _variance_cost(c: Float[Array, " 3"], y: Float[Array, "3 F K"], w: Float[Array, "F K"]) -> Float[Array, ""]:
    """``mean_k var_f |y_kf - c|`` over the markers seen in two or more frames, with the
    markers ``y_kf = R_f x_kf + t_f`` in the anchor's frame (three coordinate planes): the
    same distances as ``|x_kf - R_f^T (c - t_f)|``, the centre carried into the world."""
    d = jnp.sqrt((y[0] - c[0]) ** 2 + (y[1] - c[1]) ** 2 + (y[2] - c[2]) ** 2 + 1e-18)
    n = jnp.maximum(jnp.sum(w, axis=0), 1.0)
    mean = jnp.sum(w * d, axis=0) / n
    var = jnp.sum(w * (d - mean) ** 2, axis=0) / n
    used = jnp.sum(w, axis=0) > 1
    return jnp.sum(jnp.where(used, var, 0.0)) / jnp.maximum(jnp.sum(used), 1)


@jax.jit
def _solve(
    c0: Float[Array, "B 3"], y: Float[Array, "B 3 F K"], w: Float[Array, "B F K"]
) -> tuple[Float[Array, "B 3"], Float[Array, " B"], Float[Array, " B"], Int[Array, " B"], Int[Array, " B"],
           Float[Array, "B 3"], Float[Array, "B 3 3"]]:
    """:func:`_variance_cost` minimised by BFGS, vmapped over (joint, anchor).

    Returns the minimum ``c*``, ``C(c_0)``, ``C(c*)``, steps, result code and the
    eigenvalues (ascending) and eigenvectors (columns) of the Hessian at ``c*``.
    """

    def one(c0, y, w):
        def cost(c, args):
            return _variance_cost(c, *args)

        args = (y, w)
        sol = optx.minimise(cost, optx.BFGS(rtol=1e-10, atol=1e-12), c0, args=args, max_steps=300, throw=False)
        lam, vec = jnp.linalg.eigh(jax.hessian(cost)(sol.value, args))
        return (sol.value, cost(c0, args), cost(sol.value, args), sol.stats["num_steps"], sol.result._value,
                lam, vec)

    return jax.vmap(one)(c0, y, w)


def _solve_all(problems: list[tuple[np.ndarray, ...]], one_per_call: bool | None = None) -> tuple[np.ndarray, ...]:
    """:func:`_solve` over all (joint, anchor) problems (same padded shapes), numpy out.

    A vmapped while loop runs until its slowest member stops, and each of its steps
    costs as much for a finished problem as for a running one. The steps differ widely
    (a barely exercised joint takes several times the steps of the others), so on a
    CPU, where one problem's frames already fill the cores, each problem is its own call
    and pays only its own steps (the same centres up to rounding; timings:
    docs/bench/evidence_from_docstrings.md); on an accelerator, which needs the width,
    they go in one call, padded to a bucket. ``one_per_call``: force either way
    (``None``: by the default device, as the tree joints of :mod:`jaxskel.joints._topology`).
    """
    if one_per_call is None:
        one_per_call = uses_cpu(None)
    if one_per_call:
        outs = [_program_cache.call(_solve, *(a[None] for a in p)) for p in problems]
        return tuple(np.concatenate([np.asarray(o[k]) for o in outs]) for k in range(len(outs[0])))
    # padding problems: all weights 0, so a zero cost that BFGS leaves at once
    empty = problems[0][:2] + (np.zeros_like(problems[0][2]),)
    padded = problems + [empty] * (bucket_size(len(problems), minimum=8) - len(problems))
    out = _program_cache.call(_solve, *(np.stack(p) for p in zip(*padded)))
    return tuple(np.asarray(v)[: len(problems)] for v in out)


@float64_scope
def anchored_centres(
    x: Float[np.ndarray, "F M 3"],
    mask: Bool[np.ndarray, "F M"],
    marker_segment: Int[np.ndarray, " M"],
    edges: Int[np.ndarray, "J 2"],
    joint_positions: Float[np.ndarray, "F J 3"],
    *,
    max_frames: int = MAX_FRAMES,
    min_resolutions: float = MIN_RESOLUTIONS,
    min_exercise_deg: float = MIN_EXERCISE_DEG,
) -> AnchoredCentres:
    """Refit each joint with its centre fixed in one segment's frame (module docstring).

    ``joint_positions`` are the per-frame centres of :func:`jaxskel.joints.fit_topology` (the
    starting point, and what is kept along directions the refit does not resolve). At
    most ``max_frames`` posed frames, evenly spaced, enter each fit.
    """
    x = np.asarray(x, float)
    mask = np.asarray(mask, bool)
    seg = np.asarray(marker_segment)
    edges = np.asarray(edges)
    jp = np.asarray(joint_positions, float)
    n_frames, n_joints = jp.shape[0], edges.shape[0]
    n_seg = int(max(seg.max(initial=-1), edges.max(initial=-1))) + 1
    clouds = _mean_clouds(x, mask, seg, n_seg, max_frames)
    posed_all = _posed(clouds, mask)
    poses = _PoseRows(clouds, x, mask)

    # One problem per (joint, anchor): evenly spaced posed frames, padded to bucket sizes
    # (frames, markers, problems) so that trials share compiled shapes.
    n_sub = min(max_frames, n_frames)
    n_pad = bucket_size(n_sub)
    width = bucket_size(max(int(((seg == a) | (seg == b)).sum()) for a, b in edges) if n_joints else 1, minimum=8)
    chosen = []  # (joint, anchor, frames)
    for j, (a, b) in enumerate(edges.tolist()):
        for anchor in (a, b):
            frames = np.flatnonzero(posed_all[:, anchor] & np.isfinite(jp[:, j]).all(axis=1))
            if frames.size >= 10:
                chosen.append((j, anchor, frames[np.unique(np.linspace(0, frames.size - 1, n_sub).astype(int))]))
    poses.need([(anchor, frames) for _, anchor, frames in chosen])  # what the fits read, in one pass
    problems, keys, other_local = [], [], []
    for j, anchor, frames in chosen:
        a, b = edges[j]
        markers = np.flatnonzero((seg == a) | (seg == b))
        rot, t = poses.take(frames, anchor)
        seen = mask[np.ix_(frames, markers)]
        xs = np.where(seen[..., None], x[np.ix_(frames, markers)], 0.0)
        # the markers in the anchor's frame, as planes (3, F, K); padding (frames, markers) weighs 0
        y = np.zeros((3, n_pad, width))
        y[:, : frames.size, : markers.size] = np.einsum("fij,fkj->ifk", rot, xs) + t.T[:, :, None]
        ws = np.zeros((n_pad, width))
        ws[: frames.size, : markers.size] = seen
        local = np.einsum("fij,fj->fi", rot, jp[frames, j]) + t  # R j + t
        c0 = np.median(local, axis=0)
        other = np.flatnonzero(seg == (b if anchor == a else a))
        problems.append((c0, y, ws))
        x_other, seen_other = x[np.ix_(frames, other)], mask[np.ix_(frames, other)]
        keys.append((j, anchor, _sweep_deg(x_other, seen_other, rot, t, c0)))
        other_local.append(_median_in_frame(x_other, seen_other, rot, t))

    out = jp.copy()
    anchor_of = np.full(n_joints, -1)
    moved = np.zeros(n_joints, bool)
    shift = np.zeros(n_joints)
    exercise = np.full(n_joints, np.nan)
    displacement = np.full((n_joints, 3), np.nan)
    resolution = np.full((n_joints, 3), np.nan)
    cost_per_frame = np.full(n_joints, np.nan)
    cost = np.full(n_joints, np.nan)
    steps = np.zeros(n_joints, int)
    result = np.zeros(n_joints, int)
    radial = np.full((n_joints, 3), np.nan)
    if problems:
        c0 = np.stack([p[0] for p in problems])
        c_min, f0, f_min, n_steps, code, lam, vec = _solve_all(problems)
        best: dict[int, int] = {}
        for i, (j, _, _) in enumerate(keys):
            if j not in best or f_min[i] < f_min[best[j]]:
                best[j] = i
        for j, i in best.items():
            anchor = keys[i][1]
            # A segment that is not rigid (skin sway on three markers) wobbles as an anchor
            # and makes the other side's markers seem to sweep: the relative motion is
            # the same seen from either side, so the smaller reading is the cleaner one.
            exercise[j] = min(sweep for jj, _, sweep in keys if jj == j)
            m = vec[i].T @ (c_min[i] - c0[i])
            r = np.sqrt(2.0 * f_min[i] / np.maximum(lam[i], 1e-30))
            keep = (lam[i] > 0) & (np.abs(m) >= min_resolutions * r)
            anchor_of[j], displacement[j], resolution[j] = anchor, m, r
            cost_per_frame[j], cost[j], steps[j], result[j] = f0[i], f_min[i], n_steps[i], code[i]
            radial[j] = _radial_cosines(other_local[i], c0[i], vec[i])
            if code[i] != 0 or not keep.any() or not exercise[j] >= min_exercise_deg:
                continue
            c = c0[i] + vec[i][:, keep] @ m[keep]
            radial[j] = _radial_cosines(other_local[i], c, vec[i])
            rot, t = poses.take(np.arange(n_frames), anchor)  # the anchor on every frame
            centre = np.einsum("fji,fj->fi", rot, c[None] - t)
            out[:, j] = np.where(posed_all[:, anchor, None], centre, np.nan)
            moved[j], shift[j] = True, float(np.linalg.norm(c - c0[i]))
        directions = {j: vec[i] for j, i in best.items()}
        bone_cosines = _bone_cosines(out, edges, anchor_of, directions, poses, posed_all, n_sub)
    else:
        bone_cosines = np.full((n_joints, n_joints, 3), np.nan)
    return AnchoredCentres(
        out, anchor_of, moved, shift, exercise, displacement, resolution, cost_per_frame, cost, steps, result,
        bone_cosines, radial,
    )


def _median_in_frame(
    x: Float[np.ndarray, "F K 3"], mask: Bool[np.ndarray, "F K"], rot: Float[np.ndarray, "F 3 3"],
    t: Float[np.ndarray, "F 3"],
) -> Float[np.ndarray, "K 3"]:
    """Each marker's median position in the frame ``R x + t`` over the frames that see it
    (NaN: never seen)."""
    y = np.einsum("fij,fkj->fki", rot, x) + t[:, None]
    out = np.full((y.shape[1], 3), np.nan)
    for k in np.flatnonzero(mask.any(axis=0)):
        out[k] = np.median(y[mask[:, k], k], axis=0)
    return out


def _radial_cosines(
    points: Float[np.ndarray, "K 3"], centre: Float[np.ndarray, " 3"], vec: Float[np.ndarray, "3 3"]
) -> Float[np.ndarray, " 3"]:
    """:attr:`AnchoredCentres.radial_cosines` of one joint: ``|v_k . u_m|`` for the
    eigenvectors ``v_k`` (columns of ``vec``) and the unit directions ``u_m`` from
    ``centre`` to ``points``, RMS over the points (NaN: none)."""
    d = points[np.isfinite(points).all(axis=1)] - centre
    if not len(d):
        return np.full(3, np.nan)
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.sqrt(np.mean((u @ vec) ** 2, axis=0))


def _bone_cosines(
    centres: Float[np.ndarray, "F J 3"],
    edges: Int[np.ndarray, "J 2"],
    anchor: Int[np.ndarray, " J"],
    directions: dict[int, Float[np.ndarray, "3 3"]],
    poses: _PoseRows,
    posed: Bool[np.ndarray, "F S"],
    n_sub: int,
) -> Float[np.ndarray, "J J 3"]:
    """:attr:`AnchoredCentres.bone_cosines`: ``|v_k . u|`` for every joint ``j``'s Hessian
    eigenvectors ``v_k`` (columns of ``directions[j]``, anchor frame) and unit bone ``u``
    to each joint sharing a segment with ``j``, in the anchor's frame (``R u``), median over
    at most ``n_sub`` evenly spaced frames where the anchor is posed and both centres exist.
    A bone on the anchor keeps one direction in its frame; one on the other segment turns
    with the joint, hence the median. The frames of all bones are posed in one pass."""
    n_joints = edges.shape[0]
    out = np.full((n_joints, n_joints, 3), np.nan)
    bones = []  # (j, i, frames, bone vectors there)
    for j in directions:
        a = int(anchor[j])
        for i in range(n_joints):
            if i == j or not set(edges[i].tolist()) & set(edges[j].tolist()):
                continue
            bone = centres[:, i] - centres[:, j]
            frames = np.flatnonzero(posed[:, a] & np.isfinite(bone).all(axis=1))
            if frames.size:
                frames = frames[np.unique(np.linspace(0, frames.size - 1, min(n_sub, frames.size)).astype(int))]
                bones.append((j, i, frames, bone[frames]))
    poses.need([(int(anchor[j]), frames) for j, _, frames, _ in bones])
    for j, i, frames, bone in bones:
        rot, _ = poses.take(frames, int(anchor[j]))
        local = np.einsum("fab,fb->fa", rot, bone)
        length = np.linalg.norm(local, axis=1, keepdims=True)
        unit = local / np.maximum(length, 1e-12)
        out[j, i] = np.median(np.abs(unit @ directions[j]), axis=0)
    return out
