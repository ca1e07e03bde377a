"""Run one benchmark case in this (fresh) process and write its record as JSON.

``python -m bench.worker CASE.json OUT.json [--only ...]``. Started by
:mod:`bench.run`, one process per case, so every case's first jaxskel call pays
for tracing and compilation (cold) and its memory is its own.

Before numpy and JAX load, BLAS thread pools are limited to one thread
(``OPENBLAS_NUM_THREADS`` etc., unless already set): on a 2-core machine shared
with other work, multithreaded OpenBLAS level-1 calls inside scipy's iterative
solvers were measured 10-30x slower than single-threaded ones, which would have
made the reference look far worse than it is. The setting is recorded.
"""

from __future__ import annotations

import os
import sys

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS")


def limit_blas() -> list[str]:
    """Limit the BLAS pools to one thread where the environment does not say (module docstring); the
    variables set here."""
    set_here = [v for v in THREAD_VARS if v not in os.environ]
    for v in set_here:
        os.environ[v] = "1"
    os.environ["BENCH_SET_THREAD_VARS"] = ",".join(set_here)
    return set_here


def device_info() -> dict:
    import jax

    devs = jax.devices()
    return {
        "platform": devs[0].platform,
        "devices": [str(d) for d in devs],
        "device_kind": devs[0].device_kind,
        "jax": jax.__version__,
        "x64": bool(jax.config.jax_enable_x64),
    }


def _git_state() -> dict:
    """Commit of the working tree and the jaxskel files that differ from it (figures are of the tree as run)."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "jaxskel"], cwd=root, capture_output=True, text=True).stdout
    except OSError:
        return {}
    return {"commit": commit, "jaxskel_changes": [line[3:] for line in dirty.splitlines()]}


def machine_info() -> dict:
    import platform

    return {
        "git": _git_state(),
        "cpus": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "machine": platform.machine(),
        "python": platform.python_version(),
        "load_avg": [round(v, 2) for v in os.getloadavg()],
        "blas_threads": {v: os.environ.get(v) for v in THREAD_VARS},
    }


def run(spec: dict, only: set[str] | None) -> dict:
    record = {"case": spec, "device": device_info(), "machine": machine_info()}
    kind = spec["kind"]
    if kind == "pipeline":
        from .pipeline import run_case

        record.update(run_case(spec, only))
    elif kind == "precision":
        from .precision import run_precision

        record.update(run_precision(spec))
    elif kind == "batch":
        from .batch import run_batch

        record.update(run_batch(spec))
    elif kind == "fit_batch":
        from .batch import run_fit_batch

        record.update(run_fit_batch(spec))
    elif kind == "cli":
        from .cli_cache import run_cli

        record.update(run_cli(spec))
    elif kind == "relabel":
        from .bench_relabel import measure

        record["figures"] = measure(float(spec["duration"]))
    elif kind == "params":
        from .bench_params import measure

        record["figures"] = measure(int(spec["frames"]), [1], int(spec.get("repeats", 3)))
    else:
        raise ValueError(f"unknown case kind {kind!r}")
    record["machine"]["load_avg_after"] = [round(v, 2) for v in os.getloadavg()]
    return record


def main(argv: list[str] | None = None) -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    import argparse
    import json

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("case", help="case spec (JSON file)")
    parser.add_argument("out", help="where to write the record (JSON)")
    parser.add_argument("--only", nargs="*", default=None)
    args = parser.parse_args(argv)
    with open(args.case) as fh:
        spec = json.load(fh)
    record = run(spec, set(args.only) if args.only else None)

    def default(obj):
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
        return str(obj)

    with open(args.out, "w") as fh:
        json.dump(record, fh, indent=1, default=default)


if __name__ == "__main__":
    limit_blas()
    sys.exit(main())
