"""Joints between segments (Kirk et al. 2005, sec. 3.2): the joint cost of every pair, the
minimum spanning tree, attachments of sparsely marked segments, the pose check, near
ties, and how well the motion determines each joint.
"""

from __future__ import annotations

from ._attachments import Attachment
from ._cost import JointSolution, solve_joint, solve_joints
from ._determination import UndeterminedJoint, bone_uncertainty, joint_resolution, undetermined_joints
from ._near_ties import NearTie, near_ties
from ._pose_check import PoseExchange
from ._topology import PairCosts, Topology, UntestedJoint, fit_topology, joint_costs, untested_joints

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._anchored_centres import MIN_EXERCISE_DEG, anchored_centres
from ._attachments import core_costs
from ._determination import UNDETERMINED_RESOLUTION, loose_directions, radial_share
from ._near_ties import runner_up
from ._topology import (
    all_pairs_problem, pair_costs_from, solve_pairs, solve_trees, topology_from, tree_problem,
)

__all__ = [
    "Attachment", "JointSolution", "NearTie", "PairCosts", "PoseExchange", "Topology",
    "UndeterminedJoint", "UntestedJoint", "bone_uncertainty", "fit_topology", "joint_costs",
    "joint_resolution", "near_ties", "solve_joint", "solve_joints", "undetermined_joints",
    "untested_joints",
]
