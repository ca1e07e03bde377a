"""Names of a fitted skeleton's segments in the files other tools read (BVH, OpenSim).

* :func:`ascii_names`: any names as distinct ASCII identifiers. Each name is decomposed
  (Unicode NFKD), what is not ASCII is dropped (``Kné€`` -> ``Kne``), every run of
  characters other than letters, digits and ``_`` becomes one ``_`` (``L+R`` -> ``L_R``),
  leading and trailing ``_`` are dropped, a name starting with a digit gets a leading
  ``_``, an empty name becomes ``segment``, and names are cut to :data:`MAX_NAME` characters
  (Blender keeps 63 bytes of a bone name). A name already taken gets ``_2``, ``_3``, ...
* :data:`MIXAMO`: part -> Mixamo bone name (the names MotionBuilder's HumanIK and most
  retargeting tools recognise). The vocabulary has no neck part: the head segment, which
  turns at the neck joint, is ``Head``; the thorax is ``Spine1`` above an identified
  abdomen (``Spine``), else ``Spine``.
* :data:`OPENSIM_BODY`: part -> body name of OpenSim's gait2392 / Rajagopal models
  (``femur_r``, ``tibia_r``, ``calcn_r``, ...); the forearm is one body, ``radius``.
* :func:`part_names`: the names of every segment under a convention, falling back to the
  given segment names where the part is not identified.
"""

from __future__ import annotations

import re
import unicodedata
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from .._errors import InputError

if TYPE_CHECKING:
    from ..anatomy import Anatomy

__all__ = ["MAX_NAME", "MIXAMO", "OPENSIM_BODY", "ascii_name", "ascii_names", "part_names"]

#: Longest name written (characters), so that a ``_<k>`` suffix stays within Blender's 63 bytes.
MAX_NAME = 56

_SIDE_WORD = {"l": "Left", "r": "Right"}

MIXAMO: dict[str, str] = {"pelvis": "Hips", "abdomen": "Spine", "thorax": "Spine1", "head": "Head"}
OPENSIM_BODY: dict[str, str] = {"pelvis": "pelvis", "abdomen": "abdomen", "thorax": "torso", "head": "head"}
for _s, _w in _SIDE_WORD.items():
    MIXAMO.update({
        f"clavicle_{_s}": f"{_w}Shoulder", f"upper_arm_{_s}": f"{_w}Arm", f"forearm_{_s}": f"{_w}ForeArm",
        f"hand_{_s}": f"{_w}Hand", f"thigh_{_s}": f"{_w}UpLeg", f"shank_{_s}": f"{_w}Leg",
        f"foot_{_s}": f"{_w}Foot", f"toes_{_s}": f"{_w}ToeBase",
    })
    OPENSIM_BODY.update({
        f"clavicle_{_s}": f"clavicle_{_s}", f"upper_arm_{_s}": f"humerus_{_s}", f"forearm_{_s}": f"radius_{_s}",
        f"hand_{_s}": f"hand_{_s}", f"thigh_{_s}": f"femur_{_s}", f"shank_{_s}": f"tibia_{_s}",
        f"foot_{_s}": f"calcn_{_s}", f"toes_{_s}": f"toes_{_s}",
    })
del _s, _w

_CONVENTIONS = ("mixamo", "jaxskel", "labels", "opensim")


def ascii_name(raw: str) -> str:
    """One name as an ASCII identifier (module docstring; no de-duplication)."""
    text = unicodedata.normalize("NFKD", str(raw)).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^A-Za-z0-9_]+", "_", text)
    text = re.sub(r"_{2,}", "_", text).strip("_")[:MAX_NAME].rstrip("_")
    if text[:1].isdigit():
        text = "_" + text
    return text or "segment"


def distinct(bases: Iterable[str], reserved: Iterable[str] = ()) -> tuple[str, ...]:
    """``bases`` made distinct, in order: a name already taken (by an earlier one or by
    ``reserved``) gets ``_2``, ``_3``, ..."""
    taken = set(reserved)
    out = []
    for base in bases:
        name, k = base, 2
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        out.append(name)
    return tuple(out)


def ascii_names(names: Iterable[str], reserved: Iterable[str] = ()) -> tuple[str, ...]:
    """``names`` as distinct ASCII identifiers (module docstring); ``reserved`` names are taken."""
    return distinct((ascii_name(raw) for raw in names), reserved)


def part_names(
    anatomy: Anatomy | None, labels: Sequence[str], convention: str | Mapping[str, str] | None,
    edges: np.ndarray | None = None,
) -> tuple[str, ...]:
    """The raw (unsanitised) name of every segment.

    ``convention``: ``"mixamo"`` (:data:`MIXAMO`), ``"opensim"`` (:data:`OPENSIM_BODY`),
    ``"jaxskel"`` (the part names), ``"labels"`` (``labels`` as they are), or a mapping
    part -> name. Segments without a part (or without an anatomy, or a body that is not
    human) keep their ``labels``; so does a part a mapping leaves out. ``None`` means
    ``"mixamo"`` for a humanoid anatomy, else ``"labels"``. Where one part names several
    segments, the one in the chain of the tree ``edges`` (:meth:`Anatomy.main_segments`)
    takes the plain name and the others ``<name>_2``.
    """
    humanoid = anatomy is not None and anatomy.humanoid
    if convention is None:
        convention = "mixamo" if humanoid else "labels"
    if isinstance(convention, str):
        if convention not in _CONVENTIONS:
            raise InputError(f"names must be one of {', '.join(_CONVENTIONS)} or a mapping part -> name; "
                             f"got {convention!r}")
        if convention == "labels" or not humanoid:
            return tuple(labels)
        table: Mapping[str, str] = {"mixamo": _mixamo(anatomy), "opensim": OPENSIM_BODY}.get(
            convention, {p: p for p in MIXAMO})
    elif isinstance(convention, Mapping):
        table = convention
        if not humanoid:
            return tuple(labels)
    else:
        raise InputError(f"names must be a convention name or a mapping part -> name, got {type(convention).__name__}")
    if len(anatomy.parts) != len(labels):
        raise InputError(f"the anatomy names {len(anatomy.parts)} segments, the skeleton has {len(labels)}")
    main = anatomy.main_segments(edges)
    return tuple((str(table[p]) if m else f"{table[p]}_2") if p and p in table else lab
                 for p, lab, m in zip(anatomy.parts, labels, main))


def _mixamo(anatomy: Anatomy) -> dict[str, str]:
    """:data:`MIXAMO`, the thorax ``Spine`` when no segment is the abdomen."""
    table = dict(MIXAMO)
    if "abdomen" not in anatomy.parts:
        table["thorax"] = "Spine"
    return table
