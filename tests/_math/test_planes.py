"""Vectors and 3x3 matrices as tuples of component arrays (jaxskel._math.planes) against
numpy's dense forms."""

from __future__ import annotations

import numpy as np

from jaxskel._math import planes

N = 32


def _vec(a):
    return tuple(np.moveaxis(a, -1, 0))


def _mat(m):
    return tuple(m.reshape(-1, 9).T)


def _dense(t, shape):
    return np.stack(t, axis=-1).reshape(-1, *shape)


def _sym(s):
    return tuple(s[:, i, j] for i, j in planes.UPPER)


def test_vectors_and_general_matrices():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    m, n = rng.normal(size=(N, 3, 3)), rng.normal(size=(N, 3, 3))
    s = rng.uniform(0.5, 2.0, size=N)
    np.testing.assert_allclose(_dense(planes.vadd(_vec(a), _vec(b)), (3,)), a + b)
    np.testing.assert_allclose(_dense(planes.vsub(_vec(a), _vec(b)), (3,)), a - b)
    np.testing.assert_allclose(_dense(planes.vscale(s, _vec(a)), (3,)), s[:, None] * a)
    np.testing.assert_allclose(planes.vdot(_vec(a), _vec(b)), np.sum(a * b, -1), atol=1e-14)
    np.testing.assert_allclose(_dense(planes.vcross(_vec(a), _vec(b)), (3,)), np.cross(a, b), atol=1e-14)
    np.testing.assert_allclose(_dense(planes.mvec(_mat(m), _vec(a)), (3,)), np.einsum("nij,nj->ni", m, a), atol=1e-14)
    np.testing.assert_allclose(_dense(planes.mtvec(_mat(m), _vec(a)), (3,)), np.einsum("nji,nj->ni", m, a), atol=1e-14)
    np.testing.assert_allclose(_dense(planes.mmul(_mat(m), _mat(n)), (3, 3)), m @ n, atol=1e-14)
    mtm = np.swapaxes(m, 1, 2) @ m
    np.testing.assert_allclose(np.stack(planes.mtmul_sym(_mat(m), _mat(m)), -1), np.stack(_sym(mtm), -1), atol=1e-14)
    skew = np.zeros((N, 3, 3))
    skew[:, [2, 0, 1], [1, 2, 0]] = a
    skew[:, [1, 2, 0], [2, 0, 1]] = -a  # [a]x
    np.testing.assert_allclose(_dense(planes.cross_right(_mat(m), _vec(a)), (3, 3)), -m @ skew, atol=1e-14)
    np.testing.assert_allclose(_dense(planes.cross_left(_vec(a), _mat(m)), (3, 3)), skew @ m, atol=1e-14)


def test_symmetric_matrices():
    rng = np.random.default_rng(4)
    g = rng.normal(size=(N, 3, 3))
    sym = g @ np.swapaxes(g, 1, 2) + 0.5 * np.eye(3)
    m, v = rng.normal(size=(N, 3, 3)), rng.normal(size=(N, 3))
    s = _sym(sym)
    np.testing.assert_array_equal(_dense(planes.sym_full(s), (3, 3)), sym)
    np.testing.assert_allclose(_dense(planes.sym_apply(s, _vec(v)), (3,)), np.einsum("nij,nj->ni", sym, v), atol=1e-13)
    np.testing.assert_allclose(_dense(planes.sym_mul(s, _mat(m)), (3, 3)), sym @ m, atol=1e-13)
    inv = _dense(planes.sym_full(planes.sym_inverse(s)), (3, 3))
    np.testing.assert_allclose(inv @ sym, np.broadcast_to(np.eye(3), (N, 3, 3)), atol=1e-12)
