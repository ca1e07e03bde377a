"""Entry point: ``python -m bench`` or ``python bench/run.py``.

Runs the cases of a mode (:func:`bench.cases.plan`), each in a fresh process
(``python -m bench.worker``) so that every case's first call compiles and its
memory is its own; prints the figures and the targets; writes JSON and a log-log
scaling plot. All figures name the JAX device they came from; the reference
always runs on the CPU (numpy/scipy).

    python -m bench                      # --quick: one small full-body case (~3 min on 2 cores)
    python -m bench --full               # everything (about two hours on a shared 2-core CPU)
    python -m bench --only ik fit        # only some stages / experiments
    python -m bench --full --case "120 s" --json out.json
    python -m bench --report bench/results/full.json   # re-print a saved run

``--only`` takes stage names (clean segment joint_costs tree_joints rigid ik fit)
and experiments (label_merging normalise precision batch fit_batch cli).
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

if __package__ in (None, ""):  # ``python bench/run.py``
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    __package__ = "bench"  # noqa: A001

from bench import report  # noqa: E402
from bench.cases import plan  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PIPELINE_STAGES = ("clean", "segment", "joint_costs", "tree_joints", "rigid", "ik", "fit")
EXPERIMENTS = {"label_merging": "relabel", "normalise": "params", "precision": "precision", "batch": "batch",
               "fit_batch": "fit_batch", "cli": "cli"}


def _selected(spec: dict, only: set[str] | None) -> bool:
    if not only:
        return True
    if spec["kind"] == "pipeline":
        return bool(only & set(PIPELINE_STAGES))
    return any(EXPERIMENTS[name] == spec["kind"] for name in only if name in EXPERIMENTS)


def _tree_cpu_ticks(root_pid: int) -> int | None:
    """CPU clock ticks (user + system) used so far by a process and its live descendants (Linux)."""
    stats = {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else ():
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(entry)] = (int(fields[1]), int(fields[11]) + int(fields[12]))  # ppid, utime + stime
    if root_pid not in stats:
        return None
    total, todo = 0, [root_pid]
    while todo:
        pid = todo.pop()
        total += stats[pid][1]
        todo += [child for child, (ppid, _) in stats.items() if ppid == pid]
    return total


def run_case(spec: dict, only: set[str] | None, timeout: float | None, hang_s: float = 900.0) -> dict:
    """Run one case in a new process; the record, or one with ``error`` if it failed.

    A case whose process tree uses under 2 % of a core for ``hang_s`` seconds is
    killed as hung (XLA's CPU runtime has been seen to wedge for good, every worker
    parked; the memory sampler thread alone uses well under that).
    """
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    with tempfile.TemporaryDirectory(prefix="bench-case-") as tmp:
        case_path, out_path = Path(tmp) / "case.json", Path(tmp) / "out.json"
        case_path.write_text(json.dumps(spec))
        cmd = [sys.executable, "-m", "bench.worker", str(case_path), str(out_path)]
        if only:
            cmd += ["--only", *sorted(only)]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
        log = Path(tmp) / "log.txt"
        start = time.perf_counter()
        with open(log, "w") as fh:
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
            try:
                # wait4 gives this child's own peak RSS (ru_maxrss, KB on Linux)
                deadline = None if timeout is None else start + timeout
                why = None
                last_ticks, last_check = 0, start
                last_change = start
                while True:
                    pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                    if pid:
                        break
                    now = time.perf_counter()
                    if now - last_check > 10.0:
                        ticks = _tree_cpu_ticks(proc.pid)
                        if ticks is not None and ticks - last_ticks > 0.02 * hz * (now - last_check):
                            last_change = now
                        last_ticks, last_check = ticks or last_ticks, now
                        if now - last_change > hang_s:
                            why = f"hung: under 2 % of a core for {hang_s:.0f} s, killed"
                    if deadline is not None and now > deadline:
                        why = f"killed after {timeout:.0f} s (timeout)"
                    if why:
                        os.killpg(proc.pid, 9)  # the case's whole process group (it may have children)
                        pid, status, usage = os.wait4(proc.pid, 0)
                        break
                    time.sleep(0.2)
                proc.returncode = os.waitstatus_to_exitcode(status)
            except KeyboardInterrupt:
                os.killpg(proc.pid, 9)
                raise
        wall = time.perf_counter() - start
        if proc.returncode == 0 and out_path.exists():
            record = json.loads(out_path.read_text())
        else:
            record = {"case": spec, "error": f"{why or f'exit {proc.returncode}'}: " + log.read_text()[-2000:]}
        record["process"] = {"wall_s": wall, "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1)}
        return record


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], epilog=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="small case (default)")
    mode.add_argument("--full", action="store_true", help="every size and experiment")
    mode.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # the test's case
    parser.add_argument("--only", nargs="+", metavar="STAGE", choices=[*PIPELINE_STAGES, *EXPERIMENTS],
                        help="stages / experiments to run")
    parser.add_argument("--case", action="append", default=[], help="run only cases whose name contains this")
    parser.add_argument("--json", type=Path, help="write the records here (default bench/results/<mode>.json)")
    parser.add_argument("--plot", type=Path, help="write the log-log scaling plot here (default next to the JSON)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per case before it is killed")
    parser.add_argument("--report", type=Path, help="print the tables of a saved JSON and exit")
    parser.add_argument("--markdown", type=Path, help="also write the tables as Markdown")
    args = parser.parse_args(argv)

    if args.report:
        records = json.loads(args.report.read_text())["records"]
        print(report.format_table(records))
        if args.markdown:
            args.markdown.write_text(report.markdown(records) + "\n")
        if args.plot:
            report.plot(records, str(args.plot))
        return

    name = "full" if args.full else "tiny" if args.tiny else "quick"
    only = set(args.only) if args.only else None
    specs = [s for s in plan(name) if _selected(s, only)]
    if args.case:
        specs = [s for s in specs if any(part in s["name"] for part in args.case)]
    json_path = args.json or ROOT / "bench" / "results" / f"{name}.json"
    plot_path = args.plot or json_path.with_suffix(".png")
    records = []
    started = time.time()
    for i, spec in enumerate(specs, 1):
        print(f"[{i}/{len(specs)}] {spec['name']} ...", end=" ", flush=True)
        record = run_case(spec, only, args.timeout or spec.get("timeout"))
        records.append(record)
        status = "FAILED" if "error" in record else "ok"
        print(f"{status} ({record['process']['wall_s']:.0f} s, peak {record['process']['peak_rss_mb']:.0f} MB)", flush=True)
        if "error" in record:
            print(record["error"][-800:], file=sys.stderr)
        # write as we go, so a long run that is interrupted keeps what it measured
        json_path.parent.mkdir(parents=True, exist_ok=True)
        payload = {"mode": name, "only": sorted(only) if only else None, "started": started,
                   "finished": time.time(), "records": records, "scaling": report.scaling(records),
                   "targets": report.targets(records)}
        json_path.write_text(json.dumps(payload, indent=1))
    print()
    print(report.format_table(records))
    if report.plot(records, str(plot_path)):
        print(f"\nplot: {plot_path}")
    if args.markdown:
        args.markdown.write_text(report.markdown(records) + "\n")
    print(f"records: {json_path}")
    if any("error" in r for r in records):
        sys.exit(1)


if __name__ == "__main__":
    main()
