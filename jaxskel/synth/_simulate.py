"""`simulate`: a body + a motion + corruptions -> (Trial, GroundTruth)."""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from typing import Any

import numpy as np
from jaxtyping import Bool, Float, Int

from .._errors import InputError
from ..io import UP_AXES, Trial, rotation_between_axes
from ._bodies import Body
from ._corrupt import (
    gap_mask,
    ghost_trajectories,
    jump_offsets,
    relabel_after_gaps,
    soft_tissue_displacement,
)
from ._motion import MOTIONS, forward_kinematics

__all__ = ["GroundTruth", "simulate"]

# Independent random streams, so switching one corruption on or off leaves the
# motion and the other corruptions unchanged for a given seed.
_STREAM = {"motion": 0, "soft_tissue": 1, "noise": 2, "gaps": 3, "jumps": 4, "ghosts": 5}


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class GroundTruth:
    """Everything that is known exactly about a simulated trial.

    Marker axes (M) follow the trial's columns: physical markers first (their
    original labels), then the extra labels created by ``relabel`` (in order of
    appearance), then ghosts. World quantities are in the trial's up-axis frame.

    Attributes
    ----------
    marker_segment
        (M,) segment of each column, -1 for ghosts.
    segment_names
        (S,) segment names.
    edges
        (J, 2) parent -> child segments; row j is joint j.
    root
        Root segment index.
    joint_positions
        (F, J, 3) joint centres in the world.
    joint_types
        (J,) "ball" / "universal" / "hinge".
    joint_axes
        J arrays (k, 3): joint axes in the parent frame (see :mod:`jaxskel.synth._bodies`).
    segment_rotations, segment_translations
        (F, S, 3, 3) and (F, S, 3): segment poses, ``x_world = R x_local + t``.
    marker_offsets
        (M, 3) each column's marker in its segment frame (NaN for ghosts).
    joint_offsets
        (J, 2, 3) joint centre in the parent frame and in the child frame.
    bones, bone_lengths, bone_segment
        (B, 2) pairs of joints on one segment, (B,) their distance in metres, (B,)
        the segment they lie on. Segments with a single joint have no bone.
    physical
        (M,) physical marker behind each column (identity without relabel; -1 for ghosts).
    physical_labels
        (P,) the original label of each physical marker.
    clean_positions
        (F, M, 3) rigid-model marker positions (no soft tissue, noise, jumps or gaps)
        of each column's physical marker at every frame; NaN for ghosts.
    joint_names, joint_limits, joint_angles
        (J,) names, J arrays (k, 2) limits in radians, J arrays (F, k) angles.
    joint_axes_world
        J arrays (F, k, 3): each joint axis in the world (parent-fixed axes turn
        with the parent, a universal joint's second axis with the child).
    soft_tissue_displacement
        (F, M, 3) world displacement added by the soft-tissue artefact (zero for ghosts).
    jumped
        (F, M) True where a visible sample was displaced by a jump.
    body
        The :class:`~jaxskel.synth.Body` that was simulated.
    settings
        Motion and corruption settings used (read-only mapping).
    """

    marker_segment: Int[np.ndarray, " M"]
    segment_names: tuple[str, ...]
    edges: Int[np.ndarray, "J 2"]
    root: int
    joint_positions: Float[np.ndarray, "F J 3"]
    joint_types: tuple[str, ...]
    joint_axes: tuple[Float[np.ndarray, "k 3"], ...]
    segment_rotations: Float[np.ndarray, "F S 3 3"]
    segment_translations: Float[np.ndarray, "F S 3"]
    marker_offsets: Float[np.ndarray, "M 3"]
    joint_offsets: Float[np.ndarray, "J 2 3"]
    bones: Int[np.ndarray, "B 2"]
    bone_lengths: Float[np.ndarray, " B"]
    bone_segment: Int[np.ndarray, " B"]
    physical: Int[np.ndarray, " M"]
    physical_labels: tuple[str, ...]
    clean_positions: Float[np.ndarray, "F M 3"]
    joint_names: tuple[str, ...]
    joint_limits: tuple[Float[np.ndarray, "k 2"], ...]
    joint_angles: tuple[Float[np.ndarray, "F k"], ...]
    joint_axes_world: tuple[Float[np.ndarray, "F k 3"], ...]
    soft_tissue_displacement: Float[np.ndarray, "F M 3"]
    jumped: Bool[np.ndarray, "F M"]
    body: Body
    settings: Mapping[str, Any]

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.ndarray):
                object.__setattr__(self, field.name, _readonly(value))
            elif isinstance(value, tuple) and value and isinstance(value[0], np.ndarray):
                object.__setattr__(self, field.name, tuple(_readonly(v) for v in value))
        object.__setattr__(self, "settings", types.MappingProxyType(dict(self.settings)))

    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    @property
    def n_joints(self) -> int:
        return int(self.edges.shape[0])

    @property
    def n_physical(self) -> int:
        return len(self.physical_labels)


def _append_ghosts(a: np.ndarray, n_ghosts: int, fill: Any, axis: int = 0) -> np.ndarray:
    """``a`` with ``n_ghosts`` entries of ``fill`` appended along the marker axis."""
    shape = list(a.shape)
    shape[axis] = n_ghosts
    return np.concatenate([a, np.full(shape, fill, dtype=a.dtype)], axis=axis)


def _scatter_columns(a: np.ndarray, column: np.ndarray, n_columns: int, fill: Any) -> np.ndarray:
    """Move each visible sample ``a[f, m]`` to column ``column[f, m]`` (-1: missing)."""
    f_idx, m_idx = np.nonzero(column >= 0)
    out = np.full((a.shape[0], n_columns, *a.shape[2:]), fill, dtype=a.dtype)
    out[f_idx, column[f_idx, m_idx]] = a[f_idx, m_idx]
    return out


def _seconds_to_frames(span: tuple[float, float], rate: float, name: str) -> tuple[int, int]:
    lo, hi = (float(v) for v in span)
    if not 0 < lo <= hi:
        raise InputError(f"{name} must be (min, max) seconds with 0 < min <= max, got {span}")
    return max(1, round(lo * rate)), max(1, round(hi * rate))


def _joint_amounts(body: Body, joint_range: Mapping[str, float] | None) -> np.ndarray:
    amount = np.ones(body.n_joints)
    for name, value in (joint_range or {}).items():
        if name not in body.joint_names:
            raise InputError(
                f"joint_range names unknown joint {name!r}; joints: {body.joint_names}"
            )
        if not 0.0 <= float(value) <= 1.0:
            raise InputError(f"joint_range[{name!r}] must be in [0, 1], got {value!r}")
        amount[body.joint_names.index(name)] = float(value)
    return amount


def _check_count(value: Any, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float)):
        raise InputError(f"{name} must be a non-negative integer, got {value!r}")
    if int(value) != value or value < 0:
        raise InputError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


def _check_amount(value: Any, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a non-negative number of metres, got {value!r}") from None
    if not np.isfinite(value) or value < 0:
        raise InputError(f"{name} must be a non-negative number of metres, got {value!r}")
    return value


def simulate(
    body: Body,
    motion: str = "calibration",
    duration: float = 30.0,
    rate: float = 120.0,
    seed: int = 0,
    noise: float = 0.0,
    soft_tissue: float = 0.0,
    gaps: int = 0,
    jumps: int = 0,
    ghosts: int = 0,
    relabel: bool = False,
    up_axis: str = "z",
    *,
    gap_length: tuple[float, float] = (0.05, 0.5),
    jump_size: tuple[float, float] = (0.03, 0.08),
    jump_frames: tuple[int, int] = (1, 5),
    ghost_length: tuple[float, float] = (0.05, 0.5),
    joint_range: Mapping[str, float] | None = None,
) -> tuple[Trial, GroundTruth]:
    """Simulate a motion-capture trial of ``body`` with exact ground truth.

    Parameters
    ----------
    body
        From :func:`linkage`, :func:`full_body`, :func:`random_tree` (or a custom :class:`Body`).
    motion
        "calibration" (every joint through all its degrees of freedom, smooth,
        within its limits; the root moves and turns) or "walk" (human gait on a
        circle; wrists and neck nearly still; needs :func:`full_body`).
    duration, rate
        Seconds and frames per second; ``round(duration * rate)`` frames.
    seed
        Non-negative integer; each part (motion and every corruption) draws from
        its own stream, so turning one corruption on does not change the others.
    noise
        Standard deviation (metres) of iid Gaussian noise on every coordinate.
    soft_tissue
        RMS length (metres) of the skin-motion artefact per marker: smooth,
        driven by the angles of the joints on the marker's segment.
    gaps
        Occlusions per marker (exactly this many, lengths uniform in ``gap_length``
        seconds, never at the first or last frame); occluded samples are NaN.
    jumps
        Number of jump events in the trial: one marker displaced by ``jump_size``
        metres for ``jump_frames`` frames; with gaps, half of them next to a gap.
    ghosts
        Number of spurious markers (labels "*ghost0", ...), each visible for
        ``ghost_length`` seconds; ``truth.marker_segment`` is -1 for them.
    relabel
        Passive-system labelling: after each gap a marker comes back under a new
        label ("*1", "*2", ... in order of appearance); ``truth.physical`` maps
        every label to its physical marker.
    up_axis
        Vertical axis of the output ("z" native; any of x, y, z, -x, -y, -z).
        Every world quantity of the truth is rotated along with the trial.
    gap_length, jump_size, jump_frames, ghost_length
        (min, max) ranges for the corruptions above (seconds, metres, frames, seconds).
    joint_range
        Joint name -> factor on that joint's excursion (default 1; 0 holds the
        joint still, e.g. to test a joint that is never exercised).

    Returns
    -------
    (trial, truth)
        The corrupted :class:`~jaxskel.Trial` and its :class:`GroundTruth`.
    """
    if not isinstance(body, Body):
        raise InputError(
            f"body must be a synth.Body (from synth.linkage(), full_body() or random_tree()), "
            f"got {type(body).__name__}"
        )
    if motion not in MOTIONS:
        raise InputError(f"unknown motion {motion!r}; use one of {tuple(MOTIONS)}")
    if up_axis not in UP_AXES or up_axis == "unknown":
        raise InputError(f"up_axis must be one of {UP_AXES[:-1]}, got {up_axis!r}")
    rate = float(rate)
    n_frames = round(float(duration) * rate)
    if not (np.isfinite(rate) and rate > 0) or n_frames < 2:
        raise InputError(
            f"duration={duration!r} s at rate={rate!r} Hz gives {n_frames} frames; "
            "give a positive rate and at least two frames"
        )
    seed = _check_count(seed, "seed")
    noise = _check_amount(noise, "noise")
    soft_tissue = _check_amount(soft_tissue, "soft_tissue")
    gaps = _check_count(gaps, "gaps")
    jumps = _check_count(jumps, "jumps")
    ghosts = _check_count(ghosts, "ghosts")
    gap_frames = _seconds_to_frames(gap_length, rate, "gap_length")
    ghost_frames = _seconds_to_frames(ghost_length, rate, "ghost_length")
    jump_lo, jump_hi = (int(v) for v in jump_frames)
    if not 1 <= jump_lo <= jump_hi or not 0 <= jump_size[0] <= jump_size[1]:
        raise InputError(
            "jump_frames must be (min, max) frames >= 1 and jump_size (min, max) metres >= 0"
        )

    def stream(name: str) -> np.random.Generator:
        return np.random.default_rng([seed, _STREAM[name]])

    times = np.arange(n_frames) / rate
    amount = _joint_amounts(body, joint_range)
    angles, (root_rot, root_trans) = MOTIONS[motion](body, times, stream("motion"), amount)
    rot, trans = forward_kinematics(body, angles, root_rot, root_trans)

    seg = body.marker_segment
    seg_rot = rot[:, seg]  # (F, M, 3, 3)
    clean = np.einsum("fmij,mj->fmi", seg_rot, body.marker_offsets) + trans[:, seg]
    parents = body.edges[:, 0]
    joints = np.einsum("fjik,jk->fji", rot[:, parents], body.joint_offsets[:, 0])
    joints = joints + trans[:, parents]

    displacement = np.zeros_like(clean)
    if soft_tissue > 0:
        local = soft_tissue_displacement(body, angles, times, soft_tissue, stream("soft_tissue"))
        displacement = np.einsum("fmij,fmj->fmi", seg_rot, local)
    observed = clean + displacement
    if noise > 0:
        observed = observed + stream("noise").normal(0.0, noise, size=observed.shape)
    missing = gap_mask(n_frames, body.n_markers, gaps, gap_frames, stream("gaps"))
    offsets, jumped = jump_offsets(missing, jumps, jump_size, (jump_lo, jump_hi), stream("jumps"))
    # Ghosts are reflections of the real markers, whether or not those are seen.
    surface = observed + offsets
    observed = np.where(missing[..., None], np.nan, surface)

    labels = list(body.marker_labels)
    physical = np.arange(body.n_markers)
    if relabel:
        column, physical = relabel_after_gaps(~missing)
        observed = _scatter_columns(observed, column, physical.size, np.nan)
        jumped = _scatter_columns(jumped, column, physical.size, False)
        labels += [f"*{k}" for k in range(1, physical.size - body.n_markers + 1)]

    ghost_xyz = ghost_trajectories(surface, ghosts, ghost_frames, stream("ghosts"))
    observed = np.concatenate([observed, ghost_xyz], axis=1)
    labels += [f"*ghost{g}" for g in range(ghosts)]
    marker_segment = _append_ghosts(seg[physical], ghosts, -1)
    marker_offsets = _append_ghosts(body.marker_offsets[physical], ghosts, np.nan)
    clean_cols = _append_ghosts(clean[:, physical], ghosts, np.nan, axis=1)
    displacement_cols = _append_ghosts(displacement[:, physical], ghosts, 0.0, axis=1)
    jumped = _append_ghosts(jumped, ghosts, False, axis=1)
    physical_cols = _append_ghosts(physical, ghosts, -1)

    # Re-express the world so that +Z (native up) becomes the requested up axis. This
    # comes last, so a trial differs from its Z-up twin by exactly this rotation.
    if up_axis != "z":
        up = rotation_between_axes("z", up_axis)
        rot = up @ rot
        trans = trans @ up.T
        joints, observed, clean_cols, displacement_cols = (
            a @ up.T for a in (joints, observed, clean_cols, displacement_cols)
        )

    axes_world = []
    for j, kind in enumerate(body.joint_types):
        parent, child = body.edges[j]
        fixed_in = [parent] * len(body.joint_axes[j])
        if kind == "universal":
            fixed_in[1] = child
        axes_world.append(np.einsum("fkij,kj->fki", rot[:, fixed_in], body.joint_axes[j]))

    settings = {
        "motion": motion,
        "duration": n_frames / rate,
        "rate": rate,
        "seed": seed,
        "noise": noise,
        "soft_tissue": soft_tissue,
        "gaps": gaps,
        "gap_length": tuple(gap_length),
        "jumps": jumps,
        "jump_size": tuple(jump_size),
        "jump_frames": (jump_lo, jump_hi),
        "ghosts": ghosts,
        "ghost_length": tuple(ghost_length),
        "relabel": bool(relabel),
        "up_axis": up_axis,
        "joint_range": dict(zip(body.joint_names, amount.tolist(), strict=True)),
    }
    trial = Trial(
        positions=observed,
        labels=tuple(labels),
        rate=rate,
        up_axis=up_axis,
        source=f"synth:{body.name}/{motion} seed={seed}",
        # Flat scalars only, so every file format can store them.
        metadata={
            "synthetic": True,
            "body": body.name,
            **{k: v for k, v in settings.items() if not isinstance(v, (dict, tuple))},
        },
    )
    truth = GroundTruth(
        marker_segment=marker_segment,
        segment_names=body.segment_names,
        edges=body.edges,
        root=body.root,
        joint_positions=joints,
        joint_types=body.joint_types,
        joint_axes=body.joint_axes,
        segment_rotations=rot,
        segment_translations=trans,
        marker_offsets=marker_offsets,
        joint_offsets=body.joint_offsets,
        bones=body.bones,
        bone_lengths=body.bone_lengths,
        bone_segment=body.bone_segment,
        physical=physical_cols,
        physical_labels=body.marker_labels,
        clean_positions=clean_cols,
        joint_names=body.joint_names,
        joint_limits=body.joint_limits,
        joint_angles=tuple(angles),
        joint_axes_world=tuple(axes_world),
        soft_tissue_displacement=displacement_cols,
        jumped=jumped,
        body=body,
        settings=settings,
    )
    return trial, truth
