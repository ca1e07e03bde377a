"""Reading and writing marker recordings: the Trial, its file formats (C3D, TRC, Cortex
CSV, HDF5), the bundled sample.
"""

from __future__ import annotations

from ._load import infer_up_axis, load, save_trial
from ._report import load_report
from ._sample import load_sample, sample_path
from ._raw import UP_AXES
from ._trial import Trial, rotation_between_axes

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._atomic import atomic_output, input_sources, refuse_input
from ._bounds import available_memory
from ._output_check import check_output, check_writable, image_format
from ._h5_values import put
from ._load import check_load_arguments
from ._raw import median_extent
from ._span import PLAUSIBLE_SPAN, units_problem

__all__ = [
    "Trial", "UP_AXES", "infer_up_axis", "load", "load_report", "load_sample", "rotation_between_axes",
    "sample_path", "save_trial",
]
