"""Anderson acceleration of a fixed-point iteration ``x <- G(x)`` (host side, small x).

Given the last ``m + 1`` iterates ``x_i`` and their images ``g_i = G(x_i)``, with residuals
``f_i = g_i - x_i``, the next iterate is the image of the affine combination of the
iterates whose residual is smallest:

    gamma = argmin_gamma || f_k - dF gamma ||,   x_{k+1} = g_k - dG gamma,

with ``dF``, ``dG`` the successive differences of the ``f_i`` and ``g_i`` (Walker & Ni
2011, "Anderson acceleration for fixed-point iterations", the "type II" form). On a linear
iteration it is GMRES on ``(I - G) x = 0``, so a slow linear rate (eigenvalues of ``G``'s
Jacobian near 1) is cured along the few directions that cause it. Used by the rigid
refinement (:mod:`jaxskel.skeleton._rigid_fit`), whose alternation between poses and offsets is such
an iteration.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["anderson_step"]


def anderson_step(iterates: Sequence[np.ndarray], images: Sequence[np.ndarray]) -> np.ndarray:
    """The next iterate from ``iterates`` ``x_i`` and ``images`` ``G(x_i)`` (oldest first).

    With one pair this is the plain step ``G(x)``. The least squares is solved by SVD with
    a relative cut-off (1e-10), so nearly collinear residual differences (an iteration that
    has converged along most directions) do not blow the step up.
    """
    if len(iterates) != len(images) or not len(iterates):
        raise ValueError("anderson_step needs as many images as iterates, at least one")
    g = np.stack([np.ravel(v) for v in images], axis=1)
    if g.shape[1] == 1:
        return g[:, 0].copy()
    f = g - np.stack([np.ravel(v) for v in iterates], axis=1)
    d_f, d_g = np.diff(f, axis=1), np.diff(g, axis=1)
    gamma = np.linalg.lstsq(d_f, f[:, -1], rcond=1e-10)[0]
    return g[:, -1] - d_g @ gamma
