"""A Python with Blender's ``bpy`` package, for the BVH import test.

``bpy`` can not share jaxskel's environment: its wheels pin ``numpy<2`` while jax needs
``numpy>=2``, so it is neither in the dev extra nor in the test environment. The
``blender_python`` fixture uses the running Python when ``import bpy`` works in it (in a
subprocess, so the test process never imports Blender), else a virtual environment of its
own, ``~/.cache/jaxskel/test-blender/<bpy version>`` (``JAXSKEL_TEST_BLENDER_VENV``
overrides the folder), built once with ``pip install bpy==<version>`` (about 0.5 GB, a few
minutes). The version is the ``bpy`` release built for the running Python's minor version
(:data:`BPY_FOR_PYTHON`: ``bpy`` wheels exist for one CPython minor version per Blender
release). Where none can be had, the test fails, saying how to provide one.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

#: The pinned ``bpy`` release for each CPython minor version (Blender 5.0 embeds Python 3.11).
BPY_FOR_PYTHON = {(3, 11): "5.0.1"}


def _clean_env() -> dict[str, str]:
    """The environment for a Blender Python: without this run's PYTHONPATH/PYTHONHOME."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def _has_bpy(python: Path | str) -> bool:
    try:
        done = subprocess.run([str(python), "-c", "import bpy"], capture_output=True, env=_clean_env(), timeout=300,
                              check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _venv_python(venv: Path) -> Path:
    return venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def _instructions(why: str) -> str:
    versions = ", ".join(f"Python {a}.{b}: bpy=={v}" for (a, b), v in BPY_FOR_PYTHON.items())
    return (
        f"The Blender import test needs Blender's bpy package and could not get it: {why}\n"
        f"Either install it in a Python of its own (bpy pins numpy<2, jax needs numpy>=2), e.g.\n"
        f"    python3.11 -m venv ~/.cache/jaxskel/test-blender/{BPY_FOR_PYTHON[(3, 11)]}\n"
        f"    ~/.cache/jaxskel/test-blender/{BPY_FOR_PYTHON[(3, 11)]}/bin/python -m pip install "
        f"bpy=={BPY_FOR_PYTHON[(3, 11)]}\n"
        f"and point JAXSKEL_TEST_BLENDER_VENV at that folder, or run the tests in a Python with a bpy release "
        f"({versions})."
    )


def _build(venv: Path, version: str) -> None:
    """``python -m venv`` + ``pip install bpy==version`` into ``venv``, once (a file lock keeps
    parallel test workers from building it twice)."""
    import fcntl  # POSIX; the fixture's build is for the Linux and macOS test machines

    venv.parent.mkdir(parents=True, exist_ok=True)
    with open(venv.parent / f".{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if _has_bpy(_venv_python(venv)):
            return
        for cmd in ([sys.executable, "-m", "venv", "--clear", str(venv)],
                    [str(_venv_python(venv)), "-m", "pip", "install", "--quiet", f"bpy=={version}"]):
            done = subprocess.run(cmd, capture_output=True, text=True, env=_clean_env(), check=False)
            if done.returncode != 0:
                pytest.fail(_instructions(f"`{' '.join(cmd)}` failed:\n{(done.stdout + done.stderr)[-3000:]}"),
                            pytrace=False)


@pytest.fixture(scope="session")
def blender_python() -> str:
    """The path of a Python interpreter that can ``import bpy`` (module docstring)."""
    if _has_bpy(sys.executable):
        return sys.executable
    version = BPY_FOR_PYTHON.get(sys.version_info[:2])
    if version is None:
        pytest.fail(_instructions(f"no pinned bpy release for Python {sys.version_info.major}."
                                  f"{sys.version_info.minor}"), pytrace=False)
    venv = Path(os.environ.get("JAXSKEL_TEST_BLENDER_VENV") or Path.home() / ".cache/jaxskel/test-blender" / version)
    venv = venv.expanduser()
    if not _has_bpy(_venv_python(venv)):
        _build(venv, version)
    if not _has_bpy(_venv_python(venv)):
        pytest.fail(_instructions(f"{_venv_python(venv)} was built but cannot import bpy"), pytrace=False)
    return str(_venv_python(venv))
