"""Anatomical joint angles of a named body: Grood–Suntay joint coordinate systems, ISB signs.

**Segment frames.** Every named segment gets an anatomical frame, constant in the
segment's own frame (:class:`jaxskel.skeleton.Skeleton`: world-aligned at the rest frame),
with the ISB axes on both sides: ``X`` anterior, ``Y`` superior (the long axis), ``Z`` to
the subject's right, right-handed. ``A_s = [X Y Z]`` (columns, segment coordinates).

* Long axis ``Y``, from the fitted joints (never from marker names):
  - thigh, shank, upper arm, forearm, hand: from the distal joint down the chain (knee,
    ankle, elbow, wrist; for a chain's last segment the centroid of its markers) to the
    proximal joint;
  - abdomen, thorax, head: from the proximal joint up to the next joint of the trunk
    (thoracic, neck; for the thorax without a head the shoulders' midpoint; for the head
    its markers' centroid);
  - pelvis: the body's up at the rest frame (a fitted lumbar joint is often undetermined
    along a line: :mod:`jaxskel.joints._determination`);
  - foot, toes: ``X`` comes first, the principal axis of the segment's markers (heel to
    toe), pointing away from the proximal joint (one marker: proximal joint to it), and
    ``Y = Z x X``;
  - clavicle: ``Z`` comes first, the bone (sternoclavicular joint to shoulder) turned to
    point right, and ``Y`` the body's up made perpendicular.
* Lateral ``Z``: for the two segments of a hinge (``AngleOptions.functional_axes``: knees
  and elbows), the joint's **functional axis**, where the joint turns by at least
  ``axis_range_deg`` (RMS about its mean): with ``Q_f = R_p^T R_d`` and ``Q`` their chordal
  mean, the principal direction of the rotation vectors of ``Q_f Q^T`` is the axis in the
  proximal frame, ``Q^T`` of it in the distal one. The pelvis takes left hip to right hip;
  every other segment, and a hinge that barely moves, the body's right at the rest frame
  (``-Anatomy.left``). ``Z`` is signed to the right. A functional axis is kept exactly and
  the long axis made perpendicular to it (so a hinge's flexion is its rotation about its
  own axis, even where that axis is not perpendicular to the bone); any other ``Z`` is made
  perpendicular to the long axis (the ISB construction).

**Angles.** For the joint between proximal segment ``p`` and distal ``d``,
``M = A_p^T R_p^T R_d A_d = R_Z(a) R_X(b) R_Y(c)``: an intrinsic Z-X-Y Cardan sequence,
which is the joint coordinate system of Grood & Suntay (1983) that the ISB recommends for
the lower limb (Wu et al. 2002): ``e1 = Z_p`` (flexion), ``e3 = Y_d`` (axial rotation),
``e2 = e3 x e1`` floating (ab/adduction). ``b = asin M_21``, ``a = atan2(-M_01, M_11)``,
``c = atan2(-M_20, M_22)``. Every angle is zero when the two frames coincide (straight
knee, arm hanging).

**Clinical signs** (:data:`COMPONENTS`): each angle is ``+-a``, ``+-b``, ``+-c`` so that the
positive direction is the one named, on both sides (for a left joint ``b`` and ``c`` are
negated, as mirrored frames would give):

=================  ===============  =================  =====================
joint              ``Z`` (flexion)  ``X`` (floating)   ``Y`` (axial)
=================  ===============  =================  =====================
hip                flexion          adduction          internal_rotation
knee               flexion          adduction (varus)  internal_rotation
ankle, toe         dorsiflexion     inversion          internal_rotation
shoulder           flexion          abduction          internal_rotation
elbow              flexion          adduction          pronation
wrist              flexion          ulnar_deviation    pronation
sternoclavicular   posterior_rot.   elevation          protraction
lumbar, thoracic,  flexion          lateral_bending    axial_rotation
neck                                (to the right)     (to the right)
=================  ===============  =================  =====================

A **hinge** (knees and elbows by default) has one angle, its flexion: with its functional
axis as ``Z`` in both frames the other two are zero up to the fit's noise.

This is host-side numpy, vectorised over frames (the only loop is over the joints).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import InputError
from .._math.rotation import quat_to_matrix_np
from ._vocabulary import CHAINS, Anatomy, is_ancestor, joint_between, side_of

__all__ = ["COMPONENTS", "AngleOptions", "JointAngles", "anatomical_frames", "joint_angles"]

#: Per joint kind: the names of its three angles (Z, X, Y) and their signs on the right side.
COMPONENTS: dict[str, tuple[tuple[str, int], tuple[str, int], tuple[str, int]]] = {
    "hip": (("flexion", 1), ("adduction", 1), ("internal_rotation", 1)),
    "knee": (("flexion", -1), ("adduction", 1), ("internal_rotation", 1)),
    "ankle": (("dorsiflexion", 1), ("inversion", 1), ("internal_rotation", 1)),
    "toe": (("dorsiflexion", 1), ("inversion", 1), ("internal_rotation", 1)),
    "shoulder": (("flexion", 1), ("abduction", -1), ("internal_rotation", 1)),
    "elbow": (("flexion", 1), ("adduction", 1), ("pronation", 1)),
    "wrist": (("flexion", 1), ("ulnar_deviation", 1), ("pronation", 1)),
    "sternoclavicular": (("posterior_rotation", 1), ("elevation", -1), ("protraction", 1)),
    "lumbar": (("flexion", -1), ("lateral_bending", 1), ("axial_rotation", -1)),
    "thoracic": (("flexion", -1), ("lateral_bending", 1), ("axial_rotation", -1)),
    "neck": (("flexion", -1), ("lateral_bending", 1), ("axial_rotation", -1)),
}

_DOWN = ("upper_arm", "forearm", "hand", "thigh", "shank")  # long axis: distal joint -> proximal joint
_UP = ("abdomen", "thorax", "head")  # long axis: proximal joint -> next joint up the trunk


@dataclasses.dataclass(frozen=True)
class AngleOptions:
    """How :func:`joint_angles` builds the joint frames (validated; :class:`InputError` if not).

    Attributes
    ----------
    hinges
        Joint kinds (:data:`COMPONENTS` keys) reported as hinges, with one angle (flexion).
        ``()``: three angles for every joint.
    functional_axes
        Joint kinds whose functional axis is the lateral axis of both their segments.
    axis_range_deg
        The RMS rotation (degrees, about the joint's mean pose) such a joint must show for
        its functional axis to be used; below it the body's right at the rest frame is.
    """

    hinges: tuple[str, ...] = ("knee", "elbow")
    functional_axes: tuple[str, ...] = ("knee", "elbow")
    axis_range_deg: float = 10.0

    def __post_init__(self) -> None:
        for field in ("hinges", "functional_axes"):
            value = getattr(self, field)
            kinds = (value,) if isinstance(value, str) else tuple(value)
            unknown = sorted(set(kinds) - set(COMPONENTS))
            if unknown:
                raise InputError(f"AngleOptions.{field}: unknown joint kinds {unknown}; use names from "
                                 f"{sorted(COMPONENTS)}")
            object.__setattr__(self, field, kinds)
        if not (isinstance(self.axis_range_deg, (int, float)) and 0.0 < self.axis_range_deg < 90.0):
            raise InputError(f"AngleOptions.axis_range_deg must be a number of degrees in (0, 90), got {self.axis_range_deg!r}")


@dataclasses.dataclass(frozen=True)
class JointAngles:
    """Anatomical joint angles over a motion's frames (module docstring: frames and signs).

    Attributes
    ----------
    names
        (C,) one name per angle, ``<joint>_<component>``: ``knee_l_flexion``, ``hip_r_adduction``.
    joints
        (C,) the joint of each angle (``knee_l``).
    values
        (F, C) radians, positive in the named direction.
    rate
        Frames per second (``None`` if unknown): :attr:`time` is then the frame index.
    lateral
        Per joint (in joint order), how its flexion axis was set: ``"functional"`` (the
        hinge's own axis), ``"body"`` (the body's right, the pelvis's hips) or ``"given"``
        (frames given to :func:`joint_angles`: a calibration's, for a tracked take).
    frames
        (S, 3, 3) the anatomical frames used (:func:`anatomical_frames`; NaN for segments
        no named joint uses), or ``None``.
    """

    names: tuple[str, ...]
    joints: tuple[str, ...]
    values: np.ndarray
    rate: float | None
    lateral: dict[str, str] = dataclasses.field(default_factory=dict)
    frames: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def time(self) -> np.ndarray:
        """(F,) seconds from the first frame (frame indices when the rate is unknown)."""
        step = 1.0 / self.rate if self.rate else 1.0
        return np.arange(self.n_frames) * step

    @property
    def degrees(self) -> np.ndarray:
        """(F, C) :attr:`values` in degrees."""
        return np.rad2deg(self.values)

    def __getitem__(self, name: str) -> np.ndarray:
        """(F,) the angle ``name`` (``"knee_l_flexion"``), radians."""
        if name not in self.names:
            raise InputError(f"no angle {name!r}; angles: {', '.join(self.names)}")
        return self.values[:, self.names.index(name)]

    def of(self, joint: str) -> np.ndarray:
        """(F, k) the angles of ``joint`` (``"hip_l"``: flexion, adduction, internal rotation)."""
        cols = [i for i, j in enumerate(self.joints) if j == joint]
        if not cols:
            raise InputError(f"no joint {joint!r}; joints: {', '.join(dict.fromkeys(self.joints))}")
        return self.values[:, cols]


@dataclasses.dataclass(frozen=True)
class _Joint:
    """A named joint of the fitted tree: its edge, and its proximal and distal segments."""

    name: str
    edge: int
    proximal: int
    distal: int

    @property
    def kind(self) -> str:
        return _base(self.name)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), np.nan)


def _named_joints(skeleton, anatomy: Anatomy) -> list[_Joint]:
    """The tree's joints that the parts name, proximal segment first; of two edges that name
    one joint (a one-marker twig on its host's part), the one whose distal segment has more markers."""
    parts, seg = anatomy.parts, np.asarray(skeleton.marker_segment)
    found: dict[str, _Joint] = {}
    for j, (a, b) in enumerate(np.asarray(skeleton.edges, int).tolist()):
        name = joint_between(parts[a], parts[b])
        if not name:
            continue
        p, d = (a, b) if is_ancestor(parts[a], parts[b]) else (b, a)
        new = _Joint(name, j, p, d)
        old = found.get(name)
        if old is None or (seg == d).sum() > (seg == old.distal).sum():
            found[name] = new
    return sorted(found.values(), key=lambda jt: jt.edge)


def _point(skeleton, edge: int, segment: int) -> np.ndarray:
    """Joint ``edge`` in segment ``segment``'s frame."""
    return np.asarray(skeleton.joint_offsets[edge, 0 if skeleton.edges[edge, 0] == segment else 1], float)


def _markers(skeleton, s: int) -> np.ndarray:
    seg, off = np.asarray(skeleton.marker_segment), np.asarray(skeleton.marker_offsets, float)
    return off[(seg == s) & np.isfinite(off).all(axis=1)]


@dataclasses.dataclass(frozen=True)
class _Geometry:
    """Each named segment's proximal and distal joints (edges, -1 where none)."""

    proximal: np.ndarray
    distal: np.ndarray


_CHAIN_OF = {part: chain for chain in CHAINS for part in chain}


def _down_chain(own: str, child: str) -> int:
    """How many places ``child`` lies below ``own`` in their chain (thigh -> shank: 1), 0
    where it does not continue ``own``'s chain (thorax -> upper arm)."""
    chain = _CHAIN_OF.get(own, ())
    return max(chain.index(child) - chain.index(own), 0) if child in chain else 0


def _geometry(skeleton, anatomy: Anatomy, joints: list[_Joint]) -> _Geometry:
    """Each segment's joint to its anatomical parent, and to the nearest part down its chain."""
    n = skeleton.n_segments
    proximal, distal, nearest = np.full(n, -1), np.full(n, -1), np.zeros(n, int)
    for jt in joints:
        proximal[jt.distal] = jt.edge
        step = _down_chain(anatomy.parts[jt.proximal], anatomy.parts[jt.distal])
        if step and (not nearest[jt.proximal] or step < nearest[jt.proximal]):
            distal[jt.proximal], nearest[jt.proximal] = jt.edge, step
    return _Geometry(proximal, distal)


def _base(part: str) -> str:
    """A part or joint without its side (``thigh`` for ``thigh_l``)."""
    return part[:-2] if side_of(part) else part


def _long_axis(skeleton, anatomy: Anatomy, s: int, geo: _Geometry, joints: list[_Joint]) -> np.ndarray:
    """Unit ``Y`` of segment ``s`` (its frame), NaN where its joints cannot set it."""
    part = _base(anatomy.parts[s])
    # without a named proximal joint: the segment's origin (its joint to its fitted parent)
    prox = _point(skeleton, geo.proximal[s], s) if geo.proximal[s] >= 0 else np.zeros(3)
    markers = _markers(skeleton, s)
    centroid = markers.mean(axis=0) if len(markers) else np.full(3, np.nan)
    far = _point(skeleton, geo.distal[s], s) if geo.distal[s] >= 0 else None
    if part in _DOWN:
        return _unit(prox - (far if far is not None else centroid))
    if part in _UP:
        if far is None and part == "thorax":
            arms = [_point(skeleton, jt.edge, s) for jt in joints if jt.proximal == s]
            far = np.mean(arms, axis=0) if arms else None
        return _unit((far if far is not None else centroid) - prox)
    if part == "pelvis":
        return anatomy.up.copy()
    if part == "clavicle" and far is not None:  # the bone, sternoclavicular joint to shoulder (_frame: Z)
        return _unit(far - prox)
    return np.full(3, np.nan)


def _forward_axis(skeleton, s: int, geo: _Geometry) -> np.ndarray:
    """Unit heel-to-toe ``X`` of a foot or toes: its markers' principal axis, away from its proximal joint."""
    markers = _markers(skeleton, s)
    prox = _point(skeleton, geo.proximal[s], s) if geo.proximal[s] >= 0 else np.zeros(3)
    if not len(markers):
        return np.full(3, np.nan)
    away = markers.mean(axis=0) - prox
    if len(markers) >= 2:
        centred = markers - markers.mean(axis=0)
        _, sv, vt = np.linalg.svd(centred, full_matrices=False)
        if sv[0] > 1e-6:
            axis = vt[0]
            return axis * (1.0 if axis @ away >= 0 else -1.0)
    return _unit(away)


def _functional_axis(rot_p: np.ndarray, rot_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A joint's principal rotation axis in the proximal and distal frames, and its RMS rotation
    (rad) about the mean pose, over the frames where both segments are posed (0 with fewer than 3)."""
    q = np.einsum("fji,fjk->fik", rot_p, rot_d)  # R_p^T R_d
    q = q[np.isfinite(q).all(axis=(1, 2))]
    if len(q) < 3:
        return np.full(3, np.nan), np.full(3, np.nan), 0.0
    u, _, vt = np.linalg.svd(q.mean(axis=0))
    mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    w = Rotation.from_matrix(q @ mean.T).as_rotvec()
    vals, vecs = np.linalg.eigh(w.T @ w / len(w))
    axis_p = vecs[:, -1]
    return axis_p, mean.T @ axis_p, float(np.sqrt(max(vals.sum(), 0.0)))


def _lateral_refs(skeleton, motion_rot: np.ndarray, anatomy: Anatomy, joints: list[_Joint],
                  options: AngleOptions) -> tuple[dict[int, np.ndarray], set[int], dict[str, str]]:
    """Per segment its lateral reference (segment frame), the segments whose reference is a
    hinge's functional axis, and per joint how its flexion axis was set."""
    right = -anatomy.left
    refs: dict[int, np.ndarray] = {}
    source: dict[str, str] = {}
    functional: set[int] = set()
    hips = {side_of(jt.name): jt for jt in joints if jt.kind == "hip"}
    if len(hips) == 2 and hips["l"].proximal == hips["r"].proximal:
        pelvis = hips["l"].proximal
        refs[pelvis] = _point(skeleton, hips["r"].edge, pelvis) - _point(skeleton, hips["l"].edge, pelvis)
    for jt in joints:
        source[jt.name] = "body"
        if jt.kind not in options.functional_axes:
            continue
        axis_p, axis_d, spread = _functional_axis(motion_rot[:, jt.proximal], motion_rot[:, jt.distal])
        if np.rad2deg(spread) < options.axis_range_deg:
            continue
        for s, a in ((jt.proximal, axis_p), (jt.distal, axis_d)):
            refs.setdefault(s, a * (1.0 if a @ right >= 0 else -1.0))
            functional.add(s)
        source[jt.name] = "functional"
    return refs, functional, source


def _frame(part: str, y: np.ndarray, lateral: np.ndarray, functional: bool, forward: np.ndarray | None,
           up: np.ndarray) -> np.ndarray:
    """``[X Y Z]`` (3, 3) of one segment from its long axis, its lateral reference (kept exactly
    where it is a hinge's ``functional`` axis) and (foot, toes) its forward axis."""
    base = _base(part)
    if base in ("foot", "toes"):
        x = forward
        z = _unit(lateral) if functional else _unit(lateral - (lateral @ x) * x)
        x = _unit(x - (x @ z) * z)
        y = np.cross(z, x)
    elif base == "clavicle" and not functional:
        z = _unit(y * (1.0 if y @ lateral >= 0 else -1.0))  # the bone, pointing right
        y = _unit(up - (up @ z) * z)
        x = np.cross(y, z)
    elif functional:
        z = _unit(lateral)
        y = _unit(y - (y @ z) * z)
        x = np.cross(y, z)
    else:
        z = _unit(lateral - (lateral @ y) * y)
        x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def _frames(skeleton, rot: np.ndarray, anatomy: Anatomy, joints: list[_Joint], options: AngleOptions
            ) -> tuple[np.ndarray, dict[str, str]]:
    """:func:`anatomical_frames` from the motion's rotations (F, S, 3, 3) and the named joints."""
    geo = _geometry(skeleton, anatomy, joints)
    refs, functional, source = _lateral_refs(skeleton, rot, anatomy, joints, options)
    frames = np.full((skeleton.n_segments, 3, 3), np.nan)
    right = -anatomy.left
    for s in sorted({s for jt in joints for s in (jt.proximal, jt.distal)}):
        part = anatomy.parts[s]
        y = _long_axis(skeleton, anatomy, s, geo, joints)
        forward = _forward_axis(skeleton, s, geo) if _base(part) in ("foot", "toes") else None
        frames[s] = _frame(part, y, refs.get(s, right), s in functional, forward, anatomy.up)
    return frames, source


def anatomical_frames(skeleton, motion, anatomy: Anatomy, options: AngleOptions | None = None
                      ) -> tuple[np.ndarray, dict[str, str]]:
    """(S, 3, 3) each segment's anatomical frame ``A_s = [X Y Z]`` in its own frame (module
    docstring; NaN for a segment no named joint uses), and per joint its flexion axis source.
    Raises :class:`InputError` as :func:`joint_angles` does."""
    joints = _checked_joints(skeleton, anatomy)
    return _frames(skeleton, _rotations(motion), anatomy, joints, options or AngleOptions())


def _checked_joints(skeleton, anatomy: Anatomy) -> list[_Joint]:
    """The named joints of a human ``anatomy`` that matches ``skeleton`` (else :class:`InputError`)."""
    if len(anatomy.parts) != skeleton.n_segments:
        raise InputError(f"the anatomy names {len(anatomy.parts)} segments, the skeleton has {skeleton.n_segments}")
    if not anatomy.humanoid:
        raise InputError("joint angles need a human body; this one was not identified as human "
                         "(anatomy.humanoid is False), so its joints have no anatomical axes")
    joints = _named_joints(skeleton, anatomy)
    if not joints:
        raise InputError("the anatomy names no joint of this skeleton (no two connected segments have named parts)")
    return joints


def _rotations(motion) -> np.ndarray:
    """(F, S, 3, 3) segment orientations (segment -> world) of a one-trial motion."""
    q = np.asarray(motion.rotations, float)
    if q.ndim != 3:
        raise InputError(f"joint angles take one trial's motion (rotations (F, S, 4)), got shape {q.shape}")
    return quat_to_matrix_np(q)


def _cardan_zxy(m: np.ndarray) -> np.ndarray:
    """(F, 3) the angles ``(a, b, c)`` of ``m = R_Z(a) R_X(b) R_Y(c)`` (F, 3, 3)."""
    b = np.arcsin(np.clip(m[:, 2, 1], -1.0, 1.0))
    a = np.arctan2(-m[:, 0, 1], m[:, 1, 1])
    c = np.arctan2(-m[:, 2, 0], m[:, 2, 2])
    return np.stack([a, b, c], axis=1)


def joint_angles(skeleton, motion, anatomy: Anatomy, *, options: AngleOptions | None = None,
                 frames: np.ndarray | None = None) -> JointAngles:
    """Flexion, ab/adduction and axial rotation of every joint the anatomy names (module docstring).

    Parameters
    ----------
    skeleton, motion
        A rigid skeleton and one trial's motion (:func:`jaxskel.fit_skeleton`'s).
    anatomy
        The skeleton's body parts (:func:`jaxskel.anatomy.identify`); must be human.
    options
        :class:`AngleOptions` (which joints are hinges).
    frames
        (S, 3, 3) anatomical frames to use instead of building them from this motion: a
        calibration's (:attr:`JointAngles.frames`), so that every take of a subject is
        measured in the same frames.

    Raises
    ------
    InputError
        When the anatomy is not human, names no joint, or does not match the skeleton.
    """
    options = options or AngleOptions()
    joints = _checked_joints(skeleton, anatomy)
    rot = _rotations(motion)
    if frames is None:
        frames, source = _frames(skeleton, rot, anatomy, joints, options)
    else:
        frames = np.asarray(frames, float)
        if frames.shape != (skeleton.n_segments, 3, 3):
            raise InputError(f"frames must be (S, 3, 3) = ({skeleton.n_segments}, 3, 3), got {frames.shape}")
        source = {jt.name: "given" for jt in joints}
    names, owners, columns = [], [], []
    for jt in joints:
        m = np.einsum("ji,fjk,kl->fil", frames[jt.proximal], np.einsum("fji,fjk->fik", rot[:, jt.proximal],
                                                                       rot[:, jt.distal]), frames[jt.distal])
        abc = _cardan_zxy(m)
        mirror = -1.0 if side_of(jt.name) == "l" else 1.0
        comps = COMPONENTS[jt.kind][:1] if jt.kind in options.hinges else COMPONENTS[jt.kind]
        for k, (label, sign) in enumerate(comps):
            names.append(f"{jt.name}_{label}")
            owners.append(jt.name)
            columns.append(sign * (mirror if k else 1.0) * abc[:, k])
    return JointAngles(tuple(names), tuple(owners), np.stack(columns, axis=1), motion.rate, source, frames)

