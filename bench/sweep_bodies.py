"""Segmentation and tree over many synthetic bodies: where the automatic fit goes wrong.

Bodies (``jaxskel.synth``), each simulated for 20 s of calibration motion at 120 Hz with 2
gaps per marker:

* ``random_tree(n, seed)``: 4-16 rigid rods, 2-4 markers each, 1 mm noise;
* ``full_body(seed, markers_per_segment=k)``: 15 segments, k = 2, 3, 4 markers each,
  2 mm noise and 1 mm soft tissue.

Each is fitted with :func:`jaxskel.fit_skeleton` defaults (no IK) and judged on the
truth: ``seg`` the marker grouping is exact, ``tree`` the fitted edges (segments named by
the true segment most of their markers sit on) are exactly the true joints. Printed with
the segment counts (and whether the count grew after the rigid fit, :mod:`jaxskel.pipeline._split_refit`),
the joints the pose check exchanged (:mod:`jaxskel.joints._pose_check`), the markers the rigid
skeleton flags (``NonRigidMarkerWarning``) and the other warnings, so a
wrong answer that says nothing stands out.

Usage::

    python bench/sweep_bodies.py                       # the table of the README (~8 min on 2 cores)
    python bench/sweep_bodies.py --quick               # 4 bodies
    python bench/sweep_bodies.py --json out.json
    python bench/sweep_bodies.py --first-seed 4        # the same sizes, bodies never tuned on
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import jaxskel
from jaxskel import synth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import partition  # noqa: E402

#: The warnings that speak about a fit's result (jaxskel's own classes); a process-wide one such as
#: the memory-mapping guard's ``RuntimeWarning`` (:mod:`jaxskel._runtime.map_limit`) does not make a wrong
#: fit any less silent.
FIT_WARNINGS = {name for name in jaxskel.__all__ if name.endswith("Warning")}


def _bodies(quick: bool, first_seed: int = 0) -> list[tuple[str, int, int]]:
    """The bodies of the table: seeds ``first_seed`` .. +3 of each tree size, +2 of each
    full body (``first_seed`` > 0: bodies the defaults were never looked at on)."""
    if quick:
        return [("random_tree", 6, 0), ("random_tree", 12, 3), ("full_body", 2, 0), ("full_body", 3, 0)]
    trees = [("random_tree", n, first_seed + i) for n in (4, 6, 8, 12, 16) for i in range(4)]
    bodies = [("full_body", k, first_seed + i) for k in (2, 3, 4) for i in range(3)]
    return trees + bodies


def fit_recorded(trial, truth):
    """``fit_skeleton(trial, ik=False)`` with its warnings recorded and timed: (result,
    warnings, seconds, the fitted labels, their true segments)."""
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial, ik=False)
    seconds = time.perf_counter() - start
    labels = list(result.trial.labels)
    return result, caught, seconds, labels, truth.marker_segment[[trial.labels.index(lab) for lab in labels]]


def run_one(kind: str, size: int, seed: int) -> dict:
    if kind == "random_tree":
        body = synth.random_tree(size, seed=seed)
        trial, truth = synth.simulate(body, duration=20.0, seed=seed, noise=0.001, gaps=2)
    else:
        body = synth.full_body(seed=seed, markers_per_segment=size)
        trial, truth = synth.simulate(body, duration=20.0, seed=seed, noise=0.002, gaps=2, soft_tissue=0.001)
    result, caught, seconds, labels, true_seg = fit_recorded(trial, truth)
    fitted = result.segmentation.marker_segment
    named = {s: int(np.bincount(true_seg[fitted == s]).argmax()) for s in range(result.n_segments)}
    edges = {frozenset((named[int(a)], named[int(b)])) for a, b in result.edges}
    return {
        "body": kind, "size": size, "seed": seed, "segments": result.n_segments,
        "true_segments": len(truth.edges) + 1,
        "seg": partition(labels, fitted) == partition(labels, true_seg),
        "tree": edges == {frozenset(map(int, e)) for e in truth.edges},
        "count_rule": result.segmentation.count_rule,
        "split_from": result.segmentation.split_from,
        "flagged": list(result.skeleton.nonrigid_markers) if result.skeleton is not None else [],
        "warnings": sorted({w.category.__name__ for w in caught}),
        "pose_exchanges": len(result.topology.pose_exchanges),
        "seconds": round(seconds, 1),
    }


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--first-seed", type=int, default=0, help="seeds first_seed.. instead of 0.. (unseen bodies)")
    args = parser.parse_args()
    rows = []
    print(f"{'body':>12} {'size':>4} {'seed':>4} {'segs':>9} {'seg':>5} {'tree':>5}  warnings / flagged markers")
    for kind, size, seed in _bodies(args.quick, args.first_seed):
        row = run_one(kind, size, seed)
        rows.append(row)
        note = ", ".join(row["warnings"]) + (f" {row['flagged']}" if row["flagged"] else "")
        if row["pose_exchanges"]:
            note = f"({row['pose_exchanges']} pose exchange(s)) " + note
        if row["count_rule"] == "split":
            note = f"(split from {row['split_from']} after the rigid fit) " + note
        print(f"{kind:>12} {size:>4} {seed:>4} {row['segments']:>4}/{row['true_segments']:<4} "
              f"{row['seg']!s:>5} {row['tree']!s:>5}  {note}", flush=True)
    wrong = [r for r in rows if not (r["seg"] and r["tree"])]
    silent = [r for r in wrong if not set(r["warnings"]) & FIT_WARNINGS]
    print(f"{len(rows) - len(wrong)} of {len(rows)} exact; {len(wrong)} wrong, {len(silent)} of them without a warning "
          "about the fit")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
