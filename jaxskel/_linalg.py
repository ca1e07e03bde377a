"""Small dense linear algebra in plain XLA operations (no LAPACK custom calls).

Why not ``jnp.linalg.solve``: on CPU, jaxlib's LAPACK kernels split a batch over
XLA's intra-op thread pool and block until the pieces are done. When two such
kernels run at once on a pool of two threads (a 2-core machine: vmapped solves
inside a while loop, or two executions in flight) each waits for work queued
behind the other and neither ever returns. Native stacks of the hung process
show exactly that (both ``tf_XLAEigen`` workers in ``jax::ParallelBatchMap`` ->
``BlockingCounter::Wait`` under ``lapack_dgetrf_ffi``). The systems in the hot
loops are small (K <= a few dozen unknowns), so a Cholesky written as K
vectorised steps costs little and compiles to ordinary fused loops.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["cholesky", "spd_solve"]


def cholesky(a: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Lower Cholesky factor ``L`` (``a = L L^T``) of a symmetric positive-definite matrix.

    Column by column (Cholesky–Crout): ``L_jj = sqrt(a_jj - sum_k<j L_jk^2)``,
    ``L_ij = (a_ij - sum_k<j L_ik L_jk) / L_jj`` for ``i > j``. A pivot that is not
    positive (round-off on a semi-definite matrix) is clamped to a tiny positive
    value, so the factor stays finite. vmap/grad-able.
    """
    a = jnp.asarray(a)
    n = a.shape[-1]
    index = jnp.arange(n)
    tiny = jnp.finfo(a.dtype).tiny ** 0.5

    def column(j, low):
        row = jnp.where(index < j, low[j], 0.0)  # L[j, :j]
        pivot = jnp.sqrt(jnp.maximum(a[j, j] - row @ row, tiny))
        col = (a[:, j] - low @ row) / pivot
        col = jnp.where(index > j, col, 0.0).at[j].set(pivot)
        return low.at[:, j].set(col)

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(a))


def spd_solve(a: Float[Array, "n n"], b: Float[Array, "n *m"]) -> Float[Array, "n *m"]:
    """Solve ``a x = b`` for symmetric positive-definite ``a`` by Cholesky and two triangular sweeps."""
    low = cholesky(a)
    b = jnp.asarray(b, dtype=low.dtype)
    n = low.shape[-1]
    index = jnp.arange(n)

    def forward(i, y):  # L y = b
        row = jnp.where(index < i, low[i], 0.0)
        return y.at[i].set((b[i] - jnp.tensordot(row, y, axes=1)) / low[i, i])

    def backward(k, x):  # L^T x = y, from the last row up
        i = n - 1 - k
        col = jnp.where(index > i, low[:, i], 0.0)
        return x.at[i].set((x[i] - jnp.tensordot(col, x, axes=1)) / low[i, i])

    y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, n, backward, y)
