"""One cluster marker that soft tissue moves far more than the others: how far does it pull the joints?

Data: ``jaxskel.synth.full_body`` (15 segments, 46 markers, three on each thigh), calibration
motion at 120 Hz, 0.5 mm noise and 1 mm soft tissue on every marker, and on one thigh marker
(``LTHF``) a further soft-tissue displacement of RMS ``amplitude`` (the model of
``synth.simulate(soft_tissue=...)``: driven by the angles of the joints touching the thigh,
plus a slow wobble). Such a marker is often split off its cluster by the segmentation
and hung from the thigh as a one-marker segment, which leaves the thigh two markers.

Per case: :func:`jaxskel.fit_skeleton` with its defaults; whether the marker was split
off; the RMS distance over frames between the fitted and the true centre of the knee
(IK joints), all of it and along the knee's axis, and the angle between the fitted knee axis
and the true one (where the fit placed the knee as a hinge); the worst of the other joints; and,
where the marker is alone, the weight its joint got in the thigh's alignment and its
scatter there (``skeleton.diagnostics["attachment_weight"]``, ``["attachment_scatter"]``).

Usage::

    python bench/wobbling_marker.py                      # 15 mm over 10 s, 30 mm over 20 s, seeds 0-2
    python bench/wobbling_marker.py --json out.json --markdown docs/bench/wobbling_marker.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # soft_tissue_floor, wobble

from soft_tissue_floor import segment_map  # noqa: E402
from wobble import wobbling_trial  # noqa: E402

import jaxskel  # noqa: E402
from jaxskel._math.rotation import quat_to_matrix  # noqa: E402

#: (seconds, RMS displacement in metres) of the wobbling marker
CASES = ((10.0, 0.015), (20.0, 0.03))
MARKER = "LTHF"
KNEE = ("LTHI", "LTIB")  # a marker of each of the knee's segments


def run_one(seed: int, duration: float, amplitude: float) -> dict:
    trial, truth = wobbling_trial(seed, duration, amplitude, MARKER)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial)
    seconds = time.perf_counter() - t0
    labels = list(result.trial.labels)
    seg = np.asarray(result.segmentation.marker_segment)
    seg_map = segment_map(result, trial, truth)
    true_joint = {frozenset(map(int, e)): j for j, e in enumerate(truth.edges)}
    knee_true = true_joint[frozenset(int(truth.marker_segment[list(truth.physical_labels).index(m)]) for m in KNEE)]
    errors, knee = {}, None
    for j, (p, c) in enumerate(np.asarray(result.edges).tolist()):
        tj = true_joint.get(frozenset((seg_map[p], seg_map[c])), -1)
        if tj < 0:
            continue
        diff = result.motion.joint_positions[:, j] - truth.joint_positions[:, tj]
        errors[tj] = float(np.sqrt(np.nanmean(np.sum(diff**2, axis=-1))))
        if tj == knee_true:
            axis = truth.joint_axes_world[tj][:, 0]
            # the fitted hinge axis (parent frame) in the world, against the true one
            parent_rot = np.asarray(quat_to_matrix(np.asarray(result.motion.rotations)[:, p]))
            fitted = parent_rot @ np.asarray(result.skeleton.diagnostics["hinge_axis"][j])
            cos = np.abs(np.sum(fitted * axis, axis=-1)) / np.linalg.norm(fitted, axis=-1)
            knee = (errors[tj], float(np.sqrt(np.nanmean(np.sum(diff * axis, axis=-1) ** 2))),
                    float(np.degrees(np.arccos(min(np.nanmedian(cos), 1.0)))))
    alone = int(np.sum(seg == seg[labels.index(MARKER)])) == 1
    weight = scatter = None
    if alone:
        diag = result.skeleton.diagnostics
        j = next(k for k, e in enumerate(np.asarray(result.edges).tolist()) if seg[labels.index(MARKER)] in e)
        absent = [None] * len(result.edges)  # a fit from before these diagnostics
        weight, scatter = (diag.get(k, absent)[j] for k in ("attachment_weight", "attachment_scatter"))
    others = [e for tj, e in errors.items() if tj != knee_true]
    return {
        "seed": seed, "duration": duration, "amplitude_mm": 1e3 * amplitude, "segments": int(result.n_segments),
        "alone": alone, "knee_mm": None if knee is None else round(1e3 * knee[0], 1),
        "knee_along_axis_mm": None if knee is None else round(1e3 * knee[1], 1),
        "knee_axis_deg": None if knee is None or not np.isfinite(knee[2]) else round(knee[2], 1),
        "worst_other_mm": round(1e3 * max(others), 1) if others else None,
        "weight": weight, "scatter_mm": None if scatter is None else round(1e3 * scatter, 1),
        "seconds": round(seconds, 1),
    }


def markdown(rows: list[dict], before: list[dict] | None) -> str:
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        "# A wobbling cluster marker (`python bench/wobbling_marker.py`)",
        "",
        f"Written {time.strftime('%Y-%m-%d')} on {platform.machine()}, {os.cpu_count()} CPU cores (load {load}). "
        f"Synthetic full body, one thigh marker (`{MARKER}`) moved by soft tissue of the RMS given on top of 1 mm on "
        "every marker; `fit_skeleton` defaults. Knee: RMS distance of the fitted centre from the true one over "
        "frames, all of it and along the knee's axis. Weight: the weight of the lone marker's joint in the thigh's "
        "alignment (1 = a marker's), with its scatter there.",
        "",
        "| seconds | wobble mm | seed | segments | marker alone | knee mm (along axis) | knee axis deg | "
        "worst other joint mm | weight (scatter mm) |" + (" knee mm before (along axis) | knee axis deg before |"
                                                          if before else ""),
        "|---|---|---|---|---|---|---|---|---|" + ("---|---|" if before else ""),
    ]
    for k, r in enumerate(rows):
        weight = "-" if r["weight"] is None else f"{r['weight']:.2g} ({r['scatter_mm']})"
        line = (f"| {r['duration']:.0f} | {r['amplitude_mm']:.0f} | {r['seed']} | {r['segments']} | "
                f"{'yes' if r['alone'] else 'no'} | {r['knee_mm']} ({r['knee_along_axis_mm']}) | "
                f"{r['knee_axis_deg'] if r['knee_axis_deg'] is not None else '-'} | {r['worst_other_mm']} | {weight} |")
        if before:
            b = before[k]
            line += (f" {b['knee_mm']} ({b['knee_along_axis_mm']}) | "
                     f"{b['knee_axis_deg'] if b.get('knee_axis_deg') is not None else '-'} |")
        lines.append(line)
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--before", type=Path, help="a --json of an earlier run, shown beside (same cases)")
    args = ap.parse_args()
    rows = []
    for duration, amplitude in CASES:
        for seed in args.seeds:
            rows.append(run_one(seed, duration, amplitude))
            print(json.dumps(rows[-1]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    before = json.loads(args.before.read_text(encoding="utf-8")) if args.before else None
    text = markdown(rows, before)
    if args.markdown:
        args.markdown.write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
