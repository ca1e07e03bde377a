"""Calibrate once, track many: tracking a trial on a saved skeleton against fitting it.

For each case a skeleton is fitted once from a calibration trial and saved; then, warm
(each program compiled by a first run), every take is

* fitted from scratch with :func:`jaxskel.fit_skeleton` (what a user without ``track`` does),
* tracked on the saved skeleton with :func:`jaxskel.track`, one take per call,
* tracked with all takes in one :func:`jaxskel.track` call (one batched IK solve per group),

in the same process, and the ratio fit time / track time printed per take. The residuals
of both (median per-frame marker RMS) are reported beside the times, so the speed never
comes from a worse fit.

Cases: 8 synthetic full-body walks of 10 s on a calibration trial of 20 s (0.5 mm noise);
the real Clouthier takes (the bundled KneeltoProne01 calibrates, PronetoRun01 and
KneeltoProne01 are the takes); Hamner (static + running calibrate, running is the take).

Usage::

    python bench/track.py                 # ~6 min on 2 cores; writes docs/bench/track.md and .json
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import jaxskel
from jaxskel import synth

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
OUT = Path(__file__).resolve().parents[1] / "docs" / "bench"


def _median_mm(rms: np.ndarray) -> float:
    rms = np.asarray(rms)
    return round(1e3 * float(np.nanmedian(rms)), 3)


def _case(name: str, calibration: list, takes: list[tuple[str, jaxskel.Trial]]) -> dict:
    print(f"\n{name}: calibrating on {len(calibration)} trial(s)", flush=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        cal = jaxskel.fit_skeleton(calibration)
        calibrate_s = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "subject.h5"
            cal.save(path)
            jaxskel.track(path, takes[0][1])  # compile the tracking programs
            jaxskel.fit_skeleton(takes[0][1])  # and the fit's for this take's shapes
            rows = []
            for take, trial in takes:
                t0 = time.perf_counter()
                fitted = jaxskel.fit_skeleton(trial)
                fit_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                (outcome,) = jaxskel.track(path, trial)
                track_s = time.perf_counter() - t0
                rows.append({
                    "take": take, "frames": trial.n_frames, "fit_s": round(fit_s, 3), "track_s": round(track_s, 3),
                    "ratio": round(fit_s / track_s, 1),
                    "fit_residual_mm": _median_mm(fitted.motion.marker_rms) if fitted.motion is not None else None,
                    "track_residual_mm": _median_mm(outcome.result.motion.marker_rms),
                    "fit_segments": fitted.segmentation.n_segments, "calibration_segments": cal.segmentation.n_segments,
                })
                print(f"  {take}: fit {fit_s:.2f} s, track {track_s:.2f} s ({fit_s / track_s:.1f}x); residual "
                      f"{rows[-1]['fit_residual_mm']} mm fitted, {rows[-1]['track_residual_mm']} mm tracked", flush=True)
            jaxskel.track(path, [t for _, t in takes])  # compile the gap prior for this total length's bucket
            t0 = time.perf_counter()
            batch = jaxskel.track(path, [t for _, t in takes])
            together_s = time.perf_counter() - t0
    assert all(o.status == "ok" for o in batch), [o.error for o in batch]
    fit_total = sum(r["fit_s"] for r in rows)
    print(f"  all {len(takes)} takes in one track call: {together_s:.2f} s ({together_s / len(takes):.2f} s per take; "
          f"{fit_total / together_s:.1f}x faster than fitting each)", flush=True)
    return {"case": name, "calibrate_s": round(calibrate_s, 2), "takes": rows,
            "together_s": round(together_s, 3), "together_ratio": round(fit_total / together_s, 1)}


def main() -> int:
    from jaxskel._runtime.own_process import own_process

    own_process()  # as the jaxskel command: single-threaded Eigen
    cases = []
    body = synth.full_body(seed=0)
    cal, _ = synth.simulate(body, motion="calibration", duration=20.0, noise=0.0005, seed=0)
    walks = [(f"walk {s}", synth.simulate(body, motion="walk", duration=10.0, noise=0.0005, seed=s)[0])
             for s in range(1, 9)]
    cases.append(_case("synthetic full body: 8 walks of 10 s", [cal], walks))
    if (DATA / "auto_marker_label/PronetoRun01.c3d").is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            kneel = jaxskel.load_sample()
            run = jaxskel.load(DATA / "auto_marker_label/PronetoRun01.c3d")
            static = jaxskel.load(DATA / "opensim_models/Hamner/subject02_static.trc")
            running = jaxskel.load(DATA / "opensim_models/Hamner/subject02_running.trc")
        cases.append(_case("Clouthier: KneeltoProne01 calibrates", [kneel],
                           [("PronetoRun01", run), ("KneeltoProne01", kneel)]))
        cases.append(_case("Hamner: static + running calibrate", [static, running], [("running", running)]))
    import jax

    first = jax.devices()[0]
    device = f"{first.platform} ({first.device_kind}), {os.cpu_count()} CPU cores"
    record = {"device": device, "cases": cases, "command": "python bench/track.py"}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "track.json").write_text(json.dumps(record, indent=1))
    lines = [
        "# Tracking on a saved skeleton against fitting each take",
        "",
        f"`python bench/track.py` on {device} (warm: every program compiled by a first run; times in seconds "
        "per take, ratio = fit time / track time; residual = median per-frame marker RMS).",
        "",
        "| case | take | frames | fit s | track s | ratio | residual fitted mm | residual tracked mm |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for c in cases:
        for r in c["takes"]:
            lines.append(f"| {c['case']} | {r['take']} | {r['frames']} | {r['fit_s']} | {r['track_s']} | "
                         f"{r['ratio']} | {r['fit_residual_mm']} | {r['track_residual_mm']} |")
    lines += ["", "All takes of a case in one `jaxskel.track` call (batched IK solves):", ""]
    for c in cases:
        n = len(c["takes"])
        lines.append(f"* {c['case']}: {n} takes in {c['together_s']} s ({c['together_s'] / n:.2f} s per take), "
                     f"{c['together_ratio']}x faster than fitting each; calibration fit {c['calibrate_s']} s.")
    (OUT / "track.md").write_text("\n".join(lines) + "\n")
    print(f"\nwrote {OUT / 'track.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
