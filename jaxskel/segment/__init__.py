"""Grouping markers into rigid segments (Kirk et al. 2005, sec. 3.1): spectral clustering
of the pairwise-distance standard deviations, the count from the eigengap; and readable
segment names; each group's Procrustes scatter.
"""

from __future__ import annotations

from ._left_out import LeftOut, left_out_markers, still_trials
from ._names import names_from_markers
from ._scatter import marker_scatter
from ._spectral import Segmentation, combine_trials, distance_std, segment_markers

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._names import safe_name, segment_names
from ._scatter import crowded_flags, scatter_flags
from ._spectral import count_singletons, white_noise

__all__ = [
    "LeftOut", "Segmentation", "combine_trials", "distance_std", "left_out_markers", "marker_scatter",
    "names_from_markers", "segment_markers", "still_trials",
]
