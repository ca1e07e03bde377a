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

Reading ahead. A new process still reads each program's compiled code from the
persistent cache on its first call (XLA:CPU deserialising and linking it: 0.2-0.4 s for a
solver). Each process lists the programs it used, in the order of their first call, in
``<directory>/recently-used.json``; :func:`read_ahead` (started by
:func:`~jaxskel._runtime.compile_cache.enable_compile_cache`, which the ``jaxskel``
command's fitting subcommands call first thing) reads that list's programs in a background thread while
the process imports its modules and prepares the recording, and :func:`call` takes each
one from there (waiting for it if it is being read). A listed program that this process
does not call costs the background thread its reading, never a result.

With no directory set (the default, and every library call outside the command line)
:func:`call` is ``fn(*args, **static)``. The exported program is not differentiable
(serialized without VJP), so tracers bypass it too. Any failure to export, read or
deserialize a program falls back to the plain call; the directory is pruned, oldest
used first, beyond ``MAX_BYTES``.
"""

from __future__ import annotations

import atexit
import functools
import hashlib
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable

import jax

from .._errors import InputError
from ..io import atomic_output

__all__ = ["call", "current_directory", "read_ahead", "set_directory"]

#: Bound of the saved programs (bytes; a fit's programs take a small fraction of it, see
#: docs/bench/evidence_from_docstrings.md).
MAX_BYTES = 256 * 2**20
_SUFFIX = ".jaxexport"

#: The list of the programs the last process used (read_ahead), and its length bound.
_RECENT = "recently-used.json"
MAX_READ_AHEAD = 32

_log = logging.getLogger(__name__)
_lock = threading.Lock()
#: The folder of the saved programs, and the one this process has read ahead from.
_state: dict[str, Any] = {"directory": None, "read_ahead": None}
#: In-process programs by (function, static arguments, treedef, leaf types).
_programs: dict[tuple, Callable] = {}
#: This process's programs in the order of their first call: file name -> (x64, compiler options).
_used: dict[str, tuple[bool, dict | None]] = {}
#: Programs listed for reading ahead, by file name, not yet taken by a call.
_ahead: dict[str, _Ahead] = {}


def set_directory(path: str | os.PathLike | None) -> None:
    """Save and load programs under ``path`` (``None``: plain jitted calls; also where
    jax has no :func:`jax.export` or ``flatbuffers``, which serializes its programs, is
    missing)."""
    if path is not None and not _supported():
        path = None
    with _lock:
        _state["directory"] = None if path is None else Path(path)
        _state["read_ahead"] = None
        _programs.clear()
        _used.clear()
        _ahead.clear()  # a reader still running skips what is no longer listed


def current_directory() -> Path | None:
    """Where programs are saved and loaded (``None``: plain jitted calls)."""
    return _state["directory"]


class _Ahead:
    """One program listed for reading ahead: read by the background thread unless a call
    takes it first (``taken``); ``done`` is set once it is read (``compiled``: the
    compiled program, or ``None`` where reading it failed)."""

    __slots__ = ("compiled", "done", "name", "options", "started", "taken", "x64")

    def __init__(self, name: str, x64: bool, options: dict | None) -> None:
        self.name, self.x64, self.options = name, x64, options
        self.started = self.taken = False
        self.done = threading.Event()
        self.compiled: Any = None


def read_ahead() -> threading.Thread | None:
    """Start reading, in a background thread, the programs the last process listed
    (module docstring); ``None`` where no directory is set, nothing is listed, or this
    process already read ahead from this directory.

    The thread is a daemon, stopped after its current program when the process exits.
    """
    folder = _state["directory"]
    if folder is None or _state["read_ahead"] == folder:
        return None
    _state["read_ahead"] = folder
    try:
        listed = json.loads((folder / _RECENT).read_text())
        entries = [_Ahead(str(e["file"]), bool(e["x64"]), e.get("options")) for e in listed[:MAX_READ_AHEAD]]
    except (OSError, ValueError, TypeError, KeyError) as exc:  # none yet, or unreadable: nothing to read
        _log.debug("no programs to read ahead: %s", exc)
        return None
    entries = [e for e in entries if (folder / e.name).is_file() and "/" not in e.name]
    if not entries:
        return None
    with _lock:
        _ahead.update((e.name, e) for e in entries)
    stop = threading.Event()
    thread = threading.Thread(target=_read_listed, args=(folder, entries, stop), name="jaxskel-read-ahead",
                              daemon=True)
    atexit.register(_stop_reading, thread, stop)
    thread.start()
    return thread


def _stop_reading(thread: threading.Thread, stop: threading.Event) -> None:
    stop.set()
    thread.join(timeout=30.0)


def _read_listed(folder: Path, entries: list[_Ahead], stop: threading.Event) -> None:
    """The background thread of :func:`read_ahead`: each listed program, compiled from the
    persistent cache (``entry.compiled``, a :class:`jax.stages.Compiled`), unless a call
    took it first or ``stop`` is set."""
    for entry in entries:
        with _lock:
            skip = entry.taken or _ahead.get(entry.name) is not entry or stop.is_set()
            entry.started = not skip
        if skip:
            entry.done.set()
            continue
        try:
            exported = _load(folder / entry.name)
            if exported is not None:
                with jax.enable_x64(entry.x64):
                    jitted = jax.jit(exported.call, compiler_options=entry.options or None)
                    entry.compiled = jitted.lower(*exported.in_avals).compile()
        except Exception as exc:  # noqa: BLE001 - the call then loads it itself (compiled stays None)
            _log.debug("program %s not read ahead: %s", entry.name, exc)
        finally:
            entry.done.set()


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
    options = getattr(fn, "compiler_options", None) or None
    _note_use(folder, path.name, options)
    ahead = _ahead.pop(path.name, None)  # the caller holds _lock
    if ahead is not None:
        ahead.taken = True
        if ahead.started:
            ahead.done.wait()
            if ahead.compiled is not None:  # compiled for exactly these argument types (the memo's key)
                return ahead.compiled
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
    return jax.jit(exported.call, compiler_options=options)


def _note_use(folder: Path, name: str, options: dict | None) -> None:
    """Add a program to this process's list (the caller holds ``_lock``) and write the
    list for the next process's :func:`read_ahead`.

    Written to a temporary sibling and renamed into place, without ``fsync``: the list is
    a hint, read once by the next process, which ignores a list it cannot parse (a
    crash may leave one stale or empty), and a fit writes it about a dozen times.
    """
    if name in _used:
        return
    _used[name] = (bool(jax.config.jax_enable_x64), options)
    listed = [{"file": n, "x64": x64, "options": o} for n, (x64, o) in _used.items()][:MAX_READ_AHEAD]
    tmp = folder / f".{_RECENT}.{os.getpid()}.tmp"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(listed))
        os.replace(tmp, folder / _RECENT)
    except (OSError, TypeError, ValueError) as exc:  # read-only folder, options not JSON: no list
        _log.debug("list of used programs not written: %s", exc)
        tmp.unlink(missing_ok=True)


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
    # left by a process killed while writing
    for p in [*folder.glob(f".*{_SUFFIX}.*.tmp"), *folder.glob(f".{_RECENT}.*.tmp")]:
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
