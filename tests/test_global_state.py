"""jaxskel leaves the process it is imported into as it found it: no JAX setting, no
environment variable, no logging configuration; a float32 model next to it
stays float32. Its own computations run in float64 all the same (jaxskel._runtime.precision).

The import is checked in a fresh process each time (what an import changes stays for the
life of a process). The test process itself runs with JAX's defaults (64-bit mode off), so
the fit below is a float32 user's."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxskel
from jaxskel import synth

_IMPORT_PROBE = r"""
import json, logging, os

def state():
    root = logging.getLogger()
    return {
        "XLA_FLAGS": os.environ.get("XLA_FLAGS"),
        "x64_env": os.environ.get("JAX_ENABLE_X64"),
        "root_level": root.level,
        "root_handlers": [type(h).__name__ for h in root.handlers],
        "jax_logger": [logging.getLogger("jax").level, len(logging.getLogger("jax").handlers)],
    }

import jax, jax.numpy as jnp, numpy as np
before = dict(state(), x64=bool(jax.config.jax_enable_x64))
import jaxskel, jaxskel.cli
for name in jaxskel._SUBPACKAGES:  # every stage, as a user's first call would import it
    getattr(jaxskel, name)
after = dict(state(), x64=bool(jax.config.jax_enable_x64))
x = jnp.asarray(np.linspace(0.0, 1.0, 6).reshape(2, 3))
print(json.dumps({
    "before": before, "after": after,
    "ones": str(jnp.ones(3).dtype), "from_numpy": str(x.dtype),
    "jit": str(jax.jit(lambda a: a @ a.T + 1.0)(x).dtype),
}))
"""


@pytest.mark.parametrize("xla_flags", [None, "--xla_force_host_platform_device_count=1"], ids=["unset", "user's"])
def test_import_changes_no_global_state(xla_flags):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    run = subprocess.run([sys.executable, "-c", _IMPORT_PROBE], env=env, capture_output=True, text=True, timeout=300,
                         check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["after"] == out["before"]
    assert out["after"]["XLA_FLAGS"] == xla_flags and out["after"]["x64"] is False
    assert out["ones"] == out["from_numpy"] == out["jit"] == "float32"


def _root_logger() -> tuple:
    root = logging.getLogger()
    return root.level, tuple(root.handlers)


@pytest.mark.slow  # a whole fit, compiled: 30-110 s on a loaded 2-core machine without the run's cache
def test_a_fit_computes_in_float64_and_leaves_the_callers_float32_alone(monkeypatch):
    """A float32 user (this process) fits: every JAX operation jaxskel runs, in the calling
    thread and in its worker threads, runs in 64-bit mode, the results are float64, and the
    caller's mode, environment and logging are as they were."""
    assert not jax.config.jax_enable_x64, "something turned JAX's 64-bit mode on for the whole test process"
    flags, root = os.environ.get("XLA_FLAGS"), _root_logger()

    # Every primitive JAX binds from jaxskel's code, with the 64-bit mode it was bound in
    # (a probe of JAX internals: where they are not there, the dtypes below still tell).
    core = pytest.importorskip("jax._src.core")
    if not hasattr(core, "Primitive"):
        pytest.skip("this jax has no jax._src.core.Primitive")
    package = os.path.dirname(jaxskel.__file__)
    in_32_bit: set[str] = set()
    bind = core.Primitive.bind

    def recording_bind(self, *args, **params):
        if not jax.config.jax_enable_x64:
            frame = sys._getframe(1)
            while frame is not None and not frame.f_code.co_filename.startswith(package):
                frame = frame.f_back
            if frame is not None:
                in_32_bit.add(f"{os.path.relpath(frame.f_code.co_filename, package)}:{frame.f_code.co_name}")
        return bind(self, *args, **params)

    monkeypatch.setattr(core.Primitive, "bind", recording_bind)
    trial, _ = synth.simulate(synth.linkage(), duration=3.0, seed=0, noise=0.001)
    result = jaxskel.fit_skeleton(trial)
    (batch,) = jaxskel.fit_batch([trial], jobs=2)  # its preparing and finishing threads
    monkeypatch.undo()

    assert not in_32_bit, f"jaxskel ran JAX code in 32-bit mode: {sorted(in_32_bit)}"
    arrays = {
        "joint positions": result.topology.joint_positions, "joint costs": result.topology.joint_cost,
        "marker offsets": result.skeleton.marker_offsets, "bone lengths": result.skeleton.bone_lengths,
        "rotations": result.motion.rotations, "ik residual": result.motion.marker_rms,
    }
    for name, value in arrays.items():
        assert isinstance(value, np.ndarray) and value.dtype == np.float64, (name, type(value), value.dtype)
    assert batch.ok and batch.result.motion.rotations.dtype == np.float64

    assert not jax.config.jax_enable_x64
    assert os.environ.get("XLA_FLAGS") == flags and _root_logger() == root
    x = jnp.asarray(np.ones((2, 3)))
    assert x.dtype == jnp.float32 and jax.jit(lambda a: a @ a.T + 1.0)(x).dtype == jnp.float32


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, np.cos(2 * angle), -np.sin(2 * angle)], [0.0, np.sin(2 * angle), np.cos(2 * angle)]]
    )


def test_stage_functions_compute_float64_from_numpy_in_a_float32_process():
    """A public stage function given numpy's float64 arrays computes and answers in float64
    (the pairwise distances of a rigid body far from the origin keep a constant length to
    float64's round-off; float32 would leave ~1e-8 m of scatter)."""
    assert not jax.config.jax_enable_x64
    rng = np.random.default_rng(0)
    body = rng.normal(0.0, 0.1, (5, 3))
    frames = np.stack([body @ _rotation(a).T + [3.0, -2.0, 1.5] for a in np.linspace(0.0, 3.0, 50)])
    a, _ = jaxskel.segment.distance_std(frames, np.ones(frames.shape[:2], bool))
    assert a.dtype == jnp.float64 and float(np.max(np.asarray(a))) < 1e-12
    assert not jax.config.jax_enable_x64


def test_learn_functions_stay_float32_inside_a_float32_model():
    """The learn API in a float32 user's own jit and grad computes in float32: no float64
    anywhere in the program (joint_cost_fn and its gradient, rigid_fit_fn)."""
    assert not jax.config.jax_enable_x64
    trial, truth = synth.simulate(synth.linkage(), duration=1.0, rate=60, seed=3, noise=0.0005)
    x, mask = trial.to_arrays(np.float32)
    pair = jnp.asarray(x[:, :6]), jnp.asarray(mask[:, :6])
    assert pair[0].dtype == jnp.float32

    def loss(markers, present):
        return jaxskel.learn.joint_cost_fn(markers, present, alpha=1e-3).cost

    # the programs the user's jit would compile, traced (not compiled: a jaxpr shows every
    # dtype, and compiling the solvers in float32 as well would cost many seconds)
    jaxpr = str(jax.make_jaxpr(loss)(*pair))
    assert "f64" not in jaxpr and "f32" in jaxpr
    assert "f64" not in str(jax.make_jaxpr(jax.grad(loss))(*pair))
    structure = jaxskel.learn.SkeletonStructure(truth.edges, truth.marker_segment)
    joints = jnp.asarray(truth.joint_positions, jnp.float32)
    rigid = jax.make_jaxpr(lambda m, j: jaxskel.learn.rigid_fit_fn(structure, m, jnp.asarray(mask), j).bone_lengths)
    assert "f64" not in str(rigid(jnp.asarray(x), joints))
    assert not jax.config.jax_enable_x64
