"""jaxskel's float64 scope (jaxskel._runtime.precision): JAX's 64-bit mode on for one call in
the calling thread, the caller's mode back after it, and left alone under the caller's own
transformations. The test process runs with JAX's defaults (64-bit mode off)."""

import threading
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._runtime.precision import float64, float64_scope


@pytest.fixture(autouse=True)
def _process_in_32_bit_mode():
    assert not jax.config.jax_enable_x64, "something turned JAX's 64-bit mode on for the whole test process"
    yield
    assert not jax.config.jax_enable_x64


@float64_scope
def _default_dtype(x=None):
    """The dtype JAX gives a numpy float64 array here (or ``x``'s, when given)."""
    return jnp.asarray(np.ones(2) if x is None else x).dtype


def test_a_scoped_call_runs_in_float64_and_restores_the_callers_mode():
    assert _default_dtype() == jnp.float64
    assert jnp.asarray(np.ones(2)).dtype == jnp.float32  # the caller's mode, unchanged
    with float64():
        assert jnp.ones(2).dtype == jnp.float64
    assert jnp.ones(2).dtype == jnp.float32


def test_the_callers_mode_is_restored_when_the_call_raises():
    @float64_scope
    def fails():
        assert jax.config.jax_enable_x64
        raise ValueError("inside")

    with pytest.raises(ValueError, match="inside"):
        fails()
    assert not jax.config.jax_enable_x64


def test_float32_arrays_stay_float32_inside_the_scope():
    assert _default_dtype(np.ones(2, np.float32)) == jnp.float32
    assert _default_dtype(jnp.ones(2, jnp.float32)) == jnp.float32


def test_a_callers_transformation_keeps_the_callers_mode():
    """Under the caller's jit, grad or vmap the scope is not entered: the program stays
    float32 throughout (entering it would mix float64 constants into a float32 program)."""

    @float64_scope
    def f(x):
        return x * 2.0 + jnp.ones(x.shape[-1]) + jnp.asarray(np.ones(x.shape[-1]))

    x = jnp.ones(3, jnp.float32)
    jaxpr = str(jax.make_jaxpr(f)(x))
    assert "f64" not in jaxpr and "f32" in jaxpr
    assert jax.jit(f)(x).dtype == jnp.float32
    assert jax.grad(lambda v: f(v).sum())(x).dtype == jnp.float32
    assert jax.vmap(f)(jnp.ones((2, 3), jnp.float32)).dtype == jnp.float32
    assert f(x).dtype == jnp.float64  # called eagerly: the numpy constant is float64 in the scope


def test_threads_do_not_inherit_the_scope_so_scoped_workers_enter_their_own():
    """JAX's mode is per thread: a thread started from inside the scope runs in the
    process's mode. This is why jaxskel's thread-pool workers are scoped themselves."""
    seen = {}

    def unscoped():
        seen["unscoped"] = jnp.asarray(np.ones(2)).dtype

    with float64():
        thread = threading.Thread(target=unscoped)
        thread.start()
        thread.join()
        with ThreadPoolExecutor(2) as pool:
            scoped = list(pool.map(lambda _: _default_dtype(), range(4)))
    assert seen["unscoped"] == jnp.float32
    assert scoped == [jnp.float64] * 4


def test_nested_and_already_on():
    @float64_scope
    def outer():
        inner = _default_dtype()
        return inner, jax.config.jax_enable_x64

    assert outer() == (jnp.float64, True)
    with jax.enable_x64(True):  # a caller that is in float64 already
        assert _default_dtype() == jnp.float64
        assert jax.config.jax_enable_x64
    assert not jax.config.jax_enable_x64


def test_the_wrapper_keeps_name_and_docstring():
    assert _default_dtype.__name__ == "_default_dtype"
    assert _default_dtype.__doc__.startswith("The dtype JAX gives")
