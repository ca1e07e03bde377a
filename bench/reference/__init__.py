"""A plain numpy/scipy/scikit-learn implementation of the jaxskel method, for side-by-side figures.

:func:`fit_reference` chains the stages like :func:`jaxskel.fit_skeleton` (clean,
segment, all-pairs joint costs, MST, tree joints on all frames, rigid skeleton,
IK) and times each. It is the code a competent scientist would write in a day:
vectorised numpy within a pair or a frame, ``scipy.optimize.least_squares`` with
sparse or analytic Jacobians, ``sklearn.cluster.SpectralClustering``,
``scipy.sparse.csgraph.minimum_spanning_tree``. See the stage modules for what
each does and where it differs from jaxskel.

For long recordings the two slowest reference stages can be timed on part of the
work and extrapolated linearly (``ik_frames``, ``tree_frames``); the result then
says so (``extrapolated``) and how much was actually run.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from . import ik, joints, rigid, segment

__all__ = ["clean_and_segment", "fit_reference", "ik", "joints", "rigid", "segment", "timed_output"]


def timed_output() -> tuple[dict, Callable[[str, float, float], None]]:
    """A chain's result dict (``timings``, ``extrapolated``, ``cpu``) and ``tick(stage, t0, c0)``,
    which records the wall and CPU seconds since ``t0`` / ``c0`` under ``stage``."""
    out: dict = {"timings": {}, "extrapolated": {}, "cpu": {}}

    def tick(name: str, t0: float, c0: float) -> None:
        out["timings"][name] = time.perf_counter() - t0
        out["cpu"][name] = time.process_time() - c0

    return out, tick


def clean_and_segment(
    out: dict, tick, positions: np.ndarray, rate: float, n_segments: int | None, *,
    clean_data: bool, stages: tuple[str, ...], seed: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chains' first two stages, timed into ``out``: NaN to a mask, :func:`segment.clean`
    (with ``clean_data`` and ``"clean"`` in ``stages``), :func:`segment.segment`. Returns the
    positions (missing = 0), the mask and each marker's segment."""
    mask = np.isfinite(positions).all(-1)
    x = np.where(mask[..., None], positions, 0.0).astype(np.float64)
    keep = np.arange(x.shape[1])
    t0, c0 = time.perf_counter(), time.process_time()
    if clean_data and "clean" in stages:
        x, mask, keep = segment.clean(x, mask, rate)
    tick("clean", t0, c0)
    out["kept_markers"] = keep
    out["x"], out["mask"] = x, mask
    t0, c0 = time.perf_counter(), time.process_time()
    seg = segment.segment(x, mask, rate, n_segments, seed=seed)
    tick("segment", t0, c0)
    out["marker_segment"] = seg
    return x, mask, seg


def fit_reference(
    positions: np.ndarray,
    rate: float,
    n_segments: int | None = None,
    *,
    alpha: float = 1e-5,
    topology_frames: int = 300,
    clean_data: bool = True,
    tree_frames: int | None = None,
    ik_frames: int | None = None,
    pairs_limit: int | None = None,
    stages: tuple[str, ...] = ("clean", "segment", "joint_costs", "tree_joints", "rigid", "ik"),
    seed: int = 0,
) -> dict:
    """Run the reference chain on ``positions`` (F, M, 3), NaN = missing.

    ``tree_frames`` / ``ik_frames``: solve the tree joints / IK on at most this many
    evenly spread (tree joints) or consecutive (IK) frames and scale the time by
    ``F / frames run``. ``pairs_limit``: solve only this many (evenly chosen) pairs in
    the all-pairs pass and scale the time by ``all pairs / pairs run``; the chain then
    stops there (no topology without all pairs), so it is for timing-only runs.
    The tree-joints time includes the MST, as jaxskel's ``fit_topology`` does.
    Returns a dict with ``timings`` (seconds, extrapolated where marked),
    ``extrapolated`` (stage -> "from N of M ..."), and the stage outputs.
    """
    out, tick = timed_output()
    x, mask, seg = clean_and_segment(out, tick, positions, rate, n_segments, clean_data=clean_data, stages=stages,
                                     seed=seed)
    n_seg = int(seg.max()) + 1
    if "joint_costs" not in stages:
        return out

    pairs = None
    all_pairs = [(a, b) for a in range(n_seg) for b in range(a + 1, n_seg)]
    if pairs_limit is not None and pairs_limit < len(all_pairs):
        pick = np.unique(np.linspace(0, len(all_pairs) - 1, pairs_limit).astype(int))
        pairs = [all_pairs[i] for i in pick]
    t0, c0 = time.perf_counter(), time.process_time()
    cost, fits, pair_frames = joints.all_pair_costs(
        x, mask, seg, n_seg, alpha=alpha, max_frames=topology_frames, pairs=pairs
    )
    tick("joint_costs", t0, c0)
    out["pair_cost"], out["pair_fits"] = cost, fits
    if pairs is not None:
        scale = len(all_pairs) / len(pairs)
        out["timings"]["joint_costs"] *= scale
        out["cpu"]["joint_costs"] *= scale
        out["extrapolated"]["joint_costs"] = f"from {len(pairs)} of {len(all_pairs)} pairs"
        return out

    t_mst, c_mst = time.perf_counter(), time.process_time()
    edges, root = joints.mst_topology(cost)
    out["edges"], out["root"] = edges, root
    if "tree_joints" not in stages:
        return out

    n_frames = x.shape[0]
    frames = None
    if tree_frames is not None and tree_frames < n_frames:
        frames = np.unique(np.linspace(0, n_frames - 1, tree_frames).astype(int))
    jp, jcost = joints.tree_joints(x, mask, seg, edges, fits, pair_frames, alpha=alpha, frames=frames)
    tick("tree_joints", t_mst, c_mst)
    out["joint_cost"] = jcost
    if frames is not None:
        scale = n_frames / frames.size
        out["timings"]["tree_joints"] *= scale
        out["cpu"]["tree_joints"] *= scale
        out["extrapolated"]["tree_joints"] = f"from {frames.size} of {n_frames} frames"
        x_fit, m_fit, joint_frames = x[frames], mask[frames], frames
    else:
        x_fit, m_fit, joint_frames = x, mask, np.arange(n_frames)
    out["joint_positions"], out["joint_frames"] = jp, joint_frames
    if "rigid" not in stages:
        return out

    t0, c0 = time.perf_counter(), time.process_time()
    sk = rigid.fit_rigid(x_fit, m_fit, seg, edges, root, jp)
    tick("rigid", t0, c0)
    out["skeleton"] = sk
    if "ik" not in stages:
        return out

    n_ik = n_frames if ik_frames is None else min(ik_frames, n_frames)
    start = (n_frames - n_ik) // 2
    t0, c0 = time.perf_counter(), time.process_time()
    motion = ik.inverse_kinematics(sk, x[start : start + n_ik], mask[start : start + n_ik])
    tick("ik", t0, c0)
    motion["frames"] = np.arange(start, start + n_ik)
    if n_ik < n_frames:
        scale = n_frames / n_ik
        out["timings"]["ik"] *= scale
        out["cpu"]["ik"] *= scale
        out["extrapolated"]["ik"] = f"from {n_ik} of {n_frames} frames"
    out["motion"] = motion
    return out
