"""Saving under faults (issue 45, item 8 and the fault-injection test of saving).

A save goes: open a temporary file next to the destination, write it, fsync it, put it
in place (``os.link`` for a new file, ``os.replace`` over an old one), remove the
temporary name. A crash at any of these steps, an exception in this process or a
``kill -9`` of a writing process, leaves the destination either the old file (or
absent) or the complete new one, byte for byte; a killed process's temporary file is
removed by the next save of the same destination, with a warning naming it, and
nothing else is touched: not the temporary file of a live process, nor one of
another machine, nor another destination's, nor any other file.
"""

import errno
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import warnings

import h5py
import numpy as np
import pytest

import jaxskel
from jaxskel.io import _atomic
from jaxskel.io._atomic import StaleTempFileWarning


def trial(seed: int) -> jaxskel.Trial:
    x = np.random.default_rng(seed).normal(size=(400, 4, 3))
    return jaxskel.Trial(x, ["a", "b", "c", "d"], 100.0)


OLD, NEW = trial(1), trial(2)


def hidden(folder: pathlib.Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def new_bytes(tmp_path: pathlib.Path, name: str) -> bytes:
    """The bytes a complete save of NEW to ``name`` gives (a TRC names its file)."""
    ref = tmp_path / "reference"
    ref.mkdir(exist_ok=True)
    return jaxskel.save_trial(NEW, ref / name).read_bytes()


def fault(monkeypatch: pytest.MonkeyPatch, step: str, fmt: str) -> type[BaseException]:
    """Make ``step`` of the next save raise; returns what the save then raises."""
    if step == "open":
        if fmt == "h5":
            def refuse(*a, **k):
                raise OSError(errno.EMFILE, "Too many open files")
            monkeypatch.setattr(h5py, "File", refuse)
        else:
            def refuse(self, *a, **k):
                raise OSError(errno.ENOSPC, "No space left on device")
            monkeypatch.setattr(pathlib.Path, "write_text", refuse)
        return OSError
    if step == "write":  # half the data is on disk, then the disk is full
        if fmt == "h5":
            real = h5py.Group.create_dataset

            def create(self, *a, **k):
                real(self, *a, **k)
                raise OSError(errno.ENOSPC, "No space left on device")
            monkeypatch.setattr(h5py.Group, "create_dataset", create)
        else:
            real_write = pathlib.Path.write_text

            def half(self, text, *a, **k):
                real_write(self, text[: len(text) // 2], *a, **k)
                raise OSError(errno.ENOSPC, "No space left on device")
            monkeypatch.setattr(pathlib.Path, "write_text", half)
        return OSError
    if step == "fsync":
        def eio(fd):
            raise OSError(errno.EIO, "Input/output error")
        monkeypatch.setattr(os, "fsync", eio)
        return OSError
    if step == "publish":
        def denied(*a, **k):
            raise PermissionError(errno.EACCES, "Permission denied")
        monkeypatch.setattr(os, "replace", denied)
        monkeypatch.setattr(os, "link", denied)
        return PermissionError
    raise AssertionError(step)


@pytest.mark.parametrize("fmt", ["h5", "trc"])
@pytest.mark.parametrize("step", ["open", "write", "fsync", "publish"])
@pytest.mark.parametrize("existing", [True, False], ids=["over-old", "new-file"])
def test_an_error_at_any_step_leaves_the_old_file_and_no_temporary_file(tmp_path, monkeypatch, fmt, step, existing):
    dest = tmp_path / f"walk.{fmt}"
    expected_new = new_bytes(tmp_path, dest.name)
    old = jaxskel.save_trial(OLD, dest).read_bytes() if existing else None
    with monkeypatch.context() as patch:
        raised = fault(patch, step, fmt)
        with pytest.raises(raised):
            jaxskel.save_trial(NEW, dest, overwrite=existing)
    assert (dest.read_bytes() if dest.exists() else None) == old  # the old file, or still none
    assert hidden(tmp_path) == []
    jaxskel.save_trial(NEW, dest, overwrite=True)  # the next run
    assert dest.read_bytes() == expected_new and hidden(tmp_path) == []


def test_a_temporary_file_that_cannot_be_removed_is_removed_by_the_next_save(tmp_path, monkeypatch):
    """A new file is put in place by a hard link, then its temporary name is removed. The
    save stands when only that removal fails (a save over an old file renames the
    temporary file, so nothing is left to remove); it says so, and the next save of the
    destination removes the name (before: the save raised although the file was written)."""
    dest = tmp_path / "walk.h5"
    expected_new = new_bytes(tmp_path, dest.name)
    real_unlink = pathlib.Path.unlink

    def unlink(self, *a, **k):
        if ".jaxskel-" in self.name and self.exists():
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_unlink(self, *a, **k)

    with monkeypatch.context() as patch:
        patch.setattr(pathlib.Path, "unlink", unlink)
        with pytest.warns(StaleTempFileWarning, match=r"cannot remove the temporary file .*walk\.h5\.jaxskel-"):
            jaxskel.save_trial(NEW, dest)
    assert dest.read_bytes() == expected_new
    (left,) = hidden(tmp_path)
    assert left.startswith(f".walk.h5.jaxskel-{os.getpid()}-"), hidden(tmp_path)
    with pytest.warns(StaleTempFileWarning, match=rf"removed 1 temporary file\(s\) of an earlier, interrupted save "
                      rf"of walk\.h5 in {tmp_path}: {left}"):
        jaxskel.save_trial(NEW, dest, overwrite=True)
    assert hidden(tmp_path) == [] and dest.read_bytes() == expected_new


CHILD = textwrap.dedent(
    """
    import os, pathlib, signal, sys
    import h5py, numpy as np
    import jaxskel

    step, fmt, dest, overwrite = sys.argv[1], sys.argv[2], pathlib.Path(sys.argv[3]), sys.argv[4] == "1"
    x = np.random.default_rng(2).normal(size=(400, 4, 3))
    new = jaxskel.Trial(x, ["a", "b", "c", "d"], 100.0)

    def die(*a, **k):
        os.kill(os.getpid(), signal.SIGKILL)

    if step == "open":  # the temporary file exists, nothing is in it yet
        real_file = h5py.File
        def opened(*a, **k):
            real_file(*a, **k).close()
            die()
        h5py.File = opened
    elif step == "write":  # part of the data is on disk
        if fmt == "h5":
            real_create = h5py.Group.create_dataset
            def create(self, *a, **k):
                real_create(self, *a, **k)
                self.file.flush()
                die()
            h5py.Group.create_dataset = create
        else:
            real_write = pathlib.Path.write_text
            def half(self, text, *a, **k):
                real_write(self, text[: len(text) // 2], *a, **k)
                die()
            pathlib.Path.write_text = half
    elif step == "fsync":
        os.fsync = die
    elif step == "publish":  # written and flushed, not yet in place
        os.replace = os.link = die
    elif step == "cleanup":  # in place under its name, the temporary name not yet removed
        real_link = os.link
        def link(a, b, *r, **k):
            real_link(a, b, *r, **k)
            die()
        os.link = link
    jaxskel.save_trial(new, dest, overwrite=overwrite)
    print("the save finished: no kill point was reached")
    """
)


@pytest.mark.parametrize(
    ("step", "fmt", "existing"),
    [("open", "h5", True), ("write", "h5", True), ("write", "trc", False), ("fsync", "trc", True),
     ("publish", "h5", True), ("publish", "trc", False), ("cleanup", "h5", False)],
)
def test_kill_9_at_any_step_leaves_old_or_new_and_the_next_save_removes_its_temporary_file(
    tmp_path, step, fmt, existing
):
    dest = tmp_path / f"walk.{fmt}"
    expected_new = new_bytes(tmp_path, dest.name)
    old = jaxskel.save_trial(OLD, dest).read_bytes() if existing else None
    child = subprocess.run(
        [sys.executable, "-c", CHILD, step, fmt, str(dest), "1" if existing else "0"],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert child.returncode == -signal.SIGKILL, child.stdout + child.stderr
    now = dest.read_bytes() if dest.exists() else None
    assert now == (expected_new if step == "cleanup" else old)  # never a partial file
    (left,) = hidden(tmp_path)  # the killed process's temporary file, named after it
    assert left.startswith(f".walk.{fmt}.jaxskel-") and left.endswith(f".tmp.{fmt}"), left
    assert int(left.split("-")[1]) == child_pid(left)
    with pytest.warns(StaleTempFileWarning) as caught:
        jaxskel.save_trial(NEW, dest, overwrite=True)
    (said,) = [str(w.message) for w in caught if issubclass(w.category, StaleTempFileWarning)]
    assert said == f"removed 1 temporary file(s) of an earlier, interrupted save of walk.{fmt} in {tmp_path}: {left}"
    assert hidden(tmp_path) == [] and dest.read_bytes() == expected_new


def child_pid(name: str) -> int:
    """The process id in a temporary file's name; that process is gone."""
    pid = int(name.split(".jaxskel-")[1].split("-")[0])
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    return pid


def test_the_sweep_touches_only_dead_processes_temporary_files_of_the_destination(tmp_path):
    """Live process, other machine, other destination, an older jaxskel's temporary file
    (reported, not removed), any other file: all left alone."""
    dest = tmp_path / "walk.trc"
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    dead = int(gone.stdout)
    origin = _atomic._ORIGIN
    other_origin = "0" * 8 if origin != "0" * 8 else "1" * 8
    files = {
        "dead": f".walk.trc.jaxskel-{dead}-{origin}-0badf00d.tmp.trc",
        "live": f".walk.trc.jaxskel-{os.getpid()}-{origin}-0badf00d.tmp.trc",
        "parent": f".walk.trc.jaxskel-{os.getppid()}-{origin}-0badf00d.tmp.trc",
        "other machine": f".walk.trc.jaxskel-{dead}-{other_origin}-0badf00d.tmp.trc",
        "other destination": f".run.trc.jaxskel-{dead}-{origin}-0badf00d.tmp.trc",
        "older jaxskel": ".walk.trc.0123456789ab.tmp.trc",
        "someone's notes": ".walk.trc.notes",
        "a recording": "walk2.trc",
    }
    for name in files.values():
        (tmp_path / name).write_text("partial")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jaxskel.save_trial(NEW, dest)
    said = [str(w.message) for w in caught if issubclass(w.category, StaleTempFileWarning)]
    assert said == [
        f"removed 1 temporary file(s) of an earlier, interrupted save of walk.trc in {tmp_path}: {files['dead']}",
        (f"{tmp_path} holds 1 temporary file(s) of an interrupted save of walk.trc whose owner jaxskel cannot "
         f"tell: {files['older jaxskel']}; delete them if no program is writing there"),
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [*(v for k, v in files.items() if k != "dead"), "walk.trc"]
    )
    for key, name in files.items():
        if key != "dead":
            assert (tmp_path / name).read_text() == "partial", key


def test_a_temporary_name_says_whose_it_is(tmp_path):
    tmp = _atomic.temp_path(tmp_path / "walk.h5")
    assert tmp.parent == tmp_path and tmp.name.startswith(f".walk.h5.jaxskel-{os.getpid()}-{_atomic._ORIGIN}-")
    assert tmp.name.endswith(".tmp.h5") and tmp != _atomic.temp_path(tmp_path / "walk.h5")
