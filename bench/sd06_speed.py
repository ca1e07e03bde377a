"""Speed of jaxskel.sd06.parameterize on a long recording, next to a plain NumPy per-frame reference.

Usage::

    PYTHONPATH=. python bench/sd06_speed.py [--frames 24000] [--out docs/bench/sd06_speed.md]
    PYTHONPATH=. python bench/sd06_speed.py --compile-study   # where the first call's time goes

The recording is synthetic (``synth.full_body``, every degree of freedom moving,
the true segment poses: no IK). Each run is a fresh Python process (so "first
call" includes JAX's tracing and compilation) that times ``normalize``, then
``parameterize`` given that normalisation (the split of issue 47's figures), then
repeats both (median of ``REPEATS``); "whole" is the two together, what
``parameterize`` without a normalisation and ``jaxskel fit --parameterize`` do. It
runs once without persistent caches (the library's default), then twice with the
caches the ``jaxskel`` command turns on
(:func:`jaxskel._runtime.compile_cache.enable_compile_cache`: XLA's compiled code
and the exported programs, in a new temporary directory), empty and then filled
by the previous run. The reference computes the angles given the axes and rest
pose ``parameterize`` found (relative limb rotations, samples, circle-intersection
angles with the branch by continuity, twist) in NumPy, vectorised over frames with
the branch walk a scalar Python loop; it extracts no axes, so it does a fraction of
``parameterize``'s work.

``--compile-study`` (fresh process, no persistent cache) times each of ``parameterize``'s
three stage programs apart: tracing and lowering, XLA compilation (wall and process CPU
time: XLA:CPU compiles on several threads) and a run, and what the first call spends besides
(tracing, lowering, host work), at XLA's backend optimisation
levels 2 (the default), 1 and 0, and the three compiled at once on three threads. It
appends the table to ``--out``.
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
#: Repeated calls timed in each process (the median is reported).
REPEATS = 5


def recording(n_frames: int):
    from scipy.spatial.transform import Rotation

    from jaxskel import synth

    body = synth.full_body(seed=0)
    rate = 120.0
    _, truth = synth.simulate(body, "calibration", duration=n_frames / rate, rate=rate, seed=0)
    rot = truth.segment_rotations[:n_frames]
    quats = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(*rot.shape[:2], 4)
    return body, truth.joint_positions[:n_frames], quats, truth.segment_translations[:n_frames], rate


def inputs(n_frames: int):
    """(body, skeleton, motion): the recording as the ``skeleton`` and ``motion`` objects ``normalize`` and
    ``parameterize`` read."""
    from types import SimpleNamespace

    body, joints, quats, trans, rate = recording(n_frames)
    skeleton = SimpleNamespace(edges=body.edges, root=body.root)
    motion = SimpleNamespace(joint_positions=joints, rotations=quats, segment_translations=trans, rate=rate)
    return body, skeleton, motion


def child(n_frames: int) -> None:
    """Runs in a fresh process: time the first and repeated calls of normalize, of parameterize given
    that normalisation, and of the whole (parameterize_arrays normalises too); print JSON."""
    body, skeleton, motion = inputs(n_frames)
    if os.environ.get("JAXSKEL_CACHE_DIR"):
        # what the jaxskel command does for its process: compiled code and exported programs on disk
        from jaxskel._runtime.compile_cache import enable_compile_cache

        enable_compile_cache()
    from jaxskel.sd06 import normalize, parameterize

    def timed(fn):
        t0 = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - t0

    norm, norm_first = timed(lambda: normalize(skeleton, motion))
    param, param_first = timed(lambda: parameterize(skeleton, motion, norm))
    repeats = {"normalize": [], "parameterize": [], "whole": []}
    for _ in range(REPEATS):
        repeats["normalize"].append(timed(lambda: normalize(skeleton, motion))[1])
        repeats["parameterize"].append(timed(lambda: parameterize(skeleton, motion, norm))[1])
        repeats["whole"].append(timed(lambda: parameterize(skeleton, motion))[1])
    assert param.angles.dtype == np.float64
    np.savez("/tmp/sd06_speed_param.npz", axes=param.axes, n_axes=param.n_axes, rest_rotation=param.rest_rotation,
             rest_direction=param.rest_direction, limb=param.normalization.limb_frames, edges=body.edges,
             main_axis=param.normalization.main_axis, main_sign=param.normalization.main_sign,
             rest_frame=param.rest_frame, angles=param.angles)
    print(json.dumps({
        "first": {"normalize": norm_first, "parameterize": param_first, "whole": norm_first + param_first},
        "repeat": {k: float(np.median(v)) for k, v in repeats.items()},
        "repeats": repeats,
    }))


STAGES = ("_filter_stage", "_axes_stage", "_angles_stage")
STUDY_HEADING = "## Where the first call's time goes"


def compile_study(n_frames: int) -> dict:
    """Runs in a fresh process: each stage program's trace, compile and run time by optimisation level."""
    from concurrent.futures import ThreadPoolExecutor

    import jax

    from jaxskel.sd06 import _parameterize, normalize, parameterize

    _, skeleton, motion = inputs(n_frames)
    norm = normalize(skeleton, motion)
    programs, calls = {name: getattr(_parameterize, name) for name in STAGES}, {}

    def recorder(name):
        def call(*args, **kwargs):
            calls[name] = (args, kwargs)
            return programs[name](*args, **kwargs)
        return call

    for name in STAGES:  # the stages' arguments, as parameterize passes them
        setattr(_parameterize, name, recorder(name))
    try:
        t0 = time.perf_counter()
        parameterize(skeleton, motion, norm)
        first = time.perf_counter() - t0
    finally:
        for name in STAGES:
            setattr(_parameterize, name, programs[name])

    def lowered(name, level):
        program = programs[name]
        options = {**program.compiler_options, "xla_backend_optimization_level": level}
        args, kwargs = calls[name]
        static = set(program._kwargs.get("static_argnames", ()))
        dynamic = {k: v for k, v in kwargs.items() if k not in static}  # a compiled program takes these only
        return jax.jit(program._fn, compiler_options=options, **program._kwargs).lower(*args, **kwargs), args, dynamic

    rows = []
    with jax.enable_x64(True):  # as parameterize runs them (float64_scope)
        for level in (2, 1, 0):
            for name in STAGES:
                low, args, kwargs = lowered(name, level)
                t0, c0 = time.perf_counter(), time.process_time()
                compiled = low.compile()
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                runs = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    jax.block_until_ready(compiled(*args, **kwargs))
                    runs.append(time.perf_counter() - t0)
                text = compiled.as_text() or ""
                rows.append({"level": level, "stage": name.strip("_"), "compile": wall,
                             "compile_cpu": cpu, "run": min(runs), "fusions": text.count(" fusion(")})
        jax.clear_caches()  # the programs above stay compiled in memory otherwise
        lows = [lowered(name, 2)[0] for name in STAGES]
        t0, c0 = time.perf_counter(), time.process_time()
        with ThreadPoolExecutor(len(lows)) as pool:
            list(pool.map(lambda low: low.compile(), lows))
        together = {"compile": time.perf_counter() - t0, "compile_cpu": time.process_time() - c0}
    return {"rows": rows, "together": together, "first": first}


def compile_study_lines(study: dict) -> list[str]:
    lines = [
        STUDY_HEADING + " (`--compile-study`)",
        "",
        "Each stage program of `parameterize`, in a fresh process without persistent caches, compiled at XLA's "
        "backend optimisation levels (2 is XLA's default and jaxskel's). Seconds; compile CPU is the process's "
        "CPU time during the compilation (XLA:CPU compiles on several threads).",
        "",
        "| level | stage | compile (wall) | compile (CPU) | run | fusions |",
        "|---|---|---|---|---|---|",
    ]
    for r in study["rows"]:
        lines.append(f"| {r['level']} | `{r['stage']}` | {r['compile']:.2f} | "
                     f"{r['compile_cpu']:.2f} | {r['run']:.3f} | {r['fusions']} |")
    level2 = [r for r in study["rows"] if r["level"] == 2]
    rest = study["first"] - sum(r["compile"] + r["run"] for r in level2)
    lines += [
        "",
        f"* the first `parameterize` call of this process (given the normalisation): {study['first']:.2f} s, of "
        f"which {rest:.2f} s is not the three programs' compilation and run (tracing, lowering, host work)",
    ]
    for level in (2, 1, 0):
        rows = [r for r in study["rows"] if r["level"] == level]
        compile_s, run_s = sum(r["compile"] for r in rows), sum(r["run"] for r in rows)
        lines.append(f"* level {level}: compile {compile_s:.2f} s (CPU {sum(r['compile_cpu'] for r in rows):.2f} s), "
                     f"run {run_s:.3f} s; a first call compiled at this level would take about "
                     f"{rest + compile_s + run_s:.1f} s (the rest above, compilation, one run)")
    t = study["together"]
    lines += [
        f"* level 2, the three compiled at once on three threads: {t['compile']:.2f} s (CPU {t['compile_cpu']:.2f} s)",
        "",
    ]
    return lines


def numpy_reference() -> tuple[float, float]:
    """The angles of every joint given the axes, in NumPy: vectorised over frames, the branch walk a
    scalar loop (``tests/sd06/sd06_truth.reference_angles``, the tests' reference). Returns (seconds,
    largest angle difference to parameterize, rad)."""
    from scipy.spatial.transform import Rotation

    sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "sd06")]
    from sd06_truth import reference_angles

    z = np.load("/tmp/sd06_speed_param.npz")
    limb, edges = z["limb"], z["edges"]
    main = np.eye(3)[z["main_axis"]] * z["main_sign"][:, None]
    out = np.zeros((limb.shape[0], edges.shape[0], 3))
    t0 = time.perf_counter()
    for j, (parent, child) in enumerate(edges):
        q = np.einsum("fji,fjk->fik", limb[:, parent], limb[:, child])
        rest = Rotation.from_quat(z["rest_rotation"][j], scalar_first=True).as_matrix()
        a, b = z["axes"][j]
        out[:, j] = reference_angles(q, a, b if z["n_axes"][j] == 2 else None, rest, main[child],
                                     start=int(z["rest_frame"][j]))
    seconds = time.perf_counter() - t0
    diff = np.abs(np.angle(np.exp(1j * (out - z["angles"]))))
    return seconds, float(np.max(diff))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24000)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / "sd06_speed.md")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--compile-study", action="store_true", help="time each stage's compilation (appends to --out)")
    args = ap.parse_args()
    if args.child and args.compile_study:
        print(json.dumps(compile_study(args.frames)))
        return
    if args.child:
        child(args.frames)
        return
    if args.compile_study:
        env = {**os.environ, "PYTHONPATH": str(ROOT), "JAXSKEL_CACHE_DIR": ""}
        res = subprocess.run([sys.executable, __file__, "--child", "--compile-study", "--frames", str(args.frames)],
                             env=env, capture_output=True, text=True, check=True)
        lines = compile_study_lines(json.loads(res.stdout.strip().splitlines()[-1]))
        text = args.out.read_text(encoding="utf-8") if args.out.exists() else ""
        head = text.split(STUDY_HEADING)[0].rstrip("\n")
        args.out.write_text((head + "\n\n" if head else "") + "\n".join(lines), encoding="utf-8")
        print("\n".join(lines))
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
        "every degree of freedom moving; the defaults (direction joining, automatic calibration).",
        "",
        "| seconds | `normalize` | `parameterize` (given the normalisation) | whole |",
        "|---|---|---|---|",
    ]
    for i, (label, r) in enumerate(runs):
        first, rep = r["first"], r["repeat"]
        lines.append(f"| run {i + 1}, {label}: first call in a fresh process | {first['normalize']:.2f} | "
                     f"{first['parameterize']:.2f} | {first['whole']:.2f} |")
        lines.append(f"| run {i + 1}: repeated call in that process (median of {REPEATS}) | {rep['normalize']:.3f} | "
                     f"{rep['parameterize']:.3f} | {rep['whole']:.3f} |")
    best = runs[-1][1]["repeat"]
    lines += [
        f"| NumPy reference: angles only, given the axes (vectorised over frames, scalar branch walk) | | "
        f"{ref_s:.3f} | |",
        "",
        f"Repeated `parameterize` (given the normalisation) against the NumPy reference: "
        f"{ref_s / best['parameterize']:.1f}x; the whole against the reference: {ref_s / best['whole']:.1f}x.",
        f"Largest angle difference between the reference and `parameterize`: {ref_diff:.2e} rad.",
        "",
        "Targets (issue 47): `parameterize` first call under 2 s, repeated call under 0.5 s. Without a "
        "persistent cache the first call is XLA compiling the four stage programs; the `jaxskel` command "
        "keeps them on disk, and a library user can do the same with `jaxskel.enable_compile_cache()`.",
        "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    study = args.out.read_text(encoding="utf-8").split(STUDY_HEADING) if args.out.exists() else []
    kept = [STUDY_HEADING + study[1]] if len(study) > 1 else []  # a --compile-study section stays
    args.out.write_text("\n".join(lines + kept), encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
