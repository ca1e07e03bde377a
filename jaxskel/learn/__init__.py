"""The learning-pipeline API: pure, jit/vmap/grad-able stage functions with implicit-
function gradients.
"""

from __future__ import annotations

from ._functional import RigidFit, SkeletonStructure, ik_fn, joint_cost_fn, rigid_fit_fn

__all__ = ["RigidFit", "SkeletonStructure", "ik_fn", "joint_cost_fn", "rigid_fit_fn"]
