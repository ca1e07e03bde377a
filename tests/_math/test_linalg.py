"""Plain-XLA Cholesky solves (jaxskel._math.linalg) against numpy, batched and differentiated."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_rotation

import jaxskel  # noqa: F401  (x64)
from jaxskel._math.linalg import cholesky, spd_solve


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


# ------------------------------------------------------------------ jaxskel._math.rotation
# Moved from tests/test_rigid_ik.py (now tests/skeleton/, whose tests take their references
# from scipy in tests/helpers.py): a unit test of the rotation kit, for tests/_math/. Its
# import is the test's own, so that a kit renamed under it fails this test alone.
def test_horn_alignment_is_a_proper_rotation_even_for_mirrored_clouds():
    """Kabsch's sign correction (det3 of U and V^T) on clouds of 3-6 points: the exact pose
    is recovered, and a mirrored cloud, which the unconstrained SVD solution would fit
    by a reflection (det -1), still gets a rotation. det3 agrees with numpy's LU det."""
    from jaxskel._math.rotation import det3, horn_align

    rng = np.random.default_rng(3)
    m = rng.normal(size=(200, 3, 3))
    np.testing.assert_allclose(np.asarray(det3(jnp.asarray(m))), np.linalg.det(m), rtol=1e-10, atol=1e-12)
    for n in (3, 4, 6):
        src = rng.normal(size=(n, 3))
        rot_true = random_rotation(rng)
        dst = src @ rot_true.T + np.array([0.1, -0.2, 0.3])
        rot, t = (np.asarray(v) for v in horn_align(jnp.asarray(src), jnp.asarray(dst)))
        np.testing.assert_allclose(rot, rot_true, atol=1e-9)
        mirrored = dst * np.array([1.0, 1.0, -1.0])
        rot, _ = (np.asarray(v) for v in horn_align(jnp.asarray(src), jnp.asarray(mirrored)))
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-9)
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
