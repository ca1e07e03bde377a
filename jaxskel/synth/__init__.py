"""Synthetic articulated bodies and motion-capture trials with exact ground truth.

Every accuracy test and benchmark of jaxskel starts here::

    from jaxskel import synth
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, motion="calibration", duration=30.0, noise=0.001)

Bodies: :func:`linkage` (the three-rod calibration linkage of Kirk et al. 2005),
:func:`full_body` (a 15-segment adult with 46 skin markers), :func:`random_tree`.
Motions: "calibration" (every joint through all its degrees of freedom) and
"walk" (human gait; wrists and neck nearly still). Corruptions (all off by
default, each with its own random stream): measurement noise, soft-tissue
artefact, gaps, jumps, ghost markers, passive-system relabelling.
"""

from ._bodies import JOINT_DOF, Body, full_body, linkage, random_tree
from ._motion import MOTIONS, forward_kinematics
from ._simulate import GroundTruth, simulate

__all__ = [
    "Body",
    "GroundTruth",
    "JOINT_DOF",
    "MOTIONS",
    "forward_kinematics",
    "full_body",
    "linkage",
    "random_tree",
    "simulate",
]
