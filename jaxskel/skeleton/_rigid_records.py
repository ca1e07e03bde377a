"""The records of :func:`jaxskel.skeleton.fit_rigid`: its settings and its diagnostics.

:class:`RigidOptions` groups the solver settings of the rigid fit (validated once, on
construction, as the groups of :class:`jaxskel.FitOptions`); :class:`RigidDiagnostics`
is what the fit reports (``Skeleton.diagnostics``): a typed, documented, frozen record
that is also a read-only :class:`collections.abc.Mapping` of its entries, so that
``d["hinge_shift"]``, ``d.get(...)``, ``dict(d)`` and ``{**d, ...}`` read it as they
read the plain mapping a result file gives back.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from .._errors import InputError
from ._ik import DEFAULT_PRIOR_WEIGHT

__all__ = ["RigidDiagnostics", "RigidOptions"]

#: Weight of an input joint centre relative to a marker in the refinement (``fit_rigid``'s
#: default: the centres are trusted like a marker).
JOINT_WEIGHT = 1.0


def _real(value: object) -> bool:
    """A real number (Python or numpy), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _positive_number(value: object) -> bool:
    """A finite real number > 0 (not a bool). The type is checked first, so a string or
    ``None`` gets fit_rigid's own message rather than numpy's TypeError."""
    return _real(value) and bool(np.isfinite(value)) and value > 0


def _whole(value: object) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclasses.dataclass(frozen=True)
class RigidOptions:
    """The settings of :func:`jaxskel.skeleton.fit_rigid` (its keyword arguments of the same names).

    Attributes
    ----------
    refine
        Run the global refinement after Procrustes.
    max_steps
        Levenberg-Marquardt iterations per frame and sweep (a whole number >= 1).
    max_sweeps
        The refinement stops after this many sweeps (a whole number >= 1) ...
    xtol
        ... or when an offset update moves no offset by more than ``xtol`` metres (> 0)
        without raising the cost.
    max_frames
        At most this many frames, evenly spaced, are fitted (a whole number >= 1).
    prior_weight
        IK pose-prior weight, metres per radian (>= 0; :mod:`jaxskel.skeleton._ik`).
    nonrigid_factor
        Markers with residual RMS above this multiple of the median (and 1 mm above it)
        are reported as not rigidly attached (> 0).
    joint_weight
        ``w_J``: weight of an input joint centre relative to a marker (> 0).

    Raises :class:`jaxskel.InputError` on construction for a value outside these bounds.
    """

    refine: bool = True
    max_steps: int = 100
    max_sweeps: int = 200
    xtol: float = 1e-6
    max_frames: int = 1000
    prior_weight: float = DEFAULT_PRIOR_WEIGHT
    nonrigid_factor: float = 3.0
    joint_weight: float = JOINT_WEIGHT

    def __post_init__(self) -> None:
        if not _positive_number(self.joint_weight):
            raise InputError(f"joint_weight must be a positive number, got {self.joint_weight!r}")
        if not (_positive_number(self.xtol) and _whole(self.max_sweeps) and self.max_sweeps >= 1):
            raise InputError(
                f"xtol must be a positive length in metres and max_sweeps a whole number >= 1; got xtol={self.xtol!r}, "
                f"max_sweeps={self.max_sweeps!r}"
            )
        if not isinstance(self.refine, (bool, np.bool_)):
            raise InputError(f"refine must be True or False, got {self.refine!r}")
        for name in ("max_steps", "max_frames"):
            value = getattr(self, name)
            if not (_whole(value) and value >= 1):
                raise InputError(f"{name} must be a whole number >= 1, got {value!r}")
        if not _positive_number(self.nonrigid_factor):
            raise InputError(f"nonrigid_factor must be a positive number, got {self.nonrigid_factor!r}")
        if not (_positive_number(self.prior_weight) or (_real(self.prior_weight) and self.prior_weight == 0)):
            raise InputError(f"prior_weight must be a number >= 0 (metres per radian), got {self.prior_weight!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class RigidDiagnostics(Mapping[str, Any]):
    """What :func:`jaxskel.skeleton.fit_rigid` reports (``Skeleton.diagnostics``).

    A read-only mapping of its entries: the fields below by name, the two optional ones
    only when set, then ``extra`` (entries later stages add, e.g. the pipeline's
    ``"anchored"``). Equality is the mapping's (a plain dict of the same entries is equal).

    Attributes
    ----------
    sweeps
        Refinement sweeps run.
    result
        0 converged (or no refinement), 7 hit ``max_sweeps``.
    cost_history
        Per sweep, the mean weighted squared residual after its offset update (m^2).
    offset_steps
        Per sweep, the largest offset move of its update (m); the refinement stops below ``xtol``.
    residual_rms
        RMS marker residual over the fitting frames (m).
    frames_used, frames_rejected
        Fitting frames kept, and those left out as outliers (marker RMS above median + 5 MAD).
    rest_frame
        The frame (of the trial) whose posture is the rest pose.
    ik_steps_mean, ik_steps_max, ik_failures
        The last IK sweep's steps per kept frame, and its frames that hit ``max_steps``.
    procrustes_segments
        Segments posed by Procrustes.
    hinge_shift
        (J,) how far each joint was moved along its axis into its limb plane (m, signed
        along ``hinge_axis``; 0 for joints not moved).
    hinge_placement
        (J,) how each joint was placed: ``"limb plane"``, ``"between A and B"`` (two
        straddling landmarks or markers), ``""`` (not moved).
    hinge_axis
        (J, 3) each moved joint's axis in its parent frame (NaN for joints not moved).
    procrustes_rms
        (S,) per segment, the RMS scatter of its Procrustes points (m; NaN when none).
    attachment_weight, attachment_scatter
        (J,) the weight of a one-marker segment's joint in its host's Procrustes
        alignment (1 for the other joints) and its RMS scatter there (m; NaN for the others).
    hinges_unmoved
        Joints whose slide the refined poses rejected (turning about more than one axis):
        the fit was redone without moving them. ``None``: no such joint (not an entry).
    unplaced_markers
        Labels of markers left out because no frame shows them with the rest of their
        segment. ``None``: none (not an entry).
    extra
        Further entries, after the above.
    """

    sweeps: int
    result: int
    cost_history: list[float]
    offset_steps: list[float]
    residual_rms: float
    frames_used: int
    frames_rejected: int
    rest_frame: int
    ik_steps_mean: float
    ik_steps_max: int
    ik_failures: int
    procrustes_segments: list[int]
    hinge_shift: list[float]
    hinge_placement: list[str]
    hinge_axis: list[list[float]]
    procrustes_rms: list[float]
    attachment_weight: list[float]
    attachment_scatter: list[float]
    hinges_unmoved: list[int] | None = None
    unplaced_markers: tuple[str, ...] | None = None
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        clash = set(self.extra) & set(_ENTRIES + _OPTIONAL + ("extra",))
        if clash:
            raise InputError(f"extra diagnostics {sorted(clash)} clash with the rigid fit's own entries")
        object.__setattr__(self, "extra", types.MappingProxyType(dict(self.extra)))

    # ---- Mapping
    def _keys(self) -> tuple[str, ...]:
        optional = tuple(k for k in _OPTIONAL if getattr(self, k) is not None)
        return _ENTRIES + optional + tuple(self.extra)

    def __getitem__(self, key: str) -> Any:
        if key in _ENTRIES or (key in _OPTIONAL and getattr(self, key) is not None):
            return getattr(self, key)
        return self.extra[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def __contains__(self, key: object) -> bool:
        return key in self._keys()

    def __repr__(self) -> str:
        return f"RigidDiagnostics({dict(self)!r})"

    @classmethod
    def from_mapping(cls, entries: Mapping[str, Any]) -> RigidDiagnostics | None:
        """The record of ``entries`` (a plain mapping, e.g. read back from a result file), or
        ``None`` when they are not a rigid fit's: an entry missing, or in another order."""
        if isinstance(entries, cls):
            return entries
        if not all(k in entries for k in _ENTRIES):
            return None
        record = cls(
            **{k: entries[k] for k in _ENTRIES}, **{k: entries.get(k) for k in _OPTIONAL},
            extra={k: v for k, v in entries.items() if k not in _ENTRIES and k not in _OPTIONAL},
        )
        return record if list(record) == list(entries) else None


_FIELDS = tuple(f.name for f in dataclasses.fields(RigidDiagnostics))
_OPTIONAL = ("hinges_unmoved", "unplaced_markers")
_ENTRIES = tuple(k for k in _FIELDS if k not in _OPTIONAL + ("extra",))
