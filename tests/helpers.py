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
