"""Atomic file output: a reader never sees a half-written file.

Every writer in jaxskel (trials, results, exports) writes to a temporary file
in the destination directory and renames it onto the destination only once
the write has finished. A rename within one directory is atomic on POSIX and
Windows, so the destination is either the old file (or absent) or the complete
new one, never a partial file, even if the process dies mid-write.

A process killed mid-write (``kill -9``, out of memory, power loss) cannot remove
its temporary file. Temporary files are therefore named after their owner,
``.<name>.jaxskel-<pid>-<origin>-<random>.tmp<suffix>`` (``origin``: 8 hex digits
of the host name and PID namespace, so that a process of another machine sharing
the folder is never taken for a dead local one), and the next save of the same
destination removes those whose process is gone, with a
:class:`StaleTempFileWarning` naming them. A temporary file of a live process, of
another machine, or of an older jaxskel (named ``.<name>.<12 hex>.tmp<suffix>``,
without its owner: reported, not removed) is never touched.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import socket
import uuid
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from .._errors import InputError

__all__ = ["StaleTempFileWarning", "atomic_output", "stale_temp_files", "temp_path"]


class StaleTempFileWarning(UserWarning):
    """Temporary files of an interrupted save were found next to a destination (and
    removed where their process is gone)."""


def _origin() -> str:
    """8 hex digits naming this machine and PID namespace (a container has its own)."""
    try:
        namespace = os.readlink("/proc/self/ns/pid")
    except OSError:
        namespace = ""
    return hashlib.sha1(f"{socket.gethostname()}|{namespace}".encode()).hexdigest()[:8]


_ORIGIN = _origin()
_TEMP = r"\.jaxskel-(?P<pid>[0-9]+)-(?P<origin>[0-9a-f]{8})-[0-9a-f]{8}\.tmp"
_LEGACY = r"\.[0-9a-f]{12}\.tmp"


def temp_path(target: Path, suffix: str | None = None) -> Path:
    """A fresh temporary sibling of ``target`` owned by this process (module docstring)."""
    tmp_suffix = target.suffix if suffix is None else suffix
    tag = f"jaxskel-{os.getpid()}-{_ORIGIN}-{uuid.uuid4().hex[:8]}"
    return target.with_name(f".{target.name}.{tag}.tmp{tmp_suffix}")


def _alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine runs (in doubt: yes)."""
    if pid == os.getpid():
        return True
    if os.name == "nt":  # os.kill(pid, 0) would send CTRL_C_EVENT there: never remove
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it runs, as another user
        return True
    return True


def stale_temp_files(target: str | os.PathLike[str]) -> tuple[list[Path], list[Path]]:
    """Temporary files of earlier saves of ``target`` in its folder: ``(dead, legacy)``.

    ``dead``: those of a process of this machine that no longer runs (safe to remove);
    ``legacy``: those of an older jaxskel, whose owner is unknown. Temporary files of
    live processes and of other machines are in neither list.
    """
    target = Path(target)
    pattern = re.compile(re.escape(f".{target.name}") + f"(?:{_TEMP}|{_LEGACY})" + ".*")
    dead: list[Path] = []
    legacy: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return dead, legacy
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None:
            continue
        if match["pid"] is None:
            legacy.append(Path(entry.path))
        elif match["origin"] == _ORIGIN and not _alive(int(match["pid"])):
            dead.append(Path(entry.path))
    return sorted(dead), sorted(legacy)


def _remove_stale(target: Path) -> None:
    """Remove the temporary files of ``target`` that dead processes left (and those this
    process could not remove before); warn about them and about temporary files of an
    older jaxskel (left in place)."""
    dead, legacy = stale_temp_files(target)
    mine = f".{target.name}.jaxskel-{os.getpid()}-"
    dead += [p for p in list(_ABANDONED) if p.parent == target.parent and p.name.startswith(mine)]
    removed, kept = [], []
    for path in dead:
        _ABANDONED.discard(path)
        try:
            path.unlink()
        except FileNotFoundError:  # another process cleaned it meanwhile
            continue
        except OSError as exc:
            kept.append(f"{path.name} ({exc.strerror or exc})")
            continue
        removed.append(path)
    if removed:
        warnings.warn(
            f"removed {len(removed)} temporary file(s) of an earlier, interrupted save of {target.name} in "
            f"{target.parent}: {', '.join(p.name for p in removed)}",
            StaleTempFileWarning,
            stacklevel=4,
        )
    if kept:
        warnings.warn(
            f"cannot remove {len(kept)} temporary file(s) left in {target.parent} by an interrupted save of "
            f"{target.name}: {', '.join(kept)}; delete them by hand",
            StaleTempFileWarning,
            stacklevel=4,
        )
    if legacy:
        warnings.warn(
            f"{target.parent} holds {len(legacy)} temporary file(s) of an interrupted save of {target.name} "
            f"whose owner jaxskel cannot tell: {', '.join(p.name for p in legacy)}; delete them if no "
            "program is writing there",
            StaleTempFileWarning,
            stacklevel=4,
        )


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
    is left exactly as it was. Before the body runs, temporary files of earlier
    saves of ``path`` whose process has died are removed (module docstring).

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
    _remove_stale(target)
    # A hidden sibling named after this process: same directory (so the final rename is
    # atomic) and not pre-created, so writers create it with the user's default mode.
    tmp = temp_path(target, suffix)
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
        _discard(tmp)


#: This process's temporary files it could not remove (retried by the next save into
#: their folder: the process is alive, so the stale-file sweep would leave them).
_ABANDONED: set[Path] = set()


def _discard(tmp: Path) -> None:
    """Remove ``tmp``; where that fails, warn (the save itself stands) and retry later."""
    try:
        tmp.unlink(missing_ok=True)
    except OSError as exc:
        _ABANDONED.add(tmp)
        warnings.warn(
            f"cannot remove the temporary file {tmp} ({exc.strerror or exc}); the next save into its folder "
            "tries again",
            StaleTempFileWarning,
            stacklevel=4,
        )


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
