"""The true body part of each fitted segment, in :data:`jaxskel.anatomy.PARTS` names.

One source of truth for every anatomy, angle and export test:

* synthetic bodies (:func:`jaxskel.synth.full_body`): each marker's generating segment,
  through :data:`SYNTH_PART`;
* real recordings: the marker-set maps of ``tests/human_markers.py`` (test data; the
  package never reads marker names), through :data:`HUMAN_PART`.

A fitted segment's truth is the majority part of its markers (ties and joint markers as
``human_markers.segment_parts`` decides them); ``None`` where no marker names a part the
vocabulary has (an acromion marker alone: clavicle, thorax or upper arm), so the segment
is not scored.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from human_markers import segment_parts  # noqa: E402

#: Segment of :func:`jaxskel.synth.full_body` -> part (its torso is one thorax, no abdomen).
SYNTH_PART: dict[str, str] = {"pelvis": "pelvis", "torso": "thorax", "head": "head"}
for _side in "lr":
    SYNTH_PART.update({
        f"{_side}_upperarm": f"upper_arm_{_side}", f"{_side}_forearm": f"forearm_{_side}",
        f"{_side}_hand": f"hand_{_side}", f"{_side}_thigh": f"thigh_{_side}",
        f"{_side}_shank": f"shank_{_side}", f"{_side}_foot": f"foot_{_side}",
    })

#: ``human_markers`` part -> part (``None``: no single part; the acromion's "shoulder").
HUMAN_PART: dict[str, str | None] = {"pelvis": "pelvis", "thorax": "thorax", "head": "head"}
for _side in "LR":
    _s = _side.lower()
    HUMAN_PART.update({
        f"{_side} shoulder": None, f"{_side} upper arm": f"upper_arm_{_s}", f"{_side} forearm": f"forearm_{_s}",
        f"{_side} hand": f"hand_{_s}", f"{_side} thigh": f"thigh_{_s}", f"{_side} shank": f"shank_{_s}",
        f"{_side} foot": f"foot_{_s}",
    })
del _side, _s


def synth_truth(body, labels, marker_segment) -> list[str | None]:
    """Per fitted segment, the part of the synthetic body segment most of its markers are on."""
    part_of = {lab: SYNTH_PART.get(body.segment_names[g]) for lab, g in zip(body.marker_labels, body.marker_segment)}
    seg = np.asarray(marker_segment)
    out: list[str | None] = []
    for s in range(int(seg.max()) + 1):
        votes = [part_of.get(lab.split(":")[-1]) for lab, g in zip(labels, seg) if g == s]
        votes = [v for v in votes if v is not None]
        out.append(max(sorted(set(votes)), key=votes.count) if votes else None)
    return out


def real_truth(labels, marker_segment) -> list[str | None]:
    """Per fitted segment, its part by the real marker sets' maps (``None``: not scored)."""
    return [HUMAN_PART.get(p) if p is not None else None for p in segment_parts(labels, marker_segment)]


def result_truth(result, body=None) -> list[str | None]:
    """:func:`synth_truth` (given the synthetic ``body``) or :func:`real_truth` of a fit result."""
    labels, marker_segment = result.trial.labels, result.segmentation.marker_segment
    return synth_truth(body, labels, marker_segment) if body is not None else real_truth(labels, marker_segment)


def score(parts, truth) -> tuple[int, int, int]:
    """(right, scored, swapped): segments named right among those with a truth, and how many
    were named the same part on the other side."""
    from jaxskel.anatomy import mirror

    scored = [(p, t) for p, t in zip(parts, truth) if t is not None]
    right = sum(p == t for p, t in scored)
    swapped = sum(p != t and p == mirror(t) for p, t in scored)
    return right, len(scored), swapped
