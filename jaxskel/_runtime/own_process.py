"""Process-wide settings of the processes that jaxskel runs itself.

Importing jaxskel changes nothing in the process it is imported into. A process started
to run jaxskel (the ``jaxskel`` command, the benchmark scripts in ``bench/``, the test
suite) is jaxskel's own, and calls :func:`own_process` before JAX's first computation.

Single-threaded Eigen. XLA's CPU backend then runs with
``--xla_cpu_multi_thread_eigen=false`` in ``XLA_FLAGS``, unless ``XLA_FLAGS`` already
sets that flag or ``JAXSKEL_XLA_MULTI_THREAD=1``. With the multi-threaded Eigen pool,
batched LAPACK kernels were seen to wedge for good on 2-core machines under load: two
kernels each wait for work queued behind the other on a pool of two threads
(:mod:`jaxskel._math.linalg`, docs/design.md). XLA reads ``XLA_FLAGS`` when its CPU
backend starts, so in a process that has already run JAX code the setting reaches only
the processes it starts (a Dask ``LocalCluster``'s workers).
"""

from __future__ import annotations

import os

__all__ = ["SINGLE_THREADED_EIGEN", "own_process"]

#: The ``XLA_FLAGS`` entry that gives XLA's CPU backend a single-threaded Eigen.
SINGLE_THREADED_EIGEN = "--xla_cpu_multi_thread_eigen=false"


def own_process(*, x64: bool = False) -> None:
    """Set up this process as jaxskel's own (module docstring).

    ``x64=True`` also turns JAX's 64-bit mode on for the whole process, for scripts that
    call jaxskel's private functions or build JAX arrays of their own and need float64
    (the benchmarks); jaxskel's public functions compute in float64 without it.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if not os.environ.get("JAXSKEL_XLA_MULTI_THREAD") and "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {SINGLE_THREADED_EIGEN}".strip()
    if x64:
        import jax

        jax.config.update("jax_enable_x64", True)
