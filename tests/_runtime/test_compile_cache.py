"""The persistent XLA compilation cache of the command line (jaxskel._runtime.compile_cache):
locked, shared by processes, kept apart per CPU and jaxlib (moved from tests/test_fit_cli.py)."""

import os
import subprocess
import sys
from pathlib import Path

from jaxskel._runtime.compile_cache import machine_cache_dir

_CACHE_PROBE = """
import jax, jax.numpy as jnp
from jaxskel._runtime.compile_cache import CACHE_MAX_BYTES, enable_compile_cache
hits = []
jax.monitoring.register_event_listener(lambda event, **kw: hits.append(event) if "cache_hits" in event else None)
enable_compile_cache()
assert jax.config.jax_compilation_cache_max_size == CACHE_MAX_BYTES
print(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + x**2)(1.5)), len(hits))
"""


def test_compile_cache_is_locked_and_serves_a_second_process(tmp_path):
    """The CLI's persistent cache: bounded (so JAX locks every entry read and write, for
    parallel runs sharing it), filled by one process and hit by the next.
    ``JAXSKEL_CACHE_DIR=""`` turns it off."""
    env = {**os.environ, "JAXSKEL_CACHE_DIR": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", _CACHE_PROBE], env=env, capture_output=True, text=True,
                           timeout=120) for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), [r.stderr[-2000:] for r in runs]
    (value0, hits0), (value1, hits1) = (r.stdout.split() for r in runs)
    assert value0 == value1 and int(hits0) == 0 and int(hits1) >= 1
    (machine,) = (tmp_path / "cache").iterdir()  # one subdirectory: this CPU and jaxlib
    assert machine == machine_cache_dir(tmp_path / "cache")
    entries = list(machine.glob("*-cache"))
    assert entries and (machine / ".lockfile").exists()
    off = subprocess.run([sys.executable, "-c", _CACHE_PROBE.replace("assert jax.config", "assert not jax.config")],
                         env={**env, "JAXSKEL_CACHE_DIR": ""}, capture_output=True, text=True, timeout=120)
    assert off.returncode == 0, off.stderr[-2000:]


def test_compile_cache_is_kept_apart_per_cpu_and_jaxlib(monkeypatch):
    """XLA:CPU compiles for the host's instruction set and JAX's cache key leaves it out,
    so a cache shared by different CPUs (a cluster's home directory) must not mix them."""
    from jaxskel._runtime import compile_cache
    base = Path("/shared/cache")
    # Other machines and another jaxlib, simulated: the only way to see the key change
    # without them. The real identity is read after monkeypatch.undo() below.
    monkeypatch.setattr(compile_cache, "cpu_identity", lambda: "model name=EPYC|flags=avx avx2 avx512f")
    here = compile_cache.machine_cache_dir(base)
    assert here.parent == base and here == compile_cache.machine_cache_dir(base)  # stable
    monkeypatch.setattr(compile_cache, "cpu_identity", lambda: "model name=EPYC|flags=avx avx2")
    assert compile_cache.machine_cache_dir(base) != here  # a CPU without AVX-512
    monkeypatch.setattr(compile_cache, "cpu_identity", lambda: "model name=EPYC|flags=avx avx2 avx512f")
    import jaxlib

    monkeypatch.setattr(jaxlib, "__version__", "0.0.1")
    assert compile_cache.machine_cache_dir(base) != here  # another jaxlib
    # the real identity names the instruction set (x86 flags or aarch64 features)
    monkeypatch.undo()
    identity = compile_cache.cpu_identity()
    assert identity and ("flags=" in identity or "features=" in identity or "processor=" in identity)


_SD06_PROBE = """
import jax, numpy as np, jaxskel
from jaxskel import synth
hits = []
jax.monitoring.register_event_listener(lambda event, **kw: hits.append(event) if "cache_hits" in event else None)
where = jaxskel.enable_compile_cache()
from jaxskel._runtime import program_cache
import threading
listed = len(program_cache._ahead)  # programs the last process listed, being read ahead (none taken yet)
for reader in [t for t in threading.enumerate() if t.name == "jaxskel-read-ahead"]:
    reader.join()  # (a call that comes first reads its program itself: tests/_runtime/test_program_cache.py)
body = synth.full_body(seed=0)
_, truth = synth.simulate(body, "calibration", duration=10.0, rate=60.0, seed=0)
from scipy.spatial.transform import Rotation
quats = Rotation.from_matrix(truth.segment_rotations.reshape(-1, 3, 3)).as_quat(scalar_first=True)
param = jaxskel.sd06.parameterize_arrays(truth.joint_positions, body.edges, quats.reshape(*truth.segment_rotations.shape[:2], 4),
                                         root=body.root, segment_translations=truth.segment_translations, rate=60.0)
np.save(__import__("sys").argv[1], param.angles)
print(where, len(hits), listed, sum(isinstance(p, jax.stages.Compiled) for p in program_cache._programs.values()))
"""


def test_the_public_opt_in_serves_the_sd06_programs_to_a_second_process(tmp_path):
    """``jaxskel.enable_compile_cache()`` (what the command does, for a library user): the SD06
    stages, compiled with their own XLA options, are saved by one process and loaded by the next,
    read ahead in a background thread, with the same angles."""
    env = {**os.environ, "JAXSKEL_CACHE_DIR": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", _SD06_PROBE, str(tmp_path / f"angles{i}.npy")], env=env,
                           capture_output=True, text=True, timeout=300) for i in range(2)]
    assert all(r.returncode == 0 for r in runs), [r.stderr[-2000:] for r in runs]
    (where0, hits0, listed0, ahead0), (where1, hits1, listed1, ahead1) = (r.stdout.split() for r in runs)
    assert where0 == where1 == str(machine_cache_dir(tmp_path / "cache"))
    assert int(hits0) == 0 and int(hits1) >= 4  # at least the four SD06 stage programs
    # the second process read the first one's programs ahead (a thread started by enable_compile_cache) and used them
    assert int(listed0) == int(ahead0) == 0 and int(listed1) >= 4 and int(ahead1) >= 4
    saved = {p.name.split("-")[0] for p in Path(where0 + "-programs").glob("*.jaxexport")}
    assert {"_normalize_core", "_filter_stage", "_axes_stage", "_angles_stage"} <= saved
    import numpy as np

    np.testing.assert_array_equal(np.load(tmp_path / "angles0.npy"), np.load(tmp_path / "angles1.npy"))
