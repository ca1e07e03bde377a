"""The automatic segment count's growth past the eigengap (`segment._spectral.grow_count`)."""

import numpy as np
import pytest

from jaxskel.segment._spectral import grow_count

MM = 1e-3
LIMIT = 18 * MM


def _stds() -> np.ndarray:
    """Distance stds of 8 markers on 4 two-marker segments a b c d: a-b 50 mm apart, b-c
    40, c-d 30; d's two markers 25 mm (a marker that swings: over the 18 mm limit)."""
    seg = np.repeat(np.arange(4), 2)
    apart = np.array([[0, 50, 50, 50], [50, 0, 40, 40], [50, 40, 0, 30], [50, 40, 30, 0]]) * MM
    a = apart[seg][:, seg] + np.where(seg[:, None] == seg[None, :], 1 * MM, 0.0)
    a[6, 7] = a[7, 6] = 25 * MM
    np.fill_diagonal(a, 0.0)
    return a


EIGENGAP = [0, 0, 0, 0, 1, 1, 1, 1]  # a-b and c-d together: 50 mm
CASES = {
    # 3 splits a from b (c-d left: 30 mm), 4 c from d (d's own 25 mm left), 5 is rigid but leaves
    # d's markers alone: 4, the most rigid before it, is taken and 5 reported
    "most rigid before a rigid count that leaves markers alone": (
        {3: [0, 0, 1, 1, 2, 2, 2, 2], 4: [0, 0, 1, 1, 2, 2, 3, 3], 5: [0, 0, 1, 1, 2, 2, 3, 4]}, 8,
        ("most rigid", 5, [2, 3, 4, 5], [0, 0, 1, 1, 2, 2, 3, 3]),
    ),
    # 3 and 4 are more rigid (40, 30 mm) only by leaving d's second marker alone: the eigengap's
    # count is kept, 5 reported
    "no count that leaves a marker alone": (
        {3: [0, 0, 1, 1, 1, 1, 1, 2], 4: [0, 0, 1, 1, 2, 2, 2, 3], 5: [0, 0, 1, 1, 2, 2, 3, 4]}, 8,
        ("eigengap", 5, [2, 3, 4, 5], EIGENGAP),
    ),
    # no count up to 4 is rigid; 3 (c and d together) and 4 (c and d crossed in two groups) both
    # hold 30 mm: the smaller is taken, no rigid count reported
    "without a rigid count, the smaller on a tie": (
        {3: [0, 0, 1, 1, 2, 2, 2, 2], 4: [0, 0, 1, 1, 2, 3, 2, 3]}, 4,
        ("most rigid", 0, [2, 3, 4], [0, 0, 1, 1, 2, 2, 2, 2]),
    ),
}


@pytest.mark.parametrize("case", CASES)
def test_growth_past_a_non_rigid_eigengap_count(case):
    grown, n_max, (rule, rigid_count, calls, labels) = CASES[case]
    by_count = {2: EIGENGAP, **grown}
    asked = []

    def cluster(n: int):
        asked.append(n)
        return np.asarray(by_count[n]), [float(n)], 0

    got_rule, got_labels, scores, _, got_rigid_count = grow_count(2, cluster, _stds(), LIMIT, n_max)
    assert (got_rule, got_rigid_count, asked) == (rule, rigid_count, calls)
    np.testing.assert_array_equal(got_labels, labels)
    assert scores == [float(len(set(labels)))]  # the chosen count's own scores


def test_a_rigid_eigengap_count_is_kept_without_growing():
    a = _stds()
    a[6, 7] = a[7, 6] = 1 * MM
    asked = []

    def cluster(n: int):
        asked.append(n)
        return np.asarray([0, 0, 1, 1, 2, 2, 2, 2]), [0.0], 0

    rule, _, _, _, rigid_count = grow_count(3, cluster, a, 35 * MM, 8)
    assert (rule, rigid_count, asked) == ("eigengap", 0, [3])
