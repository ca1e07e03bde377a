"""What a format reader hands back, and the conventions every reader shares.

A reader (:mod:`jaxskel.io._c3d`, :mod:`jaxskel.io._trc`, :mod:`jaxskel.io._csv`,
:mod:`jaxskel.io._h5`) parses a file into a :class:`RawRecording`: positions in metres with
NaN for missing samples (:func:`zeros_to_nan`), labels as written, the units it found
(:func:`resolve_units`). :func:`jaxskel.load` then applies the conventions users rely on.
A writer takes any :class:`TrialLike` (a :class:`jaxskel.Trial`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .._errors import InputError
from ._bounds import describe_bytes, require_memory

__all__ = [
    "UNITS_REMEDY", "UNIT_SCALES", "UP_AXES", "RawRecording", "TrialLike", "Units", "cut_short", "median_extent", "parse_table",
    "read_text", "resolve_units", "unit_scale", "zeros_to_nan",
]

#: Copies of a text file's size that reading it holds at once: its bytes, its text,
#: its lines and their rows.
TEXT_COPIES = 4

#: The vertical axes a trial can have ("unknown": not determined).
UP_AXES = ("x", "y", "z", "-x", "-y", "-z", "unknown")

#: Length units -> metres per unit. Keys are lower case, without dots.
UNIT_SCALES = {
    "m": 1.0,
    "meter": 1.0,
    "meters": 1.0,
    "metre": 1.0,
    "metres": 1.0,
    "dm": 0.1,
    "cm": 0.01,
    "mm": 0.001,
    "millimeter": 0.001,
    "millimeters": 0.001,
    "in": 0.0254,
    "inch": 0.0254,
    "inches": 0.0254,
}


@dataclasses.dataclass(frozen=True)
class Units:
    """How raw values become metres: ``metres = raw * scale``."""

    scale: float
    name: str
    source: str  # "file", "argument" or "assumed"
    #: why an assumption was made (announced as a UnitsWarning by load), or None
    note: str | None = None


@dataclasses.dataclass(frozen=True)
class RawRecording:
    """What a format reader found, before the shared conventions are applied.

    ``positions`` are already in metres with NaN for missing samples;
    ``labels`` are as written in the file (prefixes included).
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    rate: float
    units: Units
    first_frame: int = 1
    #: point index -> why it is not a marker ("angles", "modeled_markers", ...)
    non_marker: Mapping[int, str] = dataclasses.field(default_factory=dict)
    #: points that are not positions at all (angles, forces, ...), always dropped
    non_position: frozenset[int] = frozenset()
    #: complete up axis written by jaxskel itself (authoritative) or None
    declared_up_axis: str | None = None
    #: axis letter ("x"/"y"/"z") stated by the file; its sign is not trusted
    stated_up_letter: str | None = None
    strip_prefixes: bool = True
    #: format-specific metadata entries
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    #: a saved trial's own source and metadata (HDF5), restored as they were
    source: str | None = None
    provenance: Mapping[str, Any] | None = None
    #: point index -> why the file has no sample of it, where the reader can tell
    #: (a text row that ends before its columns, :func:`cut_short`)
    empty_reasons: Mapping[int, str] = dataclasses.field(default_factory=dict)


class TrialLike(Protocol):
    """What a writer reads of a :class:`jaxskel.Trial`."""

    positions: np.ndarray
    mask: np.ndarray
    labels: tuple[str, ...]
    rate: float
    up_axis: str
    source: str | None
    metadata: Mapping[str, Any]
    n_frames: int
    n_markers: int


#: How to give a file's unit, said in every message that asks for it.
UNITS_REMEDY = "--units mm (or cm, m, ...) on the command line, or jaxskel.load(path, units='mm') in Python"


def unit_scale(units: str, file: Path, *, stated: bool = False) -> float:
    """Metres per ``units`` (case and dots ignored); InputError for unknown units.

    ``stated``: the unit is the file's own (else it was given, ``--units``/``units=``).
    """
    key = str(units).strip().lower().replace(".", "")
    if key not in UNIT_SCALES:
        known = ", ".join(sorted(UNIT_SCALES))
        if stated:
            raise InputError(
                f"{file} states the length unit {units!r}, which jaxskel does not know (it knows {known}); "
                f"give the unit of its values: {UNITS_REMEDY}"
            )
        raise InputError(f"unknown length unit {units!r} (--units / units=); expected one of {known}")
    return UNIT_SCALES[key]


def resolve_units(stated: str | None, override: str | None, raw: np.ndarray, file: Path) -> Units:
    """The length unit of raw values.

    ``override`` wins; else the stated unit; else (nothing stated) millimetres
    are assumed, unless the data are implausible as millimetres: when the
    median over frames of the markers' largest coordinate range is below 5
    units, the values must be metres (5 mm would be a marker set smaller than
    a coin). Either way the assumption is explained in ``note``, which
    :func:`load` emits as a :class:`~jaxskel.UnitsWarning`, with how to give
    the unit (:data:`UNITS_REMEDY`).
    """
    if override is not None:
        return Units(unit_scale(override, file), str(override).strip(), "argument")
    if stated is not None and stated.strip():
        return Units(unit_scale(stated, file, stated=True), stated.strip(), "file")
    extent = median_extent(raw)
    if extent is not None and extent < 5.0:
        name = "m"
        why = f"its markers span only {extent:.3g} units per frame, so they must be metres"
    else:
        name = "mm"
        why = "assuming millimetres, the usual unit of motion capture"
    note = f"{file} does not state its length unit; {why}. If that is wrong, give the unit: {UNITS_REMEDY}"
    return Units(UNIT_SCALES[name], name, "assumed", note)


def median_extent(raw: np.ndarray) -> float | None:
    """Median over frames of the largest per-axis range of the present markers."""
    present = ~np.isnan(raw).any(axis=-1) & ~(raw == 0).all(axis=-1)
    framed = present.sum(axis=1) >= 2
    if not framed.any():
        return None
    x, p = raw[framed], present[framed][..., None]
    hi = np.where(p, x, -np.inf).max(axis=1)
    lo = np.where(p, x, np.inf).min(axis=1)
    return float(np.median((hi - lo).max(axis=1)))


def cut_short(lengths: np.ndarray, offset: int, n_points: int) -> dict[int, str]:
    """Points of a text table whose X, Y, Z columns no row reaches: {index: reason}.

    ``lengths`` holds the cells of each row (:func:`parse_table`); point ``m`` takes
    columns ``offset + 3 m`` to ``offset + 3 m + 2``.
    """
    longest = int(lengths.max()) if lengths.size else 0
    return {
        m: "every data row ends before its columns"
        for m in range(n_points)
        if longest < offset + 3 * (m + 1)
    }


def zeros_to_nan(x: np.ndarray) -> np.ndarray:
    """Samples exactly at (0, 0, 0) become missing (NaN); returns a new array."""
    out = np.array(x, dtype=np.float64, copy=True)
    out[(out == 0).all(axis=-1)] = np.nan
    return out


def read_text(file: Path) -> str:
    """Text of a file (UTF-8, else Latin-1); InputError for binary data or too little memory."""
    size = file.stat().st_size
    require_memory(file, size * TEXT_COPIES, f"is {describe_bytes(size)} of text")
    data = file.read_bytes()
    if b"\x00" in data:
        raise InputError(f"cannot read {file}: it holds binary data, not text")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def parse_table(
    rows: Sequence[tuple[int, str]], width: int, file: Path, split: Callable[[int, str], Sequence[str]]
) -> tuple[np.ndarray, np.ndarray]:
    """Numbers of text rows, shape (rows, width), NaN for empty or absent cells; and the
    number of cells each row has (at most ``width``).

    ``rows`` holds (line number, text); ``split(line number, text)`` cuts a row into
    cells. Rows may be shorter than ``width`` (the missing cells are empty) or longer if
    the extra cells are empty (trailing separators); anything else, a cell that is not
    a number and an infinite value are InputErrors naming the line. The caller checks
    the table's size against the memory available first
    (:func:`jaxskel.io._bounds.require_memory`): rows are parsed one at a time into it.
    """
    table = np.full((len(rows), width), np.nan)
    lengths = np.zeros(len(rows), dtype=np.int64)
    nan = float("nan")
    for r, (line_no, line) in enumerate(rows):
        cells = split(line_no, line)
        n = len(cells)
        if n > width:
            if any(c.strip() for c in cells[width:]):
                raise InputError(f"{file}, line {line_no}: {n} values where at most {width} are expected")
            n = width
        try:
            table[r, :n] = [float(c) if c.strip() else nan for c in cells[:n]]
        except ValueError:
            for c, cell in enumerate(cells[:n]):
                try:
                    float(cell.strip() or "nan")
                except ValueError:
                    shown = f"{cell.strip()[:40]!r}{'...' if len(cell.strip()) > 40 else ''}"
                    raise InputError(f"{file}, line {line_no}, column {c + 1}: {shown} is not a number") from None
            raise
        lengths[r] = n
    if np.isinf(table).any():
        line_no = rows[int(np.argwhere(np.isinf(table))[0, 0])][0]
        raise InputError(
            f"{file}, line {line_no}: infinite value; write missing samples as empty cells"
        )
    return table, lengths
