"""The left-out test's pairwise distances (jaxskel.segment._left_out._pair_distances)."""

import numpy as np
import pytest

from jaxskel.segment._left_out import _pair_distances


@pytest.mark.parametrize("shape", [(1, 1), (7, 2), (60, 46)])
def test_pair_distances_are_numpys_norm_bit_for_bit(shape):
    rng = np.random.default_rng(shape[1])
    x = rng.normal(scale=0.4, size=(*shape, 3))
    x[rng.random(shape) < 0.2] = 0.0  # absent markers sit at the origin there
    want = np.linalg.norm(x[:, :, None, :] - x[:, None, :, :], axis=-1)
    got = _pair_distances(x)
    assert got.shape == shape + (shape[1],)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
    assert np.array_equal(got, got.transpose(0, 2, 1)) and not np.diagonal(got, axis1=1, axis2=2).any()
