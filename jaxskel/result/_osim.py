"""OpenSim 4 model export of a fitted skeleton (an ``.osim`` file, written as XML).

Mapping (a host-side edge of jaxskel; numpy, scipy and the standard library's
ElementTree only: OpenSim itself is not needed to write the file):

* **Frames.** OpenSim's ground has Y up. A lab point ``p`` (up axis ``up_axis``) is
  ``C p`` in OpenSim, ``C = opensim_frame(up_axis)`` the proper quarter (or half) turn
  taking the up axis to +Y (:func:`jaxskel.io.rotation_between_axes`); for ``"z"``,
  ``(x, y, z) -> (x, z, -y)``, lab X stays OpenSim X. Each body frame is its segment
  frame (:class:`jaxskel.skeleton.Skeleton`) turned the same way: same origin, axes
  ``C`` times the segment's, so the bodies' axes are parallel to OpenSim's ground in the
  skeleton's rest pose. Offsets ``o`` in a segment frame become ``C o`` in the body
  frame, and a segment's orientation ``R`` (segment -> lab) becomes ``C R C^T``
  (body -> ground). Lengths are metres, gravity ``(0, -9.80665, 0)``.
* **Bodies.** One per segment, named after it; with a humanoid
  :class:`jaxskel.anatomy.Anatomy`, a segment whose part is identified takes OpenSim's
  gait2392 / Rajagopal body name (:data:`jaxskel.result._export_names.OPENSIM_BODY`:
  ``pelvis``, ``torso``, ``head``, ``femur_r``, ``tibia_r``, ``calcn_r``, ``toes_r``,
  ``humerus_r``, ``radius_r`` (the forearm is one body), ``hand_r``, and ``_l``). Mass and inertia are *placeholders*
  (:data:`PLACEHOLDER_MASS` kg, a diagonal inertia of :data:`PLACEHOLDER_INERTIA`
  kg m^2 about the centre of mass, put at the centroid of the segment's markers or the
  body origin without any): a marker fit says nothing about them, so the model serves
  kinematics (inverse kinematics, marker placement, visualisation), not dynamics, until
  they are replaced. The model's ``credits`` say so.
* **Joints.** The root body hangs on ground by a ``FreeJoint`` (both offset frames at the
  origins of ground and the root body, unrotated). Tree joint ``j`` (``edges[j]``, parent
  -> child) is a ``BallJoint`` whose offset frames sit at ``C joint_offsets[j, 0]`` in the
  parent body and ``C joint_offsets[j, 1]`` (zero) in the child, unrotated; where the
  skeleton has a hinge axis ``a`` for it (``diagnostics["hinge_axis"][j]`` finite, in the
  parent frame, and ``j`` not in ``diagnostics["hinges_unmoved"]``; with a ``motion``, also
  turning off that axis by at most :data:`PIN_MAX_OFF_AXIS` in 95 % of its frames) it is a ``PinJoint``,
  which turns about the Z axis of its joint frames: both offset frames are then rotated
  by ``Q``, an orthonormal basis of the body frame with third column ``C a / |C a|``
  (in the rest pose the child's axes equal the parent's, so ``a`` is the same vector in
  both). Joint ``j`` is named ``<parent>-<child>`` like :meth:`jaxskel.SkeletonResult.joint_name`,
  the free joint ``ground-<root>``; with a humanoid anatomy, a joint whose child's part is
  identified is named after it instead (:func:`jaxskel.anatomy.joint_name`: ``hip_r``,
  ``knee_r``, ``ankle_r``, ``shoulder_r``, ``elbow_r``, ``neck``, ...).
* **Coordinates** (OpenSim's conventions, checked against OpenSim 4.6): a ``BallJoint``
  ``<joint>_rx, _ry, _rz`` are body-fixed X-Y-Z Euler angles (radians) of the child's
  joint frame in the parent's, ``R = R_X(rx) R_Y(ry) R_Z(rz)`` (scipy's intrinsic
  ``"XYZ"``); the ``FreeJoint`` has the same three rotations, then ``<joint>_tx, _ty,
  _tz``, the root body's origin in ground. A ``PinJoint``'s one coordinate ``<joint>_angle``
  is the turn about the hinge axis, ``R = Q R_Z(angle) Q^T``. Ranges are wide (+-pi for
  rotations, at least +-10 m for translations) and nothing is clamped or locked.
  Offset frames' ``orientation`` uses the same body-fixed X-Y-Z angles.
* **Default pose.** With a ``motion``, the default coordinate values are its frame
  ``frame``: the root's ``C R C^T`` and ``C root_position``, each ball joint's
  relative rotation ``C R_parent^T R_child C^T``, each pin joint's angle
  ``atan2(M_10 - M_01, M_00 + M_11)`` of ``M = Q^T C R_parent^T R_child C^T Q``: the turn
  about the axis closest (Frobenius norm) to the relative rotation, which is exactly it
  when the joint turned about its axis only (jaxskel's inverse kinematics poses every
  joint as a ball, so a pin's off-axis part, small for a true hinge, is dropped). The
  default pose then puts the markers where ``motion.fitted_markers[frame]`` are, turned
  by ``C``, up to that part. Without a motion it is the rest pose (every rotation zero)
  with the root body's origin at ground's.
* **Markers.** A ``MarkerSet`` entry per marker on the skeleton (unused markers are
  left out), on its segment's body at ``C marker_offsets[m]``. Names are the input
  labels, made valid OpenSim names by :func:`opensim_names` (OpenSim refuses ``\\ / * +``
  and whitespace in a name; each run of them becomes ``_``), so a TRC file written with
  ``opensim_names(labels)`` and positions ``to_opensim_frame(positions, up_axis)`` is the
  recording in the model's frame and names.
"""

from __future__ import annotations

import os
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import InputError
from .._version import __version__
from ..io import atomic_output, check_output, rotation_between_axes
from ._bvh import euler_angles
from ._export_names import distinct, part_names

if TYPE_CHECKING:
    from ..anatomy import Anatomy
    from ..skeleton import Motion, Skeleton

__all__ = [
    "PIN_MAX_OFF_AXIS", "PLACEHOLDER_INERTIA", "PLACEHOLDER_MASS", "export_osim", "opensim_frame", "opensim_names",
    "to_opensim_frame",
]

#: Mass of every body (kg): a placeholder, not an estimate (module docstring).
PLACEHOLDER_MASS = 1.0
#: Principal moments of every body's inertia about its centre of mass (kg m^2): a placeholder.
PLACEHOLDER_INERTIA = 0.01

#: A hinge axis becomes a ``PinJoint`` only if the motion (when given) turns the joint off
#: that axis by at most this much (radians, 95th percentile of its frames); else a ``BallJoint``.
PIN_MAX_OFF_AXIS = float(np.deg2rad(10.0))

#: OpenSim's document version for a 4.0 model.
_DOCUMENT_VERSION = "40000"
_GRAVITY = (0.0, -9.80665, 0.0)
_UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
#: Translation coordinates' range: at least this (m) either way, more if the default needs it.
_TRANSLATION_RANGE = 10.0
#: Characters OpenSim refuses in a component name (Component::finalizeFromProperties).
_INVALID = re.compile(r"[\\/*+\s]+")


def opensim_frame(up_axis: str = "z") -> np.ndarray:
    """The (3, 3) proper rotation ``C`` from a lab frame with up axis ``up_axis`` (one of
    ``x, y, z, -x, -y, -z``) to OpenSim's frame (Y up): ``p_opensim = C p_lab``,
    ``C e_up = e_Y``; for ``"z"``, ``(x, y, z) -> (x, z, -y)`` (lab X stays X)."""
    if up_axis not in _UP_AXES:
        hint = " (a trial's unknown up axis can be set with trial.replace(up_axis=...))" if up_axis == "unknown" else ""
        raise InputError(f"up_axis must be the lab's up axis, one of {', '.join(_UP_AXES)}; got {up_axis!r}{hint}")
    return rotation_between_axes(up_axis, "y")


def to_opensim_frame(positions: np.ndarray, up_axis: str = "z") -> np.ndarray:
    """Lab-frame points ``positions`` (..., 3), e.g. a trial's markers (F, M, 3), in OpenSim's
    frame: ``C p`` with ``C = opensim_frame(up_axis)``. NaN (missing) stays NaN."""
    rot = opensim_frame(up_axis)
    p = np.asarray(positions, dtype=float)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise InputError(f"positions must have shape (..., 3), got {p.shape}")
    return p @ rot.T


def _valid_name(raw: str) -> str:
    """``raw`` with each run of characters OpenSim refuses made ``_`` (ends dropped); ``unnamed`` if empty."""
    raw = str(raw)
    return (_INVALID.sub("_", raw).strip("_") if _INVALID.search(raw) else raw) or "unnamed"


def opensim_names(names: Iterable[str], reserved: Iterable[str] = ()) -> tuple[str, ...]:
    """``names`` as valid, distinct OpenSim component names.

    Each run of characters OpenSim refuses (``\\ / * +``, whitespace) becomes ``_``
    (``LASI+RASI`` -> ``LASI_RASI``; leading and trailing ones are dropped), an empty
    name becomes ``unnamed``, and a name already taken (by an earlier name or by
    ``reserved``) gets ``_2``, ``_3``, ... A valid name is kept as it is.
    """
    return distinct((_valid_name(raw) for raw in names), reserved)


# ------------------------------------------------------------------ the maths
def _axis_frame(axis: np.ndarray) -> np.ndarray:
    """A proper orthonormal (3, 3) basis whose third column is the unit ``axis``."""
    z = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]  # the coordinate axis farthest from z
    x = helper - (helper @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _xyz(rot: np.ndarray) -> np.ndarray:
    """Body-fixed X-Y-Z Euler angles (radians) of ``rot`` (..., 3, 3): ``R = R_X R_Y R_Z``."""
    return euler_angles(rot, "XYZ", degrees=False)


def _pin_angle(m: np.ndarray) -> np.ndarray:
    """The angle of the turn about Z closest to ``m`` (..., 3, 3): argmax_t trace(R_Z(t)^T m)."""
    return np.arctan2(m[..., 1, 0] - m[..., 0, 1], m[..., 0, 0] + m[..., 1, 1])


def _hinge_axes(skeleton: Skeleton) -> np.ndarray:
    """(J, 3) each joint's hinge axis in the parent frame, NaN where it is a ball."""
    n_joints = skeleton.n_joints
    axes = np.asarray(skeleton.diagnostics.get("hinge_axis", np.full((n_joints, 3), np.nan)), dtype=float)
    axes = axes.reshape(-1, 3) if axes.size else np.full((n_joints, 3), np.nan)
    if axes.shape != (n_joints, 3):
        raise InputError(f"skeleton.diagnostics['hinge_axis'] must be ({n_joints}, 3), got {axes.shape}")
    axes = axes.copy()
    unmoved = [int(j) for j in skeleton.diagnostics.get("hinges_unmoved", [])]
    axes[unmoved] = np.nan
    axes[~(np.isfinite(axes).all(axis=1) & (np.linalg.norm(np.nan_to_num(axes), axis=1) > 0))] = np.nan
    return axes


def _off_axis_turns(skeleton: Skeleton, motion: Motion, axes: np.ndarray) -> np.ndarray:
    """(F, J) radians: how far each joint's relative rotation is from a turn about its hinge
    axis (``axes`` (J, 3), parent frame; NaN rows give NaN), frames where both segments
    are posed."""
    quats = np.asarray(motion.rotations, dtype=float)
    n_frames = quats.shape[0]
    out = np.full((n_frames, len(axes)), np.nan)
    seg = Rotation.from_quat(np.nan_to_num(quats.reshape(-1, 4), nan=0.0) + [[1e-300, 0, 0, 0]],
                             scalar_first=True).as_matrix().reshape(n_frames, -1, 3, 3)
    finite = np.isfinite(quats).all(axis=-1)
    for j, (p, c) in enumerate(np.asarray(skeleton.edges, dtype=int).tolist()):
        if not np.isfinite(axes[j]).all():
            continue
        q = _axis_frame(axes[j])
        m = q.T @ (np.swapaxes(seg[:, p], -1, -2) @ seg[:, c]) @ q  # (F, 3, 3)
        t = _pin_angle(m)
        about = Rotation.from_rotvec(np.stack([np.zeros_like(t), np.zeros_like(t), t], axis=1)).as_matrix()
        rest = np.swapaxes(about, -1, -2) @ m
        cos = np.clip((np.trace(rest, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
        out[:, j] = np.where(finite[:, p] & finite[:, c], np.arccos(cos), np.nan)
    return out


def _pose(skeleton: Skeleton, motion: Motion, frame: int, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``(orientations (S, 3, 3) body -> ground, root origin (3,), frame index >= 0)`` of
    ``motion``'s frame ``frame`` in OpenSim's frame (``rot`` = C)."""
    quats = np.asarray(motion.rotations)
    if quats.ndim != 3:
        raise InputError("export_osim poses one trial; index the motion's leading trial axis first")
    n_frames, n_seg = quats.shape[0], skeleton.n_segments
    if quats.shape[1] != n_seg:
        raise InputError(f"motion has {quats.shape[1]} segments, the skeleton {n_seg}")
    if not -n_frames <= int(frame) < n_frames:
        raise InputError(f"frame {frame} is out of range for a motion of {n_frames} frames")
    q = quats[int(frame)]
    root = np.asarray(motion.root_position)[int(frame)]
    if not (np.isfinite(q).all() and np.isfinite(root).all()):
        raise InputError(f"the motion's frame {frame} is not posed (NaN); choose another frame")
    seg = Rotation.from_quat(q, scalar_first=True).as_matrix()
    return rot @ seg @ rot.T, rot @ root, int(frame) % n_frames


def _joint_labels(edges: np.ndarray, names: Sequence[str], anatomy: Anatomy | None) -> list[str]:
    """Each joint's name: ``<parent>-<child>``, or its anatomical name for a humanoid's identified child."""
    from ..anatomy import joint_name

    humanoid = anatomy is not None and anatomy.humanoid
    return [(humanoid and joint_name(anatomy.parts[c])) or f"{names[p]}-{names[c]}" for p, c in edges.tolist()]


# ---------------------------------------------------------------------- XML
def _num(v: float) -> str:
    return format(float(v), ".17g")


def _vec(v: Iterable[float]) -> str:
    return " ".join(_num(a) for a in v)


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, tag, attrs)
    if text is not None:
        el.text = text
    return el


def _offset_frame(frames: ET.Element, name: str, body_path: str, translation: np.ndarray, orientation: np.ndarray) -> None:
    f = _sub(frames, "PhysicalOffsetFrame", name=name)
    _sub(f, "socket_parent", body_path)
    _sub(f, "translation", _vec(translation))
    _sub(f, "orientation", _vec(orientation))


def _coordinate(coords: ET.Element, name: str, value: float, limit: float) -> None:
    c = _sub(coords, "Coordinate", name=name)
    _sub(c, "default_value", _num(value))
    _sub(c, "default_speed_value", "0")
    _sub(c, "range", _vec((-limit, limit)))
    _sub(c, "clamped", "false")
    _sub(c, "locked", "false")


def _credits(up_axis: str, rot: np.ndarray, frame: int | None) -> str:
    rows = "; ".join(_vec(r) for r in rot)
    pose = f"frame {frame} of the fitted motion" if frame is not None else "the rest pose, the root at the origin"
    return (
        f"Generated by jaxskel {__version__} from a skeleton fitted to motion-capture markers. "
        f"Lab frame up axis {up_axis}; lab -> OpenSim rotation C (rows: {rows}), p_opensim = C p_lab. "
        f"Default pose: {pose}. Mass ({_num(PLACEHOLDER_MASS)} kg per body) and inertia "
        f"({_num(PLACEHOLDER_INERTIA)} kg m^2 principal moments) are PLACEHOLDERS, not estimates: "
        "use this model for kinematics only unless they are replaced."
    )


def export_osim(
    skeleton: Skeleton,
    path: str | os.PathLike[str],
    *,
    motion: Motion | None = None,
    frame: int = 0,
    up_axis: str = "z",
    segment_names: Sequence[str] | None = None,
    overwrite: bool = False,
    model_name: str = "jaxskel",
    anatomy: Anatomy | None = None,
) -> Path:
    """Write a fitted skeleton as an OpenSim 4 model (``.osim``), atomically.

    The mapping (frames, bodies, joints, coordinates, markers) is in the module
    docstring. Mass and inertia are placeholders (:data:`PLACEHOLDER_MASS`,
    :data:`PLACEHOLDER_INERTIA`), recorded as such in the model's ``credits``, with the
    lab up axis and the lab -> OpenSim rotation.

    Parameters
    ----------
    skeleton
        From :func:`jaxskel.skeleton.fit_rigid` (``SkeletonResult.skeleton``).
    path
        Destination ``.osim`` file; an existing file is replaced only with ``overwrite``.
    motion
        A motion of the skeleton (one trial, :func:`jaxskel.skeleton.inverse_kinematics`):
        the model's default pose is then its frame ``frame``. Without it, the rest pose
        with the root body's origin at ground's.
    frame
        The frame of ``motion`` to use as the default pose (negative counts from the end).
    up_axis
        The lab's up axis, one of ``x, y, z, -x, -y, -z`` (:func:`opensim_frame`).
    segment_names
        Body names, one per segment (default: :meth:`Skeleton.names`, the skeleton's
        segment names or readable names from its marker labels), made valid OpenSim names
        (:func:`opensim_names`); given names must stay distinct.
    model_name
        The model's name.
    anatomy
        The body parts of the segments (:class:`jaxskel.anatomy.Anatomy`): with a humanoid
        one, identified segments and their joints take OpenSim's names (module docstring);
        the others keep ``segment_names``.

    Returns the path written. Raises :class:`jaxskel.InputError` for a bad path (not
    ``.osim``, a folder, an existing file without ``overwrite``), up axis, names or motion.
    """
    check_output(path, "osim")  # before any work: a folder, not .osim, an unwritable folder
    rot = opensim_frame(up_axis)
    n_seg = skeleton.n_segments
    if anatomy is not None and len(anatomy.parts) != n_seg:
        raise InputError(f"the anatomy names {len(anatomy.parts)} segments, the skeleton has {n_seg}")
    if segment_names is None:
        names = opensim_names(part_names(anatomy, skeleton.names(), "opensim", skeleton.edges), reserved=("ground",))
    else:
        names = tuple(_valid_name(v) for v in segment_names)
        if len(names) != n_seg or len(set(names)) != n_seg or "ground" in names:
            raise InputError(
                f"segment_names must be {n_seg} distinct names other than 'ground' (after making them valid "
                f"OpenSim names: {', '.join(names)})"
            )
        names = opensim_names(part_names(anatomy, names, "opensim", skeleton.edges), reserved=("ground",))
    edges = np.asarray(skeleton.edges, dtype=int)
    root = int(skeleton.root)
    axes = _hinge_axes(skeleton)
    if motion is not None and np.isfinite(axes).any():
        # a hinge the motion turns well off its axis (a universal joint whose centre slid
        # like a hinge's) is exported as a ball: a pin would force that turn out
        off = _off_axis_turns(skeleton, motion, axes)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: joints without an axis
            typical = np.nanpercentile(off, 95, axis=0)
        axes[np.isfinite(typical) & (typical > PIN_MAX_OFF_AXIS)] = np.nan
    joint_names = opensim_names(_joint_labels(edges, names, anatomy), reserved=[f"ground-{names[root]}"])
    root_joint = f"ground-{names[root]}"

    # Default pose (OpenSim frame): body orientations and the root origin.
    if motion is not None:
        orient, root_origin, pose_frame = _pose(skeleton, motion, frame, rot)
    else:
        orient, root_origin, pose_frame = np.broadcast_to(np.eye(3), (n_seg, 3, 3)), np.zeros(3), None

    model_doc = ET.Element("OpenSimDocument", Version=_DOCUMENT_VERSION)
    model = _sub(model_doc, "Model", name=opensim_names([model_name])[0])
    _sub(model, "credits", _credits(up_axis, rot, pose_frame))
    _sub(model, "publications",
         "Skeleton fitted by jaxskel after Kirk, O'Brien and Forsyth, Skeletal parameter estimation from "
         "optical motion capture data, CVPR 2005. Body mass and inertia are placeholders.")
    _sub(model, "length_units", "meters")
    _sub(model, "force_units", "N")
    _sub(model, "gravity", _vec(_GRAVITY))

    # Bodies.
    used = (np.asarray(skeleton.marker_segment) >= 0) & np.isfinite(skeleton.marker_offsets).all(axis=1)
    offsets = np.asarray(skeleton.marker_offsets) @ rot.T  # body frames
    bodies = _sub(_sub(model, "BodySet", name="bodyset"), "objects")
    for s in range(n_seg):
        on = used & (np.asarray(skeleton.marker_segment) == s)
        centre = offsets[on].mean(axis=0) if on.any() else np.zeros(3)
        b = _sub(bodies, "Body", name=names[s])
        _sub(b, "mass", _num(PLACEHOLDER_MASS))
        _sub(b, "mass_center", _vec(centre))
        _sub(b, "inertia", _vec([PLACEHOLDER_INERTIA] * 3 + [0.0] * 3))

    # Joints: the free root joint, then every tree edge.
    joints = _sub(_sub(model, "JointSet", name="jointset"), "objects")
    free = _sub(joints, "FreeJoint", name=root_joint)
    _sub(free, "socket_parent_frame", "ground_offset")
    _sub(free, "socket_child_frame", f"{names[root]}_offset")
    coords = _sub(free, "coordinates")
    for axis, value in zip("xyz", _xyz(orient[root])):
        _coordinate(coords, f"{root_joint}_r{axis}", value, np.pi)
    t_limit = max(_TRANSLATION_RANGE, 2.0 * float(np.max(np.abs(root_origin))))
    for axis, value in zip("xyz", root_origin):
        _coordinate(coords, f"{root_joint}_t{axis}", value, t_limit)
    frames = _sub(free, "frames")
    _offset_frame(frames, "ground_offset", "/ground", np.zeros(3), np.zeros(3))
    _offset_frame(frames, f"{names[root]}_offset", f"/bodyset/{names[root]}", np.zeros(3), np.zeros(3))

    jo = np.asarray(skeleton.joint_offsets) @ rot.T  # (J, 2, 3) in the body frames
    for j, (p, c) in enumerate(edges.tolist()):
        name = joint_names[j]
        relative = orient[p].T @ orient[c]
        pin = np.isfinite(axes[j]).all()
        if pin:
            basis = _axis_frame(rot @ axes[j])
            frame_angles = _xyz(basis)
            el = _sub(joints, "PinJoint", name=name)
        else:
            basis, frame_angles = np.eye(3), np.zeros(3)
            el = _sub(joints, "BallJoint", name=name)
        parent_frame, child_frame = f"{names[p]}_offset", f"{names[c]}_offset"
        _sub(el, "socket_parent_frame", parent_frame)
        _sub(el, "socket_child_frame", child_frame)
        coords = _sub(el, "coordinates")
        if pin:
            _coordinate(coords, f"{name}_angle", float(_pin_angle(basis.T @ relative @ basis)), np.pi)
        else:
            for axis, value in zip("xyz", _xyz(relative)):
                _coordinate(coords, f"{name}_r{axis}", value, np.pi)
        frames = _sub(el, "frames")
        _offset_frame(frames, parent_frame, f"/bodyset/{names[p]}", jo[j, 0], frame_angles)
        _offset_frame(frames, child_frame, f"/bodyset/{names[c]}", jo[j, 1], frame_angles)

    # Markers.
    marker_names = opensim_names(skeleton.marker_labels)
    markers = _sub(_sub(model, "MarkerSet", name="markerset"), "objects")
    for m in np.flatnonzero(used):
        el = _sub(markers, "Marker", name=marker_names[m])
        _sub(el, "socket_parent_frame", f"/bodyset/{names[int(skeleton.marker_segment[m])]}")
        _sub(el, "location", _vec(offsets[m]))
        _sub(el, "fixed", "false")

    ET.indent(model_doc, space="\t")
    target = Path(path)
    with atomic_output(target, overwrite) as tmp:
        ET.ElementTree(model_doc).write(tmp, encoding="UTF-8", xml_declaration=True)
    return target
