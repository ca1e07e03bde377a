"""Where a hinge's centre sits along its axis: the limb plane of its neighbouring joints.

A joint whose two segments only turn about one axis relative to each other (a knee, an
elbow, a weakly exercised wrist) keeps every marker-to-joint distance constant for any
point on that axis, so the markers do not say where along the axis the centre is
(:mod:`jaxskel.joints._cost` reports it as ``undetermined``). Kirk et al. (2005, §3.2)
let the distance prior decide: it pulls the centre towards the markers, i.e. onto the
skin where the markers are, lateral of the true centre for lateral knee and elbow
markers, which makes the long bones too long and biases every joint angle that uses them
(measured: docs/bench/evidence_from_docstrings.md).

This module places such a centre instead in the plane of the joints next to it: the
point on the axis where the axis crosses the plane, perpendicular to it, through the
mean of the other joints of the two segments (knee: hip and ankle; elbow: shoulder and
wrist). Human long bones run nearly perpendicular to their flexion axes, so this is
the mechanical-axis convention of biomechanics (the hip, knee and ankle centres in one
plane); it uses only the fitted joints, never the markers' side of the limb.

Maths. Let ``Q_f = R_c(f) R_p(f)^T`` be the relative rotation (segment mean frames of
the per-segment Procrustes fit, :mod:`jaxskel.skeleton._rigid_fit`). A hinge axis ``a_p`` (parent
frame) is a direction every ``Q_f`` maps to the same child-frame vector ``a_c``, so it
maximises ``|mean_f Q_f a_p|``: the top right singular vector of ``mean_f Q_f``, and
``a_c = mean_f Q_f a_p`` normalised. Shifting joint j by ``s_j`` moves it to
``p + s_j a`` in both segment frames. The shifts solve, in least squares over all
sliding joints at once (a neighbour may slide too)::

    for every sliding joint j, segment X of j, other joint k on X:
        a_X^j . (p_X^k + s_k a_X^k - p_X^j - s_j a_X^j) = 0

(``s_k = 0`` for a joint that does not slide; only joints that turn as hinges about an
axis that crosses their bones slide, see :data:`MAX_OFF_AXIS`, :data:`MAX_BONE_COSINE`),
each equation weighted by the inverse variance of neighbour k's position, with a ridge
``1e-6 s^2`` so that a chain of parallel hinges with nothing else attached keeps the
prior's placement. For a single sliding joint this is the weighted mean of its
neighbours' coordinates along the axis.

**Landmarks that straddle the joint** take precedence (:func:`straddling_pair`): where two
anatomical markers of a static trial, left out of the grouping (the medial and lateral
epicondyles of a knee, the malleoli of an ankle), sit on the axis on either side of the
joint, the centre goes midway between them along the axis, which is where a person puts
it. The fit's own markers are not candidates: on a moving limb an oblique axis passes
pairs of surface markers (two midfoot markers for an ankle). With ``t = a . (m - p)``
the coordinate of marker m along the axis from the joint p and ``r`` its distance from
the axis, two markers nearer this joint than any other straddle it when both ``r`` are at
most :data:`STRADDLE_RATIO` times their separation ``|t_1 - t_2|`` (their line within
~30-50 degrees of the axis); of several pairs, the one with the smallest ratio; the shift
is ``(t_1 + t_2) / 2``.
Such a joint is then a fixed neighbour (``s_k`` known) in the limb-plane equations of the
others.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

__all__ = [
    "MAX_BONE_COSINE", "MAX_OFF_AXIS", "MAX_OFF_AXIS_REFINED", "MIN_ROTATION_RMS", "STRADDLE_RATIO", "hinge_axes",
    "MIN_STRADDLE_WIDTH", "axial_coordinates", "axis_along_a_bone", "hinge_shifts", "longest_bone", "straddling_pair",
]

#: A joint slides only if it turns as a hinge: the share of its rotation about the other
#: axes (:func:`hinge_axes`) below 0.12, i.e. RMS angle about them under ~35 % of the
#: total: it separates knees and elbows from two-axis wrists and ankles (measured:
#: docs/bench/evidence_from_docstrings.md). A universal joint turned about both axes is
#: pinned by its markers in every direction, and moving it along a compromise axis makes it
#: worse, so only hinge-like motion is moved.
MAX_OFF_AXIS = 0.12

#: A moved joint is moved back (the skeleton fitted again without its slide) only if the
#: refined poses of all kept frames show it clearly not turning as a hinge: its share of
#: rotation about the other axes at least twice :data:`MAX_OFF_AXIS`. The axis that moved it
#: came from the frames Procrustes poses (every marker of both segments seen); under heavy
#: occlusion those are a few short windows, in each of which any joint turns about nearly
#: one axis. The factor of two keeps the true hinges of real recordings, which stay well
#: under it, and undoes the slides that heavy occlusion causes, which land well over it
#: (measured: docs/bench/evidence_from_docstrings.md).
MAX_OFF_AXIS_REFINED = 2.0 * MAX_OFF_AXIS

#: A joint slides only if its axis crosses its bones: the cosine between the axis and the
#: line to every neighbouring joint below 0.5 (axis at least 60 degrees from each bone).
#: An axis along a bone is a twist (an "elbow" turning about the forearm's long axis,
#: whose limb-plane target would put the centre far up the arm); there the bone line, not
#: the plane, fixes the centre, and the prior's placement is kept.
MAX_BONE_COSINE = 0.5

#: A joint must turn by at least 5 degrees RMS (about its main axis) for its axis to be
#: taken: below that the direction of least rotation is set by noise, and a pair that
#: does not move at all (every direction "least rotated") would look like a perfect hinge.
MIN_ROTATION_RMS = float(np.deg2rad(5.0))

#: Two markers straddle a hinge when each lies at most this many times their separation
#: along the axis from it (module docstring): 0.6 admits epicondyle markers 1-3 cm off the
#: axis of a 9-12 cm wide knee, and malleolus markers, whose line runs up to ~30 degrees
#: from the ankle's axis (the lateral malleolus sits lower and further back), and turns
#: away two markers on one side of a limb (a small separation along the axis) and the
#: markers of a limb's surface, which lie across the axis, not along it.
STRADDLE_RATIO = 0.6

#: Straddling markers are at least this fraction of the joint's longest bone apart: the
#: width of a joint across its axis (epicondyles, malleoli, styloids: 0.17-0.25 of the
#: bone), not two markers on one side of a limb.
MIN_STRADDLE_WIDTH = 0.1

#: Ridge on the shifts (m^2 per m^2 of equation residual); see the module docstring.
_RIDGE = 1e-6


def hinge_axes(
    rot_parent: Float[np.ndarray, "F 3 3"],
    rot_child: Float[np.ndarray, "F 3 3"],
    weight: Float[np.ndarray, " F"],
) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"], float]:
    """The axis of least relative rotation, in the parent and the child frame.

    ``rot_*[f]`` maps world directions into the segment frame. Returns ``(a_p, a_c,
    off_axis)``: ``off_axis`` is the share of the rotation about the other axes,
    ``(1 - s_1) / (1 - s_3)`` with ``s_1 >= s_2 >= s_3`` the singular values of
    ``mean_f Q_f`` (``1 - s ~ mean theta^2 / 2`` about each principal direction): ~0 for
    a hinge, ~1 for a ball joint exercised alike about all axes, and ``inf`` for a pair
    that turns less than :data:`MIN_ROTATION_RMS` (no axis to speak of).
    """
    w = np.asarray(weight, dtype=float)
    q = np.einsum("fij,fkj->fik", rot_child, rot_parent)  # R_c R_p^T
    q_mean = np.einsum("f,fij->ij", w, q) / max(w.sum(), 1e-12)
    _, sv, vt = np.linalg.svd(q_mean)
    a_p = vt[0]
    a_c = q_mean @ a_p
    turned = 1.0 - sv[2]
    off_axis = (1.0 - sv[0]) / turned if turned >= 0.5 * MIN_ROTATION_RMS**2 else np.inf
    return a_p, a_c / max(np.linalg.norm(a_c), 1e-12), float(off_axis)


def _neighbours(edges: np.ndarray, j: int):
    """``(side, k, k_side)`` for every other joint k on joint j's parent (side 0) and child
    (side 1) segment; ``k_side`` says whether that segment is k's parent (0) or child (1)."""
    for side in (0, 1):
        seg = edges[j, side]
        for k in np.flatnonzero((edges[:, 0] == seg) | (edges[:, 1] == seg)):
            if k != j:
                yield side, int(k), 0 if edges[k, 0] == seg else 1


def longest_bone(edges: Int[np.ndarray, "J 2"], j: int, joint_points: Float[np.ndarray, "J 2 3"]) -> float:
    """The longest distance from joint j to another joint on one of its segments (0: none)."""
    lengths = [np.linalg.norm(joint_points[k, k_side] - joint_points[j, side])
               for side, k, k_side in _neighbours(np.asarray(edges), j)]
    return float(max(lengths, default=0.0))


def axis_along_a_bone(
    edges: Int[np.ndarray, "J 2"], j: int, joint_points: Float[np.ndarray, "J 2 3"],
    axes: Float[np.ndarray, "J 2 3"],
) -> bool:
    """Whether joint j's axis runs along one of its bones (cosine with the line to a
    neighbouring joint above :data:`MAX_BONE_COSINE`): a twist, whose centre the bone line,
    not a plane or a pair of markers across it, fixes."""
    for side, k, k_side in _neighbours(np.asarray(edges), j):
        bone = joint_points[k, k_side] - joint_points[j, side]
        length = np.linalg.norm(bone)
        if length > 0 and abs(axes[j, side] @ bone) > MAX_BONE_COSINE * length:
            return True
    return False


def hinge_shifts(
    edges: Int[np.ndarray, "J 2"],
    slide: Bool[np.ndarray, " J"],
    joint_points: Float[np.ndarray, "J 2 3"],
    axes: Float[np.ndarray, "J 2 3"],
    weights: Float[np.ndarray, " J"] | None = None,
) -> Float[np.ndarray, " J"]:
    """Shift of every sliding joint along its axis (module docstring), metres.

    ``joint_points[j]`` / ``axes[j]``: joint j's position and axis in its parent's and
    its child's frame (rows 0 and 1). ``weights[k]`` (default 1): weight of the equations
    in which joint k is the neighbour (inverse variance of its position). Joints with
    ``slide`` false, or whose axis runs along one of their bones (:data:`MAX_BONE_COSINE`),
    get 0.
    """
    edges = np.asarray(edges)
    slide = np.array(slide, dtype=bool)
    n_joints = edges.shape[0]
    for j in np.flatnonzero(slide):
        if axis_along_a_bone(edges, j, joint_points, axes):
            slide[j] = False
    unknown = np.flatnonzero(slide)
    column = {int(j): i for i, j in enumerate(unknown)}
    rows, rhs = [], []
    for j in unknown:
        for side, k, k_side in _neighbours(edges, j):
            a_j = axes[j, side]
            row = np.zeros(unknown.size)
            row[column[int(j)]] = 1.0
            if slide[k]:
                row[column[int(k)]] -= float(a_j @ axes[k, k_side])
            w = 1.0 if weights is None else float(np.sqrt(weights[k]))
            rows.append(w * row)
            rhs.append(w * float(a_j @ (joint_points[k, k_side] - joint_points[j, side])))
    shifts = np.zeros(n_joints)
    if not rows:
        return shifts
    a = np.vstack(rows + [np.sqrt(_RIDGE) * np.eye(unknown.size)])
    b = np.concatenate([rhs, np.zeros(unknown.size)])
    shifts[unknown] = np.linalg.lstsq(a, b, rcond=None)[0]
    return shifts


def straddling_pair(
    along: Float[np.ndarray, " N"], off: Float[np.ndarray, " N"], bone: float = 0.0
) -> tuple[int, int, float] | None:
    """The pair of markers that straddles a hinge (module docstring), or ``None``.

    ``along[i]``: marker i's coordinate along the axis from the current centre (metres);
    ``off[i]``: its distance from the axis. The candidates are markers nearer this joint
    than any other (the caller's choice). A pair straddles the joint when both lie within
    :data:`STRADDLE_RATIO` times their separation of the axis; of several, the one closest
    to the axis relative to its separation. The pair must also be at least
    :data:`MIN_STRADDLE_WIDTH` times ``bone`` apart (the joint's longest bone: a knee's
    epicondyles are about a fifth of a femur apart, two markers on one side of a foot a
    twentieth of a shank). Returns ``(i, k, shift)`` with ``along[i] > along[k]`` and
    ``shift = (along[i] + along[k]) / 2``, the move along the axis that puts
    the centre midway between them (the current centre, which the motion leaves free along
    the axis, need not lie between them).
    """
    t = np.asarray(along, dtype=float)
    r = np.asarray(off, dtype=float)
    ok = np.flatnonzero(np.isfinite(t) & np.isfinite(r))
    if ok.size < 2:
        return None
    t, r = t[ok], r[ok]
    sep = np.abs(t[:, None] - t[None, :])
    worst = np.maximum(r[:, None], r[None, :]) / np.where(sep > 0, sep, np.nan)
    sep = np.where(sep >= MIN_STRADDLE_WIDTH * bone, sep, 0.0)
    np.fill_diagonal(worst, np.nan)
    if not np.isfinite(worst).any():
        return None
    a, b = np.unravel_index(np.nanargmin(worst), worst.shape)
    if worst[a, b] > STRADDLE_RATIO:
        return None
    if t[a] < t[b]:
        a, b = b, a
    return int(ok[a]), int(ok[b]), float(0.5 * (t[a] + t[b]))


def axial_coordinates(
    points: Float[np.ndarray, "N 3"], centre: Float[np.ndarray, " 3"], axis: Float[np.ndarray, " 3"]
) -> tuple[Float[np.ndarray, " N"], Float[np.ndarray, " N"]]:
    """``(t, r)``: each point's coordinate along the unit ``axis`` from ``centre`` and its
    distance from the axis line."""
    u = np.asarray(points, dtype=float) - centre
    t = u @ axis
    return t, np.linalg.norm(u - t[:, None] * axis, axis=-1)
