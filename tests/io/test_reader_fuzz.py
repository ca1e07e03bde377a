"""Fuzz of the readers (issue 45): damaged C3D, TRC, CSV and HDF5 files either load or
raise jaxskel's typed error; never another exception, never a hang, never much memory.

A seeded mutation loop over small valid files of each format: random truncation, bit
flips, overwritten, inserted and deleted bytes, and absurd header values (frame,
point and analog counts, scale factors, rates, label lengths and counts, parameter
records, dataset shapes and types). Every mutant is loaded in a worker process that
limits its address space (so a runaway allocation is a ``MemoryError``, reported, not
the machine's memory), times each load out (``SIGALRM``; the parent's timeout catches
a hang in C code) and reports how far its peak memory grew. A worker that dies (a
crash in a parsing library) is restarted after the file that killed it, which is
reported. The count is fixed and seeded; the whole test takes seconds on one core.
"""

from __future__ import annotations

import json
import math
import os
import random
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import ezc3d
import h5py
import numpy as np
import pytest

from jaxskel import Trial, save_trial

REPO = Path(__file__).resolve().parents[2]
# The children read /proc/self/status and limit their address space (Linux).
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and RLIMIT_AS (Linux)")
SEED = 45
#: Mutants per base file (five bases).
PER_BASE = 150
#: Seconds one load may take.
LOAD_TIMEOUT_S = 5
#: Address space a worker may add to what it holds after its imports.
ADDRESS_ROOM_MB = 768
#: Peak memory one load of a small file may add.
MAX_GROWTH_MB = 200

_WORKER = textwrap.dedent(
    """
    import json, resource, signal, sys, traceback, warnings
    warnings.simplefilter("ignore")
    import jaxskel
    import jaxskel.io._c3d, jaxskel.io._csv, jaxskel.io._h5, jaxskel.io._trc
    from jaxskel import JaxskelError
    paths = json.load(open(sys.argv[1]))
    jaxskel.load(sys.argv[2])  # every reader's imports, before the limit
    vm = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmSize:")][0]
    room = vm + int(sys.argv[3]) * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (room, room))

    class Hang(Exception):
        pass

    def alarm(*_):
        raise Hang()

    signal.signal(signal.SIGALRM, alarm)
    for index, path in paths:
        print(json.dumps({"start": index}), flush=True)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        signal.alarm(int(sys.argv[4]))
        try:
            trial = jaxskel.load(path)
            out = {"outcome": "loaded", "shape": list(trial.positions.shape)}
        except JaxskelError as exc:
            out = {"outcome": "typed", "error": type(exc).__name__, "message": str(exc)[:300]}
        except Hang:
            out = {"outcome": "hang"}
        except BaseException as exc:
            out = {"outcome": "other", "error": type(exc).__name__, "message": str(exc)[:300],
                   "trace": traceback.format_exc()[-1500:]}
        finally:
            signal.alarm(0)
        out["index"] = index
        out["growth_mb"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
        print(json.dumps(out), flush=True)
    """
)

# Values no header should hold, as text.
_ABSURD_TEXT = [
    "0", "-1", "4200000", "99999999999999999999", "1e308", "-1e308", "1e400", "nan", "inf", "-inf", "", "x",
    "1_0", "0x10", "\u0663", "2.5", "-0", "1e-320", "L" * 100_000, "\t" * 500, ",", " ",
]
_ABSURD_U16 = [0, 1, 2, 3, 255, 256, 0x7FFF, 0x8000, 0xFFFE, 0xFFFF]
_ABSURD_F32 = [0.0, -0.0, -1.0, 1.0, 1e30, -1e30, 1e-30, math.nan, math.inf, -math.inf, 4.2e6]


# ------------------------------------------------------------------ the valid bases
def _trial(n_frames=30, n_markers=6, seed=0) -> Trial:
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 0.3, (n_frames, n_markers, 3)) + [0.0, 0.0, 1.0]
    x[3:6, 1] = np.nan  # a gap: empty cells, C3D residuals
    return Trial(x, [f"M{i}" for i in range(n_markers)], 100.0, up_axis="z", metadata={"first_frame": 3})


def _c3d_with_analogs(path: Path) -> Path:
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ("S:LASI", "S:RASI", "S:LFEO", "*1", "C7")
    data = np.ones((4, 5, 20))
    data[:3] = np.random.default_rng(1).normal(500, 200, (3, 5, 20))
    c3d["data"]["points"] = data
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = [1000.0]
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = ("F1", "F2")
    c3d["data"]["analogs"] = np.random.default_rng(2).normal(0, 1, (1, 2, 200))
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    c3d.add_parameter("POINT", "ANGLES", ["S:LFEO"])
    c3d.write(str(path))
    return path


def _cortex_csv(path: Path, trial: Trial) -> Path:
    rows = [f"Frame number,{trial.n_frames}", "First frame,1", "Point frequency,100", "Analog frequency,1000", "",
            "Time," + ",,,".join(trial.labels) + ",,", "s" + ",mm,mm,mm" * trial.n_markers,
            ",X,Y,Z" * trial.n_markers]
    for f in range(trial.n_frames):
        cells = ["" if np.isnan(v) else f"{v:.4f}" for v in trial.positions[f].ravel() * 1000]
        rows.append(f"{f / 100:.2f}," + ",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    return path


# ------------------------------------------------------------------ mutations
def _truncate(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    at = rng.randrange(len(data))
    return data[:at], f"truncated at {at}"


def _flip_bits(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    out = bytearray(data)
    where = [rng.randrange(len(out) * 8) for _ in range(rng.choice((1, 2, 4, 16)))]
    for bit in where:
        out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out), f"bits {where[:4]} flipped"


def _overwrite(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    at, n = rng.randrange(len(data)), rng.choice((1, 2, 4, 8, 64))
    junk = rng.choice((b"\xff", b"\x00", b"\x7f", bytes([rng.randrange(256)]))) * n
    return data[:at] + junk + data[at + n :], f"{n} bytes at {at} overwritten"


def _splice(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    at, n = rng.randrange(len(data)), rng.choice((1, 3, 100, 513))
    if rng.random() < 0.5:
        return data[:at] + data[at + n :], f"{n} bytes at {at} deleted"
    return data[:at] + data[at : at + n] + data[at:], f"{n} bytes at {at} repeated"


_BYTE_MUTATIONS = (_truncate, _flip_bits, _overwrite, _splice)


def _text_absurd(rng: random.Random, data: bytes, header_lines: int, sep: str) -> tuple[bytes, str]:
    """An absurd value in a header cell or a data cell, or a line deleted or repeated."""
    lines = data.decode("latin-1").split("\n")
    kind = rng.random()
    if kind < 0.15:
        k = rng.randrange(len(lines))
        what = rng.choice(("deleted", "repeated"))
        lines[k : k + 1] = [] if what == "deleted" else [lines[k]] * rng.choice((2, 5000))
        return "\n".join(lines).encode("latin-1", "replace"), f"line {k + 1} {what}"
    k = rng.randrange(header_lines) if kind < 0.75 else rng.randrange(header_lines, len(lines) - 1)
    cells = lines[k].split(sep)
    c = rng.randrange(len(cells))
    value = rng.choice(_ABSURD_TEXT)
    cells[c] = value
    lines[k] = sep.join(cells)
    return "\n".join(lines).encode("utf-8"), f"line {k + 1} cell {c + 1} = {value[:12]!r}"


def _c3d_records(data: bytes) -> list[tuple[str, int, int, int, int]]:
    """(name, record start, offset field, data type byte, data start) of each parameter
    of an Intel C3D; stops at anything damaged."""
    start = (data[0] - 1) * 512
    pos, out = start + 4, []
    while pos + 4 <= len(data):
        name_len, group = struct.unpack("bb", data[pos : pos + 2])
        if name_len == 0:
            break
        field = pos + 2 + abs(name_len)
        (offset,) = struct.unpack("<h", data[field : field + 2])
        if group > 0:
            body = field + 2
            n_dims = data[body + 1]
            out.append((data[pos + 2 : field].decode("latin-1"), pos, field, body, body + 2 + n_dims))
        if offset <= 0:
            break
        pos = field + offset
    return out


def _c3d_absurd(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """An absurd header word, scale, parameter value, data type, dimension or record offset."""
    out = bytearray(data)
    if rng.random() < 0.35:
        word = rng.choice((2, 4, 6, 8, 16, 18, 20))
        value = rng.choice(_ABSURD_U16)
        out[word : word + 2] = struct.pack("<H", value)
        if rng.random() < 0.3:
            out[12:16] = struct.pack("<f", rng.choice(_ABSURD_F32))
        return bytes(out), f"header byte {word} = {value}"
    name, record, field, body, values = rng.choice(_c3d_records(data))
    kind = rng.randrange(6)
    if kind == 0:  # the value: an absurd number of its type
        dtype = struct.unpack("b", out[body : body + 1])[0]
        if dtype == 4:
            value = rng.choice(_ABSURD_F32)
            out[values : values + 4] = struct.pack("<f", value)
        else:
            value = rng.choice(_ABSURD_U16)
            out[values : values + 2] = struct.pack("<H", value)
        return bytes(out), f"parameter {name} value = {value}"
    if kind == 1:
        value = rng.choice((-128, -2, -1, 0, 3, 5, 8, 127))
        out[body] = value & 0xFF
        return bytes(out), f"parameter {name} data type = {value}"
    if kind == 2:
        value = rng.choice((0, 1, 7, 8, 255))
        out[body + 1] = value
        return bytes(out), f"parameter {name} dimension count = {value}"
    if kind == 3:
        dims = [rng.choice((0, 1, 2, 50, 255)) for _ in range(values - body - 2)]
        out[body + 2 : values] = bytes(dims)
        return bytes(out), f"parameter {name} dimensions = {dims}"
    if kind == 4:  # a parameter readers need goes missing
        out[record + 2] = ord("Q")
        return bytes(out), f"parameter {name} renamed"
    value = rng.choice((-32768, -1, 0, 1, 32767))
    out[field : field + 2] = struct.pack("<h", value)
    return bytes(out), f"parameter {name} record offset = {value}"


def _h5_absurd(rng: random.Random, base: Path, path: Path) -> str:
    """A trial file rewritten with an absurd shape, type or attribute."""
    path.write_bytes(base.read_bytes())
    with h5py.File(base, "r") as src:
        positions, labels = src["positions"][()], src["labels"][()]
    kind = rng.randrange(10)
    if kind == 9:  # a byte of the global heap (the labels' and text attributes' strings)
        data = bytearray(base.read_bytes())
        at = data.find(b"GCOL") + rng.randrange(16, 320)
        data[at] = rng.choice((0, 1, 2, 0x80, 0xFF))
        path.write_bytes(bytes(data))
        return f"global heap byte {at} = {data[at]}"
    with h5py.File(path, "a") as h5:
        if kind == 0:  # shape far beyond the data written
            n = rng.choice((4_200_000, 2**31, 2**40))
            del h5["positions"]
            h5.create_dataset("positions", data=positions, maxshape=(None, None, 3), chunks=True, compression="gzip")
            h5["positions"].resize((n, positions.shape[1], 3))
            return f"positions resized to {n} frames"
        if kind == 1:
            n = rng.choice((10**6, 10**9))
            del h5["labels"]
            h5.create_dataset("labels", shape=(n,), dtype=h5py.string_dtype(), chunks=True)
            return f"labels declared {n} long"
        if kind == 2:
            del h5["labels"]
            h5["labels"] = np.array([b"M" * rng.choice((2000, 10**6))] * len(labels))
            return "long fixed-width labels"
        if kind == 3:
            del h5["positions"]
            with np.errstate(all="ignore"):  # the casts overflow on purpose
                odd = (
                    positions[..., 0], positions.astype("f2"), positions.astype("i1"), np.zeros((0, 6, 3)),
                    np.full(positions.shape, 1e308) * 10, positions.reshape(-1, 6, 3, 1), np.array([b"x"] * 4),
                )
            h5["positions"] = rng.choice(odd)
            return "positions of another shape or type"
        if kind == 4:
            key = rng.choice(("rate", "up_axis", "jaxskel_trial_version", "metadata", "source"))
            value = rng.choice((math.nan, -1.0, 1e308, 0, 2**62, "abc", "", np.zeros(3), b"\xff\xfe"))
            h5.attrs[key] = value
            return f"attribute {key} = {value!r:.20}"
        if kind == 5:
            value = rng.choice(('[]', '{"first_frame": "x"}', '{"first_frame": 1e400}', '{"first_frame": null}',
                                '{"dropped_labels": 5, "dropped_reasons": []}', "{" * 100_000, '"x"'))
            h5.attrs["metadata"] = value
            return f"metadata = {value[:30]!r}"
        if kind == 6:
            del h5[rng.choice(("positions", "labels"))]
            return "a dataset removed"
        if kind == 7:
            del h5["labels"]
            h5["labels"] = rng.choice((np.arange(6), np.array([b"A", b"A", b"B", b"C", b"D", b"E"]), np.array([b""] * 6)))
            return "labels of another type, or repeated"
        for key in list(h5.attrs):
            if rng.random() < 0.5:
                del h5.attrs[key]
        return "attributes removed"


def _absurd(base: str, rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """An absurd header value of the format of ``base`` (not HDF5: :func:`_h5_absurd`)."""
    if base.startswith("c3d"):
        return _c3d_absurd(rng, data)
    if base == "trc":
        return _text_absurd(rng, data, 5, "\t")
    return _text_absurd(rng, data, 8, ",")


# ------------------------------------------------------------------ the test
@pytest.fixture(scope="module")
def mutants(tmp_path_factory) -> list[tuple[Path, str]]:
    root = tmp_path_factory.mktemp("fuzz")
    trial = _trial()
    bases = {
        "c3d": save_trial(trial, root / "base.c3d"),
        "c3d_analogs": _c3d_with_analogs(root / "analogs.c3d"),
        "trc": save_trial(trial, root / "base.trc"),
        "csv": _cortex_csv(root / "base.csv", trial),
        "h5": save_trial(trial, root / "base.h5"),
    }
    rng = random.Random(SEED)
    out: list[tuple[Path, str]] = [(p, f"{name}: unchanged") for name, p in bases.items()]
    for name, base in bases.items():
        data = base.read_bytes()
        suffix = base.suffix
        for k in range(PER_BASE):
            path = root / f"{name}_{k}{suffix}"
            if k % 2 == 0 and name == "h5":
                how = _h5_absurd(rng, base, path)
            else:
                mutant, how = _absurd(name, rng, data) if k % 2 == 0 else rng.choice(_BYTE_MUTATIONS)(rng, data)
                path.write_bytes(mutant)
            out.append((path, f"{name} #{k}: {how}"))
    return out


def _run_workers(mutants: list[tuple[Path, str]], warm: Path) -> dict[int, dict]:
    """Load every mutant in worker processes; the outcome of each, by index."""
    results: dict[int, dict] = {}
    todo = list(range(len(mutants)))
    work = warm.parent / "paths.json"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    while todo:
        work.write_text(json.dumps([(i, str(mutants[i][0])) for i in todo]))
        started = None
        try:
            done = subprocess.run(
                [sys.executable, "-c", _WORKER, str(work), str(warm), str(ADDRESS_ROOM_MB), str(LOAD_TIMEOUT_S)],
                capture_output=True, text=True, cwd=REPO, env=env, check=False,
                timeout=60 + 2 * LOAD_TIMEOUT_S + 0.5 * len(todo),
            )
            stdout, died = done.stdout, f"worker exited with {done.returncode}: {done.stderr[-800:]}"
        except subprocess.TimeoutExpired as exc:
            stdout = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
            died = "hang: the worker did not answer in time"
        for line in stdout.splitlines():
            record = json.loads(line)
            if "start" in record:
                started = record["start"]
            else:
                results[record["index"]] = record
        left = [i for i in todo if i not in results]
        if left and started is not None and started in left:  # the file that killed the worker
            results[started] = {"outcome": "died", "message": died, "index": started}
            left.remove(started)
        elif left:
            pytest.fail(f"the fuzz worker failed before loading anything: {died}")
        todo = left
    return results


def test_damaged_files_load_or_raise_a_typed_error_in_bounded_time_and_memory(mutants, tmp_path):
    warm = save_trial(_trial(), tmp_path / "warm.h5")
    results = _run_workers(mutants, warm)
    bad = []
    for i, (path, how) in enumerate(mutants):
        r = results[i]
        if r["outcome"] not in ("loaded", "typed") or r.get("growth_mb", 0) > MAX_GROWTH_MB:
            bad.append(f"{how} ({path.name}): {r['outcome']} {r.get('error', '')}: {r.get('message', '')} "
                       f"[+{r.get('growth_mb', 0):.0f} MB] {r.get('trace', '')}")
    assert not bad, f"{len(bad)} of {len(mutants)} damaged files:\n" + "\n".join(bad)
    outcomes = [results[i]["outcome"] for i in range(len(mutants))]
    # The loop exercises both sides: some mutants still load, most are refused.
    assert outcomes[:5] == ["loaded"] * 5
    assert 0.1 < outcomes.count("loaded") / len(outcomes) < 0.9
