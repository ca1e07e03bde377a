"""No LAPACK kernel in the inverse kinematics' compiled solver (moved from
tests/test_linalg.py): IK chunks run on several host threads at once, and two LAPACK calls
at once deadlock XLA:CPU's thread pool."""

import jax.numpy as jnp
import pytest

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


def test_ik_solver_uses_no_lapack_custom_call():
    """IK chunks run on several host threads at once: no LAPACK kernels may be in them."""
    import numpy as np

    from jaxskel.skeleton._ik_batch import batch_model, solve_chunk

    edges = np.array([[0, 1], [1, 2]])
    joint_offsets = np.array([[[0.0, 0.0, -0.2], [0.0, 0.0, 0.2]], [[0.0, 0.0, -0.2], [0.0, 0.0, 0.2]]])
    marker_offsets = np.array([[0.05, 0, 0], [0, 0.05, 0], [0.05, 0, 0], [0, 0.05, 0], [0.05, 0, 0], [0, 0.05, 0]])
    model = batch_model(edges, joint_offsets, marker_offsets, np.array([0, 0, 1, 1, 2, 2]))
    b = 4
    q = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (b, 3, 1))
    args = (model, jnp.zeros((b, 6, 3)), jnp.ones((b, 6), bool), jnp.zeros((b, 3)), q, q, jnp.full(3, 1e-3),
            jnp.asarray(True), jnp.asarray(20), jnp.asarray(3))
    hlo = solve_chunk.lower(*args).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo
