"""Synthetic data with one cluster marker that soft tissue moves far more than the others (test data)."""

from __future__ import annotations

import numpy as np

import jaxskel
from jaxskel import synth
from jaxskel.synth._corrupt import soft_tissue_displacement


def wobbling_trial(seed: int, duration: float, amplitude: float, marker: str = "LTHF"):
    """(trial, truth): ``synth.full_body`` (0.5 mm noise, 1 mm soft tissue on every marker) with
    ``marker`` moved in its segment by a further soft-tissue displacement of RMS ``amplitude``
    metres (the model of ``synth.simulate``: driven by the angles of the joints touching its
    segment, plus a slow wobble)."""
    body = synth.full_body()
    trial, truth = synth.simulate(body, duration=duration, seed=seed, noise=0.0005, soft_tissue=0.001)
    times = np.arange(trial.positions.shape[0]) / trial.rate
    shift = soft_tissue_displacement(body, truth.joint_angles, times, amplitude, np.random.default_rng(100 + seed))
    m = list(trial.labels).index(marker)
    positions = np.array(trial.positions)
    positions[:, m] += np.einsum("fij,fj->fi", truth.segment_rotations[:, truth.marker_segment[m]], shift[:, m])
    return jaxskel.io.Trial(positions=positions, labels=trial.labels, rate=trial.rate, up_axis="z"), truth
