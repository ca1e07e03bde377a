"""jaxskel's own trial file: HDF5 that round-trips a :class:`~jaxskel.Trial` exactly.

Layout (``jaxskel_trial_version`` = 1):

==========================  ============================================
``/positions``              (F, M, 3) float64, metres, NaN = missing
``/labels``                 (M,) UTF-8 strings
attribute ``rate``          frames per second
attribute ``up_axis``       one of ``x y z -x -y -z unknown``
attribute ``source``        where the trial came from
attribute ``units``         ``"m"``
attribute ``metadata``      the trial's metadata as a JSON object
attribute ``jaxskel_trial_version``, ``jaxskel_version``
==========================  ============================================

Reading validates the version (a newer one is a :class:`~jaxskel.SchemaError`),
the shapes, and, before reading a dataset, that the file holds the data its shape
declares (:func:`_check_stored`) and that memory suffices
(:mod:`jaxskel.io._bounds`); anything h5py raises becomes an :class:`~jaxskel.InputError`.
"""

from __future__ import annotations

import json
import mmap
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .._errors import InputError, SchemaError
from ._atomic import atomic_output
from ._bounds import LOAD_COPIES, MAX_LABEL_CHARS, check_labels, describe_bytes, require_memory
from ._raw import UP_AXES, RawRecording, TrialLike, Units

__all__ = ["TRIAL_VERSION", "read_h5", "write_h5"]

#: Version of the layout above; bump it when the layout changes incompatibly.
TRIAL_VERSION = 1

#: Most a compressed dataset may expand: gzip's limit (1032:1), with a margin.
MAX_COMPRESSION = 1100


def write_h5(trial: TrialLike, file: Path, *, overwrite: bool = False) -> None:
    """Write ``trial`` in the layout of the module docstring (gzip-compressed positions)."""
    from .._version import __version__

    # "file" is where a load read the trial from: set anew by every load, never stored
    metadata = json.dumps(_jsonable({k: v for k, v in trial.metadata.items() if k != "file"}))
    with atomic_output(file, overwrite) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["jaxskel_trial_version"] = TRIAL_VERSION
        h5.attrs["jaxskel_version"] = __version__
        h5.attrs["rate"] = float(trial.rate)
        h5.attrs["up_axis"] = trial.up_axis
        h5.attrs["source"] = trial.source
        h5.attrs["units"] = "m"
        h5.attrs["metadata"] = metadata
        compress = {"compression": "gzip", "shuffle": True} if trial.positions.size else {}
        h5.create_dataset("positions", data=np.asarray(trial.positions, np.float64), **compress)
        h5.create_dataset(
            "labels", data=np.array(trial.labels, dtype=object), dtype=h5py.string_dtype()
        )


def read_h5(file: Path, *, units: str | None = None) -> RawRecording:
    """Read a trial written by :func:`write_h5`."""
    if units is not None:
        raise InputError(
            f"{file}: --units / units= does not apply to HDF5 trials, which are always stored in metres"
        )
    _check_global_heaps(file)
    try:
        h5 = h5py.File(file, "r")
    except Exception as err:  # h5py raises OSError (and others) for non-HDF5/damaged files
        raise InputError(f"cannot read {file}: not a valid HDF5 file ({err})") from None
    try:
        with h5:
            return _parse(h5, file)
    except (InputError, SchemaError):
        raise
    except Exception as err:  # a damaged file fails while reading a dataset
        raise InputError(
            f"cannot read {file}: damaged HDF5 trial ({type(err).__name__}: {err})"
        ) from None


def _parse(h5: h5py.File, file: Path) -> RawRecording:
    attrs = h5.attrs
    if "jaxskel_trial_version" not in attrs:
        if "schema_version" in attrs:
            raise InputError(
                f"{file} is a jaxskel result file, not a trial; read it with jaxskel.load_result"
            )
        raise InputError(
            f"{file} is not a jaxskel trial (no 'jaxskel_trial_version' attribute); "
            "trials are written by jaxskel.save_trial / Trial.save"
        )
    version = int(np.asarray(attrs["jaxskel_trial_version"]).item())
    if version > TRIAL_VERSION or version < 1:
        raise SchemaError(
            f"{file} uses trial format version {version}; this jaxskel reads version "
            f"{TRIAL_VERSION}. Upgrade jaxskel (or re-save the trial with this version)."
        )
    for name in ("positions", "labels"):
        if name not in h5 or not isinstance(h5[name], h5py.Dataset):
            raise InputError(
                f"{file}: jaxskel trial without a '{name}' dataset; the file is damaged"
            )
    # Shapes and sizes first, from the file's declarations, before anything is allocated.
    shape, n_labels = h5["positions"].shape, h5["labels"].size
    if len(shape) != 3 or shape[-1] != 3 or shape[1] != n_labels:
        raise InputError(
            f"{file}: positions have shape {shape} for {n_labels} labels; expected (frames, labels, 3)"
        )
    _check_type(h5["positions"], (h5py.h5t.FLOAT, h5py.h5t.INTEGER), "numbers", file)
    _check_type(h5["labels"], (h5py.h5t.STRING,), "text", file)
    _check_stored(h5["positions"], file, f"{shape[0]} frames x {shape[1]} markers")
    _check_stored(h5["labels"], file, f"{n_labels} labels")
    _check_label_lengths(h5["labels"], file)
    declared = f"declares {shape[0]} frames x {shape[1]} markers"
    require_memory(file, shape[0] * shape[1] * 3 * 8 * LOAD_COPIES, declared)
    labels = tuple(
        v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in h5["labels"][()].ravel()
    )
    check_labels(labels, file)
    positions = np.asarray(h5["positions"][()], dtype=np.float64)
    for name in ("rate", "up_axis"):
        if name not in attrs:
            raise InputError(
                f"{file}: jaxskel trial without the '{name}' attribute; the file is damaged"
            )
    up_axis = _text(attrs["up_axis"])
    if up_axis not in UP_AXES:
        raise InputError(f"{file}: invalid up_axis attribute {up_axis!r}")
    try:
        metadata = json.loads(_text(attrs.get("metadata", "{}")))
    except json.JSONDecodeError:
        raise InputError(f"{file}: the metadata attribute is not valid JSON") from None
    if not isinstance(metadata, dict):
        raise InputError(f"{file}: the metadata attribute is not a JSON object")
    return RawRecording(
        positions=positions,
        labels=labels,
        rate=float(np.asarray(attrs["rate"]).item()),
        units=Units(1.0, "m", "file"),
        first_frame=int(metadata.get("first_frame", 1)),
        declared_up_axis=up_axis,
        strip_prefixes=False,
        source=_text(attrs.get("source", str(file))),
        provenance=metadata,
    )


def _check_global_heaps(file: Path) -> None:
    """InputError for a damaged global heap collection, before HDF5 reads one.

    Variable-length strings (the labels, the text attributes) live in global heap
    collections: ``GCOL``, version 1, 3 reserved bytes, the collection's size (8 bytes),
    then objects of a 2-byte index, a reference count, 4 reserved bytes, an 8-byte size
    and the data padded to 8 bytes; index 0 is the free space, which runs to the end
    (its size counts its own header).
    libhdf5 trusts those sizes: one damaged size made it corrupt its memory, then hang
    or crash the interpreter. So every collection must walk exactly to its end.
    (A match of the signature that is not followed by a plausible header is data.)
    """
    with open(file, "rb") as handle:
        try:
            data = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # not mappable: HDF5 opens it, or says why not
            return
    with data:
        at = data.find(b"GCOL")
        while at >= 0:
            head = data[at : at + 16]
            if len(head) == 16 and head[4] == 1 and head[5:8] == b"\0\0\0":
                (size,) = struct.unpack("<Q", head[8:16])
                if 4096 <= size <= len(data) - at and not _heap_objects_fit(data, at, size):
                    raise InputError(
                        f"cannot read {file}: the global heap at byte {at} (the labels and text attributes) is "
                        "damaged"
                    )
            at = data.find(b"GCOL", at + 4)


def _heap_objects_fit(data: mmap.mmap, start: int, size: int) -> bool:
    """Whether the objects of the collection at ``start`` end exactly at its end."""
    pos, end = start + 16, start + size
    while pos + 16 <= end:
        index, _, _, length = struct.unpack("<HHIQ", data[pos : pos + 16])
        if index == 0:  # the free space (its size counts its header): the rest of the collection
            return pos + length == end
        pos += 16 + (length + 7) // 8 * 8
    return pos == end or 0 <= end - pos < 16


def _check_label_lengths(dataset: h5py.Dataset, file: Path) -> None:
    """InputError for a variable-length label declared longer than a label can be.

    Each element of a contiguous variable-length string dataset is a heap reference:
    the string's length in bytes (4), its collection's address (8) and its index (4).
    libhdf5 allocates the declared length before it finds the string, so a damaged
    length takes gigabytes; the lengths are read from the file and checked first.
    """
    tid = dataset.id.get_type()
    layout = dataset.id.get_create_plist().get_layout()
    offset = dataset.id.get_offset()
    if not (isinstance(tid, h5py.h5t.TypeStringID) and tid.is_variable_str()) or layout != h5py.h5d.CONTIGUOUS \
            or offset is None or dataset.size == 0:
        return
    with open(file, "rb") as handle:
        handle.seek(offset)
        refs = handle.read(16 * dataset.size)
    if len(refs) < 16 * dataset.size:
        raise InputError(f"cannot read {file}: /labels lies past the end of the file; the file is damaged or truncated")
    lengths = struct.unpack(f"<{dataset.size}Q", b"".join(refs[k : k + 4] + b"\0\0\0\0" for k in range(0, len(refs), 16)))
    for i, n in enumerate(lengths):
        if n > 4 * MAX_LABEL_CHARS:  # UTF-8: at most 4 bytes a character
            raise InputError(
                f"cannot read {file}: label {i + 1} is {n} bytes long; a marker label has at most "
                f"{MAX_LABEL_CHARS} characters, so the file is damaged or not a marker recording"
            )


def _check_type(dataset: h5py.Dataset, classes: tuple[int, ...], what: str, file: Path) -> None:
    """InputError unless ``dataset``'s stored type is of one of ``classes`` (HDF5 type
    classes): reading a damaged type (a variable-length sequence where text was written)
    can crash the HDF5 library."""
    if dataset.id.get_type().get_class() not in classes:
        raise InputError(
            f"cannot read {file}: /{dataset.name.lstrip('/')} does not hold {what} "
            f"({type(dataset.id.get_type()).__name__}); the file is damaged"
        )


def _check_stored(dataset: h5py.Dataset, file: Path, declared: str) -> None:
    """InputError unless the file holds the data that ``dataset``'s shape declares.

    A dataset's shape is a declaration: HDF5 returns its fill value for every element
    never written, so an 8 KB file can declare gigabytes. Its stored bytes must cover
    its size, or, compressed, come within :data:`MAX_COMPRESSION` of it, and lie within
    the file.
    """
    size = int(dataset.size) * int(dataset.id.get_type().get_size())
    stored = int(dataset.id.get_storage_size())
    compressed = dataset.id.get_create_plist().get_nfilters() > 0
    reach = stored * (MAX_COMPRESSION if compressed else 1)
    if size > reach or stored > file.stat().st_size:
        holds = "no data for it" if stored == 0 else f"{describe_bytes(stored)} of data for it" + (
            f" (compressed: at most {describe_bytes(reach)} once expanded)" if compressed else ""
        )
        raise InputError(
            f"cannot read {file}: /{dataset.name.lstrip('/')} declares {declared} ({describe_bytes(size)}) "
            f"but the file holds {holds}; the file is damaged or truncated"
        )


def _text(value: Any) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


def _jsonable(value: Any) -> Any:
    """Metadata as plain JSON types (mappings, sequences, numbers, strings, None)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)
