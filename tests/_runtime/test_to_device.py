"""``to_device``: host arrays onto the device as ``jnp.asarray`` puts them, compiling nothing,
and a fit and SD06 that hand their host arrays to compiled stages without op-by-op programs."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._runtime.backend import to_device

CASES = [
    (np.arange(12.0).reshape(3, 4), None),
    (np.arange(12.0).reshape(3, 4), np.float32),
    (2.5, np.float64),
    (np.arange(5), None),
    (np.arange(5), np.int32),
    (7, np.int32),
    (True, bool),
    (np.ones((2, 1), bool), None),
    (np.ones((1, 3)), jnp.float64),
    (3, None),  # Python numbers: weakly typed
    (2.5, None),
]


@pytest.mark.parametrize("x64", [False, True])
@pytest.mark.parametrize("value,dtype", CASES)
def test_to_device_equals_jnp_asarray(value, dtype, x64):
    with jax.enable_x64(x64):
        got = to_device(value, dtype)
        with np.errstate(all="ignore"), pytest.warns(UserWarning) if (
            not x64 and dtype is not None and np.dtype(dtype).itemsize == 8
        ) else _no_warning():
            want = jnp.asarray(value, dtype)
        assert isinstance(got, jax.Array)
        assert (got.dtype, got.shape, got.weak_type) == (want.dtype, want.shape, want.weak_type)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        same = to_device(got)  # a device array in its dtype passes through
        assert same is got


class _no_warning:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_to_device_compiles_nothing():
    records: list[str] = []

    class Grab(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Compiling "):
                records.append(record.getMessage().split()[1])

    handler, logger = Grab(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True), jax.enable_x64(True):
            to_device(np.zeros((7, 13, 3)))  # shapes no other test uses
            to_device(np.zeros((11, 5), np.float32), np.float64)
            to_device(0.25, np.float64)
            to_device(17)
            jnp.asarray(np.zeros((7, 13, 2)))  # the comparison: jnp.asarray does compile
    finally:
        logger.removeHandler(handler)
    assert records == ["jit(stage)"], records


# The programs a fresh process compiles for a whole fit. Host-side orchestration hands
# numpy arrays to compiled stages (to_device) and keeps its own geometry in numpy, so no
# array operation runs eagerly: every compiled program is a named stage (the names below
# are the op-by-op programs eager jnp compiles: this fit compiled 95 programs before, 13 now; SD06's
# normalize and parameterize 14 op-by-op programs before, none now).
# ``convert_element_type`` is not listed: optimistix's BFGS converts one constant eagerly
# while it is traced.
_PROBE = textwrap.dedent("""
    import collections, json, logging, warnings
    import jax
    names = {"fit": collections.Counter(), "sd06": collections.Counter()}
    stage = ["fit"]
    class Grab(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Compiling "):
                names[stage[0]][record.getMessage().split()[1]] += 1
    logging.getLogger("jax").addHandler(Grab())
    jax.config.update("jax_log_compiles", True)
    warnings.simplefilter("ignore")
    import jaxskel
    from jaxskel import synth
    from jaxskel.sd06 import normalize, parameterize
    trial, _ = synth.simulate(synth.full_body(seed=0), "calibration", duration=3.0, rate=60.0, seed=0)
    result = jaxskel.fit_skeleton(trial, n_segments=15, progress=False)
    assert result.motion is not None
    stage[0] = "sd06"
    parameterize(result.skeleton, result.motion, normalize(result.skeleton, result.motion))
    print(json.dumps(names))
""")
_EAGER = {
    "stage", "add", "subtract", "multiply", "true_divide", "broadcast_in_dim", "iota", "stack", "unstack", "gather",
    "scatter", "equal", "less", "greater", "squeeze", "_squeeze", "dynamic_slice", "select_n", "_where", "_einsum",
    "matmul", "solve", "round", "_moveaxis", "_broadcast_arrays", "concatenate", "reshape", "transpose",
}


def test_a_fit_and_sd06_compile_no_op_by_op_programs():
    import json

    run = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    names = json.loads(run.stdout.strip().splitlines()[-1])
    for stage, compiled in names.items():
        eager = {n: c for n, c in compiled.items() if n.removeprefix("jit(").removesuffix(")") in _EAGER}
        assert not eager, f"op-by-op programs compiled by {stage}: {eager}"
    # and the stages did compile (the probe saw the compiles at all)
    assert {"jit(solve_chunk)", "jit(procrustes)", "jit(_chunk_solve)"} <= set(names["fit"]), names
    assert {"jit(_normalize_core)", "jit(_filter_stage)", "jit(_angles_stage)"} <= set(names["sd06"]), names
