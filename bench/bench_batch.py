"""Trials per minute: one by one vs ``fit_batch`` vs ``fit_batch`` on a 2-worker Dask cluster.

    python bench/bench_batch.py                 # 1, 8 and 64 trials of 60 s full-body data (hours on 2 cores)
    python bench/bench_batch.py --quick         # 1, 2 and 4 trials of 10 s (a few minutes)
    python bench/bench_batch.py --sizes 1 8 --duration 60 --modes one batched dask

Data: synthetic full bodies (``jaxskel.synth.full_body``, four subjects) doing the
calibration motion at 120 Hz with 2 mm noise, 2 mm soft tissue and one gap per
marker, written as C3D files. Every mode reads the files, fits, and writes one
result file per trial:

* ``one``: ``jaxskel.load`` + ``fit_skeleton`` + ``save`` in a loop (one process);
* ``batched``: ``jaxskel.fit_batch(folder, outdir)`` (shared vmapped solves,
  overlapped host work, one process);
* ``dask``: the same through ``scheduler=`` on a ``LocalCluster`` of 2 worker
  processes (one thread each).

Each mode first fits warm-up trials of the same length (so compilation is not
timed; the persistent compilation cache is on for all), then the timed set. The
machine's load average is recorded with every figure: on a shared 2-core machine
the figures move with what else runs.

``run(quick)`` returns the figures as a dict (for ``python -m bench``).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

__all__ = ["run", "main"]

MODES = ("one", "batched", "dask")


def make_trials(folder: Path, n: int, duration: float, first_seed: int = 0) -> list[Path]:
    """``n`` C3D recordings of four synthetic subjects in ``folder/subjectK/``."""
    from jaxskel import synth

    paths = []
    for i in range(first_seed, first_seed + n):
        body = synth.full_body(seed=i % 4)
        trial, _ = synth.simulate(body, "calibration", duration=duration, rate=120.0, seed=100 + i,
                                  noise=0.002, soft_tissue=0.002, gaps=1)
        sub = folder / f"subject{i % 4}"
        sub.mkdir(parents=True, exist_ok=True)
        path = sub / f"trial{i:03d}.c3d"
        trial.save(path)
        paths.append(path)
    return paths


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _one_by_one(paths: list[Path], outdir: Path) -> None:
    import jaxskel

    for p in paths:
        result = jaxskel.fit_skeleton(jaxskel.load(p))
        dest = outdir / p.parent.name / f"{p.stem}.h5"
        dest.parent.mkdir(parents=True, exist_ok=True)
        result.save(dest, overwrite=True)


def _workers_cpu(client) -> float:
    """CPU seconds used so far by the Dask worker processes (0 without a client)."""
    if client is None:
        return 0.0
    return float(sum(client.run(_cpu).values()))


def _timed(fn, *args, client=None) -> dict:
    load0, cpu0, wcpu0, t0 = os.getloadavg()[0], _cpu(), _workers_cpu(client), time.perf_counter()
    fn(*args)
    seconds = time.perf_counter() - t0
    return {"seconds": round(seconds, 1), "cpu_s_this_process": round(_cpu() - cpu0, 1),
            "cpu_s_workers": round(_workers_cpu(client) - wcpu0, 1),
            "load_avg_before": round(load0, 2), "load_avg_after": round(os.getloadavg()[0], 2)}


def run(quick: bool = False, *, sizes: list[int] | None = None, duration: float | None = None,
        modes: tuple[str, ...] = MODES, batch_size: int = 8, workers: int = 2) -> dict:
    """Time every mode on every size; returns ``{"rows": [...], "ratios": [...], ...}``."""
    import jaxskel
    from jaxskel._runtime.compile_cache import enable_compile_cache as _enable_compile_cache

    _enable_compile_cache()
    sizes = sizes or ([1, 2, 4] if quick else [1, 8, 64])
    duration = duration or (10.0 if quick else 60.0)
    root = Path(tempfile.mkdtemp(prefix="jaxskel-bench-batch-"))
    rows: list[dict] = []
    cluster = client = None
    try:
        warm_dir = root / "warmup"
        make_trials(warm_dir, 2, duration, first_seed=1000)
        data = {}
        for n in sizes:
            folder = root / f"in{n}"
            data[n] = (folder, make_trials(folder, n, duration))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for mode in modes:
                if mode == "one":
                    _one_by_one(sorted(warm_dir.rglob("*.c3d"))[:1], root / "warm-out-one")
                elif mode == "batched":
                    jaxskel.fit_batch(warm_dir, root / "warm-out-batched", batch_size=batch_size, overwrite=True)
                elif mode == "dask":
                    from distributed import Client, LocalCluster

                    t0 = time.perf_counter()
                    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None)
                    client = Client(cluster)
                    started = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    jaxskel.fit_batch(warm_dir, root / "warm-out-dask", scheduler=client, batch_size=batch_size,
                                      overwrite=True)
                    print(f"dask: cluster of {workers} workers up in {started:.1f} s, warm-up "
                          f"{time.perf_counter() - t0:.1f} s", flush=True)
                for n in sizes:
                    folder, paths = data[n]
                    out = root / f"out-{mode}-{n}"
                    if mode == "one":
                        fig = _timed(_one_by_one, paths, out)
                    elif mode == "batched":
                        fig = _timed(lambda: jaxskel.fit_batch(folder, out, batch_size=batch_size, overwrite=True))
                    else:
                        fig = _timed(lambda: jaxskel.fit_batch(folder, out, scheduler=client, batch_size=batch_size,
                                                               overwrite=True), client=client)
                    done = len(list(out.rglob("*.h5")))
                    row = {"mode": mode, "trials": n, "fitted": done, "duration_s": duration,
                           "trials_per_min": round(60.0 * n / fig["seconds"], 2), **fig}
                    rows.append(row)
                    print(_format_row(row), flush=True)
                if mode == "dask":
                    client.close()
                    cluster.close()
                    client = cluster = None
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
        shutil.rmtree(root, ignore_errors=True)
    ratios = []
    base = {r["trials"]: r["seconds"] for r in rows if r["mode"] == "one"}
    for r in rows:
        if r["mode"] != "one" and r["trials"] in base:
            ratios.append({"mode": r["mode"], "trials": r["trials"],
                           "speedup_vs_one_by_one": round(base[r["trials"]] / r["seconds"], 2)})
    import jax

    return {
        "name": "fit_batch throughput",
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "jaxskel": jaxskel.__version__,
        "data": f"synthetic full body, {duration:g} s at 120 Hz, 46 markers, C3D in / HDF5 out",
        "batch_size": batch_size,
        "workers": workers,
        "rows": rows,
        "ratios": ratios,
    }


def _format_row(r: dict) -> str:
    cpu = r["cpu_s_this_process"] + r.get("cpu_s_workers", 0.0)
    return (f"{r['mode']:>8} {r['trials']:>6} {r['seconds']:>9.1f} {r['trials_per_min']:>12.2f} "
            f"{cpu:>9.1f} {r['load_avg_before']:>6.2f} {r['load_avg_after']:>6.2f}")


def print_table(result: dict) -> None:
    print(f"\n{result['name']} on {result['device']} ({result['cpu_count']} cores); {result['data']}")
    print(f"{'mode':>8} {'trials':>6} {'seconds':>9} {'trials/min':>12} {'cpu s':>9} {'load0':>6} {'load1':>6}")
    print("(cpu s: this process plus the Dask workers; load0/load1: 1-min load average before/after)")
    for r in result["rows"]:
        print(_format_row(r))
    print("\nspeed-up vs one by one (same trials):")
    for q in result["ratios"]:
        print(f"  {q['mode']:>8}, {q['trials']:>3} trials: x{q['speedup_vs_one_by_one']:.2f}")


def main(argv: list[str] | None = None) -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--sizes", type=int, nargs="+")
    p.add_argument("--duration", type=float)
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    result = run(args.quick, sizes=args.sizes, duration=args.duration, modes=tuple(args.modes),
                 batch_size=args.batch_size, workers=args.workers)
    print_table(result)
    if args.json:
        import json

        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
