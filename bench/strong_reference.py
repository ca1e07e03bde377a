"""jaxskel against a strong numpy reference (issue 48, item 1), stage by stage, in one process.

Usage::

    PYTHONPATH=. python bench/strong_reference.py --durations 10 120 \\
        [--no-scipy] [--workers N] [--json docs/bench/strong_reference.json] \\
        [--markdown docs/bench/strong_reference.md] [--append]

``--append`` adds the new durations to the records already in ``--json`` (e.g. a 600 s run
without scipy after the 10/120 s run) and writes the markdown of all of them.

For each duration: a synthetic noisy full body (``bench.cases.make_trial({"body": "full_body"},
seed=0, duration=D)``: 15 segments, 46 markers, 120 Hz, 2 mm noise, 3 mm soft tissue, two gaps
per marker), fitted in this one process by

* jaxskel: ``fit_skeleton(trial, ik=False, alpha=1e-5, topology_frames=300, seed=0)`` once to
  compile, then timed on the second call; stage times from ``result.timings``;
* the strong reference (:func:`bench.reference.schur.fit_strong`): the reference cleaning and
  segmentation, all-pairs joint costs on 300 frames and the tree joints on all frames by the
  batched Schur-complement Levenberg–Marquardt, scipy's MST, the Procrustes skeleton; run with
  one thread and with the default pool (``--workers``), the faster run reported;
* the scipy reference (:func:`bench.reference.fit_reference`, the same chain with
  ``scipy.optimize.least_squares`` per pair), unless ``--no-scipy``.

Ratios are reference seconds / jaxskel warm seconds (above 1: jaxskel faster). Accuracy of
each against the synthetic truth is :func:`bench.accuracy.evaluate` (as ``python -m bench``).
The work count (arithmetic of the LM stages) and the limit estimate are explained in the
markdown this writes.
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

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# As bench/worker.py: BLAS pools limited to one thread before numpy loads (unless set), for jaxskel
# and both references alike: on a shared 2-core machine multithreaded OpenBLAS calls on small
# arrays were measured many times slower (a first run of this script without it: the scipy
# reference's 10 s tree joints took 149 s, not ~4 s). The strong reference's own pool is its
# threads (--workers).
from bench.worker import THREAD_VARS, limit_blas  # noqa: E402

_SET_HERE = limit_blas()

import numpy as np  # noqa: E402

ALPHA = 1e-5
TOPOLOGY_FRAMES = 300
STAGES = {  # our name -> jaxskel result.timings name
    "clean": "clean",
    "segment": "segment",
    "joint_costs": "joint costs",
    "tree_joints": "tree joints",
    "rigid": "rigid",
}
LABELS = {
    "clean": "cleaning",
    "segment": "segmentation",
    "joint_costs": "all-pairs joint costs (300 frames)",
    "tree_joints": "MST + tree joints, all frames",
    "rigid": "rigid fit",
}


# ----------------------------------------------------------------------------- work count
def lm_flops(frames: int, markers: int, steps: int) -> float:
    """Floating-point operations of ``steps`` LM steps on one pair (F frames, K markers).

    Per frame and marker and step (the maths of ``jaxskel/joints/_cost_lm.py``, counted on
    ``bench/reference/schur.py``): geometry at the current joint 13 (3 sub, 5 for |v|^2,
    sqrt, 1/d, 3 for u), gradient and model 34 (e, beta(e + alpha/2), g_c 6, g_r 2, curvature
    3, A's six entries 15, -B 3), elimination 27 + 6K (A^-1 B 15, the Schur product
    sum_i B_i (A^-1 B)_i 6K, right-hand side 6, back-substitution 6), trial costs 47 (three
    candidate joints x 14: |v|^2, sqrt, (d - r')^2, weighted sum; and the kept joint 5): about
    121 + 6K, of which 4 square roots and 1 division. Per frame about 60 more (3x3 inverse,
    damping, selection of the candidates).
    """
    return float(steps) * frames * (markers * (121.0 + 6.0 * markers) + 60.0)


def special_ops(frames: int, markers: int, steps: int) -> float:
    """Square roots and divisions of the same steps (4 sqrt + 1 division per frame, marker, step)."""
    return 5.0 * steps * frames * markers


def jaxskel_work(result) -> dict:
    """What jaxskel's LM actually computes: padded shapes, chunks of pairs run to their slowest.

    All pairs: candidate pairs in row order, chunks of ``PAIR_CHUNK_CPU``, each padded to
    (f_pad, k_pad) and iterated until its slowest pair stops (a vmapped while loop). Tree
    joints: one joint per call on CPU, frames padded to four buckets per octave.
    """
    from jaxskel._math.padding import bucket_size
    from jaxskel.joints._topology import PAIR_CHUNK_CPU

    pc = result.topology.pair_costs
    sizes = np.bincount(result.segmentation.marker_segment, minlength=result.segmentation.n_segments)
    s = len(sizes)
    solved = [(a, b) for a in range(s) for b in range(a + 1, s) if pc.steps[a, b] > 0]
    kmax = max((int(sizes[a] + sizes[b]) for a, b in solved), default=4)
    k_pad = bucket_size(kmax, minimum=4, steps_per_octave=1)
    f_pad = len(pc.frames) if len(pc.frames) == TOPOLOGY_FRAMES else bucket_size(len(pc.frames))  # as all_pairs_problem
    flops = special = useful = 0.0
    for lo in range(0, len(solved), PAIR_CHUNK_CPU):
        chunk = solved[lo : lo + PAIR_CHUNK_CPU]
        slowest = max(int(pc.steps[a, b]) for a, b in chunk)
        flops += PAIR_CHUNK_CPU * lm_flops(f_pad, k_pad, slowest)
        special += PAIR_CHUNK_CPU * special_ops(f_pad, k_pad, slowest)
        useful += sum(lm_flops(len(pc.frames), int(sizes[a] + sizes[b]), int(pc.steps[a, b])) for a, b in chunk)
    pairs = {"gflop": flops / 1e9, "gspecial": special / 1e9, "useful_gflop": useful / 1e9,
             "pairs": len(solved), "f_pad": f_pad, "k_pad": k_pad, "chunk": PAIR_CHUNK_CPU,
             "steps_sum": int(sum(int(pc.steps[a, b]) for a, b in solved))}
    topo = result.topology
    n_frames = result.trial.n_frames
    ks = np.array([int(sizes[a] + sizes[b]) for a, b in topo.edges])
    kt_pad = bucket_size(int(ks.max(initial=4)), minimum=4, steps_per_octave=1)
    ft_pad = bucket_size(n_frames, steps_per_octave=4)
    steps = np.asarray(topo.steps, int)
    tree = {
        "gflop": sum(lm_flops(ft_pad, kt_pad, int(st)) for st in steps) / 1e9,
        "gspecial": sum(special_ops(ft_pad, kt_pad, int(st)) for st in steps) / 1e9,
        "useful_gflop": sum(lm_flops(n_frames, int(k), int(st)) for k, st in zip(ks, steps)) / 1e9,
        "joints": len(steps), "f_pad": ft_pad, "k_pad": kt_pad, "steps": steps.tolist(), "ks": ks.tolist(),
    }
    return {"joint_costs": pairs, "tree_joints": tree}


def strong_work(out: dict, n_frames: int) -> dict:
    """The strong reference's LM work: no padding of frames, K padded within chunks of similar K."""
    f1 = len(np.arange(0, n_frames, max(1, int(np.ceil(n_frames / TOPOLOGY_FRAMES)))))
    ks, steps = list(out["pair_ks"].values()), list(out["pair_steps"].values())
    pairs = {
        "gflop": sum(lm_flops(f1, k, st) for k, st in zip(ks, steps)) / 1e9,
        "gspecial": sum(special_ops(f1, k, st) for k, st in zip(ks, steps)) / 1e9,
        "pairs": len(ks), "frames": f1, "steps_sum": int(sum(steps)),
    }
    tree = {
        "gflop": sum(lm_flops(n_frames, k, st) for k, st in zip(out["tree_ks"], out["tree_steps"])) / 1e9,
        "gspecial": sum(special_ops(n_frames, k, st) for k, st in zip(out["tree_ks"], out["tree_steps"])) / 1e9,
        "joints": len(out["tree_steps"]), "steps": out["tree_steps"], "ks": out["tree_ks"],
    }
    return {"joint_costs": pairs, "tree_joints": tree}


def machine_rates() -> dict:
    """Single-core yardsticks of this machine: a float64 square root over an L2-resident array
    (ns each, numpy's SIMD loop) and dgemm (Gflop/s, OpenBLAS on one thread: the best a fused
    elementwise kernel could hope for)."""
    from threadpoolctl import threadpool_limits

    x = np.random.default_rng(0).random(32768) + 1.0
    out = np.empty_like(x)
    np.sqrt(x, out=out)
    reps = 400
    t0 = time.perf_counter()
    for _ in range(reps):
        np.sqrt(x, out=out)
    sqrt_ns = (time.perf_counter() - t0) / (reps * x.size) * 1e9
    a = np.random.default_rng(1).random((512, 512))
    with threadpool_limits(1):
        a @ a
        t0 = time.perf_counter()
        for _ in range(8):
            a @ a
        gemm = 8 * 2 * 512**3 / (time.perf_counter() - t0) / 1e9
    return {"sqrt_ns": sqrt_ns, "dgemm_gflops_1core": gemm}


# ----------------------------------------------------------------------------- runs
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_jaxskel(trial) -> tuple[dict, object]:
    import jaxskel

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        jaxskel.fit_skeleton(trial, ik=False, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES, seed=0)
        cold = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        res = jaxskel.fit_skeleton(trial, ik=False, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES, seed=0)
        warm, warm_cpu = time.perf_counter() - t0, time.process_time() - c0
    stages = {name: float(res.timings.get(key, 0.0)) for name, key in STAGES.items()}
    return {"cold_s": cold, "warm_s": warm, "warm_cpu_s": warm_cpu, "stages": stages,
            "other_s": warm - sum(stages.values())}, res


def run_strong(trial, workers) -> tuple[dict, dict]:
    from bench.reference.schur import fit_strong

    t0, c0 = time.perf_counter(), time.process_time()
    out = fit_strong(np.asarray(trial.positions, np.float64), trial.rate, alpha=ALPHA,
                     topology_frames=TOPOLOGY_FRAMES, seed=0, workers=workers)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"s": wall, "cpu_s": cpu, "stages": dict(out["timings"]), "cpu": dict(out["cpu"])}, out


def run_scipy(trial) -> tuple[dict, dict]:
    from bench.reference import fit_reference

    t0, c0 = time.perf_counter(), time.process_time()
    out = fit_reference(np.asarray(trial.positions, np.float64), trial.rate, alpha=ALPHA,
                        topology_frames=TOPOLOGY_FRAMES, seed=0, stages=tuple(STAGES))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"s": wall, "cpu_s": cpu, "stages": dict(out["timings"]), "cpu": dict(out["cpu"])}, out


def _same_joints(a: dict, b: dict) -> dict | None:
    """Joint positions and bone lengths of two reference outputs (same segmentation and tree):
    RMS over frames of the joint difference (mm, median/max over joints), bone-length difference (mm)."""
    if not (np.array_equal(a["marker_segment"], b["marker_segment"]) and np.array_equal(a["edges"], b["edges"])):
        return {"same_tree": False}
    pa, pb = a["joint_positions"], b["joint_positions"]
    ok = np.isfinite(pa).all(-1) & np.isfinite(pb).all(-1)
    rms = np.array([np.sqrt(np.mean(np.sum((pa[ok[:, j], j] - pb[ok[:, j], j]) ** 2, -1)))
                    for j in range(pa.shape[1])])
    out = {"same_tree": True,
           "joint_rms_diff_mm": {"median": float(np.median(rms) * 1e3), "max": float(rms.max() * 1e3)}}
    if "skeleton" in a and "skeleton" in b:
        out["bone_diff_mm_max"] = float(np.max(np.abs(a["skeleton"].bone_lengths - b["skeleton"].bone_lengths)) * 1e3)
    pc_a, pc_b = a["pair_cost"], b["pair_cost"]
    both = np.isfinite(pc_a) & np.isfinite(pc_b)
    rel = (pc_a[both] - pc_b[both]) / pc_b[both]
    out["pair_cost_rel_diff"] = {"median": float(np.median(rel)), "first_lower_fraction": float(np.mean(rel < -1e-3)),
                                 "second_lower_fraction": float(np.mean(rel > 1e-3))}
    return out


def _bones_from_joints(truth, labels, marker_segment, edges, joints, bones) -> dict:
    """Bone error (%) with each bone's length the median over frames of the distance between its two
    fitted joints: the joint stages' bones, before any rigid fit."""
    from bench.accuracy import evaluate

    bones = np.asarray(bones, int).reshape(-1, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        lengths = [float(np.nanmedian(np.linalg.norm(joints[:, a] - joints[:, b], axis=-1))) for a, b in bones]
    return evaluate(truth, labels, marker_segment, edges=edges, bones=bones, bone_lengths=lengths)["bone_error_pct"]


def run_duration(duration: float, scipy: bool, workers) -> dict:
    from bench.cases import make_trial
    from bench.pipeline import _agreement, _jaxskel_accuracy, _reference_accuracy

    trial, truth = make_trial({"body": "full_body"}, seed=0, duration=duration)
    rec: dict = {"duration_s": duration, "frames": trial.n_frames, "markers": trial.n_markers,
                 "load_avg_start": list(os.getloadavg())}
    print(f"--- {duration:g} s: {trial.n_frames} frames, {trial.n_markers} markers", flush=True)
    jx, res = run_jaxskel(trial)
    print(f"jaxskel warm {jx['warm_s']:.2f} s (cold {jx['cold_s']:.1f} s) {_fmt(jx['stages'])}", flush=True)
    runs = {}
    for w in sorted({1, workers}):
        runs[w] = run_strong(trial, w)
        print(f"strong ({w} thread{'s' if w > 1 else ''}) {runs[w][0]['s']:.2f} s {_fmt(runs[w][0]['stages'])}",
              flush=True)
    best = min(runs, key=lambda w: runs[w][0]["s"])
    strong, sout = runs[best]
    strong["workers"] = best
    strong["whole_s_by_workers"] = {str(w): r[0]["s"] for w, r in runs.items()}
    rec["jaxskel"], rec["strong"] = jx, strong
    jx_out = {"trial": res.trial, "segmentation": res.segmentation, "pairs": res.topology.pair_costs,
              "topology": res.topology, "skeleton": res.skeleton, "motion": None}
    rec["jaxskel"]["accuracy"] = _jaxskel_accuracy(jx_out, truth)
    rec["strong"]["accuracy"] = _reference_accuracy(sout, trial, truth)
    rec["jaxskel"]["accuracy"]["bone_from_joints_pct"] = _bones_from_joints(
        truth, res.trial.labels, res.segmentation.marker_segment, res.topology.edges,
        np.asarray(res.topology.joint_positions), res.skeleton.bones)
    ref_labels = [trial.labels[i] for i in sout["kept_markers"]]
    rec["strong"]["accuracy"]["bone_from_joints_pct"] = _bones_from_joints(
        truth, ref_labels, sout["marker_segment"], sout["edges"], sout["joint_positions"], sout["skeleton"].bones)
    rec["strong"]["agreement_with_jaxskel"] = _agreement(jx_out, sout, trial)
    rec["work"] = {"jaxskel": jaxskel_work(res), "strong": strong_work(sout, len(sout["x"]))}
    if scipy:
        ref, rout = run_scipy(trial)
        print(f"scipy   {ref['s']:.2f} s {_fmt(ref['stages'])}", flush=True)
        rec["scipy"] = ref
        rec["scipy"]["accuracy"] = _reference_accuracy(rout, trial, truth)
        rec["scipy"]["accuracy"]["bone_from_joints_pct"] = _bones_from_joints(
            truth, [trial.labels[i] for i in rout["kept_markers"]], rout["marker_segment"], rout["edges"],
            rout["joint_positions"], rout["skeleton"].bones)
        rec["scipy"]["agreement_with_jaxskel"] = _agreement(jx_out, rout, trial)
        rec["strong_vs_scipy"] = _same_joints(sout, rout)
    rec["load_avg_end"] = list(os.getloadavg())
    for name in ("strong", "scipy"):
        if name in rec:
            rec[name]["ratio"] = {st: rec[name]["stages"][st] / jx["stages"][st] for st in STAGES}
            rec[name]["ratio"]["whole"] = rec[name]["s"] / jx["warm_s"]
    print(f"ratios strong/jaxskel {_fmt(rec['strong']['ratio'], 'x')}", flush=True)
    if "scipy" in rec:
        print(f"ratios scipy/jaxskel  {_fmt(rec['scipy']['ratio'], 'x')}", flush=True)
    return rec


def _fmt(d: dict, unit: str = "") -> str:
    return " ".join(f"{k}={v:.2f}{unit}" for k, v in d.items())


# ----------------------------------------------------------------------------- report
def _acc_row(name: str, acc: dict) -> str:
    je, be, bj = acc.get("joint_error_mm", {}), acc.get("bone_error_pct", {}), acc.get("bone_from_joints_pct", {})
    return (f"| {name} | {acc['segmentation_ari']} | {acc.get('topology_correct')} | {je.get('median')} | "
            f"{je.get('max')} | {be.get('median')} | {be.get('max')} | {bj.get('median')} | {bj.get('max')} |")


def markdown(payload: dict) -> str:
    lines = ["# jaxskel against a strong numpy reference (issue 48, item 1)", ""]
    for i, run in enumerate(payload["runs"]):
        m = run["machine"]
        durations = ", ".join(f"{r['duration_s']:g} s" for r in payload["records"] if r["run"] == i)
        lines += [
            f"Run {i + 1} ({durations}): `{run['command']}`; started {run['started']}, took {run['elapsed_s']:.0f} s. "
            f"Machine: {m['cpu']}, {m['cores']} cores (affinity {m['affinity']}), Python {m['python']}, "
            f"numpy {m['numpy']}, JAX {m['jax']} ({m['jax_backend']}), jaxskel {m['jaxskel']}; strong reference "
            f"pool: {m['workers']} threads; BLAS threads {m.get('blas_threads')}. "
            f"Load average (1/5/15 min) at start {_load(run['load_avg_start'])}, "
            f"at end {_load(run['load_avg_end'])}.",
            "",
        ]
    lines += [
        "Data: `bench.cases.make_trial({'body': 'full_body'}, seed=0, duration=D)` (15 segments, 46 markers, 120 Hz, "
        "2 mm noise, 3 mm soft tissue, two gaps per marker). jaxskel: `fit_skeleton(trial, ik=False, alpha=1e-5, "
        "topology_frames=300, seed=0)`, second call (the first compiles), stage times from `result.timings`. "
        "Strong reference: `bench.reference.schur.fit_strong` (batched Schur-complement LM for the all-pairs costs "
        "and the tree joints, the reference cleaning, segmentation, MST and Procrustes skeleton). scipy reference: "
        "`bench.reference.fit_reference` up to the rigid stage (`least_squares` per pair). Ratio = reference s / "
        "jaxskel warm s (above 1: jaxskel is faster). One process, in this order: jaxskel twice, the strong "
        "reference with 1 thread and with the pool, the scipy reference once.",
        "",
        "## Times",
        "",
        "| D | stage | jaxskel warm s | strong s | scipy s | strong / jaxskel | scipy / jaxskel |",
        "|---|---|---|---|---|---|---|",
    ]
    for rec in payload["records"]:
        d = f"{rec['duration_s']:g} s"
        jx, st, sc = rec["jaxskel"], rec["strong"], rec.get("scipy")
        for name in STAGES:
            sc_s = f"{sc['stages'][name]:.2f}" if sc else "-"
            sc_r = f"{sc['ratio'][name]:.2f}x" if sc else "-"
            lines.append(f"| {d} | {LABELS[name]} | {jx['stages'][name]:.2f} | {st['stages'][name]:.2f} | {sc_s} | "
                         f"{st['ratio'][name]:.2f}x | {sc_r} |")
        sc_s = f"{sc['s']:.2f}" if sc else "-"
        sc_r = f"{sc['ratio']['whole']:.2f}x" if sc else "-"
        lines.append(f"| {d} | **whole** (jaxskel: fit_skeleton wall, {jx['other_s']:.2f} s outside stages) | "
                     f"**{jx['warm_s']:.2f}** | **{st['s']:.2f}** | **{sc_s}** | **{st['ratio']['whole']:.2f}x** | "
                     f"**{sc_r}** |")
    lines += ["", "The strong reference ran with 1 thread and with the default pool; the table shows the faster run "
              "(whole: " + "; ".join(
                  f"{r['duration_s']:g} s: " + ", ".join(f"{w} thread(s) {t:.2f} s"
                                                        for w, t in r["strong"]["whole_s_by_workers"].items())
                  for r in payload["records"]) + ")."]
    lines += ["", "CPU seconds (all threads) of the whole: " + "; ".join(
        f"{r['duration_s']:g} s: jaxskel {r['jaxskel']['warm_cpu_s']:.1f}, strong {r['strong']['cpu_s']:.1f}"
        + (f", scipy {r['scipy']['cpu_s']:.1f}" if "scipy" in r else "") for r in payload["records"]) + ". "
        "jaxskel's cold (compiling) call: " + ", ".join(
        f"{r['duration_s']:g} s: {r['jaxskel']['cold_s']:.1f} s" for r in payload["records"]) + "."]
    busy = [r for r in payload["records"]
            if max(r["load_avg_start"][0], r["load_avg_end"][0]) > payload["runs"][r["run"]]["machine"]["affinity"]]
    if busy:
        lines += ["", "Load: " + "; ".join(
            f"{r['duration_s']:g} s: 1-min load average {r['load_avg_start'][0]:.2f} at its start, "
            f"{r['load_avg_end'][0]:.2f} at its end" for r in busy)
            + f" on {payload['runs'][0]['machine']['affinity']} cores. The machine was shared with other fits, so "
            "every time here is inflated; jaxskel's warm fit used " + ", ".join(
                f"{r['jaxskel']['warm_cpu_s'] / r['jaxskel']['warm_s']:.2f}" for r in busy)
            + " CPU seconds per second, i.e. about one core, like the references."]
    lines += ["", "| target | measured | met |", "|---|---|---|"]
    for dur, want in ((120.0, 10.0), (600.0, 15.0)):
        rec = next((r for r in payload["records"] if r["duration_s"] == dur), None)
        got = rec["strong"]["ratio"]["whole"] if rec else None
        lines.append(f"| warm fit_skeleton, full body {dur:g} s: >= {want:g}x the strong reference | "
                     + (f"{got:.2f}x | {'met' if got >= want else 'not met'} |" if rec else "- | not measured |"))
    lines += [
        "",
        "## Accuracy against the synthetic truth",
        "",
        "`bench.accuracy.evaluate`: joint error = RMS over frames of the distance to the true centre (hinges: to "
        "the axis), median/max over the 14 joints; bone error relative to the true length, of the rigid "
        "skeleton's bones and (last two columns) of bones measured straight from the fitted joints (median over "
        "frames of the distance between a segment's two joints), which isolates the joint stages from the rigid "
        "fit.",
        "",
        "| D, pipeline | segmentation ARI | tree correct | joint err median mm | joint err max mm | "
        "bone err median % | bone err max % | bone from joints median % | bone from joints max % |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for rec in payload["records"]:
        d = f"{rec['duration_s']:g} s"
        lines.append(_acc_row(f"{d} jaxskel", rec["jaxskel"]["accuracy"]))
        lines.append(_acc_row(f"{d} strong", rec["strong"]["accuracy"]))
        if "scipy" in rec:
            lines.append(_acc_row(f"{d} scipy", rec["scipy"]["accuracy"]))
    lines.append("")
    for rec in payload["records"]:
        d = f"{rec['duration_s']:g} s"
        ag = rec["strong"]["agreement_with_jaxskel"]
        pc = ag.get("pair_cost_rel_diff", {})
        lines.append(f"* {d}: strong vs jaxskel: same tree {ag.get('same_topology')}, pair costs median relative "
                     f"difference {pc.get('median')} (strong lower in {pc.get('reference_lower_fraction')}, jaxskel "
                     f"lower in {pc.get('jaxskel_lower_fraction')} of the pairs).")
        sv = rec.get("strong_vs_scipy")
        if sv and sv.get("same_tree"):
            jd, pc2 = sv["joint_rms_diff_mm"], sv["pair_cost_rel_diff"]
            lines.append(f"  Strong vs scipy (same segmentation and tree): joints differ by {jd['median']:.2f} mm RMS "
                         f"(median over joints; max {jd['max']:.2f} mm), bone lengths by at most "
                         f"{sv['bone_diff_mm_max']:.2f} mm; pair costs median relative difference "
                         f"{pc2['median']:.4f} (strong lower in {pc2['first_lower_fraction']:.2f}, scipy lower in "
                         f"{pc2['second_lower_fraction']:.2f} of the pairs).")
        elif sv:
            lines.append("  Strong vs scipy: different segmentation or tree.")
    lines += ["", "## Work of the joint stages and what bounds the ratio", ""]
    lines += _limits(payload)
    return "\n".join(lines) + "\n"


def _load(v) -> str:
    return "/".join(f"{x:.2f}" for x in v)


def _limits(payload: dict) -> list[str]:
    out = [
        "Arithmetic per LM step (`lm_flops` in bench/strong_reference.py: the maths of "
        "`jaxskel/joints/_cost_lm.py`, counted on `bench/reference/schur.py`): about (121 + 6K) flops per frame "
        "and marker, of which 4 square roots and 1 division, plus ~60 per frame; K = the pair's markers (4 to 8 "
        "here), ~160 flops per frame-marker at K = 6. Both run the same iteration with the same tolerances "
        "(pairs: 1e-10/1e-9, at most 100 steps; tree: 1e-7/1e-6, at most 500), so their step counts agree "
        "(jaxskel drops the prior for the tree joints it finds determined, which changes some tree counts). jaxskel "
        "computes padded shapes: frames to a bucket, K to 8, chunks of 8 pairs that all iterate until the "
        "chunk's slowest pair stops; numpy computes the real shapes and drops finished pairs.",
        "",
        "| D | stage | LM steps jaxskel / strong | jaxskel Gflop (padded / useful) | strong Gflop | jaxskel s | "
        "strong s | jaxskel Gflop/s | strong Gflop/s | floor s | strong s / floor s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    bounds = []
    for rec in payload["records"]:
        d = f"{rec['duration_s']:g} s"
        rates = payload["runs"][rec["run"]]["machine"]["rates"]
        cores = payload["runs"][rec["run"]]["machine"]["affinity"]
        floors = 0.0
        for stage in ("joint_costs", "tree_joints"):
            wj, ws = rec["work"]["jaxskel"][stage], rec["work"]["strong"][stage]
            tj, ts = rec["jaxskel"]["stages"][stage], rec["strong"]["stages"][stage]
            if stage == "joint_costs":
                steps = f"{wj['steps_sum']} / {ws['steps_sum']}"
            else:
                steps = f"{sum(wj['steps'])} / {sum(ws['steps'])}"
            floor = _floor_s(ws, rates, cores)
            floors += floor
            out.append(f"| {d} | {LABELS[stage]} | {steps} | {wj['gflop']:.2f} / {wj['useful_gflop']:.2f} | "
                       f"{ws['gflop']:.2f} | {tj:.2f} | {ts:.2f} | {wj['gflop'] / tj:.2f} | {ws['gflop'] / ts:.2f} | "
                       f"{floor:.3f} | {ts / floor:.0f} |")
        jx = rec["jaxskel"]
        rest = jx["warm_s"] - jx["stages"]["joint_costs"] - jx["stages"]["tree_joints"]
        bounds.append(f"{d}: jaxskel outside the LM stages {rest:.2f} s, so at most "
                      f"{rec['strong']['s'] / (rest + floors):.2f}x the strong reference ({rec['strong']['s']:.2f} s) "
                      f"even with both LM stages at the floor")
    out += [
        "",
        f"Floor: the strong reference's own arithmetic at this machine's best single-core rates (measured here: "
        f"a float64 square root {rates['sqrt_ns']:.2f} ns in numpy's SIMD loop over an L2-resident array; dgemm "
        f"{rates['dgemm_gflops_1core']:.1f} Gflop/s on one thread), square roots and divisions at the first, all "
        f"else at the second, over {cores} cores: a perfectly fused kernel with no memory traffic and perfect "
        "parallel speed-up. No implementation reaches it; it bounds what any could gain on these stages. The "
        "jaxskel stage times include work outside the LM (pair arrays and feasibility; MST, pose checks, "
        "rooting and the identifiability test in 'tree joints'), so its Gflop/s are lower bounds.",
        "",
        "What bounds each ratio:",
        "",
        "* **LM stages.** Same iteration, same steps, so the ratio is one of throughputs. numpy runs each step as "
        "about 90 separate passes over (K, F) arrays (a 3-vector array counted as three; no fusion), ~0.7 kB of "
        "memory traffic per frame-marker-step against ~160 flops: it is bound by memory traffic and per-call "
        "overhead (in a development measurement its time per frame-marker-step was flat, ~85 ns, from 4k "
        "to 36k frames: not a cache effect that frame blocking would cure), at the Gflop/s in its column. "
        "jaxskel's XLA loop reaches the Gflop/s in its column on padded shapes (its padding alone costs the "
        "padded/useful factor). The last column is the most any implementation could gain over the strong "
        "reference on that stage.",
        "* **Cleaning, segmentation, rigid.** jaxskel does more work than the reference here (the reference's "
        "cleaning and segmentation are simple versions of the same rules, bench/reference/segment.py; jaxskel's "
        "rigid stage refines all offsets globally by "
        "alternating IK and a linear solve where the reference stops at a per-segment Procrustes average: the "
        "source of the reference's larger rigid-skeleton bone errors, the same for strong and scipy, while "
        "the bones straight from the joints agree with jaxskel's), so these ratios are below "
        "1 by design and cap the whole: " + "; ".join(bounds) + ".",
        "* **Targets.** 10x at 120 s and 15x at 600 s against this reference are out of reach while jaxskel's "
        "non-LM stages alone take more than a tenth of the strong reference's whole time; on the LM stages "
        "jaxskel would also need to run close to the floor. Against the scipy reference (per-pair "
        "`least_squares`, sparse Jacobians rebuilt per evaluation, one pair at a time) the ratios are in the "
        "scipy column above.",
    ]
    return out


def _floor_s(work: dict, rates: dict, cores: int) -> float:
    special = work["gspecial"] * 1e9
    other = work["gflop"] * 1e9 - special
    return (special * rates["sqrt_ns"] * 1e-9 + other / (rates["dgemm_gflops_1core"] * 1e9)) / max(cores, 1)


# ----------------------------------------------------------------------------- main
def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[10.0, 120.0])
    ap.add_argument("--no-scipy", action="store_true", help="skip the scipy reference (slow: ~1 min at 120 s)")
    ap.add_argument("--workers", type=int, default=None,
                    help="threads of the strong reference's pool (default: cores); it also runs with 1, the faster "
                         "run is reported")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--append", action="store_true",
                    help="add to the records already in --json (replacing those of the same durations) and "
                         "write the markdown of all of them")
    args = ap.parse_args(argv)

    import jax
    import sklearn.cluster  # noqa: F401  (imported before any timing: the reference segmentation uses it)

    import jaxskel
    from bench.reference.schur import default_workers

    started = time.strftime("%Y-%m-%d %H:%M:%S")
    t_start = time.perf_counter()
    load_start = list(os.getloadavg())
    workers = default_workers() if args.workers is None else args.workers
    machine = {
        "cpu": _cpu_model(), "cores": os.cpu_count(), "affinity": len(os.sched_getaffinity(0)),
        "python": platform.python_version(), "numpy": np.__version__, "jax": jax.__version__,
        "jax_backend": jax.default_backend(), "jaxskel": getattr(jaxskel, "__version__", "?"), "workers": workers,
        "blas_threads": {v: os.environ.get(v) for v in THREAD_VARS}, "blas_threads_set_here": _SET_HERE,
        "rates": machine_rates(),
    }
    records = [run_duration(d, not args.no_scipy, workers) for d in args.durations]
    run = {
        "command": "PYTHONPATH=. python bench/strong_reference.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "started": started, "elapsed_s": time.perf_counter() - t_start, "machine": machine,
        "load_avg_start": load_start, "load_avg_end": list(os.getloadavg()),
    }
    payload = {"runs": [], "records": []}
    if args.append and args.json and args.json.exists():
        old = json.loads(args.json.read_text())
        kept = [r for r in old["records"] if r["duration_s"] not in set(args.durations)]
        used = sorted({r["run"] for r in kept})
        payload["runs"] = [old["runs"][i] for i in used]
        payload["records"] = [{**r, "run": used.index(r["run"])} for r in kept]
    for rec in records:
        rec["run"] = len(payload["runs"])
    payload["runs"].append(run)
    payload["records"] = sorted(payload["records"] + records, key=lambda r: r["duration_s"])
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=1, default=_jsonable) + "\n")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(markdown(payload))
    return payload


def _jsonable(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v))


if __name__ == "__main__":
    main()
