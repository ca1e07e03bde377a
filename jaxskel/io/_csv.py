"""Cortex / MAC3D marker CSV exports (Motion Analysis).

Layout (comma separated)::

    Frame number,3812          <- key,value header lines (any number)
    First frame,1
    Point frequency,200
    Analog frequency,200
                               <- blank line
    Time,RAsis,,,LAsis,,,...   <- one name per marker, every third column
    s,mm,mm,mm,mm,mm,mm,...    <- units
    ,X,Y,Z,X,Y,Z,...           <- axes
    0,38.2141,999.424,...      <- time, then X, Y, Z per marker

Empty cells are missing coordinates. The frame rate is ``Point frequency``
(or, without it, the spacing of the time column); ``Frame number`` is the
frame count and a file with fewer rows is rejected as truncated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._errors import InputError
from ._bounds import LOAD_COPIES, check_labels, require_memory
from ._raw import RawRecording, cut_short, parse_table, read_text, resolve_units, zeros_to_nan

__all__ = ["read_csv"]

_FORMAT_HINT = (
    "expected a Cortex/MAC3D export: 'key,value' header lines, a blank line, "
    "then a name row starting with 'Time', a units row, an axis row and data rows"
)


def read_csv(file: Path, *, units: str | None = None) -> RawRecording:
    """Parse a Cortex/MAC3D marker CSV (see the module docstring); positions in metres."""
    text = read_text(file)
    lines = text.splitlines()
    blank = next((i for i, line in enumerate(lines) if not line.strip(" ,\t")), None)
    if blank is None or len(lines) < blank + 4:
        raise InputError(f"cannot read {file}: {_FORMAT_HINT}")
    header = {}
    for line in lines[:blank]:
        key, _, value = line.partition(",")
        header[key.strip().lower()] = value.strip().strip(",").strip()

    name_cells = [c.strip() for c in lines[blank + 1].split(",")]
    if not name_cells or name_cells[0].lower() != "time":
        raise InputError(f"cannot read {file}: line {blank + 2} is not a name row; {_FORMAT_HINT}")
    names = [c for c in name_cells[1:] if c]
    check_labels(names, file)
    n_markers = len(names)
    if n_markers == 0:
        raise InputError(f"cannot read {file}: the name row lists no markers")
    misplaced = [
        name
        for k, name in enumerate(names)
        if len(name_cells) <= 1 + 3 * k or name_cells[1 + 3 * k] != name
    ]
    if misplaced:
        raise InputError(
            f"cannot read {file}: marker names must be every third column after 'Time'; "
            f"{misplaced[0]!r} is not"
        )
    width = 1 + 3 * n_markers
    unit_cells = [c.strip() for c in lines[blank + 2].split(",")][1:width]
    stated_units = {c for c in unit_cells if c}
    if len(stated_units) > 1:
        raise InputError(
            f"{file}: markers are in different units {sorted(stated_units)}; convert them to one"
        )
    axis_cells = [c.strip().upper() for c in lines[blank + 3].split(",")][1:width]
    if axis_cells and set(axis_cells) - {"X", "Y", "Z", ""}:
        raise InputError(
            f"cannot read {file}: line {blank + 4} is not an X,Y,Z axis row; {_FORMAT_HINT}"
        )

    rows = [(k + blank + 5, line) for k, line in enumerate(lines[blank + 4 :]) if line.strip(" ,\t")]
    n_frames_header = _int(header.get("frame number"))
    if n_frames_header is not None and len(rows) < n_frames_header:
        raise InputError(
            f"cannot read {file}: the file is truncated: 'Frame number' says {n_frames_header} "
            f"frames but there are {len(rows)} data rows"
        )
    if rows and not text.endswith(("\n", "\r")) and len(rows[-1][1].split(",")) < width:
        raise InputError(f"cannot read {file}: the file is truncated: the last row is cut off")
    if not rows:
        raise InputError(f"{file} contains no frames")
    require_memory(file, len(rows) * width * 8 * LOAD_COPIES, f"holds {len(rows)} frames x {n_markers} markers")
    table, lengths = parse_table(rows, width, file, lambda _, line: line.split(","))

    rate = _float(header.get("point frequency"))
    if rate is None:
        steps = np.diff(table[:, 0])
        steps = steps[np.isfinite(steps)]
        rate = 1.0 / float(np.median(steps)) if steps.size and np.median(steps) > 0 else None
    if rate is None or not np.isfinite(rate) or rate <= 0:
        raise InputError(f"{file}: no valid 'Point frequency' and no usable time column")

    raw = table[:, 1:].reshape(len(rows), n_markers, 3)
    stated = next(iter(stated_units)) if stated_units else None
    length_unit = resolve_units(stated, units, raw, file)
    first = _int(header.get("first frame"))
    return RawRecording(
        positions=zeros_to_nan(raw) * length_unit.scale,
        labels=tuple(names),
        rate=rate,
        units=length_unit,
        first_frame=1 if first is None else first,
        extra={"analog_rate": _float(header.get("analog frequency")), "short_rows": int((lengths < width).sum())},
        empty_reasons=cut_short(lengths, 1, n_markers),
    )


def _float(value: str | None) -> float | None:
    try:
        return float(value) if value else None
    except ValueError:
        return None


def _int(value: str | None) -> int | None:
    number = _float(value)
    return int(number) if number is not None and np.isfinite(number) else None
