"""jaxskel's per-program XLA options (jaxskel._runtime.compiler_options): applied to its own programs
only, harmless inside a caller's jit and through the saved-program cache, dropped where unknown."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._runtime import compiler_options as co
from jaxskel._runtime import program_cache

# jaxskel's programs run in float64 (jaxskel._runtime.precision), where YNNPACK's fusions are slow.
pytestmark = pytest.mark.usefixtures("float64")


def _angles(v):
    u = v / jnp.linalg.norm(v, axis=-1, keepdims=True)
    return jnp.arctan2(jnp.sum(jnp.cross(u, u[::-1]), -1), jnp.sum(u * u[::-1], -1))


def test_programs_get_the_options_and_the_same_results():
    v = jnp.asarray(np.random.default_rng(0).normal(size=(4096, 2, 3)))
    fast = co.jit(_angles)
    assert fast.__name__ == "_angles" and fast.__wrapped__ is _angles
    np.testing.assert_allclose(np.asarray(fast(v)), np.asarray(jax.jit(_angles)(v)), rtol=1e-12, atol=1e-14)
    assert co.compiler_options() == co.OPTIONS  # this jaxlib knows them
    if jax.default_backend() == "cpu":
        text = fast.lower(v).compile().as_text()
        assert "ynn" not in text.lower()
        # without the options this jaxlib hands the same program to YNNPACK: the option is what changes it
        assert "ynn" in jax.jit(_angles).lower(v).compile().as_text().lower()


def test_inside_a_callers_jit_grad_and_vmap():
    fast = co.jit(_angles)
    v = jnp.asarray(np.random.default_rng(1).normal(size=(5, 8, 3)))
    outer = jax.jit(lambda x: jnp.sum(jax.vmap(fast)(x) ** 2))
    np.testing.assert_allclose(float(outer(v)), float(jnp.sum(jax.vmap(_angles)(v) ** 2)), rtol=1e-12)
    w = jnp.arange(1.0, 9.0)
    g = jax.grad(lambda x: jnp.sum(w * fast(x)))(v[0])
    want = jax.grad(lambda x: jnp.sum(w * _angles(x)))(v[0])
    assert np.abs(np.asarray(want)).max() > 0.1
    np.testing.assert_allclose(np.asarray(g), np.asarray(want), rtol=1e-10, atol=1e-12)


def test_through_the_saved_program_cache(tmp_path):
    fast = co.jit(_angles)
    v = jnp.asarray(np.random.default_rng(2).normal(size=(32, 3)))
    program_cache.set_directory(tmp_path)
    try:
        first = program_cache.call(fast, v)
        assert list(tmp_path.glob("_angles-*.jaxexport")), "the program was not exported"
        program_cache._programs.clear()
        again = program_cache.call(fast, v)  # loaded from the file
    finally:
        program_cache.set_directory(None)
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    np.testing.assert_allclose(np.asarray(first), np.asarray(_angles(v)), rtol=1e-12, atol=1e-14)


def test_an_unknown_option_is_left_out_and_the_known_ones_kept(monkeypatch):
    known = dict(co.OPTIONS)
    monkeypatch.setattr(co, "OPTIONS", {**known, "xla_cpu_no_such_option_anywhere": ""})
    co.compiler_options.cache_clear()
    try:
        assert co.compiler_options() == known
        v = jnp.arange(6.0).reshape(2, 3) + 1.0
        np.testing.assert_allclose(np.asarray(co.jit(_angles)(v)), np.asarray(_angles(v)), atol=1e-12)
        monkeypatch.setattr(co, "OPTIONS", {"xla_cpu_no_such_option_anywhere": ""})
        co.compiler_options.cache_clear()
        assert co.compiler_options() == {}
        np.testing.assert_allclose(np.asarray(co.jit(_angles)(v)), np.asarray(_angles(v)), atol=1e-12)
    finally:
        monkeypatch.undo()
        co.compiler_options.cache_clear()


def test_the_fusion_emitter_option_reaches_xla():
    """XLA refuses a wrong type for an option it knows: the entry is passed to XLA, not dropped on the way."""
    assert co.OPTIONS["xla_cpu_use_fusion_emitters"] is False
    v = jnp.ones((4, 3))
    jax.jit(_angles, compiler_options={"xla_cpu_use_fusion_emitters": False}).lower(v).compile()
    with pytest.raises(Exception, match="(?i)xla_cpu_use_fusion_emitters|bool|invalid|parse"):
        jax.jit(_angles, compiler_options={"xla_cpu_use_fusion_emitters": "not a bool"}).lower(v).compile()
    assert co.jit(_angles).compiler_options == co.compiler_options()


def test_no_global_flags_change():
    before = os.environ.get("XLA_FLAGS")
    co.jit(_angles)(jnp.ones((3, 3)))
    assert os.environ.get("XLA_FLAGS") == before
