"""Name the body parts of a fitted skeleton from its tree, its bones and its motion.

No marker name is read. The method (issue 72):

1. **Tree.** The fitted tree is taken undirected (its root is the tree's centre, not
   necessarily the pelvis). A *hub* is a segment with three or more neighbours; a
   *branch* of a hub runs out through segments with two neighbours each and ends in a
   leaf (a *limb*) or in another hub (a *spine*). A segment's length in its branch is
   the distance from the joint it is entered by to the joint it is left by, or for a
   leaf to its farthest marker (at the rest pose).
2. **Pairs.** A limb's *hinge* (knee, elbow) is a joint between two consecutive
   segments whose shorter one is at least half the longest such (thigh and shank, upper
   arm and forearm; a long clavicle or a head segment before an upper arm a rival), its
   *span* the sum of those two. The two limbs' hinges are chosen among these so that the
   spans agree and the hinges straighten: least ``mismatch + (bend_a + bend_b) / 2``, with
   ``mismatch`` the spans' difference over the larger and a joint's *bend* ``1 - a / pi``,
   ``a`` the straightest angle it reaches between its two segments (95th percentile over the
   frames). A knee or an elbow straightens; an ankle never does, so a foot as long as half
   the shank does not take the knee's place when its spans happen to agree better. Two
   limbs of one hub whose spans agree to ``limb_match`` and that choose each other are a
   mirror pair. Of
   two pairs the longer is the legs, its hub the pelvis (a tree without hubs, a chain,
   is split at the segment that leaves the best-matched pair: a pelvis with two legs
   and no trunk); the other's hub is the thorax. A lone pair is legs when its span is at
   least
   ``min_leg_span``. The branches between pelvis and thorax are the spine (one segment:
   the abdomen); the thorax's remaining limb (the one pointing along the spine, away
   from the pelvis) is the head chain, all of it the head (the vocabulary has no neck). Along a limb: the
   segment before the hinge is the thigh (upper arm), the one after it the shank
   (forearm), then the foot (hand) and the toes; a short segment before the upper arm
   (``clavicle_ratio``) is the clavicle.
3. **Sides**, from the body's own geometry in every frame, so that neither the lab
   frame nor the heading matters and a mirrored recording swaps every side. A knee
   bends so that the shank goes backwards: with ``u`` the unit thigh (knee to hip) and
   ``c`` the shank (knee to ankle), ``u x (-c_perp) / |c|`` points to the subject's
   left (``c_perp``: ``c`` less its component along ``u``), with length the sine of
   the flexion. A foot points forwards: with ``u`` the unit shank (ankle to knee) and
   ``c`` ankle to the foot's markers, ``u x c_perp / |c|`` points left. An elbow bends
   the forearm forwards: ``u x c_perp / |c|`` (upper arm, forearm). Summing a pair's
   estimates ``L`` per frame, the side evidence of limb 1 being the left one is, per
   limb, ``e = sum_f (h_f . L_f) / sum_f |L_f|`` with ``h_f`` the unit vector from limb
   2's first joint to limb 1's; the mean of the two limbs' (0 where they disagree) is
   the pair's, and sides are named when ``|e| >= min_side_evidence``. Arms are
   sided by their upper arms' middles along the pelvis's left (right hip to left hip),
   which the trunk's twist never turns by a quarter turn, when the legs are sided and
   their elbows do not say the other side as firmly (else they are left unnamed), and by their elbows alone without
   sided legs.
4. **Up and front.** ``up`` is the given lab axis, or (``"auto"``) the mean over the
   frames of the body's up (pelvis to thorax, hips to the legs' distal ends), snapped
   to the nearest signed lab axis within ``axis_snap_deg``. ``front = left x up`` with
   ``left`` at the rest pose (right hip to left hip where the legs are sided, else the
   limbs' side estimate), made perpendicular to ``up``.

Without a motion the rest pose (the skeleton's posture at its rest frame: every
rotation identity, :class:`jaxskel.skeleton.Skeleton`) is the only frame: straight knees
then say little, and the feet and elbows decide.

A tree with no mirror pair of limbs, or whose pairs lack side evidence, is not human:
every part ``""``, confidence 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import InputError
from ._options import AnatomyOptions
from ._vocabulary import Anatomy, is_ancestor

__all__ = ["identify", "identify_result"]

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclasses.dataclass(frozen=True)
class _Branch:
    """Segments from a hub outwards (``segments[0]`` next to the hub), the joints
    entering each, and the hub it ends in (-1: it ends in a leaf)."""

    hub: int
    segments: tuple[int, ...]
    joints: tuple[int, ...]
    end_hub: int
    lengths: np.ndarray  # (len(segments),) metres
    bends: np.ndarray  # (len(segments),) the bend at each segment's entry joint (0 at the hub), in half turns


@dataclasses.dataclass(frozen=True)
class _Limb:
    branch: _Branch
    hinge: int  # index into branch.segments of the segment after the hinge
    span: float


@dataclasses.dataclass(frozen=True)
class _Pair:
    a: _Limb
    b: _Limb
    mismatch: float


@dataclasses.dataclass(frozen=True)
class _Poses:
    """(F, J, 3) joint centres and (F, M, 3) markers (NaN: not on the skeleton), metres."""

    joints: np.ndarray
    markers: np.ndarray


# --------------------------------------------------------------------------- poses
def _rest_pose(skeleton) -> _Poses:
    """The rest pose: every rotation identity, the root's origin at zero (a joint sits at
    ``joint_offsets[j, 0]`` in its parent's frame and ``joint_offsets[j, 1]`` in its child's)."""
    edges = np.asarray(skeleton.edges, int).reshape(-1, 2)
    origin = np.zeros((skeleton.n_segments, 3))
    done = np.zeros(skeleton.n_segments, bool)
    done[skeleton.root] = True
    offsets = np.asarray(skeleton.joint_offsets, float)
    while not done.all():
        ready = done[edges[:, 0]] & ~done[edges[:, 1]]
        if not ready.any():
            break
        origin[edges[ready, 1]] = origin[edges[ready, 0]] + offsets[ready, 0] - offsets[ready, 1]
        done[edges[ready, 1]] = True
    joints = origin[edges[:, 0]] + offsets[:, 0]
    seg = np.asarray(skeleton.marker_segment, int)
    markers = np.where((seg >= 0)[:, None], origin[np.maximum(seg, 0)] + skeleton.marker_offsets, np.nan)
    return _Poses(joints[None], markers[None])


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)  # fmt: skip


def _motion_poses(skeleton, motion, max_frames: int) -> _Poses:
    """Joint centres and markers of the motion's frames (trials stacked), at most
    ``max_frames`` of them spread evenly; frames with a non-finite pose dropped."""
    joints = np.asarray(motion.joint_positions, float).reshape(-1, skeleton.n_joints, 3)
    trans = np.asarray(motion.segment_translations, float).reshape(-1, skeleton.n_segments, 3)
    rot = np.asarray(motion.rotations, float).reshape(-1, skeleton.n_segments, 4)
    keep = np.isfinite(joints).all(axis=(1, 2)) & np.isfinite(trans).all(axis=(1, 2))
    keep &= np.isfinite(rot).all(axis=(1, 2))
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return _rest_pose(skeleton)
    idx = idx[np.unique(np.linspace(0, idx.size - 1, min(max_frames, idx.size)).round().astype(int))]
    seg = np.asarray(skeleton.marker_segment, int)
    on = seg >= 0
    s = np.maximum(seg, 0)
    r = _quat_matrix(rot[idx][:, s])  # (F, M, 3, 3)
    off = np.nan_to_num(np.asarray(skeleton.marker_offsets, float))
    markers = np.einsum("fmij,mj->fmi", r, off) + trans[idx][:, s]
    markers[:, ~on] = np.nan
    return _Poses(joints[idx], markers)


def _point(poses: _Poses, segment: int, marker_segment: np.ndarray) -> np.ndarray:
    """(F, 3) the mean of a segment's markers (NaN without markers)."""
    sel = marker_segment == segment
    if not sel.any():
        return np.full((poses.joints.shape[0], 3), np.nan)
    return poses.markers[:, sel].mean(axis=1)


# --------------------------------------------------------------------------- tree
def _is_proximal(a: str, b: str) -> bool:
    return is_ancestor(a, b)


def _neighbours(edges: np.ndarray, n: int, all_edges: np.ndarray | None = None) -> list[list[tuple[int, int]]]:
    """Each segment's (neighbour, joint) pairs; joints indexed in ``all_edges`` when ``edges``
    is a subset of them."""
    index = {tuple(e): j for j, e in enumerate((edges if all_edges is None else all_edges).tolist())}
    out: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for a, b in edges.tolist():
        out[a].append((b, index[(a, b)]))
        out[b].append((a, index[(a, b)]))
    return out


def _twigs(nbrs, rest: _Poses, marker_segment: np.ndarray, opts: AnatomyOptions) -> dict[int, int]:
    """Twig -> its joint: a leaf with at most ``twig_markers`` markers that either hangs from
    a segment with two other neighbours or sits on another joint of its host (within
    ``twig_ratio`` of the host's extent): a marker over a joint or a landmark, split off
    its segment. Twigs are left out of the tree's chains."""
    out = {}
    for leaf, links in enumerate(nbrs):
        if len(links) != 1 or np.count_nonzero(marker_segment == leaf) > opts.twig_markers:
            continue
        host, joint = links[0]
        others = [j for s, j in nbrs[host] if s != leaf and s not in out]
        if len(others) >= 2:
            out[leaf] = joint
            continue
        extent = _extent(host, nbrs, rest, marker_segment)
        gaps = [np.linalg.norm(rest.joints[0, j] - rest.joints[0, joint]) for j in others]
        near = [g for g in gaps if g <= opts.twig_ratio * extent]
        if near:
            out[leaf] = joint
    return out


def _extent(segment: int, nbrs, rest: _Poses, marker_segment: np.ndarray) -> float:
    """The largest distance between two of a segment's joints and markers at rest."""
    points = np.concatenate([rest.joints[0, [j for _, j in nbrs[segment]]], rest.markers[0, marker_segment == segment]])
    return float(np.linalg.norm(points[:, None] - points[None], axis=-1).max())


def _name_twigs(naming, twigs: dict[int, int], nbrs_all, rest: _Poses, marker_segment, opts: AnatomyOptions) -> None:
    """A twig on a joint of its host takes the part proximal of that joint (an ankle
    marker: the shank), any other twig its host's part; both at half the confidence."""
    for leaf, joint in twigs.items():
        host = [s for s, j in nbrs_all[leaf] if j == joint][0]
        extent = _extent(host, nbrs_all, rest, marker_segment)
        for other, j in nbrs_all[host]:
            if other == leaf or j == joint:
                continue
            near = np.linalg.norm(rest.joints[0, j] - rest.joints[0, joint])
            a, b = naming.parts[host], naming.parts[other]
            if a and b and near <= opts.twig_ratio * extent:
                proximal = b if _is_proximal(b, a) else a
                naming.name(leaf, proximal, 0.5 * min(naming.confidence[host], naming.confidence[other]))
                break
        else:
            naming.name(leaf, naming.parts[host], 0.5 * naming.confidence[host])


def _bends(segments, joints, poses: _Poses, marker_segment: np.ndarray) -> np.ndarray:
    """Per segment of a branch, ``1 - a / pi`` with ``a`` the straightest angle over the
    frames (the 95th percentile) between the previous segment and this one at the joint
    entering it (``segments[0]``: 0); a leaf's far end is its markers' mean."""
    out = np.zeros(len(segments))
    for i in range(1, len(segments)):
        at = poses.joints[:, joints[i]]
        far = poses.joints[:, joints[i + 1]] if i + 1 < len(joints) else _point(poses, segments[i], marker_segment)
        u, c = _unit(poses.joints[:, joints[i - 1]] - at), _unit(far - at)
        angle = np.arccos(np.clip(np.sum(u * c, -1), -1.0, 1.0))
        angle = angle[np.isfinite(angle) & (np.linalg.norm(c, axis=-1) > 0)]
        out[i] = 1.0 - np.percentile(angle, 95) / np.pi if angle.size else 1.0
    return out


def _branches(skeleton, rest: _Poses, nbrs, hub: int, poses: _Poses) -> list[_Branch]:
    """Every branch of ``hub`` (module docstring, 1)."""
    seg = np.asarray(skeleton.marker_segment, int)
    out = []
    for first, j0 in nbrs[hub]:
        segments, joints, prev = [first], [j0], hub
        while len(nbrs[segments[-1]]) == 2:
            nxt = [(s, j) for s, j in nbrs[segments[-1]] if s != prev][0]
            prev = segments[-1]
            segments.append(nxt[0])
            joints.append(nxt[1])
        end = segments[-1]
        end_hub = end if len(nbrs[end]) >= 3 else -1
        if end_hub >= 0:
            segments, joints = segments[:-1], joints[:-1]
        lengths = []
        for i, (s, j) in enumerate(zip(segments, joints)):
            entry = rest.joints[0, j]
            if i + 1 < len(joints):
                lengths.append(float(np.linalg.norm(rest.joints[0, joints[i + 1]] - entry)))
            elif end_hub >= 0:
                exit_j = [jj for ss, jj in nbrs[s] if ss == end_hub][0]
                lengths.append(float(np.linalg.norm(rest.joints[0, exit_j] - entry)))
            else:
                m = rest.markers[0, seg == s]
                lengths.append(float(np.linalg.norm(m - entry, axis=1).max()) if len(m) else 0.0)
        bends = _bends(segments, joints, poses, seg)
        out.append(_Branch(hub, tuple(segments), tuple(joints), end_hub, np.asarray(lengths), bends))
    return out


def _hinge_options(branch: _Branch) -> list[tuple[int, float, float]]:
    """A leaf branch's possible hinges (index of the segment after it), spans and bends: the
    joints between two consecutive segments whose shorter is at least half the best such
    (the knee or elbow, and a near rival: an ankle, a clavicle or head segment before the
    upper arm)."""
    if branch.end_hub >= 0 or len(branch.segments) < 2:
        return []
    pair_len = np.minimum(branch.lengths[:-1], branch.lengths[1:])
    ks = np.flatnonzero(pair_len >= 0.5 * pair_len.max()) + 1
    return [(int(k), float(branch.lengths[k - 1] + branch.lengths[k]), float(branch.bends[k])) for k in ks]


def _limb(branch: _Branch) -> _Limb | None:
    """A leaf branch of two or more segments as a limb: its hinge (the joint between the
    two longest consecutive segments) and span."""
    if branch.end_hub >= 0 or len(branch.segments) < 2:
        return None
    pair_len = np.minimum(branch.lengths[:-1], branch.lengths[1:])
    k = int(np.argmax(pair_len)) + 1
    return _Limb(branch, k, float(branch.lengths[k - 1] + branch.lengths[k]))


def _limbs(branches: list[_Branch]) -> list[_Limb]:
    return [limb for limb in map(_limb, branches) if limb is not None]


def _match(a: _Limb, b: _Limb) -> tuple[float, _Limb, _Limb]:
    """The two limbs' hinges chosen among their options so that their spans agree best and
    the hinges straighten (module docstring, 2): least ``mismatch + (bend_a + bend_b) / 2``.
    Returns the mismatch of the spans at the hinges chosen."""
    best, cost = (np.inf, a, b), np.inf
    for ka, sa, ba in _hinge_options(a.branch):
        for kb, sb, bb in _hinge_options(b.branch):
            m = abs(sa - sb) / max(sa, sb, 1e-12)
            c = m + 0.5 * (ba + bb)
            if c < cost - 1e-9 or (c < cost + 1e-9 and (ka, kb) == (a.hinge, b.hinge)):
                best, cost = (m, _Limb(a.branch, ka, sa), _Limb(b.branch, kb, sb)), c
    return best


def _pairs(limbs: list[_Limb], limb_match: float) -> list[_Pair]:
    """Mutual best mirror partners among one hub's limbs (each pair's hinges by :func:`_match`)."""
    if len(limbs) < 2:
        return []
    matches = {(i, j): _match(limbs[i], limbs[j]) for i in range(len(limbs)) for j in range(len(limbs)) if i != j}
    mismatch = np.full((len(limbs), len(limbs)), np.inf)
    for (i, j), m in matches.items():
        mismatch[i, j] = m[0]
    best = np.argmin(mismatch, axis=1)
    out = []
    for i, j in enumerate(best.tolist()):
        if i < j and best[j] == i and mismatch[i, j] <= limb_match:
            m, a, b = matches[(i, j)]
            out.append(_Pair(a, b, float(m)))
    return out


# --------------------------------------------------------------------------- sides
def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), 0.0)


def _bend_left(u_from: np.ndarray, at: np.ndarray, c_to: np.ndarray, sign: float) -> np.ndarray:
    """(F, 3) ``u x (sign c_perp) / |c|`` with ``u`` the unit vector from ``at`` to
    ``u_from`` and ``c = c_to - at`` (module docstring, 3); zero where undefined."""
    u = _unit(u_from - at)
    c = c_to - at
    c_perp = c - np.sum(c * u, -1, keepdims=True) * u
    out = np.cross(u, sign * c_perp) / np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-12)
    return np.nan_to_num(out)


def _limb_left(limb: _Limb, poses: _Poses, marker_segment: np.ndarray, leg: bool) -> np.ndarray:
    """(F, 3) the limb's own estimates of the subject's left: its hinge's bend and, for a
    leg, its foot (module docstring, 3)."""
    b, k = limb.branch, limb.hinge
    proximal = poses.joints[:, b.joints[k - 1]]
    hinge = poses.joints[:, b.joints[k]]
    distal = poses.joints[:, b.joints[k + 1]] if k + 1 < len(b.joints) else _point(poses, b.segments[k], marker_segment)
    left = _bend_left(proximal, hinge, distal, -1.0 if leg else 1.0)
    if leg and k + 1 < len(b.joints):
        foot = np.nanmean(np.stack([_point(poses, s, marker_segment) for s in b.segments[k + 1:]]), axis=0)
        left = left + _bend_left(hinge, distal, foot, 1.0)
    return left


def _first_joint(limb: _Limb, poses: _Poses) -> np.ndarray:
    return poses.joints[:, limb.branch.joints[0]]


def _side_evidence(pair: _Pair, poses: _Poses, marker_segment: np.ndarray, leg: bool) -> float:
    """``e`` in [-1, 1]: positive when ``pair.a`` is the left limb (module docstring, 3).
    Each limb's estimates are weighed on their own and the two averaged: two limbs that
    disagree give 0."""
    h = _unit(_first_joint(pair.a, poses) - _first_joint(pair.b, poses))
    each = []
    for limb in (pair.a, pair.b):
        left = _limb_left(limb, poses, marker_segment, leg)
        total = np.linalg.norm(left, axis=-1).sum()
        each.append(float(np.sum(h * left) / total) if total > 1e-12 else 0.0)
    return 0.5 * (each[0] + each[1]) if each[0] * each[1] > 0 else 0.0


def _shoulder(limb: _Limb, poses: _Poses) -> np.ndarray:
    """(F, 3) the middle of the upper arm (between its proximal joint, past a clavicle,
    and the elbow): lateral of the trunk however the arm swings."""
    b, k = limb.branch, limb.hinge
    return 0.5 * (poses.joints[:, b.joints[k - 1]] + poses.joints[:, b.joints[k]])


def _along(points_a: np.ndarray, points_b: np.ndarray, left: np.ndarray) -> float:
    """Mean over frames of ``unit(a - b) . unit(left)``."""
    return float(np.mean(np.sum(_unit(points_a - points_b) * _unit(left), -1)))


# --------------------------------------------------------------------------- naming
@dataclasses.dataclass
class _Naming:
    parts: list[str]
    confidence: np.ndarray
    notes: list[str]

    def name(self, segment: int, part: str, confidence: float) -> None:
        if part and segment >= 0:
            self.parts[segment] = part
            self.confidence[segment] = float(np.clip(confidence, 0.0, 1.0))


def _name_limb(naming: _Naming, limb: _Limb, side: str, conf: float, leg: bool, clavicle_ratio: float) -> None:
    b, k = limb.branch, limb.hinge
    distal = ("thigh", "shank", "foot", "toes") if leg else ("upper_arm", "forearm", "hand")
    for i, part in enumerate(distal):
        if k - 1 + i < len(b.segments):
            naming.name(b.segments[k - 1 + i], f"{part}_{side}", conf)
    if not leg and k >= 2 and b.lengths[k - 2] <= clavicle_ratio * b.lengths[k - 1]:
        naming.name(b.segments[k - 2], f"clavicle_{side}", conf)


def _name_pair(naming: _Naming, pair: _Pair, evidence: float, leg: bool, opts: AnatomyOptions) -> bool:
    """Name a pair's limbs by the sign of their side evidence; False where too weak."""
    what = "legs" if leg else "arms"
    if abs(evidence) < opts.min_side_evidence:
        naming.notes.append(
            f"The {what}' side evidence {evidence:+.2f} is below {opts.min_side_evidence}: sides not named."
        )
        return False
    left, right = (pair.a, pair.b) if evidence > 0 else (pair.b, pair.a)
    conf = abs(evidence) * (1.0 - 0.5 * pair.mismatch / max(opts.limb_match, 1e-12))
    _name_limb(naming, left, "l", conf, leg, opts.clavicle_ratio)
    _name_limb(naming, right, "r", conf, leg, opts.clavicle_ratio)
    naming.notes.append(
        f"The {what} (spans {left.span:.2f} and {right.span:.2f} m) are sided by evidence {abs(evidence):.2f}."
    )
    return True


# --------------------------------------------------------------------------- up, front
def _lab_up(up_axis: str) -> np.ndarray | None:
    if up_axis == "auto":
        return None
    axis = up_axis.lstrip("-")
    if axis not in _AXES or up_axis.count("-") > 1:
        raise InputError(f"up_axis must be 'auto', 'x', 'y', 'z', '-x', '-y' or '-z'; got {up_axis!r}")
    v = np.zeros(3)
    v[_AXES[axis]] = -1.0 if up_axis.startswith("-") else 1.0
    return v


def _snap(v: np.ndarray, max_deg: float) -> np.ndarray:
    v = _unit(v)
    i = int(np.argmax(np.abs(v)))
    axis = np.zeros(3)
    axis[i] = np.sign(v[i]) or 1.0
    return axis if np.degrees(np.arccos(np.clip(abs(v[i]), -1, 1))) <= max_deg else v


def _rest_left(legs: _Pair | None, arms: _Pair | None, rest: _Poses, marker_segment: np.ndarray) -> np.ndarray:
    for pair, leg in ((legs, True), (arms, False)):
        if pair is not None:
            left = _limb_left(pair.a, rest, marker_segment, leg) + _limb_left(pair.b, rest, marker_segment, leg)
            if np.linalg.norm(left[0]) > 1e-9:
                return left[0]
    return np.zeros(3)


def _front(up: np.ndarray, left: np.ndarray) -> np.ndarray:
    left = left - np.dot(left, up) * up
    if np.linalg.norm(left) < 1e-9:
        left = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    return _unit(np.cross(_unit(left), up))


# --------------------------------------------------------------------------- main
def _not_human(n: int, up: np.ndarray | None, why: str) -> Anatomy:
    notes = (why,) if up is not None else (why, "No body to find the vertical from: +Z taken as up.")
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    return Anatomy(("",) * n, np.zeros(n), False, up, _front(up, np.zeros(3)), notes)


def _check(skeleton, up_axis, options) -> AnatomyOptions:
    if options is None:
        return AnatomyOptions()
    if not isinstance(options, AnatomyOptions):
        raise InputError(f"options must be a jaxskel.anatomy.AnatomyOptions; got {type(options).__name__}")
    if not isinstance(up_axis, str):
        raise InputError(f"up_axis must be a string ('auto', 'x', ..., '-z'); got {up_axis!r}")
    return options


def identify(skeleton, motion=None, *, up_axis: str = "auto", options: AnatomyOptions | None = None) -> Anatomy:
    """The body part of every segment of a fitted skeleton (module docstring).

    Parameters
    ----------
    skeleton
        A fitted :class:`jaxskel.skeleton.Skeleton` (``result.skeleton``).
    motion
        Its :class:`jaxskel.skeleton.Motion` (``result.motion``), or None: the rest pose
        is then the only frame.
    up_axis
        The lab's vertical (``"x"``, ``"y"``, ``"z"``, ``"-x"``, ``"-y"``, ``"-z"``), or
        ``"auto"``: measured from the body. It sets :attr:`Anatomy.up` and
        :attr:`Anatomy.front`; the parts and their sides do not depend on it.
    options
        :class:`AnatomyOptions`; default the defaults.
    """
    opts = _check(skeleton, up_axis, options)
    lab_up = _lab_up(up_axis)
    n = int(skeleton.n_segments)
    edges = np.asarray(skeleton.edges, int).reshape(-1, 2)
    marker_segment = np.asarray(skeleton.marker_segment, int)
    rest = _rest_pose(skeleton)
    poses = rest if motion is None else _motion_poses(skeleton, motion, opts.max_frames)
    twigs = _twigs(_neighbours(edges, n), rest, marker_segment, opts)
    nbrs = _neighbours(edges[[j not in twigs.values() for j in range(len(edges))]] if twigs else edges, n, edges)
    hubs = [s for s in range(n) if len(nbrs[s]) >= 3]
    branches = {h: _branches(skeleton, rest, nbrs, h, poses) for h in hubs}
    pairs = [p for h in hubs for p in _pairs(_limbs(branches[h]), opts.limb_match)]
    if not pairs:  # a partial body: two legs on a pelvis with no trunk, a chain
        pairs = _chain_pair(skeleton, rest, nbrs, poses, opts)
        hubs = [p.a.branch.hub for p in pairs]
        branches = {h: _branches(skeleton, rest, nbrs, h, poses) for h in hubs}
    if not pairs:
        return _not_human(n, lab_up, "No hub of the tree carries two limbs of matching length: not a human body.")
    pairs.sort(key=lambda p: -(p.a.span + p.b.span))
    legs, arms = _legs_and_arms(pairs, opts)
    naming = _Naming([""] * n, np.zeros(n), [])
    leg_e = _side_evidence(legs, poses, marker_segment, True) if legs is not None else 0.0
    arm_e = _side_evidence(arms, poses, marker_segment, False) if arms is not None else 0.0
    if max(abs(leg_e), abs(arm_e)) < opts.min_side_evidence:
        return _not_human(
            n, lab_up,
            f"The matched limbs do not bend like knees or elbows (side evidence {leg_e:+.2f}, {arm_e:+.2f}): "
            "not a human body.",
        )  # fmt: skip
    legs_sided = legs is not None and _name_pair(naming, legs, leg_e, True, opts)
    if legs is not None:
        naming.name(legs.a.branch.hub, "pelvis", 1.0 - 0.5 * legs.mismatch / max(opts.limb_match, 1e-12))
    thorax = _thorax(legs, arms, branches)
    if thorax >= 0:
        naming.name(thorax, "thorax", 0.9)
    if arms is not None:
        if legs_sided:
            by_hips = _arms_by_hips(arms, legs, leg_e, poses, opts)
            conflict = by_hips * arm_e < 0 and abs(arm_e) >= opts.min_side_evidence
            if conflict:
                naming.notes.append(
                    f"The arms' shoulders ({by_hips:+.2f}) and elbows ({arm_e:+.2f}) disagree on their sides: "
                    "not named."
                )
            arm_e = 0.0 if conflict else by_hips
        _name_pair(naming, arms, arm_e, False, opts)
    elif legs_sided and thorax >= 0:
        _name_lone_arm(naming, legs, leg_e, thorax, branches, poses, opts)
    if thorax >= 0:
        _name_trunk(naming, legs, thorax, branches, poses, marker_segment)
    _name_twigs(naming, twigs, _neighbours(edges, n), rest, marker_segment, opts)
    up = lab_up if lab_up is not None else _auto_up(legs, thorax, poses, marker_segment, opts)
    rest_left = _hip_left(legs, leg_e, rest)[0] if legs_sided else _rest_left(legs, arms, rest, marker_segment)
    front = _front(up, rest_left)
    return Anatomy(tuple(naming.parts), naming.confidence, True, up, front, tuple(naming.notes))


def _chain_pair(skeleton, rest: _Poses, nbrs, poses: _Poses, opts: AnatomyOptions) -> list[_Pair]:
    """A tree without a hub, a chain: the segment that splits it into the best-matched
    pair of limbs (a pelvis between two legs), as a one-pair list (empty: none)."""
    best: list[_Pair] = []
    for s in range(len(nbrs)):
        if len(nbrs[s]) == 2:
            pairs = _pairs(_limbs(_branches(skeleton, rest, nbrs, s, poses)), opts.limb_match)
            if pairs and (not best or pairs[0].mismatch < best[0].mismatch):
                best = pairs
    return best


def _legs_and_arms(pairs: list[_Pair], opts: AnatomyOptions) -> tuple[_Pair | None, _Pair | None]:
    """The longest pair is the legs and the next the arms; a lone pair by its span."""
    if len(pairs) >= 2:
        return pairs[0], pairs[1]
    p = pairs[0]
    return (p, None) if 0.5 * (p.a.span + p.b.span) >= opts.min_leg_span else (None, p)


def _thorax(legs: _Pair | None, arms: _Pair | None, branches: dict[int, list[_Branch]]) -> int:
    """The arms' hub, else the hub the pelvis's spine branch ends in (-1: none)."""
    if arms is not None:
        return arms.a.branch.hub
    if legs is None:
        return -1
    ends = [b.end_hub for b in branches[legs.a.branch.hub] if b.end_hub >= 0]
    return ends[0] if len(ends) == 1 else -1


def _spine(legs: _Pair | None, thorax: int, branches: dict[int, list[_Branch]]) -> _Branch | None:
    if legs is None:
        return None
    for b in branches[legs.a.branch.hub]:
        if b.end_hub == thorax:
            return b
    return None


def _name_trunk(naming, legs, thorax, branches, poses, marker_segment) -> None:
    """The abdomen (a one-segment spine) and the head (the distal segment of the
    thorax's free leaf branch pointing most along the spine)."""
    spine = _spine(legs, thorax, branches)
    if spine is not None and len(spine.segments) == 1:
        naming.name(spine.segments[0], "abdomen", 0.8)
    taken = {s for s in range(len(naming.parts)) if naming.parts[s]}
    free = [b for b in branches[thorax] if b.end_hub < 0 and not taken.intersection(b.segments)]
    if spine is not None:
        free = [b for b in free if b is not spine]
    if not free:
        return
    centre = _point(poses, thorax, marker_segment)
    if legs is not None:
        pelvis = _point(poses, legs.a.branch.hub, marker_segment)
        axis = _unit(centre - pelvis)
    else:
        axis = np.zeros_like(centre)
    tips = [_unit(_point(poses, b.segments[-1], marker_segment) - centre) for b in free]
    score = [float(np.nanmean(np.sum(tip * axis, -1))) for tip in tips]
    best = free[int(np.nanargmax(score))] if legs is not None else (free[0] if len(free) == 1 else None)
    if best is not None and (legs is None or max(score) > 0.3):
        conf = 0.8 if len(free) == 1 else 0.6
        for i, segment in enumerate(best.segments):  # no neck part: the whole chain is the head
            naming.name(segment, "head", conf if i == len(best.segments) - 1 else 0.5 * conf)


def _hip_left(legs: _Pair, leg_e: float, poses: _Poses) -> np.ndarray:
    """(F, 3) right hip to left hip."""
    a, b = _first_joint(legs.a, poses), _first_joint(legs.b, poses)
    return a - b if leg_e > 0 else b - a


def _arms_by_hips(arms: _Pair, legs: _Pair, leg_e: float, poses: _Poses, opts: AnatomyOptions) -> float:
    """Side evidence of ``arms.a`` being the left arm: its shoulder along the hips' left."""
    left = _hip_left(legs, leg_e, poses)
    sa, sb = _shoulder(arms.a, poses), _shoulder(arms.b, poses)
    return _along(sa, sb, left) * min(1.0, abs(leg_e) / max(opts.min_side_evidence, 1e-12))


def _name_lone_arm(naming, legs, leg_e, thorax, branches, poses, opts) -> None:
    """One arm on the thorax (the other has no markers): sided by its shoulder's place
    along the hips' left relative to the thorax's other joints."""
    taken = {s for s in range(len(naming.parts)) if naming.parts[s]}
    cands = [lb for lb in _limbs(branches[thorax]) if not taken.intersection(lb.branch.segments)]
    if len(cands) != 1:
        return
    arm = cands[0]
    others = [j for b in branches[thorax] for j in b.joints[:1] if b is not arm.branch]
    mid = poses.joints[:, others].mean(axis=1)
    e = _along(_shoulder(arm, poses), mid, _hip_left(legs, leg_e, poses))
    if abs(e) >= opts.min_side_evidence:
        _name_limb(naming, arm, "l" if e > 0 else "r", abs(e) * 0.8, False, opts.clavicle_ratio)
        naming.notes.append(f"One arm only: sided by its shoulder along the hips' left ({abs(e):.2f}).")


def _auto_up(legs, thorax, poses, marker_segment, opts) -> np.ndarray:
    """Mean body up over the frames, snapped to a lab axis (module docstring, 4)."""
    ups = []
    if legs is not None:
        for limb in (legs.a, legs.b):
            b, k = limb.branch, limb.hinge
            tip = poses.joints[:, b.joints[k + 1]] if k + 1 < len(b.joints) else None
            tip = _point(poses, b.segments[k], marker_segment) if tip is None else tip
            ups.append(_unit(_first_joint(limb, poses) - tip))
        if thorax >= 0:
            ups.append(_unit(_point(poses, thorax, marker_segment) - _point(poses, legs.a.branch.hub, marker_segment)))
    mean = np.nanmean(np.concatenate(ups), axis=0) if ups else np.array([0.0, 0.0, 1.0])
    return _snap(mean, opts.axis_snap_deg)


def identify_result(result, *, options: AnatomyOptions | None = None) -> Anatomy:
    """:func:`identify` of a :class:`jaxskel.SkeletonResult`: its skeleton, its motion
    (None without IK) and its trial's up axis (``"unknown"``: ``"auto"``)."""
    if result.skeleton is None:
        raise InputError("the result has no rigid skeleton; fit with rigid=True to name its body parts")
    up = result.trial.up_axis
    return identify(result.skeleton, result.motion, up_axis="auto" if up == "unknown" else up, options=options)
