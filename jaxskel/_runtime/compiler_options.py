"""XLA compiler options of jaxskel's own programs, set per program (never through ``XLA_FLAGS``).

The SD06 programs (:mod:`jaxskel.sd06`) are compiled through :func:`jit`, which passes
:data:`OPTIONS` as ``jax.jit(..., compiler_options=...)``: they apply to that program
alone, and the host's other programs and global flags are left as they are. Other
backends ignore the CPU options. The fit's programs keep XLA's defaults: the options
did not measurably change their compile or run time.

* ``xla_cpu_experimental_ynn_fusion_type`` empty: XLA:CPU hands no elementwise
  fusions to YNNPACK, whose float64 (every jaxskel computation) fusions run several
  times slower than XLA's own loops;
* ``xla_cpu_use_fusion_emitters`` off: XLA:CPU emits its fusions with its older
  LLVM emitters, which compile the SD06 programs faster and run them as
  fast (measured: CHANGELOG; ``bench/sd06_speed.py``).

Called inside another jit (its arguments are tracers), a program is a plain nested
``jax.jit``: JAX accepts compiler options on the outermost jit only. A jaxlib that
does not know an option (older or newer releases) compiles without it: which options
are known is found out once, by compiling a one-element program per option at the
first call of a program built by :func:`jit` (not at import, which must not start a
backend).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

__all__ = ["compiler_options", "jit"]

#: The options jaxskel's programs are compiled with, where the running jaxlib knows them.
OPTIONS: dict[str, Any] = {"xla_cpu_experimental_ynn_fusion_type": "", "xla_cpu_use_fusion_emitters": False}


@functools.lru_cache(maxsize=1)
def compiler_options() -> dict[str, Any]:
    """The entries of :data:`OPTIONS` that this jaxlib accepts."""
    known = {}
    for name, value in OPTIONS.items():
        try:
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(np.zeros(1, np.float32)).compile()
        except Exception:  # noqa: BLE001 - "No such compile option": compile without it
            continue
        known[name] = value
    return known


class _Jitted:
    """``jax.jit(fn, compiler_options=compiler_options(), **kwargs)``, built at its first use."""

    def __init__(self, fn: Callable, kwargs: dict[str, Any]) -> None:
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._kwargs = kwargs
        self._jitted: Callable | None = None
        self._nested: Callable | None = None
        self._lock = threading.Lock()

    @property
    def jitted(self) -> Callable:
        """The ``jax.jit`` function (``lower``, ``trace``, ``eval_shape`` ... are forwarded to it)."""
        if self._jitted is None:
            with self._lock:
                if self._jitted is None:
                    self._jitted = jax.jit(self._fn, compiler_options=self.compiler_options or None, **self._kwargs)
        return self._jitted

    @property
    def compiler_options(self) -> dict[str, Any]:
        return compiler_options()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kwargs))):
            # Inside another jit (a caller's, or an export): JAX takes compiler options
            # from the outermost jit only and refuses them on a nested one.
            if self._nested is None:
                self._nested = jax.jit(self._fn, **self._kwargs)
            return self._nested(*args, **kwargs)
        return self.jitted(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.jitted, name)


def jit(fn: Callable | None = None, **kwargs: Any) -> Any:
    """``jax.jit`` with jaxskel's compiler options (module docstring).

    Usable as ``@jit`` or ``@jit(static_argnames=...)``."""
    if fn is None:
        return functools.partial(jit, **kwargs)
    return _Jitted(fn, kwargs)
