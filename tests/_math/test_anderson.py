"""Anderson acceleration (jaxskel._math.anderson) against known answers on linear iterations."""

from __future__ import annotations

import numpy as np
import pytest

from jaxskel._math.anderson import anderson_step


def _slow_linear_map(n: int, seed: int):
    """x <- A x + b with A symmetric, eigenvalues in [0.5, 0.99]: plain iteration needs
    ~2000 steps for 1e-9; its fixed point is (I - A)^-1 b."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    a = q @ np.diag(np.linspace(0.5, 0.99, n)) @ q.T
    b = rng.normal(size=n)
    return (lambda x: a @ x + b), np.linalg.solve(np.eye(n) - a, b)


def _iterate(g, x0, memory: int, steps: int) -> np.ndarray:
    xs, gs, x = [], [], x0
    for _ in range(steps):
        xs, gs = [*xs, x][-(memory + 1):], [*gs, g(x)][-(memory + 1):]
        x = anderson_step(xs, gs)
    return x


def test_memory_beyond_the_dimension_solves_a_linear_iteration_exactly():
    """On a linear map Anderson's iterate is GMRES's: with memory >= n it is exact after n
    + 1 images, where plain iteration (memory 0) has barely moved."""
    g, fixed = _slow_linear_map(4, seed=0)
    x0 = np.zeros(4)
    accelerated = _iterate(g, x0, memory=5, steps=5)
    plain = _iterate(g, x0, memory=0, steps=5)
    assert np.abs(accelerated - fixed).max() < 1e-9 * np.abs(fixed).max()
    assert np.abs(plain - fixed).max() > 0.5 * np.abs(fixed).max()


def test_short_memory_still_converges_much_faster_than_plain_iteration():
    """40 unknowns, memory 5, 60 images: 4e-5 relative error (measured), plain 0.99^60 ~ 0.5."""
    g, fixed = _slow_linear_map(40, seed=1)
    x0 = np.zeros(40)
    err = lambda x: np.abs(x - fixed).max() / np.abs(fixed).max()  # noqa: E731
    assert err(_iterate(g, x0, memory=5, steps=60)) < 1e-4
    assert err(_iterate(g, x0, memory=0, steps=60)) > 0.1


def test_one_pair_is_the_plain_step_and_collinear_history_does_not_blow_up():
    g, _ = _slow_linear_map(3, seed=2)
    x = np.ones(3)
    np.testing.assert_array_equal(anderson_step([x], [g(x)]), g(x))
    # the same pair twice: the residual differences vanish, the step is the plain one
    np.testing.assert_allclose(anderson_step([x, x], [g(x), g(x)]), g(x), rtol=1e-12)
    with pytest.raises(ValueError, match="as many images as iterates"):
        anderson_step([x, x], [g(x)])
