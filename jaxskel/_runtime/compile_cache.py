"""The persistent compilation cache of a jaxskel process (CLI, batch workers).

Opt-in by the entry points that own their process (:mod:`jaxskel.cli`, the Dask
workers of :func:`jaxskel.fit_batch`); importing jaxskel never turns it on.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CACHE_MAX_BYTES", "cpu_identity", "enable_compile_cache", "machine_cache_dir"]


#: Bound of the persistent compilation cache (bytes; a fit's programs take a small
#: fraction of it, see docs/bench/evidence_from_docstrings.md).
CACHE_MAX_BYTES = 2 * 1024**3


def cpu_identity() -> str:
    """The host CPU as XLA:CPU compiles for it: model and instruction-set flags.

    Linux: the first processor's ``model name`` and ``flags`` lines of ``/proc/cpuinfo``;
    elsewhere what :mod:`platform` knows (processor, machine).
    """
    try:
        lines = Path("/proc/cpuinfo").read_text(errors="replace").splitlines()
    except OSError:
        lines = []
    wanted = ("model name", "flags", "features", "cpu part")  # x86; aarch64 names the last two
    found: dict[str, str] = {}
    for line in lines:
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key in wanted and key not in found:
            found[key] = " ".join(sorted(value.split())) if key in ("flags", "features") else value.strip()
    if found:
        return "|".join(f"{k}={found[k]}" for k in sorted(found))
    import platform

    return f"processor={platform.processor()}|machine={platform.machine()}"


def machine_cache_dir(base: Path) -> Path:
    """``base/<arch>-<hash of the CPU identity and jaxlib version>``.

    XLA:CPU compiles for the host's instruction set, and JAX's cache key does not
    include it. Loading a program compiled on another CPU only logs "Machine type used
    for XLA:CPU compilation doesn't match ... could lead to execution errors such as
    SIGILL" and runs it. A cache in a home directory shared by the nodes of a cluster
    (``jaxskel fit-batch --scheduler``), or a VM moved to another host, would do that.
    So each CPU model and flag set, and each jaxlib, gets its own subdirectory.
    """
    import hashlib
    import platform

    import jaxlib

    digest = hashlib.sha256(f"{cpu_identity()}|jaxlib={jaxlib.__version__}".encode()).hexdigest()[:16]
    return base / f"{platform.machine() or 'cpu'}-{digest}"


def enable_compile_cache(*, read_ahead: bool = True) -> Path | None:
    """Keep compiled programs on disk, so that a later process skips compiling them.

    Turns on JAX's persistent compilation cache (so a second process skips XLA's
    compilation) and saves jaxskel's traced solver and SD06 programs beside it
    (``<cache>-programs``, so it skips their tracing too). The ``jaxskel`` command
    does this for its own process. A library user calls it once, opting in: it sets
    JAX's process-wide ``jax_compilation_cache_dir`` (and its size bound and
    thresholds), which then serves every program of the process, not only
    jaxskel's; importing jaxskel never does.

    Location: a subdirectory per CPU model and jaxlib (:func:`machine_cache_dir`) of
    ``$JAXSKEL_CACHE_DIR`` or ``~/.cache/jaxskel/jax``; set ``JAXSKEL_CACHE_DIR=""`` to
    disable both, ``JAXSKEL_PROGRAM_CACHE=0`` to disable the saved programs alone.
    Returns the directory of the compiled code, or ``None`` when no cache could be set
    up (disabled, no ``filelock``, a read-only home or an old jax).

    ``read_ahead``: also start reading, in a background (daemon) thread, the compiled
    programs the last process that used this cache listed
    (:func:`jaxskel._runtime.program_cache.read_ahead`), so that this process's first fit
    finds them loaded; once per process. ``False``: nothing is read before it is called.
    """
    base = os.environ.get("JAXSKEL_CACHE_DIR", str(Path.home() / ".cache" / "jaxskel" / "jax"))
    if not base:
        return None
    cache = str(machine_cache_dir(Path(base)))
    try:
        # JAX locks cache entries only with filelock and a size bound (its LRU bookkeeping);
        # unbounded, entries are written in place unlocked while parallel fits may read them
        # (a torn read is caught by the entries' zlib checksum and recompiled, but a lock is
        # what JAX asks for a shared cache). No filelock: no cache.
        import filelock  # noqa: F401
    except ImportError:
        return None
    import jax

    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
        # Every program, however quick to compile: a fit runs many small ones (eager
        # array ops between the jitted stages), each costing a lowering and an XLA
        # compile per process; cached, a new process skips them for a little more disk
        # (measured: docs/bench/evidence_from_docstrings.md).
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        jax.config.update("jax_compilation_cache_dir", cache)  # last: only once locked and bounded
    except (OSError, AttributeError):  # read-only home or an old jax: run without the cache
        return None
    # The solvers' traced and lowered programs beside it: a new process then skips their
    # tracing too (jaxskel._runtime.program_cache). JAXSKEL_PROGRAM_CACHE=0 keeps only the compiled code.
    if os.environ.get("JAXSKEL_PROGRAM_CACHE", "1") != "0":
        from . import program_cache as _program_cache

        programs = Path(cache + "-programs")
        if _program_cache.current_directory() != programs:  # a second call keeps what is loaded
            _program_cache.set_directory(programs)
        if read_ahead:
            _program_cache.read_ahead()
    return Path(cache)
