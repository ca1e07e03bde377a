"""Body parts of a fitted skeleton, without a template or marker names: which segment is
the pelvis, the left thigh, the right hand, from the tree, the body frame, the geometry
and the motion.
"""

from __future__ import annotations

from ._vocabulary import (
    CHAINS, JOINT_OF_PART, PARENT_PART, PARTS, SIDES, VIRTUAL_MARKER, Anatomy, is_ancestor, joint_between, joint_name, mirror,
    side_of,
)
from ._identify import identify, identify_result
from ._options import AnatomyOptions
from ._angles import COMPONENTS, AngleOptions, JointAngles, anatomical_frames, joint_angles

__all__ = [
    "AnatomyOptions", "identify", "identify_result",
    "AngleOptions", "COMPONENTS", "JointAngles", "anatomical_frames", "joint_angles",
    "Anatomy", "CHAINS", "JOINT_OF_PART", "PARENT_PART", "PARTS", "SIDES", "VIRTUAL_MARKER", "is_ancestor", "joint_between",
    "joint_name", "mirror", "side_of",
]
