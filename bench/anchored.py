"""The anchored refit alone, this checkout against an earlier revision, on the inputs the fit hands it.

Usage::

    PYTHONPATH=. python bench/anchored.py --baseline REV [--rounds 2] [--calls 7] [--markdown FILE]

The inputs of :func:`jaxskel.joints._anchored_centres.anchored_centres` are recorded once, from
``fit_skeleton`` on the synthetic full bodies of :mod:`bench.fast_core` (10 s and 120 s, with its
gaps) and on the bundled KneeltoProne01. Then a process of each checkout in turn (``REV`` from a detached
worktree, :func:`bench.fast_core.baseline_root`) calls the function ``--calls`` times after one warm-up;
``--rounds`` such pairs run one after the other, so both checkouts see the same load. Printed: the median
seconds of each round, the speed-up of the medians, and whether the moved joints' centres agree (1e-8 m).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.worker import limit_blas  # noqa: E402

limit_blas()

import numpy as np  # noqa: E402

CASES = ("full body 10 s", "full body 120 s", "KneeltoProne01")


def record(path: Path) -> None:
    """Fit each case and keep the arguments the fit passes to ``anchored_centres``."""
    import jaxskel
    from bench.cases import make_trial
    from jaxskel.joints import _anchored_centres
    from jaxskel.pipeline import _plan

    trials = [make_trial({"body": "full_body"}, seed=0, duration=d)[0] for d in (10.0, 120.0)]
    trials.append(jaxskel.load_sample())
    inputs = {}
    real = _anchored_centres.anchored_centres
    for name, trial in zip(CASES, trials):
        seen = []
        # A spy: it records the arguments and calls through, so the fit is unchanged.
        _plan.anchored_centres = lambda *a, _seen=seen, **k: _seen.append((a, k)) or real(*a, **k)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            jaxskel.fit_skeleton(trial, ik=False)
        inputs[name] = seen[-1]
    _plan.anchored_centres = real
    path.write_bytes(pickle.dumps(inputs))


def worker(inputs_path: Path, out_path: Path, calls: int) -> None:
    """Time ``anchored_centres`` of the jaxskel on ``sys.path`` on the recorded inputs."""
    from jaxskel.joints._anchored_centres import anchored_centres

    inputs = pickle.loads(inputs_path.read_bytes())
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (args, kwargs) in inputs.items():
            res = anchored_centres(*args, **kwargs)
            times = []
            for _ in range(calls):
                t0 = time.perf_counter()
                anchored_centres(*args, **kwargs)
                times.append(time.perf_counter() - t0)
            out[name] = {"median_s": float(np.median(times)), "min_s": float(min(times)),
                         "moved": res.moved.tolist(), "centres": np.nan_to_num(res.joint_positions, nan=0.0)}
    out_path.write_bytes(pickle.dumps(out))


def run_worker(code_root: Path, inputs_path: Path, calls: int) -> dict:
    """Run :func:`worker` in a new process that imports jaxskel from ``code_root``."""
    from bench.fast_core import run_in_checkout  # the parent's; a worker's bench may be the baseline's

    out = Path(tempfile.mkstemp(suffix=".pkl")[1])
    run_in_checkout(code_root, __file__, "worker", inputs_path, out, calls)
    result = pickle.loads(out.read_bytes())
    out.unlink()
    return result


def markdown(rows: list[dict], command: str) -> str:
    lines = [
        "# The anchored refit alone, before and after (`bench/anchored.py`)", "",
        f"`{command}`. Median seconds of each round (one process per checkout and round, the rounds one after "
        "the other).", "",
        "| inputs | baseline s | current s | speed-up | same moved joints | centres max diff m |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['case']} | {r['baseline']} | {r['current']} | {r['speedup']:.2f}x | {r['same_moved']} "
                     f"| {r['centres_diff']:.1e} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--calls", type=int, default=7)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    from bench.fast_core import baseline_root

    base = baseline_root(args.baseline)
    inputs = Path(tempfile.mkstemp(suffix=".pkl")[1])
    record(inputs)
    rounds = [(run_worker(base, inputs, args.calls), run_worker(ROOT, inputs, args.calls)) for _ in range(args.rounds)]
    inputs.unlink()
    rows = []
    for name in CASES:
        b = [r[0][name]["median_s"] for r in rounds]
        c = [r[1][name]["median_s"] for r in rounds]
        first_b, first_c = rounds[0][0][name], rounds[0][1][name]
        rows.append({
            "case": name, "baseline": " / ".join(f"{v:.2f}" for v in b), "current": " / ".join(f"{v:.2f}" for v in c),
            "speedup": float(np.median(b) / np.median(c)), "same_moved": first_b["moved"] == first_c["moved"],
            "centres_diff": float(np.max(np.abs(first_b["centres"] - first_c["centres"]))),
        })
    command = "PYTHONPATH=. python bench/anchored.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = markdown(rows, command)
    print(text)
    print(json.dumps(rows))
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
