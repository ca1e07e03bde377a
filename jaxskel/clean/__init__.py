"""Cleaning marker trajectories (Kirk et al. 2005, sec. 3): gap-edge trimming, jump
rejection, duplicates, short runs; and the low-pass filter applied before inverse
kinematics.
"""

from __future__ import annotations

from ._clean import CleaningReport, clean
from ._lowpass import Lowpassed, lowpass_markers

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._lowpass import check_cutoff

__all__ = ["CleaningReport", "Lowpassed", "clean", "lowpass_markers"]
