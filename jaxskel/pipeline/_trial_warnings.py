"""The warnings of a batch's trials, caught per trial and said again naming the trial.

:func:`jaxskel.fit_batch` works on several trials at once: threads prepare and finish
trials (:mod:`jaxskel.pipeline._local`) while the main thread solves a batch, and Dask
workers do the same in other processes (:mod:`jaxskel.pipeline._dask`). A warning
raised in such a thread says nothing of the trial it concerns, and the same warning
of a second trial is hidden by Python's once-per-code-location rule. So, while a
batch runs (:class:`TrialWarnings`):

* every warning shown in a thread that works for a trial (inside
  :meth:`TrialWarnings.trial`) goes into that trial's list instead of being shown,
  each ``(category, text)`` once; warnings of other threads are shown as before. The
  hook is :func:`warnings._showwarnmsg` (the warnings module's "replace if you like"
  hook, which :class:`warnings.catch_warnings` neither saves nor restores, so a
  ``catch_warnings`` in another thread cannot undo it);
* warnings no filter matches use the action ``"always"`` rather than Python's
  default (once per code location), so that each trial's warning reaches its list;
  the filters set (``ignore``, ``error``, also ``default`` or ``once``, which then
  count over the whole batch) still apply;
* a ``catch_warnings(record=True)`` of the thread that holds the device lock keeps
  what it records: :meth:`jaxskel.pipeline.StagePlan.grow_count` records the warnings
  of candidate fits and re-emits only the kept fit's, which are then caught;

:func:`emit` says a trial's warnings again, each as a warning of its category whose
text starts with ``[trial name]`` and which carries ``.trial`` and ``.text`` (the
command line prints ``jaxskel: warning (Category) [trial name]: text``).

Python before 3.14 keeps one warnings state per process, and a
``catch_warnings`` that ends in one thread while another thread's is open restores
a stale state; :meth:`TrialWarnings.heal` puts back the state the batch started
with, called while the device lock is held (no recording is open then).
"""

from __future__ import annotations

import contextlib
import importlib
import threading
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

__all__ = ["Caught", "TrialWarnings", "emit", "pack", "unpack"]

#: One warning of a trial: its category and text.
Caught = tuple[type[Warning], str]

_thread = threading.local()  # .sink: the list of the trial this thread works for
_install_lock = threading.Lock()
_installed: dict[str, Any] = {}  # while >= 1 batch runs: count, the hook replaced, the state to heal to


def _owns(lock: Any) -> bool:
    owned = getattr(lock, "_is_owned", None)
    return bool(owned()) if owned is not None else False


def _show(msg: warnings.WarningMessage) -> None:
    """The hook: a trial thread's warning into its trial's list, any other shown as before."""
    sink = getattr(_thread, "sink", None)
    state = _installed
    recording = warnings._showwarnmsg_impl is not state.get("impl")  # type: ignore[attr-defined]
    if sink is None or (recording and _owns(state.get("records_under"))):
        state["original"](msg)
        return
    caught = (msg.category, str(msg.message))
    if caught not in sink:
        sink.append(caught)


class TrialWarnings:
    """Catch the warnings of each trial of a batch while it runs (module docstring).

    ``tw = TrialWarnings(records_under=lock)``; ``with tw.installed():`` around the
    batch; ``with tw.trial(key):`` around a trial's work in any thread; ``tw.take(key)``
    returns and forgets what the trial raised.
    """

    def __init__(self, *, records_under: Any) -> None:
        self._records_under = records_under
        self._caught: dict[Any, list[Caught]] = {}
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        """While the block runs, the hook is in place (several batches in one process share it)."""
        with _install_lock:
            if not _installed:
                _installed.update(
                    count=0, original=warnings._showwarnmsg, impl=warnings._showwarnmsg_impl,  # type: ignore[attr-defined]
                    showwarning=warnings.showwarning, defaultaction=warnings.defaultaction,
                    records_under=self._records_under,
                )
                warnings._showwarnmsg = _show  # type: ignore[attr-defined]
                warnings.defaultaction = "always"
                warnings._filters_mutated()  # type: ignore[attr-defined]
            _installed["count"] += 1
        try:
            yield
        finally:
            with _install_lock:
                _installed["count"] -= 1
                if _installed["count"] == 0:
                    warnings._showwarnmsg = _installed["original"]  # type: ignore[attr-defined]
                    warnings.defaultaction = _installed["defaultaction"]
                    warnings._filters_mutated()  # type: ignore[attr-defined]
                    _installed.clear()

    @contextlib.contextmanager
    def trial(self, key: Any) -> Iterator[None]:
        """In this thread, until the block ends, warnings go to trial ``key``'s list."""
        with self._lock:
            sink = self._caught.setdefault(key, [])
        before = getattr(_thread, "sink", None)
        _thread.sink = sink
        try:
            yield
        finally:
            _thread.sink = before

    def take(self, key: Any) -> tuple[Caught, ...]:
        """The warnings trial ``key`` raised so far (forgotten here)."""
        with self._lock:
            return tuple(self._caught.pop(key, ()))

    def heal(self) -> None:
        """Put back the warnings state the batch started with where a ``catch_warnings``
        of another thread left a stale one (module docstring). Call it while holding
        the device lock: no recording is open then."""
        with _install_lock:
            if not _installed:
                return
            if warnings.showwarning is not _installed["showwarning"]:
                warnings.showwarning = _installed["showwarning"]
            if warnings._showwarnmsg_impl is not _installed["impl"]:  # type: ignore[attr-defined]
                warnings._showwarnmsg_impl = _installed["impl"]  # type: ignore[attr-defined]


def _tagged(category: type[Warning], text: str, trial: str) -> Warning:
    """A warning of ``category`` saying ``[trial] text`` that carries ``.trial`` and ``.text``."""
    try:
        warning = category(f"[{trial}] {text}")
    except Exception:  # noqa: BLE001 - a category whose constructor wants more
        warning = UserWarning(f"[{trial}] {text}")
    warning.trial = trial  # type: ignore[attr-defined]
    warning.text = text  # type: ignore[attr-defined]
    return warning


def emit(trial: str, caught: Sequence[Caught], stacklevel: int = 2) -> None:
    """Warn again each warning trial ``trial`` raised, naming it (module docstring)."""
    for category, text in caught:
        warnings.warn(_tagged(category, text, trial), stacklevel=stacklevel + 1)


def pack(caught: Sequence[Caught]) -> list[tuple[str, str]]:
    """Warnings as plain data for another process: ``("module:QualName", text)``."""
    return [(f"{c.__module__}:{c.__qualname__}", text) for c, text in caught]


def unpack(packed: Sequence[tuple[str, str]]) -> tuple[Caught, ...]:
    """:func:`pack`'s warnings back (``UserWarning`` for a category this process cannot import)."""
    out = []
    for name, text in packed:
        module, _, qualname = name.partition(":")
        try:
            category: Any = importlib.import_module(module)
            for part in qualname.split("."):
                category = getattr(category, part)
            if not (isinstance(category, type) and issubclass(category, Warning)):
                raise TypeError(name)
        except Exception:  # noqa: BLE001
            category = UserWarning
        out.append((category, text))
    return tuple(out)
