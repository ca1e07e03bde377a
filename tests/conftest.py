import os
import sys
from pathlib import Path

# The CLI tests call jaxskel's main() in the test process, which turns JAX's persistent
# compilation cache on for the rest of that process (in ~/.cache/jaxskel/jax unless
# JAXSKEL_CACHE_DIR says otherwise). Tests should neither read programs cached by other
# code versions nor fill the developer's cache; the cache itself is tested in subprocesses
# with their own directory (tests/_runtime/test_compile_cache.py). Set JAXSKEL_CACHE_DIR to test with a cache.
os.environ.setdefault("JAXSKEL_CACHE_DIR", "")

import gc
import shutil
import tempfile

# The test run is jaxskel's own process, as the command line is: single-threaded Eigen
# (XLA_FLAGS) before JAX starts, against the thread-pool wedge of 2-core machines. JAX's
# 64-bit mode stays off: the library's public functions turn it on for their own calls.
from jaxskel._runtime.own_process import own_process

own_process()

import jax
import pytest

# One XLA compilation cache per test run, shared by the xdist workers and the processes
# tests start (notebook kernels, command lines): the controller makes the directory, sets
# it in the environment they all inherit (JAX reads JAX_COMPILATION_CACHE_DIR at import)
# and removes it at the end. Most of the suite's time is XLA compiling the solvers (4-6 s
# per program and shape on two cores), many of them the same in both workers. The cache
# is fresh per run, so no test sees code compiled by another version, and it is XLA's
# cache alone: jaxskel's saved programs (_program_cache) stay off, so every test traces
# the library's code as a user's first run does. Bounded, so JAX locks each entry.
_RUN_CACHE_BYTES = str(4 * 2**30)


def pytest_configure(config):
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") is None and not hasattr(config, "workerinput"):
        config._jaxskel_run_cache = tempfile.mkdtemp(prefix="jaxskel-test-xla-")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = config._jaxskel_run_cache
        os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = _RUN_CACHE_BYTES
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):  # ours, or one the developer set
        size = os.environ.get("JAX_COMPILATION_CACHE_MAX_SIZE", _RUN_CACHE_BYTES)
        jax.config.update("jax_compilation_cache_max_size", int(size))
        jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])


def pytest_unconfigure(config):
    made = getattr(config, "_jaxskel_run_cache", None)
    if made:
        shutil.rmtree(made, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
    """Each test module's compiled programs go when it ends (the next module loads what it
    shares from the run's cache). A worker keeps them otherwise: ~12 memory mappings each,
    54,941 in one worker by the end of a run, against the kernel's limit of 65,530
    (vm.max_map_count) past which XLA segfaults (jaxskel._runtime.map_limit)."""
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture
def float64():
    """JAX's 64-bit mode on for the test (``jaxskel._runtime.precision.float64``): for tests
    that call jaxskel's private JAX functions, which run inside the scope of the public
    functions that call them, or that compare against float64 themselves."""
    from jaxskel._runtime.precision import float64 as scope

    with scope():
        yield


import matplotlib

matplotlib.use("Agg")
sys.path.insert(0, str(Path(__file__).parent))
