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

``/angles`` (a human body with a motion): the anatomical joint angles
(:func:`jaxskel.anatomy.joint_angles`, its default options):

* ``values`` (F, C) float, radians, positive in the named direction;
* ``names`` (C,) str (``knee_l_flexion``) and ``joints`` (C,) str (``knee_l``);
* ``lateral_joints``, ``lateral`` (J,) str: how each joint's flexion axis was set
  (``functional``, ``body``, or ``given``: a tracked take measured in its calibration's frames);
* ``frames`` (S, 3, 3) float: each segment's anatomical frame in its own frame (NaN where unused);
* attributes ``units`` (``"rad"``), ``convention`` and ``rate`` (Hz, NaN if unknown).

A file without ``/angles`` reads as ``None`` (:func:`read_angles`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..anatomy import Anatomy, JointAngles, joint_angles
from ..io import put

__all__ = ["angles_or_none", "load_anatomy", "load_angles", "read_anatomy", "read_angles", "write_anatomy", "write_angles"]

#: What ``/angles@convention`` says.
CONVENTION = "Grood-Suntay joint coordinate system (intrinsic Z-X-Y), ISB axes and clinical signs"


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


def angles_or_none(skeleton: Any, motion: Any, anatomy: Anatomy | None,
                   frames: np.ndarray | None = None) -> JointAngles | None:
    """The joint angles a result file holds: :func:`jaxskel.anatomy.joint_angles` with its
    defaults (in ``frames`` where given) where there is a motion and a human anatomy that
    names a joint, else ``None``."""
    if skeleton is None or motion is None or anatomy is None or not anatomy.humanoid:
        return None
    if not any(anatomy.joint_names(skeleton.edges, [""] * len(skeleton.edges))):
        return None
    return joint_angles(skeleton, motion, anatomy, frames=frames)


def write_angles(group: h5py.Group, angles: JointAngles) -> None:
    """Fill ``group`` (``/angles``) with ``angles`` (module docstring)."""
    put(group, "values", np.asarray(angles.values, float))
    put(group, "names", np.asarray(list(angles.names), dtype=str))
    put(group, "joints", np.asarray(list(angles.joints), dtype=str))
    put(group, "lateral_joints", np.asarray(list(angles.lateral), dtype=str))
    put(group, "lateral", np.asarray(list(angles.lateral.values()), dtype=str))
    if angles.frames is not None:
        put(group, "frames", np.asarray(angles.frames, float))
    group.attrs["units"] = "rad"
    group.attrs["convention"] = CONVENTION
    group.attrs["rate"] = float(angles.rate) if angles.rate else float("nan")


def read_angles(f: h5py.File) -> JointAngles | None:
    """The :class:`JointAngles` of an open result file, ``None`` where it has no ``/angles``."""
    if "angles" not in f:
        return None
    g = f["angles"]
    rate = float(g.attrs["rate"])
    return JointAngles(
        names=_text(g["names"][()]), joints=_text(g["joints"][()]), values=np.asarray(g["values"][()], float),
        rate=rate if np.isfinite(rate) else None,
        lateral=dict(zip(_text(g["lateral_joints"][()]), _text(g["lateral"][()]), strict=True)),
        frames=np.asarray(g["frames"][()], float) if "frames" in g else None,
    )


def load_angles(path: str | os.PathLike[str]) -> JointAngles | None:
    """:func:`read_angles` of the result file at ``path`` (a fit's or a tracked trial's)."""
    from ._format import open_result

    with open_result(Path(path)) as f:
        return read_angles(f)
