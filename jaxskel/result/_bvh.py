"""BVH (Biovision hierarchy) export of a fitted skeleton and motion, and a reader.

Mapping (a host-side edge of jaxskel; numpy and scipy only):

* **Axes: Y up, facing +Z.** A lab point ``p`` is written as ``C p`` (:func:`bvh_frame`).
  With an :class:`jaxskel.anatomy.Anatomy`, ``C`` has rows ``(left, up, front)``
  (``front`` made orthogonal to ``up``): the body's up is +Y, its front +Z and its left
  +X, the frame MotionBuilder, Maya and Blender's importer expect. Without one, ``C`` is
  the quarter (or half) turn taking the recording's ``up_axis`` to +Y
  (:func:`jaxskel.io.rotation_between_axes`; for ``"z"``: ``(x, y, z) -> (x, z, -y)``),
  the facing kept; ``up_axis="unknown"`` keeps the lab axes.
* **Joints.** Each segment is one BVH joint at its proximal joint (the root segment: at
  its origin, the centroid of its markers). A leaf ends in an ``End Site`` at the
  centroid of its markers.
* **Rest pose** (every channel zero). Each segment has a rest orientation ``T_s`` (a
  rotation of BVH space) and ``OFFSET`` of the joint of child ``c`` is
  ``T_p C (o_j,0 - n_p)``: its joint in the parent frame, less the parent's node origin
  ``n_p``, turned by the parent's rest orientation. With a humanoid anatomy this is a
  **T-pose**: each segment of a chain is turned by the smallest rotation taking its
  bone (node origin to the next joint down the chain, or to its markers' centroid at the
  chain's end) to the T-pose direction: abdomen, thorax and head +Y (up); clavicle,
  upper arm, forearm and hand level sideways (left +X, right -X); thigh and shank -Y
  (down); foot and toes forward (+Z, their bone's pitch kept: the heading turned to +Z).
  The pelvis keeps its fitted orientation (``T = I``); a segment whose part is not
  identified, and the second piece of a part (a one-marker twig on its host's part:
  :meth:`jaxskel.anatomy.Anatomy.main_segments`), turns with its parent (``T_s = T_parent``). The bones keep their fitted
  lengths. Without an anatomy, or for a body that is not human, ``T_s = I``: the
  skeleton's default pose (every segment frame at its rest orientation, world-aligned in
  the lab frame, :mod:`jaxskel.skeleton._rigid_fit`), turned by ``C``.
* **Channels.** The root has position channels (``C`` times the world position of its
  node origin) and every joint three rotation channels, by default ``Zrotation
  Xrotation Yrotation``, in degrees: the local rotation ``L_s = G_p^T G_s`` with
  ``G_s = C R_s C^T T_s^T`` (``R_s`` the segment's orientation, segment -> lab), as
  intrinsic Euler angles in channel order, ``L = R_Z(a) R_X(b) R_Y(c)``. Then
  ``G_p OFFSET_c = C R_p (o_j,0 - n_p)``: the BVH's joint positions in every frame are
  ``C`` times the fit's joint positions, whatever the rest pose.
* **Names** (:mod:`jaxskel.result._export_names`): Mixamo's bone names for a humanoid by
  default (``Hips``, ``Spine``, ``LeftUpLeg``, ...), else the segment names; always
  distinct ASCII identifiers (no ``+``, non-ASCII letters transliterated).
* Lengths in centimetres (``units="cm"``, the default: the unit of Mixamo's, MotionBuilder's
  and Maya's BVH files; Blender reads it at 100 units per metre unless imported with
  ``global_scale=0.01``) or metres (``units="m"``).

:func:`read_bvh` parses any BVH file (arbitrary channel sets and orders) into
:class:`BvhData`, whose :meth:`BvhData.world_positions` is an independent forward
kinematics used to check the export.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import InputError
from ..anatomy import CHAINS
from ..io import atomic_output, check_output, rotation_between_axes
from ._export_names import ascii_names, part_names

if TYPE_CHECKING:
    from ..anatomy import Anatomy
    from ..skeleton import Motion, Skeleton

__all__ = ["BvhData", "bvh_frame", "bvh_rest_orientations", "export_bvh", "read_bvh"]

_UNITS = {"m": 1.0, "cm": 100.0}
_AXES = {"X": 0, "Y": 1, "Z": 2}
_UP_AXES = ("x", "y", "z", "-x", "-y", "-z")

_CHAIN_OF = {part: chain for chain in CHAINS for part in chain}
#: T-pose direction of each part's bone in BVH axes ("forward": +Z, pitch kept).
_T_DIRECTION: dict[str, tuple[float, float, float] | str] = {"abdomen": (0, 1, 0), "thorax": (0, 1, 0),
                                                            "head": (0, 1, 0)}
for _s, _x in (("l", 1.0), ("r", -1.0)):
    _T_DIRECTION.update({f"{p}_{_s}": (_x, 0, 0) for p in ("clavicle", "upper_arm", "forearm", "hand")})
    _T_DIRECTION.update({f"thigh_{_s}": (0, -1, 0), f"shank_{_s}": (0, -1, 0), f"foot_{_s}": "forward",
                         f"toes_{_s}": "forward"})
del _s, _x


def euler_angles(local: np.ndarray, order: str, *, degrees: bool = True) -> np.ndarray:
    """Intrinsic Euler angles (degrees, or radians) in ``order`` with ``R = R_o1 R_o2 R_o3``
    of the rotation matrices ``local`` (..., 3, 3)."""
    with warnings.catch_warnings():
        # Gimbal lock: scipy picks one of the equivalent solutions, which still
        # reproduces the rotation matrix exactly.
        warnings.simplefilter("ignore", UserWarning)
        return Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler(order, degrees=degrees).reshape(
            *local.shape[:-2], 3
        )


def bvh_frame(anatomy: Anatomy | None = None, up_axis: str = "z") -> np.ndarray:
    """The (3, 3) proper rotation ``C`` from the lab frame to the BVH's (module docstring):
    rows ``(left, up, front)`` of ``anatomy``, else the turn of ``up_axis`` to +Y."""
    if anatomy is None:
        if up_axis == "unknown":
            return np.eye(3)
        if up_axis not in _UP_AXES:
            raise InputError(f"up_axis must be one of {', '.join(_UP_AXES)} or 'unknown'; got {up_axis!r}")
        return rotation_between_axes(up_axis, "y")
    up, front = np.asarray(anatomy.up, float), np.asarray(anatomy.front, float)
    if up.shape != (3,) or front.shape != (3,) or not (np.isfinite(up).all() and np.isfinite(front).all()):
        raise InputError("the anatomy's up and front must be finite 3-vectors")
    n_up = np.linalg.norm(up)
    front = front - (front @ up) / max(n_up, 1e-300) ** 2 * up
    if n_up < 1e-9 or np.linalg.norm(front) < 1e-6 * max(np.linalg.norm(anatomy.front), 1e-300):
        raise InputError("the anatomy's up and front must be non-zero and not parallel")
    up, front = up / n_up, front / np.linalg.norm(front)
    return np.stack([np.cross(up, front), up, front])


def _node_origins(skeleton: Skeleton) -> np.ndarray:
    """(S, 3) each segment's BVH node origin in its own frame (its proximal joint; root: 0)."""
    origin = np.zeros((skeleton.n_segments, 3))
    origin[skeleton.edges[:, 1]] = skeleton.joint_offsets[:, 1]
    return origin


def _marker_centroids(skeleton: Skeleton) -> np.ndarray:
    """(S, 3) centroid of each segment's markers in its frame (NaN without any)."""
    seg = np.asarray(skeleton.marker_segment)
    on = (seg >= 0) & np.isfinite(skeleton.marker_offsets).all(axis=1)
    out = np.full((skeleton.n_segments, 3), np.nan)
    for s in np.unique(seg[on]):
        out[s] = skeleton.marker_offsets[on & (seg == s)].mean(axis=0)
    return out


def _tree_order(skeleton: Skeleton) -> list[int]:
    """Segments depth-first from the root, children in joint order."""
    children: list[list[int]] = [[] for _ in range(skeleton.n_segments)]
    for p, c in skeleton.edges.tolist():
        children[p].append(c)
    order, stack = [], [int(skeleton.root)]
    while stack:
        s = stack.pop()
        order.append(s)
        stack.extend(reversed(children[s]))
    return order


def _bone(skeleton: Skeleton, parts: Sequence[str], s: int, origin: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Segment ``s``'s bone in its frame: node origin to the joint of its nearest child down
    its chain, else to its markers' centroid (NaN where it has neither)."""
    chain = _CHAIN_OF[parts[s]]
    rank = chain.index(parts[s])
    best, vector = len(chain), centroid[s] - origin[s]
    for j, (p, c) in enumerate(skeleton.edges.tolist()):
        if p == s and parts[c] in chain and rank < chain.index(parts[c]) < best:
            best, vector = chain.index(parts[c]), skeleton.joint_offsets[j, 0] - origin[s]
    return vector


def _turn(d: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction ``d`` to direction ``target``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # one vector: scipy says the rotation is not unique
        return Rotation.align_vectors(target[None], d[None])[0].as_matrix()


def bvh_rest_orientations(skeleton: Skeleton, anatomy: Anatomy | None, frame: np.ndarray) -> np.ndarray:
    """(S, 3, 3) each segment's rest orientation ``T_s`` in BVH axes (module docstring): the
    T-pose for a humanoid ``anatomy``, else identities. ``frame`` is ``C`` (:func:`bvh_frame`)."""
    n_seg = skeleton.n_segments
    rest = np.broadcast_to(np.eye(3), (n_seg, 3, 3)).copy()
    if anatomy is None or not anatomy.humanoid:
        return rest
    parts = anatomy.parts
    origin, centroid = _node_origins(skeleton), _marker_centroids(skeleton)
    parent, main = skeleton.parent, anatomy.main_segments(skeleton.edges)
    for s in _tree_order(skeleton):  # parents first: an unnamed segment takes its parent's
        if parent[s] >= 0 and parts[s] != "pelvis":
            rest[s] = rest[parent[s]]
        direction = _T_DIRECTION.get(parts[s])
        if direction is None or not main[s]:  # the pelvis, the root, an unnamed segment, a part's second piece
            continue
        d = frame @ _bone(skeleton, parts, s, origin, centroid)
        if not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
            continue
        target = np.array([0.0, d[1], np.hypot(d[0], d[2])]) if direction == "forward" else np.asarray(direction, float)
        rest[s] = _turn(d, target / np.linalg.norm(target))
    return rest


def _segment_names(
    skeleton: Skeleton, labels: Sequence[str] | None, anatomy: Anatomy | None,
    names: str | Mapping[str, str] | None,
) -> tuple[str, ...]:
    """The BVH joint names (ASCII, distinct) of every segment."""
    n_seg = skeleton.n_segments
    base = skeleton.names() if labels is None else tuple(str(v) for v in labels)
    if len(base) != n_seg:
        raise InputError(f"labels must be {n_seg} segment names, got {len(base)}")
    if labels is not None and len(set(base)) != n_seg:
        raise InputError(f"labels must be {n_seg} distinct segment names")
    if anatomy is not None and len(anatomy.parts) != n_seg:
        raise InputError(f"the anatomy names {len(anatomy.parts)} segments, the skeleton has {n_seg}")
    return ascii_names(part_names(anatomy, base, names, skeleton.edges))


def export_bvh(
    skeleton: Skeleton,
    motion: Motion,
    path: str | os.PathLike[str],
    *,
    rate: float | None = None,
    overwrite: bool = False,
    units: str = "cm",
    labels: Sequence[str] | None = None,
    rotation_order: str = "ZXY",
    anatomy: Anatomy | None = None,
    names: str | Mapping[str, str] | None = None,
    up_axis: str = "z",
) -> Path:
    """Write a skeleton and its motion as a BVH file (atomically), Y up, facing +Z.

    The mapping (axes, rest pose, channels, names) is in the module docstring.

    Parameters
    ----------
    skeleton, motion
        From :func:`jaxskel.skeleton.fit_rigid` and :func:`jaxskel.skeleton.inverse_kinematics` (one trial).
    path
        Destination ``.bvh`` file; an existing file is replaced only with ``overwrite``.
    rate
        Frames per second (default: ``motion.rate``).
    units
        ``"cm"`` (default) or ``"m"`` for offsets and root positions.
    labels
        Segment names (default: :meth:`Skeleton.names`, the skeleton's segment names or
        readable names from its marker labels): the names under ``names="labels"`` and of
        the segments whose part is not identified. Must be distinct.
    rotation_order
        Order of the three rotation channels, a permutation of ``"XYZ"``.
    anatomy
        The body parts of the skeleton's segments and the body's up and front
        (:class:`jaxskel.anatomy.Anatomy`): they set the axes, and a humanoid's T-pose
        rest and names. ``None``: the lab frame turned by ``up_axis``, the default pose as
        rest, the segment names.
    names
        ``"mixamo"`` (the default for a humanoid), ``"jaxskel"`` (part names),
        ``"opensim"`` (OpenSim body names), ``"labels"`` (the default otherwise) or a
        mapping part -> name. Written as distinct ASCII identifiers.
    up_axis
        The lab's up axis (``x, y, z, -x, -y, -z`` or ``"unknown"``), used without an anatomy.

    Returns the path written. Raises :class:`jaxskel.InputError` for a bad argument.
    """
    check_output(path, "bvh")  # before any work: a folder, not .bvh, an unwritable folder
    if units not in _UNITS:
        raise InputError(f"units must be 'm' or 'cm', got {units!r}")
    order = str(rotation_order).upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise InputError(f"rotation_order must be a permutation of 'XYZ', got {rotation_order!r}")
    rate = motion.rate if rate is None else rate
    if rate is None or not np.isfinite(rate) or rate <= 0:
        raise InputError("export_bvh needs the frame rate: pass rate= (Hz) or a Motion from a Trial")
    if motion.rotations.ndim != 3:
        raise InputError("export_bvh writes one trial; index the motion's leading trial axis first")
    n_seg = skeleton.n_segments
    if motion.rotations.shape[1] != n_seg:
        raise InputError(f"motion has {motion.rotations.shape[1]} segments, the skeleton {n_seg}")
    joint_names = _segment_names(skeleton, labels, anatomy, names)
    frame = bvh_frame(anatomy, up_axis)
    rest = bvh_rest_orientations(skeleton, anatomy, frame)
    hierarchy, dfs = _hierarchy(skeleton, joint_names, frame, rest, _UNITS[units], order)
    values = _channels(skeleton, motion, frame, rest, dfs, _UNITS[units], order)
    n_frames = values.shape[0]
    lines = [*hierarchy, "MOTION", f"Frames: {n_frames}", f"Frame Time: {1.0 / float(rate):.9g}"]
    body = "\n".join(" ".join(f"{v:.10g}" for v in row) for row in values)
    text = "\n".join(lines) + "\n" + body + ("\n" if n_frames else "")
    target = Path(path)
    with atomic_output(target, overwrite) as tmp:
        tmp.write_text(text, encoding="ascii")  # every name is ASCII (ascii_names)
    return target


def _hierarchy(
    skeleton: Skeleton, names: Sequence[str], frame: np.ndarray, rest: np.ndarray, scale: float, order: str,
) -> tuple[list[str], list[int]]:
    """The HIERARCHY lines and the segments in their (depth-first) order."""
    edges = skeleton.edges
    origin, centroid = _node_origins(skeleton), _marker_centroids(skeleton)
    children: list[list[int]] = [[] for _ in range(skeleton.n_segments)]
    for j, p in enumerate(edges[:, 0].tolist()):
        children[p].append(j)
    rot_channels = " ".join(f"{a}rotation" for a in order)
    lines, dfs = ["HIERARCHY"], []

    def fmt(v: np.ndarray) -> str:
        return " ".join(f"{float(a):.9g}" for a in v * scale)

    def write(s: int, depth: int, offset: np.ndarray) -> None:
        dfs.append(s)
        pad = "\t" * depth
        root = s == skeleton.root
        lines.extend([f"{pad}{'ROOT' if root else 'JOINT'} {names[s]}", f"{pad}{{", f"{pad}\tOFFSET {fmt(offset)}"])
        lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}" if root
                     else f"{pad}\tCHANNELS 3 {rot_channels}")
        for j in children[s]:
            write(int(edges[j, 1]), depth + 1, rest[s] @ frame @ (skeleton.joint_offsets[j, 0] - origin[s]))
        if not children[s]:
            tip = centroid[s] if np.isfinite(centroid[s]).all() else origin[s]
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{",
                          f"{pad}\t\tOFFSET {fmt(rest[s] @ frame @ (tip - origin[s]))}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    write(int(skeleton.root), 0, np.zeros(3))
    return lines, dfs


def _channels(
    skeleton: Skeleton, motion: Motion, frame: np.ndarray, rest: np.ndarray, dfs: Sequence[int], scale: float,
    order: str,
) -> np.ndarray:
    """(F, 6 + 3 (S - 1)) channel values in hierarchy order: ``G_s = C R_s C^T T_s^T``,
    local ``G_p^T G_s`` as Euler angles; the root's node origin ``C (t + R n)``."""
    quats = np.asarray(motion.rotations, float)
    n_frames, n_seg = quats.shape[:2]
    seg = Rotation.from_quat(quats.reshape(-1, 4), scalar_first=True).as_matrix().reshape(n_frames, n_seg, 3, 3)
    world = frame @ seg @ frame.T @ np.swapaxes(rest, -1, -2)  # (F, S, 3, 3) G_s
    parent = skeleton.parent
    local = world.copy()
    child = parent >= 0
    local[:, child] = np.swapaxes(world[:, parent[child]], -1, -2) @ world[:, child]
    angles = euler_angles(local, order)  # (F, S, 3)
    root = int(skeleton.root)
    root_node = np.asarray(motion.root_position, float) + seg[:, root] @ _node_origins(skeleton)[root]
    return np.concatenate([root_node @ frame.T * scale, *(angles[:, s] for s in dfs)], axis=1)


# --------------------------------------------------------------------- reading
@dataclasses.dataclass(frozen=True, eq=False)
class BvhData:
    """A parsed BVH file.

    Attributes
    ----------
    names
        (K,) joint names in file order (depth-first); ``parents`` (K,) their parent
        index (-1 for the root).
    offsets
        (K, 3) ``OFFSET`` of each joint (file units).
    channels
        K tuples of channel names (e.g. ``("Zrotation", "Xrotation", "Yrotation")``).
    end_sites
        (K, 3) ``End Site`` offset of each joint, NaN where it has none.
    frame_time
        Seconds per frame.
    frames
        (F, C) channel values, C = total channel count, in file order.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: np.ndarray
    frame_time: float
    frames: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    def world_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R (F, K, 3, 3), p (F, K, 3))``: each joint's world frame and origin.

        ``p = p_parent + R_parent (offset + position channels)`` and
        ``R = R_parent R_c1 R_c2 ...`` over the rotation channels in file order.
        """
        n_frames, k = self.n_frames, len(self.names)
        rot = np.zeros((n_frames, k, 3, 3))
        pos = np.zeros((n_frames, k, 3))
        col = 0
        for i, chans in enumerate(self.channels):
            local_t = np.broadcast_to(self.offsets[i], (n_frames, 3)).copy()
            local_r = np.broadcast_to(np.eye(3), (n_frames, 3, 3)).copy()
            for name in chans:
                value = self.frames[:, col]
                col += 1
                axis = _AXES[name[0].upper()]
                if name[1:].lower() == "position":
                    local_t[:, axis] += value
                else:
                    rv = np.zeros((n_frames, 3))
                    rv[:, axis] = np.deg2rad(value)
                    local_r = local_r @ Rotation.from_rotvec(rv).as_matrix()
            p = self.parents[i]
            if p < 0:
                rot[:, i] = local_r
                pos[:, i] = local_t
            else:
                rot[:, i] = rot[:, p] @ local_r
                pos[:, i] = pos[:, p] + np.einsum("fab,fb->fa", rot[:, p], local_t)
        return rot, pos

    def world_positions(self) -> np.ndarray:
        """(F, K, 3) world position of every joint origin (file units)."""
        return self.world_transforms()[1]


def read_bvh(path: str | os.PathLike[str]) -> BvhData:
    """Parse a BVH file (our own reader; any channel layout). Raises :class:`InputError`."""
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise InputError(f"cannot read {file}: {err}") from None
    head, sep, motion = text.partition("MOTION")
    if not sep:
        raise InputError(f"{file} is not a BVH file: no MOTION section")
    tokens = head.split()
    if not tokens or tokens[0] != "HIERARCHY":
        raise InputError(f"{file} is not a BVH file: it does not start with HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: list[list[float]] = []
    stack: list[int] = []
    pos = 1

    def need(n: int) -> list[str]:
        nonlocal pos
        if pos + n > len(tokens):
            raise InputError(f"{file}: hierarchy ends unexpectedly")
        out = tokens[pos : pos + n]
        pos += n
        return out

    try:
        while pos < len(tokens):
            tok = need(1)[0]
            if tok in ("ROOT", "JOINT"):
                names.append(need(1)[0])
                parents.append(stack[-1] if stack else -1)
                offsets.append([0.0, 0.0, 0.0])
                channels.append(())
                end_sites.append([np.nan] * 3)
                if need(1)[0] != "{":
                    raise InputError(f"{file}: expected '{{' after {tok} {names[-1]}")
                stack.append(len(names) - 1)
            elif tok == "OFFSET":
                offsets[stack[-1]] = [float(v) for v in need(3)]
            elif tok == "CHANNELS":
                n = int(need(1)[0])
                channels[stack[-1]] = tuple(need(n))
            elif tok == "End":
                if need(2) != ["Site", "{"] or need(1)[0] != "OFFSET":
                    raise InputError(f"{file}: malformed End Site")
                end_sites[stack[-1]] = [float(v) for v in need(3)]
                if need(1)[0] != "}":
                    raise InputError(f"{file}: End Site not closed")
            elif tok == "}":
                stack.pop()
            else:
                raise InputError(f"{file}: unexpected token {tok!r} in the hierarchy")
    except (ValueError, IndexError):
        raise InputError(f"{file}: malformed hierarchy near token {pos}") from None
    if stack or not names:
        raise InputError(f"{file}: unbalanced braces or no joints in the hierarchy")
    for chans in channels:
        for c in chans:
            if c[:1].upper() not in _AXES or c[1:].lower() not in ("position", "rotation"):
                raise InputError(f"{file}: unknown channel {c!r}")
    lines = motion.strip().splitlines()
    try:
        n_frames = int(lines[0].split(":")[1])
        frame_time = float(lines[1].split(":")[1])
        values = np.array([[float(v) for v in ln.split()] for ln in lines[2:] if ln.strip()], dtype=float)
    except (IndexError, ValueError):
        raise InputError(f"{file}: malformed MOTION section (Frames:, Frame Time:, then one row per frame)") from None
    n_chan = sum(len(c) for c in channels)
    if not values.size:
        values = np.zeros((0, n_chan))
    if values.ndim != 2 or values.shape != (n_frames, n_chan):
        raise InputError(
            f"{file}: MOTION declares {n_frames} frames of {n_chan} channels but holds {values.shape}"
        )
    return BvhData(
        names=tuple(names),
        parents=np.asarray(parents, dtype=int),
        offsets=np.asarray(offsets, dtype=float),
        channels=tuple(channels),
        end_sites=np.asarray(end_sites, dtype=float),
        frame_time=frame_time,
        frames=values,
    )
