"""The whole pipeline under the acquisition conditions recordings differ in, on bodies no default was tuned on.

Where ``sweep_bodies`` varies the body under one recording condition, this sweep varies the
recording: frame rate, duration, noise and soft tissue, marker jumps (swaps), ghost
markers, passive labelling (a new label after every gap), the up axis, a rotated and
shifted laboratory frame, a small subject, uneven marker counts (one marker on a hand),
heavy occlusion (about 40 % of the samples seen), a walk alone and a walk fitted
together with a calibration trial. Every case runs
:func:`jaxskel.fit_skeleton` with its defaults (cleaning, label merging, segmentation,
joints, rigid skeleton, IK), then writes and reads back the HDF5 result and a BVH file, and
is judged on the truth (``jaxskel.synth``, seeds 30 and up):

* ``seg``: the marker grouping is exact (markers with a physical marker; ghosts left out);
  ``~`` where it is exact up to markers on joint centres (a marker that moves less than the
  recording's artefact in a neighbour's frame may go either way, as in ``sweep_motion_range``);
* ``tree``: the fitted joints are the true ones (segments named by their markers' majority);
* ``joint mm``: mean over joints of the RMS distance of the IK joint centres to the true
  ones (a hinge's position along its axis, which markers do not fix, left out), on the
  first trial's frames; ``bone %``: mean relative bone-length error of the rigid skeleton
  over the bones between non-hinge joints (a hinge's centre slides along its axis, so a bone
  ending at one has no length the markers fix); both only where the tree is exact;
* ``IK mm``: median marker residual of the IK motion; the warnings raised.

Usage::

    python bench/sweep_conditions.py                  # 13 recordings, ~7 min on 2 cores
    python bench/sweep_conditions.py --only walk      # the cases whose name contains "walk"
    python bench/sweep_conditions.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import jaxskel
from jaxskel import synth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import (  # noqa: E402
    marker_artefact, off_axis_rmse, partition, random_rotation, same_grouping_up_to_joint_markers,
)


def _cases():
    """(name, body, [simulate keyword sets: one per trial fitted together], transform seed or None)."""
    fb = synth.full_body
    return [
        ("tree 6, 60 Hz, 2 mm noise, 4 gaps", synth.random_tree(6, seed=30),
         [dict(duration=15.0, rate=60.0, seed=30, noise=0.002, gaps=4)], None),
        ("tree 8, marker jumps", synth.random_tree(8, seed=31),
         [dict(duration=20.0, seed=31, noise=0.001, gaps=2, jumps=3)], None),
        ("tree 8, ghost markers", synth.random_tree(8, seed=32),
         [dict(duration=20.0, seed=32, noise=0.001, gaps=2, ghosts=4)], None),
        ("tree 10, passive labels", synth.random_tree(10, seed=33),
         [dict(duration=20.0, seed=33, noise=0.001, gaps=2, relabel=True)], None),
        ("tree 12, y up", synth.random_tree(12, seed=34),
         [dict(duration=20.0, seed=34, noise=0.001, gaps=2, up_axis="y")], None),
        ("linkage, 4 s take", synth.linkage(), [dict(duration=4.0, seed=35, noise=0.001, gaps=1)], None),
        ("body, passive labels + ghosts", fb(seed=30),
         [dict(duration=30.0, seed=30, noise=0.002, soft_tissue=0.001, gaps=2, relabel=True, ghosts=4)], None),
        ("body, 1-5 markers a segment, jumps", fb(seed=31, markers_per_segment={"l_hand": 1, "head": 2, "pelvis": 5}),
         [dict(duration=30.0, seed=31, noise=0.002, soft_tissue=0.002, gaps=3, jumps=2)], None),
        ("body, child size, 100 Hz, 15 s", fb(seed=32, scale=0.6),
         [dict(duration=15.0, rate=100.0, seed=32, noise=0.001, soft_tissue=0.001, gaps=1)], None),
        ("body, rotated + shifted lab", fb(seed=33),
         [dict(duration=30.0, seed=33, noise=0.002, soft_tissue=0.001, gaps=2)], 33),
        ("body, 41 % seen (14 gaps a marker)", fb(seed=36),
         [dict(duration=30.0, seed=36, noise=0.002, gaps=14, gap_length=(0.5, 2.0))], None),
        ("body, walk alone", fb(seed=34), [dict(motion="walk", duration=30.0, seed=34, noise=0.002, gaps=2)], None),
        ("body, walk + calibration trial", fb(seed=34),
         [dict(motion="walk", duration=30.0, seed=34, noise=0.002, gaps=2),
          dict(duration=20.0, seed=35, noise=0.002, gaps=2)], None),
    ]  # fmt: skip


def _true_markers(result, truth) -> tuple[np.ndarray, list]:
    """True segment and physical label of every fitted marker (-1 / None: no physical
    marker, e.g. a ghost)."""
    phys = result.physical_input()
    segment, label = np.full(result.trial.n_markers, -1), [None] * result.trial.n_markers
    for i in np.flatnonzero((truth.physical >= 0) & (phys >= 0)):
        segment[phys[i]] = truth.marker_segment[i]
        label[phys[i]] = truth.physical_labels[truth.physical[i]]
    return segment, label


def run_case(name, body, sims, transform) -> dict:
    trials = []
    rot, shift = (random_rotation(transform), np.array([2.5, -1.0, 0.7])) if transform is not None else (np.eye(3), 0.0)
    for kw in sims:
        trial, truth = synth.simulate(body, **kw)
        trials.append((trial.transformed(rot, shift) if transform is not None else trial, truth))
    trial, truth = trials[0]
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton([t for t, _ in trials] if len(trials) > 1 else trial)
        seconds = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as tmp:
            result.save(Path(tmp) / "r.h5")
            back = jaxskel.load_result(Path(tmp) / "r.h5")
            bvh = jaxskel.result.read_bvh(result.export_bvh(Path(tmp) / "r.bvh", trial=0))
    files_ok = len(back.segments.names) == result.n_segments and bvh.n_frames == trial.n_frames

    # Trials fitted together share the marker set: the first one's truth names every label.
    true_seg, physical = _true_markers(result, truth)
    fitted = result.segmentation.marker_segment
    known = true_seg >= 0
    labels = np.array(result.trial.labels)[known]
    seg_ok = partition(labels, fitted[known]) == partition(labels, true_seg[known])
    kw = sims[0]
    near_joint = not seg_ok and same_grouping_up_to_joint_markers(
        [physical[k] for k in np.flatnonzero(known)], fitted[known], truth,
        marker_artefact(kw.get("noise", 0.0), kw.get("soft_tissue", 0.0)),
    )
    named = {s: int(np.bincount(true_seg[(fitted == s) & known]).argmax()) if ((fitted == s) & known).any() else -1
             for s in range(result.n_segments)}
    true_edges = [frozenset(map(int, e)) for e in truth.edges]
    fitted_edges = [frozenset((named[int(a)], named[int(b)])) for a, b in result.edges]
    tree_ok = set(fitted_edges) == set(true_edges)
    joint_mm = bone_pct = float("nan")
    if tree_ok and result.motion is not None:
        first = slice(*result.trial_bounds[0])
        to_true = [true_edges.index(e) for e in fitted_edges]
        joint_mm = 1e3 * float(np.mean([
            off_axis_rmse((result.motion.joint_positions[first, j] - shift) @ rot, truth, tj)  # the lab frame undone
            for j, tj in enumerate(to_true)
        ]))  # fmt: skip
        true_bones = {frozenset(map(int, b)): length for b, length in zip(truth.bones.tolist(), truth.bone_lengths)}
        sk = result.skeleton
        hinge = [t == "hinge" for t in truth.joint_types]
        errors = [abs(length - true_bones[key]) / true_bones[key]
                  for b, length in zip(sk.bones.tolist(), sk.bone_lengths)
                  if (key := frozenset(to_true[j] for j in b)) in true_bones and not any(hinge[t] for t in key)]  # fmt: skip
        bone_pct = 100 * float(np.mean(errors)) if errors else float("nan")
    return {
        "case": name, "segments": result.n_segments, "true_segments": len(truth.edges) + 1,
        "seg": bool(seg_ok), "seg_up_to_joint_markers": bool(seg_ok or near_joint), "tree": bool(tree_ok), "joint_mm": round(joint_mm, 2), "bone_pct": round(bone_pct, 3),
        "ik_median_mm": round(1e3 * float(np.median(result.motion.marker_rms)), 2) if result.motion is not None else None,
        "files_ok": bool(files_ok), "warnings": sorted({w.category.__name__ for w in caught}),
        "seconds": round(seconds, 1),
    }  # fmt: skip


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=None, help="run the cases whose name contains this text")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    rows = []
    print(f"{'case':>36} {'segs':>7} {'seg':>5} {'tree':>5} {'joint mm':>8} {'bone %':>7} {'IK mm':>6} {'s':>5}  warnings")
    for name, body, sims, transform in _cases():
        if args.only and args.only not in name:
            continue
        try:
            row = run_case(name, body, sims, transform)
        except Exception as exc:  # a crash is a result of this sweep, not its end
            row = {"case": name, "error": f"{type(exc).__name__}: {exc}"}
            print(f"{name:>36} ERROR {row['error'][:200]}", flush=True)
            rows.append(row)
            continue
        rows.append(row)
        seg = "True" if row["seg"] else "~" if row["seg_up_to_joint_markers"] else "False"
        print(f"{name:>36} {row['segments']:>3}/{row['true_segments']:<3} {seg:>5} {row['tree']!s:>5} "
              f"{row['joint_mm']:>8.2f} {row['bone_pct']:>7.3f} {row['ik_median_mm']:>6.2f} {row['seconds']:>5.1f}  "
              f"{', '.join(row['warnings'])}{'' if row['files_ok'] else '  FILES WRONG'}", flush=True)
    done = [r for r in rows if "error" not in r]
    wrong = [r for r in done if not (r["seg_up_to_joint_markers"] and r["tree"])]
    silent = [r for r in wrong if not r["warnings"]]
    print(f"{len(done) - len(wrong)} of {len(rows)} exact (up to markers on joints); {len(wrong)} wrong, {len(silent)} of them without a warning; "
          f"{len(rows) - len(done)} errors; files written and read back: {sum(r['files_ok'] for r in done)} of {len(done)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
