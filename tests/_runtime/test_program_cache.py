"""Saved exported programs (jaxskel._runtime.program_cache): same answers as the jitted call,
one program per distinct trace, loaded (not re-traced) by a fresh process, read ahead by
the next process, robust to torn files, bounded, and out of the way of differentiation."""

import functools
import json
import os
import subprocess
import sys
import threading

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel import synth
from jaxskel._runtime import program_cache as _program_cache

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


class _Model(eqx.Module):
    weights: jax.Array
    offset: tuple
    power: int = eqx.field(static=True)


@functools.partial(jax.jit, static_argnames=("scale",))
def _program(model, x, *, scale):
    y = model.weights * x**model.power + model.offset[0] - model.offset[1]
    return {"value": scale * jnp.sum(jnp.sin(y)), "y": y}


def _model(power=2, n=4, dtype=jnp.float64):
    return _Model(jnp.linspace(0.5, 1.5, n, dtype=dtype), (jnp.asarray(0.25, dtype), jnp.ones(n, dtype)), power)


@pytest.fixture
def folder(tmp_path):
    _program_cache.set_directory(tmp_path)
    yield tmp_path
    _program_cache.set_directory(None)


def _saved(folder):
    return sorted(p.name for p in folder.glob("*.jaxexport"))


# The monkeypatches here: jax.export.export replaced by a guard that fails if called (an
# instrument: the only way to see that a program was loaded, not traced again) or by a
# failure (fault injection: a program XLA cannot export); the package's source digest, the
# traced libraries' versions and MAX_BYTES set for the test (an edit of the source, an
# upgrade of optimistix, a full folder: what a test cannot otherwise bring about).
def _no_export(monkeypatch):
    def refuse(*_, **__):
        raise AssertionError("traced and exported again")

    monkeypatch.setattr(jax.export, "export", refuse)


def test_without_a_directory_it_is_the_jitted_call(monkeypatch):
    _program_cache.set_directory(None)
    _no_export(monkeypatch)
    x = jnp.arange(4.0)
    out = _program_cache.call(_program, _model(), x, scale=2.0)
    assert float(out["value"]) == float(_program(_model(), x, scale=2.0)["value"])


def test_saved_program_gives_the_jitted_answer_and_serves_a_fresh_start(folder, monkeypatch):
    x = jnp.arange(4.0) / 3
    want = _program(_model(), x, scale=2.0)
    got = _program_cache.call(_program, _model(), x, scale=2.0)
    assert len(_saved(folder)) == 1 and _saved(folder)[0].startswith("_program-")
    np.testing.assert_array_equal(got["y"], want["y"])
    assert float(got["value"]) == float(want["value"])
    # A new process: nothing in memory, the program read from disk, never re-traced.
    _program_cache.set_directory(folder)
    _no_export(monkeypatch)
    again = _program_cache.call(_program, _model(), x, scale=2.0)
    assert float(again["value"]) == float(want["value"])
    # New values of the same shapes and types: the same program.
    other = _program_cache.call(_program, _model(), x + 1.0, scale=2.0)
    assert float(other["value"]) == float(_program(_model(), x + 1.0, scale=2.0)["value"])
    assert len(_saved(folder)) == 1


@pytest.mark.parametrize(
    "change",
    ["static argument", "static field", "shape", "dtype", "weak type", "tree", "source"],
)
def test_whatever_changes_the_trace_gets_its_own_program(folder, monkeypatch, change):
    x = jnp.arange(4.0)
    first = _program_cache.call(_program, _model(), x, scale=2.0)
    model, arg, scale = _model(), x, 2.0
    if change == "static argument":
        scale = 3.0
    elif change == "static field":
        model = _model(power=3)
    elif change == "shape":
        model, arg = _model(n=5), jnp.arange(5.0)
    elif change == "dtype":
        model, arg = _model(dtype=jnp.float32), x.astype(jnp.float32)
    elif change == "weak type":
        model = eqx.tree_at(lambda m: m.offset, model, (0.25, jnp.ones(4)))  # a Python float: weakly typed
    elif change == "tree":
        model = eqx.tree_at(lambda m: m.offset, model, [jnp.asarray(0.25), jnp.ones(4)])  # list, not tuple
    else:  # an edit of the package's source, seen by the next process
        monkeypatch.setattr(_program_cache, "_source_digest", lambda: "edited")
        _program_cache.set_directory(folder)
        assert float(_program_cache.call(_program, _model(), x, scale=2.0)["value"]) == float(first["value"])
    if change != "source":
        got = _program_cache.call(_program, model, arg, scale=scale)
        np.testing.assert_allclose(got["y"], _program(model, arg, scale=scale)["y"], rtol=1e-6)
    assert len(_saved(folder)) == 2


def test_each_64_bit_mode_gets_its_own_program(folder):
    """JAX's 64-bit mode is per thread and part of every trace (jaxskel turns it on for its
    own calls only): the same float32 arguments in the other mode are another program, in
    memory as on disk, never the one traced in the first mode."""
    model, x = _model(dtype=jnp.float32), jnp.arange(4.0, dtype=jnp.float32)
    in_64 = _program_cache.call(_program, model, x, scale=2.0)
    with jax.enable_x64(False):
        in_32 = _program_cache.call(_program, model, x, scale=2.0)
    assert len(_saved(folder)) == 2
    assert in_32["y"].dtype == in_64["y"].dtype == jnp.float32
    np.testing.assert_allclose(in_32["y"], in_64["y"], rtol=1e-6)


def test_torn_program_file_is_replaced(folder):
    x = jnp.arange(4.0)
    want = float(_program_cache.call(_program, _model(), x, scale=2.0)["value"])
    (name,) = _saved(folder)
    (folder / name).write_bytes(b"not a program")
    _program_cache.set_directory(folder)
    assert float(_program_cache.call(_program, _model(), x, scale=2.0)["value"]) == want
    assert _saved(folder) == [name] and (folder / name).stat().st_size > 1000


def test_gradients_bypass_the_saved_program(folder):
    def loss(x):
        return _program_cache.call(_program, _model(), x, scale=2.0)["value"]

    x = jnp.arange(4.0) / 3
    grad = jax.grad(loss)(x)
    np.testing.assert_allclose(grad, jax.grad(lambda v: _program(_model(), v, scale=2.0)["value"])(x), rtol=1e-12)
    assert _saved(folder) == []


def test_folder_is_bounded_oldest_use_first(folder, monkeypatch):
    x = jnp.arange(4.0)
    _program_cache.call(_program, _model(), x, scale=1.0)
    (first,) = _saved(folder)
    size = (folder / first).stat().st_size
    os.utime(folder / first, (1, 1))  # long unused
    monkeypatch.setattr(_program_cache, "MAX_BYTES", int(1.5 * size))
    _program_cache.call(_program, _model(), x, scale=2.0)
    assert len(_saved(folder)) == 1 and _saved(folder) != [first]


def _listed(folder):
    return [entry["file"] for entry in json.loads((folder / "recently-used.json").read_text())]


def _refuse_loading(monkeypatch):
    def refuse(path):
        raise AssertionError(f"{path.name} read again")

    monkeypatch.setattr(_program_cache, "_load", refuse)


def test_the_programs_a_process_used_are_read_ahead_by_the_next(folder, monkeypatch):
    """A process lists its programs in the order of their first call; the next one reads
    them in a background thread (read_ahead) and its calls take them from there: the same
    answers, in both 64-bit modes, without reading the disk again."""
    x, model32, x32 = jnp.arange(4.0) / 3, _model(dtype=jnp.float32), jnp.arange(4.0, dtype=jnp.float32)
    want = [_program_cache.call(_program, _model(), x, scale=2.0),
            _program_cache.call(_program, _model(), x, scale=3.0)]
    with jax.enable_x64(False):
        want.append(_program_cache.call(_program, model32, x32, scale=2.0))
    saved = {p.name: p.stat().st_mtime for p in folder.glob("*.jaxexport")}
    assert len(_listed(folder)) == 3 and set(_listed(folder)) == set(saved)
    assert sorted(_listed(folder), key=saved.get) == _listed(folder)  # first call first
    _program_cache.set_directory(folder)  # a new process
    reader = _program_cache.read_ahead()
    assert _program_cache.read_ahead() is None  # once per process
    reader.join(timeout=120)
    assert not reader.is_alive()
    _no_export(monkeypatch)
    _refuse_loading(monkeypatch)
    got = [_program_cache.call(_program, _model(), x, scale=2.0),
           _program_cache.call(_program, _model(), x, scale=3.0)]
    with jax.enable_x64(False):
        got.append(_program_cache.call(_program, model32, x32, scale=2.0))
    for g, w in zip(got, want):
        assert g["y"].dtype == w["y"].dtype
        np.testing.assert_array_equal(g["y"], w["y"])
        assert float(g["value"]) == float(w["value"])


def test_a_call_that_comes_before_the_reader_reads_its_program_itself(folder, monkeypatch):
    """The reader is held on the first listed program; a call of the second meanwhile loads
    it itself, and the reader, let go, skips it. A listed program that is gone is skipped."""
    x = jnp.arange(4.0)
    want = [float(_program_cache.call(_program, _model(), x, scale=s)["value"]) for s in (1.0, 2.0, 3.0)]
    first, second, third = _listed(folder)
    (folder / third).unlink()
    _program_cache.set_directory(folder)
    held, loads, load = threading.Event(), [], _program_cache._load

    def slow_load(path):
        loads.append((threading.current_thread().name, path.name))
        if path.name == first:
            assert held.wait(timeout=60)
        return load(path)

    monkeypatch.setattr(_program_cache, "_load", slow_load)
    reader = _program_cache.read_ahead()
    assert float(_program_cache.call(_program, _model(), x, scale=2.0)["value"]) == want[1]
    held.set()
    reader.join(timeout=120)
    assert float(_program_cache.call(_program, _model(), x, scale=1.0)["value"]) == want[0]
    assert float(_program_cache.call(_program, _model(), x, scale=3.0)["value"]) == want[2]
    assert loads[:2] == [("jaxskel-read-ahead", first), ("MainThread", second)]
    assert ("jaxskel-read-ahead", second) not in loads and ("jaxskel-read-ahead", third) not in loads


def test_nothing_listed_or_an_unreadable_list_reads_nothing(folder):
    assert _program_cache.read_ahead() is None
    (folder / "recently-used.json").write_text("{not json")
    _program_cache.set_directory(folder)  # a new process
    assert _program_cache.read_ahead() is None
    x = jnp.arange(4.0)
    assert float(_program_cache.call(_program, _model(), x, scale=2.0)["value"]) == float(
        _program(_model(), x, scale=2.0)["value"])
    assert len(_listed(folder)) == 1


_COUNTING_FIT = """
import sys, jax
exports = []
export = jax.export.export
jax.export.export = lambda *a, **k: exports.append(1) or export(*a, **k)
from jaxskel.cli import main
from jaxskel._runtime import program_cache
start = program_cache.read_ahead
def read_then_wait():  # the reader finishes first (a call that comes first reads for itself: tested above)
    reader = start()
    if reader is not None:
        reader.join()
    return reader
program_cache.read_ahead = read_then_wait
code = main(["fit", sys.argv[1], "-o", sys.argv[2], "--quiet"])
print("read ahead", sum(isinstance(p, jax.stages.Compiled) for p in program_cache._programs.values()))
print("programs", len(program_cache._programs))
print("exports", len(exports))
sys.exit(code)
"""


def test_second_command_line_process_loads_every_solver_program(tmp_path):
    """End to end: the first ``jaxskel fit`` exports the solver programs (joint costs,
    tree joints, anchored centres, IK); a second process on the same recording exports
    none, and writes the same result, bit for bit."""
    trial, _ = synth.simulate(synth.linkage(), duration=8.0, seed=2, noise=0.001)
    src = tmp_path / "chain.c3d"
    trial.save(src)
    env = {**os.environ, "JAXSKEL_CACHE_DIR": str(tmp_path / "cache")}
    counts, ahead = [], []
    for name in ("first.h5", "second.h5"):
        run = subprocess.run([sys.executable, "-c", _COUNTING_FIT, str(src), str(tmp_path / name)], env=env,
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-3000:]
        counts.append(int(run.stdout.split("exports")[-1]))
        ahead.append(tuple(int(run.stdout.split(word)[-1].split()[0]) for word in ("read ahead", "programs")))
    # the second process took every program from its read-ahead thread (jaxskel fit calls read_ahead)
    assert ahead[0][0] == 0 and ahead[1][0] == ahead[1][1] == ahead[0][1] >= 3
    (programs,) = (tmp_path / "cache").glob("*-programs")
    names = {p.name.split("-")[0] for p in programs.glob("*.jaxexport")}
    assert {"_chunk_solve", "_solve", "solve_chunk"} <= names
    assert counts[0] >= 3 and counts[1] == 0
    with h5py.File(tmp_path / "first.h5") as a, h5py.File(tmp_path / "second.h5") as b:
        for key in ("topology/edges", "joints/positions", "skeleton/bone_lengths", "motion/rotations"):
            np.testing.assert_array_equal(a[key][()], b[key][()], err_msg=key)


def test_key_follows_the_traced_libraries_versions(monkeypatch):
    """An upgrade of optimistix (or equinox, lineax, ...) changes what is traced: new keys."""
    from importlib import metadata

    _program_cache._source_digest.cache_clear()
    before = _program_cache._source_digest()
    real = metadata.version
    monkeypatch.setattr(metadata, "version", lambda name: "99.0" if name == "optimistix" else real(name))
    _program_cache._source_digest.cache_clear()
    try:
        assert _program_cache._source_digest() != before
    finally:
        monkeypatch.undo()
        _program_cache._source_digest.cache_clear()
    assert _program_cache._source_digest() == before


def test_stale_temporary_files_are_cleared(folder):
    stale = folder / "._program-0.jaxexport.ab12.tmp"  # atomic_output's temporary name
    stale.write_bytes(b"half a program")
    os.utime(stale, (1, 1))
    fresh = folder / "._program-1.jaxexport.cd34.tmp"  # perhaps another process writing now
    fresh.write_bytes(b"being written")
    stale_list = folder / ".recently-used.json.12345.tmp"  # the list of a process killed while writing it
    stale_list.write_text("[")
    os.utime(stale_list, (1, 1))
    _program_cache.call(_program, _model(), jnp.arange(4.0), scale=2.0)
    assert not stale.exists() and fresh.exists() and not stale_list.exists()
    assert not list(folder.glob(".recently-used.json.*.tmp"))  # this process's own list was renamed into place


def test_a_program_that_cannot_be_exported_runs_as_the_jitted_call(folder, monkeypatch):
    def fail(*_, **__):
        raise RuntimeError("custom call not on the export allowlist")

    monkeypatch.setattr(jax.export, "export", fail)
    x = jnp.arange(4.0)
    got = _program_cache.call(_program, _model(), x, scale=2.0)
    np.testing.assert_array_equal(got["y"], _program(_model(), x, scale=2.0)["y"])
    assert _saved(folder) == []
