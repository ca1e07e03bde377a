"""The whole chain, from one options object: one fit (fit_skeleton), many trials
(fit_batch, optionally on Dask), and the stage plan both run.
"""

from __future__ import annotations

from ._batch import BatchResult, TrialOutcome, fit_batch
from ._batch_io import bone_length, plot_bone_lengths
from ._fit import fit_skeleton
from ._options import (
    BodyOptions, CleanOptions, FitOptions, JointOptions, LabelOptions, MotionOptions, SegmentOptions, SettingInfo, SkeletonOptions,
)
from ._plan import PreparedFit, StagePlan
from ._track import track

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._batch_io import parse_bone_spec
from ._batch_memory import parse_memory

__all__ = [
    "BatchResult", "BodyOptions", "CleanOptions", "FitOptions", "JointOptions", "LabelOptions", "MotionOptions", "PreparedFit",
    "SegmentOptions", "SettingInfo", "SkeletonOptions", "StagePlan", "TrialOutcome", "bone_length", "fit_batch",
    "fit_skeleton", "plot_bone_lengths", "track",
]
