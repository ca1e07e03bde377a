"""The whole chain: one fit (fit_skeleton), many trials (fit_batch, optionally on Dask),
from one options object.
"""

from __future__ import annotations

from ._batch import BatchResult, TrialOutcome, fit_batch
from ._batch_io import bone_length, plot_bone_lengths
from ._fit import fit_skeleton

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._batch_io import parse_bone_spec

__all__ = ["BatchResult", "TrialOutcome", "bone_length", "fit_batch", "fit_skeleton", "plot_bone_lengths"]
