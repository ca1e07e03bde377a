"""Rigid-body skeleton from markers and joint centres (Kirk et al. 2005, §3.3).

The joint centres of §3.2 are noisy: the joints of one segment drift relative to each
other from frame to frame. This stage projects markers and joints onto a true rigid
skeleton, in two steps.

1. **Per-segment Procrustes** (the paper's method). For each segment take the frames in
   which all its markers are present; align each frame's points (its markers and the
   centres of its joints) to a reference by Horn's method, replace the reference by the
   mean of the aligned clouds and repeat (generalised Procrustes analysis). The mean
   cloud gives constant marker and joint offsets in the segment frame. Including the
   joint centres is what lets segments with one or two markers be posed: a segment with
   fewer than three non-collinear points in total is skipped here and placed by step 2.
   The joint of a one-marker segment weighs in its host's alignment by how still it
   sits there (:mod:`jaxskel.skeleton._attachment_weights`): a cluster marker split off
   by soft tissue drags its joint with it and must not turn the host.

2. **Global refinement** (optional, on by default). One least-squares problem over the
   frames where the skeleton is rigid::

       min  sum_f sum_m mask_fm |R_s(m)(f) o_m + t_s(m)(f) - x_fm|^2
          + w_J^2 sum_f sum_j mask_fj |joint_j(f) - z_fj|^2

   over the constant offsets (``o_m`` and each joint's offset in its parent frame) and
   each frame's root translation and segment rotations, with the tree constraint built
   in (:mod:`jaxskel.skeleton._ik`). ``z`` are the input joint centres with weight ``w_J``
   (``joint_weight``): they pin what the markers leave free (the centre of a hinge along
   its axis). Which weight is right depends on where the centres come from. Exact centres
   keep soft-tissue motion, which is correlated with the joint angles, from dragging the
   joints, so ``fit_rigid``'s default trusts them like a marker (``w_J = 1``). Centres
   solved from the same soft-tissue markers carry that bias themselves, larger on small
   segments; :func:`jaxskel.fit_skeleton` therefore uses ``w_J = 0.1`` and places hinges
   along their axes itself (``SOLVED_JOINT_WEIGHT``, ``sliding_joints``).

   Structure: given the offsets the frames are independent (a batch of small IK
   problems); given the poses the problem is *linear* in the offsets. So the solve
   alternates an IK sweep over all frames (the batched solver of
   :mod:`jaxskel.skeleton._ik_batch`, warm-started from the previous sweep) with the exact
   linear least-squares solution for the offsets (normal equations assembled from
   per-frame rotation products). Each sweep cannot increase the cost (up to the weak IK
   pose prior); the loop stops when an offset update moves no offset by more than
   ``xtol``, the updates Anderson-accelerated. The whole alternation, its IK sweeps
   included, is one device program (:mod:`jaxskel.skeleton._rigid_sweeps`, ``_refine``).
   Frames whose marker RMS after the first sweep is an outlier (above median + 5 MAD:
   swaps, jumps, a marker knocked loose) are left out. At most ``max_frames`` frames,
   spread evenly over the trial, are used.

Segment frames (the convention of :class:`Skeleton`, :class:`jaxskel.skeleton.Motion` and the BVH
export): the origin of a segment is its proximal joint (the joint to its parent), so
``joint_offsets[:, 1]`` is zero; the root's origin is the centroid of its markers. The
axes are parallel to the world axes at the *rest frame* ``diagnostics["rest_frame"]``
(the first of the fitting frames that shows the most markers): the rest pose, all
rotations identity, is the subject's posture in that frame.

Markers whose residual RMS exceeds ``nonrigid_factor`` (3) times the median marker RMS
and the median by more than 1 mm are reported as not rigidly attached (soft tissue, a
marker on the wrong segment); the test is relative so that it adapts to the noise level
of the recording, with the absolute margin keeping it quiet on nearly noise-free data
(:func:`jaxskel._math.outliers.above_median`, the rule the segmentation's scatter uses too).
"""

from __future__ import annotations

import dataclasses
import types
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._errors import ConvergenceWarning, DegenerateMotionError, DegenerateMotionWarning, InputError
from .._math.outliers import above_median
from .._math.padding import bucket_size
from .._math.procrustes import procrustes
from .._math.rotation import quat_to_matrix_np
from .._runtime import program_cache as _program_cache
from .._runtime.backend import to_device
from .._runtime.precision import float64_scope
from ..io import Trial
from ._attachment_weights import attachment_points, attachment_weights, scatter_about_mean
from ._hinge_centres import (
    MAX_OFF_AXIS, MAX_OFF_AXIS_REFINED, axial_coordinates, axis_along_a_bone, hinge_axes, hinge_shifts,
    longest_bone, straddling_pair,
)
from ._ik import (
    DEFAULT_PRIOR_WEIGHT,
    RESULT_MAX_STEPS,
    RESULT_SUCCESSFUL,
    IKModel,
    ik_model,
    kinematic_chain,
)
from ._ik_batch import batch_model, solver_shape
from ._rigid_records import JOINT_WEIGHT, RigidDiagnostics, RigidOptions
from ._rigid_sweeps import SweepProblem, alternate, offset_pairs

__all__ = ["JOINT_WEIGHT", "RigidDiagnostics", "RigidOptions", "Skeleton", "fit_rigid", "validate_tree"]

#: Pairs (beyond the newest) the refinement's Anderson acceleration combines (``_refine``).
_ANDERSON_MEMORY = 5

#: The weight :func:`jaxskel.fit_skeleton` gives the centres of its own joint solve. Soft
#: tissue that moves with the joint angles biases each per-frame centre (a marker near
#: the joint sliding 3 mm moves the sphere centre by centimetres on a small segment), while
#: the articulated fit of all markers averages it out; the centres are then needed only
#: where markers say nothing (a hinge along its axis, placed by :mod:`jaxskel.skeleton._hinge_centres`
#: before and after the refinement). A much smaller weight lets hinges drift along their
#: axes again.
SOLVED_JOINT_WEIGHT = 0.1

#: A flagged marker's residual RMS is also this far (m) over the median (:func:`jaxskel._math.outliers.above_median`).
NONRIGID_MARGIN = 1e-3


# ----------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True, eq=False)
class Skeleton:
    """A rigid articulated skeleton: constant offsets on a tree of segments.

    Segment frames: origin at the proximal joint (root: centroid of its markers), axes
    parallel to the world at the rest frame (module docstring).

    Attributes
    ----------
    n_segments
        S.
    edges
        (J, 2) parent -> child segments; row j is joint j.
    root
        Root segment.
    marker_labels
        (M,) labels.
    marker_segment
        (M,) segment of each marker, -1 if unused.
    marker_offsets
        (M, 3) each marker in its segment frame, metres (NaN if unused).
    joint_offsets
        (J, 2, 3) joint j in the parent frame and in the child frame (the latter zero).
    bones
        (B, 2) pairs of joints on one segment (every pair, so a segment with k joints has
        k (k - 1) / 2 bones and a leaf segment none).
    bone_lengths
        (B,) rigid length of each bone, metres.
    bone_segment
        (B,) the segment each bone lies on.
    segment_lengths
        (S,) largest distance between two joints of a segment (NaN with fewer than two).
    marker_rms
        (M,) RMS distance between each marker and its fitted position over the fitting
        frames (noise plus soft-tissue motion), NaN if unused.
    nonrigid_markers
        Labels of markers that do not sit rigidly on their segment (module docstring).
    diagnostics
        The fit's :class:`RigidDiagnostics` (its entries are documented there): a typed
        record that is also a read-only mapping. A plain mapping given here (one read back
        from a result file, or the pipeline's with its ``"anchored"`` entry added) becomes
        that record when it holds a rigid fit's entries, else stays a read-only mapping.
    segment_names
        (S,) names of the segments (display and export only; ``()`` when not named:
        :meth:`names` derives them from the markers' labels).
    """

    n_segments: int
    edges: np.ndarray
    root: int
    marker_labels: tuple[str, ...]
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    joint_offsets: np.ndarray
    bones: np.ndarray
    bone_lengths: np.ndarray
    bone_segment: np.ndarray
    segment_lengths: np.ndarray
    marker_rms: np.ndarray
    nonrigid_markers: tuple[str, ...]
    diagnostics: Mapping[str, Any]
    segment_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in (
            "edges", "marker_segment", "marker_offsets", "joint_offsets", "bones",
            "bone_lengths", "bone_segment", "segment_lengths", "marker_rms",
        ):
            a = np.array(getattr(self, name), copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        # a rigid fit's entries as their typed record (also when read back as a plain mapping)
        typed = RigidDiagnostics.from_mapping(self.diagnostics)
        diagnostics = typed if typed is not None else types.MappingProxyType(dict(self.diagnostics))
        object.__setattr__(self, "diagnostics", diagnostics)
        object.__setattr__(self, "marker_labels", tuple(str(v) for v in self.marker_labels))
        object.__setattr__(self, "nonrigid_markers", tuple(str(v) for v in self.nonrigid_markers))
        names = tuple(str(v) for v in self.segment_names)
        if names and len(names) != self.n_segments:
            raise InputError(f"segment_names has {len(names)} names for {self.n_segments} segments")
        object.__setattr__(self, "segment_names", names)

    @property
    def n_joints(self) -> int:
        return int(self.edges.shape[0])

    @property
    def n_markers(self) -> int:
        return len(self.marker_labels)

    def names(self) -> tuple[str, ...]:
        """(S,) segment names: :attr:`segment_names`, else readable names from the markers'
        labels (:func:`jaxskel.segment.names_from_markers`)."""
        if self.segment_names:
            return self.segment_names
        from ..segment import names_from_markers

        return tuple(names_from_markers(self.marker_labels, self.marker_segment, self.n_segments))

    @property
    def parent(self) -> np.ndarray:
        """(S,) parent segment of each segment, -1 for the root."""
        parent = np.full(self.n_segments, -1)
        parent[self.edges[:, 1]] = self.edges[:, 0]
        return parent

    @float64_scope
    def ik_model(self, n_markers: int | None = None, dtype: Any = np.float64) -> IKModel:
        """The arrays :func:`jaxskel.skeleton._ik.solve_frame` needs, markers padded to ``n_markers``."""
        return ik_model(
            self.edges, self.joint_offsets, self.marker_offsets, self.marker_segment,
            n_markers=n_markers, dtype=dtype,
        )

    def __repr__(self) -> str:
        return (
            f"Skeleton({self.n_segments} segments, {self.n_joints} joints, {self.n_markers} markers, "
            f"root={self.root}, residual {1e3 * self.diagnostics.get('residual_rms', np.nan):.2f} mm, "
            f"{len(self.nonrigid_markers)} non-rigid markers)"
        )


def longest_bones(bone_segment: np.ndarray, bone_lengths: np.ndarray, n_segments: int) -> np.ndarray:
    """(S,) each segment's longest bone (:attr:`Skeleton.segment_lengths`; NaN without one)."""
    out = np.full(n_segments, np.nan)
    for s, length in zip(np.asarray(bone_segment).tolist(), np.asarray(bone_lengths).tolist()):
        out[s] = np.nanmax([out[s], length])
    return out


# ----------------------------------------------------------------- validation
def validate_tree(edges: np.ndarray, n_segments: int, root: int | None) -> tuple[np.ndarray, int]:
    """Check a parent->child edge list is a tree over ``n_segments``; re-root it if asked.

    Returns ``(edges, root)`` with every edge pointing away from ``root``; rows keep their
    order (row j stays joint j, its direction may flip).
    """
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer):
        raise InputError(f"edges must be an integer array of shape (J, 2); got {edges.shape} {edges.dtype}")
    if edges.shape[0] != n_segments - 1:
        raise InputError(
            f"a tree over {n_segments} segments has {n_segments - 1} joints, but edges has "
            f"{edges.shape[0]} rows; pass the topology's edges (one row per joint)"
        )
    if edges.size and (edges.min() < 0 or edges.max() >= n_segments):
        raise InputError(f"edges refer to segments outside 0..{n_segments - 1}")
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n_segments)]
    for j, (a, b) in enumerate(edges.tolist()):
        adj[a].append((b, j))
        adj[b].append((a, j))
    if root is None:
        children = set(edges[:, 1].tolist())
        roots = [s for s in range(n_segments) if s not in children]
        if len(roots) != 1:
            raise InputError("edges do not form a rooted tree (every segment but one must be a child); pass root=")
        root = roots[0]
    root = int(root)
    if not 0 <= root < n_segments:
        raise InputError(f"root {root} is not a segment index (0..{n_segments - 1})")
    directed = edges.copy()
    seen = {root}
    stack = [root]
    while stack:
        u = stack.pop()
        for v, j in adj[u]:
            if v in seen:
                continue
            seen.add(v)
            directed[j] = (u, v)
            stack.append(v)
    if len(seen) != n_segments:
        raise InputError("edges do not connect all segments into one tree")
    return directed, root


def _as_arrays(trial: Trial | tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, tuple[str, ...] | None]:
    if isinstance(trial, Trial):
        x, mask = trial.to_arrays()
        return x, mask, trial.labels
    try:
        x, mask = trial
    except (TypeError, ValueError):
        raise InputError("pass a Trial or a tuple (x (F, M, 3), mask (F, M))") from None
    x = np.asarray(x, dtype=float)
    mask = np.asarray(mask, dtype=bool)
    if x.ndim != 3 or x.shape[-1] != 3 or mask.shape != x.shape[:2]:
        raise InputError(f"x must be (F, M, 3) and mask (F, M); got {x.shape} and {mask.shape}")
    mask = mask & np.isfinite(x).all(axis=-1)
    return np.where(mask[..., None], x, 0.0), mask, None


def _nearest_usable(usable: np.ndarray, frame: int) -> int:
    """The usable frame nearest ``frame`` (``usable`` has at least one)."""
    ok = np.flatnonzero(usable)
    return int(ok[np.argmin(np.abs(ok - frame))])


def _place_hinges(
    sliding: Sequence[bool] | np.ndarray | None,
    edges: np.ndarray,
    members: list[np.ndarray],
    seg_joints: list[np.ndarray],
    ref: np.ndarray,
    rot: np.ndarray,
    gpa_rms: np.ndarray,
    usable: np.ndarray,
    alignable: np.ndarray,
    js: np.ndarray,
    jm: np.ndarray,
    landmark_local: np.ndarray,
    landmark_joint: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Move sliding joints along their axes (:mod:`jaxskel.skeleton._hinge_centres`), in place.

    ``gpa_rms`` (S, P): each Procrustes point's scatter about its mean (neighbour weights).
    Updates the Procrustes mean clouds ``ref`` (both segments' copies of the joint)
    and the per-frame joint centres ``js`` the refinement is pinned to: frame f moves
    along the axis seen in that frame (the parent's pose, else the child's, else the
    nearest frame's). Returns the shifts (J,), the parent-frame axes (J, 3; NaN for
    joints not moved) and each joint's weight as a neighbour (J,; inverse variance of
    its centre, for :func:`_replace_hinges`) and the pair of landmarks that straddles
    each joint (J, 2: ``n_used + k`` for landmark k of
    ``landmark_local`` (S, L, 3, each landmark in each segment's Procrustes frame, NaN
    where unknown; ``landmark_joint`` (L,) the joint each is nearest); -1 where none does:
    the limb plane placed it). A joint moves only if
    it turns as a hinge (``MAX_OFF_AXIS``) and both segments were posed by Procrustes in at
    least 3 common frames.
    """
    n_joints = edges.shape[0]
    shift = np.zeros(n_joints)
    axis_parent = np.full((n_joints, 3), np.nan)
    if sliding is None:
        return shift, axis_parent, np.ones(n_joints), np.full((n_joints, 2), -1)
    sliding = np.asarray(sliding, dtype=bool)
    if sliding.shape != (n_joints,):
        raise InputError(f"sliding_joints must be {n_joints} booleans (one per joint); got shape {sliding.shape}")

    def slot(s: int, j: int) -> int:
        return len(members[s]) + int(np.flatnonzero(seg_joints[s] == j)[0])

    points = np.stack([[ref[edges[j, i], slot(edges[j, i], j)] for i in (0, 1)] for j in range(n_joints)])
    axes = np.zeros((n_joints, 2, 3))
    movable = np.zeros(n_joints, bool)
    for j in np.flatnonzero(sliding):
        p, c = int(edges[j, 0]), int(edges[j, 1])
        both = usable[:, p] & usable[:, c]
        if alignable[p] and alignable[c] and both.sum() >= 3 and np.isfinite(points[j]).all():
            a_p, a_c, off_axis = hinge_axes(rot[:, p], rot[:, c], both.astype(float))
            axes[j] = a_p, a_c
            movable[j] = off_axis < MAX_OFF_AXIS
    points = np.nan_to_num(points)
    # Landmarks (markers on no segment: a static trial's medial markers) that straddle a
    # hinge place it midway between them; it is then a fixed neighbour of the others'
    # limb-plane placement. The markers of the fit are not candidates: on a moving limb an
    # oblique axis passes pairs of surface markers (two midfoot markers for an ankle).
    straddle = np.full((n_joints, 2), -1)
    placed = np.zeros(n_joints)
    n_used = sum(len(m) for m in members)
    for j in np.flatnonzero(movable):
        if axis_along_a_bone(edges, j, points, axes):
            continue
        ids, along, off = [], [], []
        # a landmark nearer this joint than any other, once, from the parent's frame (else the child's)
        for k in np.flatnonzero(landmark_joint == j):
            for side in (0, 1):
                here = landmark_local[int(edges[j, side]), k]
                if np.isfinite(here).all():
                    t, r = axial_coordinates(here[None], points[j, side], axes[j, side])
                    ids.append(n_used + k)
                    along.append(float(t[0]))
                    off.append(float(r[0]))
                    break
        bone = longest_bone(edges, j, points)
        found = straddling_pair(np.asarray(along), np.asarray(off), bone) if bone > 0 else None
        if found is not None:
            straddle[j] = ids[found[0]], ids[found[1]]
            placed[j] = found[2]
            points[j, 0] += placed[j] * axes[j, 0]
            points[j, 1] += placed[j] * axes[j, 1]
    # Neighbours weighted by how steadily their centre sits on its segments (Procrustes
    # scatter, floor 1 mm): a wandering wrist or ankle centre moves the elbow or knee less.
    scatter = np.array([np.mean([gpa_rms[edges[j, i], slot(edges[j, i], j)] for i in (0, 1)]) for j in range(n_joints)])
    weights = 1.0 / (np.nan_to_num(scatter, nan=1.0) ** 2 + 1e-6)
    shift = hinge_shifts(edges, movable & (straddle[:, 0] < 0), points, axes, weights) + placed
    frames = np.arange(js.shape[0])
    for j in np.flatnonzero(shift):
        p, c = int(edges[j, 0]), int(edges[j, 1])
        ref[p, slot(p, j)] += shift[j] * axes[j, 0]
        ref[c, slot(c, j)] += shift[j] * axes[j, 1]
        world = np.where(
            usable[:, p, None], axes[j, 0] @ rot[:, p], np.where(usable[:, c, None], axes[j, 1] @ rot[:, c], np.nan)
        )
        seen = np.isfinite(world[:, 0])
        world = np.stack([np.interp(frames, frames[seen], world[seen, d]) for d in range(3)], axis=1)
        world /= np.linalg.norm(world, axis=1, keepdims=True)
        js[:, j] = np.where(jm[:, j, None], js[:, j] + shift[j] * world, js[:, j])
        axis_parent[j] = axes[j, 0]
    return shift, axis_parent, weights, straddle


def _landmarks_local(
    landmarks: Trial | None,
    padded: np.ndarray,
    real: np.ndarray,
    rot: np.ndarray,
    trans: np.ndarray,
    usable: np.ndarray,
    n_frames: int,
    ref: np.ndarray,
    edges: np.ndarray,
    members: list[np.ndarray],
    seg_joints: list[np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Each landmark in each segment's Procrustes frame (S, L, 3: ``R x + t``, the median
    over the fitted frames that show both; NaN where none does), and the joint each is
    nearest to (L,; the median over frames of its distance to each joint centre, placed in
    the world by the joint's parent; -1 where none is known)."""
    n_seg = usable.shape[1]
    if landmarks is None or landmarks.n_markers == 0:
        return np.zeros((n_seg, 0, 3)), np.zeros(0, int)
    if landmarks.n_frames != n_frames:
        raise InputError(f"landmarks must have the trial's {n_frames} frames, got {landmarks.n_frames}")
    x = np.asarray(landmarks.positions, dtype=float)[padded]  # (F, L, 3)
    seen = np.isfinite(x).all(axis=-1) & real[:, None]
    local = np.einsum("fsij,flj->fsli", rot, np.nan_to_num(x)) + trans[:, :, None, :]
    ok = seen[:, None, :] & usable[:, :, None]  # (F, S, L)
    n_joints = edges.shape[0]
    distance = np.full((n_joints, x.shape[1]), np.inf)
    for j in range(n_joints):
        p = int(edges[j, 0])
        point = ref[p, len(members[p]) + int(np.flatnonzero(seg_joints[p] == j)[0])]
        world = np.einsum("fji,fj->fi", rot[:, p], point[None] - trans[:, p])  # R^T (q - t)
        d = np.linalg.norm(x - world[:, None], axis=-1)
        d = np.where(seen & usable[:, p, None], d, np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            distance[j] = np.nan_to_num(np.nanmedian(d, axis=0), nan=np.inf)
    nearest = np.where(np.isfinite(distance).any(axis=0), np.argmin(distance, axis=0), -1) if n_joints else \
        np.full(x.shape[1], -1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a landmark a segment never shares a frame with
        return np.nanmedian(np.where(ok[..., None], local, np.nan), axis=0), nearest


def _turns_as_hinge(
    edges: np.ndarray, rot: np.ndarray, keep: np.ndarray, joints: np.ndarray, limit: float = MAX_OFF_AXIS
) -> np.ndarray:
    """(J,) whether each joint in ``joints`` turns as a hinge (off-axis share below
    ``limit``, :func:`hinge_axes`) on the refined poses ``rot`` (F, S, 3, 3; segment ->
    world) of the ``keep`` frames."""
    to_local = np.swapaxes(rot[keep], -1, -2)  # world -> segment
    out = np.zeros(edges.shape[0], bool)
    for j in np.flatnonzero(joints):
        p, c = int(edges[j, 0]), int(edges[j, 1])
        out[j] = hinge_axes(to_local[:, p], to_local[:, c], np.ones(int(keep.sum())))[2] < limit
    return out


def _replace_hinges(
    edges: np.ndarray,
    useg: np.ndarray,
    m_th: np.ndarray,
    j_th: np.ndarray,
    rot: np.ndarray,
    keep: np.ndarray,
    weights: np.ndarray,
    axis_local: np.ndarray,
    straddle: np.ndarray,
) -> np.ndarray:
    """Put the moved hinges back into their limb plane on the refined skeleton, in place;
    those placed between straddling landmarks (``straddle``, J x 2, -1 for none) stay.

    Frames: a segment's origin is its proximal joint, so joint j sits at ``j_th[j]`` in
    its parent and at 0 in its child. Moving it by ``s a`` moves ``j_th[j]`` by ``s a_p``
    and everything expressed in the child frame (its markers, its child joints) by
    ``-s a_c``. ``axis_local`` (J, 3): the axes of the joints moved before the refinement
    (NaN for the others), in the parent's local frame; only those move, and their axes
    are replaced by the refined ones (same sign). Returns the extra shifts (J,).
    """
    n_joints = edges.shape[0]
    moved = np.isfinite(axis_local[:, 0])
    axes = np.zeros((n_joints, 2, 3))
    to_local = np.swapaxes(rot[keep], -1, -2)  # world -> segment
    ok = moved.copy()
    for j in np.flatnonzero(moved):
        p, c = int(edges[j, 0]), int(edges[j, 1])
        a_p, a_c, off_axis = hinge_axes(to_local[:, p], to_local[:, c], np.ones(int(keep.sum())))
        axes[j] = (a_p, a_c) if a_p @ axis_local[j] >= 0 else (-a_p, -a_c)
        ok[j] = off_axis < MAX_OFF_AXIS
        if ok[j]:
            axis_local[j] = axes[j, 0]

    def move(j: int, amount: float) -> None:
        c = int(edges[j, 1])
        j_th[j] += amount * axes[j, 0]
        m_th[useg == c] -= amount * axes[j, 1]
        j_th[edges[:, 0] == c] -= amount * axes[j, 1]

    points = np.zeros((n_joints, 2, 3))
    points[:, 0] = j_th
    free = ok & (straddle[:, 0] < 0)  # placed by landmarks, which the refinement does not carry: kept
    plane = hinge_shifts(edges, free, points, axes, weights)
    for j in np.flatnonzero(free):
        move(j, plane[j])
    return plane


# ------------------------------------------------------------------ refinement
def _refine(
    marker_theta: np.ndarray,
    joint_theta: np.ndarray,
    obs: np.ndarray,
    present: np.ndarray,
    obs_segment: np.ndarray,
    obs_base_weight: np.ndarray,
    edges: np.ndarray,
    coef: np.ndarray,
    unknown_segment: np.ndarray,
    start: dict[str, np.ndarray] | None,
    prior_weight: np.ndarray,
    xtol: float,
    refine: bool,
    *,
    max_sweeps: int,
    max_steps: int,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], list[float], list[float], bool]:
    """Alternate IK sweeps and exact offset updates (module docstring), on the device
    (:func:`jaxskel.skeleton._rigid_sweeps.alternate`).

    A sweep is the batched IK of :mod:`jaxskel.skeleton._ik_batch` over all fitting frames, the
    joint centres entering as extra "markers" (weight ``joint_weight^2``) at the proximal
    end of the joint's child, where the parent's joint offset puts it; it starts from
    ``start`` (the previous sweep's poses, the prior their relative rotations) or, for
    ``None``, from the batched Horn alignment. With ``refine`` each sweep is followed by
    the offset update ``theta* = G(theta)`` until it moves no offset by more than
    ``xtol`` (metres) without raising the cost: a fixed point of the alternation, i.e. a
    stationary point of the joint problem. A last sweep then fits the poses to the final
    offsets. The updates are Anderson-accelerated (the last ``_ANDERSON_MEMORY`` + 1
    pairs), restarted whenever the cost rose. Returns the offsets, the last sweep's
    solution, the cost history (mean weighted squared residual after each update), the
    largest offset move of each update (m) and whether ``xtol`` was met.
    """
    n_m = marker_theta.shape[0]
    parent = kinematic_chain(np.asarray(edges)).parent
    # The IK's shapes (solver_shape): the refinement and the final IK share one layout.
    slots, columns = solver_shape(obs_segment[:n_m], edges, n_m)
    pad = ((0, 0), (0, columns - obs.shape[1]))
    # The layout of the offsets (slots, weights, tree): a joint centre is observed at its
    # child's proximal end (offset 0), one slot on the child.
    model = batch_model(
        edges, np.stack([joint_theta, np.zeros_like(joint_theta)], axis=1),
        np.concatenate([marker_theta, np.zeros_like(joint_theta)]), obs_segment, obs_base_weight, slots=slots,
    )
    pairs, pair_index = offset_pairs(coef, unknown_segment)
    problem = SweepProblem(
        model=model, obs_in=to_device(np.pad(obs, (*pad, (0, 0)))), observed=to_device(np.pad(present > 0, pad)),
        prior_weight=to_device(prior_weight), parent=to_device(np.asarray(parent), np.int32),
        max_steps=to_device(max_steps, np.int32), xtol=to_device(float(xtol)), obs=to_device(obs),
        weight=to_device(present * obs_base_weight), coef=to_device(coef),
        unknown_segment=to_device(unknown_segment, np.int32), pairs=to_device(pairs, np.int32),
        pair_index=to_device(pair_index, np.int32),
    )
    n_frames, n_seg = obs.shape[0], edges.shape[0] + 1
    if start is None:
        t0, q0 = np.zeros((n_frames, 3)), np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), (n_frames, n_seg, 4))
    else:
        t0, q0 = start["root_position"], start["rotations"]
    out = _program_cache.call(
        alternate, problem, to_device(np.concatenate([marker_theta, joint_theta])), to_device(t0), to_device(q0),
        to_device(start is None, bool), to_device(bool(refine), bool), max_sweeps=int(max_sweeps),
        memory=_ANDERSON_MEMORY,
    )
    n_sweeps = int(out["sweeps"])
    theta = np.asarray(out["theta"])
    sol = {key: np.asarray(out[key]) for key in ("root_position", "rotations", "num_steps", "done", "rms")}
    history = np.asarray(out["cost_history"])[:n_sweeps].tolist()
    steps = np.asarray(out["offset_steps"])[:n_sweeps].tolist()
    return theta[:n_m], theta[n_m:], sol, history, steps, bool(out["met"])


# ------------------------------------------------------------------- fit_rigid
# The fit in phases, each a small function between typed records:
#   _validate_inputs -> [per attempt: _choose_frames -> _procrustes -> _hinges ->
#   _starting_offsets -> _refinement -> _residuals -> _rebase -> _bones -> _assemble].
# An attempt may instead say what to leave out (LeftOut); fit_rigid then fits again without it.
def _unposed_segments(marker_segment: np.ndarray, edges: np.ndarray, n_segments: int) -> np.ndarray:
    """Segments with no marker and a single joint: nothing fixes their pose."""
    markers = np.bincount(marker_segment[marker_segment >= 0], minlength=n_segments)
    joints = np.bincount(np.asarray(edges).reshape(-1), minlength=n_segments)
    return np.flatnonzero((markers == 0) & (joints < 2))


@dataclasses.dataclass(frozen=True)
class _Inputs:
    """fit_rigid's data, checked: markers ``x`` (F, M, 3) where ``mask`` (F, M), their
    segments (M,; -1 unused), the tree (J, 2) directed away from ``root``, the joint
    centres (F, J, 3; NaN where undefined) and the markers' labels (M,)."""

    x: np.ndarray
    mask: np.ndarray
    marker_segment: np.ndarray
    edges: np.ndarray
    root: int
    joint_positions: np.ndarray
    labels: tuple[str, ...]

    @property
    def n_segments(self) -> int:
        return int(self.edges.shape[0]) + 1


@dataclasses.dataclass(frozen=True)
class LeftOut:
    """What the fit leaves out, as its attempts find it: ``markers`` (indices into the
    trial's markers, in the order found) that no frame shows with the rest of their
    segment, and ``hinges`` (sorted joint indices) whose slide the refined poses rejected."""

    markers: tuple[int, ...] = ()
    hinges: tuple[int, ...] = ()

    def __or__(self, other: LeftOut) -> LeftOut:
        return LeftOut(self.markers + other.markers, tuple(sorted(set(self.hinges) | set(other.hinges))))

    def marker_segment(self, marker_segment: np.ndarray) -> np.ndarray:
        """``marker_segment`` with the markers left out set to -1 (a copy)."""
        kept = np.array(marker_segment, copy=True)
        kept[list(self.markers)] = -1
        return kept

    def sliding(self, sliding: Sequence[bool] | np.ndarray | None) -> Sequence[bool] | np.ndarray | None:
        """``sliding_joints`` without the hinges left unmoved."""
        if not self.hinges:
            return sliding
        rejected = np.zeros(np.asarray(sliding).shape[0], bool)
        rejected[list(self.hinges)] = True
        return np.asarray(sliding, dtype=bool) & ~rejected


def _validate_inputs(
    trial: Trial | tuple[np.ndarray, np.ndarray], marker_segment: Sequence[int] | np.ndarray, edges: np.ndarray,
    joint_positions: np.ndarray, root: int | None, labels: Sequence[str] | None,
) -> _Inputs:
    """Phase 0: check fit_rigid's data (its docstring); raise :class:`InputError` or
    :class:`DegenerateMotionError` (fewer than 3 frames)."""
    x, mask, trial_labels = _as_arrays(trial)
    n_frames, n_markers = mask.shape
    seg = np.asarray(marker_segment)
    if seg.shape != (n_markers,) or not np.issubdtype(seg.dtype, np.integer):
        raise InputError(f"marker_segment must be {n_markers} integers (one per marker, -1 = unused); got shape {seg.shape}")
    edges_in = np.asarray(edges)
    n_seg = int(edges_in.shape[0]) + 1 if edges_in.ndim == 2 else 0
    edges, root = validate_tree(edges_in, n_seg, root)
    if seg.max(initial=-1) >= n_seg or seg.min(initial=0) < -1:
        raise InputError(f"marker_segment entries must be -1 or segment indices 0..{n_seg - 1}")
    jp = np.asarray(joint_positions, dtype=float)
    if jp.shape != (n_frames, n_seg - 1, 3):
        raise InputError(
            f"joint_positions must have shape (frames, joints, 3) = {(n_frames, n_seg - 1, 3)}; got {jp.shape}"
        )
    if labels is not None:
        labels = tuple(str(v) for v in labels)
    else:
        labels = trial_labels or tuple(f"M{i}" for i in range(n_markers))
    if len(labels) != n_markers:
        raise InputError(f"{len(labels)} labels for {n_markers} markers")
    if n_frames < 3:
        raise DegenerateMotionError("fit_rigid needs a motion (at least 3 frames); record more frames")
    return _Inputs(x=x, mask=mask, marker_segment=seg, edges=edges, root=root, joint_positions=jp, labels=labels)


@dataclasses.dataclass(frozen=True)
class _Frames:
    """The fitting frames and their data. ``frames`` (n,): the trial frames fitted;
    ``padded`` (F,): them padded to a bucket of frames (repeats of the last), ``real``
    (F,) false for the padding. ``used`` (U,): the trial's markers on a segment, ``useg``
    (U,) their segments. ``xs``, ``ms`` (F, U, 3 / F, U): their positions and presence
    (absent in the padding); ``js``, ``jm`` (F, J, 3 / F, J): the joint centres (0 where
    absent) and their presence."""

    frames: np.ndarray
    padded: np.ndarray
    real: np.ndarray
    used: np.ndarray
    useg: np.ndarray
    xs: np.ndarray
    ms: np.ndarray
    js: np.ndarray
    jm: np.ndarray


def _choose_frames(inputs: _Inputs, seg: np.ndarray, max_frames: int) -> _Frames:
    """Phase 1: at most ``max_frames`` frames, evenly spaced among those showing some
    marker, padded to a bucket of frames (:func:`bucket_size`) so that trials share
    compiled shapes. Raises :class:`DegenerateMotionError` for a segment nothing poses
    or fewer than 3 frames with markers."""
    n_seg, edges = inputs.n_segments, inputs.edges
    used = np.flatnonzero(seg >= 0)
    useg = seg[used]
    joint_ok = np.isfinite(inputs.joint_positions).all(axis=-1)
    unposed = _unposed_segments(seg, edges, n_seg)
    if unposed.size:
        raise DegenerateMotionError(
            f"segment {int(unposed[0])} has no markers and a single joint, so nothing fixes its pose; "
            "merge it into its neighbour or add markers"
        )
    candidates = np.flatnonzero(inputs.mask[:, used].any(axis=1))
    if candidates.size < 3:
        raise DegenerateMotionError("fewer than 3 frames show any marker; nothing to fit")
    frames = candidates[np.unique(np.linspace(0, candidates.size - 1, min(max_frames, candidates.size)).astype(int))]
    n_fit = frames.size
    padded = np.concatenate([frames, np.full(bucket_size(n_fit) - n_fit, frames[-1])])
    real = np.arange(padded.size) < n_fit
    jp = inputs.joint_positions
    return _Frames(
        frames=frames, padded=padded, real=real, used=used, useg=useg,
        xs=inputs.x[padded][:, used], ms=inputs.mask[padded][:, used] & real[:, None],
        js=np.where(joint_ok[padded][..., None], jp[padded], 0.0), jm=joint_ok[padded] & real[:, None],
    )


@dataclasses.dataclass(frozen=True)
class _Procrustes:
    """Per-segment Procrustes. Segment s's points are its markers ``members[s]`` (indices
    into ``used``), then its joints ``seg_joints[s]``, padded to ``width``: ``pts`` (F, S,
    P, 3), ``pres`` (F, S, P). ``usable`` (F, S): the frames aligned; ``covered`` (S, P):
    the points seen in one. ``ref`` (S, P, 3) the mean clouds, ``rot``, ``trans`` (F, S,
    3, 3 / F, S, 3) each frame's alignment (world -> segment: ``R x + t``), ``rms`` (S, P)
    each point's scatter; ``alignable`` (S,): posed by Procrustes. ``attachment_weight``,
    ``attachment_scatter`` (J,): as reported (:class:`RigidDiagnostics`)."""

    members: list[np.ndarray]
    seg_joints: list[np.ndarray]
    width: int
    pts: np.ndarray
    pres: np.ndarray
    usable: np.ndarray
    covered: np.ndarray
    ref: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    rms: np.ndarray
    alignable: np.ndarray
    attachment_weight: np.ndarray
    attachment_scatter: np.ndarray


def _procrustes(fr: _Frames, edges: np.ndarray, n_seg: int) -> _Procrustes:
    """Phase 2: generalised Procrustes per segment (module docstring, step 1), the joints
    of one-marker attachments weighted by how still they sit in their host."""
    n_used, n_joints = fr.used.size, n_seg - 1
    useg, xs, ms, js, jm = fr.useg, fr.xs, fr.ms, fr.js, fr.jm
    members = [np.flatnonzero(useg == s) for s in range(n_seg)]
    seg_joints = [np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s)) for s in range(n_seg)]
    width = max(len(m) + len(j) for m, j in zip(members, seg_joints))
    pidx = np.full((n_seg, width), -1)
    for s in range(n_seg):
        ids = np.concatenate([members[s], n_used + seg_joints[s]])
        pidx[s, : ids.size] = ids
    allp = np.concatenate([xs, js], axis=1)
    allm = np.concatenate([ms, jm], axis=1)
    pts = allp[:, np.maximum(pidx, 0)]  # (F, S, P, 3)
    pres = allm[:, np.maximum(pidx, 0)] & (pidx >= 0)[None]
    all_markers = np.stack([ms[:, m].all(axis=1) for m in members], axis=1)  # (F, S)
    usable = all_markers & (pres.sum(axis=-1) >= 3)
    # The paper aligns only frames showing all of a segment's markers. A segment with a
    # marker seldom seen with the others (a label present for 3 s of a 19 s take) has
    # few or no such frames: it uses every frame with three points, the masked
    # Procrustes placing each marker from the frames that show it.
    seldom = ((pres & usable[..., None]).sum(axis=0) < 3) & (pidx >= 0)  # (S, P)
    partial = seldom.any(axis=1)
    usable[:, partial] = pres[:, partial].sum(axis=-1) >= 3
    weights = (pres & usable[..., None]).astype(float)
    first = np.argmax(weights.sum(axis=-1), axis=0)  # per segment: best-covered frame
    ref0 = pts[first, np.arange(n_seg)]
    refw0 = weights[first, np.arange(n_seg)]
    hung = attachment_points(edges, members, seg_joints, width)
    trust = np.ones((n_seg, width))
    if hung.any():
        # the joints of one-marker attachments steer their host by how still they sit in it
        _, own_rot, own_t, own_rms = (
            np.array(a) for a in _program_cache.call(procrustes, pts, weights * ~hung[None], ref0, refw0)
        )
        trust = attachment_weights(hung, own_rms, scatter_about_mean(pts, weights, own_rot, own_t)[1])
    ref, gpa_rot, gpa_t, gpa_rms = (
        np.array(a) for a in _program_cache.call(procrustes, pts, weights * trust[None], ref0, refw0)
    )
    if hung.any():
        # a point of small weight: its mean and scatter in the final pose, weighed like a marker's
        mean, spread = scatter_about_mean(pts, weights, gpa_rot, gpa_t)
        ref = np.where(hung[..., None], mean, ref)
        gpa_rms = np.where(hung, np.nan_to_num(spread), gpa_rms)
    # per joint, as reported: its weight in its host's alignment and its scatter there (NaN: not an attachment's)
    hung_weight, hung_scatter = np.ones(n_joints), np.full(n_joints, np.nan)
    for s, k in zip(*np.nonzero(hung)):
        j = int(seg_joints[s][k - len(members[s])])
        hung_weight[j], hung_scatter[j] = trust[s, k], gpa_rms[s, k]
    covered = weights.sum(axis=0) > 0  # (S, P)
    alignable = np.zeros(n_seg, bool)
    for s in range(n_seg):
        cloud = ref[s][covered[s]]
        if usable[:, s].sum() >= 3 and cloud.shape[0] >= 3:
            sv = np.linalg.svd(cloud - cloud.mean(axis=0), compute_uv=False)
            alignable[s] = sv[1] > 1e-3 * max(sv[0], 1e-12)
    return _Procrustes(
        members=members, seg_joints=seg_joints, width=width, pts=pts, pres=pres, usable=usable, covered=covered,
        ref=ref, rot=gpa_rot, trans=gpa_t, rms=gpa_rms, alignable=alignable, attachment_weight=hung_weight,
        attachment_scatter=hung_scatter,
    )


@dataclasses.dataclass(frozen=True)
class _Hinges:
    """The sliding joints' placement (:func:`_place_hinges`): ``shift`` (J,), ``axis``
    (J, 3; parent Procrustes frame, NaN for joints not moved), ``weights`` (J,; as
    neighbours) and ``straddle`` (J, 2; the landmarks that placed each, -1 for none)."""

    shift: np.ndarray
    axis: np.ndarray
    weights: np.ndarray
    straddle: np.ndarray


def _hinges(
    fr: _Frames, gp: _Procrustes, edges: np.ndarray, sliding: Sequence[bool] | np.ndarray | None,
    landmarks: Trial | None, n_frames: int,
) -> _Hinges:
    """Phase 3: move the sliding joints along their axes (:func:`_place_hinges`): this
    updates ``gp.ref`` and ``fr.js`` in place."""
    landmark_local, landmark_joint = _landmarks_local(
        landmarks, fr.padded, fr.real, gp.rot, gp.trans, gp.usable, n_frames, gp.ref, edges, gp.members,
        gp.seg_joints,
    )
    shift, axis, weights, straddle = _place_hinges(
        sliding, edges, gp.members, gp.seg_joints, gp.ref, gp.rot, gp.rms, gp.usable, gp.alignable, fr.js, fr.jm,
        landmark_local, landmark_joint,
    )
    return _Hinges(shift=shift, axis=axis, weights=weights, straddle=straddle)


@dataclasses.dataclass(frozen=True)
class _Start:
    """Starting offsets of the refinement: ``marker_theta`` (U, 3), ``joint_theta`` (J, 3),
    in local frames world-aligned at a common frame; ``hinge_axis_local`` (J, 3) the moved
    joints' axes in those parent frames (NaN for the others)."""

    marker_theta: np.ndarray
    joint_theta: np.ndarray
    hinge_axis_local: np.ndarray


def _starting_offsets(
    fr: _Frames, gp: _Procrustes, hinges: _Hinges, inputs: _Inputs, seg: np.ndarray
) -> _Start | LeftOut:
    """Phase 4: local frames (world-aligned at a common frame, or the segment's nearest
    usable one) and the offsets of markers and joints in them. Markers nothing places
    (never seen with the points that fix their segment) are returned as a
    :class:`LeftOut` when their segments stay posable without them; otherwise a segment
    that cannot be placed raises :class:`DegenerateMotionError`."""
    edges, root, n_seg, labels = inputs.edges, inputs.root, inputs.n_segments, inputs.labels
    members, seg_joints, usable, gpa_rot = gp.members, gp.seg_joints, gp.usable, gp.rot
    n_used, n_joints = fr.used.size, n_seg - 1
    common = int(np.argmax(usable.sum(axis=1)))
    hinge_axis_local = np.full((n_joints, 3), np.nan)
    for j in np.flatnonzero(np.isfinite(hinges.axis[:, 0])):
        p = int(edges[j, 0])
        hinge_axis_local[j] = hinges.axis[j] @ gpa_rot[_nearest_usable(usable[:, p], common), p]
    local = np.full((n_seg, gp.width, 3), np.nan)
    for s in range(n_seg):
        n_pts = len(members[s]) + len(seg_joints[s])
        if gp.alignable[s]:
            f = _nearest_usable(usable[:, s], common)
            cloud = gp.ref[s, :n_pts] @ gpa_rot[f, s]  # rows: R^T p (world-aligned axes)
            cloud[~gp.covered[s, :n_pts]] = np.nan
        else:
            seen = gp.pres[:, s, :n_pts]
            score = seen.sum(axis=1) - 1e-6 * np.abs(np.arange(seen.shape[0]) - common)
            f = int(np.argmax(score))
            cloud = np.where(seen[f][:, None], gp.pts[f, s, :n_pts], np.nan)
        local[s, :n_pts] = cloud
    proximal = np.full(n_seg, -1)
    proximal[edges[:, 1]] = np.arange(n_joints)

    def point_of(s: int, joint: int) -> np.ndarray:
        k = len(members[s]) + int(np.flatnonzero(seg_joints[s] == joint)[0])
        return local[s, k]

    origin = np.zeros((n_seg, 3))
    for s in range(n_seg):
        if s == root:
            pts_s = local[s, : len(members[s])] if len(members[s]) else local[s, len(members[s]) :]
            origin[s] = np.nanmean(pts_s, axis=0)
        else:
            origin[s] = point_of(s, proximal[s])
    marker_theta = np.zeros((n_used, 3))
    for s in range(n_seg):
        marker_theta[members[s]] = local[s, : len(members[s])] - origin[s]
    joint_theta = np.stack([point_of(int(edges[j, 0]), j) - origin[edges[j, 0]] for j in range(n_joints)])
    bad = [s for s in range(n_seg) if not np.isfinite(origin[s]).all()]
    bad += [int(edges[j, 1]) for j in np.flatnonzero(~np.isfinite(joint_theta).all(axis=1))]
    unplaced = np.flatnonzero(~np.isfinite(marker_theta).all(axis=1))
    if unplaced.size and not bad:
        # Markers never seen in a frame with the points that fix their segment (a label
        # that takes over another's frames, a sync light clustered with a hand): nothing
        # places them on it. Leave them out of the skeleton, say so, and fit the rest.
        left = LeftOut(markers=tuple(int(m) for m in fr.used[unplaced]))
        if not _unposed_segments(left.marker_segment(seg), edges, n_seg).size:
            return left
    bad += [int(fr.useg[i]) for i in unplaced]
    if bad:
        def points(s: int) -> str:
            shown = [labels[fr.used[i]] for i in members[s]] + [f"joint {int(j)}" for j in seg_joints[s]]
            return f"segment {s} ({', '.join(shown)})"

        raise DegenerateMotionError(
            f"{'; '.join(points(s) for s in sorted(set(bad)))}: no frame shows enough of these points together "
            "(three of a segment's markers and joint centres, its proximal joint among them) to place the segment's "
            "offsets, so the rigid skeleton cannot be fitted. Joint centres exist only in frames that show both of "
            "their segments: give more frames in which these segments and their neighbours are seen together "
            "(or, calling fit_rigid yourself, check joint_positions for NaN)"
        )
    return _Start(marker_theta=marker_theta, joint_theta=joint_theta, hinge_axis_local=hinge_axis_local)


def _unplaced_warning(labels: tuple[str, ...], markers: Sequence[int], seg: np.ndarray) -> str:
    """The warning for markers left out by :func:`_starting_offsets`."""
    listed = ", ".join(f"{labels[m]} (segment {int(seg[m])})" for m in markers)
    return (
        f"markers {listed} are never seen in a frame together with the other markers and joints of their "
        "segment, so the rigid skeleton cannot place them: they are left out of the skeleton and the IK "
        "(skeleton.diagnostics['unplaced_markers']). A label that takes over another marker's frames, or "
        "a marker that is not on the body: relabel or remove it"
    )


@dataclasses.dataclass(frozen=True)
class _Refined:
    """The refinement's result: offsets ``marker_theta`` (U, 3), ``joint_theta`` (J, 3)
    (local frames of :class:`_Start`), the last sweep's solution ``sol`` (per frame:
    ``root_position``, ``rotations``, ``num_steps``, ``done``, ``rms``) and its rotations
    ``rot`` (F, S, 3, 3; segment -> world), the frames ``keep`` (F,), the sweeps' cost
    ``history`` and ``offset_steps``, whether ``xtol`` was met (``done``), the hinges'
    total ``hinge_shift`` (J,) and ``chain`` (S, J; :func:`kinematic_chain`)."""

    marker_theta: np.ndarray
    joint_theta: np.ndarray
    sol: dict[str, np.ndarray]
    rot: np.ndarray
    keep: np.ndarray
    history: list[float]
    offset_steps: list[float]
    done: bool
    hinge_shift: np.ndarray
    chain: np.ndarray


def _refinement(
    fr: _Frames, start: _Start, hinges: _Hinges, edges: np.ndarray, options: RigidOptions
) -> _Refined | LeftOut:
    """Phase 5: the global refinement (module docstring, step 2). A first pass without
    offset updates rejects the non-rigid frames (marker RMS above median + 5 MAD); the
    refinement then runs on the others. A moved hinge the refined poses show turning about
    more than one axis (``MAX_OFF_AXIS_REFINED``) is returned as a :class:`LeftOut`; the
    others are placed once more on the refined poses (``start.hinge_axis_local`` is
    updated in place, :func:`_replace_hinges`)."""
    n_used, n_joints, n_seg = fr.used.size, edges.shape[0], edges.shape[0] + 1
    useg, real = fr.useg, fr.real
    obs = np.concatenate([fr.xs, fr.js], axis=1)
    present = np.concatenate([fr.ms, fr.jm], axis=1).astype(float)
    obs_segment = np.concatenate([useg, edges[:, 1]]).astype(np.int32)  # joints: on the child
    base_weight = np.concatenate([np.ones(n_used), np.full(n_joints, float(options.joint_weight) ** 2)])
    chain_np = kinematic_chain(np.asarray(edges)).path
    coef = np.zeros((n_used + n_joints, n_used + n_joints))
    coef[np.arange(n_used), np.arange(n_used)] = 1.0
    coef[:n_used, n_used:] = chain_np[useg]
    coef[n_used:, n_used:] = chain_np[edges[:, 0]] + np.eye(n_joints)
    unknown_segment = np.concatenate([useg, edges[:, 0]]).astype(np.int32)

    prior_w = np.full((n_seg,), float(options.prior_weight))
    common_args = dict(
        obs_segment=obs_segment, obs_base_weight=base_weight, edges=np.asarray(edges), coef=coef,
        unknown_segment=unknown_segment, prior_weight=prior_w, xtol=options.xtol, max_steps=options.max_steps,
        max_sweeps=options.max_sweeps,
    )
    marker_theta, joint_theta, hinge_axis_local = start.marker_theta, start.joint_theta, start.hinge_axis_local
    # First pass without offset updates: per-frame residuals to reject non-rigid frames.
    _, _, first, _, _, _ = _refine(marker_theta, joint_theta, obs, present, start=None, refine=False, **common_args)
    rms = first["rms"]
    med = np.median(rms[real])
    mad = 1.4826 * np.median(np.abs(rms[real] - med))
    keep = real & (rms <= med + 5.0 * max(mad, 1e-4 * med))
    m_th, j_th, sol, history, offset_steps, done = _refine(
        marker_theta, joint_theta, obs, present * keep[:, None], start=first, refine=options.refine, **common_args
    )
    rot = quat_to_matrix_np(sol["rotations"])  # (F, S, 3, 3)
    hinge_shift = hinges.shift
    if options.refine and np.isfinite(hinge_axis_local[:, 0]).any():
        moved = np.isfinite(hinge_axis_local[:, 0])
        rejected = moved & ~_turns_as_hinge(edges, rot, keep, moved, MAX_OFF_AXIS_REFINED)
        if rejected.any():
            # The slide's axis came from the frames Procrustes poses; the refined poses of
            # all kept frames show the joint turning about more than one axis, so its
            # markers pin the centre and the slide is wrong (MAX_OFF_AXIS_REFINED): fit
            # again without it.
            return LeftOut(hinges=tuple(int(j) for j in np.flatnonzero(rejected)))
        # The refinement weighs the joint centres lightly, so a hinge may drift along its
        # axis again with the markers' soft tissue: place it once more on the final poses.
        m_th, j_th = np.array(m_th), np.array(j_th)
        again = _replace_hinges(edges, useg, m_th, j_th, rot, keep, hinges.weights, hinge_axis_local, hinges.straddle)
        if np.any(again):
            hinge_shift = hinge_shift + again
            _, _, sol, _, _, _ = _refine(
                m_th, j_th, obs, present * keep[:, None], start=sol, refine=False, **common_args
            )
            rot = quat_to_matrix_np(sol["rotations"])
    return _Refined(
        marker_theta=m_th, joint_theta=j_th, sol=sol, rot=rot, keep=keep, history=history,
        offset_steps=offset_steps, done=done, hinge_shift=hinge_shift, chain=chain_np,
    )


def _residuals(fr: _Frames, rf: _Refined, edges: np.ndarray) -> tuple[np.ndarray, float]:
    """Phase 6: per-marker residual RMS (U,; NaN where never seen) and the overall RMS
    over the kept frames, with the final offsets and poses."""
    rot = rf.rot
    # segment origins (forward kinematics, ik._poses, on the host): each joint sits at its
    # parent's offset and at its child's origin
    step = np.einsum("fjab,jb->fja", rot[:, edges[:, 0]], rf.joint_theta)
    trans = np.asarray(rf.sol["root_position"])[:, None, :] + np.einsum("sj,fja->fsa", rf.chain, step)
    pred = np.einsum("fmab,mb->fma", rot[:, fr.useg], rf.marker_theta) + trans[:, fr.useg]
    err2 = np.sum((pred - fr.xs) ** 2, axis=-1)
    w = fr.ms & rf.keep[:, None]
    marker_rms_used = np.sqrt(np.sum(err2 * w, axis=0) / np.maximum(w.sum(axis=0), 1))
    marker_rms_used[w.sum(axis=0) == 0] = np.nan
    residual_rms = float(np.sqrt(np.sum(err2 * w) / max(w.sum(), 1)))
    return marker_rms_used, residual_rms


@dataclasses.dataclass(frozen=True)
class _Rested:
    """Offsets re-based to the rest frame: ``marker_theta`` (U, 3), ``joint_theta`` (J, 3),
    ``rest`` (index into the padded frames) and ``r_rest`` (S, 3, 3) its rotations."""

    marker_theta: np.ndarray
    joint_theta: np.ndarray
    rest: int
    r_rest: np.ndarray


def _rebase(fr: _Frames, rf: _Refined, edges: np.ndarray, root: int) -> _Rested:
    """Phase 7: axes world-aligned at the rest frame (the first kept frame that shows the
    most markers), the root's origin at its markers' centroid (else its joints')."""
    useg = fr.useg
    kept = np.flatnonzero(rf.keep)
    rest_local = kept[np.argmax(fr.ms[kept].sum(axis=1))]
    r_rest = rf.rot[rest_local]
    m_th = np.einsum("mab,mb->ma", r_rest[useg], rf.marker_theta)
    j_th = np.einsum("jab,jb->ja", r_rest[edges[:, 0]], rf.joint_theta)
    root_markers = useg == root
    shift = m_th[root_markers].mean(axis=0) if root_markers.any() else j_th[edges[:, 0] == root].mean(axis=0)
    m_th[root_markers] -= shift
    j_th[edges[:, 0] == root] -= shift
    return _Rested(marker_theta=m_th, joint_theta=j_th, rest=rest_local, r_rest=r_rest)


def _bones(
    seg_joints: list[np.ndarray], edges: np.ndarray, joint_offsets: np.ndarray, n_seg: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Phase 8: every pair of joints on a segment: ``(bones (B, 2), bone_lengths (B,),
    bone_segment (B,), segment_lengths (S,))``."""
    bones, bone_seg = [], []
    for s in range(n_seg):
        js_s = seg_joints[s]
        for a in range(len(js_s)):
            for b in range(a + 1, len(js_s)):
                bones.append((js_s[a], js_s[b]))
                bone_seg.append(s)
    bones_arr = np.asarray(bones, dtype=int).reshape(-1, 2)

    def joint_on(s: int, j: int) -> np.ndarray:
        return joint_offsets[j, 0] if edges[j, 0] == s else joint_offsets[j, 1]

    bone_lengths = np.asarray(
        [np.linalg.norm(joint_on(s, a) - joint_on(s, b)) for (a, b), s in zip(bones, bone_seg)]
    )
    segment_lengths = longest_bones(bone_seg, bone_lengths, n_seg)
    return bones_arr, bone_lengths, np.asarray(bone_seg, dtype=int), segment_lengths


def _report(
    fr: _Frames, gp: _Procrustes, hinges: _Hinges, start: _Start, rf: _Refined, rested: _Rested,
    residual_rms: float, inputs: _Inputs, options: RigidOptions, landmarks: Trial | None, left: LeftOut,
) -> tuple[RigidDiagnostics, list[str]]:
    """Phase 9: the diagnostics and the texts of the :class:`ConvergenceWarning` s to give."""
    edges, labels = inputs.edges, inputs.labels
    n_used, n_joints, n_seg = fr.used.size, edges.shape[0], inputs.n_segments
    keep, sol = rf.keep, rf.sol
    steps = sol["num_steps"][keep]
    results = np.where(sol["done"], RESULT_SUCCESSFUL, RESULT_MAX_STEPS)[keep]
    converged = bool(rf.done) or not options.refine
    notes = []
    if not converged:
        notes.append(
            f"rigid refinement stopped after max_sweeps={options.max_sweeps} sweeps without meeting "
            f"xtol={options.xtol} m (the last update moved an offset by {rf.offset_steps[-1]:.2g} m); "
            "raise max_sweeps (see skeleton.diagnostics['cost_history'])"
        )
    if (results != RESULT_SUCCESSFUL).any():
        notes.append(
            f"IK hit max_steps={options.max_steps} in {(results != RESULT_SUCCESSFUL).sum()} of {results.size} "
            "fitting frames"
        )
    landmark_labels = tuple(landmarks.labels) if landmarks is not None else ()

    def names_of(i: int) -> str:
        return labels[fr.used[i]] if i < n_used else landmark_labels[i - n_used]

    axis_local, straddle, covered = start.hinge_axis_local, hinges.straddle, gp.covered
    # Hinge axes in the final parent frames (fitting-local -> rest-aligned).
    hinge_axis_rest = np.einsum("jab,jb->ja", rested.r_rest[edges[:, 0]], axis_local)
    diagnostics = RigidDiagnostics(
        sweeps=len(rf.history),
        result=RESULT_SUCCESSFUL if converged else RESULT_MAX_STEPS,
        cost_history=rf.history,
        offset_steps=rf.offset_steps,
        residual_rms=residual_rms,
        frames_used=int(keep.sum()),
        frames_rejected=int((fr.real & ~keep).sum()),
        rest_frame=int(fr.frames[rested.rest]),
        ik_steps_mean=float(steps.mean()) if steps.size else 0.0,
        ik_steps_max=int(steps.max()) if steps.size else 0,
        ik_failures=int((results != RESULT_SUCCESSFUL).sum()),
        procrustes_segments=[int(s) for s in np.flatnonzero(gp.alignable)],
        hinge_shift=[float(v) for v in rf.hinge_shift],
        hinge_placement=[
            "" if not np.isfinite(axis_local[j, 0]) and straddle[j, 0] < 0
            else f"between {names_of(straddle[j, 0])} and {names_of(straddle[j, 1])}" if straddle[j, 0] >= 0
            else "limb plane" for j in range(n_joints)
        ],
        hinge_axis=hinge_axis_rest.tolist(),
        procrustes_rms=[float(np.sqrt(np.mean(gp.rms[s][covered[s]] ** 2))) if covered[s].any() else float("nan")
                        for s in range(n_seg)],
        attachment_weight=gp.attachment_weight.tolist(),
        attachment_scatter=gp.attachment_scatter.tolist(),
        hinges_unmoved=list(left.hinges) if left.hinges else None,
        unplaced_markers=tuple(labels[m] for m in left.markers) if left.markers else None,
    )
    return diagnostics, notes


def _fit_once(
    inputs: _Inputs, options: RigidOptions, sliding: Sequence[bool] | np.ndarray | None, landmarks: Trial | None,
    left: LeftOut,
) -> tuple[Skeleton, list[str]] | LeftOut:
    """One attempt of the fit without what ``left`` leaves out: the skeleton and the
    texts of its convergence warnings, or what to leave out besides."""
    edges, root, n_seg = inputs.edges, inputs.root, inputs.n_segments
    seg = left.marker_segment(inputs.marker_segment)
    n_markers = seg.shape[0]
    fr = _choose_frames(inputs, seg, options.max_frames)
    gp = _procrustes(fr, edges, n_seg)
    hinges = _hinges(fr, gp, edges, left.sliding(sliding), landmarks, inputs.mask.shape[0])
    start = _starting_offsets(fr, gp, hinges, inputs, seg)
    if isinstance(start, LeftOut):
        return start
    rf = _refinement(fr, start, hinges, edges, options)
    if isinstance(rf, LeftOut):
        return rf
    marker_rms_used, residual_rms = _residuals(fr, rf, edges)
    rested = _rebase(fr, rf, edges, root)
    marker_offsets = np.full((n_markers, 3), np.nan)
    marker_offsets[fr.used] = rested.marker_theta
    joint_offsets = np.stack([rested.joint_theta, np.zeros_like(rested.joint_theta)], axis=1)
    marker_rms = np.full(n_markers, np.nan)
    marker_rms[fr.used] = marker_rms_used
    flagged = above_median(marker_rms, options.nonrigid_factor, NONRIGID_MARGIN)
    bones, bone_lengths, bone_segment, segment_lengths = _bones(gp.seg_joints, edges, joint_offsets, n_seg)
    diagnostics, notes = _report(fr, gp, hinges, start, rf, rested, residual_rms, inputs, options, landmarks, left)
    skeleton = Skeleton(
        n_segments=n_seg,
        edges=edges,
        root=root,
        marker_labels=inputs.labels,
        marker_segment=np.where(seg >= 0, seg, -1),
        marker_offsets=marker_offsets,
        joint_offsets=joint_offsets,
        bones=bones,
        bone_lengths=bone_lengths,
        bone_segment=bone_segment,
        segment_lengths=segment_lengths,
        marker_rms=marker_rms,
        nonrigid_markers=tuple(inputs.labels[i] for i in np.flatnonzero(flagged)),
        diagnostics=diagnostics,
    )
    return skeleton, notes


@float64_scope
def fit_rigid(
    trial: Trial | tuple[np.ndarray, np.ndarray],
    marker_segment: Sequence[int] | np.ndarray,
    edges: np.ndarray,
    joint_positions: np.ndarray,
    *,
    root: int | None = None,
    refine: bool = True,
    max_steps: int = 100,
    max_sweeps: int = 200,
    xtol: float = 1e-6,
    max_frames: int = 1000,
    prior_weight: float = DEFAULT_PRIOR_WEIGHT,
    nonrigid_factor: float = 3.0,
    labels: Sequence[str] | None = None,
    sliding_joints: Sequence[bool] | np.ndarray | None = None,
    joint_weight: float = JOINT_WEIGHT,
    landmarks: Trial | None = None,
    options: RigidOptions | None = None,
) -> Skeleton:
    """Fit a rigid skeleton to markers and joint centres (Kirk et al. 2005, §3.3).

    Parameters
    ----------
    trial
        A :class:`Trial`, or ``(x (F, M, 3), mask (F, M))`` in metres.
    marker_segment
        (M,) segment of each marker, -1 for markers to ignore.
    edges
        (J, 2) parent -> child segment pairs forming a tree over S = J + 1 segments.
    joint_positions
        (F, J, 3) joint centres per frame (row j <-> edge j), NaN where undefined, e.g.
        ``Topology.joint_positions``.
    root
        Root segment (default: the tree's root). Given a different root, edges are
        re-oriented away from it (rows keep their order).
    refine
        Run the global refinement after Procrustes (module docstring).
    max_steps
        Levenberg-Marquardt iterations per frame and sweep.
    max_sweeps, xtol
        Refinement stops after ``max_sweeps`` or when an offset update moves no offset by
        more than ``xtol`` metres without raising the cost (default 1 um: the alternation
        is slow along bone lengths, so a small update may still be far from the optimum).
    max_frames
        At most this many frames (evenly spaced) are used.
    prior_weight
        IK pose-prior weight, metres per radian (see :mod:`jaxskel.skeleton._ik`).
    nonrigid_factor
        Flag markers with residual RMS above this multiple of the median (and 1 mm above it).
    labels
        Marker labels when ``trial`` is an array tuple (default ``M0, M1, ...``).
    sliding_joints
        (J,) booleans: joints whose centre the markers leave free along an axis (hinges;
        :func:`jaxskel.fit_skeleton` passes ``topology.undetermined > 0``). Each is moved
        along its axis into the plane of its neighbouring joints before the refinement
        (:mod:`jaxskel.skeleton._hinge_centres`); the shifts are in ``diagnostics["hinge_shift"]``.
        Default: none moved (the input centres' placement, i.e. the distance prior's).
        After the refinement they are placed once more on the refined poses.
    joint_weight
        Weight of an input joint centre relative to a marker in the refinement (1: like a
        marker; :func:`jaxskel.fit_skeleton` uses ``SOLVED_JOINT_WEIGHT`` = 0.1 for its own
        solved centres, see there).
    landmarks
        Markers on the same frames that are on no segment (the extra markers of a static
        trial fitted with a dynamic one, :func:`jaxskel.segment.left_out_markers`): they take
        no part in the fit, but two that straddle a sliding joint place it midway between
        them (:func:`jaxskel.skeleton._hinge_centres.straddling_pair`), located in the
        joint's segment frames from the frames that show them. The fit's own markers never
        do (a moving limb's oblique axis passes pairs of surface markers).
    options
        The solver settings as one :class:`RigidOptions` (``refine`` ... ``nonrigid_factor``
        and ``joint_weight``), instead of those keywords (which must then keep their defaults).

    Returns
    -------
    :class:`Skeleton`, its ``diagnostics`` a :class:`RigidDiagnostics`. Raises
    :class:`InputError` for inconsistent inputs and :class:`DegenerateMotionError` when a
    segment cannot be placed. A marker never seen in a frame with the other points of its
    segment (nothing places it there) is left out instead, with a
    :class:`DegenerateMotionWarning`, as long as its segment keeps a marker or two joints:
    ``marker_segment`` -1 in the result, its label in ``diagnostics["unplaced_markers"]``.
    A moved hinge that the refined poses show turning about more than one axis is left
    where its input centre puts it, and the fit redone (``diagnostics["hinges_unmoved"]``).
    """
    keywords = dict(
        refine=refine, max_steps=max_steps, max_sweeps=max_sweeps, xtol=xtol, max_frames=max_frames,
        prior_weight=prior_weight, nonrigid_factor=nonrigid_factor, joint_weight=joint_weight,
    )
    if options is None:
        options = RigidOptions(**keywords)
    elif keywords != dataclasses.asdict(RigidOptions()):
        raise InputError("pass fit_rigid's settings either as options=RigidOptions(...) or as keywords, not both")
    inputs = _validate_inputs(trial, marker_segment, edges, joint_positions, root, labels)
    left = LeftOut()
    while True:
        attempt = _fit_once(inputs, options, sliding_joints, landmarks, left)
        if not isinstance(attempt, LeftOut):
            break
        if attempt.markers:
            warnings.warn(
                _unplaced_warning(inputs.labels, attempt.markers, inputs.marker_segment), DegenerateMotionWarning,
                stacklevel=3,  # fit_rigid's caller (2 is float64_scope's wrapper)
            )
        left = left | attempt
    skeleton, notes = attempt
    for note in notes:
        warnings.warn(note, ConvergenceWarning, stacklevel=3)  # fit_rigid's caller (2 is float64_scope's wrapper)
    return skeleton
