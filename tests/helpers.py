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
