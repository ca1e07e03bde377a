"""Peak memory of ``fit_batch`` with and without its memory bound (issue 49).

Four noisy synthetic full bodies (``bench.cases.make_trial``, seeds 0-3) of ``--duration``
seconds are fitted by :func:`jaxskel.fit_batch` with ``batch_size=8`` twice, each in a fresh
process: ``memory=None`` (the four solved together) and ``memory`` set to 1.5 times the
largest trial's estimate (:func:`jaxskel.pipeline._batch_memory.fit_bytes`), so that each is
solved alone. Printed and written: each run's batch sizes, peak RSS (sampled, :mod:`bench.memory`),
RSS before the batch, wall time, and the largest bone-length difference between the two
runs (the grouping must not change a fit). Also the estimate against what a single
warm fit adds to the process, the ratio :data:`FIT_COPIES` stands for.

Usage::

    python bench/batch_memory.py [--duration 240] [--markdown docs/bench/batch_memory.md]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(duration: float, bound: str) -> None:
    """In a fresh process: fit the four trials once; print JSON."""
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from bench.cases import make_trial
    from bench.memory import PeakRSS, rss_mb

    import jaxskel
    from jaxskel.pipeline import _local
    from jaxskel.pipeline._batch_memory import fit_bytes

    trials = [make_trial({"body": "full_body", "duration": duration}, seed=s)[0] for s in range(4)]
    largest = max(fit_bytes(t.n_frames, t.n_markers) for t in trials)
    memory = None if bound == "none" else int(1.5 * largest)
    sizes = []
    solve = _local._solve_batch

    def spy(works, *args, **kwargs):
        sizes.append(len(works))
        return solve(works, *args, **kwargs)

    _local._solve_batch = spy
    jaxskel.fit_skeleton(trials[0])  # compiles
    before = rss_mb()
    with PeakRSS() as single:  # what one warm fit adds to the process
        jaxskel.fit_skeleton(trials[0])
    sizes.clear()
    t0 = time.perf_counter()
    with PeakRSS() as peak:
        batch = jaxskel.fit_batch(trials, batch_size=8, memory=memory)
    seconds = time.perf_counter() - t0
    print(json.dumps({
        "bound": bound, "memory_bytes": memory, "estimate_mb": round(largest / 2**20, 1),
        "positions_mb": round(trials[0].positions.nbytes / 2**20, 1),
        "single_fit_adds_mb": round(single.peak_mb - before, 1), "sizes": sizes,
        "start_mb": round(peak.start_mb, 1), "peak_mb": round(peak.peak_mb, 1), "seconds": round(seconds, 1),
        "status": [o.status for o in batch],
        "bones": [np.asarray(o.result.skeleton.bone_lengths).tolist() for o in batch],
    }))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=240.0)
    parser.add_argument("--markdown", type=Path)
    parser.add_argument("--child", choices=("none", "bound"))
    args = parser.parse_args(argv)
    if args.child:
        child(args.duration, args.child)
        return
    runs = {}
    for bound in ("none", "bound"):
        out = subprocess.run([sys.executable, __file__, "--child", bound, "--duration", str(args.duration)],
                             capture_output=True, text=True, check=True, cwd=ROOT)
        runs[bound] = json.loads(out.stdout.strip().splitlines()[-1])
    diff = max(abs(a - b) for ta, tb in zip(runs["none"]["bones"], runs["bound"]["bones"]) for a, b in zip(ta, tb))
    lines = [
        "# fit_batch's memory bound (`python bench/batch_memory.py`)",
        "",
        f"Written {time.strftime('%Y-%m-%d')} on {platform.machine()} ({platform.processor() or 'CPU'}), "
        f"4 noisy synthetic full bodies of {args.duration:g} s, `batch_size=8`; each run in a fresh process, after "
        "two `fit_skeleton` calls on the first trial (the first compiles). Peak RSS sampled every 20 ms "
        "(`bench/memory.py`).",
        "",
        "| memory | trials solved together | RSS before (MB) | peak RSS (MB) | batch adds (MB) | wall s |",
        "|---|---|---|---|---|---|",
    ]
    for bound, r in runs.items():
        label = "None (batch_size alone)" if bound == "none" else f"{r['memory_bytes'] / 2**20:.0f} MB"
        lines.append(f"| {label} | {r['sizes']} | {r['start_mb']:.0f} | {r['peak_mb']:.0f} | "
                     f"{r['peak_mb'] - r['start_mb']:.0f} | {r['seconds']} |")
    r = runs["none"]
    lines += [
        "",
        f"Largest bone-length difference between the two runs: {diff * 1e3:.2g} mm. One trial's positions: "
        f"{r['positions_mb']} MB; its estimate (`fit_bytes`, 14 x positions): {r['estimate_mb']} MB; a warm "
        f"`fit_skeleton` of it added {r['single_fit_adds_mb']} MB to the process (peak RSS less RSS before).",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
