"""Repeated overlapping batches in fresh processes: does ``fit_batch`` ever hang?

Issue 49: ``fit_batch`` deadlocked on 16 synthetic full bodies when preparing, solving
and finishing overlapped (two XLA:CPU executions at once). Each repeat runs one batch in
a new process under a timeout, so a hang shows as ``timeout``, not as a stuck bench.

    python bench/batch_hang_stress.py --repeats 20 --trials 16 --json out.json
    python bench/batch_hang_stress.py --repeats 2 --trials 4 --duration 3    # a quick look

Runs on the CPU (``JAX_PLATFORMS=cpu`` is set for the children): the deadlock is XLA:CPU's.
Stops starting repeats once ``--budget`` seconds are spent and says how many ran.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

CHILD = textwrap.dedent("""
    import sys, warnings
    from jaxskel._runtime.own_process import own_process
    own_process()  # jaxskel's own process: single-threaded Eigen unless the environment says otherwise
    import jaxskel
    from jaxskel import synth
    warnings.simplefilter("ignore")
    n, duration, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    trials = [synth.simulate(synth.full_body(seed=k % 4), duration=duration, seed=k, noise=0.002)[0] for k in range(n)]
    result = jaxskel.fit_batch(trials, out, batch_size=4, jobs=2, n_segments=15, progress=False)
    print("ok", sum(o.status == "ok" for o in result), "of", n)
""")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--trials", type=int, default=16)
    parser.add_argument("--duration", type=float, default=4.0)
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds one batch may take")
    parser.add_argument("--budget", type=float, default=1e9, help="seconds after which no repeat starts")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    env = dict(os.environ, JAX_PLATFORMS="cpu")

    runs, start = [], time.perf_counter()
    for r in range(args.repeats):
        if time.perf_counter() - start > args.budget:
            break
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            try:
                proc = subprocess.run([sys.executable, "-c", CHILD, str(args.trials), str(args.duration), out],
                                      env=env, capture_output=True, text=True, timeout=args.timeout)
                status = proc.stdout.strip().splitlines()[-1] if proc.returncode == 0 else f"exit {proc.returncode}: {proc.stderr[-300:]}"
            except subprocess.TimeoutExpired:
                status = "timeout"
        runs.append({"repeat": r, "seconds": round(time.perf_counter() - t0, 1), "status": status})
        print(runs[-1], flush=True)
    ok = sum(run["status"].startswith("ok") for run in runs)
    summary = {"trials": args.trials, "duration_s": args.duration, "repeats_run": len(runs), "finished": ok,
               "timeouts": sum(run["status"] == "timeout" for run in runs), "cpus": os.cpu_count(), "runs": runs}
    print(f"{ok} of {len(runs)} batches of {args.trials} trials finished", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
