"""The install extras the README names exist and pull what they say (issue 48: the GPU extra)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _extras() -> dict[str, list[str]]:
    if sys.version_info >= (3, 11):
        import tomllib

        return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    import importlib.metadata as metadata  # Python 3.10: the installed metadata

    extras: dict[str, list[str]] = {}
    for req in metadata.requires("jaxskel") or []:
        found = re.search(r'extra == "([^"]+)"', req)
        if found:
            extras.setdefault(found.group(1), []).append(req.split(";")[0].strip())
    return extras


def test_the_cuda_extras_install_jax_with_its_cuda_plugin():
    extras = _extras()
    assert extras["cuda"] == extras["cuda12"] and extras["cuda"][0].startswith("jax[cuda12]")
    assert extras["cuda13"][0].startswith("jax[cuda13]")
    readme = (ROOT / "README.md").read_text()
    for name in re.findall(r"\[(\w+)\] \(", readme.split("## Install and demo", 1)[1].split("```", 2)[1]):
        assert name in extras, name  # every extra the install line names exists
