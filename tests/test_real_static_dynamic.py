"""A lab's static trials fitted together with its dynamic trials: Hamner (static pose with medial
knee and ankle markers, then treadmill running; opensim_models/Hamner) and biobuddy's lower-limb
calibration set (two static postures and seven functional trials)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from human_markers import implausible_edges, misplaced_markers, segment_parts
from osim_reference import hamner_joint_centres, read_osim

import jaxskel

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "opensim_models" / "Hamner"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real recordings not found at {DATA}")

STATIC_ONLY = {f"{s}.{m}.{lm}" for s in "RL" for m in ("Knee", "Ankle") for lm in ("Lat", "Med")} | {"L.Bicep"}


def _part(label: str) -> str:
    side = label[0]
    for key, part in (("ASIS", "pelvis"), ("Sacral", "pelvis"), ("Thigh", "thigh"), ("Shank", "shank"),
                      ("Heel", "foot"), ("Midfoot", "foot"), ("Toe", "foot")):
        if key in label:
            return part if part == "pelvis" else f"{side} {part}"
    return "upper body"


@pytest.mark.extended
def test_static_plus_running_places_every_marker_or_leaves_it_out():
    static = jaxskel.load(DATA / "subject02_static.trc")
    running = jaxskel.load(DATA / "subject02_running.trc")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton([static, running])
    seg = result.segmentation
    # the static trial's own markers are left out, with the reason; its frames leave the joint stages
    assert set(seg.left_out) == STATIC_ONLY
    assert all("seen only while no two segments moved" in why for why in seg.left_out.values())
    assert seg.still_spans == ((0, static.n_frames),)
    # every lower-body group holds one body part, and the lower-body tree is the human one
    parts = {}
    for label, s in zip(result.trial.labels, seg.marker_segment.tolist()):
        parts.setdefault(s, set()).add(_part(label))
    lower = {s: p.pop() for s, p in parts.items() if p != {"upper body"}}
    assert all(len(parts[s]) == 0 for s in lower), parts  # no mixed group
    expected = {frozenset(("pelvis", f"{s} thigh")) for s in "RL"} | {frozenset((f"{s} thigh", f"{s} shank"))
                                                                    for s in "RL"}
    expected |= {frozenset((f"{s} shank", f"{s} foot")) for s in "RL"}
    edges = {frozenset((lower[p], lower[c])) for p, c in result.edges.tolist()
             if p in lower and c in lower and lower[p] != lower[c]}
    assert edges == expected
    # knees and ankles go between the static trial's epicondyles and malleoli
    placement = result.skeleton.diagnostics["hinge_placement"]
    placed = " ".join(placement)
    for s in "RL":
        assert f"{s}.Knee.Lat" in placed and f"{s}.Ankle.Lat" in placed, placement
    # and come within 3.5 cm of the lab's centres (RMS over the running frames; bench/joint_centres.py)
    reference = hamner_joint_centres(read_osim(DATA / "subject02_scaled.osim"), static, running)
    lo, hi = result.trial_bounds[1]
    for (p, c), j in zip(result.edges.tolist(), range(len(result.edges))):
        name = {frozenset(("R thigh", "R shank")): "R knee", frozenset(("L thigh", "L shank")): "L knee",
                frozenset(("R shank", "R foot")): "R ankle", frozenset(("L shank", "L foot")): "L ankle"}.get(
            frozenset((lower.get(p), lower.get(c))))
        if name is None:
            continue
        err = np.linalg.norm(result.motion.joint_positions[lo:hi, j] - reference[name], axis=-1)
        assert np.sqrt(np.nanmean(err**2)) < 0.035, (name, np.sqrt(np.nanmean(err**2)))


BIOBUDDY = DATA.parents[1] / "biobuddy" / "lower_limb_calibration"
BIOBUDDY_TRIALS = ("anatomical_posture", "Test_func_anat", "Test_func_lhip", "Test_func_rhip", "Test_func_lknee",
                   "Test_func_rknee", "Test_func_lankle", "Test_func_rankle", "Test_func_trunk")


@pytest.mark.extended  # about 1 min
def test_biobuddy_static_postures_and_functional_trials_place_every_marker():
    """biobuddy's whole calibration set (Vicon, 12 Hz, 59-60 markers: Plug-in-Gait plus spinal
    processes, medial epicondyles and malleoli, navicular): both static postures are found still
    and kept out of the joint stages, every marker sits with the body part it is on (a marker on
    a joint with either neighbour, the fingers with a forearm whose wrist no trial bends), and
    the tree is anatomical; nothing is left out, as every trial carries every marker."""
    trials = [jaxskel.load(BIOBUDDY / f"{name}.c3d") for name in BIOBUDDY_TRIALS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trials, ik=False)
    seg = result.segmentation
    bounds = result.trial_bounds
    assert seg.still_spans == (bounds[0], bounds[1])
    assert seg.left_out == {}
    labels, groups = list(result.trial.labels), seg.marker_segment
    assert misplaced_markers(labels, groups, seg.distance_std, seg.rigid_limit) == []
    # judged without the rigidity excuse, only the fingers sit off their part
    assert sorted(misplaced_markers(labels, groups)) == [("LFIN", "L forearm"), ("RFIN", "R forearm")]
    assert implausible_edges(labels, groups, result.edges) == []
    parts = segment_parts(labels, groups)
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    for s in "LR":
        for a, b in (("pelvis", f"{s} thigh"), (f"{s} thigh", f"{s} shank"), (f"{s} shank", f"{s} foot"),
                     (f"{s} upper arm", f"{s} forearm")):
            assert frozenset((a, b)) in edges, (a, b)
    assert frozenset(("thorax", "head")) in edges and frozenset(("pelvis", "thorax")) in edges
