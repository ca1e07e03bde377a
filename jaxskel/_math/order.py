"""Order statistics of masked arrays without sorting.

A sort of a long recording's frames is one of the slowest XLA:CPU operations
(``O(n log n)`` with data-dependent branches); a median needs only one order
statistic. :func:`kth_smallest` finds it exactly by bisection on the values' bit
patterns: a float's IEEE bits, read as a signed integer and with the magnitude
bits negated for negative numbers, order like the floats. Each of the
``bits`` steps counts the values at or below a key (one pass), so the cost is
``O(bits n)`` elementwise work, vectorised, and the result is the same element a
sort would return.

Host form: :func:`nanquantiles_np`, numpy's ``nanquantile`` along the last axis
without its per-row Python loop.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

__all__ = ["kth_smallest", "masked_median", "nanquantiles_np"]


def _ordered_keys(values: Float[Array, "..."]) -> tuple[Int[Array, "..."], int]:
    """Integer keys that order like ``values`` (-0.0 and +0.0 alike), and their bit width."""
    bits = jnp.finfo(values.dtype).bits
    itype = {64: jnp.int64, 32: jnp.int32, 16: jnp.int16}[bits]
    raw = jax.lax.bitcast_convert_type(values, itype)
    magnitude = raw & jnp.asarray(jnp.iinfo(itype).max, itype)
    return jnp.where(raw < 0, -magnitude, magnitude), bits


def kth_smallest(values: Float[Array, " n"], mask: Bool[Array, " n"], k: Int[Array, ""]) -> Float[Array, ""]:
    """The ``k``-th smallest (0-based) of the masked ``values``, exactly; ``+inf`` when fewer than ``k + 1`` are masked.

    Equal to ``jnp.sort(jnp.where(mask, values, inf))[k]`` for non-NaN values and ``k < n``.
    vmap-able; ``k`` may be traced.
    """
    values = jnp.where(mask, values, jnp.inf)
    keys, bits = _ordered_keys(values)
    k = jnp.asarray(k)

    def bisect(_, bounds):
        lo, hi = bounds  # count(keys <= lo) <= k < count(keys <= hi)
        mid = (lo >> 1) + (hi >> 1) + (lo & hi & 1)
        above = jnp.sum(keys <= mid) > k
        return jnp.where(above, lo, mid), jnp.where(above, mid, hi)

    lo = jnp.min(keys) - 1
    hi = jnp.max(keys)
    _, hi = jax.lax.fori_loop(0, bits, bisect, (lo, hi))
    found = jnp.min(jnp.where(keys >= hi, values, jnp.inf))
    return jnp.where(k < jnp.sum(mask), found, jnp.inf)


def masked_median(values: Float[Array, " n"], mask: Bool[Array, " n"]) -> Float[Array, ""]:
    """The lower median of the masked values (the ``(m - 1) // 2``-th smallest of ``m``), as :func:`kth_smallest`."""
    return kth_smallest(values, mask, jnp.maximum((jnp.sum(mask) - 1) // 2, 0))


def nanquantiles_np(a: Float[np.ndarray, "... n"], q: Float[np.ndarray, " Q"]) -> Float[np.ndarray, "Q ..."]:
    """``np.nanquantile(a, q, axis=-1)`` (the default "linear" method), vectorised over the rows.

    numpy's NaN-aware quantiles along an axis run a Python loop over the rows; here one
    sort sends each row's NaNs to its end, and with ``n`` finite values the quantile
    ``q`` interpolates between the sorted values at ``floor(q (n - 1))`` and the next,
    with numpy's own interpolation formula (so the values are numpy's, bit for bit).
    Rows without a finite value give NaN.
    """
    a = np.asarray(a, dtype=float)
    q = np.asarray(q, dtype=float).reshape(-1)
    ordered = np.sort(a, axis=-1)
    n = a.shape[-1] - np.count_nonzero(np.isnan(ordered), axis=-1)  # (...)
    pos = q.reshape((-1,) + (1,) * n.ndim) * np.maximum(n - 1, 0)  # (Q, ...)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, np.maximum(n - 1, 0))
    t = pos - lo
    per_q = np.broadcast_to(ordered, (q.size, *ordered.shape))
    below = np.take_along_axis(per_q, lo[..., None], axis=-1)[..., 0]
    above = np.take_along_axis(per_q, hi[..., None], axis=-1)[..., 0]
    diff = above - below
    with np.errstate(invalid="ignore"):
        out = np.where(t >= 0.5, above - diff * (1.0 - t), below + diff * t)  # numpy's _lerp
    return np.where(n > 0, out, np.nan)
