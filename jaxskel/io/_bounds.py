"""What a reader may allocate: sizes a file declares, checked before they are allocated.

A file's header can declare anything: 4.2 million frames in an 8 KB HDF5 file, a
label of 50 million characters. Readers allocate from what a file declares, so each
one checks it first against what the file holds (the bytes present, per format) and
against the memory available (:func:`require_memory`), and refuses with an
:class:`~jaxskel.InputError` that says what was declared and what is there. Labels
longer than :data:`MAX_LABEL_CHARS` are refused (:func:`check_labels`): no marker name
is that long, and every stage after the reader copies the labels into fixed-width
text arrays, as wide as the longest one for every marker.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from .._errors import InputError

__all__ = [
    "LOAD_COPIES", "MAX_LABEL_CHARS", "MAX_NUMBER_CHARS", "available_memory", "check_labels", "describe_bytes",
    "require_memory",
]

#: Longest marker label accepted, in characters (C3D's own limit is 255).
MAX_LABEL_CHARS = 1024

#: Longest cell of a text table that may hold a number (``%.17g`` writes at most 24).
MAX_NUMBER_CHARS = 64

#: Arrays of the size of the positions that a load holds at once, at most: the parsed
#: table, the unit guess, the missing-sample conversion, the kept markers, the Trial and
#: the up-axis inference.
LOAD_COPIES = 8


def describe_bytes(n: float) -> str:
    """``1536`` -> ``"1.5 KB"`` (powers of 1024)."""
    for unit in ("bytes", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TB"  # pragma: no cover


def available_memory() -> int | None:
    """Bytes this process can still allocate, or None where it cannot be told.

    The least of: the system's available memory (``MemAvailable``), the room left in
    the process's cgroup (``memory.max`` less ``memory.current``), and the room left
    under the process's own limits (``RLIMIT_AS`` less its address space,
    ``RLIMIT_DATA`` less its data segment).
    """
    room: list[int] = []
    meminfo = _read_kb_fields("/proc/meminfo")
    if "MemAvailable" in meminfo:
        room.append(meminfo["MemAvailable"])
    limit, used = _read_int("/sys/fs/cgroup/memory.max"), _read_int("/sys/fs/cgroup/memory.current")
    if limit is not None and used is not None:
        room.append(max(limit - used, 0))
    try:
        import resource
    except ImportError:  # pragma: no cover - not on POSIX
        resource = None  # type: ignore[assignment]
    if resource is not None:
        status = _read_kb_fields("/proc/self/status")
        for rlimit, field in ((resource.RLIMIT_AS, "VmSize"), (getattr(resource, "RLIMIT_DATA", None), "VmData")):
            if rlimit is None or field not in status:
                continue
            soft, _ = resource.getrlimit(rlimit)
            if soft != resource.RLIM_INFINITY:
                room.append(max(soft - status[field], 0))
    return min(room) if room else None


def require_memory(file: Path, need: int, what: str) -> None:
    """InputError when reading ``file`` needs ``need`` bytes and fewer are available.

    ``what`` says what the file declares or is, as a verb phrase
    (``"declares 4200000 frames x 14 markers"``, ``"is 3.2 GB of text"``).
    """
    free = available_memory()
    if free is not None and need > free:
        raise InputError(
            f"cannot read {file}: it {what}, which takes about {describe_bytes(need)} of memory "
            f"to read, but only {describe_bytes(free)} is available; split the recording or free memory"
        )


def check_labels(labels: Sequence[str], file: Path) -> None:
    """InputError for a label longer than :data:`MAX_LABEL_CHARS`."""
    for i, label in enumerate(labels):
        if len(label) > MAX_LABEL_CHARS:
            raise InputError(
                f"cannot read {file}: label {i + 1} ({label[:20]!r}...) is {len(label)} characters long; "
                f"a marker label has at most {MAX_LABEL_CHARS} characters, so the file is damaged or not a marker recording"
            )


def _read_kb_fields(path: str) -> dict[str, int]:
    """``Name:  123 kB`` lines of a /proc file, in bytes."""
    try:
        with open(path) as handle:
            text = handle.read()
    except OSError:
        return {}
    out = {}
    for line in text.splitlines():
        name, _, value = line.partition(":")
        parts = value.split()
        if len(parts) == 2 and parts[1] == "kB" and parts[0].isdigit():
            out[name] = int(parts[0]) * 1024
    return out


def _read_int(path: str) -> int | None:
    try:
        with open(path) as handle:
            text = handle.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None
