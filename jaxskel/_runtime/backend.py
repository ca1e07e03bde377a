"""Which backend a computation runs on."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax

__all__ = ["uses_cpu"]


def uses_cpu(devices: Sequence[Any] | None) -> bool:
    """Whether any of ``devices`` (``None``: the default device) is a CPU."""
    return any((d or jax.devices()[0]).platform == "cpu" for d in (devices or [None]))
