"""Exact order statistics without a sort (jaxskel._math.order) against numpy's sort."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxskel._math.order import kth_smallest, masked_median


def test_kth_smallest_equals_the_sorted_element():
    """kth_smallest against a sort, for float64 and float32, with ties, signed zeros,
    infinities, masks and k past the masked count; and under vmap with a traced k."""
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        f = jax.jit(kth_smallest)
        for dtype in (np.float64, np.float32):
            for trial in range(150):
                n = int(rng.integers(1, 50))
                v = (rng.normal(size=n) * 10.0 ** rng.integers(-30, 30)).astype(dtype)
                if trial % 3 == 0:
                    v = np.round(v)
                if trial % 5 == 0:
                    v[: n // 2] = -0.0
                if trial % 7 == 0:
                    v[0] = -np.inf
                mask = rng.random(n) < 0.7
                k = int(rng.integers(0, n + 2))
                got = float(f(jnp.asarray(v), jnp.asarray(mask), k))
                want = float(np.sort(np.where(mask, v, np.inf))[k]) if k < mask.sum() else np.inf
                assert got == want, (v, mask, k, got, want)
        v = rng.normal(size=(6, 101))
        mask = rng.random(101) < 0.6
        med = jax.vmap(masked_median, (0, None))(jnp.asarray(v), jnp.asarray(mask))
        m = int(mask.sum())
        np.testing.assert_array_equal(np.asarray(med), np.sort(v[:, mask], axis=1)[:, (m - 1) // 2])


def test_nanquantiles_equal_numpys_bit_for_bit():
    """The host form against np.nanquantile (linear method) along rows: NaNs, all-NaN rows,
    one finite value, ties, magnitudes from 1e-5 to 1e5, quantiles 0 to 1."""
    import warnings

    from jaxskel._math.order import nanquantiles_np

    rng = np.random.default_rng(5)
    q = np.array([0.0, 0.25, 1 / 3, 0.5, 0.75, 1.0])
    for trial in range(1000):
        m, n = int(rng.integers(1, 8)), int(rng.integers(1, 12))
        a = rng.normal(size=(m, n)) * 10.0 ** rng.integers(-5, 6)
        a[rng.random((m, n)) < 0.3] = np.nan
        if trial % 7 == 0:
            a[0] = np.nan
        if trial % 5 == 0:
            a = np.round(a)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # numpy warns on all-NaN rows
            want = np.nanquantile(a, q, axis=1)
        np.testing.assert_array_equal(nanquantiles_np(a, q), want)
