"""Anderson acceleration of a fixed-point iteration ``x <- G(x)`` (small x).

Given the last ``m + 1`` iterates ``x_i`` and their images ``g_i = G(x_i)``, with residuals
``f_i = g_i - x_i``, the next iterate is the image of the affine combination of the
iterates whose residual is smallest:

    gamma = argmin_gamma || f_k - dF gamma ||,   x_{k+1} = g_k - dG gamma,

with ``dF``, ``dG`` the successive differences of the ``f_i`` and ``g_i`` (Walker & Ni
2011, "Anderson acceleration for fixed-point iterations", the "type II" form). On a linear
iteration it is GMRES on ``(I - G) x = 0``, so a slow linear rate (eigenvalues of ``G``'s
Jacobian near 1) is cured along the few directions that cause it. Used by the rigid
refinement (:mod:`jaxskel.skeleton._rigid_sweeps`), whose alternation between poses and offsets is such
an iteration.

:func:`anderson_step` takes host lists; :func:`anderson_step_buffered` is the same step on
a fixed-size history buffer with a count of valid rows, for a traced loop.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

__all__ = ["RCOND", "anderson_step", "anderson_step_buffered"]

#: Relative cut-off of the singular values in the least squares for ``gamma``.
RCOND = 1e-10


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
    gamma = np.linalg.lstsq(d_f, f[:, -1], rcond=RCOND)[0]
    return g[:, -1] - d_g @ gamma


def anderson_step_buffered(
    iterates: Float[Array, "H N"], images: Float[Array, "H N"], count: Int[Array, ""]
) -> Float[Array, " N"]:
    """:func:`anderson_step` on a history buffer (jittable): rows oldest first, the newest
    last, and only the last ``count`` rows (1 <= count <= H) valid.

    The differences that involve an invalid row are zeroed; a zero column of ``dF`` gets
    a zero ``gamma`` in the minimum-norm least squares (its singular value is cut), so the
    step equals :func:`anderson_step` on the valid rows. Solved by a thin SVD with the same
    relative cut-off (:data:`RCOND`).
    """
    g = images
    f = images - iterates
    n_hist = g.shape[0]
    valid = (jnp.arange(n_hist - 1) >= n_hist - count)[:, None]  # difference i uses rows i, i + 1
    d_f = jnp.where(valid, f[1:] - f[:-1], 0.0).T  # (N, H - 1)
    d_g = jnp.where(valid, g[1:] - g[:-1], 0.0).T
    u, s, vt = jnp.linalg.svd(d_f, full_matrices=False)
    keep = (s > RCOND * s[0]) & (s > 0)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    gamma = vt.T @ (inv * (u.T @ f[-1]))
    return g[-1] - d_g @ gamma
