"""The named human body: the parts a segment can be, their tree, and the joints between them.

A fitted segment is named with one of :data:`PARTS` (or ``""`` where it is not identified).
Side suffixes are the subject's own left and right (``_l``, ``_r``), never the camera's.

The human tree (parent part -> child part), from the pelvis out::

    pelvis -> abdomen -> thorax -> head
                         thorax -> clavicle_s -> upper_arm_s -> forearm_s -> hand_s
    pelvis -> thigh_s -> shank_s -> foot_s -> toes_s

A recording's tree may skip parts that it has no markers on (an upper arm hanging from
the thorax with no clavicle segment, a thorax on the pelvis with no abdomen); such a joint
is named after its child part all the same (:func:`joint_name`).

:class:`Anatomy` is what :mod:`jaxskel.anatomy` returns for a fitted skeleton, and what
the exporters read: the part of every segment, a confidence for each, whether the body is
human at all, and the body's up and front directions in the recording's frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .._errors import InputError

__all__ = [
    "Anatomy", "CHAINS", "JOINT_OF_PART", "PARENT_PART", "PARTS", "SIDES", "VIRTUAL_MARKER", "is_ancestor", "joint_between",
    "joint_name", "mirror", "side_of",
]

#: Every part a segment can be named, proximal before distal.
PARTS: tuple[str, ...] = (
    "pelvis", "abdomen", "thorax", "head",
    "clavicle_l", "clavicle_r", "upper_arm_l", "upper_arm_r", "forearm_l", "forearm_r", "hand_l", "hand_r",
    "thigh_l", "thigh_r", "shank_l", "shank_r", "foot_l", "foot_r", "toes_l", "toes_r",
)  # fmt: skip

#: The subject's sides, as the suffixes of :data:`PARTS`.
SIDES: tuple[str, ...] = ("l", "r")

#: Parent of each part in the full human tree (the pelvis is the root: ``""``).
PARENT_PART: dict[str, str] = {"pelvis": "", "abdomen": "pelvis", "thorax": "abdomen", "head": "thorax"}
for _s in SIDES:
    PARENT_PART.update({
        f"clavicle_{_s}": "thorax", f"upper_arm_{_s}": f"clavicle_{_s}", f"forearm_{_s}": f"upper_arm_{_s}",
        f"hand_{_s}": f"forearm_{_s}", f"thigh_{_s}": "pelvis", f"shank_{_s}": f"thigh_{_s}",
        f"foot_{_s}": f"shank_{_s}", f"toes_{_s}": f"foot_{_s}",
    })

#: The chains of the human tree, proximal to distal: the trunk, each arm, each leg.
CHAINS: tuple[tuple[str, ...], ...] = (
    ("pelvis", "abdomen", "thorax", "head"),
    *((f"clavicle_{s}", f"upper_arm_{s}", f"forearm_{s}", f"hand_{s}") for s in SIDES),
    *((f"thigh_{s}", f"shank_{s}", f"foot_{s}", f"toes_{s}") for s in SIDES),
)

#: The joint at the proximal end of each part (named after the child part it moves).
JOINT_OF_PART: dict[str, str] = {"abdomen": "lumbar", "thorax": "thoracic", "head": "neck"}
for _s in SIDES:
    JOINT_OF_PART.update({
        f"clavicle_{_s}": f"sternoclavicular_{_s}", f"upper_arm_{_s}": f"shoulder_{_s}",
        f"forearm_{_s}": f"elbow_{_s}", f"hand_{_s}": f"wrist_{_s}", f"thigh_{_s}": f"hip_{_s}",
        f"shank_{_s}": f"knee_{_s}", f"foot_{_s}": f"ankle_{_s}", f"toes_{_s}": f"toe_{_s}",
    })

#: Virtual-marker names of the joint centres labs use (Plug-in Gait style), by joint.
VIRTUAL_MARKER: dict[str, str] = {}
for _s, _p in (("l", "L"), ("r", "R")):
    VIRTUAL_MARKER.update({
        f"hip_{_s}": f"{_p}HJC", f"knee_{_s}": f"{_p}KJC", f"ankle_{_s}": f"{_p}AJC", f"toe_{_s}": f"{_p}TJC",
        f"shoulder_{_s}": f"{_p}SJC", f"elbow_{_s}": f"{_p}EJC", f"wrist_{_s}": f"{_p}WJC",
        f"sternoclavicular_{_s}": f"{_p}CJC",
    })
VIRTUAL_MARKER.update({"lumbar": "LJC", "thoracic": "TJC", "neck": "NJC"})
del _s, _p


def side_of(part: str) -> str:
    """``"l"``, ``"r"`` or ``""`` (a part on the body's midline, or no part)."""
    return part[-1] if part[-2:] in ("_l", "_r") else ""


def mirror(part: str) -> str:
    """The same part on the other side (midline parts and ``""`` unchanged)."""
    side = side_of(part)
    return part[:-1] + {"l": "r", "r": "l"}[side] if side else part


def joint_name(child_part: str) -> str:
    """The name of the joint at a part's proximal end (``""`` for the root or no part)."""
    return JOINT_OF_PART.get(child_part, "")


def is_ancestor(part: str, of: str) -> bool:
    """Whether ``part`` lies on the path from ``of`` to the pelvis in :data:`PARENT_PART`
    (``of`` itself excluded)."""
    up = PARENT_PART.get(of, "")
    while up:
        if up == part:
            return True
        up = PARENT_PART[up]
    return False


def joint_between(part_a: str, part_b: str) -> str:
    """The joint of two named parts one of which is proximal to the other in the human tree,
    named after the distal one (a thorax on the pelvis, no abdomen between: ``thoracic``);
    ``""`` where either is unnamed or neither is proximal to the other."""
    if part_a and part_b:
        if is_ancestor(part_a, part_b):
            return joint_name(part_b)
        if is_ancestor(part_b, part_a):
            return joint_name(part_a)
    return ""


@dataclasses.dataclass(frozen=True)
class Anatomy:
    """The body parts of a fitted skeleton's segments.

    Attributes
    ----------
    parts
        (S,) one of :data:`PARTS` per segment, or ``""`` where the part is not identified
        (every entry ``""`` when the body is not human).
    confidence
        (S,) in [0, 1]: how sure the naming is of each segment's part (0 where ``""``).
    humanoid
        Whether the skeleton is a human body (whole or partial: a lower-limb set, one arm).
    up, front
        (3,) unit vectors in the recording's frame: the body's superior direction and its
        anterior direction (the way it faces) at the skeleton's rest. ``left = up x front``.
    notes
        What decided the naming, and why a part was left out, as short sentences.
    """

    parts: tuple[str, ...]
    confidence: np.ndarray
    humanoid: bool
    up: np.ndarray
    front: np.ndarray
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        unknown = sorted({p for p in self.parts if p and p not in PARTS})
        if unknown:
            raise InputError(f"unknown body parts {unknown}; use names from jaxskel.anatomy.PARTS")
        object.__setattr__(self, "parts", tuple(self.parts))
        object.__setattr__(self, "confidence", np.asarray(self.confidence, float))
        object.__setattr__(self, "up", np.asarray(self.up, float))
        object.__setattr__(self, "front", np.asarray(self.front, float))
        if self.confidence.shape != (len(self.parts),):
            raise InputError(
                f"confidence has shape {self.confidence.shape}; expected ({len(self.parts)},): one value per segment"
            )

    @property
    def left(self) -> np.ndarray:
        """(3,) the subject's left, ``up x front``."""
        return np.cross(self.up, self.front)

    def segment_of(self, part: str) -> int | None:
        """The segment named ``part``, or None."""
        return self.parts.index(part) if part in self.parts else None

    def main_segments(self, edges: np.ndarray | None = None) -> np.ndarray:
        """(S,) bool: the segment that carries its part's plain name. Where one part names
        several segments (a one-marker twig on its host's part, a limb cut in two), the one
        joined to the most segments of other named parts in the tree ``edges`` (the piece in
        the chain), the first in segment order on a tie or without ``edges``; every
        segment with a part of its own, and none without a part."""
        links = np.zeros(len(self.parts), int)
        for a, b in np.asarray(edges if edges is not None else [], int).reshape(-1, 2).tolist():
            if self.parts[a] and self.parts[b] and self.parts[a] != self.parts[b]:
                links[a] += 1
                links[b] += 1
        main = np.zeros(len(self.parts), bool)
        for part in set(self.parts) - {""}:
            members = [s for s, p in enumerate(self.parts) if p == part]
            main[max(members, key=lambda s: (links[s], -s))] = True
        return main

    def segment_names(self, fallback: Sequence[str], edges: np.ndarray | None = None) -> tuple[str, ...]:
        """Each segment's part, or its ``fallback`` name where the part is not identified;
        distinct: a part that names several segments is ``part`` on its
        :meth:`main_segments` one (given the tree ``edges``) and ``part_2``, ... on the others."""
        if len(fallback) != len(self.parts):
            raise InputError(f"{len(fallback)} fallback names for {len(self.parts)} segments")
        main = self.main_segments(edges)
        names: list[str | None] = [p if m else None for p, m in zip(self.parts, main)]
        taken = set(n for n in names if n) | {f for f, p in zip(fallback, self.parts) if not p}
        for s, (p, f) in enumerate(zip(self.parts, fallback)):
            if names[s] is not None:
                continue
            name, k = p or f, 1
            while p and name in taken:
                k += 1
                name = f"{p}_{k}"
            names[s] = name
            taken.add(name)
        return tuple(names)

    def joint_names(self, edges: np.ndarray, fallback: Sequence[str]) -> tuple[str, ...]:
        """(J,) each tree joint's anatomical name (:func:`joint_between` of its two segments'
        parts: ``knee_l``), or its ``fallback`` name where the parts do not name it."""
        pairs = np.asarray(edges, int).reshape(-1, 2).tolist()
        return tuple(joint_between(self.parts[a], self.parts[b]) or f for (a, b), f in zip(pairs, fallback))
