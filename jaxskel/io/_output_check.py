"""What an output path must be, checked before any work is done.

A fit can take minutes; an output that cannot be written must be refused before it
starts, not after. :func:`check_output` says, for one output, everything that can be
known up front: the path is not a folder, its suffix is one the writer knows (a
result ``.h5``, a ``.bvh``, an image type matplotlib can write, ...), and the folder
it goes into (or the nearest existing folder above it) is writable. The library's
writers call it before they write; the command line calls it for every output
before it reads the inputs (together with :func:`jaxskel.io._atomic.refuse_input`).
"""

from __future__ import annotations

import os
from pathlib import Path

from .._errors import InputError

__all__ = ["OUTPUT_KINDS", "check_output", "check_writable", "image_format", "image_types"]

#: kind -> (what the file is called, its suffixes (None: an image type), an example name)
OUTPUT_KINDS: dict[str, tuple[str, tuple[str, ...] | None, str]] = {
    "result": ("a result file", (".h5", ".hdf5"), "result.h5"),
    "trial": ("a recording", (".h5", ".hdf5", ".c3d", ".trc"), "trial.h5"),
    "bvh": ("a BVH file", (".bvh",), "skeleton.bvh"),
    "trc": ("a TRC file", (".trc",), "fitted_markers.trc"),
    "osim": ("an OpenSim model", (".osim",), "skeleton.osim"),
    "image": ("a figure", None, "summary.png"),
    "table": ("a table", (".csv",), "summary.csv"),
    "sto": ("an OpenSim storage file", (".sto", ".mot"), "angles.sto"),
}


def _head(path: Path, who: str | None) -> str:
    """The start of a message about output ``path``: ``"-o out.h5"`` or ``"cannot write out.h5"``."""
    return f"{who} {path}" if who else f"cannot write {path}"


def image_types() -> tuple[str, ...]:
    """The file suffixes matplotlib can write a figure to (``.png``, ``.pdf``, ``.svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(f".{k}" for k in FigureCanvasBase.get_supported_filetypes()))


def image_format(path: str | os.PathLike[str], who: str | None = None) -> str:
    """Matplotlib's format name for the suffix of ``path`` (``"png"`` for ``x.png``);
    :class:`InputError` naming the types it can write for any other suffix (or none)."""
    path = Path(path)
    suffix = path.suffix.lower()
    known = image_types()
    if suffix not in known:
        shown = f"a {suffix!r} image" if suffix else "an image without a file type"
        raise InputError(
            f"{_head(path, who)}: matplotlib cannot write {shown}; give a name ending in one of "
            f"{', '.join(known)} (e.g. {path.with_suffix('.png')})"
        )
    return suffix[1:]


def check_output(path: str | os.PathLike[str], kind: str, who: str | None = None) -> Path:
    """Refuse an output ``path`` of ``kind`` (:data:`OUTPUT_KINDS`) that cannot be written:
    a folder, an unknown suffix, a folder above it that is a file or is not writable.

    ``who`` names the output in the message (a flag such as ``"-o"``; default: the
    message starts ``cannot write PATH``). Returns the path.
    """
    path = Path(path)
    what, suffixes, example = OUTPUT_KINDS[kind]
    if path.is_dir():
        raise InputError(f"{_head(path, who)}: it is a folder; give a file name inside it, e.g. {path / example}")
    if suffixes is None:
        image_format(path, who)
    elif path.suffix.lower() not in suffixes:
        given = f"not {path.suffix!r}" if path.suffix else "not a name without a file type"
        raise InputError(
            f"{_head(path, who)}: {what} must end in {' or '.join(suffixes)}, {given} "
            f"(e.g. {path.with_suffix(suffixes[0])})"
        )
    check_writable(path, who)
    return path


def check_writable(path: str | os.PathLike[str], who: str | None = None, *, folder: bool = False) -> Path:
    """Refuse ``path`` when it cannot be written: the nearest existing folder at or above
    the folder it goes into (``path`` itself where ``folder``: an output folder) must be a
    writable folder (the folders below it are created when written). Returns that folder."""
    path = Path(path)
    start = path if folder else path.parent
    found = next((p for p in (start, *start.parents) if p.exists()), Path("."))
    if not found.is_dir():
        raise InputError(f"{_head(path, who)}: {found} is a file, not a folder")
    if not os.access(found, os.W_OK | os.X_OK):
        raise InputError(f"{_head(path, who)}: the folder {found} is not writable; choose another place")
    return found
