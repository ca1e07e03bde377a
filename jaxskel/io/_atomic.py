"""Atomic file output: a reader never sees a half-written file.

Every writer in jaxskel (trials, results, exports) writes to a temporary file
in the destination directory and renames it onto the destination only once
the write has finished. A rename within one directory is atomic on POSIX and
Windows, so the destination is either the old file (or absent) or the complete
new one, never a partial file, even if the process dies mid-write.
"""

from __future__ import annotations

import contextlib
import errno
import os
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from .._errors import InputError

__all__ = ["atomic_output"]


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike[str],
    overwrite: bool = False,
    *,
    suffix: str | None = None,
) -> Iterator[Path]:
    """Context manager yielding a temporary path to write instead of ``path``.

    On a normal exit the temporary file is flushed to disk and moved onto
    ``path``; if the body raises, the temporary file is removed and ``path``
    is left exactly as it was.

    Parameters
    ----------
    path
        The destination file. Its directory must exist.
    overwrite
        Replace an existing ``path``. Without it an existing file is never
        touched: the check is made up front (so no work is wasted) and again,
        race-free, when the file is put in place (a hard link fails if the name
        has been taken meanwhile).
    suffix
        Suffix of the temporary name (default: the suffix of ``path``); for
        libraries that insist on a particular extension when writing.

    Raises
    ------
    InputError
        ``path`` exists (without ``overwrite``), is a directory, its directory
        is missing, or the body did not create the temporary file.

    Examples
    --------
    >>> with atomic_output("trial.trc") as tmp:  # doctest: +SKIP
    ...     tmp.write_text(text)
    """
    target = Path(path)
    if target.is_dir():
        raise InputError(f"cannot write {target}: it is a directory; give a file name")
    if not target.parent.is_dir():
        raise InputError(
            f"cannot write {target}: directory {target.parent} does not exist; create it first"
        )
    if target.exists() and not overwrite:
        raise InputError(
            f"{target} already exists; pass overwrite=True to replace it or choose another name"
        )
    # A hidden, unique sibling: same directory (so the final rename is atomic)
    # and not pre-created, so writers create it with the user's default mode.
    tmp_suffix = target.suffix if suffix is None else suffix
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp{tmp_suffix}")
    try:
        yield tmp
        if not tmp.is_file():
            raise InputError(f"writing {target} produced no file; nothing was written")
        _fsync(tmp)
        if overwrite:
            os.replace(tmp, target)
        else:
            _publish_exclusive(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def _fsync(path: Path) -> None:
    """Flush a file's contents to disk so the rename never exposes an empty file."""
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


def _publish_exclusive(tmp: Path, target: Path) -> None:
    """Move ``tmp`` onto ``target`` unless ``target`` exists (checked atomically).

    ``os.link`` fails with EEXIST when the name is taken, which closes the race
    between the up-front existence check and the move. Filesystems without hard
    links fall back to a plain replace after a last check.
    """
    try:
        os.link(tmp, target)
    except FileExistsError:
        raise InputError(
            f"{target} was created by someone else while writing; nothing was overwritten. "
            "Pass overwrite=True to replace it."
        ) from None
    except OSError as err:
        if err.errno not in (
            errno.EPERM,
            errno.ENOTSUP,
            errno.EOPNOTSUPP,
            errno.EXDEV,
            errno.EMLINK,
        ):
            raise
        if target.exists():
            raise InputError(
                f"{target} already exists; pass overwrite=True to replace it"
            ) from None
        os.replace(tmp, target)


def input_sources(trial: Any) -> list[str]:
    """The files a (possibly combined) trial was read from."""
    meta = getattr(trial, "metadata", None) or {}
    sources = [*(meta.get("sources", ()) or ()), *(meta.get("files", ()) or ()), meta.get("file", "")]
    sources += str(getattr(trial, "source", "") or "").split(" + ")
    return [v for v in sources if v and v != "<array>"]


def refuse_input(path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]], what: str = "the output") -> None:
    """Raise :class:`InputError` when ``path`` names one of ``inputs`` (the same file by
    path or, where both exist, by inode): an input is never written over, whatever
    ``overwrite`` says."""
    target = Path(path)
    for source in inputs:
        src = Path(source)
        same = target.resolve() == src.resolve()
        if not same and target.exists() and src.exists():
            same = os.path.samefile(target, src)
        if same:
            raise InputError(
                f"{what} {target} is the input recording {src}; jaxskel never writes over an input, even with "
                "overwrite: choose another name"
            )
