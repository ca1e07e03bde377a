"""Batched fitting on whatever JAX's default backend is (written for a first GPU figure).

    python bench/gpu_batch.py --json out.json                      # 16 and 64 trials batched, 4 one by one
    python bench/gpu_batch.py --sizes 2 4 --one 1 --warm 1 --json out.json   # a quick check on a CPU

Data: synthetic full bodies (``jaxskel.synth.full_body(seed=k % 4)``, 46 markers) doing
the calibration motion, ``--duration`` seconds at 120 Hz with 2 mm noise, built in
memory (no C3D reading, so no ezc3d). Warm-up first (``fit_batch`` on ``--warm``
trials of other seeds and ``fit_skeleton`` on one, so compilation is not timed; the
warm-up seconds are recorded as ``warmup``), then:

* ``one``: ``fit_skeleton`` + ``save`` one by one on the first ``--one`` trials;
* ``batched``: ``fit_batch(trials, outdir, keep_results=False)`` on the first N
  trials for each N of ``--sizes`` (result files and summary written, as in a real run).

Order: warm-up, the smallest batch, the one-by-one warm-up and run, the larger batches.
Each phase records wall seconds, seconds per trial, trials per minute, this process's
CPU seconds, and the device's ``peak_bytes_in_use`` after it (JAX keeps one peak per
process and cannot reset it, so each figure is the peak so far; phases run from the
smallest up; ``device_peak_mb_per_trial`` is that peak over the phase's trials, not
an additive per-trial cost) and ``bytes_in_use``. A phase whose projected end (seconds
per trial of the last phase of the same mode, else the slowest so far) would pass
``--budget`` seconds since the start is skipped and recorded as such; a larger batch
that would is shrunk to the largest multiple of ``--batch-size`` that fits (``shrunk``
in the JSON). The JSON is rewritten after every phase, so a run cut off by a time
limit still leaves the phases it finished.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

T0 = time.perf_counter()


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _mem() -> dict:
    import jax

    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 - the CPU backend has none
        stats = {}
    mb = lambda k: None if k not in stats else round(stats[k] / 2**20, 1)  # noqa: E731
    return {"device_peak_mb": mb("peak_bytes_in_use"), "device_in_use_mb": mb("bytes_in_use"),
            "device_limit_mb": mb("bytes_limit")}


def _versions() -> dict:
    from importlib import metadata

    out = {}
    for name in ("jax", "jaxlib", "jax-cuda13-plugin", "jax-cuda12-plugin", "equinox", "optimistix", "lineax",
                 "jaxtyping", "numpy", "scipy", "scikit-learn", "h5py"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def make_trials(n: int, duration: float, first_seed: int = 0) -> list:
    from jaxskel import synth

    trials = []
    for k in range(first_seed, first_seed + n):
        body = synth.full_body(seed=k % 4)
        trial, _ = synth.simulate(body, duration=duration, seed=k, noise=0.002)
        trials.append(trial)
    return trials


def main(argv: list[str] | None = None) -> dict:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[16, 64])
    p.add_argument("--one", type=int, default=4, help="trials fitted one by one (0: none)")
    p.add_argument("--warm", type=int, default=4, help="warm-up trials for fit_batch (one per subject)")
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--budget", type=float, default=1e9, help="skip phases that would end later than this (s)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)

    import jax

    import jaxskel

    dev = jax.devices()[0]
    rec: dict = {
        "name": "fit_batch on the default JAX backend",
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "device_kind": getattr(dev, "device_kind", "?"),
        "x64": bool(jax.config.jax_enable_x64),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "versions": _versions(),
        "jaxskel": jaxskel.__version__,
        "jaxskel_file": jaxskel.__file__,
        "data": f"synthetic full body (46 markers), calibration motion, {args.duration:g} s at 120 Hz, "
                "2 mm noise, in memory; HDF5 out",
        "batch_size": args.batch_size,
        "budget_s": args.budget,
        "phases": [],
    }
    print(json.dumps({k: v for k, v in rec.items() if k != "phases"}, indent=1), flush=True)

    def dump() -> None:
        rec["elapsed_s"] = round(time.perf_counter() - T0, 1)
        if args.json:
            args.json.write_text(json.dumps(rec, indent=1))

    root = Path(tempfile.mkdtemp(prefix="jaxskel-gpu-batch-"))
    rates: dict[str, float] = {}  # seconds per trial of the last phase of each mode

    def fits(mode: str, n: int) -> bool:
        rate = rates.get(mode, max(rates.values(), default=None))
        return rate is None or time.perf_counter() - T0 + n * rate <= args.budget

    def phase(mode: str, n: int, fn) -> None:
        rate = rates.get(mode, max(rates.values(), default=None))
        if rate is not None:
            projected = time.perf_counter() - T0 + n * rate
            if projected > args.budget:
                row = {"mode": mode, "trials": n, "skipped": f"projected to end at {projected:.0f} s > budget"}
                rec["phases"].append(row)
                print(row, flush=True)
                dump()
                return
        cpu0, t0 = _cpu(), time.perf_counter()
        try:
            ok, failed = fn()
            err = None
        except Exception as exc:  # noqa: BLE001 - recorded, the next phase still runs
            ok, failed, err = 0, n, "".join(traceback.format_exception(exc))[-3000:]
        s = time.perf_counter() - t0
        row = {"mode": mode, "trials": n, "ok": ok, "failed": failed, "seconds": round(s, 2),
               "s_per_trial": round(s / n, 3), "trials_per_min": round(60.0 * n / s, 2),
               "cpu_s": round(_cpu() - cpu0, 1), **_mem()}
        if err:
            row["error"] = err
        if not mode.startswith("warmup") and not err:
            rates[mode] = s / n
        if row["device_peak_mb"] is not None:
            row["device_peak_mb_per_trial"] = round(row["device_peak_mb"] / n, 1)
        rec["phases"].append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "error"}), flush=True)
        if err:
            print(err, flush=True)
        dump()

    def batched(trials, names, out):
        res = jaxskel.fit_batch(trials, out, names=names, batch_size=args.batch_size, keep_results=False,
                                overwrite=True)
        for o in res.failed[:3]:
            print(f"FAILED {o.name}: {o.error}\n{o.traceback[-2000:]}", flush=True)
        c = res.counts()
        return c.get("ok", 0) + c.get("skipped", 0), c.get("failed", 0)

    def one_by_one(trials, names, out):
        out.mkdir(parents=True, exist_ok=True)
        for t, name in zip(trials, names):
            jaxskel.fit_skeleton(t).save(out / f"{name}.h5", overwrite=True)
        return len(trials), 0

    try:
        n_max = max(args.sizes + [args.one])
        t0 = time.perf_counter()
        warm = make_trials(args.warm, args.duration, first_seed=1000)
        data = make_trials(n_max, args.duration)
        names = [f"trial{k:03d}" for k in range(n_max)]
        rec["synth_s"] = round(time.perf_counter() - t0, 1)
        print(f"synthesised {args.warm + n_max} trials in {rec['synth_s']} s", flush=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # Order: the smallest batch first (the figure wanted most), then the one-by-one
            # comparison, then the larger batches, so a budget cut drops the largest first.
            sizes = sorted(args.sizes)
            phase("warmup", args.warm,
                  lambda: batched(warm, [f"warm{k}" for k in range(args.warm)], root / "warm-batched"))
            phase("batched", sizes[0], lambda: batched(data[: sizes[0]], names[: sizes[0]], root / "batched0"))
            if args.one:
                phase("warmup_one", 1, lambda: one_by_one(warm[:1], ["warm0"], root / "warm-one"))
                phase("one", args.one, lambda: one_by_one(data[: args.one], names[: args.one], root / "one"))
            done = sizes[0]
            for n in sizes[1:]:
                # Too long for the budget: the largest multiple of the batch size that fits
                # and is larger than the last batch run (recorded as "requested").
                m = n
                while m > done and not fits("batched", m):
                    m -= args.batch_size
                if m > done and m != n:
                    print(f"{n} trials would pass the budget: {m} instead", flush=True)
                    rec.setdefault("shrunk", []).append({"requested": n, "ran": m})
                    n = m
                phase("batched", n, lambda n=n: batched(data[:n], names[:n], root / f"batched{n}"))
                done = max(done, n)
    finally:
        shutil.rmtree(root, ignore_errors=True)

    by = {(r["mode"], r["trials"]): r for r in rec["phases"] if "s_per_trial" in r and not r.get("error")}
    one = next((r for (m, _), r in by.items() if m == "one"), None)
    rec["ratios"] = [
        {"trials": r["trials"], "speedup_vs_one_by_one": round(one["s_per_trial"] / r["s_per_trial"], 2)}
        for (m, _), r in by.items() if m == "batched" and one is not None
    ]
    dump()
    print("\nmode         trials   seconds   s/trial  trials/min  peak MB")
    for r in rec["phases"]:
        if "s_per_trial" in r:
            print(f"{r['mode']:<12} {r['trials']:>6} {r['seconds']:>9.1f} {r['s_per_trial']:>9.2f} "
                  f"{r['trials_per_min']:>11.2f}  {r['device_peak_mb']}")
        else:
            print(f"{r['mode']:<12} {r['trials']:>6}  skipped: {r['skipped']}")
    for q in rec["ratios"]:
        print(f"batched {q['trials']} vs one by one: x{q['speedup_vs_one_by_one']}")
    return rec


if __name__ == "__main__":
    main()
