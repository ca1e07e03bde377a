"""Body parts named without marker names, on the real recordings of ``bench/real_trees.py``.

Each recording is fitted with :func:`jaxskel.fit_skeleton` defaults and named with
:func:`jaxskel.anatomy.identify_result`; the names are judged with the body-part maps of
``tests/human_markers.py`` (test data; the package never reads marker names) through
``tests/anatomy/truth.py``: ``right`` of the ``scored`` segments (those whose markers lie
on one part of the vocabulary), ``swapped`` those named the same part on the other side.

Fits are cached with pickle in ``--cache`` (default ``/tmp/anat_fits``) so that the
naming can be re-judged without refitting (a fit takes 1-3 min).

Usage::

    python bench/anatomy.py
    python bench/anatomy.py --only 85_12
    python bench/anatomy.py --markdown docs/bench/anatomy.md
"""

from __future__ import annotations

import argparse
import copyreg
import pickle
import sys
import time
import types
import warnings
from pathlib import Path

import jaxskel
import numpy as np

from jaxskel.anatomy import identify, identify_result

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "anatomy"))
from real_trees import DATA, RECORDINGS  # noqa: E402
from truth import result_truth, score  # noqa: E402


def _pickle_mappingproxy(m: types.MappingProxyType) -> tuple:
    return dict, (dict(m),)


def fitted(rel: str, cache: Path):
    """The default fit of a recording, from the cache when there."""
    path = cache / (rel.replace("/", "__") + ".pkl")
    if path.exists():
        with open(path, "rb") as f:
            return pickle.load(f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(jaxskel.load(DATA / rel))
    cache.mkdir(parents=True, exist_ok=True)
    dispatch = copyreg.dispatch_table.copy()
    dispatch[types.MappingProxyType] = _pickle_mappingproxy
    with open(path, "wb") as f:
        pickler = pickle.Pickler(f)
        pickler.dispatch_table = dispatch
        pickler.dump(result)
    return result


def _axis_name(v: np.ndarray) -> str:
    i = int(np.argmax(np.abs(v)))
    exact = np.isclose(abs(v[i]), 1.0)
    return ("-" if v[i] < 0 else "") + "xyz"[i] + ("" if exact else f" ({abs(v[i]):.2f})")


def judge(rel: str, cache: Path) -> dict:
    result = fitted(rel, cache)
    t0 = time.perf_counter()
    anatomy = identify_result(result)
    seconds = time.perf_counter() - t0
    right, scored, swapped = score(anatomy.parts, result_truth(result))
    auto = identify(result.skeleton, result.motion, up_axis="auto")
    same = auto.parts == anatomy.parts
    return {
        "auto_up": f"{_axis_name(auto.up)} ({'same parts' if same else 'other parts'})", "up_axis": result.trial.up_axis,
        "recording": rel, "segments": result.skeleton.n_segments, "right": right, "scored": scored,
        "swapped": swapped, "humanoid": anatomy.humanoid, "seconds": seconds, "notes": anatomy.notes,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/anat_fits"))
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    rows = [judge(rel, args.cache) for rel in RECORDINGS if args.only in rel]
    lines = [
        "| recording | segments | right / scored | swapped | humanoid | up axis | up found (`auto`) |",
        "|---|---:|---:|---:|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['recording']} | {r['segments']} | {r['right']} / {r['scored']} | {r['swapped']} | {r['humanoid']} "
            f"| {r['up_axis']} | {r['auto_up']} |"
        )
        print(f"{r['recording']:50s} {r['right']:3d} / {r['scored']:3d} right, {r['swapped']} swapped"
              f", up {r['up_axis']}, auto {r['auto_up']} ({r['seconds']:.2f} s)", flush=True)
    total = [sum(r[k] for r in rows) for k in ("right", "scored", "swapped")]
    lines.append(f"| **all** | | {total[0]} / {total[1]} | {total[2]} | | | |")
    print(f"{'all':50s} {total[0]:3d} / {total[1]:3d} right, {total[2]} swapped")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        head = ("# Body parts without marker names (`python bench/anatomy.py`)\n\n"
                "Each real recording fitted with `fit_skeleton` defaults and named by "
                "`jaxskel.anatomy.identify_result`; judged with the body-part maps of `tests/human_markers.py`.\n\n")
        args.markdown.write_text(head + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
