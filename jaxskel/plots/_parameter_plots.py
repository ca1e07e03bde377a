"""Figures of the parameterisation (Sar Dessai et al. 2006, Figs. 2 and 4): joint spheres, speeds, angles.

Every function takes a :class:`~jaxskel.sd06.Parameterization`, returns a
:class:`matplotlib.figure.Figure` (built without pyplot, so no GUI backend or
global state is involved) and, given ``path``, also saves it there.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from .._errors import InputError
from .._math.rotation import axis_angle_to_matrix_np

__all__ = ["plot_joint_spheres", "plot_speed_histograms", "plot_angles"]

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
