"""Shared test helpers (no fixtures with hidden state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def partition(labels, groups) -> set[frozenset]:
    """A clustering as a set of label sets (independent of cluster numbering)."""
    out: dict[int, set] = {}
    for lab, g in zip(labels, groups):
        if g >= 0:
            out.setdefault(int(g), set()).add(lab)
    return {frozenset(v) for v in out.values()}


def true_partition(trial, truth) -> set[frozenset]:
    return partition(trial.labels, truth.marker_segment)


def random_rotation(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix()


def segment_map(result, trial, truth) -> dict[int, int]:
    """Fitted segment -> true segment (majority of its markers)."""
    idx = [trial.labels.index(lab) for lab in result.trial.labels]
    tseg = truth.marker_segment[idx]
    seg = result.segmentation.marker_segment
    return {s: int(np.bincount(tseg[seg == s]).argmax()) for s in range(result.n_segments)}


def off_axis_rmse(positions, truth, tj) -> float:
    """RMS over the finite frames of (F, 3) ``positions`` from true joint ``tj``'s centre;
    a hinge's error along its axis (which marker data does not fix) left out."""
    err = positions - truth.joint_positions[:, tj]
    if truth.joint_types[tj] == "hinge":
        axis = truth.joint_axes_world[tj][:, 0]
        err = err - np.sum(err * axis, -1, keepdims=True) * axis
    ok = np.isfinite(err[:, 0])
    return float(np.sqrt(np.mean(np.sum(err[ok] ** 2, -1))))


def linkage_with_a_bending_marker():
    """The linkage with its last rod's third marker swinging 4 cm from the middle one (a
    toe on a foot): rigid with that marker, not with the rod's first (distance std 22 mm
    against the 18 mm limit at ``sigma`` = 6 mm). Every rigid split of that rod leaves a
    marker alone, as HDM05 dg's left heel at 15 segments."""
    from jaxskel import synth

    trial, _ = synth.simulate(synth.linkage(), duration=30.0, seed=0, noise=0.001)
    x = np.array(trial.positions)
    pivot, swing = trial.labels.index("R3M2"), trial.labels.index("R3M3")
    theta = 0.6 * np.sin(2 * np.pi * 0.23 * trial.times) + 0.4 * np.sin(2 * np.pi * 0.61 * trial.times + 1.0)
    arm = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=-1)
    noise = np.random.default_rng(5).normal(0.0, 0.001, arm.shape)
    x[:, swing] = x[:, pivot] + 0.04 * arm + noise
    return trial.replace(positions=x)


def marker_artefact(noise: float, soft_tissue: float) -> float:
    """RMS 3-D length (metres) of one marker's artefact in ``synth.simulate``: white noise
    of std ``noise`` per coordinate and skin motion of RMS length ``soft_tissue``."""
    return float(np.sqrt(3 * noise**2 + soft_tissue**2))


def markers_on_joints(truth, tol: float) -> dict[str, int]:
    """Markers that move less than ``tol`` (RMS over frames, metres) in a neighbouring
    segment's frame as well as not at all in their own (on a joint centre or near a hinge's
    axis, like ``synth.full_body``'s elbow and knee markers): label -> that neighbour.
    With ``tol`` the recording's noise, distances cannot say which of the two such a
    marker belongs to; the noise-free poses of ``truth`` measure it."""
    body = truth.body
    rot, shift = np.asarray(truth.segment_rotations), np.asarray(truth.segment_translations)
    out = {}
    for i, (label, s) in enumerate(zip(body.marker_labels, body.marker_segment)):
        world = np.einsum("fij,j->fi", rot[:, s], body.marker_offsets[i]) + shift[:, s]
        for a, b in np.asarray(body.edges):
            if s not in (a, b):
                continue
            other = int(b if a == s else a)
            local = np.einsum("fji,fj->fi", rot[:, other], world - shift[:, other])
            if np.sqrt(np.mean(np.sum((local - local.mean(0)) ** 2, axis=1))) < tol:
                out[label] = other
    return out


def whole_segment_homes(labels, groups, truth, tol: float) -> dict[int, int] | None:
    """True segment -> the fitted group holding it, if every fitted group is a union of
    whole true segments (the exact grouping or a coarser one), each marker of
    :func:`markers_on_joints` at ``tol`` allowed in the group of either of its two
    segments; ``None`` when a true segment is split or such a marker sits anywhere else."""
    true_of = dict(zip(truth.body.marker_labels, truth.body.marker_segment))
    either = markers_on_joints(truth, tol)
    group_of_segment: dict[int, set] = {}
    for label, g in zip(labels, groups):
        if label not in either:
            group_of_segment.setdefault(int(true_of[label]), set()).add(int(g))
    if any(len(v) > 1 for v in group_of_segment.values()):
        return None  # a true segment's own markers in two groups
    home = {s: next(iter(v)) for s, v in group_of_segment.items()}
    placed = all(
        int(g) in (home.get(int(true_of[label])), home.get(either[label]))
        for label, g in zip(labels, groups)
        if label in either
    )
    return home if placed else None


def same_grouping_up_to_joint_markers(labels, groups, truth, tol: float) -> bool:
    """Whether a fitted grouping is the true one, each marker of :func:`markers_on_joints`
    allowed in either of its two segments (and nothing else allowed): every true segment
    whole in a group of its own (:func:`whole_segment_homes`, one to one), and no other group."""
    home = whole_segment_homes(labels, groups, truth, tol)
    return home is not None and len(set(home.values())) == len(home) == int(np.max(groups)) + 1


# ------------------------------------------------------------------ rotations (scipy)
# Independent references for the tests: rotations come from scipy, never from jaxskel's
# own rotation kit (jaxskel._math), which has unit tests of its own.
def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (scipy, independent of jaxskel)."""
    from scipy.spatial.transform import Rotation

    rotvec = np.asarray(rotvec, dtype=float)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*rotvec.shape[:-1], 3, 3)


def matrix_to_quat(m) -> np.ndarray:
    """Unit quaternions (..., 4), scalar first, of rotation matrices (..., 3, 3) (scipy).

    The sign is jaxskel's: ``w >= 0``; where ``w`` is 0 (half turns), the component of the
    largest of m00, m11, m22 (x, y, z respectively) is positive (Shepperd's method)."""
    from scipy.spatial.transform import Rotation

    m = np.asarray(m, dtype=float)
    flat = m.reshape(-1, 3, 3)
    q = Rotation.from_matrix(flat).as_quat(scalar_first=True)
    diag = np.stack([np.trace(flat, axis1=1, axis2=2), flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2]], axis=-1)
    pick = np.argmax(diag, axis=-1)
    q *= np.where(q[np.arange(len(q)), pick] < 0, -1.0, 1.0)[:, None]
    q *= np.where(q[:, 0] < 0, -1.0, 1.0)[:, None]
    return q.reshape(*m.shape[:-2], 4)


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), scalar first (scipy; scale divided out)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(*q.shape[:-1], 3, 3)


def horn_align(source, target, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` minimising ``sum_i w_i |R source_i + t - target_i|^2`` over proper rotations
    (Kabsch by numpy's SVD, reflections corrected); points of zero weight are ignored."""
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mu_s, mu_t = w @ source, w @ target
    cov = np.einsum("n,ni,nj->ij", w, target - mu_t, source - mu_s)
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rot = (u * np.array([1.0, 1.0, d])) @ vt
    return rot, mu_t - rot @ mu_s


# ------------------------------------------------------------------ fitted joints
def true_joint_index(result, trial, truth, j) -> int:
    """The true joint that fitted joint ``j`` stands for (its segments mapped by :func:`segment_map`)."""
    m = segment_map(result, trial, truth)
    p, c = result.edges[j]
    key = frozenset((m[int(p)], m[int(c)]))
    return [i for i, e in enumerate(truth.edges) if frozenset(map(int, e)) == key][0]


def truth_skeleton(trial, truth, segment_names=()):
    """The synthetic body's own rigid skeleton (no solver), in ``trial``'s marker order."""
    from jaxskel.skeleton import Skeleton

    n_seg = len(truth.segment_names)
    return Skeleton(
        n_segments=n_seg,
        edges=truth.edges,
        root=truth.root,
        marker_labels=trial.labels,
        marker_segment=truth.marker_segment,
        marker_offsets=truth.marker_offsets,
        joint_offsets=truth.joint_offsets,
        bones=truth.bones,
        bone_lengths=truth.bone_lengths,
        bone_segment=truth.bone_segment,
        segment_lengths=np.full(n_seg, np.nan),
        marker_rms=np.zeros(trial.n_markers),
        nonrigid_markers=(),
        diagnostics={},
        segment_names=tuple(segment_names),
    )


def truth_motion(trial, truth):
    """The synthetic trial's true motion as a :class:`jaxskel.skeleton.Motion` (no solver)."""
    from scipy.spatial.transform import Rotation

    from jaxskel.skeleton import Motion

    n_seg = len(truth.segment_names)
    quats = Rotation.from_matrix(truth.segment_rotations.reshape(-1, 3, 3)).as_quat(scalar_first=True)
    return Motion(
        root_position=truth.segment_translations[:, truth.root],
        rotations=quats.reshape(trial.n_frames, n_seg, 4),
        segment_translations=truth.segment_translations,
        joint_positions=truth.joint_positions,
        fitted_markers=truth.clean_positions,
        marker_rms=np.zeros(trial.n_frames),
        segment_observed=np.ones((trial.n_frames, n_seg), bool),
        steps=np.zeros(trial.n_frames, int),
        result=np.zeros(trial.n_frames, int),
        converged=True,
        marker_labels=trial.labels,
        rate=trial.rate,
    )


def opensim_ik_rms(osim, model_path, take, folder) -> np.ndarray:
    """OpenSim's per-frame marker RMS (m) for ``take``, a Trial already in the model's frame
    and names, by its InverseKinematicsTool with the model at ``model_path``; files go to ``folder``."""
    import jaxskel

    trc = jaxskel.save_trial(take, folder / "take.trc")
    tool = osim.InverseKinematicsTool()
    tool.setName("take")
    model = osim.Model(str(model_path))  # the tool does not own it: keep it alive while it runs
    tool.setModel(model)
    tool.setMarkerDataFileName(str(trc))
    tool.setStartTime(float(take.times[0]))
    tool.setEndTime(float(take.times[-1]))
    tool.setResultsDir(str(folder))
    tool.setOutputMotionFileName(str(folder / "take.mot"))
    tool.set_accuracy(1e-6)
    assert tool.run()
    table = osim.TimeSeriesTable(str(folder / "take_ik_marker_errors.sto"))
    rms = table.getDependentColumn("marker_error_RMS").to_numpy()
    assert len(rms) == take.n_frames
    return rms
