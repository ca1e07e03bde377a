"""Values far above their median: the rule that flags a marker as not rigidly attached.

A value is flagged when it exceeds ``factor`` times the median of the finite values and
the median by ``margin`` as well. The margin keeps a noise-free recording, whose median
is near zero, from flagging markers that are only a fraction of a millimetre apart. The
rigid skeleton applies the rule to its markers' residual RMS
(:mod:`jaxskel.skeleton._rigid_fit`), and the segmentation to each group's Procrustes
scatter (:mod:`jaxskel.segment._scatter`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["above_median"]


def above_median(values: np.ndarray, factor: float, margin: float) -> np.ndarray:
    """Boolean mask of ``values > factor * median`` and ``values > median + margin``, the
    median taken over the finite values; ``False`` where a value is NaN, and everywhere
    when none is finite."""
    values = np.asarray(values, dtype=float)
    known = np.isfinite(values)
    if not known.any():
        return np.zeros(values.shape, dtype=bool)
    median = float(np.median(values[known]))
    return (values > factor * median) & (values > median + margin)  # NaN compares False
