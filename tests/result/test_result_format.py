"""Every group, dataset and attribute a result file or a trial file can hold is documented.

A small synthetic fit goes through the public API (``jaxskel.synth``, ``jaxskel.fit_skeleton``,
``SkeletonResult.save``, ``jaxskel.save_trial``, the ``jaxskel fit --parameterize`` command and
``jaxskel.fit_batch``, ``jaxskel.track``); the test walks every file written and asserts that each name is in
``docs/result-format.md``. A new dataset or attribute that is not documented fails here.

Naming in the document: a group or dataset by its full path (```/topology/edges```), an
attribute as ``PATH@NAME`` (```/segments@sigma```, on the root ```/@rate```); a ``*`` stands for
a family of names (```/diagnostics@time_*```). The trial file's names are looked up in the
document's "## Trial file" section, the result file's everywhere else, and the columns of
``summary.csv`` in its "## summary.csv" section.
"""

from __future__ import annotations

import csv
import fnmatch
import re
from pathlib import Path

import h5py
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.cli import main

DOC = Path(__file__).resolve().parents[2] / "docs" / "result-format.md"


def _sections(text: str) -> dict[str, str]:
    """The document split at its ``## `` headings: title -> body (the preamble under "")."""
    parts: dict[str, str] = {}
    title, lines = "", []
    for line in text.splitlines():
        if line.startswith("## "):
            parts[title] = "\n".join(lines)
            title, lines = line[3:].strip(), []
        else:
            lines.append(line)
    parts[title] = "\n".join(lines)
    return parts


def _documented(text: str) -> tuple[set[str], list[str]]:
    """Backticked names in ``text``: exact ones and ``*`` patterns."""
    names = {m.strip() for m in re.findall(r"`([^`\n]+)`", text)}
    patterns = [n for n in names if "*" in n]
    for p in patterns:  # a pattern must name a family, not a whole group (no "/x/*" or "/x@*")
        assert not re.search(r"[/@]\*", p), f"{DOC.name}: pattern {p!r} is too broad"
    return names, patterns


def _objects(path: Path) -> list[str]:
    """Every group, dataset and attribute of an HDF5 file, in the document's notation."""
    out: list[str] = []
    with h5py.File(path, "r") as f:
        out += [f"/@{k}" for k in f.attrs]

        def visit(name: str, obj) -> None:
            out.append(f"/{name}")
            out.extend(f"/{name}@{k}" for k in obj.attrs)

        f.visititems(visit)
    return out


def _undocumented(objects: list[str], text: str) -> list[str]:
    names, patterns = _documented(text)
    return [o for o in objects if o not in names and not any(fnmatch.fnmatchcase(o, p) for p in patterns)]


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("format")
    trial, _ = synth.simulate(synth.random_tree(4, seed=0), duration=4.0, seed=1, noise=0.001, gaps=1)
    trial_file = tmp / "trial.h5"
    jaxskel.save_trial(trial, trial_file)

    result = jaxskel.fit_skeleton(trial)
    result.save(tmp / "fit.h5")

    assert main(["fit", str(trial_file), "-o", str(tmp / "parameterized.h5"), "--parameterize", "--quiet"]) == 0

    batch = jaxskel.fit_batch([trial_file], tmp / "batch")
    assert not batch.failed, batch.failed

    tracked = jaxskel.track(tmp / "fit.h5", trial_file, tmp / "tracked")
    assert not tracked.failed, tracked.failed
    return {
        "trial": trial_file,
        "fit": tmp / "fit.h5",
        "parameterized": tmp / "parameterized.h5",
        "batch": tmp / "batch" / "trial.h5",
        "summary": tmp / "batch" / "summary.csv",
        "tracked": tmp / "tracked" / "trial.h5",
    }


def test_result_files_are_documented(written):
    sections = _sections(DOC.read_text(encoding="utf-8"))
    text = "\n".join(body for title, body in sections.items() if not title.startswith("Trial file"))
    for kind in ("fit", "parameterized", "batch", "tracked"):
        objects = _objects(written[kind])
        assert "/@schema_version" in objects
        missing = _undocumented(objects, text)
        assert not missing, f"not documented in {DOC}: {missing} (from the {kind} result file)"
    groups = {o.split("/")[1].split("@")[0] for o in _objects(written["parameterized"])}
    assert {"normalized", "parameters", "skeleton", "motion"} <= groups
    assert "/batch@signature" in _objects(written["batch"])
    assert "/motion/segment_posed" in _objects(written["tracked"])


def test_trial_file_is_documented(written):
    sections = _sections(DOC.read_text(encoding="utf-8"))
    trial = next(body for title, body in sections.items() if title.startswith("Trial file"))
    objects = _objects(written["trial"])
    assert "/@jaxskel_trial_version" in objects
    missing = _undocumented(objects, trial)
    assert not missing, f"not documented in the trial file section of {DOC}: {missing}"


def test_summary_columns_are_documented(written):
    sections = _sections(DOC.read_text(encoding="utf-8"))
    summary = next(body for title, body in sections.items() if title.startswith("summary.csv"))
    with open(written["summary"], newline="", encoding="utf-8") as f:
        header = next(csv.reader(f))
    names, _ = _documented(summary)
    missing = [c for c in header if c not in names and not c.startswith("bone:")]
    assert not missing, f"summary.csv columns not documented in {DOC}: {missing}"
