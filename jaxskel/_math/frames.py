"""Cutting the frames of a per-frame result (host side)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["cut_frames"]


def cut_frames(obj: Any, n_frames: int, keep: slice, **changes: Any) -> Any:
    """A copy of the dataclass ``obj`` with every numpy array whose leading axis is its
    ``n_frames`` frames cut to ``keep``, and the fields in ``changes`` replaced (those are
    not cut). Other fields (scalars, per-marker or per-segment arrays) are kept."""
    out = dict(changes)
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if field.name not in out and isinstance(value, np.ndarray) and value.ndim and value.shape[0] == n_frames:
            out[field.name] = value[keep]
    return dataclasses.replace(obj, **out)
