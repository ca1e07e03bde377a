"""Trees on real recordings with standard marker sets, judged by body-part maps.

Each recording is fitted with :func:`jaxskel.fit_skeleton` defaults (no IK) and judged
with the body-part maps of ``tests/human_markers.py`` (test data; the package never
reads marker names): ``bad edges`` joins of body parts not adjacent in a human body,
``misplaced`` markers grouped with a body part they are not on (unless the recording
keeps them rigid with it: a wrist it never bends). Printed per recording
with the segment count, the groups, the tree and the fit time; HDM_bd's limb bones are
compared with ``HDM_bd.asf``.

Usage::

    python bench/real_trees.py                 # all recordings below (~12 min on 2 cores)
    python bench/real_trees.py --only 85_12    # names containing a string
    python bench/real_trees.py --json out.json
    python bench/real_trees.py --markdown docs/bench/real_trees.md
    python bench/real_trees.py --halves --markdown docs/bench/real_trees_halves.md

``--halves`` fits the first and the second half of each recording instead, each as a take
of its own: the same marker set and subject in a motion the whole-recording fit did not
see in full (issue 42 asks for right trees on unseen takes of these marker sets).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from human_markers import (  # noqa: E402
    asf_bone_lengths, bone_index_by_part, implausible_edges, misplaced_markers, segment_parts,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

#: Full-body recordings with a standard marker set (issue 42).
RECORDINGS = (
    "auto_marker_label/KneeltoProne01.c3d",
    "auto_marker_label/PronetoRun01.c3d",
    "nimblephysics/cmu_02_05.c3d",
    "c3d_to_xyz_cmu/01_01.c3d",
    "numediart/85_12.c3d",
    "numediart/HDM_bd_05-01_01_120.c3d",
    "dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d",
    # Vicon Plug-in-Gait (the CMU set's names, ASI/PSI/TIB for WT/SHN)
    "nimblephysics/squat.c3d",
    "pycgm/Movement_trial.c3d",
    "kineticstoolkit/kinematics_tennis_serve.c3d",
    "kineticstoolkit/kinematics_basket_sprint.c3d",
    # numediart's 68-marker set: four-marker thigh and shank clusters, ISB landmarks
    "numediart/03_rolling.c3d",
)
ASF = {"HDM_bd_05": "jointlearning_hdm05/HDM_bd.asf", "HDM_dg_06": "dynamic_clustering_hdm05/HDM_dg.asf",
       "cmu_02_05": "timegan_cmu/02.asf"}
ASF_BONES = {"thigh": ("femur",), "shank": ("tibia",), "upper arm": ("humerus",), "forearm": ("radius", "wrist")}


#: ``--halves``: the frames of each half, as a fraction of the recording.
HALVES = {"first half": (0.0, 0.5), "second half": (0.5, 1.0)}


def judge(rel: str, window: str | None = None, **fit_kwargs) -> dict:
    trial = jaxskel.load(DATA / rel)
    if window is not None:
        lo, hi = HALVES[window]
        trial = trial.select_frames(slice(int(lo * trial.n_frames), int(hi * trial.n_frames)))
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial, ik=False, **fit_kwargs)
    seconds = time.perf_counter() - t0
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    parts = segment_parts(labels, seg)
    out = {
        "recording": rel, "window": window, "frames": int(trial.n_frames), "seconds": round(seconds, 1),
        "segments": int(result.n_segments),
        "count_rule": result.segmentation.count_rule,
        "groups": [[lab.split(":")[-1] for lab, g in zip(labels, seg) if g == s] for s in range(result.n_segments)],
        "parts": parts,
        "edges": [[parts[a] or str(a), parts[b] or str(b)] for a, b in np.asarray(result.edges).tolist()],
        "bad_edges": [list(e) for e in implausible_edges(labels, seg, result.edges)],
        "misplaced": [list(m) for m in misplaced_markers(
            labels, seg, result.segmentation.distance_std, result.segmentation.rigid_limit)],
        "warnings": sorted({type(w.message).__name__ for w in caught}),
    }
    key = next((k for k in ASF if k in rel), None)
    if key is not None:
        reference = asf_bone_lengths(DATA / ASF[key])
        bones = {}
        for part, b in bone_index_by_part(result).items():
            names = [part[0].lower() + bone for bone in ASF_BONES[part[2:]]]
            if all(n in reference for n in names):
                bones[part] = round(1e3 * (float(result.skeleton.bone_lengths[b]) - sum(reference[n] for n in names)), 1)
        out["bone_error_mm"] = bones
    return out


def main(argv=None) -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="")
    parser.add_argument("--json")
    parser.add_argument("--markdown", help="write the table (and the groups and trees) here")
    parser.add_argument("--halves", action="store_true", help="fit each half of every recording as a take of its own")
    args = parser.parse_args(argv)
    rows = []
    windows = tuple(HALVES) if args.halves else (None,)
    for rel in RECORDINGS:
        if args.only not in rel:
            continue
        for window in windows:
            rows.append(_report(judge(rel, window)))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(markdown(rows, halves=args.halves))


def _report(row: dict) -> dict:
    """Print one judged fit; returns it."""
    rel = row["recording"] + (f" ({row['window']}, {row['frames']} frames)" if row["window"] else "")
    print(f"\n{rel}: {row['segments']} segments ({row['count_rule']}), {row['seconds']} s, "
          f"{len(row['bad_edges'])} bad edges, {len(row['misplaced'])} misplaced; {row['warnings']}")
    for s, (p, g) in enumerate(zip(row["parts"], row["groups"])):
        print(f"   {s:2d} {p!s:12s} {' '.join(g)}")
    print("   edges:", "; ".join(f"{a}-{b}" for a, b in row["edges"]))
    print("   bad:", row["bad_edges"], "misplaced:", row["misplaced"])
    if "bone_error_mm" in row:
        print("   bone error vs asf [mm]:", row["bone_error_mm"])
    sys.stdout.flush()
    return row


def markdown(rows: list[dict], halves: bool = False) -> str:
    """The table of :func:`main`'s rows, then each recording's groups and tree."""
    command = "python bench/real_trees.py" + (" --halves" if halves else "")
    lines = [
        f"# Trees on real recordings with standard marker sets (`{command}`)",
        "",
        f"Written {time.strftime('%Y-%m-%d')} by `bench/real_trees.py` on a 2-core CPU; `fit_skeleton(trial, ik=False)`",
        "defaults; edges and groups judged with the body-part maps of `tests/human_markers.py` (test data).",
        "",
        "| recording | frames | segments | count rule | implausible joints | misplaced markers | fit s |",
        "|---|---|---|---|---|---|---|",
    ]

    def name(r: dict) -> str:
        return f"`{r['recording']}`" + (f", {r['window']}" if r.get("window") else "")

    for r in rows:
        lines.append(f"| {name(r)} | {r.get('frames', '')} | {r['segments']} | {r['count_rule']} | "
                     f"{len(r['bad_edges'])} | {len(r['misplaced'])} | {r['seconds']} |")
    for r in rows:
        lines += ["", f"## {name(r)}", ""]
        lines += [f"* {p}: {' '.join(g)}" for p, g in zip(r["parts"], r["groups"])]
        lines.append(f"* tree: {'; '.join(f'{a}-{b}' for a, b in r['edges'])}")
        lines.append(f"* implausible: {r['bad_edges'] or 'none'}; misplaced: {r['misplaced'] or 'none'}")
        if "bone_error_mm" in r:
            lines.append(f"* limb bones against the .asf (fitted - asf, mm): {r['bone_error_mm']}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
