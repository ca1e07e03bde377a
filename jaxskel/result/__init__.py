"""The result of a fit: SkeletonResult, its summary, its HDF5 file format, its BVH
export and its OpenSim model export.
"""

from __future__ import annotations

from ._anatomy_file import load_anatomy, load_angles
from ._bvh import BvhData, export_bvh, read_bvh
from ._format import ResultFile, SCHEMA_VERSION, load_result
from ._osim import export_osim, opensim_frame, opensim_names, to_opensim_frame
from ._result import SkeletonResult
from ._skeleton_file import load_skeleton
from ._sto import StoTable, read_sto, write_angles_sto
from ._tracked import TrackedTrial
from ._virtual import fitted_markers_trial, with_joint_centres

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._anatomy_file import angles_or_none
from ._summary import (
    near_tie_text, nonrigid_group_hint, nonrigid_group_texts, nonrigid_text, undetermined_lines,
    untested_text,
)

__all__ = [
    "BvhData", "ResultFile", "SCHEMA_VERSION", "SkeletonResult", "StoTable", "TrackedTrial", "export_bvh",
    "export_osim", "fitted_markers_trial", "load_anatomy", "load_angles", "load_result", "load_skeleton", "opensim_frame", "opensim_names",
    "read_bvh", "read_sto", "to_opensim_frame", "with_joint_centres", "write_angles_sto",
]
