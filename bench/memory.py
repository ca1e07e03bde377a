"""Peak memory of a block of code: host RSS sampled by a thread, plus JAX device statistics.

``ru_maxrss`` only ever grows, so it cannot attribute a peak to one phase of a
process that runs jaxskel and the reference one after the other. :class:`PeakRSS`
samples ``/proc/self/statm`` every ``interval`` seconds while the block runs and
reports the largest resident set seen (MB) and the one at the start; peaks shorter
than the interval can be missed. Off Linux it falls back to ``ru_maxrss``. Device
memory (``jax.Device.memory_stats()["peak_bytes_in_use"]``) is reported where the
backend keeps it (GPUs; the CPU backend returns nothing).
"""

from __future__ import annotations

import os
import resource
import threading
import time

__all__ = ["PeakRSS", "device_peak_mb", "rss_mb"]

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class PeakRSS:
    """Context manager: ``.peak_mb`` and ``.start_mb`` of the host RSS while the block ran."""

    def __init__(self, interval: float = 0.02):
        self.interval = interval
        self.start_mb = self.peak_mb = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _watch(self) -> None:
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, rss_mb())
            time.sleep(self.interval)

    def __enter__(self) -> "PeakRSS":
        self.start_mb = self.peak_mb = rss_mb()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.peak_mb = max(self.peak_mb, rss_mb())

    def as_dict(self) -> dict[str, float]:
        return {"peak_rss_mb": round(self.peak_mb, 1), "start_rss_mb": round(self.start_mb, 1)}


def device_peak_mb() -> float | None:
    """Peak bytes in use on the default JAX device (MB), or None where the backend does not say."""
    import jax

    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - backends without statistics raise various errors
        return None
    if not stats or "peak_bytes_in_use" not in stats:
        return None
    return round(stats["peak_bytes_in_use"] / 2**20, 1)
