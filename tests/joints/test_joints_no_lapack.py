"""No LAPACK kernel in the joints stage's compiled solves (moved from tests/test_linalg.py):
two LAPACK calls at once deadlock XLA:CPU's thread pool, so the joint solve runs on the
plain-XLA linear algebra of jaxskel._math.linalg (tested there) and must stay free of them."""

import jax
import jax.numpy as jnp
import pytest

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


def test_joint_solver_uses_no_lapack_custom_call():
    """The hot while loop must not contain LAPACK kernels (they deadlock XLA:CPU's 2-thread pool)."""
    from jaxskel.joints._cost_lm import block_solve

    f = jax.jit(block_solve)
    args = (jnp.tile(jnp.eye(3), (4, 1, 1)), jnp.ones((4, 3, 5)), jnp.full(5, 10.0), jnp.ones((4, 3)), jnp.ones(5))
    hlo = f.lower(*args).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo


def test_whole_joint_solve_has_no_lapack_custom_call():
    """No LAPACK kernel anywhere in the compiled joint solve (start, loop, identifiability):
    two at once deadlock XLA:CPU's pool even inside one execution."""
    from jaxskel.joints._cost import _settings, _solve_batch

    settings, controls = _settings("lm", 20, None, None, jnp.float64)
    p, f, k = 2, 16, 4
    args = (jnp.ones((p, f, k, 3)), jnp.ones((p, f, k), bool), jnp.zeros(p), jnp.zeros((p, f, 3)),
            jnp.zeros((p, k)), False, False, controls)
    hlo = _solve_batch.lower(*args, settings=settings).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo


def test_consistency_start_has_no_lapack_custom_call():
    """The four-marker start runs before the solve on the same device (docs/design.md)."""
    from jaxskel.joints._cost_init import consistency_start_batched

    hlo = consistency_start_batched.lower(jnp.ones((2, 16, 4, 3)), jnp.ones((2, 16, 4), bool)).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo
