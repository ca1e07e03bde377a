"""Saved traced programs, so that a new process skips tracing and lowering.

The persistent compilation cache (:func:`jaxskel._runtime.compile_cache.enable_compile_cache`) keeps
XLA's compiled code, but a new process still traces every jitted stage in Python and
lowers it to StableHLO before it can look that code up. For the solvers, built from
optimistix and equinox, this is most of what a cached ``jaxskel fit`` still pays, and
most of that is in the few solver programs that go through :func:`call` (measured:
docs/bench/evidence_from_docstrings.md).

:func:`call` runs a jitted function through a :func:`jax.export` of it: traced and
lowered once, serialized to ``<directory>/<name>-<key>.jaxexport``, and in a later
process deserialized and called. The StableHLO module it hands to XLA is the same bytes
in both processes, so the compilation cache finds its compiled code too. ``key`` is a
SHA-256 over everything that decides the traced program:

* the source of every module of this package (any edit gives new keys),
* the versions of the libraries traced into the programs (jax, jaxlib, optimistix,
  equinox, lineax, numpy), the backend, the x64 flag,
* the function's module and name, its static keyword arguments (``repr``), the
  argument tree (``str`` of the treedef: container types, equinox fields and their
  static values) and every leaf's type (dtype, shape, weak type).

The x64 flag is read in the calling thread: JAX's 64-bit mode is per thread, and jaxskel
turns it on only for its own calls (:mod:`jaxskel._runtime.precision`). The in-process
programs are kept by the same flag.

With no directory set (the default, and every library call outside the command line)
:func:`call` is ``fn(*args, **static)``. The exported program is not differentiable
(serialized without VJP), so tracers bypass it too. Any failure to export, read or
deserialize a program falls back to the plain call; the directory is pruned, oldest
used first, beyond ``MAX_BYTES``.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable

import jax

from .._errors import InputError
from ..io import atomic_output

__all__ = ["call", "set_directory"]

#: Bound of the saved programs (bytes; a fit's programs take a small fraction of it, see
#: docs/bench/evidence_from_docstrings.md).
MAX_BYTES = 256 * 2**20
_SUFFIX = ".jaxexport"

_log = logging.getLogger(__name__)
_lock = threading.Lock()
_state: dict[str, Any] = {"directory": None}
#: In-process programs by (function, static arguments, treedef, leaf types).
_programs: dict[tuple, Callable] = {}


def set_directory(path: str | os.PathLike | None) -> None:
    """Save and load programs under ``path`` (``None``: plain jitted calls; also where
    jax has no :func:`jax.export` or ``flatbuffers``, which serializes its programs, is
    missing)."""
    if path is not None and not _supported():
        path = None
    with _lock:
        _state["directory"] = None if path is None else Path(path)
        _programs.clear()


def _supported() -> bool:
    try:
        import flatbuffers  # noqa: F401
    except ImportError:
        return False
    return hasattr(jax, "export") and hasattr(jax, "typeof")


#: Libraries whose code is traced into the programs (their versions are keyed).
_TRACED_LIBRARIES = ("jax", "jaxlib", "optimistix", "equinox", "lineax", "numpy")


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """SHA-256 over this package's Python sources (paths and contents) and the versions
    of the libraries traced into its programs."""
    from importlib import metadata

    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    for name in _TRACED_LIBRARIES:
        try:
            digest.update(f"{name}=={metadata.version(name)}".encode())
        except metadata.PackageNotFoundError:
            digest.update(f"{name} missing".encode())
    return digest.hexdigest()


def call(fn: Callable, *args: Any, **static: Any) -> Any:
    """``fn(*args, **static)`` through a saved export of ``fn`` when a directory is set.

    ``fn`` is a :func:`jax.jit` function whose keyword arguments are its static ones
    and whose output is a tuple, list or dict of arrays (containers that
    :mod:`jax.export` serializes); ``args`` may be any pytrees of arrays.
    """
    folder = _state["directory"]
    if folder is None:
        return fn(*args, **static)
    leaves, treedef = jax.tree.flatten(args)
    if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
        return fn(*args, **static)
    types = tuple(jax.typeof(leaf) for leaf in leaves)
    # the 64-bit mode is per thread (jaxskel._runtime.precision) and changes the traced program
    memo = (fn, tuple(sorted(static.items())), treedef, types, bool(jax.config.jax_enable_x64))
    program = _programs.get(memo)
    if program is None:
        with _lock:
            program = _programs.get(memo)
            if program is None:
                program = _programs[memo] = _program(folder, fn, static, treedef, types)
    return program(*leaves)


def _program(folder: Path, fn: Callable, static: dict, treedef: Any, types: tuple) -> Callable:
    """The jitted call of ``fn``'s exported program: loaded, else exported and saved."""
    name = getattr(fn, "__name__", "program")
    key = hashlib.sha256(
        repr((
            _source_digest(), jax.default_backend(),
            bool(jax.config.jax_enable_x64), getattr(fn, "__module__", ""), getattr(fn, "__qualname__", name),
            sorted((k, repr(v)) for k, v in static.items()), str(treedef), [str(t) for t in types],
        )).encode()
    ).hexdigest()[:40]
    path = folder / f"{name}-{key}{_SUFFIX}"
    exported = _load(path)
    if exported is None:

        def flat(*leaves: Any) -> Any:
            return fn(*jax.tree.unflatten(treedef, leaves), **static)

        try:
            specs = [jax.ShapeDtypeStruct(t.shape, t.dtype, weak_type=t.weak_type) for t in types]
            exported = jax.export.export(jax.jit(flat))(*specs)
            _save(path, exported.serialize())
        except Exception as exc:  # noqa: BLE001 - any failure: the plain jitted call
            _log.debug("program %s not exported: %s", name, exc)
            return flat  # the plain jitted call
    # the function's own compiler options (jaxskel._runtime.compiler_options.jit), if any
    return jax.jit(exported.call, compiler_options=getattr(fn, "compiler_options", None) or None)


def _load(path: Path) -> Any:
    """The deserialized program at ``path``, or ``None`` (missing or unreadable: removed)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        exported = jax.export.deserialize(bytearray(data))
    except Exception as exc:  # noqa: BLE001 - a torn or foreign file: forget it
        _log.debug("saved program %s unreadable (%s); removed", path.name, exc)
        path.unlink(missing_ok=True)
        return None
    try:
        os.utime(path)  # last use, for pruning
    except OSError:
        pass
    return exported


def _save(path: Path, data: bytes | bytearray) -> None:
    """Write atomically (jaxskel's :func:`~jaxskel.io._atomic.atomic_output`: a hidden
    temporary ``.<name>.jaxskel-<pid>-<host>-<random>.tmp`` renamed into place), then prune the folder."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path, overwrite=True, suffix="") as tmp:
            tmp.write_bytes(data)
        _prune(path.parent)
    except (OSError, InputError) as exc:  # read-only or full disk: run on without saving
        _log.debug("program %s not saved: %s", path.name, exc)


def _prune(folder: Path) -> None:
    """Remove the least recently used programs beyond ``MAX_BYTES``."""
    entries = []
    for p in folder.glob(f"*{_SUFFIX}"):
        try:
            st = p.stat()
        except OSError:
            continue
        entries.append((st.st_mtime, st.st_size, p))
    for p in folder.glob(f".*{_SUFFIX}.*.tmp"):  # left by a process killed while writing
        try:
            if time.time() - p.stat().st_mtime > 3600:
                p.unlink()
        except OSError:
            pass
    total = sum(size for _, size, _ in entries)
    for _, size, p in sorted(entries):
        if total <= MAX_BYTES:
            break
        p.unlink(missing_ok=True)
        total -= size
