"""Speed of jaxskel.sd06.parameterize on a long recording, next to a plain NumPy per-frame reference.

Usage::

    PYTHONPATH=. python bench/sd06_speed.py [--frames 24000] [--out docs/bench/sd06_speed.md]

The recording is synthetic (``synth.full_body``, every degree of freedom moving,
the true segment poses: no IK). Each timing of ``parameterize`` runs in a fresh
Python process (so "first call" includes JAX's tracing and compilation), then
the same call is repeated in that process: once without persistent caches (the
library's default), then twice with the caches the ``jaxskel`` command turns on
(:func:`jaxskel._runtime.compile_cache.enable_compile_cache`: XLA's compiled code
and the exported programs, in a new temporary directory), empty and then filled
by the previous run. The reference computes the same
per-frame quantities (relative limb rotations, samples, circle-intersection
angles with the branch by continuity, twist) with NumPy in a Python loop over
frames, given the axes and rest pose ``parameterize`` found; it does no axis
extraction, so it is a lower bound for a per-frame implementation.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def recording(n_frames: int):
    from scipy.spatial.transform import Rotation

    from jaxskel import synth

    body = synth.full_body(seed=0)
    rate = 120.0
    _, truth = synth.simulate(body, "calibration", duration=n_frames / rate, rate=rate, seed=0)
    rot = truth.segment_rotations[:n_frames]
    quats = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(*rot.shape[:2], 4)
    return body, truth.joint_positions[:n_frames], quats, truth.segment_translations[:n_frames], rate


def child(n_frames: int) -> None:
    """Runs in a fresh process: time the first and a repeated parameterize call; print JSON."""
    body, joints, quats, trans, rate = recording(n_frames)
    if os.environ.get("JAXSKEL_CACHE_DIR"):
        # what the jaxskel command does for its process: compiled code and exported programs on disk
        from jaxskel._runtime.compile_cache import enable_compile_cache

        enable_compile_cache()
    from jaxskel.sd06 import parameterize_arrays

    def call():
        return parameterize_arrays(joints, body.edges, quats, root=body.root, segment_translations=trans, rate=rate)

    t0 = time.perf_counter()
    param = call()
    first = time.perf_counter() - t0
    repeats = []
    for _ in range(3):
        t0 = time.perf_counter()
        call()
        repeats.append(time.perf_counter() - t0)
    np.savez("/tmp/sd06_speed_param.npz", axes=param.axes, n_axes=param.n_axes, rest_rotation=param.rest_rotation,
             rest_direction=param.rest_direction, limb=param.normalization.limb_frames, edges=body.edges,
             main_axis=param.normalization.main_axis, main_sign=param.normalization.main_sign,
             rest_frame=param.rest_frame, angles=param.angles)
    print(json.dumps({"first": first, "repeat": min(repeats), "repeats": repeats}))


def _angle_about(a, u, v):
    return np.arctan2(np.cross(u, v) @ a, u @ v - (a @ u) * (a @ v))


def numpy_reference() -> tuple[float, float]:
    """Per-frame NumPy loop over the angles of every joint; returns (seconds, max angle difference in rad)."""
    from scipy.spatial.transform import Rotation

    z = np.load("/tmp/sd06_speed_param.npz")
    limb, edges = z["limb"], z["edges"]
    main = np.eye(3)[z["main_axis"]] * z["main_sign"][:, None]
    n_f, n_j = limb.shape[0], edges.shape[0]
    out = np.zeros((n_f, n_j, 3))
    t0 = time.perf_counter()
    for j in range(n_j):
        a, b = z["axes"][j]
        r = z["rest_direction"][j]
        rest = Rotation.from_quat(z["rest_rotation"][j], scalar_first=True).as_matrix()
        two = z["n_axes"][j] == 2
        start = int(z["rest_frame"][j])
        prev = np.zeros(2)
        for f in list(range(start, n_f)) + list(range(start - 1, -1, -1)):
            if f == start - 1:
                prev = np.zeros(2)
            q = limb[f, edges[j, 0]].T @ limb[f, edges[j, 1]]
            p = q @ main[edges[j, 1]]
            if two:
                c = a @ b
                h1, h2 = a @ r, p @ b
                x0 = ((h1 - c * h2) * a + (h2 - c * h1) * b) / (1 - c * c)
                line = np.cross(a, b) / np.linalg.norm(np.cross(a, b))
                t = np.sqrt(max(1 - x0 @ x0, 0.0))
                best, cost = None, np.inf
                for x in (x0 + t * line, x0 - t * line):
                    x = x / np.linalg.norm(x)
                    ab = np.array([_angle_about(a, r, x), _angle_about(b, x, p)])
                    step = np.angle(np.exp(1j * (ab - prev)))
                    k = step @ step + 0.1 * ab @ ab
                    if k < cost:
                        best, cost = ab, k
                alpha, beta = prev = best
                swing = Rotation.from_rotvec(beta * b) * Rotation.from_rotvec(alpha * a)
            else:
                alpha, beta = _angle_about(a, r, p), 0.0
                swing = Rotation.from_rotvec(alpha * a)
            d = swing.apply(r)
            m = Rotation.from_matrix(q @ (swing.as_matrix() @ rest).T).as_quat()  # x, y, z, w
            if m[3] < 0:
                m = -m
            out[f, j] = alpha, beta, 2 * np.arctan2(m[:3] @ d, m[3])
    seconds = time.perf_counter() - t0
    diff = np.abs(np.angle(np.exp(1j * (out - z["angles"]))))
    return seconds, float(np.max(diff))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24000)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "sd06_speed.md")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.frames)
        return
    import tempfile

    runs = []
    with tempfile.TemporaryDirectory(prefix="sd06-speed-cache-") as cache:
        cases = (
            ("no persistent cache (library default)", ""),
            ("`jaxskel` command's caches, empty", cache),
            ("`jaxskel` command's caches, filled by the run above", cache),
        )
        for label, cache_dir in cases:
            env = {**os.environ, "PYTHONPATH": str(ROOT), "JAXSKEL_CACHE_DIR": cache_dir}
            res = subprocess.run([sys.executable, __file__, "--child", "--frames", str(args.frames)], env=env,
                                 capture_output=True, text=True, check=True)
            runs.append((label, json.loads(res.stdout.strip().splitlines()[-1])))
    ref_s, ref_diff = numpy_reference()
    import jax

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    device = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores visible (load average {load} "
              f"at the end, shared machine), JAX {jax.__version__} on {jax.default_backend()}")
    lines = [
        "# SD06 parameterisation speed",
        "",
        f"Command: `PYTHONPATH=. python bench/sd06_speed.py --frames {args.frames}`",
        "",
        f"Device: {device} (no GPU). Recording: `synth.full_body`, 14 joints, {args.frames} frames at 120 Hz, "
        "every degree of freedom moving; `parameterize_arrays` with the defaults (direction joining).",
        "",
        "| what | seconds |",
        "|---|---|",
    ]
    for i, (label, r) in enumerate(runs):
        lines.append(f"| run {i + 1}, {label}: `parameterize`, first call in a fresh process | {r['first']:.2f} |")
        lines.append(f"| run {i + 1}: repeated call in that process (best of 3) | {r['repeat']:.3f} |")
    lines += [
        f"| NumPy per-frame loop: angles only, given the axes (reference) | {ref_s:.2f} |",
        "",
        f"Largest angle difference between the reference and `parameterize`: {ref_diff:.2e} rad.",
        "",
        "Targets (issue 47): first call under 2 s, repeated call under 0.5 s.",
        "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
