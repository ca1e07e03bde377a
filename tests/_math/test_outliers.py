"""The flag rule shared by the rigid skeleton and the groups' scatter."""

from __future__ import annotations

import numpy as np

from jaxskel._math.outliers import above_median


def test_flags_values_over_both_the_factor_and_the_margin():
    values = np.array([0.002] * 5 + [0.0059, 0.0061, 0.0071, np.nan])  # median 2 mm: flag over 6 mm
    np.testing.assert_array_equal(above_median(values, 3.0, 1e-3), [0] * 6 + [1, 1, 0])
    # a median of 0.2 mm: the margin (over 1.2 mm) decides, not the factor (over 0.6 mm)
    np.testing.assert_array_equal(above_median(values / 10, 3.0, 1e-3), [0] * 9)
    np.testing.assert_array_equal(above_median(values / 10, 3.0, 3e-4), [0] * 6 + [1, 1, 0])


def test_the_margin_keeps_noise_free_values_quiet():
    values = np.array([1e-6, 1e-6, 1e-6, 5e-4])  # 500x the median, but half a millimetre
    assert not above_median(values, 3.0, 1e-3).any()
    assert above_median(values, 3.0, 1e-4)[-1]


def test_no_finite_value_flags_nothing():
    assert above_median(np.full(4, np.nan), 3.0, 1e-3).tolist() == [False] * 4
    assert above_median(np.zeros(0), 3.0, 1e-3).shape == (0,)
