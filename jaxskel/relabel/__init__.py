"""Merging the labels of one physical marker (Kirk et al. 2005, sec. 4, passive systems),
and confirming merges against a fitted skeleton.
"""

from __future__ import annotations

from ._confirm import confirm_merges
from ._merge import LabelMapping, merge_labels, needs_merging

__all__ = ["LabelMapping", "confirm_merges", "merge_labels", "needs_merging"]
