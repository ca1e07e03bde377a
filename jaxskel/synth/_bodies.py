"""Articulated bodies with exactly known geometry: the ground truth of every test.

A :class:`Body` is a tree of rigid segments joined by rotational joints.

Conventions
-----------
* Each segment has a local frame; a pose ``(R, t)`` maps it to the world,
  ``x_world = R @ x_local + t``. In the rest pose (all joint angles zero) every
  segment frame is parallel to the world frame, so an axis written "in the parent
  frame" is also the same vector in the child frame at rest.
* Joint ``j`` is edge ``edges[j] = (parent, child)``. It sits at
  ``joint_offsets[j, 0]`` in the parent frame and ``joint_offsets[j, 1]`` in the
  child frame; both points coincide in the world at every frame.
* The child orientation is ``R_child = R_parent @ R_rel(theta)`` with
  ``theta`` the joint's angles (radians), one per axis in ``joint_axes[j]`` (k, 3):

  - ``"hinge"`` (k = 1): ``R_rel = exp(theta_0 [a_0]x)``, axis fixed in both segments;
  - ``"universal"`` (k = 2): ``R_rel = exp(theta_0 [a_0]x) exp(theta_1 [a_1]x)``,
    ``a_0`` fixed in the parent, ``a_1`` fixed in the child;
  - ``"ball"`` (k = 3, orthonormal axes): ``R_rel = exp([sum_k theta_k a_k]x)``
    (rotation-vector components along the axes).

  ``joint_limits[j]`` (k, 2) bounds each angle (physiological range of motion).
* Positions in metres, vertical axis +Z, the human faces +X with its left side on +Y.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from jaxtyping import Float, Int

from .._errors import InputError
from .._math.rotation import axis_angle_to_matrix_np

__all__ = ["Body", "JOINT_DOF", "linkage", "full_body", "random_tree"]

#: Rotational degrees of freedom of each joint type.
JOINT_DOF = {"hinge": 1, "universal": 2, "ball": 3}


def _frozen(a: np.ndarray, dtype: type) -> np.ndarray:
    a = np.array(a, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class Body:
    """A rigid-segment tree with markers; see the module docstring for conventions.

    Attributes
    ----------
    name
        Kind of body ("linkage", "full_body", "random_tree").
    segment_names
        S segment names.
    edges
        (J, 2) parent -> child segment indices, one row per joint.
    joint_names
        J joint names.
    joint_types
        J joint types, keys of :data:`JOINT_DOF`.
    joint_axes
        J arrays (k, 3) of unit axes in the parent frame (equal to the child frame at rest).
    joint_limits
        J arrays (k, 2) of (low, high) angle limits in radians, one row per axis.
    joint_offsets
        (J, 2, 3): the joint centre in the parent frame and in the child frame.
    marker_offsets
        (M, 3): each marker in its segment frame.
    marker_segment
        (M,) segment index of each marker.
    marker_labels
        M unique marker labels.
    root
        Index of the root segment (moved freely by the root pose).
    rest_translation
        (3,) root frame origin in the world at rest (e.g. pelvis height).
    upright
        True for bodies that stand (a human): the root turns mostly about the vertical.
    """

    name: str
    segment_names: tuple[str, ...]
    edges: Int[np.ndarray, "J 2"]
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    joint_axes: tuple[Float[np.ndarray, "k 3"], ...]
    joint_limits: tuple[Float[np.ndarray, "k 2"], ...]
    joint_offsets: Float[np.ndarray, "J 2 3"]
    marker_offsets: Float[np.ndarray, "M 3"]
    marker_segment: Int[np.ndarray, " M"]
    marker_labels: tuple[str, ...]
    root: int = 0
    rest_translation: Float[np.ndarray, " 3"] = dataclasses.field(
        default_factory=lambda: np.zeros(3)
    )
    upright: bool = False

    def __post_init__(self) -> None:
        n_seg = len(self.segment_names)
        edges = np.asarray(self.edges, dtype=int).reshape(-1, 2)
        n_joint = edges.shape[0]
        if n_joint != n_seg - 1:
            raise InputError(f"a tree of {n_seg} segments needs {n_seg - 1} joints, got {n_joint}")
        if edges.size and (edges.min() < 0 or edges.max() >= n_seg):
            raise InputError("joint edges refer to segments that do not exist")
        children = edges[:, 1]
        if len(set(children.tolist())) != n_joint or self.root in children:
            raise InputError("every segment except the root must be the child of exactly one joint")
        for name, seq in (
            ("joint_names", self.joint_names),
            ("joint_types", self.joint_types),
            ("joint_axes", self.joint_axes),
            ("joint_limits", self.joint_limits),
        ):
            if len(seq) != n_joint:
                raise InputError(f"{name} has {len(seq)} entries for {n_joint} joints")
        axes, limits = [], []
        for j, (kind, ax, lim) in enumerate(
            zip(self.joint_types, self.joint_axes, self.joint_limits, strict=True)
        ):
            if kind not in JOINT_DOF:
                raise InputError(f"joint {j} has type {kind!r}; use one of {tuple(JOINT_DOF)}")
            ax = np.asarray(ax, dtype=float).reshape(-1, 3)
            lim = np.asarray(lim, dtype=float).reshape(-1, 2)
            if ax.shape[0] != JOINT_DOF[kind] or lim.shape[0] != JOINT_DOF[kind]:
                raise InputError(
                    f"a {kind} joint needs {JOINT_DOF[kind]} axes and limits; joint {j} has "
                    f"{ax.shape[0]} axes and {lim.shape[0]} limits"
                )
            if not np.all(lim[:, 0] <= lim[:, 1]):
                raise InputError(f"joint {j} has a limit with low > high: {lim.tolist()}")
            ax = ax / np.linalg.norm(ax, axis=1, keepdims=True)
            if kind == "ball" and not np.allclose(ax @ ax.T, np.eye(3), atol=1e-6):
                raise InputError(f"ball joint {j} needs three orthonormal axes, got {ax.tolist()}")
            if kind == "universal" and abs(ax[0] @ ax[1]) > 0.99:
                raise InputError(f"universal joint {j} has (nearly) parallel axes {ax.tolist()}")
            axes.append(_frozen(ax, float))
            limits.append(_frozen(lim, float))
        marker_segment = np.asarray(self.marker_segment, dtype=int)
        marker_offsets = np.asarray(self.marker_offsets, dtype=float).reshape(-1, 3)
        labels = tuple(str(x) for x in self.marker_labels)
        if not (len(labels) == marker_offsets.shape[0] == marker_segment.shape[0]):
            raise InputError("marker_offsets, marker_segment and marker_labels differ in length")
        if len(set(labels)) != len(labels):
            raise InputError("marker labels must be unique")
        if marker_segment.size and (marker_segment.min() < 0 or marker_segment.max() >= n_seg):
            raise InputError("marker_segment refers to segments that do not exist")
        set_ = object.__setattr__
        set_(self, "segment_names", tuple(self.segment_names))
        set_(self, "edges", _frozen(edges, int))
        set_(self, "joint_names", tuple(self.joint_names))
        set_(self, "joint_types", tuple(self.joint_types))
        set_(self, "joint_axes", tuple(axes))
        set_(self, "joint_limits", tuple(limits))
        set_(self, "joint_offsets", _frozen(np.reshape(self.joint_offsets, (n_joint, 2, 3)), float))
        set_(self, "marker_offsets", _frozen(marker_offsets, float))
        set_(self, "marker_segment", _frozen(marker_segment, int))
        set_(self, "marker_labels", labels)
        set_(self, "rest_translation", _frozen(np.reshape(self.rest_translation, 3), float))

    # ------------------------------------------------------------- structure
    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    @property
    def n_joints(self) -> int:
        return int(self.edges.shape[0])

    @property
    def n_markers(self) -> int:
        return len(self.marker_labels)

    @property
    def parents(self) -> Int[np.ndarray, " S"]:
        """(S,) parent segment of each segment, -1 for the root."""
        out = np.full(self.n_segments, -1, dtype=int)
        out[self.edges[:, 1]] = self.edges[:, 0]
        return out

    @property
    def joint_order(self) -> Int[np.ndarray, " J"]:
        """Joint indices in topological order (each parent posed before its children)."""
        order, placed = [], {self.root}
        pending = list(range(self.n_joints))
        while pending:
            ready = [j for j in pending if self.edges[j, 0] in placed]
            if not ready:
                raise InputError("joint edges do not form a tree reachable from the root")
            for j in ready:
                order.append(j)
                placed.add(int(self.edges[j, 1]))
                pending.remove(j)
        return np.asarray(order, dtype=int)

    @property
    def bones(self) -> Int[np.ndarray, "B 2"]:
        """(B, 2) pairs of joints ``(i, k)``, ``i < k``, that lie on one segment.

        A segment with n joints contributes all n (n - 1) / 2 pairs (they are all
        rigid distances); end segments with one joint contribute none.
        """
        pairs = []
        for s in range(self.n_segments):
            on_segment = np.flatnonzero((self.edges[:, 0] == s) | (self.edges[:, 1] == s))
            pairs += [
                (int(a), int(b)) for i, a in enumerate(on_segment) for b in on_segment[i + 1 :]
            ]
        return np.asarray(pairs, dtype=int).reshape(-1, 2)

    @property
    def bone_segment(self) -> Int[np.ndarray, " B"]:
        """(B,) the segment each bone of :attr:`bones` lies on."""
        e = self.edges
        b = self.bones
        # Two distinct joints share exactly one segment in a tree.
        shared = [
            ({int(e[i, 0]), int(e[i, 1])} & {int(e[k, 0]), int(e[k, 1])}).pop() for i, k in b
        ]
        return np.asarray(shared, dtype=int)

    def joint_in_segment(self, joint: int, segment: int) -> Float[np.ndarray, " 3"]:
        """Position of ``joint`` in the frame of ``segment`` (its parent or child)."""
        parent, child = self.edges[joint]
        if segment == parent:
            return self.joint_offsets[joint, 0]
        if segment == child:
            return self.joint_offsets[joint, 1]
        raise InputError(f"joint {joint} does not touch segment {segment}")

    @property
    def bone_lengths(self) -> Float[np.ndarray, " B"]:
        """(B,) rigid distance in metres between the two joints of each bone."""
        return np.asarray(
            [
                np.linalg.norm(self.joint_in_segment(i, s) - self.joint_in_segment(k, s))
                for (i, k), s in zip(self.bones, self.bone_segment, strict=True)
            ]
        ).reshape(-1)

    def segment_markers(self, segment: int) -> Int[np.ndarray, " m"]:
        """Indices of the markers on one segment."""
        return np.flatnonzero(self.marker_segment == segment)

    def select_markers(self, labels: Sequence[str]) -> Body:
        """The same body carrying only the given markers (in that order)."""
        lookup = {lab: i for i, lab in enumerate(self.marker_labels)}
        missing = [lab for lab in labels if lab not in lookup]
        if missing:
            raise InputError(
                f"no marker labelled {missing[:5]} on this body; available: "
                f"{', '.join(self.marker_labels)}"
            )
        idx = np.asarray([lookup[lab] for lab in labels], dtype=int)
        return dataclasses.replace(
            self,
            marker_offsets=self.marker_offsets[idx],
            marker_segment=self.marker_segment[idx],
            marker_labels=tuple(labels),
        )

    def __repr__(self) -> str:
        kinds = {k: self.joint_types.count(k) for k in JOINT_DOF if k in self.joint_types}
        return (
            f"Body({self.name}: {self.n_segments} segments, {self.n_markers} markers, "
            f"joints {kinds})"
        )


# --------------------------------------------------------------------- linkage
def linkage(
    lengths: tuple[float, float, float] = (0.30, 0.341, 0.30),
    marker_offset: float = 0.03,
) -> Body:
    """The three-rod aluminium calibration linkage of Kirk et al. (2005), Fig. 4.

    Three rods along +X joined end to end by two universal joints (axes Y then Z,
    both perpendicular to the rods, range +-75 deg). The middle rod is 0.341 m
    between its joints as in the paper. Each rod carries three markers at 15 %,
    50 % and 85 % of its length, pushed ``marker_offset`` metres off the rod axis
    in three different directions, so each rod's marker set spans a plane and its
    pose is determined.
    """
    l0, l1, l2 = (float(x) for x in lengths)
    if min(l0, l1, l2) <= 0 or marker_offset <= 0:
        raise InputError("rod lengths and marker_offset must be positive metres")
    ex = np.array([1.0, 0.0, 0.0])
    # Off-axis directions (unit, perpendicular to the rod) for the three markers on a rod.
    side = np.array([[0.0, 1.0, 0.0], [0.0, -0.5, 0.866], [0.0, -0.5, -0.866]])
    offsets, segment, labels = [], [], []
    for s, length in enumerate((l0, l1, l2)):
        for k, frac in enumerate((0.15, 0.5, 0.85)):
            offsets.append(frac * length * ex + marker_offset * side[(k + s) % 3])
            segment.append(s)
            labels.append(f"R{s + 1}M{k + 1}")
    limit = np.deg2rad(75.0)
    uaxes = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return Body(
        name="linkage",
        segment_names=("rod1", "rod2", "rod3"),
        edges=np.array([[0, 1], [1, 2]]),
        joint_names=("joint1", "joint2"),
        joint_types=("universal", "universal"),
        joint_axes=(uaxes, uaxes),
        joint_limits=(np.array([[-limit, limit]] * 2),) * 2,
        joint_offsets=np.array([[[l0, 0, 0], [0, 0, 0]], [[l1, 0, 0], [0, 0, 0]]], dtype=float),
        marker_offsets=np.array(offsets),
        marker_segment=np.array(segment),
        marker_labels=tuple(labels),
        root=0,
        rest_translation=np.array([-0.5 * (l0 + l1 + l2), 0.0, 1.2]),
        upright=False,
    )


# ------------------------------------------------------------------ full body
_X, _Y, _Z = np.eye(3)

# Joints of the human model: name, parent, child, type, axes, limits (radians), and
# the joint centre in the parent frame for a 1.75 m adult (child frames start at the joint).
# Axes are chosen so that a positive first/second angle is flexion / abduction on both
# sides (mirrored axes on the right).
_SEGMENTS = (
    "pelvis", "torso", "head",
    "l_upperarm", "l_forearm", "l_hand", "r_upperarm", "r_forearm", "r_hand",
    "l_thigh", "l_shank", "l_foot", "r_thigh", "r_shank", "r_foot",
)  # fmt: skip


def _human_joints(side: str) -> list[tuple]:
    s = 1.0 if side == "l" else -1.0
    return [
        # name, parent, child, type, axes, limits (rad), centre in parent frame
        (f"{side}_shoulder", "torso", f"{side}_upperarm", "ball",
         [s * _X, -_Y, s * _Z], [[-0.2, 1.6], [-0.6, 1.7], [-0.8, 0.8]], [0.0, s * 0.18, 0.40]),
        (f"{side}_elbow", f"{side}_upperarm", f"{side}_forearm", "hinge",
         [-_Y], [[0.0, 2.4]], [0.0, 0.0, -0.29]),
        (f"{side}_wrist", f"{side}_forearm", f"{side}_hand", "universal",
         [-_Y, s * _X], [[-1.0, 1.0], [-0.3, 0.45]], [0.0, 0.0, -0.25]),
        (f"{side}_hip", "pelvis", f"{side}_thigh", "ball",
         [s * _X, -_Y, s * _Z], [[-0.35, 0.7], [-0.35, 1.9], [-0.6, 0.6]], [0.0, s * 0.085, -0.08]),
        (f"{side}_knee", f"{side}_thigh", f"{side}_shank", "hinge",
         [_Y], [[0.0, 2.2]], [0.0, 0.0, -0.42]),
        (f"{side}_ankle", f"{side}_shank", f"{side}_foot", "universal",
         [_Y, s * _X], [[-0.35, 0.6], [-0.3, 0.4]], [0.0, 0.0, -0.41]),
    ]  # fmt: skip


_HUMAN_JOINTS = [
    ("spine", "pelvis", "torso", "ball",
     [_X, -_Y, _Z], [[-0.3, 0.3], [-0.25, 0.5], [-0.4, 0.4]], [-0.03, 0.0, 0.08]),
    ("neck", "torso", "head", "ball",
     [_X, -_Y, _Z], [[-0.4, 0.4], [-0.5, 0.7], [-0.9, 0.9]], [0.0, 0.0, 0.45]),
    *_human_joints("l"),
    *_human_joints("r"),
]  # fmt: skip


def _human_markers() -> list[tuple[str, str, list[float]]]:
    """Plug-in-gait-like marker catalogue: label, segment, offset in the segment frame.

    Offsets sit on the skin, 3-7 cm from the bone line; per segment the first
    entries are the most common ones (used when fewer markers are requested).
    The right side mirrors the left except RUPA/RTHI, placed asymmetrically as in
    common protocols so that left and right are distinguishable.
    """
    out = [
        ("LASI", "pelvis", [0.10, 0.12, 0.0]),
        ("RASI", "pelvis", [0.10, -0.12, 0.0]),
        ("LPSI", "pelvis", [-0.10, 0.045, 0.02]),
        ("RPSI", "pelvis", [-0.10, -0.045, 0.02]),
        ("C7", "torso", [-0.07, 0.0, 0.46]),
        ("CLAV", "torso", [0.07, 0.0, 0.42]),
        ("T10", "torso", [-0.11, 0.0, 0.22]),
        ("STRN", "torso", [0.12, 0.0, 0.28]),
        ("LFHD", "head", [0.09, 0.07, 0.12]),
        ("RFHD", "head", [0.09, -0.07, 0.12]),
        ("LBHD", "head", [-0.09, 0.07, 0.10]),
        ("RBHD", "head", [-0.09, -0.07, 0.10]),
    ]
    for side, s in (("L", 1.0), ("R", -1.0)):
        low = side.lower()
        upa = -0.15 if side == "L" else -0.11
        thi = -0.22 if side == "L" else -0.16
        out += [
            (f"{side}ELB", f"{low}_upperarm", [0.0, s * 0.045, -0.28]),
            (f"{side}SHO", f"{low}_upperarm", [0.01, s * 0.04, 0.04]),
            (f"{side}UPA", f"{low}_upperarm", [-0.03, s * 0.05, upa]),
            (f"{side}WRA", f"{low}_forearm", [0.035, s * 0.01, -0.245]),
            (f"{side}WRB", f"{low}_forearm", [-0.035, s * 0.01, -0.245]),
            (f"{side}FRM", f"{low}_forearm", [-0.02, s * 0.04, -0.12]),
            (f"{side}FIN", f"{low}_hand", [0.005, s * 0.03, -0.08]),
            (f"{side}MC5", f"{low}_hand", [-0.03, s * 0.02, -0.07]),
            (f"{side}KNE", f"{low}_thigh", [0.0, s * 0.05, -0.41]),
            (f"{side}THI", f"{low}_thigh", [0.0, s * 0.065, thi]),
            (f"{side}THF", f"{low}_thigh", [0.07, s * 0.02, -0.18]),
            (f"{side}ANK", f"{low}_shank", [0.0, s * 0.04, -0.40]),
            (f"{side}TIB", f"{low}_shank", [0.0, s * 0.05, -0.20]),
            (f"{side}SHN", f"{low}_shank", [0.045, 0.0, -0.15]),
            (f"{side}HEE", f"{low}_foot", [-0.06, 0.0, -0.05]),
            (f"{side}TOE", f"{low}_foot", [0.15, 0.0, -0.06]),
            (f"{side}MT5", f"{low}_foot", [0.11, s * 0.045, -0.07]),
        ]
    return out


def full_body(
    seed: int = 0,
    markers: Sequence[str] | None = None,
    markers_per_segment: int | Mapping[str, int] | None = None,
    scale: float | None = None,
) -> Body:
    """An adult human: 15 segments, 14 joints, 46 skin markers (Plug-in-gait-like labels).

    Segments: pelvis (root), torso, head, and left/right upper arm, forearm, hand,
    thigh, shank, foot. Joints: spine and neck, shoulders and hips are ball joints;
    elbows and knees hinges; wrists and ankles universal (flexion, then deviation /
    inversion). Lengths are those of a ~1.75 m adult (thigh 0.42, shank 0.41, upper
    arm 0.29, forearm 0.25 m) times ``scale``; markers sit 3-7 cm off the bone line.
    The rest pose stands facing +X with the arms hanging; each segment frame starts
    at its proximal joint (the pelvis frame 8 cm above the midpoint of the hips).

    Parameters
    ----------
    seed
        Varies the subject: overall scale ~N(1, 0.05) (unless ``scale`` is given),
        each segment's length by +-3 %, every marker by ~5 mm and the hinge axes
        by up to ~4 degrees (knees and elbows are not exactly lateral).
    markers
        Labels to keep (default: all 46).
    markers_per_segment
        Keep only the first n catalogue markers of each segment (an int for all
        segments, or a mapping segment name -> n, 1-4); useful for sparse sets.
    scale
        Overall size factor; 1.0 is the 1.75 m reference adult.
    """
    rng = np.random.default_rng(seed)
    size = float(rng.normal(1.0, 0.05)) if scale is None else float(scale)
    if not 0.3 < size < 3.0:
        raise InputError(f"scale must be a plausible body-size factor (0.3-3), got {size}")
    seg_index = {name: i for i, name in enumerate(_SEGMENTS)}
    seg_scale = size * rng.uniform(0.97, 1.03, size=len(_SEGMENTS))

    edges, names, types, axes, limits, offsets = [], [], [], [], [], []
    for name, parent, child, kind, ax, lim, centre in _HUMAN_JOINTS:
        p = seg_index[parent]
        edges.append((p, seg_index[child]))
        names.append(name)
        types.append(kind)
        ax = np.asarray(ax, dtype=float)
        if kind == "hinge":
            # Tilt the hinge axis a few degrees about the segment's long axis (Z).
            ax = ax @ axis_angle_to_matrix_np(_Z * rng.normal(0.0, np.deg2rad(2.0))).T
        axes.append(ax)
        limits.append(np.asarray(lim, dtype=float))
        offsets.append([np.asarray(centre) * seg_scale[p], np.zeros(3)])

    catalogue = _human_markers()
    if markers_per_segment is not None:
        if isinstance(markers_per_segment, Mapping):
            unknown = set(markers_per_segment) - set(_SEGMENTS)
            if unknown:
                raise InputError(f"unknown segments {sorted(unknown)}; use names from {_SEGMENTS}")
            counts = {s: int(markers_per_segment.get(s, 4)) for s in _SEGMENTS}
        else:
            counts = {s: int(markers_per_segment) for s in _SEGMENTS}
        if min(counts.values()) < 1:
            raise InputError("markers_per_segment must be >= 1 for every segment")
        taken: dict[str, int] = {}
        kept = []
        for lab, seg, off in catalogue:
            if taken.get(seg, 0) < counts[seg]:
                kept.append((lab, seg, off))
                taken[seg] = taken.get(seg, 0) + 1
        catalogue = kept
    labels = [lab for lab, _, _ in catalogue]
    m_seg = np.asarray([seg_index[seg] for _, seg, _ in catalogue])
    m_off = np.asarray([off for _, _, off in catalogue]) * seg_scale[m_seg][:, None]
    m_off = m_off + rng.normal(0.0, 0.005, size=m_off.shape)

    # Pelvis height at rest: hip drop + thigh + shank + ankle height above the sole.
    hip_drop = 0.08 * seg_scale[0]
    leg = 0.42 * seg_scale[seg_index["l_thigh"]] + 0.41 * seg_scale[seg_index["l_shank"]]
    body = Body(
        name="full_body",
        segment_names=_SEGMENTS,
        edges=np.asarray(edges),
        joint_names=tuple(names),
        joint_types=tuple(types),
        joint_axes=tuple(axes),
        joint_limits=tuple(limits),
        joint_offsets=np.asarray(offsets),
        marker_offsets=m_off,
        marker_segment=m_seg,
        marker_labels=tuple(labels),
        root=0,
        rest_translation=np.array([0.0, 0.0, hip_drop + leg + 0.08 * size]),
        upright=True,
    )
    return body if markers is None else body.select_markers(list(markers))


# ---------------------------------------------------------------- random tree
def _orthonormal_frame(rng: np.random.Generator) -> np.ndarray:
    """Random proper rotation (rows are orthonormal axes)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q.T


def random_tree(n_segments: int, seed: int = 0) -> Body:
    """A random articulated tree of ``n_segments`` rigid rods.

    Segment i > 0 hangs from a random earlier segment (biased to the most recent
    ones, so trees are chain-like with some branching): the first child at that
    segment's far end, later children 30-85 % along it. Lengths are uniform in
    [0.1, 0.5] m with random rest directions; joint types are drawn uniformly
    from hinge / universal / ball with random axes and symmetric limits of 35-70
    degrees per axis. Each segment carries 2-4 markers spread along the rod and
    2-5 cm off its axis. Unlike the other bodies, segment frames sit at the middle
    of each rod, so both joint offsets of a joint are non-zero.
    """
    n_segments = int(n_segments)
    if n_segments < 2:
        raise InputError(f"a random tree needs at least 2 segments, got {n_segments}")
    rng = np.random.default_rng(seed)
    lengths = rng.uniform(0.1, 0.5, size=n_segments)
    directions = rng.normal(size=(n_segments, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)

    edges, types, axes, limits, offsets = [], [], [], [], []
    attach: dict[int, list[float]] = {}  # parent -> fractions along it where joints sit
    for child in range(1, n_segments):
        weights = np.arange(1, child + 1, dtype=float) ** 2
        parent = int(rng.choice(child, p=weights / weights.sum()))
        kind = str(rng.choice(list(JOINT_DOF)))
        frame = _orthonormal_frame(rng)
        edges.append((parent, child))
        types.append(kind)
        axes.append(frame[: JOINT_DOF[kind]])
        half = rng.uniform(np.deg2rad(35.0), np.deg2rad(70.0), size=JOINT_DOF[kind])
        limits.append(np.stack([-half, half], axis=1))
        # The first child hangs from the parent's far end, later ones part-way along it
        # and >= 8 % of the rod away from every other joint on it (the parent's own
        # joint at 0 included), so every bone has a real length.
        taken = attach.setdefault(parent, [0.0])
        frac = 1.0
        if len(taken) > 1:
            candidates = rng.uniform(0.3, 0.85, size=64)
            spacing = np.abs(candidates[:, None] - np.asarray(taken)[None]).min(axis=1)
            frac = float(candidates[np.argmax(spacing >= min(0.08, spacing.max()))])
        taken.append(frac)
        offsets.append(
            [
                (frac - 0.5) * lengths[parent] * directions[parent],
                -0.5 * lengths[child] * directions[child],
            ]
        )

    m_off, m_seg, labels = [], [], []
    for s in range(n_segments):
        n = int(rng.integers(2, 5))
        fracs = np.sort(rng.uniform(0.1, 0.9, size=n))
        perp = rng.normal(size=(n, 3))
        perp -= (perp @ directions[s])[:, None] * directions[s]
        perp /= np.linalg.norm(perp, axis=1, keepdims=True)
        dist = rng.uniform(0.02, 0.05, size=n)
        m_off += list((fracs - 0.5)[:, None] * lengths[s] * directions[s] + dist[:, None] * perp)
        m_seg += [s] * n
        labels += [f"S{s}M{k}" for k in range(n)]
    return Body(
        name="random_tree",
        segment_names=tuple(f"seg{s}" for s in range(n_segments)),
        edges=np.asarray(edges),
        joint_names=tuple(f"joint{j}" for j in range(n_segments - 1)),
        joint_types=tuple(types),
        joint_axes=tuple(axes),
        joint_limits=tuple(limits),
        joint_offsets=np.asarray(offsets),
        marker_offsets=np.asarray(m_off),
        marker_segment=np.asarray(m_seg),
        marker_labels=tuple(labels),
        root=0,
        rest_translation=np.array([0.0, 0.0, 1.0]),
        upright=False,
    )
