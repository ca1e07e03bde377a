"""Benchmark cases: the synthetic data each case fits, and the case lists of each mode.

Every recording comes from :mod:`jaxskel.synth` with its exact ground truth:
calibration motion (every joint through its range) at 120 Hz, 2 mm marker noise,
3 mm soft-tissue artefact and two gaps per marker (the README's accuracy setting).

Bodies: ``full_body`` (15 segments, 46 markers), the same with 2 markers per
segment (30) or with every marker doubled / quadrupled (92 / 184 markers: each
copy sits 2-4 cm from its original on the same segment), and ``random_tree`` of
5-40 segments (2-4 markers each).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["CORRUPTION", "make_body", "make_trial", "plan"]

CORRUPTION = {"noise": 0.002, "soft_tissue": 0.003, "gaps": 2}


def make_body(spec: dict):
    """The synth Body of a case spec (``body``, ``segments``, ``markers_per_segment``, ``marker_copies``)."""
    from jaxskel import synth

    if spec.get("body", "full_body") == "random_tree":
        return synth.random_tree(int(spec["segments"]), seed=int(spec.get("body_seed", 1)))
    body = synth.full_body(seed=0, markers_per_segment=spec.get("markers_per_segment"))
    copies = int(spec.get("marker_copies", 1))
    if copies > 1:
        rng = np.random.default_rng(7)
        offsets, segments, labels = [body.marker_offsets], [body.marker_segment], list(body.marker_labels)
        for c in range(1, copies):
            shift = rng.normal(size=body.marker_offsets.shape)
            shift *= rng.uniform(0.02, 0.04, size=(len(shift), 1)) / np.linalg.norm(shift, axis=1, keepdims=True)
            offsets.append(body.marker_offsets + shift)
            segments.append(body.marker_segment)
            labels += [f"{lab}_{c}" for lab in body.marker_labels]
        body = dataclasses.replace(
            body, marker_offsets=np.concatenate(offsets), marker_segment=np.concatenate(segments),
            marker_labels=tuple(labels),
        )
    return body


def make_trial(spec: dict, seed: int | None = None, duration: float | None = None):
    """(trial, truth) of a case spec."""
    from jaxskel import synth

    corruption = {**CORRUPTION, **spec.get("corruption", {})}
    return synth.simulate(
        make_body(spec), "calibration", duration=float(duration or spec["duration"]),
        rate=float(spec.get("rate", 120.0)), seed=int(spec.get("seed", 0) if seed is None else seed), **corruption,
    )


def _pipe(name: str, group: str, **kw) -> dict:
    return {"kind": "pipeline", "name": name, "group": group, **kw}


def plan(mode: str) -> list[dict]:
    """Case specs of a mode: ``tiny`` (the test), ``quick`` (CI, ~3 min) or ``full``."""
    if mode == "tiny":
        return [
            _pipe("random tree 4 seg, 5 s @ 60 Hz", "test", body="random_tree", segments=4, duration=5.0,
                  rate=60.0, stages_upto="tree_joints"),
        ]
    if mode == "quick":
        return [
            _pipe("full body, 5 s", "frames", duration=5.0, ref={"ik_frames": 200}),
            {"kind": "params", "name": "normalise/parameterise, 2,400 frames", "frames": 2400, "repeats": 2},
        ]
    if mode != "full":
        raise ValueError(f"unknown mode {mode!r}")
    ref_long = {"ik_frames": 2400}
    return [
        _pipe("full body, 10 s", "frames", duration=10.0, ref={"ik_frames": 1200}),
        _pipe("full body, 120 s", "frames", duration=120.0, ref=ref_long),
        _pipe("full body, 600 s", "frames", duration=600.0, ref={**ref_long, "tree_frames": 24000}),
        _pipe("random tree 5 seg, 10 s", "segments", body="random_tree", segments=5, duration=10.0, ref={"ik_frames": 600}),
        _pipe("random tree 10 seg, 10 s", "segments", body="random_tree", segments=10, duration=10.0, ref={"ik_frames": 600}),
        _pipe("random tree 20 seg, 10 s", "segments", body="random_tree", segments=20, duration=10.0, ref={"ik_frames": 600}),
        _pipe("random tree 40 seg, 10 s", "segments", body="random_tree", segments=40, duration=10.0, ref={"ik_frames": 600}),
        _pipe("full body 30 markers, 10 s", "markers", markers_per_segment=2, duration=10.0, ref={"ik_frames": 600}),
        _pipe("full body 92 markers, 10 s", "markers", marker_copies=2, duration=10.0, ref={"ik_frames": 600}),
        _pipe("full body 184 markers, 10 s", "markers", marker_copies=4, duration=10.0, ref={"ik_frames": 600}),
        {"kind": "precision", "name": "float32 vs float64, full body 10 s", "duration": 10.0},
        {"kind": "batch", "name": "batch of trials (IK), full body 10 s each", "duration": 10.0,
         "sizes": [1, 4, 16, 64], "ref_frames": 300},
        {"kind": "fit_batch", "name": "fit_batch, full body 10 s each", "duration": 10.0, "sizes": [1, 4, 16],
         "timeout": 2400},
        {"kind": "relabel", "name": "label merging, 30 s relabelled walk", "duration": 30.0},
        {"kind": "params", "name": "normalise/parameterise, 24,000 frames", "frames": 24000, "repeats": 3},
        {"kind": "cli", "name": "jaxskel fit, new process, 10 s full body", "duration": 10.0},
    ]
