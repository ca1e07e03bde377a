"""The public API is small, listed in ``__all__``, and documented in docs/api.md."""

import importlib
import re
from pathlib import Path

import jaxskel

API_PAGE = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def _documented() -> dict[str, set[str]]:
    """Names per section (``jaxskel``, ``jaxskel.segment``, ...) of docs/api.md's tables."""
    sections: dict[str, set[str]] = {}
    current = None
    for line in API_PAGE.read_text().splitlines():
        head = re.match(r"^## `([\w.]+)`", line)
        if head:
            current = head.group(1)
            sections[current] = set()
        row = re.match(r"^\| `(\w+)` \|", line)
        if row and current:
            sections[current].add(row.group(1))
    return sections


def test_every_public_name_is_documented_and_nothing_else():
    documented = _documented()
    top = {n for n in jaxskel.__all__ if n not in jaxskel._SUBPACKAGES}
    assert documented["jaxskel"] == top
    for sub in jaxskel._SUBPACKAGES:
        module = importlib.import_module(f"jaxskel.{sub}")
        assert documented[f"jaxskel.{sub}"] == set(module.__all__), sub
    assert set(documented) == {"jaxskel"} | {f"jaxskel.{s}" for s in jaxskel._SUBPACKAGES}


def test_every_public_name_resolves_and_none_is_private():
    for name in jaxskel.__all__:
        assert not name.startswith("_") or name == "__version__"
        getattr(jaxskel, name)
    for sub in jaxskel._SUBPACKAGES:
        module = importlib.import_module(f"jaxskel.{sub}")
        for name in module.__all__:
            assert not name.startswith("_"), (sub, name)
            getattr(module, name)


def test_the_top_level_holds_entry_points_and_stage_namespaces_only():
    """No stage function is exported flat: each lives in its stage's namespace."""
    top = set(jaxskel.__all__)
    assert {"fit_skeleton", "fit_batch", "load", "FitOptions", "SkeletonResult", "segment", "joints"} <= top
    assert not top & {"segment_markers", "fit_topology", "inverse_kinematics", "normalize", "plot_summary"}
    try:
        jaxskel.segment_markers  # noqa: B018
    except AttributeError as exc:  # says where the name lives now
        assert "it is jaxskel.segment.segment_markers" in str(exc)
    else:
        raise AssertionError("a stage function is reachable at the top level")
