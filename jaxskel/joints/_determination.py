"""How well a recording determines each joint centre and bone length.

A joint centre is only as well placed as the motion makes it. The fixed-centre refit of
:mod:`jaxskel.joints._anchored_centres` minimises the marker-joint distance variance ``C(c)``
with the centre ``c`` fixed in an anchor segment, and reports at the minimum ``C*`` the
Hessian's eigenvectors ``v_k`` and *resolutions*

    r_k = sqrt(2 C* / lambda_k),

the distance along ``v_k`` over which the fitted misfit doubles. Where the two segments
turn about every axis, all three are millimetres to a few centimetres; where they turn
about one axis only (a hip in a walk, a knee), or barely at all, the weakest one runs to
decimetres, and anything along it, soft-tissue artefact included, moves the centre there
at almost no cost. This module reads those numbers as the recording's own statement of
how well it fixes the skeleton:

* :func:`joint_resolution`: per joint, the largest ``r_k`` that nothing else fixes. A
  hinge that the rigid stage placed along its axis in the plane of its neighbours
  (:mod:`jaxskel.skeleton._hinge_centres`) has its weakest direction, the axis, fixed by that
  placement, so its next ``r_k`` counts. The placement is the human convention (long
  bones across their flexion axes); where a body breaks it (random rods), the error
  along the axis is not in the resolution;
* :func:`bone_uncertainty`: per bone (two joints on one segment), how far its length can
  move with its joints inside their resolution ellipsoids ``sum_k r_k^2 v_k v_k^T``
  (the same directions left out): ``e_j = sqrt(sum_k (r_k |v_k . u|)^2)`` for the bone's
  unit direction ``u`` seen from joint ``j``, and ``sqrt(e_a^2 + e_b^2)`` for the bone. A
  hinge's axis runs across its bones, so it hardly lengthens them; a walk's hips, free
  along the line between them, make the pelvis width unknown but not the thighs;
* :func:`undetermined_joints`: the joints whose resolution exceeds
  :data:`UNDETERMINED_RESOLUTION` (10 cm), named by the fit (summary, result file and a
  :class:`jaxskel.DegenerateMotionWarning`);
* :func:`radial_share`, :func:`loose_directions`: which way the least determined
  direction runs, and how many are loose, and so which motion is missing. Along the
  line from the centre to the other segment's markers, the arc is too short to fix their
  distance from the centre (a larger range of rotation would); across it, the recording
  turns the joint about that direction only, and the centre slides along its axis
  (rotation about other axes would fix it).

Why 10 cm. It is a scale a user reads directly (a joint placed only to within a hand's
width is not identified by any standard of biomechanics), and it lies between the two
families of fits: a motion that turns every joint through its range fixes every centre
to within centimetres, while a motion that leaves joints barely turned (a walk's hips
and shoulders, part of the range at ankles and wrists) leaves them free over
decimetres, and those fits, wrong or loosely placed, say so here. The resolution is a sensitivity
to an artefact of the misfit's size, not an error bar: errors run at a fraction of it,
more only along the axis of a hinge the rigid stage could not place, where soft tissue
gives the flat direction some curvature. On real recordings most takes are short or
exercise some joints little, and the resolution says so joint by joint. (The
resolutions and errors measured on synthetic bodies and real recordings:
docs/bench/evidence_from_docstrings.md.)

Joints with no anchor (neither segment carries three non-collinear markers) have no
fixed-centre fit and report NaN: unknown, not determined. Joints the recording does not
exercise at all (:data:`jaxskel.joints._anchored_centres.MIN_EXERCISE_DEG`) are named by their
own warning and not again here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from .._errors import InputError

__all__ = [
    "UNDETERMINED_RESOLUTION", "UndeterminedJoint", "bone_uncertainty", "joint_resolution", "loose_directions",
    "radial_share", "undetermined_joints",
]

#: A joint whose centre the recording fixes only to within more than this (metres) is
#: named undetermined (module docstring).
UNDETERMINED_RESOLUTION = 0.1


class UndeterminedJoint(NamedTuple):
    """A tree joint whose centre the recording fixes only loosely (:func:`undetermined_joints`).

    ``joint`` indexes ``edges``; ``resolution`` (metres) is how far the centre can move
    along its least determined direction before the fit's misfit doubles.
    """

    joint: int
    resolution: float


def _require_skeleton(skeleton: Any, caller: str) -> None:
    """Raise :class:`InputError` unless ``skeleton`` looks like a :class:`jaxskel.skeleton.Skeleton`
    (the fields read here: ``diagnostics``, ``n_joints``, ``bones``)."""
    if not all(hasattr(skeleton, name) for name in ("diagnostics", "n_joints", "bones")):
        raise InputError(
            f"{caller}() takes the rigid skeleton of a fit (result.skeleton from jaxskel.fit_skeleton), "
            f"got {type(skeleton).__name__}"
        )


def _report(diagnostics: Mapping[str, Any], n_joints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(r, cosines, placed)`` from a skeleton's diagnostics: resolutions (J, 3) and bone
    cosines (J, J, 3), NaN where unknown, and (J,) whether a hinge was placed on its axis."""
    anchored = diagnostics.get("anchored") or {}
    r = np.asarray(anchored.get("resolution", np.full((n_joints, 3), np.nan)), dtype=float).reshape(n_joints, 3)
    cos = np.asarray(anchored.get("bone_cosines", np.full((n_joints, n_joints, 3), np.nan)), dtype=float)
    cos = cos.reshape(n_joints, n_joints, 3)
    axis = np.asarray(diagnostics.get("hinge_axis", np.full((n_joints, 3), np.nan)), dtype=float)
    placed = np.isfinite(axis.reshape(n_joints, 3)[:, 0])
    return r, cos, placed


def _free_directions(r: np.ndarray, placed: np.ndarray) -> np.ndarray:
    """(J, 3) resolutions with a placed hinge's weakest direction (its axis) set to 0."""
    r = r.copy()
    r[placed, 0] = 0.0
    return r


def joint_resolution(skeleton: Any) -> np.ndarray:
    """(J,) metres: the largest resolution of each joint's centre that nothing else fixes
    (module docstring); NaN for a joint with no fixed-centre fit.

    ``skeleton`` is a :class:`jaxskel.skeleton.Skeleton` fitted by :func:`jaxskel.fit_skeleton`
    (its ``diagnostics["anchored"]``); one from :func:`jaxskel.skeleton.fit_rigid` alone has no
    fixed-centre fit, and every joint reads NaN.
    """
    _require_skeleton(skeleton, "joint_resolution")
    r, _, placed = _report(skeleton.diagnostics, skeleton.n_joints)
    return np.max(_free_directions(r, placed), axis=1)


def bone_uncertainty(skeleton: Any) -> np.ndarray:
    """(B,) metres, for ``skeleton.bones``: how far each bone's length can move with its two
    joints inside their resolution ellipsoids (module docstring).

    A joint with no fixed-centre fit adds nothing, its own share being unknown, so where
    one end has none the figure is a lower bound (:func:`joint_resolution` is NaN there);
    NaN where neither end has one.
    """
    _require_skeleton(skeleton, "bone_uncertainty")
    bones = np.asarray(skeleton.bones, dtype=int).reshape(-1, 2)
    r, cos, placed = _report(skeleton.diagnostics, skeleton.n_joints)
    r = _free_directions(r, placed)
    along = np.sqrt(np.sum((r[:, None, :] * cos) ** 2, axis=-1))  # (J, J): joint j seen along the bone to i
    ends = np.stack([along[bones[:, 0], bones[:, 1]], along[bones[:, 1], bones[:, 0]]], axis=1)
    known = np.isfinite(ends).any(axis=1)
    return np.where(known, np.sqrt(np.nansum(ends**2, axis=1)), np.nan)


def radial_share(skeleton: Any) -> np.ndarray:
    """(J,) ``|v . u|`` for each joint's least determined direction that nothing else fixes
    (the one :func:`joint_resolution` reads) against the directions ``u`` from its centre to
    the other segment's markers, RMS over them: near 1 the markers' distance from the
    centre, near 0 an axis across them. NaN where unknown (no fixed-centre fit)."""
    _require_skeleton(skeleton, "radial_share")
    n_joints = skeleton.n_joints
    r, _, placed = _report(skeleton.diagnostics, n_joints)
    anchored = skeleton.diagnostics.get("anchored") or {}
    radial = np.asarray(anchored.get("radial_cosines", np.full((n_joints, 3), np.nan)), dtype=float)
    free = np.where(np.isfinite(r), _free_directions(r, placed), -np.inf)
    k = np.argmax(free, axis=1)
    return np.where(np.isfinite(r).all(axis=1), radial.reshape(n_joints, 3)[np.arange(n_joints), k], np.nan)


def loose_directions(skeleton: Any, *, limit: float = UNDETERMINED_RESOLUTION) -> np.ndarray:
    """(J,) how many of each joint's directions that nothing else fixes have a resolution
    above ``limit`` metres (0 where unknown)."""
    _require_skeleton(skeleton, "loose_directions")
    r, _, placed = _report(skeleton.diagnostics, skeleton.n_joints)
    return np.sum(np.nan_to_num(_free_directions(r, placed), nan=0.0) > limit, axis=1)


def undetermined_joints(skeleton: Any, *, limit: float = UNDETERMINED_RESOLUTION) -> list[UndeterminedJoint]:
    """Joints whose :func:`joint_resolution` exceeds ``limit`` metres, in joint order,
    leaving out those the recording does not exercise at all (named separately)."""
    from ._anchored_centres import MIN_EXERCISE_DEG

    _require_skeleton(skeleton, "undetermined_joints")
    n_joints = skeleton.n_joints
    resolution = joint_resolution(skeleton)
    anchored = skeleton.diagnostics.get("anchored") or {}
    exercise = np.asarray(anchored.get("exercise", np.full(n_joints, np.nan)), float)
    return [
        UndeterminedJoint(int(j), float(resolution[j]))
        for j in range(n_joints)
        if resolution[j] > limit and not exercise[j] < MIN_EXERCISE_DEG
    ]
