"""The named body in a result file: ``/anatomy``, written and read back.

Layout (docs/result-format.md):

* ``segment_part`` (S,) str: each segment's part from :data:`jaxskel.anatomy.PARTS`, ``""``
  where the part is not identified (every entry for a body that is not human);
* ``segment_confidence`` (S,) float in [0, 1];
* ``notes`` (n,) str: what decided the naming;
* attributes ``humanoid`` (bool), ``up`` and ``front`` (3,): the body's superior and
  anterior directions in the recording's frame.

A file without ``/anatomy`` (a fit with ``anatomy=False``, or written before jaxskel named
bodies) reads as ``None``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..anatomy import Anatomy
from ..io import put

__all__ = ["load_anatomy", "read_anatomy", "write_anatomy"]


def write_anatomy(group: h5py.Group, anatomy: Anatomy) -> None:
    """Fill ``group`` (``/anatomy``) with ``anatomy`` (module docstring)."""
    put(group, "segment_part", np.asarray(list(anatomy.parts), dtype=str))
    put(group, "segment_confidence", np.asarray(anatomy.confidence, float))
    put(group, "notes", np.asarray(list(anatomy.notes), dtype=str))
    group.attrs["humanoid"] = bool(anatomy.humanoid)
    group.attrs["up"] = np.asarray(anatomy.up, float)
    group.attrs["front"] = np.asarray(anatomy.front, float)


def _text(values: Any) -> tuple[str, ...]:
    return tuple(v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel().tolist())


def read_anatomy(f: h5py.File) -> Anatomy | None:
    """The :class:`Anatomy` of an open result file, ``None`` where it has no ``/anatomy``."""
    if "anatomy" not in f:
        return None
    g = f["anatomy"]
    return Anatomy(
        parts=_text(g["segment_part"][()]), confidence=np.asarray(g["segment_confidence"][()], float),
        humanoid=bool(g.attrs["humanoid"]), up=np.asarray(g.attrs["up"], float),
        front=np.asarray(g.attrs["front"], float), notes=_text(g["notes"][()]) if "notes" in g else (),
    )


def load_anatomy(path: str | os.PathLike[str]) -> Anatomy | None:
    """:func:`read_anatomy` of the result file at ``path`` (a fit's or a tracked trial's)."""
    from ._format import open_result

    with open_result(Path(path)) as f:
        return read_anatomy(f)
