"""Figures of the parameterisation (Sar Dessai et al. 2006, Figs. 2 and 4): joint spheres, speeds, angles.

:func:`plot_joint_angles` is the clinical-report view of the angles: one panel per
joint against seconds, or against % of a cycle (mean +- 1 SD over gait cycles).

Every function takes a :class:`~jaxskel.sd06.Parameterization`, returns a
:class:`matplotlib.figure.Figure` (built without pyplot, so no GUI backend or
global state is involved) and, given ``path``, also saves it there.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from itertools import pairwise
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from .._errors import InputError
from .._math.rotation import axis_angle_to_matrix_np

__all__ = ["plot_angles", "plot_joint_angles", "plot_joint_spheres", "plot_speed_histograms"]

_AXIS_COLOURS = ("tab:red", "tab:blue")


def _joints(param: Any, joints: Sequence[int] | None) -> list[int]:
    n = param.n_joints
    chosen = list(range(n)) if joints is None else [int(j) for j in joints]
    bad = [j for j in chosen if not 0 <= j < n]
    if bad or not chosen:
        raise InputError(f"joints must be indices in 0..{n - 1}, got {list(joints or [])}")
    return chosen


def _label(j: int, names: Sequence[str] | None) -> str:
    return f"joint {j}" if names is None else f"{names[j]} (joint {j})"


def _grid(n: int, width: float, height: float, **subplot: Any) -> tuple[Figure, list[Any]]:
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(width * cols, height * rows), layout="constrained")
    return fig, [fig.add_subplot(rows, cols, k + 1, **subplot) for k in range(n)]


def _save(fig: Figure, path: str | os.PathLike[str] | None) -> Figure:
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig


def plot_joint_spheres(
    param: Any,
    joints: Sequence[int] | None = None,
    *,
    names: Sequence[str] | None = None,
    max_points: int = 1500,
    path: str | os.PathLike[str] | None = None,
) -> Figure:
    """Each joint's samples on its unit joint sphere with the extracted axes (Fig. 2a/c, 4a).

    Movement samples are coloured by time, stationary ones grey; arrows are the
    axes (red acts first), the curves through the rest direction (black star)
    are the circles each axis alone sweeps it along.
    """
    chosen = _joints(param, joints)
    fig, panels = _grid(len(chosen), 3.2, 3.2, projection="3d")
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    sweep = np.linspace(-np.pi, np.pi, 181)
    for ax, j in zip(panels, chosen, strict=True):
        samples = param.samples[:, j]
        stride = max(1, samples.shape[0] // max_points)
        frames = np.arange(0, samples.shape[0], stride)
        moving = param.movement[frames, j]
        ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85", lw=0.3)
        still = samples[frames[~moving]]
        ax.scatter(*still.T, s=2, color="0.6", depthshade=False)
        active = samples[frames[moving]]
        ax.scatter(*active.T, s=3, c=frames[moving], cmap="viridis", depthshade=False)
        rest = param.rest_direction[j]
        for k in range(int(param.n_axes[j])):
            axis = param.axes[j, k]
            colour = _AXIS_COLOURS[k]
            ax.quiver(0, 0, 0, *(1.4 * axis), color=colour, lw=1.5, arrow_length_ratio=0.1)
            ax.plot(*(axis_angle_to_matrix_np(sweep[:, None] * axis) @ rest).T, color=colour, lw=1.0)
        ax.scatter(*rest, s=80, marker="*", color="black", depthshade=False)
        ax.set_title(f"{_label(j, names)}: {int(param.n_axes[j])} axis", fontsize=9)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlim(-1.2, 1.2), ax.set_ylim(-1.2, 1.2), ax.set_zlim(-1.2, 1.2)
        ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z")
    fig.suptitle(f"Joint spheres ({param.method}), parent joint frames")
    return _save(fig, path)


def plot_speed_histograms(
    param: Any,
    joints: Sequence[int] | None = None,
    *,
    names: Sequence[str] | None = None,
    path: str | os.PathLike[str] | None = None,
) -> Figure:
    """Histogram of sample speeds per joint with the movement threshold (Fig. 2b)."""
    chosen = _joints(param, joints)
    fig, panels = _grid(len(chosen), 3.2, 2.4)
    for ax, j in zip(panels, chosen, strict=True):
        counts = param.histogram[j]
        width = param.top_speed[j] / counts.size if param.top_speed[j] > 0 else 1.0
        ax.bar(np.arange(counts.size) * width, counts, width=width, align="edge", color="0.5")
        ax.axvline(param.speed_threshold[j], color="tab:red", lw=1.2, label="threshold")
        ax.set_yscale("symlog")
        ax.set_title(_label(j, names), fontsize=9)
        ax.set_xlabel("speed (rad / frame)")
    panels[0].legend(fontsize=8)
    return _save(fig, path)


def plot_angles(
    param: Any,
    joints: Sequence[int] | None = None,
    *,
    names: Sequence[str] | None = None,
    rate: float | None = None,
    path: str | os.PathLike[str] | None = None,
) -> Figure:
    """Angle curves per joint in degrees: first axis, second axis (two-axis joints) and twist."""
    chosen = _joints(param, joints)
    n_frames = param.n_frames
    time = np.arange(n_frames) / rate if rate else np.arange(n_frames)
    fig = Figure(figsize=(9.0, 1.8 * len(chosen) + 0.6), layout="constrained")
    panels = [fig.add_subplot(len(chosen), 1, k + 1) for k in range(len(chosen))]
    for ax, j in zip(panels, chosen, strict=True):
        angles = np.degrees(param.angles[:, j])
        ax.plot(time, angles[:, 0], color=_AXIS_COLOURS[0], lw=0.9, label="axis 1")
        if param.n_axes[j] > 1:
            ax.plot(time, angles[:, 1], color=_AXIS_COLOURS[1], lw=0.9, label="axis 2")
        ax.plot(time, angles[:, 2], color="0.4", lw=0.8, ls="--", label="twist")
        moving = param.movement[:, j]
        ax.fill_between(time, 0, 1, where=moving, color="tab:green", alpha=0.08, transform=ax.get_xaxis_transform())
        ax.set_ylabel("degrees")
        ax.set_title(_label(j, names), fontsize=9, loc="left")
    panels[0].legend(fontsize=8, ncols=3, loc="upper right")
    panels[-1].set_xlabel("seconds" if rate else "frame")
    return _save(fig, path)


#: Samples per cycle in :func:`plot_joint_angles` with ``cycle=``: 0, 1, ..., 100 % of the cycle.
CYCLE_POINTS = 101


def _angle_joints(param: Any, joints: Any, names: Sequence[str] | None) -> list[int]:
    """Joint indices from indices or (with ``names``) names; InputError for anything unknown."""
    n = param.n_joints
    if joints is None:
        return list(range(n))
    items = [joints] if isinstance(joints, (str, int, np.integer)) else list(joints)
    if not items:
        raise InputError(f"joints is empty; give joint indices in 0..{n - 1} or joint names, or None for all")
    chosen = []
    for item in items:
        if isinstance(item, str):
            if names is None or item not in names:
                known = "no names= were given" if names is None else f"known: {', '.join(names)}"
                raise InputError(f"unknown joint {item!r} ({known})")
            chosen.append(list(names).index(item))
        elif isinstance(item, (int, np.integer)) and not isinstance(item, (bool, np.bool_)) and 0 <= item < n:
            chosen.append(int(item))
        else:
            raise InputError(f"unknown joint {item!r}: joints are indices in 0..{n - 1} or names from names=")
    return chosen


def _cycle_starts(cycle: Any, n_frames: int) -> np.ndarray:
    """``cycle`` as (K + 1,) float frame positions: finite, strictly increasing, in [0, F - 1]."""
    try:
        starts = np.asarray(cycle, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"cycle must be an array of cycle-start frames (e.g. heel strikes), got {cycle!r}") from None
    if starts.ndim != 1 or starts.size < 2:
        raise InputError(
            f"cycle must be a 1-D array of at least 2 cycle-start frames (K + 1 starts bound K cycles), "
            f"got shape {starts.shape}"
        )
    if not np.all(np.isfinite(starts)) or np.any(np.diff(starts) <= 0):
        raise InputError(f"cycle start frames must be finite and strictly increasing, got {starts.tolist()}")
    if starts[0] < 0 or starts[-1] > n_frames - 1:
        raise InputError(
            f"cycle start frames must lie in 0..{n_frames - 1} (the recording's frames), got "
            f"{starts.min():g}..{starts.max():g}"
        )
    return starts


def _cycle_curves(values: np.ndarray, starts: np.ndarray, n_points: int = CYCLE_POINTS) -> np.ndarray:
    """(K, n_points, ...) ``values`` (F, ...) resampled over each of the K cycles ``starts[k]..starts[k + 1]``.

    Point ``i`` of cycle ``k`` is ``values`` linearly interpolated at frame position
    ``starts[k] + (starts[k + 1] - starts[k]) * i / (n_points - 1)`` (so 0 % and 100 %
    are the cycle's bounding events).
    """
    frames = np.arange(values.shape[0])
    flat = values.reshape(values.shape[0], -1)
    u = np.linspace(0.0, 1.0, n_points)
    out = []
    for s0, s1 in pairwise(starts):
        at = s0 + (s1 - s0) * u
        out.append(np.stack([np.interp(at, frames, flat[:, c]) for c in range(flat.shape[1])], axis=1))
    return np.stack(out).reshape(len(out), n_points, *values.shape[1:])


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) frame ranges (stop exclusive) where ``mask`` is True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def plot_joint_angles(
    parameterization: Any,
    *,
    joints: Any = None,
    names: Sequence[str] | None = None,
    rate: float | None = None,
    cycle: Any = None,
    path: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
) -> Figure:
    """Joint angles per joint, as clinical gait reports show them: one small panel per joint.

    Each panel shows, in degrees, the angle about the joint's first movement axis
    ("axis 1", ``angles[:, j, 0]``), about its second axis ("axis 2", two-axis joints
    only, ``angles[:, j, 1]``) and the twist about the limb's long axis ("twist",
    ``angles[:, j, 2]``); the axes are the extracted ones (no anatomical
    flexion/abduction names: SD06 finds axes, not their anatomical meaning).

    * ``cycle`` None: against time, ``t_f = f / rate`` seconds (frame index f when
      ``rate`` is None, since a parameterisation does not record its rate). Frames a
      joint's axes were taken from (``parameterization.calibration[:, j]``) are
      shaded, each frame covering ``t_f +- 1 / (2 rate)``, unless they are all frames.
    * ``cycle`` (K + 1,) increasing frame positions (e.g. one foot's heel strikes;
      fractional frames allowed, all in ``0..F - 1``) bounding K cycles: against %
      cycle. Cycle k is resampled at ``p = 0, 1, ..., 100`` % by linear interpolation
      at frame ``s_k + (s_{k+1} - s_k) p / 100``; each curve is the mean over the K
      cycles, with a band of +- 1 sample SD (``ddof=1``; none for K = 1).

    ``joints``: indices, or names from ``names`` (J names, one per joint, used in the
    panel titles); default all. Angles are taken as stored (continuous branches), so
    the means are plain means. Returns the :class:`~matplotlib.figure.Figure`; with
    ``path`` it is also saved there atomically (suffix: an image type matplotlib
    writes; an existing file only with ``overwrite``), all checked before drawing.
    Raises :class:`~jaxskel.InputError` for unknown joints, bad names, rate, cycle or path.
    """
    param = parameterization
    n_frames, n_joints = param.n_frames, param.n_joints
    if names is not None:
        if isinstance(names, str) or len(names) != n_joints or not all(isinstance(x, str) for x in names):
            raise InputError(f"names must be {n_joints} strings, one per joint, got {names!r}")
        names = list(names)
    chosen = _angle_joints(param, joints, names)
    if rate is not None and not (isinstance(rate, (int, float, np.number)) and math.isfinite(rate) and rate > 0):
        raise InputError(f"rate must be a positive number of frames per second, got {rate!r}")
    starts = None if cycle is None else _cycle_starts(cycle, n_frames)
    fmt = None
    if path is not None:
        if not isinstance(path, (str, os.PathLike)):
            raise InputError(f"path must be a file name (str or path), got {type(path).__name__}")
        from ..io import check_output, image_format

        fmt = image_format(check_output(path, "image"))
        if os.path.exists(path) and not overwrite:
            raise InputError(f"{path} already exists; pass overwrite=True to replace it or choose another name")

    degrees = np.degrees(np.asarray(param.angles, dtype=float))
    fig, panels = _grid(len(chosen), 3.0, 2.3)
    if starts is None:
        x = np.arange(n_frames) / rate if rate else np.arange(n_frames, dtype=float)
        half = 0.5 / rate if rate else 0.5
        xlabel = "seconds" if rate else "frame"
    else:
        x = np.linspace(0.0, 100.0, CYCLE_POINTS)
        curves = _cycle_curves(degrees, starts)  # (K, 101, J, 3)
        mean = curves.mean(axis=0)
        sd = curves.std(axis=0, ddof=1) if curves.shape[0] > 1 else None
        xlabel = "% cycle"
    series = [(0, "axis 1", _AXIS_COLOURS[0], "-"), (1, "axis 2", _AXIS_COLOURS[1], "-"), (2, "twist", "0.35", "--")]
    legend: dict[str, Any] = {}
    for ax, j in zip(panels, chosen, strict=True):
        for k, label, colour, style in series:
            if k == 1 and int(param.n_axes[j]) < 2:
                continue
            if starts is None:
                (line,) = ax.plot(x, degrees[:, j, k], color=colour, ls=style, lw=0.9, label=label)
            else:
                (line,) = ax.plot(x, mean[:, j, k], color=colour, ls=style, lw=1.1, label=label)
                if sd is not None:
                    ax.fill_between(x, mean[:, j, k] - sd[:, j, k], mean[:, j, k] + sd[:, j, k],
                                    color=colour, alpha=0.18, lw=0)
            legend.setdefault(label, line)
        if starts is None:
            mask = np.asarray(param.calibration[:, j], bool)
            if mask.any() and not mask.all():
                for a, b in _runs(mask):
                    span = ax.axvspan(x[a] - half, x[b - 1] + half, color="tab:green", alpha=0.1, lw=0,
                                      label="calibration")
                    legend.setdefault("calibration", span)
            ax.set_xlim(x[0], x[-1])
        else:
            ax.set_xlim(0.0, 100.0)
        ax.axhline(0.0, color="0.7", lw=0.5)
        ax.set_title(_label(j, names), fontsize=9)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("degrees", fontsize=8)
        ax.tick_params(labelsize=7)
    order = [k for k in ("axis 1", "axis 2", "twist", "calibration") if k in legend]
    fig.legend([legend[k] for k in order], order, loc="outside upper right", ncols=len(order), fontsize=8)
    what = "joint angles" if starts is None else f"joint angles, mean +- 1 SD over {len(starts) - 1} cycle(s)"
    fig.suptitle(f"{what} ({param.method})", fontsize=10)
    if path is not None:
        from ..io import atomic_output

        with atomic_output(path, overwrite) as tmp:
            fig.savefig(tmp, dpi=110, format=fmt)
    return fig
