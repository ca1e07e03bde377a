"""How many trials a batch may solve together: their estimated memory against a budget.

:func:`jaxskel.fit_batch` solves the joint stages of up to ``batch_size`` prepared trials
in shared programs, and each trial's arrays stay alive until its rigid fit and IK are
done. What a fit holds at its peak grows with its frames and markers: the tree joints'
pooled per-frame arrays (joints x frames x markers of the pair, with their solver's
workspace), the IK's, the trial itself. :func:`fit_bytes` estimates it as
:data:`FIT_COPIES` times the trial's positions array (``frames x markers x 3`` float64),
the ratio measured on the 600 s full body of ``docs/bench/pipeline_600s.md`` (a warm
``fit_skeleton`` adds 1,046 MB to the process for 78 MB of positions: 13.4).

A batch closes early when the next prepared trial would take the estimate of the batch,
and of the trials of earlier batches still being finished (rigid fit, IK, writing), past
the budget (:func:`memory_budget`: by default half the memory the process can still
allocate when the batch starts, :func:`jaxskel.io.available_memory`); a trial whose own
estimate exceeds the budget is solved alone. So a batch of long recordings is split
into groups that fit, and results do not depend on the grouping (each trial's fit is
the same alone or batched).
"""

from __future__ import annotations

import math
from typing import Any

from .._errors import InputError
from ..io import available_memory

__all__ = ["FIT_COPIES", "fit_bytes", "memory_budget", "parse_memory"]

#: Peak bytes of a fit per byte of its trial's positions (module docstring).
FIT_COPIES = 14

_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "m": 2**20, "mb": 2**20, "g": 2**30, "gb": 2**30,
          "t": 2**40, "tb": 2**40}


def fit_bytes(n_frames: int, n_markers: int) -> int:
    """Estimated peak bytes of fitting a trial of ``n_frames`` x ``n_markers`` (module docstring)."""
    return int(FIT_COPIES * 24 * max(int(n_frames), 0) * max(int(n_markers), 0))


def parse_memory(value: Any) -> int | str | None:
    """A memory setting as given (``"auto"``, ``None``/``"none"``, bytes, or text such as
    ``"6GB"``, ``"512M"``), checked: ``"auto"``, ``None`` or a positive number of bytes.
    Raises :class:`InputError` naming the value and what is allowed."""
    if value is None or value == "auto":
        return value
    if isinstance(value, str):
        text = value.strip().lower().replace(" ", "")
        if text in ("none", "unbounded"):
            return None
        if text == "auto":
            return "auto"
        number = text.rstrip("kmgtb")
        unit = text[len(number):]
        try:
            amount = float(number)
        except ValueError:
            amount = math.nan
        if unit not in _UNITS or not math.isfinite(amount) or amount <= 0:
            raise InputError(
                f"memory={value!r} is not a size: give 'auto', 'none', or a positive size such as 6GB, 512MB or "
                "1.5G (powers of 1024)"
            )
        return int(amount * _UNITS[unit])
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise InputError(f"memory={value!r} must be 'auto', None or a positive number of bytes")
    return int(value)


def memory_budget(memory: int | str | None) -> int | None:
    """Bytes the trials solved together may take (``None``: no bound). ``"auto"``: half of
    what the process can still allocate now (no bound where that cannot be told)."""
    memory = parse_memory(memory)
    if memory == "auto":
        free = available_memory()
        return None if free is None else max(free // 2, 1)
    return memory

