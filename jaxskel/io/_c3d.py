"""C3D marker recordings, read and written with ezc3d.

Reading keeps the 3D points (``c3d["data"]["points"]``, shape (4, N, F)) and
the parameters that give them meaning: ``POINT:LABELS`` (``LABELS2``, ... for
more than 255 points), ``POINT:UNITS``, ``POINT:RATE``, the groups listing
model outputs (``POINT:ANGLES``, ``FORCES``, ``MODELED_MARKERS``, ...),
``POINT:Y_SCREEN`` and ``MANUFACTURER``. ezc3d turns samples with a negative
residual (the C3D flag for "not seen") into NaN; exact zeros are made missing
by the shared rule in :mod:`jaxskel.io._load`.

Before ezc3d sees a file, its structure is checked from the raw bytes
(:func:`_check_layout`): ezc3d reads a truncated data section without
complaint (it shortens the recording and rewrites the frame count), and some
damaged parameter sections make it crash the interpreter.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from pathlib import Path

import ezc3d
import numpy as np

from .._errors import InputError
from ._atomic import atomic_output
from ._bounds import LOAD_COPIES, describe_bytes, require_memory
from ._raw import RawRecording, TrialLike, resolve_units, zeros_to_nan

__all__ = ["read_c3d", "write_c3d"]

# POINT groups listing points that are not positions (C3D TYPE_GROUPS convention).
_NON_POSITION_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "REACTIONS", "SCALARS")
# POINT groups listing positions computed by a model rather than measured.
_VIRTUAL_GROUPS = ("MODELED_MARKERS",)
# Parameters that readers (ezc3d included) use as numbers: where present, they
# must be numeric and hold a value.
_NUMERIC_PARAMETERS = {
    "POINT": ("USED", "FRAMES", "SCALE", "RATE", "DATA_START"),
    "ANALOG": ("USED", "RATE", "GEN_SCALE"),
    "ROTATION": ("USED", "RATE", "DATA_START", "RATIO"),
}
# Bytes ezc3d holds per point sample and per analog sample: it keeps every sample as an
# object of its own (with ezc3d 1.7 about 210 and 18 bytes, 13 and 4.5 times their size
# in a float file).
_EZC3D_POINT_BYTES = 256
_EZC3D_ANALOG_BYTES = 24
# ... and per rotation sample (an empty vector), plus per rotation in it (a 4 x 4 matrix).
_EZC3D_ROTATION_BYTES = 32
_EZC3D_MATRIX_BYTES = 320
# Header "key" byte of every C3D file (byte 2 of block 1).
_C3D_KEY = 0x50
# Parameter-section processor types: Intel, DEC (both little-endian words), MIPS.
_PROCESSORS = {84: "<", 85: "<", 86: ">"}
# Vertical axis <- (X_SCREEN, Y_SCREEN) written for it: the screen's "up" is the
# vertical, and "right" is the next axis so that the view is right-handed.
_SCREEN = {
    "x": ("+Y", "+X"),
    "-x": ("-Y", "-X"),
    "y": ("+X", "+Y"),
    "-y": ("-X", "-Y"),
    "z": ("+X", "+Z"),
    "-z": ("-X", "-Z"),
}


def read_c3d(file: Path, *, units: str | None = None) -> RawRecording:
    """Parse a C3D file (see the module docstring); positions in metres."""
    _check_layout(file)
    try:
        c3d = ezc3d.c3d(str(file))
    except Exception as err:  # ezc3d raises RuntimeError/OSError/IndexError with bare messages
        raise InputError(f"cannot read {file}: not a valid C3D file ({err})") from None
    try:
        return _parse(c3d, file, units)
    except InputError:
        raise
    except Exception as err:  # malformed parameters surface as KeyError/TypeError/...
        raise InputError(
            f"cannot read {file}: malformed C3D parameters ({type(err).__name__}: {err})"
        ) from None


def _parse(c3d: ezc3d.c3d, file: Path, units: str | None) -> RawRecording:
    params = c3d["parameters"]
    point = params["POINT"]
    data = np.asarray(c3d["data"]["points"], dtype=np.float64)
    if data.ndim != 3 or data.shape[1] == 0:
        raise InputError(
            f"{file} contains no 3D points (only analog or force-plate data?); "
            "it is not a marker recording"
        )
    n_points, n_frames = data.shape[1], data.shape[2]
    if n_frames == 0:
        raise InputError(f"{file} contains no frames")

    labels = _labels(point, n_points)
    non_position: set[int] = set()
    non_marker: dict[int, str] = {}
    for group in _point_type_groups(point):
        listed = {str(v).strip() for v in point[group]["value"]}
        for i, lab in enumerate(labels):
            if lab in listed or lab.rpartition(":")[2].strip() in listed:
                non_marker.setdefault(i, group.lower())
                if group not in _VIRTUAL_GROUPS:
                    non_position.add(i)

    raw = data[:3].transpose(2, 1, 0)  # (F, N, 3)
    position_cols = [i for i in range(n_points) if i not in non_position]
    stated = _first_string(point, "UNITS")
    length_unit = resolve_units(stated, units, raw[:, position_cols], file)
    positions = zeros_to_nan(raw) * length_unit.scale

    rate = _first_number(point, "RATE") or float(c3d["header"]["points"]["frame_rate"])
    if not np.isfinite(rate) or rate <= 0:
        raise InputError(f"{file}: invalid frame rate {rate!r} in POINT:RATE")

    declared = None
    if "JAXSKEL" in params and "UP_AXIS" in params["JAXSKEL"]:
        declared = _first_string(params["JAXSKEL"], "UP_AXIS")
    screen = _first_string(point, "Y_SCREEN")
    letter = screen.strip().lstrip("+-").lower() if screen else None
    extra = {
        "manufacturer": _manufacturer(params),
        "stated_up_axis": screen.strip() if screen else None,
        "n_points_in_file": n_points,
    }
    return RawRecording(
        positions=positions,
        labels=tuple(labels),
        rate=float(rate),
        units=length_unit,
        first_frame=int(c3d["header"]["points"]["first_frame"]) + 1,  # ezc3d is 0-based
        non_marker=non_marker,
        non_position=frozenset(non_position),
        declared_up_axis=declared if declared in _SCREEN or declared == "unknown" else None,
        stated_up_letter=letter if letter in ("x", "y", "z") else None,
        extra=extra,
    )


def write_c3d(trial: TrialLike, file: Path, *, overwrite: bool = False) -> None:
    """Write ``trial`` as a C3D: float32 millimetres, labels, rate, first frame, up axis.

    Missing samples are written as C3D marks them, (0, 0, 0) with residual -1
    ("not seen"); ezc3d would otherwise write NaN coordinates that other
    software does not expect. The up axis goes to ``POINT:X_SCREEN``/
    ``Y_SCREEN`` (for other software) and to ``JAXSKEL:UP_AXIS`` (read back
    verbatim by :func:`jaxskel.load`).
    """
    present = trial.mask.T  # (M, F)
    points = np.ones((4, trial.n_markers, trial.n_frames))
    points[:3] = np.where(present, np.transpose(trial.positions * 1000.0, (2, 1, 0)), 0.0)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [trial.rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(trial.labels)
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {
        "residuals": np.where(present, 0.0, -1.0)[None],
        "camera_masks": np.zeros((7, trial.n_markers, trial.n_frames), dtype=bool),
    }
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    if trial.up_axis in _SCREEN:
        x_screen, y_screen = _SCREEN[trial.up_axis]
        c3d.add_parameter("POINT", "X_SCREEN", [x_screen])
        c3d.add_parameter("POINT", "Y_SCREEN", [y_screen])
    c3d.add_parameter("JAXSKEL", "UP_AXIS", [trial.up_axis])
    first_frame = int(trial.metadata.get("first_frame", 1))
    c3d["header"]["points"]["first_frame"] = max(first_frame - 1, 0)
    with atomic_output(file, overwrite, suffix=".c3d") as tmp:
        try:
            c3d.write(str(tmp))
        except Exception as err:  # ezc3d reports bad labels/shapes as bare RuntimeErrors
            raise InputError(f"cannot write {file}: {err}") from None


# ------------------------------------------------------------------ helpers
def _check_layout(file: Path) -> None:
    """Validate the C3D structure before ezc3d parses it.

    ezc3d trusts the sizes it reads: a corrupt parameter record (a parameter
    claiming 171 dimensions) or a frame count larger than the data (POINT:FRAMES
    changed by one byte) can crash the interpreter, and a truncated data section
    is silently read as a shorter recording. So, from the raw bytes:

    1. the 512-byte header must be there with its key byte (0x50);
    2. every parameter record must lie within the parameter section
       (:func:`_parameter_records`), counts, scales and rates must be numbers
       (ANALOG:SCALE and OFFSET too where there are analog data), no text
       parameter may lack dimensions, and every DATA_START block must lie
       within the file;
    3. the file must hold the data of every frame that the header, POINT:FRAMES
       or POINT:LONG_FRAMES announce: the data start at the header's data block
       and take frames x (4 x points + analog samples per frame) words of 4
       bytes (float files, scale < 0) or 2 bytes. (TRIAL:ACTUAL_END_FIELD is not
       used: resampled files, like biobuddy's, keep the original value.)
    4. rotation data (the ROTATION group) must be in the file and of a plausible
       count (:func:`_rotation_samples`);
    5. the memory that ezc3d and the load take for those frames must be available
       (:func:`jaxskel.io._bounds.require_memory`).
    """
    with open(file, "rb") as handle:
        head = handle.read(512)
        size = os.fstat(handle.fileno()).st_size
        if len(head) < 512:
            raise InputError(
                f"cannot read {file}: only {len(head)} bytes, shorter than a C3D header (512); "
                "the file is truncated or not a C3D file"
            )
        if head[1] != _C3D_KEY:
            raise InputError(
                f"cannot read {file}: not a C3D file (header key byte is {head[1]:#04x}, "
                f"expected {_C3D_KEY:#04x})"
            )
        handle.seek(max(head[0] - 1, 0) * 512)
        section = handle.read(4)
        if head[0] < 2 or len(section) < 4 or section[3] not in _PROCESSORS:
            raise InputError(f"cannot read {file}: the C3D parameter section is missing or damaged")
        processor = section[3]
        endian = _PROCESSORS[processor]
        # Header words 2-5: points, analog samples per frame, first and last frame;
        # words 9-10: first data block, analog samples per frame per channel.
        n_points, n_analog, first, last = struct.unpack(endian + "4H", head[2:10])
        data_block, analog_ratio = struct.unpack(endian + "2H", head[16:20])
        # Parameters end where the data start (the block count in byte 2 of the
        # parameter section is unreliable in real files, so it is not used).
        n_blocks = data_block - head[0] if data_block > head[0] else 255
        section += handle.read(n_blocks * 512 - 4)
    records = _parameter_records(section, endian, file, (head[0] - 1) * 512)
    for (group, name), (dtype, _, data) in records.items():
        if name in _NUMERIC_PARAMETERS.get(group, ()) and (dtype == -1 or not data):
            raise InputError(
                f"cannot read {file}: parameter {group}:{name} holds no number; the file is damaged"
            )
    for (group, name), (dtype, dims, _) in records.items():
        if dtype == -1 and not dims:  # ezc3d crashes the interpreter on these
            raise InputError(
                f"cannot read {file}: parameter {group}:{name} is text without dimensions; the file is damaged"
            )

    def number(group: str, name: str, index: int = 0) -> float | None:
        return _record_number(records.get((group, name)), index, endian, processor)

    frames = [last - first + 1 if last >= first else 0]
    frames += [number("POINT", "FRAMES"), number("POINT", "LONG_FRAMES")]
    points = [n_points, number("POINT", "USED")]
    analog_used = number("ANALOG", "USED")
    analogs = [n_analog, (analog_used or 0) * analog_ratio]
    scales = [number("POINT", "SCALE"), _header_scale(head, endian, processor)]
    word = 4 if any(v is not None and v < 0 for v in scales) else 2

    def most(values: list[float | None]) -> int:
        return int(max((v for v in values if v is not None and np.isfinite(v)), default=0))

    if most(analogs) > 0:  # ezc3d scales every analog sample by these, and crashes without them
        for name in ("SCALE", "OFFSET"):
            dtype = records.get(("ANALOG", name), (-1,))[0]
            if dtype == -1:
                raise InputError(
                    f"cannot read {file}: it holds analog data but no numeric ANALOG:{name}; the file is damaged"
                )

    n_frames = most(frames)
    expected = (max(data_block, 1) - 1) * 512 + n_frames * (4 * most(points) + most(analogs)) * word
    if size < expected:
        raise InputError(
            f"cannot read {file}: the file is truncated: it announces {n_frames} frames "
            f"({expected} bytes) but has {size} bytes"
        )
    rotation_samples = _rotation_samples(records, number, n_frames, size, head, endian, processor, file)
    need = n_frames * (most(points) * (_EZC3D_POINT_BYTES + 3 * 8 * LOAD_COPIES) + most(analogs) * _EZC3D_ANALOG_BYTES)
    need += rotation_samples * (_EZC3D_ROTATION_BYTES + int(number("ROTATION", "USED") or 0) * _EZC3D_MATRIX_BYTES)
    declared = f"declares {n_frames} frames x {most(points)} points and {most(analogs)} analog samples a frame"
    require_memory(file, need, declared)
    for group in ("POINT", "ROTATION"):
        block = number(group, "DATA_START")
        used = number(group, "USED")
        if block is not None and used and (block - 1) * 512 > size:
            raise InputError(
                f"cannot read {file}: {group}:DATA_START points to block {block:.0f}, past the "
                "end of the file; the file is damaged or truncated"
            )


def _rotation_samples(
    records: dict[tuple[str, str], tuple[int, tuple[int, ...], bytes]],
    number: Callable[[str, str], float | None],
    n_frames: int,
    size: int,
    head: bytes,
    endian: str,
    processor: int,
    file: Path,
) -> int:
    """Rotation samples ezc3d makes room for (C-Motion's ROTATION group), after checking them.

    ezc3d allocates frames x RATIO entries (RATIO read as a signed int16; without it,
    ROTATION:RATE over the header's point rate), then reads ROTATION:USED rotations of
    17 floats into each, from ROTATION:DATA_START. A file whose rotation data stop
    short makes ezc3d abort the interpreter, and an absurd RATIO takes gigabytes
    though no rotation is stored.
    """
    if not any(group == "ROTATION" and name in ("RATIO", "RATE") for group, name in records):
        return 0
    if ("ROTATION", "RATIO") in records:
        ratio = number("ROTATION", "RATIO")
        what = f"ROTATION:RATIO = {ratio:.0f}" if ratio is not None else "ROTATION:RATIO"
    else:
        point_rate = None if processor == 85 else struct.unpack(endian + "f", head[20:24])[0]
        rate = number("ROTATION", "RATE")
        ratio = rate / point_rate if rate is not None and point_rate and np.isfinite(point_rate) else None
        what = f"ROTATION:RATE / the point rate = {ratio}"
    if ratio is None or not np.isfinite(ratio) or not 0 <= ratio < 2**15:
        raise InputError(f"cannot read {file}: {what} is not a number of rotation samples per frame; the file is damaged")
    samples = n_frames * int(ratio)
    used = int(number("ROTATION", "USED") or 0)
    start = number("ROTATION", "DATA_START")
    if used and (start is None or (start - 1) * 512 + samples * used * 17 * 4 > size):
        raise InputError(
            f"cannot read {file}: the file is truncated: its ROTATION group announces {used} rotations in "
            f"{samples} samples ({samples * used * 68} bytes from block {start or 0:.0f}) but it has {size} bytes"
        )
    if samples > max(2**20, size):
        raise InputError(
            f"cannot read {file}: {what} announces {samples} rotation samples, more than a file of "
            f"{describe_bytes(size)} holds; the file is damaged"
        )
    return samples


def _parameter_records(
    section: bytes, endian: str, file: Path, section_start: int
) -> dict[tuple[str, str], tuple[int, tuple[int, ...], bytes]]:
    """(GROUP, NAME) -> (data type, dimensions, data) of every parameter.

    A record is: name length (int8, negative = locked), group id (int8,
    negative = a group), the name, the offset to the next record (int16
    counted from its own position, 0 = last record); then a group has a
    description (uint8 length + text) and a parameter a data type (-1 char,
    1 byte, 2 int16, 4 float), up to 7 dimensions (uint8 each), the data and a
    description. InputError if a record reaches past the next one or the end.
    """
    end = len(section)
    groups: dict[int, str] = {}
    params: list[tuple[int, str, tuple[int, tuple[int, ...], bytes]]] = []
    pos = 4
    while pos + 2 <= end:
        name_len, group_id = struct.unpack("bb", section[pos : pos + 2])
        if name_len == 0:  # explicit end of the parameters
            break
        field = pos + 2 + abs(name_len)
        name = section[pos + 2 : field].decode("latin-1").strip().upper()
        fault = pos if field + 2 > end else None
        if fault is None:
            (offset,) = struct.unpack(endian + "h", section[field : field + 2])
            record_end = field + offset if offset else end
            fault = field if offset < 0 or record_end > end else None
        if fault is None:
            body = field + 2
            if group_id > 0:  # a parameter: data type, dimensions, data
                fault = body if body + 2 > record_end else None
                if fault is None:
                    dtype, n_dims = struct.unpack("bB", section[body : body + 2])
                    dims = tuple(section[body + 2 : body + 2 + n_dims])
                    size = abs(dtype) * int(np.prod(dims, dtype=np.int64))
                    data_at = body + 2 + n_dims
                    # A zero dimension empties the parameter, but ezc3d still loops over the
                    # others: their product is bounded by what the section could hold.
                    spread = int(np.prod([d for d in dims if d], dtype=np.int64))
                    if dtype not in (-1, 1, 2, 4) or n_dims > 7 or data_at + size > record_end or spread > end:
                        fault = body
                    else:
                        params.append(
                            (group_id, name, (dtype, dims, section[data_at : data_at + size]))
                        )
                        body = data_at + size
            else:
                groups[-group_id] = name
            # The description: a length byte and its text (may be absent on the last record).
            if fault is None and body < record_end and body + 1 + section[body] > record_end:
                fault = body
        if fault is not None:
            raise InputError(
                f"cannot read {file}: corrupt C3D parameter record at byte "
                f"{section_start + fault}; the file is damaged"
            )
        if offset == 0:
            break
        pos = record_end
    return {(groups.get(gid, ""), name): value for gid, name, value in params}


def _record_number(
    record: tuple[int, tuple[int, ...], bytes] | None, index: int, endian: str, processor: int
) -> float | None:
    """Element ``index`` of a numeric parameter (int16 read as unsigned, as counts
    are), or None if absent, not numeric or a DEC float."""
    if record is None:
        return None
    dtype, _, data = record
    if dtype == 2 and len(data) >= 2 * (index + 1):
        return float(struct.unpack(endian + "H", data[2 * index : 2 * index + 2])[0])
    if dtype == 1 and len(data) > index:
        return float(data[index])
    if dtype == 4 and len(data) >= 4 * (index + 1) and processor != 85:
        return float(struct.unpack(endian + "f", data[4 * index : 4 * index + 4])[0])
    return None


def _header_scale(head: bytes, endian: str, processor: int) -> float | None:
    """The header's point scale factor (words 7-8); for DEC files only its sign."""
    if processor == 85:  # VAX float: the sign is the top bit of the first 16-bit word
        return -1.0 if head[13] & 0x80 else 1.0
    return float(struct.unpack(endian + "f", head[12:16])[0])


def _labels(point: dict, n_points: int) -> list[str]:
    """POINT:LABELS, LABELS2, ... concatenated, padded with blanks to ``n_points``."""
    labels: list[str] = []
    key, k = "LABELS", 1
    while key in point:
        labels.extend(str(v).strip() for v in point[key]["value"])
        k += 1
        key = f"LABELS{k}"
    labels = labels[:n_points]
    return labels + [""] * (n_points - len(labels))


def _point_type_groups(point: dict) -> list[str]:
    """POINT parameters that list model-output labels (standard plus TYPE_GROUPS)."""
    groups = list(_NON_POSITION_GROUPS + _VIRTUAL_GROUPS)
    if "TYPE_GROUPS" in point:
        # Pairs (group parameter, singular type name): ANGLES, ANGLE, FORCES, FORCE, ...
        groups += [str(v).strip() for v in list(point["TYPE_GROUPS"]["value"])[0::2]]
    return [g for g in dict.fromkeys(groups) if g and g in point and g != "LABELS"]


def _first_string(group: dict, name: str) -> str | None:
    if name not in group:
        return None
    value = group[name]["value"]
    values = list(value) if not isinstance(value, str) else [value]
    return str(values[0]).strip() if values and str(values[0]).strip() else None


def _first_number(group: dict, name: str) -> float | None:
    if name not in group:
        return None
    value = np.asarray(group[name]["value"]).ravel()
    return float(value[0]) if value.size and np.issubdtype(value.dtype, np.number) else None


def _manufacturer(params: dict) -> str | None:
    if "MANUFACTURER" not in params:
        return None
    group = params["MANUFACTURER"]
    parts = [_first_string(group, key) for key in ("COMPANY", "SOFTWARE")]
    return " ".join(p for p in parts if p) or None
