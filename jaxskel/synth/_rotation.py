"""Host-side (numpy, float64) rotations for the synthetic-data generator."""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

__all__ = ["rotvec_to_matrix"]


def rotvec_to_matrix(rotvec: Float[np.ndarray, "... 3"]) -> Float[np.ndarray, "... 3 3"]:
    """``exp([r]x)`` for rotation vectors r (axis times angle, radians), by Rodrigues:

        R = I + sin(a) K + (1 - cos(a)) K^2,   a = |r|,  K = [r / a]x.

    The generator stays on the host in float64 on purpose: it is the independent
    reference the JAX code in :mod:`jaxskel._math.rotation` is tested against, and eager
    JAX would compile every operation anew for each trial length.
    """
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1)[..., None, None]
    unit = r / np.where(angle[..., 0] > 0, angle[..., 0], 1.0)
    x, y, z = np.moveaxis(unit, -1, 0)
    zero = np.zeros_like(x)
    k = np.stack(
        [np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2
    )
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
