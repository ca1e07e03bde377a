"""Benchmark the joint-cost solvers: block-arrow Levenberg–Marquardt vs nonlinear CG.

Data: ``jaxskel.synth.full_body`` (15 segments, 46 markers), calibration motion at
120 Hz with 1 mm noise. Cases, as in the topology pass and the tree-joint pass:

* 1 pair (the left hip: pelvis + thigh markers, a ball joint) x 1,200 frames (every 10th frame);
* 1 pair x 12,000 frames (100 s);
* 105 pairs (all pairs of the 15 segments) x 300 frames, markers padded to the
  largest pair's bucket, solved in one vmapped call.

"cold" includes tracing and XLA compilation (first call for that shape), "warm" is
the second call. Each solver is run to its own convergence criterion with default
tolerances (LM capped at 256 steps, NCG at 20,000); ``lm@60`` is the capped LM the
topology pass runs on all pairs. ``conv`` counts pairs whose solver met its criterion
and whose Newton decrement is below 1e-6 of the cost. The cost reported is Q averaged over pairs;
``joint err`` is the RMS distance to the true joint centre for true-joint pairs.

Usage::

    python bench/bench_jointcost.py            # full run, prints a table
    python bench/bench_jointcost.py --quick    # small shapes for CI
    python bench/bench_jointcost.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxskel import synth  # noqa: E402

from jaxskel._math.padding import bucket_size
from jaxskel.joints._cost import solve_joints  # noqa: E402

ALPHA = 1e-4


def pair_arrays(trial, truth, frames, pairs):
    """Markers of each segment pair (P, F, K, 3), mask, and the true joint (P, F, 3) or NaN."""
    x, mask = trial.to_arrays()
    segment = np.asarray(truth.marker_segment)
    members = [np.flatnonzero(segment == s) for s in range(len(truth.segment_names))]
    k = bucket_size(max(len(members[a]) + len(members[b]) for a, b in pairs), minimum=4)
    xs = np.zeros((len(pairs), len(frames), k, 3))
    ms = np.zeros((len(pairs), len(frames), k), bool)
    joints = np.full((len(pairs), len(frames), 3), np.nan)
    edges = {tuple(e): j for j, e in enumerate(np.asarray(truth.edges))}
    for p, (a, b) in enumerate(pairs):
        cols = np.concatenate([members[a], members[b]])
        xs[p, :, : len(cols)] = x[frames][:, cols]
        ms[p, :, : len(cols)] = mask[frames][:, cols]
        j = edges.get((a, b), edges.get((b, a)))
        if j is not None:
            joints[p] = np.asarray(truth.joint_positions)[frames, j]
    return xs, ms, joints


def timed(fn):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def run_case(name, xs, ms, joints, variants=(("lm", None), ("ncg", None))):
    """Time each (method, max_steps) variant cold and warm; ratios are against the first."""
    rows = []
    for method, max_steps in variants:
        solve = lambda: solve_joints(xs, ms, alpha=ALPHA, method=method, max_steps=max_steps)  # noqa: E731
        _, cold = timed(solve)
        sol, warm = timed(solve)
        true_pair = np.isfinite(joints[:, 0, 0])
        err = np.sqrt(np.mean(np.sum((np.asarray(sol.positions) - joints) ** 2, -1), -1))
        rows.append(
            dict(
                case=name,
                method=method if max_steps is None else f"{method}@{max_steps}",
                cold_s=cold,
                warm_s=warm,
                steps_max=int(np.max(sol.steps)),
                steps_mean=float(np.mean(sol.steps)),
                converged=int(np.sum(sol.converged)),
                pairs=int(xs.shape[0]),
                cost_mean=float(np.mean(sol.cost)),
                residual_max=float(np.max(sol.residual)),
                joint_err_mm=float(1e3 * np.mean(err[true_pair])) if true_pair.any() else float("nan"),
            )
        )
    lm = rows[0]
    for row in rows:
        row["warm_vs_lm"] = row["warm_s"] / lm["warm_s"]
        row["cost_vs_lm"] = row["cost_mean"] / lm["cost_mean"] - 1.0
    return rows


def main(argv=None):
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small shapes (CI smoke run)")
    parser.add_argument("--json", help="write the rows to this JSON file")
    args = parser.parse_args(argv)

    long_frames = 1200 if args.quick else 12000
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, motion="calibration", duration=long_frames / 120.0, noise=1e-3, seed=0)
    names = list(truth.segment_names)
    hip = next(tuple(e) for e in np.asarray(truth.edges) if names[e[1]] == "l_thigh")
    segments = len(names)
    all_pairs = [(a, b) for a in range(segments) for b in range(a + 1, segments)]

    cases = [
        (f"1 pair x {long_frames // 10} frames", [hip], np.arange(0, long_frames, 10)),
        (f"1 pair x {long_frames} frames", [hip], np.arange(long_frames)),
        (f"{len(all_pairs)} pairs x 300 frames", all_pairs, np.linspace(0, long_frames - 1, 300).astype(int)),
    ]
    if args.quick:
        cases = cases[:1]
    rows = []
    for name, pairs, frames in cases:
        xs, ms, joints = pair_arrays(trial, truth, frames, pairs)
        variants = [("lm", None), ("ncg", None)]
        if len(pairs) > 1:  # the topology pass caps the all-pairs solve (jaxskel.joints._topology uses 60)
            variants.insert(1, ("lm", 60))
        rows += run_case(name, xs, ms, joints, variants)

    header = (
        f"{'case':<24}{'method':<8}{'cold s':>8}{'warm s':>9}{'x LM':>7}{'steps max':>10}{'mean':>8}"
        f"{'conv':>7}{'cost mean':>12}{'vs LM':>10}{'joint err':>11}"
    )
    platform = jax.devices()[0].platform
    print(f"joint cost, alpha={ALPHA}, float64, {platform}, single pair = {names[hip[0]]}-{names[hip[1]]} (ball joint)")
    print(header)
    for r in rows:
        print(
            f"{r['case']:<24}{r['method']:<8}{r['cold_s']:8.2f}{r['warm_s']:9.3f}{r['warm_vs_lm']:7.1f}"
            f"{r['steps_max']:10d}{r['steps_mean']:8.0f}{r['converged']:>4d}/{r['pairs']:<2d}"
            f"{r['cost_mean']:12.4e}{r['cost_vs_lm']:10.1e}{r['joint_err_mm']:9.2f}mm"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
