"""Normalisation and motion parameterisation (Sar Dessai, Hornung & Kobbelt 2006, sec. 3
and 4): default pose, body planes, limb frames; movement filtering, axes by direction
joining, joint angles by circle intersection, twist.
"""

from __future__ import annotations

from ._normalize import Normalization, normalize, normalize_arrays
from ._parameterize import Parameterization, Pose, parameterize, parameterize_arrays

# Used by the other parts of jaxskel (they import a stage through its package, never
# its private modules); not public API.
from ._anatomy import AXIS_COUNTS
from ._normalize import write_normalized
from ._parameterize import write_parameters

__all__ = [
    "Normalization", "Parameterization", "Pose", "normalize", "normalize_arrays", "parameterize",
    "parameterize_arrays",
]
