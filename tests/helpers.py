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
