"""float64 for jaxskel's JAX work, without changing JAX's settings for the process.

Joint costs are differences of squared distances at the 1e-6 m² level, which float32
loses, so jaxskel computes in float64. It never turns JAX's 64-bit mode on for the
whole process (``import jaxskel`` changes no JAX setting, and a float32 model next to
it stays float32). Instead every public function that runs JAX code is wrapped in
:func:`float64_scope`: JAX's 64-bit mode (:func:`jax.enable_x64`) is on for the length
of the call and the caller's mode is back on return.

What follows from JAX's mode being per thread and part of every trace:

* **Threads.** A new thread runs in the process's mode, not in its creator's. A
  function that jaxskel runs in a thread pool and that runs JAX code is wrapped too.
* **Under a transformation** (the caller's ``jit``, ``vmap``, ``grad``, ...) the
  scope is not entered, because a mode changed inside a trace mixes widths in one
  program. The caller's mode and the arguments' dtypes decide: in a float32 model the
  pure functions (:mod:`jaxskel.learn`, :func:`jaxskel.joints.solve_joints`,
  :func:`jaxskel.skeleton.ik_solve`, ...) compute in float32.
* **Explicit dtypes stay.** Inside the scope, arrays given as float32 compute in
  float32: the mode changes JAX's default dtypes and how numpy's float64 arrays are
  converted, not the dtype of a JAX array.
* **What leaves the scope.** Results (:class:`jaxskel.SkeletonResult`, ``Skeleton``,
  ``Motion``, ``Segmentation``, ``Topology``, ...) hold numpy arrays. The pure
  functions return JAX arrays of the dtype they computed in (float64 for numpy
  input); in a process whose 64-bit mode is off, the next JAX operation on such an
  array converts it to float32 (convert with ``numpy.asarray`` to keep float64).
* **One frame more.** The wrapper is a frame between the function and its caller: a
  warning the function aims at its caller counts it (``stacklevel=3``, not 2). Where
  warnings count many frames up through the function (:func:`jaxskel.fit_skeleton`),
  its body enters :func:`float64` in a ``with`` block instead, which adds no frame.
* **Private functions** that run JAX code expect to be called inside the scope (by the
  public functions that call them); a caller of its own (a test, a benchmark) enters it.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import jax

try:  # whether a JAX transformation is tracing the caller (private to jax, so guarded)
    from jax._src.core import trace_state_clean as _at_top_level
except ImportError:  # pragma: no cover - then arguments that are tracers tell
    _at_top_level = None

__all__ = ["float64", "float64_scope"]

_F = TypeVar("_F", bound=Callable[..., Any])


def _enable_x64() -> Any:
    """JAX's context manager that turns 64-bit mode on in this thread."""
    enable = getattr(jax, "enable_x64", None)
    if enable is None:  # pragma: no cover - jax before the public spelling
        from jax.experimental import enable_x64 as enable
    return enable(True)


def _tracing(args: tuple = (), kwargs: dict | None = None) -> bool:
    """Whether a JAX transformation is tracing the caller (or, on a jax that cannot say,
    whether an argument is a tracer)."""
    if _at_top_level is not None:
        return not _at_top_level()
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kwargs or {})))


@contextlib.contextmanager
def float64() -> Iterator[None]:
    """JAX's 64-bit mode on in this thread for the ``with`` block (as for a call of a
    :func:`float64_scope` function: left alone when already on or under a transformation)."""
    if jax.config.jax_enable_x64 or _tracing():
        yield
        return
    with _enable_x64():
        yield


def float64_scope(fn: _F) -> _F:
    """``fn`` with JAX's 64-bit mode on in the calling thread for the length of each call.

    The caller's mode is restored on return or on an exception. Nothing changes when the
    mode is already on, or when a JAX transformation traces the call (module docstring).
    """

    @functools.wraps(fn)
    def scoped(*args: Any, **kwargs: Any) -> Any:
        if jax.config.jax_enable_x64 or _tracing(args, kwargs):
            return fn(*args, **kwargs)
        with _enable_x64():
            return fn(*args, **kwargs)

    return scoped  # type: ignore[return-value]
