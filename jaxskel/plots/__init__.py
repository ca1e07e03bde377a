"""Figures of a fit and of its SD06 parameters (matplotlib).
"""

from __future__ import annotations

from ._parameter_plots import plot_angles, plot_joint_angles, plot_joint_spheres, plot_speed_histograms
from ._summary_plots import (
    plot_distance_std, plot_joint_costs, plot_residuals, plot_skeleton_3d, plot_spectrum,
    plot_summary, plot_tree,
)

__all__ = [
    "plot_angles", "plot_distance_std", "plot_joint_angles", "plot_joint_costs", "plot_joint_spheres", "plot_residuals",
    "plot_skeleton_3d", "plot_spectrum", "plot_speed_histograms", "plot_summary", "plot_tree",
]
