"""The rigid-body skeleton and its motion (Kirk et al. 2005, sec. 3.3): the rigid fit,
inverse kinematics (which fills gaps) and forward kinematics.
"""

from __future__ import annotations

from ._ik import Motion, forward_kinematics, ik_solve, inverse_kinematics
from ._rigid_fit import Skeleton, fit_rigid
from ._rigid_records import RigidDiagnostics, RigidOptions

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._ik import (
    DEFAULT_PRIOR_WEIGHT, FrameSolution, IKModel, ik_initial_guess, kinematic_chain, measured_rms, segment_members,
    tree_levels,
)
from ._ik_batch import solver_shape
from ._rigid_fit import SOLVED_JOINT_WEIGHT, longest_bones

__all__ = ["Motion", "RigidDiagnostics", "RigidOptions", "Skeleton", "fit_rigid", "forward_kinematics", "ik_solve", "inverse_kinematics"]
