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
  fraction reads as an amount of motion.

Printed with the warnings of each fit, so a wrong answer that says nothing stands out.

Usage::

    python bench/sweep_motion_range.py                 # ~5 min on 2 cores
    python bench/sweep_motion_range.py --seeds 0 --json out.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

import jaxskel
from jaxskel import synth

FRACTIONS = (1.0, 0.5, 0.3, 0.2, 0.1)
NOISE, SOFT_TISSUE = 0.002, 0.001


def _on_joint(truth, tol: float) -> dict[str, int]:
    """Markers moving less than ``tol`` (RMS, m) in a neighbouring segment's frame ->
    that neighbour (noise-free poses of the truth)."""
    body = truth.body
    rot, shift = np.asarray(truth.segment_rotations), np.asarray(truth.segment_translations)
    out = {}
    for i, (label, s) in enumerate(zip(body.marker_labels, body.marker_segment)):
        world = np.einsum("fij,j->fi", rot[:, s], body.marker_offsets[i]) + shift[:, s]
        for edge in np.asarray(body.edges):
            if s in edge:
                other = int(edge[1] if edge[0] == s else edge[0])
                local = np.einsum("fji,fj->fi", rot[:, other], world - shift[:, other])
                if np.sqrt(np.mean(np.sum((local - local.mean(0)) ** 2, axis=1))) < tol:
                    out[label] = other
    return out


def _homes(labels, fitted, truth) -> dict[int, int] | None:
    """True segment -> the fitted group holding it, if every fitted group is a union of
    whole true segments (markers on joint centres allowed on either side); else None."""
    true_of = dict(zip(truth.body.marker_labels, truth.body.marker_segment))
    either = _on_joint(truth, float(np.sqrt(3 * NOISE**2 + 3 * SOFT_TISSUE**2)))
    group_of_segment: dict[int, set] = {}
    for label, g in zip(labels, fitted):
        if label not in either:
            group_of_segment.setdefault(int(true_of[label]), set()).add(int(g))
    if any(len(v) > 1 for v in group_of_segment.values()):
        return None  # a true segment's own markers in two groups
    home = {s: next(iter(v)) for s, v in group_of_segment.items()}
    placed = all(
        int(g) in (home.get(int(true_of[label])), home.get(either[label])) for label, g in zip(labels, fitted)
        if label in either
    )
    return home if placed else None


def run_one(seed: int, motion: str, fraction: float) -> dict:
    body = synth.full_body(seed=seed)
    joint_range = {name: fraction for name in body.joint_names}
    trial, truth = synth.simulate(
        body, motion, duration=30.0, seed=seed, noise=NOISE, soft_tissue=SOFT_TISSUE, gaps=2, joint_range=joint_range
    )
    excursion = [np.degrees(np.max(np.ptp(a, axis=0))) for a in truth.joint_angles]
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial, ik=False)
    seconds = time.perf_counter() - start
    labels = list(result.trial.labels)
    true_seg = truth.marker_segment[[trial.labels.index(lab) for lab in labels]]
    fitted = result.segmentation.marker_segment
    home = _homes(labels, fitted, truth)
    # The truth's tree with the joined segments contracted: what a coarser fit should find.
    contracted = home is not None and len(home) == len(truth.edges) + 1 and {
        frozenset(map(int, e)) for e in result.edges
    } == {frozenset((home[int(a)], home[int(b)])) for a, b in truth.edges if home[int(a)] != home[int(b)]}

    def partition(groups):
        out: dict[int, set] = {}
        for lab, g in zip(labels, groups):
            out.setdefault(int(g), set()).add(lab)
        return {frozenset(v) for v in out.values()}

    return {
        "seed": seed, "motion": motion, "fraction": fraction,
        "range_deg": round(float(np.median(excursion)), 1),
        "segments": result.n_segments, "true_segments": len(truth.edges) + 1,
        "seg": partition(fitted) == partition(true_seg),
        "coarser": home is not None,
        "tree": contracted,
        "warnings": sorted({w.category.__name__ for w in caught}),
        "seconds": round(seconds, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    cases = [(seed, "calibration", f) for f in FRACTIONS for seed in args.seeds]
    cases += [(seed, "walk", 1.0) for seed in args.seeds]
    rows = []
    print(f"{'motion':>11} {'fraction':>8} {'range':>6} {'seed':>4} {'segs':>6} {'seg':>5} {'tree':>5} {'coarser':>7}  warnings")
    for seed, motion, fraction in cases:
        row = run_one(seed, motion, fraction)
        rows.append(row)
        print(f"{motion:>11} {fraction:>8} {row['range_deg']:>6} {seed:>4} {row['segments']:>3}/{row['true_segments']:<2} "
              f"{row['seg']!s:>5} {row['tree']!s:>5} {row['coarser']!s:>7}  {', '.join(row['warnings'])}", flush=True)
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
