"""Readable segment names from the labels of their markers (display only).

A segment is named after its markers, with each label read without a ``Subject:``
prefix (everything up to the last ``:``):

* one marker: its label (``C7``);
* several: their longest common prefix, less trailing digits and separators, where
  that is meaningful: at least two characters and more than a side (``L``, ``R``,
  ``Left``, ``Right``; case ignored). ``RTHPA, RTHPP, RTHDP, RTHDA`` -> ``RTH``;
  ``R1M1, R1M2, R1M3`` -> ``R1M``;
* otherwise the labels joined by ``+`` in the segmentation's order, all of them up to
  :data:`MAX_LISTED`, else the first three and how many more: ``LFWT+RFWT+LBWT+RBWT``,
  ``LFHD+RFHD+LBHD+2more``;
* no marker: ``seg<i>`` (its index).

Names are unique: segments whose prefixes coincide are named by their marker lists
instead, and a name still taken (labels equal without their prefixes) gets ``_2``,
``_3``, ... Whitespace becomes ``_``, so every name is one BVH token
(:func:`safe_name`, also applied to names a user gives the BVH writer).

Names are for people: the summary, warnings, plots, the result file's
``/segments/names`` and the BVH joints. No stage of the fit reads them, so the labels a
recording carries never change its skeleton.
"""

from __future__ import annotations

import os
import re
from collections import Counter
from collections.abc import Sequence

import numpy as np

__all__ = ["MAX_LISTED", "bare_label", "group_name", "names_from_markers", "safe_name", "segment_names"]

#: A segment of up to this many markers with no meaningful prefix is named by all of them.
MAX_LISTED = 4

#: Prefixes that name only a side of the body, not a part (compared in lower case).
_SIDES = frozenset({"l", "r", "left", "right"})


def safe_name(name: str) -> str:
    """``name`` as one token: whitespace runs become ``_``; empty -> ``segment``."""
    return re.sub(r"\s+", "_", str(name).strip()) or "segment"


def bare_label(label: str) -> str:
    """A marker label without its ``Subject:`` prefix, as one token."""
    return safe_name(str(label).rsplit(":", 1)[-1])


def _prefix(labels: Sequence[str]) -> str:
    """The meaningful common prefix of ``labels`` (module docstring), or ``""``."""
    common = os.path.commonprefix(list(labels))
    common = re.sub(r"[^A-Za-z]+$", "", common)  # R1M1, R1M2 -> R1M; T1, T10 -> T; *12, *13 -> ""
    if len(common) < 2 or common.lower() in _SIDES:
        return ""
    return common


def _listed(labels: Sequence[str]) -> str:
    """The labels joined by ``+``; past :data:`MAX_LISTED`, the first three and ``+Nmore``."""
    if len(labels) <= MAX_LISTED:
        return "+".join(labels)
    return "+".join(labels[:3]) + f"+{len(labels) - 3}more"


def group_name(labels: Sequence[str]) -> str:
    """The name of one segment carrying markers ``labels`` (module docstring; ``""`` if none)."""
    bare = [bare_label(v) for v in labels]
    if len(bare) <= 1:
        return "".join(bare)
    return _prefix(bare) or _listed(bare)


def _deduplicate(names: list[str]) -> list[str]:
    """Second and later copies of a name get ``_2``, ``_3``, ... (skipping names taken)."""
    taken = set(names)
    seen: Counter[str] = Counter()
    out = []
    for name in names:
        seen[name] += 1
        if seen[name] > 1:
            k = seen[name]
            while f"{name}_{k}" in taken:
                k += 1
            name = f"{name}_{k}"
            taken.add(name)
        out.append(name)
    return out


def segment_names(groups: Sequence[Sequence[str]]) -> tuple[str, ...]:
    """Unique readable names of segments whose markers carry ``groups`` of labels."""
    names = [group_name(g) or f"seg{i}" for i, g in enumerate(groups)]
    counts = Counter(names)
    for i, g in enumerate(groups):
        if counts[names[i]] > 1 and len(g) > 1:  # a shared prefix: name the markers instead
            names[i] = _listed([bare_label(v) for v in g])
    return tuple(_deduplicate(names))


def names_from_markers(labels: Sequence[str], marker_segment: np.ndarray, n_segments: int) -> tuple[str, ...]:
    """:func:`segment_names` of ``n_segments`` segments given each marker's segment (-1: none)."""
    seg = np.asarray(marker_segment, dtype=int)
    return segment_names([[lab for lab, s in zip(labels, seg) if s == g] for g in range(n_segments)])
