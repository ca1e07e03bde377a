"""Plain-XLA linear algebra (jaxskel._math.linalg) against numpy/LAPACK: Cholesky solves batched and
differentiated, Jacobi and closed-form 3x3 eigendecompositions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._math.linalg import cholesky, spd_solve

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


def _spd(rng, n, cond=1e6):
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (q * np.geomspace(1.0, 1.0 / cond, n)) @ q.T


def test_cholesky_and_solve_match_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 3, 7, 24):
        a = _spd(rng, n)
        np.testing.assert_allclose(cholesky(jnp.asarray(a)), np.linalg.cholesky(a), atol=1e-12)
        b = rng.normal(size=n)
        np.testing.assert_allclose(spd_solve(jnp.asarray(a), jnp.asarray(b)), np.linalg.solve(a, b), rtol=1e-7)
        bm = rng.normal(size=(n, 4))
        np.testing.assert_allclose(spd_solve(jnp.asarray(a), jnp.asarray(bm)), np.linalg.solve(a, bm), rtol=1e-7)


def test_batched_and_differentiable():
    rng = np.random.default_rng(1)
    a = np.stack([_spd(rng, 5, 100.0) for _ in range(6)])
    b = rng.normal(size=(6, 5))
    x = jax.jit(jax.vmap(spd_solve))(jnp.asarray(a), jnp.asarray(b))
    np.testing.assert_allclose(x, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-9)

    def loss(a0, b0):
        return jnp.sum(spd_solve(a0 @ a0.T + jnp.eye(5), b0) ** 2)

    g_a, g_b = jax.grad(loss, argnums=(0, 1))(jnp.asarray(a[0]), jnp.asarray(b[0]))
    eps = 1e-6
    da = np.zeros((5, 5))
    da[1, 2] = eps
    fd = (loss(a[0] + da, b[0]) - loss(a[0] - da, b[0])) / (2 * eps)
    np.testing.assert_allclose(g_a[1, 2], fd, rtol=1e-5)
    db = np.zeros(5)
    db[3] = eps
    fd = (loss(a[0], b[0] + db) - loss(a[0], b[0] - db)) / (2 * eps)
    np.testing.assert_allclose(g_b[3], fd, rtol=1e-5)


def test_jacobi_eigenvalues_match_numpy():
    from jaxskel._math.linalg import eigvalsh, generalised_eigvalsh

    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 8, 17):
        m = rng.normal(size=(n, n))
        a = m + m.T
        np.testing.assert_allclose(eigvalsh(jnp.asarray(a)), np.linalg.eigvalsh(a), atol=1e-10)
        # repeated and zero eigenvalues
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        d = np.round(rng.normal(size=n)) * (np.arange(n) % 3 > 0)
        a = (q * d) @ q.T
        np.testing.assert_allclose(eigvalsh(jnp.asarray(a)), np.sort(d), atol=1e-10)
        b = _spd(rng, n, 1e4)
        expected = np.sort(np.linalg.eigvals(np.linalg.solve(b, a)).real)
        np.testing.assert_allclose(generalised_eigvalsh(jnp.asarray(a), jnp.asarray(b)), expected, atol=1e-7)
    batch = rng.normal(size=(5, 3, 3))
    batch = batch + np.swapaxes(batch, 1, 2)
    np.testing.assert_allclose(jax.vmap(eigvalsh)(jnp.asarray(batch)), np.linalg.eigvalsh(batch), atol=1e-10)


def test_round_robin_rounds_are_disjoint_and_cover_every_pair_once():
    """The Jacobi sweep's schedule: a round's rotations must touch disjoint rows (so that
    applying them together equals applying them in turn), and a sweep must visit every pair."""
    from jaxskel._math.linalg import _round_robin

    for n in (2, 3, 8, 9, 64):
        rounds = _round_robin(n)
        size = n + n % 2
        assert rounds.shape == (size - 1, size // 2, 2)
        for pairs in rounds:
            assert sorted(pairs.ravel().tolist()) == list(range(size))
        seen = {tuple(sorted(p)) for p in rounds.reshape(-1, 2).tolist()}
        assert len(seen) == rounds.shape[0] * rounds.shape[1] == size * (size - 1) // 2


def test_jacobi_on_a_large_graded_matrix():
    """A group of 60-odd markers gives the identifiability test matrices of that size, with
    eigenvalues over many decades (a joint's directions from undetermined to well fixed)."""
    from jaxskel._math.linalg import eigh, generalised_eigvalsh

    rng = np.random.default_rng(4)
    for n in (63, 64):
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        d = np.logspace(-6, 6, n) * rng.choice([-1.0, 1.0], n)
        a = (q * d) @ q.T
        w, v = (np.asarray(t) for t in eigh(jnp.asarray(a)))
        np.testing.assert_allclose(w, np.sort(d), rtol=1e-9, atol=100 * np.finfo(float).eps * np.abs(d).max())
        np.testing.assert_allclose(v.T @ v, np.eye(n), atol=1e-10)
        b = _spd(rng, n, 1e4)
        expected = np.sort(np.linalg.eigvals(np.linalg.solve(b, a)).real)
        np.testing.assert_allclose(generalised_eigvalsh(jnp.asarray(a), jnp.asarray(b)), expected,
                                   rtol=1e-7, atol=1e-7)


def test_jacobi_eigenvectors_match_numpy():
    from jaxskel._math.linalg import eigh

    rng = np.random.default_rng(3)
    for n in (1, 3, 4, 9):
        m = rng.normal(size=(n, n))
        a = m + m.T
        w, v = (np.asarray(t) for t in eigh(jnp.asarray(a)))
        np.testing.assert_allclose(w, np.linalg.eigvalsh(a), atol=1e-10)
        np.testing.assert_allclose(v.T @ v, np.eye(n), atol=1e-10)
        np.testing.assert_allclose(v @ np.diag(w) @ v.T, a, atol=1e-10)



def _rotations(rng, n):
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    return q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]


@pytest.mark.parametrize(
    "spectrum",
    [None, (1.0, 1.0, 2.0), (1.0, 2.0, 2.0), (3.0, 3.0, 3.0), (0.0, 0.0, 1.0), (1e-12, 1.0, 1.0),
     (1.0, 1.0 + 1e-9, 5.0), (0.0, 1e-6, 1.0), (-2.0, 0.5, 0.5), (1e6, 1e6 + 1.0, 3e6)],
)
def test_closed_form_eigh3_matches_lapack(spectrum):
    """eigh3 against numpy's LAPACK on random and on (nearly) repeated spectra: values to
    eps |A|, a decomposition that rebuilds A, orthonormal right-handed vectors, and the
    vector of every well-separated eigenvalue equal to LAPACK's up to sign."""
    from jaxskel._math.linalg import eigh3

    rng = np.random.default_rng(3)
    if spectrum is None:
        x = rng.normal(size=(4000, 3, 3))
        a = x @ np.swapaxes(x, -1, -2)
    else:
        q = _rotations(rng, 500)
        a = q @ np.diag(spectrum) @ np.swapaxes(q, -1, -2)
    with jax.enable_x64(True):
        vals, vecs = (np.asarray(v) for v in jax.jit(eigh3)(jnp.asarray(a)))
    size = np.abs(a).max(axis=(-2, -1))
    ref_vals, ref_vecs = np.linalg.eigh(a)
    np.testing.assert_array_less(np.abs(vals - ref_vals).max(-1), 20 * np.finfo(float).eps * size)
    rebuilt = np.einsum("...ij,...j,...kj->...ik", vecs, vals, vecs)
    np.testing.assert_array_less(np.abs(rebuilt - a).max(axis=(-2, -1)), 20 * np.finfo(float).eps * size)
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", vecs, vecs), np.broadcast_to(np.eye(3), a.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(vecs), 1.0, atol=1e-12)
    gaps = np.diff(ref_vals, axis=-1)
    far = np.full(len(a), np.inf)
    for k in range(3):
        above = gaps[:, k] if k < 2 else far
        below = gaps[:, k - 1] if k > 0 else far
        separated = np.minimum(above, below) > 1e-3 * size
        cos = np.abs(np.sum(vecs[..., k] * ref_vecs[..., k], -1))
        np.testing.assert_allclose(cos[separated], 1.0, atol=1e-9)
