"""The benchmark harness (bench/) runs end to end on a tiny case and its reference agrees with jaxskel.

Runs ``python -m bench --tiny`` (a 4-segment random tree, 5 s at 60 Hz, stages up to
the tree joints) in a subprocess, as a user would, and checks the JSON it writes. No
wall-clock assertions: timings on a shared CI machine mean nothing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_tiny_runs_and_reference_agrees(tmp_path):
    out = tmp_path / "tiny.json"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "--json", str(out), "--plot", str(tmp_path / "tiny.png")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "targets:" in proc.stdout
    payload = json.loads(out.read_text())
    assert {"mode", "records", "scaling", "targets"} <= set(payload)
    (record,) = payload["records"]
    assert "error" not in record
    assert {"case", "device", "machine", "data", "jaxskel", "reference", "agreement", "process"} <= set(record)
    assert record["device"]["platform"]
    for stage in ("clean", "segment", "joint_costs", "tree_joints"):
        jx = record["jaxskel"]["stages"][stage]
        assert jx["cold_s"] > 0 and jx["warm_s"] > 0
        assert record["reference"]["stages"][stage]["s"] > 0
    assert record["jaxskel"]["memory"]["warm"]["peak_rss_mb"] > 0
    # Same method, same data: both must find the true grouping and tree, and the same tree.
    agreement = record["agreement"]
    assert agreement["segmentation_ari"] == 1.0
    assert agreement["same_topology"] is True
    for side in ("jaxskel", "reference"):
        accuracy = record[side]["accuracy"]
        assert accuracy["segmentation_ari"] == 1.0
        assert accuracy["topology_correct"] is True
        assert accuracy["joint_error_mm"]["median"] < 50.0
    # Per-pair costs of the two solvers agree to a few per cent (median).
    assert abs(agreement["pair_cost_rel_diff"]["median"]) < 0.1
