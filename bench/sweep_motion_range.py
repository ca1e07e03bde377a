"""How much joint motion the automatic fit needs: full bodies at shrinking joint ranges.

The segmentation tells segments apart by how much their markers' distances vary
(``A_ij``), against a rigidity limit of 3 sigma >= 9 mm that soft tissue on real
recordings needs (``segment_markers(sigma_min=0.003)``). A joint that moves its
markers' distances by less than that is read as rigid and its two segments come out
as one. This sweep measures where that starts: ``synth.full_body`` under the issue's
recording conditions (30 s calibration motion at 120 Hz, 2 mm noise, 1 mm soft tissue,
2 gaps per marker) with every joint's excursion scaled by ``fraction``
(``simulate(joint_range=...)``), and the walk (``motion="walk"``: wrists and neck
nearly still, elbows near extension), each fitted with :func:`jaxskel.fit_skeleton`
defaults (no IK) and judged on the truth:

* ``segs``: segments found / true;
* ``seg``: the grouping is exact;
* ``coarser``: every fitted group is a union of whole true segments -- the skeleton is
  coarser than the truth (or exact) but not wrong -- with a marker that moves less than
  the recording's artefact in a neighbour's frame (on a joint centre) allowed on either side;
* ``tree``: the fitted tree is the true one with the joined segments contracted (the
  true tree when nothing is joined);
* ``range``: the median over joints of each joint's largest excursion (degrees), so a
  fraction reads as an amount of motion;
* ``undet``: how many joints the fit names undetermined (:mod:`jaxskel.joints._determination`:
  centre fixed only to within more than 10 cm).

Printed with the warnings of each fit, so a wrong answer that says nothing stands out.

Usage::

    python bench/sweep_motion_range.py                 # ~5 min on 2 cores
    python bench/sweep_motion_range.py --seeds 0 --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxskel import synth

sys.path.insert(0, str(Path(__file__).resolve().parent))  # sweep_bodies, also under python -m
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import marker_artefact, partition, whole_segment_homes  # noqa: E402
from sweep_bodies import fit_recorded  # noqa: E402

FRACTIONS = (1.0, 0.5, 0.3, 0.2, 0.1)
NOISE, SOFT_TISSUE = 0.002, 0.001


def run_one(seed: int, motion: str, fraction: float) -> dict:
    body = synth.full_body(seed=seed)
    joint_range = {name: fraction for name in body.joint_names}
    trial, truth = synth.simulate(
        body, motion, duration=30.0, seed=seed, noise=NOISE, soft_tissue=SOFT_TISSUE, gaps=2, joint_range=joint_range
    )
    excursion = [np.degrees(np.max(np.ptp(a, axis=0))) for a in truth.joint_angles]
    result, caught, seconds, labels, true_seg = fit_recorded(trial, truth)
    fitted = result.segmentation.marker_segment
    home = whole_segment_homes(labels, fitted, truth, marker_artefact(NOISE, SOFT_TISSUE))
    # The truth's tree with the joined segments contracted: what a coarser fit should find.
    contracted = home is not None and len(home) == len(truth.edges) + 1 and {
        frozenset(map(int, e)) for e in result.edges
    } == {frozenset((home[int(a)], home[int(b)])) for a, b in truth.edges if home[int(a)] != home[int(b)]}

    return {
        "seed": seed, "motion": motion, "fraction": fraction,
        "range_deg": round(float(np.median(excursion)), 1),
        "segments": result.n_segments, "true_segments": len(truth.edges) + 1,
        "seg": partition(labels, fitted) == partition(labels, true_seg),
        "coarser": home is not None,
        "tree": contracted,
        "warnings": sorted({w.category.__name__ for w in caught}),
        "undetermined": len(result.undetermined_joints()),
        "seconds": round(seconds, 1),
    }


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--walk-seeds", type=int, nargs="*", default=[],
                        help="more seeds for the walk alone (e.g. 3 4 5 6 7 15, the walks of docs/bench/motion_range.md)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    cases = [(seed, "calibration", f) for f in FRACTIONS for seed in args.seeds]
    cases += [(seed, "walk", 1.0) for seed in [*args.seeds, *args.walk_seeds]]
    rows = []
    print(f"{'motion':>11} {'fraction':>8} {'range':>6} {'seed':>4} {'segs':>6} {'seg':>5} {'tree':>5} {'coarser':>7} "
          f"{'undet':>5}  warnings")
    for seed, motion, fraction in cases:
        row = run_one(seed, motion, fraction)
        rows.append(row)
        print(f"{motion:>11} {fraction:>8} {row['range_deg']:>6} {seed:>4} {row['segments']:>3}/{row['true_segments']:<2} "
              f"{row['seg']!s:>5} {row['tree']!s:>5} {row['coarser']!s:>7} {row['undetermined']:>5}  "
              f"{', '.join(row['warnings'])}", flush=True)
    # exact: the true groups (up to markers on joint centres) and tree; coarser: whole
    # segments joined and the contracted tree; anything else is wrong
    exact = [r for r in rows if r["tree"] and r["segments"] == r["true_segments"]]
    coarse = [r for r in rows if r["tree"] and r not in exact]
    wrong = [r for r in rows if not r["tree"]]
    silent = [r for r in wrong if not r["warnings"]]
    print(f"{len(rows)} fits: {len(exact)} exact (up to markers on joints), {len(coarse)} coarser and right (whole segments joined, "
          f"the contracted tree), "
          f"{len(wrong)} wrong ({len(silent)} of them without a warning)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
