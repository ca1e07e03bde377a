"""The real recording bundled with jaxskel (see ``jaxskel/data/ATTRIBUTION.md``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["sample_path", "load_sample"]

SAMPLE = "KneeltoProne01.c3d"


def sample_path() -> Path:
    """Path of the bundled sample recording (a labelled full-body floor-transition trial)."""
    return Path(str(resources.files("jaxskel") / "data" / SAMPLE))


def load_sample():
    """The bundled sample as a :class:`jaxskel.Trial` (metres)."""
    from ._load import load

    return load(sample_path())
