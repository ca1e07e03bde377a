"""BVH (Biovision hierarchy) export of a fitted skeleton and motion, and a reader.

Mapping (a host-side edge of jaxskel; numpy and scipy only):

* Each segment is one BVH joint, named after the segment (by default from its markers'
  labels, :mod:`jaxskel.segment._names`); the root segment is ``ROOT``.
  Its node frame is the segment frame moved to the segment's proximal joint (for the
  root: the segment origin, the centroid of its markers), axes unchanged.
* ``OFFSET`` of a joint is the position of its proximal joint relative to its parent's
  node origin in the rest pose, in the parent frame: ``o_j0 - o_prox(parent),1``.
  Segment axes are world-aligned at the rest frame (:mod:`jaxskel.skeleton._rigid_fit`), so the BVH
  rest pose (all channels zero) is the subject's posture in that frame.
* The root has position channels (the world position of its node origin) and every
  joint three rotation channels, by default ``Zrotation Xrotation Yrotation``: the
  local rotation ``R_parent^T R_segment = R_Z(a) R_X(b) R_Y(c)`` (intrinsic, in channel
  order), in degrees.
* A leaf segment ends in an ``End Site`` at the centroid of its markers.
* Lengths in metres (``units="m"``) or centimetres (``units="cm"``).

:func:`read_bvh` parses any BVH file (arbitrary channel sets and orders) into
:class:`BvhData`, whose :meth:`BvhData.world_positions` is an independent forward
kinematics used to check the export.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import InputError
from ..io import atomic_output, check_output
from ..segment import safe_name

if TYPE_CHECKING:
    from ..skeleton import Motion, Skeleton

__all__ = ["BvhData", "export_bvh", "read_bvh"]

_UNITS = {"m": 1.0, "cm": 100.0}
_AXES = {"X": 0, "Y": 1, "Z": 2}


def _local_rotations(skeleton: Skeleton, rotations: np.ndarray) -> np.ndarray:
    """(F, S, 4) global quaternions -> (F, S, 3, 3) rotations relative to the parent."""
    rot = Rotation.from_quat(rotations.reshape(-1, 4), scalar_first=True).as_matrix()
    rot = rot.reshape(*rotations.shape[:-1], 3, 3)
    parent = skeleton.parent
    local = rot.copy()
    child = parent >= 0
    local[:, child] = np.swapaxes(rot[:, parent[child]], -1, -2) @ rot[:, child]
    return local


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


def export_bvh(
    skeleton: Skeleton,
    motion: Motion,
    path: str | os.PathLike[str],
    *,
    rate: float | None = None,
    overwrite: bool = False,
    units: str = "m",
    labels: Sequence[str] | None = None,
    rotation_order: str = "ZXY",
) -> Path:
    """Write a skeleton and its motion as a BVH file (atomically).

    Parameters
    ----------
    skeleton, motion
        From :func:`jaxskel.skeleton.fit_rigid` and :func:`jaxskel.skeleton.inverse_kinematics` (one trial).
    path
        Destination ``.bvh`` file; an existing file is replaced only with ``overwrite``.
    rate
        Frames per second (default: ``motion.rate``).
    units
        ``"m"`` or ``"cm"`` for offsets and root positions.
    labels
        Segment names (default: :meth:`Skeleton.names`, the skeleton's segment names or
        readable names from its marker labels); whitespace becomes ``_``.
    rotation_order
        Order of the three rotation channels, a permutation of ``"XYZ"``.

    Returns the path written.
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
    if labels is None:
        labels = skeleton.names()
    names = [safe_name(v) for v in labels]
    if len(names) != n_seg or len(set(names)) != n_seg:
        raise InputError(f"labels must be {n_seg} distinct segment names")
    scale = _UNITS[units]
    edges = skeleton.edges
    proximal = np.full(n_seg, -1)
    proximal[edges[:, 1]] = np.arange(skeleton.n_joints)
    # Node origin of each segment in its own frame: its proximal joint (root: origin).
    node_origin = np.zeros((n_seg, 3))
    node_origin[edges[:, 1]] = skeleton.joint_offsets[:, 1]
    children: list[list[int]] = [[] for _ in range(n_seg)]
    for j, (p, c) in enumerate(edges.tolist()):
        children[p].append(j)

    def fmt(v: np.ndarray) -> str:
        return " ".join(f"{float(a):.9g}" for a in v)

    lines = ["HIERARCHY"]
    rot_channels = " ".join(f"{a}rotation" for a in order)

    def write(s: int, depth: int, offset: np.ndarray) -> None:
        pad = "\t" * depth
        kind = "ROOT" if s == skeleton.root else "JOINT"
        lines.append(f"{pad}{kind} {names[s]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {fmt(offset * scale)}")
        if s == skeleton.root:
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
        else:
            lines.append(f"{pad}\tCHANNELS 3 {rot_channels}")
        for j in children[s]:
            c = int(edges[j, 1])
            write(c, depth + 1, skeleton.joint_offsets[j, 0] - node_origin[s])
        if not children[s]:
            on = (skeleton.marker_segment == s) & np.isfinite(skeleton.marker_offsets).all(axis=1)
            tip = skeleton.marker_offsets[on].mean(axis=0) if on.any() else node_origin[s]
            lines.append(f"{pad}\tEnd Site")
            lines.append(f"{pad}\t{{")
            lines.append(f"{pad}\t\tOFFSET {fmt((tip - node_origin[s]) * scale)}")
            lines.append(f"{pad}\t}}")
        lines.append(f"{pad}}}")

    write(skeleton.root, 0, np.zeros(3))

    # Channel values in hierarchy (depth-first) order.
    dfs: list[int] = []

    def visit(s: int) -> None:
        dfs.append(s)
        for j in children[s]:
            visit(int(edges[j, 1]))

    visit(skeleton.root)
    angles = euler_angles(_local_rotations(skeleton, motion.rotations), order)  # (F, S, 3)
    rot = Rotation.from_quat(motion.rotations[:, skeleton.root], scalar_first=True).as_matrix()
    root_node = motion.root_position + np.einsum("fab,b->fa", rot, node_origin[skeleton.root])
    columns = [root_node * scale] + [angles[:, s] for s in dfs]
    values = np.concatenate(columns, axis=1)
    n_frames = values.shape[0]
    lines += ["MOTION", f"Frames: {n_frames}", f"Frame Time: {1.0 / float(rate):.9g}"]
    body = "\n".join(" ".join(f"{v:.10g}" for v in row) for row in values)
    text = "\n".join(lines) + "\n" + body + ("\n" if n_frames else "")
    target = Path(path)
    with atomic_output(target, overwrite) as tmp:
        tmp.write_text(text, encoding="ascii")
    return target


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
