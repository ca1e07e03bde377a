"""Bucket sizes: pad shapes to a few sizes so compiled JAX functions are reused.

A jit-compiled function is specialised to its input shapes. Rounding every
frame/marker/pair count up to a bucket keeps the number of distinct shapes
(and therefore compilations, 1-5 s each) small across recordings.
"""

from __future__ import annotations

import math

__all__ = ["bucket_size"]


def bucket_size(n: int, *, minimum: int = 16, steps_per_octave: int = 2) -> int:
    """Smallest bucket >= n.

    Buckets are ``minimum * 2**(k / steps_per_octave)`` rounded up to a multiple
    of 8, so with the default two steps per octave padding wastes at most ~41 %.

    >>> [bucket_size(n) for n in (1, 16, 17, 100, 1000)]
    [16, 16, 24, 128, 1024]
    """
    n = int(n)
    if n < 0:
        raise ValueError(f"size must be >= 0, got {n}")
    if n <= minimum:
        return int(minimum)
    k = math.ceil(steps_per_octave * math.log2(n / minimum) - 1e-9)
    while True:
        size = int(8 * math.ceil(minimum * 2 ** (k / steps_per_octave) / 8))
        if size >= n:
            return size
        k += 1
