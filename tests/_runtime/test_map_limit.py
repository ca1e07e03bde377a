"""jaxskel._runtime.map_limit: a long-lived process is kept under the kernel's limit on memory
mappings (vm.max_map_count), past which XLA dies with a segmentation fault."""

import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxskel
from jaxskel._runtime import map_limit as _map_limit

# The monkeypatches here stand in for the kernel: a process near vm.max_map_count (a
# lower RELEASE_FRACTION, or map_usage returning a count near the limit), or a system
# whose /proc does not say (map_usage returning None); short of exhausting the process's
# mappings, that is the only way to get there. "Said once" is per process, so the once-
# flag is reset for the test, and jax.clear_caches is replaced by a counter where
# dropping the test process's programs is not what is tested.
linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/maps is Linux's")


@linux
def test_dropping_the_programs_unmaps_them_and_is_said_once(monkeypatch):
    monkeypatch.setitem(_map_limit._state, "warned", False)
    f = jax.jit(lambda x: jnp.sin(x) * 2.0 + x.sum())
    for n in range(1, 101):  # 100 programs
        f(jnp.ones(n)).block_until_ready()
    count, limit = _map_limit.map_usage()
    assert 0 < count < limit
    assert not _map_limit.near_map_limit() and not _map_limit.release_programs_near_map_limit()
    assert _map_limit.map_usage()[0] >= count - 50  # nothing dropped below the threshold
    monkeypatch.setattr(_map_limit, "RELEASE_FRACTION", count / limit / 2)  # as if near the limit
    assert _map_limit.near_map_limit()
    with pytest.warns(RuntimeWarning, match="held [0-9,]+ memory mappings.*vm.max_map_count"):
        assert _map_limit.release_programs_near_map_limit()
    after = _map_limit.map_usage()[0]
    assert after < count - 500  # ~12 mappings per program are gone
    np.testing.assert_allclose(f(jnp.ones(3)), np.sin(1.0) * 2 + 3)  # compiled again when called
    monkeypatch.setattr(_map_limit, "RELEASE_FRACTION", 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _map_limit.release_programs_near_map_limit()  # dropped again, said only once


def test_fit_skeleton_drops_the_programs_before_it_fits(monkeypatch):
    monkeypatch.setattr(_map_limit, "map_usage", lambda: (60_000, 65_530))
    monkeypatch.setitem(_map_limit._state, "warned", False)
    cleared = []
    monkeypatch.setattr(jax, "clear_caches", lambda: cleared.append(True))
    few = jaxskel.Trial(positions=np.zeros((50, 2, 3)), labels=["a", "b"], rate=100.0)
    with pytest.warns(RuntimeWarning, match="60,000 memory mappings.*65,530") as caught:
        with pytest.raises(jaxskel.JaxskelError):
            jaxskel.fit_skeleton(few)
    assert cleared == [True]
    assert caught[0].filename == __file__  # pointed at the caller's line


def test_nothing_is_done_where_the_count_is_unknown(monkeypatch):
    monkeypatch.setattr(_map_limit, "map_usage", lambda: None)
    cleared = []
    monkeypatch.setattr(jax, "clear_caches", lambda: cleared.append(True))
    assert not _map_limit.near_map_limit() and not _map_limit.release_programs_near_map_limit()
    assert cleared == []
