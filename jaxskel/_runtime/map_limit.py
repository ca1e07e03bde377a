"""Keep a long-lived process under the kernel's limit on memory mappings.

Every program XLA:CPU compiles lives in memory mappings of its own, and JAX keeps every
program it compiled for the life of the process. Linux caps a process's mappings at
``vm.max_map_count`` (65,530 by default); once a new mapping is refused, XLA dies with a
segmentation fault, not an exception. A process that fits many recordings of different
shapes (a notebook, a training loop, ``fit_batch`` over a large folder, a test suite's
worker) gets there (the counts observed: docs/bench/evidence_from_docstrings.md).

:func:`release_programs_near_map_limit` runs before each fit: past three quarters of the
limit it drops JAX's compiled programs (:func:`jax.clear_caches`, which unmaps them;
later calls compile again) and says so, once per process, in a :class:`RuntimeWarning`
(shown by default, unlike a :class:`ResourceWarning`). Where ``/proc`` does not tell (not
Linux), it does nothing.
"""

from __future__ import annotations

import gc
import warnings
from pathlib import Path

__all__ = ["map_usage", "near_map_limit", "release_programs_near_map_limit"]

#: Fraction of ``vm.max_map_count`` past which JAX's programs are dropped. The last
#: quarter of the limit is headroom for several fits' new programs (mappings per fit:
#: docs/bench/evidence_from_docstrings.md).
RELEASE_FRACTION = 0.75

_state = {"warned": False}


def map_usage() -> tuple[int, int] | None:
    """``(mappings, limit)`` of this process, or ``None`` where ``/proc`` does not say."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text().split()[0])
        with open("/proc/self/maps", "rb") as maps:
            count = sum(1 for _ in maps)
    except (OSError, ValueError, IndexError):
        return None
    return count, limit


def _past_release(usage: tuple[int, int] | None) -> bool:
    return usage is not None and usage[0] >= RELEASE_FRACTION * usage[1]


def near_map_limit() -> bool:
    """Whether this process holds more than ``RELEASE_FRACTION`` of its mapping limit."""
    return _past_release(map_usage())


def release_programs_near_map_limit(*, stacklevel: int = 2) -> bool:
    """Drop JAX's compiled programs if this process nears ``vm.max_map_count``.

    Call it only where no other thread is running JAX code of this package. Returns
    whether the programs were dropped.
    """
    usage = map_usage()
    if not _past_release(usage):
        return False
    import jax

    jax.clear_caches()
    gc.collect()  # the executables go with their last Python reference
    if not _state["warned"]:
        _state["warned"] = True
        after = map_usage()
        now = f"{after[0]:,}" if after else "fewer"
        warnings.warn(
            f"this process held {usage[0]:,} memory mappings, near the kernel's limit of {usage[1]:,} "
            f"(vm.max_map_count), mostly JAX's compiled programs; past the limit XLA crashes. jaxskel "
            f"dropped JAX's compiled programs ({now} mappings now), so the next "
            "fits compile again. To keep them, raise the limit (sysctl -w vm.max_map_count=262144) or fit "
            "recordings of fewer different lengths and marker counts per process.",
            RuntimeWarning,
            stacklevel=stacklevel + 1,
        )
    return True
