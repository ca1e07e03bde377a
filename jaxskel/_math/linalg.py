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

import itertools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["cholesky", "spd_solve", "eigvalsh", "eigh", "generalised_eigvalsh"]


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


def _forward_substitute(low: Float[Array, "n n"], b: Float[Array, "n *m"]) -> Float[Array, "n *m"]:
    """``L^-1 b`` for lower-triangular ``L`` (row by row)."""
    b = jnp.asarray(b, dtype=low.dtype)
    index = jnp.arange(low.shape[-1])

    def row(i, y):
        coef = jnp.where(index < i, low[i], 0.0)
        return y.at[i].set((b[i] - jnp.tensordot(coef, y, axes=1)) / low[i, i])

    return jax.lax.fori_loop(0, low.shape[-1], row, jnp.zeros_like(b))


def spd_solve(a: Float[Array, "n n"], b: Float[Array, "n *m"]) -> Float[Array, "n *m"]:
    """Solve ``a x = b`` for symmetric positive-definite ``a`` by Cholesky and two triangular sweeps."""
    low = cholesky(a)
    n = low.shape[-1]
    index = jnp.arange(n)

    def backward(k, x):  # L^T x = y, from the last row up
        i = n - 1 - k
        col = jnp.where(index > i, low[:, i], 0.0)
        return x.at[i].set((x[i] - jnp.tensordot(col, x, axes=1)) / low[i, i])

    return jax.lax.fori_loop(0, n, backward, _forward_substitute(low, b))  # L y = b, then L^T x = y


def _jacobi(a: Float[Array, "n n"], sweeps: int | None, vectors: bool) -> tuple[Array, Array | None]:
    """Cyclic Jacobi rotations of a symmetric matrix (see :func:`eigvalsh`).

    Returns the rotated (diagonal to round-off) matrix and, with ``vectors``, the
    product of the rotations, whose columns are the eigenvectors.
    """
    n = a.shape[-1]
    if sweeps is None:
        sweeps = 6 + int(n - 1).bit_length()
    pairs = jnp.asarray(list(itertools.combinations(range(n), 2)), dtype=jnp.int32)
    dtype = a.dtype

    def rotate(k, state):
        m, v = state
        p, q = pairs[k % pairs.shape[0], 0], pairs[k % pairs.shape[0], 1]
        app, aqq, apq = m[p, p], m[q, q], m[p, q]
        small = jnp.abs(apq) <= jnp.finfo(dtype).tiny ** 0.5
        safe = jnp.where(small, 1.0, apq)
        tau = (aqq - app) / (2.0 * safe)
        t = jnp.where(tau >= 0, 1.0, -1.0) / (jnp.abs(tau) + jnp.sqrt(1.0 + tau * tau))
        t = jnp.where(small, 0.0, t)
        c = 1.0 / jnp.sqrt(1.0 + t * t)
        s = t * c
        rp, rq = m[p], m[q]
        m = m.at[p].set(c * rp - s * rq).at[q].set(s * rp + c * rq)
        cp, cq = m[:, p], m[:, q]
        m = m.at[:, p].set(c * cp - s * cq).at[:, q].set(s * cp + c * cq)
        if vectors:
            vp, vq = v[:, p], v[:, q]
            v = v.at[:, p].set(c * vp - s * vq).at[:, q].set(s * vp + c * vq)
        return m, v

    start = (0.5 * (a + a.T), jnp.eye(n, dtype=dtype) if vectors else None)
    return jax.lax.fori_loop(0, sweeps * int(pairs.shape[0]), rotate, start)


def eigvalsh(a: Float[Array, "n n"], sweeps: int | None = None) -> Float[Array, " n"]:
    """Eigenvalues (ascending) of a symmetric matrix by cyclic Jacobi rotations.

    Each rotation ``J(p, q, theta)`` zeroes ``a_pq``: with ``tau = (a_qq - a_pp) / (2 a_pq)``,
    ``t = sign(tau) / (|tau| + sqrt(1 + tau^2))``, ``c = 1 / sqrt(1 + t^2)``, ``s = t c``,
    ``a <- J^T a J``. A sweep visits every pair once; convergence is quadratic, so
    ``sweeps`` (default ``6 + ceil(log2 n)``) leaves off-diagonals at round-off for the
    small (n <= a few dozen) matrices used here. Only row/column updates and a sort:
    no LAPACK kernel (see the module docstring). vmap-able.
    """
    a = jnp.asarray(a)
    if a.shape[-1] == 1:
        return a[..., 0]
    return jnp.sort(jnp.diagonal(_jacobi(a, sweeps, vectors=False)[0]))


def eigh(a: Float[Array, "n n"], sweeps: int | None = None) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Eigenvalues (ascending) and eigenvectors (columns) of a symmetric matrix.

    The rotations of :func:`eigvalsh`, accumulated: ``a = V diag(w) V^T`` with
    ``V = J_1 J_2 ...``. No LAPACK kernel. vmap-able.
    """
    a = jnp.asarray(a)
    if a.shape[-1] == 1:
        return a[0], jnp.ones_like(a)
    m, v = _jacobi(a, sweeps, vectors=True)
    w = jnp.diagonal(m)
    order = jnp.argsort(w)
    return w[order], v[:, order]


def generalised_eigvalsh(
    a: Float[Array, "n n"], b: Float[Array, "n n"], ridge: float = 1e-14
) -> Float[Array, " n"]:
    """Eigenvalues (ascending) of ``a v = lambda b v``, ``a`` symmetric, ``b`` positive semi-definite.

    ``b + ridge * max(diag b) I = L L^T`` (Cholesky), then the eigenvalues of the
    symmetric ``L^-1 a L^-T`` (:func:`eigvalsh`). The relative ``ridge`` bounds the
    eigenvalues of directions ``b`` leaves (almost) unmeasured. No LAPACK kernel.
    """
    scale = jnp.maximum(jnp.max(jnp.diagonal(b)), jnp.finfo(b.dtype).tiny)
    low = cholesky(b + ridge * scale * jnp.eye(b.shape[-1], dtype=b.dtype))
    half = _forward_substitute(low, a)  # L^-1 a
    return eigvalsh(_forward_substitute(low, half.T))  # L^-1 (L^-1 a)^T = L^-1 a L^-T
