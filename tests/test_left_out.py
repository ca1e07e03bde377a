"""Markers the motion cannot place are left out of the skeleton and reported
(jaxskel.segment.left_out_markers, through fit_skeleton): a static object next to a moving
body, and a static trial's extra markers fitted together with a dynamic trial."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import segment_map

import jaxskel
from jaxskel import synth
from jaxskel.segment import left_out_markers, white_noise


def _undirected_truth(result, trial, truth):
    m = segment_map(result, trial, truth)
    return {frozenset((m[int(p)], m[int(c)])) for p, c in result.edges}, {frozenset(map(int, e)) for e in truth.edges}


@pytest.fixture(scope="module")
def body():
    trial, truth = synth.simulate(synth.full_body(seed=3), duration=12.0, seed=3, noise=0.001)
    return trial, truth


def _with_object(trial, rng):
    """The trial plus a 4-marker L-frame standing 1.5 m beside the body (1 mm noise)."""
    centre = np.nanmedian(trial.positions, axis=(0, 1)) + np.array([1.5, 0.4, -0.6])
    frame = centre + np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.2, 0.0], [0.5, 0.0, 0.0]])
    obj = frame[None] + rng.normal(0.0, 0.001, (trial.n_frames, 4, 3))
    labels = trial.labels + ("L1", "L2", "L3", "L4")
    return trial.replace(positions=np.concatenate([trial.positions, obj], axis=1), labels=labels)


def test_a_stationary_object_is_left_out_and_the_tree_stays_exact(body):
    trial, truth = body
    with_object = _with_object(trial, np.random.default_rng(0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(with_object, ik=False)
    left = result.segmentation.left_out
    assert set(left) == {"L1", "L2", "L3", "L4"}
    assert all("stationary object" in why for why in left.values())
    segment = dict(zip(result.input_labels, result.marker_segment_input().tolist()))
    assert all(segment[lab] == -1 for lab in left)
    fitted, true = _undirected_truth(result, trial, truth)
    assert result.n_segments == len(truth.segment_names) and fitted == true
    assert "left out of the skeleton (4 marker(s)" in result.summary()


def test_a_planted_segment_is_not_an_object(body):
    """Markers that stay still are kept when they stay next to moving markers: a foot
    standing on the floor while the leg above it turns. Here the pelvis of a body whose
    root does not move carries the chain."""
    trial, truth = body
    # Freeze the right foot's markers in place (as if planted): still, but linked to the
    # shank's markers, which move.
    foot = [i for i, s in enumerate(truth.marker_segment) if truth.segment_names[s] == "foot_r"]
    planted = trial.positions.copy()
    planted[:, foot] = np.nanmedian(planted[:, foot], axis=0)
    t = trial.replace(positions=planted)
    left = left_out_markers(t, white_noise=white_noise(t.positions))
    assert not any("stationary" in why for why in left.reasons.values()), left.reasons


def test_a_static_trials_extra_markers_are_left_out_of_a_static_plus_dynamic_fit(body):
    """A lab's static pose with extra (medial) markers, fitted together with a dynamic trial:
    those markers are seen only while nothing moves, so no segment can claim them; they are
    left out with that reason, and the tree is the dynamic trial's, exact."""
    trial, truth = body
    rng = np.random.default_rng(1)
    # the static pose: the dynamic trial's first frame held for 2 s (1 mm noise), plus two
    # markers 5 cm off two existing markers, present only here
    n = int(2.0 * trial.rate)
    still = np.repeat(trial.positions[:1], n, axis=0)
    extra = still[:, :2] + np.array([0.05, 0.0, 0.0])
    static = jaxskel.Trial(
        positions=np.concatenate([still, extra], axis=1) + rng.normal(0.0, 0.001, (n, trial.n_markers + 2, 3)),
        labels=trial.labels + ("MED1", "MED2"), rate=trial.rate, up_axis=trial.up_axis,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton([static, trial], ik=False)
    left = result.segmentation.left_out
    assert set(left) == {"MED1", "MED2"}
    assert all("seen only while no two segments moved" in why for why in left.values())
    fitted, true = _undirected_truth(result, trial, truth)
    assert result.n_segments == len(truth.segment_names) and fitted == true


def test_nothing_is_left_out_of_a_moving_body_or_a_static_one(body):
    trial, _ = body
    assert not left_out_markers(trial, white_noise=white_noise(trial.positions))
    still = trial.replace(positions=np.repeat(trial.positions[:1], 200, axis=0)[:200])
    assert not left_out_markers(still, white_noise=0.0)
