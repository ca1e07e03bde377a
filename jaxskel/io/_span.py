"""Whether a trial's positions are metres of a body, and what to do when they are not.

A human or a lab linkage spans centimetres to a few metres per frame. A fit checks the
median over frames of the markers' largest coordinate range (:func:`median_extent`,
the measure the readers use to guess a missing unit) against :data:`PLAUSIBLE_SPAN`.
Outside it the unit is almost surely wrong, and the remedy depends on where the
positions came from: a file whose unit was stated, assumed or given (``--units`` on
the command line, ``units=`` in :func:`jaxskel.load`), a saved HDF5 trial (always
metres as saved), or an array built in Python. :func:`units_problem` says which, and
names the unit that would make the recording a body where one does.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ._raw import UNIT_SCALES, median_extent

__all__ = ["PLAUSIBLE_SPAN", "units_problem"]

#: Median span per frame (metres) of a recording jaxskel fits: 2 cm to 40 m.
PLAUSIBLE_SPAN = (0.02, 40.0)

# The span of a body, for naming the likely unit (metres): a hand to a few people.
_BODY_SPAN = (0.1, 10.0)
# Units a file's values may be offered in.
_LIKELY_UNITS = ("mm", "cm", "m", "in")


def units_problem(trial: Any) -> str | None:
    """Why ``trial``'s positions are not metres of a body (its unit advice), or None.

    None also when no frame has two markers present (there is no span to judge).
    """
    extent = median_extent(np.asarray(trial.positions))
    low, high = PLAUSIBLE_SPAN
    if extent is None or low <= extent <= high:
        return None
    metadata = trial.metadata
    file = str(metadata.get("file", ""))
    name = trial.source or file or "the trial"
    head = (
        f"{name}: the markers span {_length(extent)} per frame, too {'large' if extent > high else 'small'} "
        f"for a body or a lab linkage ({_length(low)} to {_length(high)})"
    )
    read_as = str(metadata.get("original_units", "")).strip()
    key = read_as.lower().replace(".", "")
    if file and Path(file).suffix.lower() in (".h5", ".hdf5"):
        likely = _likely(extent, {"mm": 1e-3, "cm": 1e-2})
        fix = f"scale them (trial.replace(positions=trial.positions * {likely[1]:g}))" if likely else "convert them"
        return (
            f"{head}. An HDF5 trial holds the positions as they were saved, in metres; these were saved in "
            f"another unit: {fix} and save the trial again"
        )
    if file and key in UNIT_SCALES:
        raw_span = extent / UNIT_SCALES[key]
        how = {
            "file": f"as the file states {read_as}",
            "assumed": f"the file states no unit, and {read_as} was assumed",
            "argument": f"as given by --units {read_as} / units={read_as!r}",
        }.get(metadata.get("units_source"), f"as {read_as}")
        head = f"{head}: its values were read as {_unit_name(read_as)} ({how})"
        scales = {u: UNIT_SCALES[u] for u in _LIKELY_UNITS if UNIT_SCALES[u] != UNIT_SCALES[key]}
        likely = _likely(raw_span, scales)
        if likely is None:
            return f"{head}, and no length unit makes them a body (they span {raw_span:.3g} per frame): check the file"
        unit = likely[0]
        return (
            f"{head}, but they look like {_unit_name(unit)}. Give the unit: --units {unit} on the command line "
            f"(jaxskel fit, fit-batch, info), or jaxskel.load(path, units={unit!r}) in Python"
        )
    # Built in Python: positions must be metres.
    likely = _likely(extent, {"mm": 1e-3, "cm": 1e-2})
    if likely is None:
        return (
            f"{head}. Trial positions are metres: convert them; for a file, jaxskel.load(path, units=...) "
            "converts its unit"
        )
    unit, factor = likely
    return (
        f"{head}: they look like {_unit_name(unit)}. Trial positions are metres: multiply them by {factor:g} "
        f"(trial.replace(positions=trial.positions * {factor:g})); for a file, jaxskel.load(path, units={unit!r}) "
        "converts its unit"
    )


def _likely(span: float, scales: dict[str, float]) -> tuple[str, float] | None:
    """The unit (and its metres per unit) that makes ``span`` the span of a body, or None."""
    low, high = _BODY_SPAN
    fits = [(abs(math.log(span * s)), u, s) for u, s in scales.items() if low <= span * s <= high]
    return min(fits)[1:] if fits else None


def _unit_name(unit: str) -> str:
    key = unit.strip().lower().replace(".", "")
    return {"mm": "millimetres", "cm": "centimetres", "dm": "decimetres", "m": "metres", "in": "inches"}.get(key, unit)


def _length(metres: float) -> str:
    if metres >= 1:
        return f"{metres:.3g} m"
    if metres >= 0.01:
        return f"{metres * 100:.3g} cm"
    return f"{metres * 1000:.3g} mm"
