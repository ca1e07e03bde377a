"""Which backend a computation runs on, and moving host arrays onto it.

:func:`to_device` is how host-side orchestration hands numpy arrays to compiled stages:
``jnp.asarray`` of a numpy array compiles a small conversion program for every new shape
and dtype (JAX 0.10: ``jit(stage)``, ``jit(convert_element_type)``), which a new process
pays in compilation or cache lookups; :func:`jax.device_put` of an array already in the
wanted dtype compiles nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

__all__ = ["to_device", "uses_cpu"]


def uses_cpu(devices: Sequence[Any] | None) -> bool:
    """Whether any of ``devices`` (``None``: the default device) is a CPU."""
    return any((d or jax.devices()[0]).platform == "cpu" for d in (devices or [None]))


def to_device(value: Any, dtype: Any = None) -> jax.Array:
    """``value`` (array-like) as a JAX array on the default device, in ``dtype`` (default:
    its own), converted on the host: what ``jnp.asarray(value, dtype)`` gives (a Python
    number without ``dtype`` weakly typed), without compiling a conversion program. Under
    JAX's default 32-bit mode a 64-bit dtype becomes its 32-bit counterpart, as
    ``jnp.asarray`` makes it."""
    if isinstance(value, jax.Array) and (dtype is None or value.dtype == np.dtype(dtype)):
        return value
    if dtype is None and type(value) in (int, float, complex):
        return jax.device_put(value)  # weakly typed, as jnp.asarray makes a Python number
    host = np.asarray(value, dtype=dtype)
    if not jax.config.jax_enable_x64 and host.dtype.itemsize == 8 and host.dtype.kind in "fiuc":
        host = host.astype({"f": np.float32, "i": np.int32, "u": np.uint32, "c": np.complex64}[host.dtype.kind])
    return jax.device_put(host)
