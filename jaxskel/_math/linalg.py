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
import numpy as np
from jaxtyping import Array, Float

__all__ = ["cholesky", "spd_solve", "eigvalsh", "eigh", "eigh3", "generalised_eigvalsh"]


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


def _round_robin(n: int) -> np.ndarray:
    """(rounds, n_even / 2, 2) index pairs: every pair of ``range(n_even)`` once, each round a
    set of disjoint pairs (the circle method of a round-robin tournament; ``n_even`` is ``n``
    rounded up to even, the extra index a dummy)."""
    m = n + n % 2
    players = list(range(m))
    rounds = []
    for _ in range(m - 1):
        rounds.append([(players[i], players[m - 1 - i]) for i in range(m // 2)])
        players = [players[0], players[-1], *players[1:-1]]  # fix the first, rotate the rest
    return np.asarray(rounds, dtype=np.int32).reshape(m - 1, m // 2, 2)


def _jacobi(a: Float[Array, "n n"], sweeps: int | None, vectors: bool) -> tuple[Array, Array | None]:
    """Cyclic Jacobi rotations of a symmetric matrix (see :func:`eigvalsh`), a round of
    disjoint pairs at a time.

    Rotations of disjoint pairs ``(p, q)`` touch disjoint rows and columns, so their angles
    (read from ``a_pp``, ``a_qq``, ``a_pq``) and results are those of applying them one
    after another: a round-robin ordering (Brent & Luk 1985) runs a sweep as ``n - 1``
    vectorised rounds instead of ``n (n - 1) / 2`` single rotations. For odd ``n`` the
    matrix is bordered by a zero row and column, which every rotation leaves alone (its
    off-diagonal entries stay zero), and dropped at the end.

    Returns the rotated (diagonal to round-off) matrix and, with ``vectors``, the
    product of the rotations, whose columns are the eigenvectors.
    """
    n = a.shape[-1]
    if sweeps is None:
        sweeps = 8 + int(n - 1).bit_length()
    rounds = jnp.asarray(_round_robin(n))
    size = n + n % 2
    dtype = a.dtype

    def rotate(k, state):
        m, v = state
        p, q = rounds[k % rounds.shape[0], :, 0], rounds[k % rounds.shape[0], :, 1]
        app, aqq, apq = m[p, p], m[q, q], m[p, q]
        small = jnp.abs(apq) <= jnp.finfo(dtype).tiny ** 0.5
        safe = jnp.where(small, 1.0, apq)
        tau = (aqq - app) / (2.0 * safe)
        t = jnp.where(tau >= 0, 1.0, -1.0) / (jnp.abs(tau) + jnp.sqrt(1.0 + tau * tau))
        t = jnp.where(small, 0.0, t)
        c = 1.0 / jnp.sqrt(1.0 + t * t)
        s = t * c
        rp, rq = m[p], m[q]
        m = m.at[p].set(c[:, None] * rp - s[:, None] * rq).at[q].set(s[:, None] * rp + c[:, None] * rq)
        cp, cq = m[:, p], m[:, q]
        m = m.at[:, p].set(c * cp - s * cq).at[:, q].set(s * cp + c * cq)
        if vectors:
            vp, vq = v[:, p], v[:, q]
            v = v.at[:, p].set(c * vp - s * vq).at[:, q].set(s * vp + c * vq)
        return m, v

    sym = jnp.zeros((size, size), dtype).at[:n, :n].set(0.5 * (a + a.T))
    start = (sym, jnp.eye(size, dtype=dtype) if vectors else None)
    m, v = jax.lax.fori_loop(0, sweeps * int(rounds.shape[0]), rotate, start)
    return m[:n, :n], (v[:n, :n] if vectors else None)


def eigvalsh(a: Float[Array, "n n"], sweeps: int | None = None) -> Float[Array, " n"]:
    """Eigenvalues (ascending) of a symmetric matrix by cyclic Jacobi rotations.

    Each rotation ``J(p, q, theta)`` zeroes ``a_pq``: with ``tau = (a_qq - a_pp) / (2 a_pq)``,
    ``t = sign(tau) / (|tau| + sqrt(1 + tau^2))``, ``c = 1 / sqrt(1 + t^2)``, ``s = t c``,
    ``a <- J^T a J``. A sweep visits every pair once, in ``n - 1`` rounds of disjoint
    pairs (:func:`_jacobi`); ``sweeps`` (default ``8 + ceil(log2 n)``) takes the
    off-diagonals of random, graded (eigenvalues over twelve decades) and clustered
    matrices of up to 64 rows to below ``1e-8`` of the matrix's norm (128 rows: ``1e-7``),
    far below what the identifiability thresholds here resolve. Only row/column updates
    and a sort: no LAPACK kernel (see the module docstring). vmap-able.
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



def _null_vector(rows: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """Unit vector orthogonal to the rows of a rank-2 matrix: the longest of the rows' three cross products."""
    c = jnp.stack([jnp.cross(rows[..., 0, :], rows[..., 1, :]), jnp.cross(rows[..., 0, :], rows[..., 2, :]),
                   jnp.cross(rows[..., 1, :], rows[..., 2, :])], axis=-2)
    size = jnp.sum(c * c, axis=-1)
    best = jnp.take_along_axis(c, jnp.argmax(size, axis=-1)[..., None, None], axis=-2)[..., 0, :]
    norm = jnp.sqrt(jnp.max(size, axis=-1))[..., None]
    return best / jnp.where(norm > 0, norm, 1.0)


def eigh3(a: Float[Array, "... 3 3"]) -> tuple[Float[Array, "... 3"], Float[Array, "... 3 3"]]:
    """Eigenvalues (ascending) and eigenvectors (columns, right-handed) of symmetric 3x3 matrices, in closed form.

    Elementwise over the leading axes: no LAPACK kernel and no iteration, for the
    per-frame decompositions of long recordings, where a batched ``eigh`` would dominate.

    Eigenvalues by the trigonometric solution of the characteristic cubic (Smith 1961):
    with ``m = tr(A)/3``, ``p = sqrt(|A - m I|_F^2 / 6)``, ``r = det((A - m I)/p) / 2`` and
    ``phi = acos(r)/3``: ``l_3 = m + 2p cos(phi)``, ``l_1 = m + 2p cos(phi + 2 pi/3)``,
    ``l_2 = 3m - l_1 - l_3``. Eigenvectors: of the two outer eigenvalues, the one farther
    from ``l_2`` is simple; its vector is orthogonal to the rows of ``A - l I`` (the
    longest cross product of two rows). The other two are the eigenvectors of ``A``
    restricted to the plane orthogonal to it, a 2x2 problem solved by the rotation angle
    ``theta = atan2(2 b, a - c) / 2``. So a double eigenvalue gets an orthonormal basis
    of its space and a multiple of the identity gets ``I``. The eigenvalues returned are
    the vectors' Rayleigh quotients ``v^T A v`` (the cubic's roots lose half their digits
    at a double root; the quotients do not), accurate to about ``eps |A|``; an
    eigenvector is as well determined as its eigenvalue is separated.
    """
    a = 0.5 * (a + jnp.swapaxes(a, -1, -2))
    eye = jnp.eye(3, dtype=a.dtype)
    m = jnp.trace(a, axis1=-2, axis2=-1) / 3.0
    b = a - m[..., None, None] * eye
    p = jnp.sqrt(jnp.sum(b * b, axis=(-2, -1)) / 6.0)
    scale = jnp.maximum(jnp.max(jnp.abs(a), axis=(-2, -1)), jnp.finfo(a.dtype).tiny)
    flat = p <= 4.0 * jnp.finfo(a.dtype).eps * scale
    c = b / jnp.where(flat, 1.0, p)[..., None, None]
    det = (c[..., 0, 0] * (c[..., 1, 1] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 1])
           - c[..., 0, 1] * (c[..., 1, 0] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 0])
           + c[..., 0, 2] * (c[..., 1, 0] * c[..., 2, 1] - c[..., 1, 1] * c[..., 2, 0]))
    phi = jnp.arccos(jnp.clip(det / 2.0, -1.0, 1.0)) / 3.0
    high = m + 2.0 * p * jnp.cos(phi)
    low = m + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)
    mid = 3.0 * m - low - high
    # The simple outer eigenvalue's vector, from the rows of A - l I.
    low_simple = (mid - low) >= (high - mid)
    outer = jnp.where(low_simple, low, high)
    e = _null_vector(a - outer[..., None, None] * eye)
    # An orthonormal basis (u, w) of the plane orthogonal to e, and A restricted to it.
    least = eye[jnp.argmin(jnp.abs(e), axis=-1)]
    u = jnp.cross(e, least)
    u = u / jnp.linalg.norm(u, axis=-1, keepdims=True)
    w = jnp.cross(e, u)
    au = jnp.einsum("...ij,...j->...i", a, u)
    aw = jnp.einsum("...ij,...j->...i", a, w)
    theta = 0.5 * jnp.arctan2(2.0 * jnp.sum(u * aw, -1), jnp.sum(u * au, -1) - jnp.sum(w * aw, -1))
    cos, sin = jnp.cos(theta)[..., None], jnp.sin(theta)[..., None]
    larger = cos * u + sin * w  # the larger eigenvalue of the restriction
    smaller = cos * w - sin * u
    v1 = jnp.where(low_simple[..., None], e, smaller)
    v3 = jnp.where(low_simple[..., None], larger, e)
    vecs = jnp.stack([v1, jnp.cross(v3, v1), v3], axis=-1)
    # Rayleigh quotients: the cubic's roots lose half the digits at a double root
    # (acos near +-1); the quotients of the vectors do not.
    vals = jnp.einsum("...ji,...jk,...ki->...i", vecs, a, vecs)
    return jnp.where(flat[..., None], m[..., None], vals), jnp.where(flat[..., None, None], eye, vecs)
