"""Before and after, stage by stage: this checkout's jaxskel against an earlier revision and the numpy reference.

Usage::

    PYTHONPATH=. python bench/fast_core.py --baseline REV --durations 10 120 600 \\
        [--repeats 3] [--json docs/bench/fast_core.json] [--markdown docs/bench/fast_core.md]

For each duration, a synthetic noisy full body (``bench.cases.make_trial({"body": "full_body"}, seed=0,
duration=D)``: 15 segments, 46 markers, 120 Hz) is written once to a ``.npz`` and fitted

* by jaxskel at ``REV`` (a detached git worktree of that revision, made under the system's temporary
  folder if it is not there) and by this checkout's jaxskel, each in a process of its own
  (``fit_skeleton(trial, ik=False, alpha=1e-5, topology_frames=300, seed=0)``: one call to compile,
  then ``--repeats`` warm calls, the fastest reported with its stage times from ``result.timings``);
* by the strong numpy reference (:func:`bench.reference.schur.fit_strong`) in this process, with one
  thread and with two, the faster reported.

The two jaxskel runs are interleaved per duration (baseline, then current), so both see the same load.
Ratios: reference seconds / jaxskel seconds (above 1: jaxskel is faster) and baseline seconds / current
seconds (the speed-up of this checkout). Correctness of the current fit against the baseline's: same
segment groups, same tree, the largest difference of a joint offset and of a bone length (mm).

``--ik`` also runs ``bench/bench_ik.py --json`` in both checkouts (IK throughput, frames per second of
the compiled core).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.worker import limit_blas  # noqa: E402

limit_blas()

import numpy as np  # noqa: E402

ALPHA = 1e-5
TOPOLOGY_FRAMES = 300
STAGES = ("clean", "segment", "joint costs", "tree joints", "rigid")


# ----------------------------------------------------------------------------- the worker
def worker(trial_path: Path, out_path: Path, repeats: int) -> None:
    """Fit the trial in ``trial_path`` with the jaxskel on ``sys.path``; write times and the fit to ``out_path``."""
    import warnings

    import jaxskel

    data = np.load(trial_path)
    trial = jaxskel.Trial(positions=data["positions"], labels=tuple(str(s) for s in data["labels"]),
                          rate=float(data["rate"]))
    kw = dict(ik=False, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        jaxskel.fit_skeleton(trial, **kw)
        cold = time.perf_counter() - t0
        best = None
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            res = jaxskel.fit_skeleton(trial, **kw)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if best is None or wall < best[0]:
                best = (wall, cpu, dict(res.timings), res)
    wall, cpu, timings, res = best
    sk = res.skeleton
    np.savez(
        out_path,
        meta=json.dumps({"cold_s": cold, "warm_s": wall, "warm_cpu_s": cpu, "timings": timings,
                         "jaxskel": str(Path(jaxskel.__file__).parent)}),
        marker_segment=np.asarray(res.segmentation.marker_segment),
        edges=np.asarray(res.topology.edges),
        joint_offsets=np.asarray(sk.joint_offsets),
        marker_offsets=np.asarray(sk.marker_offsets),
        bone_lengths=np.asarray(sk.bone_lengths),
        joint_positions=np.asarray(res.topology.joint_positions),
    )


def run_in_checkout(code_root: Path, script: str, function: str, *args) -> None:
    """Call ``function(*args)`` of the file ``script`` in a new process that imports jaxskel from
    ``code_root`` (first on the path; ``bench`` from this checkout). ``args``: paths and numbers."""
    call = ", ".join(f"Path({str(a)!r})" if isinstance(a, Path) else repr(a) for a in args)
    source = (f"import sys; sys.path.insert(0, {str(code_root)!r}); sys.path.insert(1, {str(ROOT)!r});"
              f"import importlib.util as u; from pathlib import Path;"
              f"spec = u.spec_from_file_location('bench_worker', {script!r}); m = u.module_from_spec(spec);"
              f"spec.loader.exec_module(m); m.{function}({call})")
    env = {**os.environ, "PYTHONPATH": str(code_root)}
    subprocess.run([sys.executable, "-c", source], env=env, check=True, cwd=str(code_root))


def run_worker(code_root: Path, trial_path: Path, repeats: int) -> dict:
    """Run :func:`worker` in a new process that imports jaxskel from ``code_root``."""
    out = Path(tempfile.mkstemp(suffix=".npz")[1])
    run_in_checkout(code_root, __file__, "worker", trial_path, out, repeats)
    with np.load(out) as f:
        rec = {k: f[k] for k in f.files}
    out.unlink()
    meta = json.loads(str(rec.pop("meta")))
    return {**meta, "fit": rec}


def baseline_root(rev: str) -> Path:
    """A detached worktree of ``rev`` (made once under the temporary folder)."""
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", rev], capture_output=True, text=True,
                         check=True).stdout.strip()
    path = Path(tempfile.gettempdir()) / f"jaxskel-baseline-{sha[:10]}"
    if not (path / "jaxskel").is_dir():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), sha], check=True,
                       capture_output=True)
    return path


# ----------------------------------------------------------------------------- the run
def run_strong(positions: np.ndarray, rate: float) -> dict:
    from bench.reference.schur import fit_strong

    best = None
    for workers in (1, 2):
        t0 = time.perf_counter()
        out = fit_strong(positions, rate, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES, seed=0, workers=workers)
        wall = time.perf_counter() - t0
        if best is None or wall < best["s"]:
            best = {"s": wall, "workers": workers, "stages": dict(out["timings"])}
    return best


def compare(base: dict, cur: dict) -> dict:
    """Current fit against the baseline's: same groups and tree, largest offset and bone differences (mm)."""
    a, b = base["fit"], cur["fit"]
    same_groups = bool(np.array_equal(a["marker_segment"], b["marker_segment"]))
    same_tree = same_groups and bool(np.array_equal(a["edges"], b["edges"]))
    out = {"same_groups": same_groups, "same_tree": same_tree}
    if same_tree:
        for name in ("joint_offsets", "marker_offsets", "bone_lengths"):
            out[f"{name}_max_mm"] = float(np.nanmax(np.abs(a[name] - b[name])) * 1e3)
        pa, pb = a["joint_positions"], b["joint_positions"]
        ok = np.isfinite(pa).all(-1) & np.isfinite(pb).all(-1)
        out["tree_joints_rms_mm"] = float(np.sqrt(np.mean(np.sum((pa - pb)[ok] ** 2, -1))) * 1e3)
    return out


STRONG_STAGE = {"clean": "clean", "segment": "segment", "joint costs": "joint_costs", "tree joints": "tree_joints",
                "rigid": "rigid"}


def run_duration(duration: float, base: Path, repeats: int) -> dict:
    from bench.cases import make_trial

    trial, _ = make_trial({"body": "full_body"}, seed=0, duration=duration)
    path = Path(tempfile.mkstemp(suffix=".npz")[1])
    np.savez(path, positions=np.asarray(trial.positions), labels=np.array(trial.labels), rate=trial.rate)
    print(f"--- {duration:g} s: {trial.n_frames} frames", flush=True)
    load0 = os.getloadavg()
    b = run_worker(base, path, repeats)
    print(f"baseline warm {b['warm_s']:.2f} s (cold {b['cold_s']:.1f} s)", flush=True)
    c = run_worker(ROOT, path, repeats)
    print(f"current  warm {c['warm_s']:.2f} s (cold {c['cold_s']:.1f} s)", flush=True)
    s = run_strong(np.asarray(trial.positions, np.float64), trial.rate)
    print(f"strong   {s['s']:.2f} s ({s['workers']} threads)", flush=True)
    path.unlink()
    rec = {"duration_s": duration, "frames": trial.n_frames, "baseline": _strip(b), "current": _strip(c),
           "strong": s, "agreement": compare(b, c), "load_avg": [list(load0), list(os.getloadavg())]}
    print(json.dumps(rec["agreement"]), flush=True)
    return rec


def _strip(r: dict) -> dict:
    return {k: v for k, v in r.items() if k != "fit"}


def run_ik(base: Path) -> dict:
    """bench/bench_ik.py in both checkouts (the compiled core's frames per second)."""
    out = {}
    for name, root in (("baseline", base), ("current", ROOT)):
        path = Path(tempfile.mkstemp(suffix=".json")[1])
        env = {**os.environ, "PYTHONPATH": str(root)}
        subprocess.run([sys.executable, "bench/bench_ik.py", "--json", str(path)], env=env, cwd=str(root),
                       check=True, capture_output=True)
        out[name] = json.loads(path.read_text())
        path.unlink()
    return out


# ----------------------------------------------------------------------------- the report
def markdown(payload: dict) -> str:
    lines = ["# Fast core: before and after, against the numpy reference (issue 70)", "",
             f"`{payload['command']}`; started {payload['started']}, took {payload['elapsed_s']:.0f} s, on "
             f"{payload['machine']}. Baseline: {payload['baseline']} (a git worktree). Each jaxskel figure is the "
             f"fastest of {payload['repeats']} warm calls in its own process; the reference is "
             "`bench.reference.schur.fit_strong`, the faster of 1 and 2 threads, in the parent process.", "",
             "| D | stage | baseline s | current s | speed-up | reference s | reference / current |",
             "|---|---|---|---|---|---|---|"]
    for r in payload["records"]:
        b, c, s = r["baseline"], r["current"], r["strong"]
        for st in STAGES:
            bs, cs, ss = b["timings"].get(st, 0.0), c["timings"].get(st, 0.0), s["stages"].get(STRONG_STAGE[st])
            ref = f"{ss:.2f} | {ss / cs:.2f}x" if ss is not None and cs > 0 else "- | -"
            lines.append(f"| {r['duration_s']:g} s | {st} | {bs:.2f} | {cs:.2f} | {bs / max(cs, 1e-9):.2f}x | {ref} |")
        lines.append(f"| {r['duration_s']:g} s | **whole** | **{b['warm_s']:.2f}** | **{c['warm_s']:.2f}** | "
                     f"**{b['warm_s'] / c['warm_s']:.2f}x** | **{s['s']:.2f}** | **{s['s'] / c['warm_s']:.2f}x** |")
    lines += ["", "| D | cold baseline s | cold current s | same groups | same tree | joint offsets max mm | "
              "marker offsets max mm | bone lengths max mm | tree joints RMS mm |", "|---|---|---|---|---|---|---|---|---|"]
    for r in payload["records"]:
        a = r["agreement"]

        def f(key: str, a=a) -> str:
            return f"{a[key]:.4f}" if key in a else "-"

        lines.append(f"| {r['duration_s']:g} s | {r['baseline']['cold_s']:.1f} | {r['current']['cold_s']:.1f} | "
                     f"{a['same_groups']} | {a['same_tree']} | {f('joint_offsets_max_mm')} | "
                     f"{f('marker_offsets_max_mm')} | {f('bone_lengths_max_mm')} | {f('tree_joints_rms_mm')} |")
    if "ik" in payload:
        lines += ["", "IK (`bench/bench_ik.py`, each checkout's own):", "", "```",
                  json.dumps(payload["ik"], indent=1)[:4000], "```"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--baseline", required=True, help="git revision to compare against")
    parser.add_argument("--durations", type=float, nargs="+", default=[10.0, 120.0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ik", action="store_true", help="also run bench/bench_ik.py in both checkouts")
    parser.add_argument("--json")
    parser.add_argument("--markdown")
    args = parser.parse_args(argv)
    from bench.strong_reference import _cpu_model

    started, t0 = time.strftime("%Y-%m-%d %H:%M:%S"), time.perf_counter()
    base = baseline_root(args.baseline)
    records = [run_duration(d, base, args.repeats) for d in args.durations]
    payload = {"command": "PYTHONPATH=. python bench/fast_core.py " + " ".join(argv or sys.argv[1:]),
               "started": started, "baseline": args.baseline, "repeats": args.repeats,
               "machine": f"{_cpu_model()}, {os.cpu_count()} cores", "records": records}
    if args.ik:
        payload["ik"] = run_ik(base)
    payload["elapsed_s"] = time.perf_counter() - t0
    if args.json:
        Path(args.json).write_text(json.dumps(payload, indent=1, default=float))
    text = markdown(payload)
    if args.markdown:
        Path(args.markdown).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
