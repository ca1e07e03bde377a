"""Readers allocate what a file holds, not what it declares (issue 45, item 3).

An 8 KB HDF5 trial declaring 4.2 million frames made a load allocate 3.1 GB (4.3 GB peak
here), and a 50 MB label 2.9 GB in a fit (every label copied into fixed-width arrays as
wide as the longest). The large cases run in a child process whose peak memory is
measured (``ru_maxrss``) under an address-space limit, so that a regression fails the
test instead of taking the machine's memory.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from jaxskel import InputError, Trial, load, save_trial
from jaxskel.io import _bounds

REPO = Path(__file__).resolve().parents[2]
# The children read /proc/self/status and limit their address space (Linux).
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and RLIMIT_AS (Linux)")

# The child loads one small file first (imports, lazy modules), then limits its address
# space to what it uses plus LIMIT_MB, then loads the file under test and reports.
_CHILD = textwrap.dedent(
    """
    import json, resource, sys, warnings
    warnings.simplefilter("ignore")
    import jaxskel
    jaxskel.load(sys.argv[2])
    def status(field):
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    limit = status("VmSize") + int(sys.argv[3]) * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        trial = jaxskel.load(sys.argv[1])
        out = {"loaded": repr(trial)}
    except Exception as exc:
        out = {"error": type(exc).__name__, "message": str(exc)}
    out["peak_growth_mb"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    print(json.dumps(out))
    """
)
LIMIT_MB = 1024
_ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _load_in_child(path: Path, warm: Path) -> dict:
    """Load ``path`` in a fresh process with at most LIMIT_MB more address space; its outcome."""
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), str(warm), str(LIMIT_MB)],
        capture_output=True, text=True, timeout=120, cwd=REPO, env=_ENV, check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _body(n_frames=50, n_markers=14, seed=0) -> Trial:
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 0.3, (n_frames, n_markers, 3)) + [0.0, 0.0, 1.0]
    return Trial(x, [f"M{i}" for i in range(n_markers)], 100.0, up_axis="z")


@pytest.fixture(scope="module")
def warm(tmp_path_factory) -> Path:
    return save_trial(_body(), tmp_path_factory.mktemp("warm") / "warm.h5")


def _declaring_h5(path: Path, n_frames: int) -> Path:
    """A jaxskel trial file whose positions declare ``n_frames`` frames but hold none."""
    with h5py.File(path, "w") as h5:
        h5.attrs.update({"jaxskel_trial_version": 1, "rate": 100.0, "up_axis": "z", "units": "m", "metadata": "{}"})
        h5.create_dataset("positions", shape=(n_frames, 14, 3), dtype="f8", chunks=(1024, 14, 3),
                          compression="gzip")
        h5.create_dataset("labels", data=[f"M{i}" for i in range(14)], dtype=h5py.string_dtype())
    return path


def test_h5_declaring_millions_of_frames_is_refused_without_allocating_them(tmp_path, warm):
    path = _declaring_h5(tmp_path / "declares.h5", 4_200_000)
    assert path.stat().st_size < 10 * 1024
    out = _load_in_child(path, warm)
    assert out.get("error") == "InputError", out
    assert "/positions declares 4200000 frames x 14 markers (1.3 GB) but the file holds no data for it" in out["message"]
    assert out["peak_growth_mb"] < 50, out


def test_h5_compressed_positions_may_expand_only_as_far_as_gzip_can(tmp_path, warm):
    """Written data that compresses well (a trial that is mostly gaps) still loads; a
    dataset claiming more than gzip's 1:1032 of what it stores does not."""
    gappy = _body(n_frames=4000)
    x = np.full(gappy.positions.shape, np.nan)
    x[:10] = gappy.positions[:10]
    path = save_trial(gappy.replace(positions=x), tmp_path / "gappy.h5")
    assert load(path).n_frames == 4000
    with h5py.File(path, "a") as h5:  # grow the dataset's shape without writing its chunks
        data = h5["positions"][()]
        del h5["positions"]
        h5.create_dataset("positions", data=data, maxshape=(None, 14, 3), chunks=(1000, 14, 3), compression="gzip")
        h5["positions"].resize((40_000_000, 14, 3))
    out = _load_in_child(path, warm)
    assert out.get("error") == "InputError", out
    assert re.search(r"declares 40000000 frames x 14 markers .* \(compressed: at most .* once expanded\)",
                     out["message"]), out


@pytest.mark.parametrize("suffix", [".h5", ".trc"])
def test_a_50_mb_label_is_refused_in_bounded_memory(tmp_path, warm, suffix):
    path = save_trial(_body(), tmp_path / f"label{suffix}")
    if suffix == ".trc":  # the name row: Frame#, Time, then a name every third cell
        lines = path.read_text().split("\n")
        lines[3] = lines[3].replace("\tM3\t", "\t" + "L" * 50_000_000 + "\t")
        path.write_text("\n".join(lines))
    else:
        with h5py.File(path, "a") as h5:
            labels = [f"M{i}" for i in range(14)]
            labels[3] = "L" * 50_000_000
            del h5["labels"]
            h5.create_dataset("labels", data=labels, dtype=h5py.string_dtype())
    assert path.stat().st_size > 50_000_000
    out = _load_in_child(path, warm)
    assert out.get("error") == "InputError", out
    assert re.search(r"label 4 (\('LLLLLLLLLLLLLLLLLLLL'...\) is 50000000 characters|is 50000000 bytes) long; a marker "
                     r"label has at most 1024 characters", out["message"]), out
    assert out["peak_growth_mb"] < 8 * 50, out  # the file's bytes, its text and lines: not the 2.9 GB of a fit


def test_a_trial_refuses_a_label_no_marker_has():
    labels = [f"M{i}" for i in range(14)]
    labels[3] = "L" * 2000
    with pytest.raises(InputError, match=r"marker label 4 \('LLLLLLLLLLLLLLLLLLLL'...\) is 2000 characters long; "
                                         r"labels have at most 1024"):
        Trial(_body().positions, labels, 100.0)


def test_a_huge_cell_in_a_text_table_is_a_bad_number_not_a_huge_array(tmp_path, warm):
    """The table was parsed through a fixed-width text array as wide as its longest cell:
    one 1 MB cell in a 200-row file asked for 35 GB."""
    path = save_trial(_body(n_frames=200), tmp_path / "cell.trc")
    lines = path.read_text().splitlines()
    cells = lines[8].split("\t")
    cells[4] = "9" * 500_000 + "x" * 500_000
    lines[8] = "\t".join(cells)
    path.write_text("\n".join(lines) + "\n")
    out = _load_in_child(path, warm)
    assert out.get("error") == "InputError", out
    assert "line 9, column 5: '" + "9" * 40 + "'... is not a number" in out["message"]
    assert out["peak_growth_mb"] < 100, out


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".csv", ".h5"])
def test_every_reader_refuses_a_recording_larger_than_the_memory_available(tmp_path, monkeypatch, suffix):
    trial = _body(n_frames=1000)
    if suffix == ".csv":
        path = tmp_path / "cortex.csv"
        rows = ["Frame number,1000", "Point frequency,100", "", "Time," + ",,,".join(trial.labels) + ",,",
                "s" + ",mm,mm,mm" * 14, "" + ",X,Y,Z" * 14]
        rows += [f"{f / 100}," + ",".join(f"{v:.3f}" for v in trial.positions[f].ravel() * 1000) for f in range(1000)]
        path.write_text("\n".join(rows) + "\n")
    else:
        path = save_trial(trial, tmp_path / f"body{suffix}")
    assert load(path).n_frames == 1000
    # Room for the file's bytes, not for the positions a load makes of them.
    monkeypatch.setattr(_bounds, "available_memory", lambda: path.stat().st_size * 5)
    with pytest.raises(InputError, match=r"it (declares|holds) 1000 frames x 14 (markers|points).* which takes about "
                                         r".* of memory to read, but only .* is available; split the recording"):
        load(path)


def test_available_memory_follows_the_address_space_limit():
    """The child's limit lowers what the readers see as available."""
    code = (
        "import resource; from jaxskel.io._bounds import available_memory, describe_bytes\n"
        "free = available_memory()\n"
        "vm = [int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize:')][0]\n"
        "resource.setrlimit(resource.RLIMIT_AS, (vm + 300 * 2**20, vm + 300 * 2**20))\n"
        "print(free > 300 * 2**20, 250 * 2**20 < available_memory() <= 300 * 2**20)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO, check=False,
                          env=_ENV)
    assert done.stdout.split() == ["True", "True"], done.stderr[-2000:]

