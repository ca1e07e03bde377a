"""Accuracy against soft-tissue artefact, with the floor a marker-only method can reach.

Data: ``jaxskel.synth.full_body`` (15 segments, 46 markers), 30 s calibration motion at
120 Hz, 2 mm noise, 2 gaps per marker, soft tissue of RMS amplitude 0-5 mm per marker
(``synth.simulate(soft_tissue=...)``: each marker slides in its segment frame with the
angles of the joints touching that segment, plus a slow wobble).

Two estimates of the same quantities on the same recordings:

* ``jaxskel``: :func:`jaxskel.fit_skeleton` with its defaults (segment count by
  eigengap, topology, joint solve, rigid skeleton, IK);
* ``floor``: the oracle of ``tests/soft_tissue_floor.py``, which is *given* every
  marker's segment and true offset and the true tree, poses each cluster by Horn's
  alignment and solves each joint by least squares on those poses (hinges pinned along
  their axis to the truth). Soft tissue that moves with the joint angles is, to first
  order, indistinguishable from a shifted joint centre, so this is an estimate of what
  marker data allows; it cannot pose a segment with fewer than three markers (the hands),
  so the comparison is over the other 12 joints and 15 bones.

Measures (``tests/soft_tissue_floor.py``): per joint the RMS distance of the centre
from the truth over frames (hinges: from the axis line), per bone the relative length
error; means over joints and bones, and the worst. The issue's targets (joint RMSE < 5
mm, mean bone error < 0.5 %) are drawn on the figure. Beside them, how many of the 17 bone
errors lie within the bound the fit itself reports (:func:`jaxskel.joints.bone_uncertainty`).

Usage::

    python bench/bench_soft_tissue.py                  # 0-5 mm x seeds 0-2 (~12 min on 2 cores)
    python bench/bench_soft_tissue.py --quick          # 3 mm, seed 0, 10 s
    python bench/bench_soft_tissue.py --json out.json --plot out.png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import warnings
from pathlib import Path

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # soft_tissue_floor

import jaxskel  # noqa: E402
from jaxskel import synth  # noqa: E402
from soft_tissue_floor import fitted_errors, floor_skeleton  # noqa: E402

TARGET_JOINT_MM, TARGET_BONE_PCT = 5.0, 0.5


def run_one(amplitude: float, seed: int, duration: float) -> dict:
    """Fit one recording and evaluate the fit and the oracle on it."""
    trial, truth = synth.simulate(
        synth.full_body(seed=seed), duration=duration, seed=seed, noise=0.002, soft_tissue=amplitude, gaps=2
    )
    floor = floor_skeleton(trial, truth)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial, seed=seed)
    fit = fitted_errors(result, trial, truth)
    joints = np.isfinite(floor["joint_rmse"])
    bones = np.isfinite(floor["bone_error"])
    row = {
        "amplitude_mm": amplitude * 1e3,
        "seed": seed,
        "segments": int(result.n_segments),
        "segments_true": int(truth.n_segments),
        "joints_found": int(np.isfinite(fit["joint_rmse"]).sum()),
    }
    for name, errors in (("jaxskel", fit), ("floor", floor)):
        j, b = errors["joint_rmse"] * 1e3, errors["bone_error"] * 100
        row[name] = {
            "joint_mm_mean": float(np.mean(j[joints])),
            "joint_mm_max": float(np.max(j[joints])),
            "bone_pct_mean": float(np.mean(b[bones])),
            "bone_pct_max": float(np.max(b[bones])),
        }
    j, b = fit["joint_rmse"] * 1e3, fit["bone_error"] * 100
    row["jaxskel_all"] = {  # every joint and bone, hands included (nan: the fit missed it)
        "joint_mm_mean": float(np.mean(j)),
        "joint_mm_max": float(np.max(j)),
        "bone_pct_mean": float(np.mean(b)),
        "bone_pct_max": float(np.max(b)),
        # the fit's own bound on each bone (jaxskel.joints.bone_uncertainty), and how many errors it covers
        "bone_bound_pct_median": float(np.nanmedian(fit["bone_bound"]) * 100),
        "bones_within_bound": int(np.sum(fit["bone_error"] < fit["bone_bound"])),
        "bones": int(np.isfinite(fit["bone_error"]).sum()),
    }
    return row


def _table(rows: list[dict]) -> str:
    lines = [
        "| soft tissue mm | seed | segments | jaxskel joint mm mean / max | floor joint mm mean / max "
        "| jaxskel bone % mean / max | floor bone % mean / max | bone ratio jaxskel / floor "
        "| jaxskel, all 14 joints / 17 bones: joint mm max, bone % mean | bones within the fit's bound (median bound %) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        f, o, a = r["jaxskel"], r["floor"], r["jaxskel_all"]
        lines.append(
            f"| {r['amplitude_mm']:.0f} | {r['seed']} | {r['segments']}/{r['segments_true']} "
            f"| {f['joint_mm_mean']:.2f} / {f['joint_mm_max']:.1f} | {o['joint_mm_mean']:.2f} / {o['joint_mm_max']:.1f} "
            f"| {f['bone_pct_mean']:.2f} / {f['bone_pct_max']:.2f} | {o['bone_pct_mean']:.2f} / {o['bone_pct_max']:.2f} "
            f"| {f['bone_pct_mean'] / o['bone_pct_mean']:.2f} | {a['joint_mm_max']:.1f}, {a['bone_pct_mean']:.2f} "
            f"| {a['bones_within_bound']}/{a['bones']} ({a['bone_bound_pct_median']:.1f}) |"
        )
    return "\n".join(lines)


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    amps = sorted({r["amplitude_mm"] for r in rows})
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, target, label in (
        (axes[0], "joint_mm_mean", TARGET_JOINT_MM, "mean joint-centre RMSE [mm]"),
        (axes[1], "bone_pct_mean", TARGET_BONE_PCT, "mean bone-length error [%]"),
    ):
        for name, style in (("jaxskel", "o-"), ("floor", "s--")):
            values = [[r[name][key] for r in rows if r["amplitude_mm"] == a] for a in amps]
            mean = [np.mean(v) for v in values]
            ax.plot(amps, mean, style, label=name if name == "jaxskel" else "floor (oracle, given the offsets)")
            for a, v in zip(amps, values):
                ax.plot([a] * len(v), v, ".", color=ax.lines[-1].get_color(), alpha=0.5)
        ax.axhline(target, color="k", lw=0.8, ls=":", label="issue target")
        ax.set_xlabel("soft-tissue artefact, RMS per marker [mm]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Synthetic full body, 30 s calibration, 2 mm noise, gaps (12 joints / 15 bones the oracle can pose)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3 mm, seed 0, 10 s")
    ap.add_argument("--amplitudes", type=float, nargs="+", default=[0.0, 1.0, 2.0, 3.0, 5.0], help="mm")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--plot", type=Path, help="write the accuracy-vs-amplitude figure here")
    args = ap.parse_args()
    if args.quick:
        args.amplitudes, args.seeds, args.duration = [3.0], [0], 10.0
    rows = []
    for amplitude in args.amplitudes:
        for seed in args.seeds:
            rows.append(run_one(amplitude * 1e-3, seed, args.duration))
            r = rows[-1]
            print(
                f"soft tissue {amplitude:.0f} mm seed {seed}: bone error jaxskel {r['jaxskel']['bone_pct_mean']:.2f} % "
                f"floor {r['floor']['bone_pct_mean']:.2f} %, joint RMSE jaxskel {r['jaxskel']['joint_mm_mean']:.2f} mm "
                f"floor {r['floor']['joint_mm_mean']:.2f} mm",
                flush=True,
            )
    print()
    print(_table(rows))
    results = {
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "duration_s": args.duration,
        "noise_mm": 2.0,
        "rows": rows,
    }
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
        args.json.with_suffix(".md").write_text(_table(rows) + "\n")
    if args.plot:
        _plot(rows, args.plot)


if __name__ == "__main__":
    main()
