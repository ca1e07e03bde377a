"""OpenSim TRC marker files (tab separated text).

Layout::

    PathFileType  4  (X/Y/Z)  <file name>
  DataRate CameraRate NumFrames NumMarkers Units OrigDataRate OrigDataStartFrame OrigNumFrames
    <values of the line above>
    Frame#  Time  <marker 1>  ""  ""  <marker 2>  ""  "" ...
    ""  ""  X1  Y1  Z1  X2  Y2  Z2 ...
    (optional blank line)
    <frame>  <time>  x  y  z  x  y  z ...

An empty cell is a missing coordinate. Readers are tolerant of trailing tabs,
of tab-separated rows that end early (the remaining markers are missing in that
frame: a gap, ``metadata["short_rows"]`` counts such rows) and of markers that are
never seen (kept as all-NaN; :func:`jaxskel.load` lists them in
``metadata["empty_labels"]`` with the reason). A row separated by spaces must hold
every value: there a missing value cannot be told from a shifted one, so a short
one is rejected. A file with fewer data rows than ``NumFrames``, or whose last row
is cut off, is truncated and rejected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._errors import InputError
from ._atomic import atomic_output
from ._bounds import LOAD_COPIES, check_labels, require_memory
from ._raw import RawRecording, TrialLike, cut_short, parse_table, read_text, resolve_units, zeros_to_nan

__all__ = ["read_trc", "write_trc"]

_HEADER_KEYS = (
    "DataRate",
    "CameraRate",
    "NumFrames",
    "NumMarkers",
    "Units",
    "OrigDataRate",
    "OrigDataStartFrame",
    "OrigNumFrames",
)


def read_trc(file: Path, *, units: str | None = None) -> RawRecording:
    """Parse a TRC file (see the module docstring); positions in metres."""
    text = read_text(file)
    lines = text.splitlines()
    if not lines or not lines[0].startswith("PathFileType"):
        raise InputError(
            f"cannot read {file}: not a TRC file (the first line should start with 'PathFileType')"
        )
    if len(lines) < 5:
        raise InputError(
            f"cannot read {file}: the TRC header is incomplete ({len(lines)} lines; "
            "the file is truncated)"
        )
    header = _header(lines[1], lines[2], file)
    n_markers = _header_int(header, "NumMarkers", file)
    n_frames_header = _header_int(header, "NumFrames", file)
    rate = _header_float(header, "DataRate", file)
    if not np.isfinite(rate) or rate <= 0:
        raise InputError(f"{file}: invalid DataRate {header['DataRate']!r}")

    names = [cell.strip() for cell in _split(lines[3])[2:] if cell.strip()]
    check_labels(names, file)
    if len(names) != n_markers:
        raise InputError(
            f"{file}: the header says NumMarkers={n_markers} but the name row lists "
            f"{len(names)} markers; fix the header or the name row"
        )
    width = 2 + 3 * n_markers
    rows = [(k + 6, line) for k, line in enumerate(lines[5:]) if line.strip()]
    if len(rows) < n_frames_header:
        raise InputError(
            f"cannot read {file}: the file is truncated: the header says NumFrames="
            f"{n_frames_header} but there are {len(rows)} data rows"
        )
    if rows and not text.endswith(("\n", "\r")) and len(_split(rows[-1][1])) < width:
        raise InputError(
            f"cannot read {file}: the file is truncated: the last row (line {rows[-1][0]}) "
            "is cut off"
        )
    require_memory(file, len(rows) * width * 8 * LOAD_COPIES, f"holds {len(rows)} frames x {n_markers} markers")

    def cells(line_no: int, line: str) -> list[str]:
        if "\t" in line:
            return line.split("\t")
        values = line.split()
        if len(values) < width:
            raise InputError(
                f"{file}, line {line_no}: {len(values)} values where {width} are expected (frame, time and "
                f"X, Y, Z of {n_markers} markers); in a row separated by spaces a missing value cannot be told "
                "from a shifted one: write missing values as empty tab-separated cells or as NaN"
            )
        return values

    table, lengths = parse_table(rows, width, file, cells)
    raw = table[:, 2:].reshape(len(rows), n_markers, 3)
    length_unit = resolve_units(header.get("Units"), units, raw, file)
    first_frame = header.get("OrigDataStartFrame", "")
    try:
        first = int(float(first_frame)) if first_frame else int(table[0, 0]) if rows else 1
    except (ValueError, OverflowError):  # not a number, NaN or infinite
        first = 1
    extra = {
        "camera_rate": _optional_float(header.get("CameraRate")),
        "orig_data_rate": _optional_float(header.get("OrigDataRate")),
        "num_frames_header": n_frames_header,
        "short_rows": int((lengths < width).sum()),
    }
    return RawRecording(
        positions=zeros_to_nan(raw) * length_unit.scale,
        labels=tuple(names),
        rate=rate,
        units=length_unit,
        first_frame=first,
        extra=extra,
        empty_reasons=cut_short(lengths, 2, n_markers),
    )


def write_trc(trial: TrialLike, file: Path, *, overwrite: bool = False) -> None:
    """Write ``trial`` as a TRC in millimetres (6 decimals); missing samples are empty cells."""
    for lab in trial.labels:
        if any(ch in lab for ch in "\t\r\n"):
            raise InputError(f"cannot write {file}: label {lab!r} contains a tab or line break")
    n_frames, n_markers = trial.n_frames, trial.n_markers
    first = int(trial.metadata.get("first_frame", 1))
    rate = f"{trial.rate:.12g}"
    # A trial read from a TRC remembers its camera and original rates.
    camera_rate = f"{trial.metadata.get('camera_rate') or trial.rate:.12g}"
    orig_rate = f"{trial.metadata.get('orig_data_rate') or trial.rate:.12g}"
    values = [rate, camera_rate, str(n_frames), str(n_markers), "mm", orig_rate, str(first)]
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{file.name}",
        "\t".join(_HEADER_KEYS),
        "\t".join([*values, str(n_frames)]),
        "Frame#\tTime\t" + "\t".join(f"{lab}\t\t" for lab in trial.labels),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, n_markers + 1)),
        "",
    ]
    cells = np.char.mod("%.6f", trial.positions.reshape(n_frames, 3 * n_markers) * 1000.0)
    cells[np.isnan(trial.positions.reshape(n_frames, 3 * n_markers))] = ""
    frames = np.arange(first, first + n_frames).astype(str)
    times = np.char.mod("%.6f", np.arange(n_frames) / trial.rate)
    body = ["\t".join(row) for row in np.column_stack([frames, times, cells])]
    with atomic_output(file, overwrite) as tmp:
        tmp.write_text("\n".join(header + body) + "\n", encoding="utf-8")


# ------------------------------------------------------------------ helpers
def _split(line: str) -> list[str]:
    """Cells of a row: tab separated; whitespace separated if it has no tab."""
    return line.split("\t") if "\t" in line else line.split()


def _header(keys_line: str, values_line: str, file: Path) -> dict[str, str]:
    keys = [k.strip() for k in _split(keys_line)]
    values = [v.strip() for v in _split(values_line)]
    header = {k: v for k, v in zip(keys, values, strict=False) if k}
    missing = [k for k in ("DataRate", "NumFrames", "NumMarkers") if k not in header]
    if missing:
        raise InputError(f"{file}: TRC header lacks {', '.join(missing)} (line 2 names the fields)")
    return header


def _header_int(header: dict[str, str], key: str, file: Path) -> int:
    try:
        value = int(float(header[key]))
    except (ValueError, OverflowError):  # not a number, NaN or infinite
        raise InputError(f"{file}: TRC header {key}={header[key]!r} is not a whole number") from None
    if value < 0:
        raise InputError(f"{file}: TRC header {key}={value} is negative")
    return value


def _header_float(header: dict[str, str], key: str, file: Path) -> float:
    try:
        return float(header[key])
    except ValueError:
        raise InputError(f"{file}: TRC header {key}={header[key]!r} is not a number") from None


def _optional_float(value: str | None) -> float | None:
    try:
        return float(value) if value else None
    except ValueError:
        return None
