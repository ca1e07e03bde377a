"""The groups' Procrustes scatter (:func:`jaxskel.segment.marker_scatter`) and its flags:
rigid groups at the noise, a joined pair of segments flagged on its smaller part."""

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel._runtime.precision import float64
from jaxskel.segment import crowded_flags, marker_scatter, scatter_flags


def _scatter(trial, segment):
    with float64():
        return marker_scatter(trial.positions, segment)


@pytest.fixture(scope="module")
def tree():
    return synth.simulate(synth.random_tree(8, seed=1), duration=10.0, seed=1, noise=0.001, gaps=2)


@pytest.fixture(scope="module")
def linkage():
    # three rods, three markers each, turning by two universal joints; 1 mm noise, gaps
    return synth.simulate(synth.linkage(), duration=10.0, seed=4, noise=0.001, gaps=2)


def test_rigid_groups_scatter_at_the_noise_and_nothing_is_flagged(linkage):
    trial, truth = linkage
    scatter = _scatter(trial, truth.marker_segment)
    # white noise of 1 mm per coordinate: about sqrt(3 * (K - 1) / K) mm about a K-point mean shape
    assert np.all((scatter > 0.8e-3) & (scatter < 2.0e-3)), scatter
    assert not scatter_flags(scatter).any()
    assert crowded_flags(truth.marker_segment, scatter_flags(scatter)).size == 0


def test_noise_free_rigid_groups_scatter_nothing():
    trial, truth = synth.simulate(synth.linkage(), duration=5.0, seed=1, noise=0.0)
    assert np.nanmax(_scatter(trial, truth.marker_segment)) < 1e-7


@pytest.mark.parametrize("pair", range(7))
def test_two_segments_in_one_group_flag_the_markers_of_the_joined_pair(tree, pair):
    """Each joint of a random 8-segment tree in turn: its two segments as one group."""
    trial, truth = tree
    parent, child = truth.edges[pair]
    joined = np.where(truth.marker_segment == child, parent, truth.marker_segment)
    scatter = _scatter(trial, joined)
    flags = scatter_flags(scatter)
    assert flags.sum() >= 2 and set(joined[flags]) == {parent}
    # one rigid pose per frame cannot follow both segments: their markers stray by centimetres
    assert np.nanmedian(scatter[joined == parent]) > 5 * np.nanmax(scatter[joined != parent])
    assert np.array_equal(crowded_flags(joined, flags), np.flatnonzero(flags))


def test_scatter_is_unchanged_by_a_rigid_motion_of_the_recording(linkage):
    trial, truth = linkage
    joined = np.where(truth.marker_segment == 2, 1, truth.marker_segment)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    moved = trial.transformed(rot, np.array([3.0, -1.0, 0.5]))
    assert np.allclose(_scatter(moved, joined), _scatter(trial, joined), atol=1e-9, equal_nan=True)


def test_small_groups_and_left_out_markers_have_no_scatter(linkage):
    trial, truth = linkage
    segment = truth.marker_segment.copy()
    two = np.flatnonzero(segment == 0)[:2]
    segment[np.flatnonzero(segment == 0)[2]] = -1  # rod 0: two markers left in its group, one left out
    scatter = _scatter(trial, segment)
    assert np.isnan(scatter[segment == -1]).all() and np.isnan(scatter[two]).all()
    assert np.isfinite(scatter[segment > 0]).all()
    assert not scatter_flags(np.full(4, np.nan)).any()


def test_a_lone_flag_or_a_group_of_two_is_not_crowded():
    segment = np.array([0, 0, 0, 1, 1, 2, 2, 2, -1])
    flags = np.array([1, 1, 0, 1, 1, 1, 0, 0, 1], dtype=bool)
    # group 0: two flags among three (crowded); group 1: a pair; group 2: one flag; -1: left out
    assert crowded_flags(segment, flags).tolist() == [0, 1]


def test_bad_input_is_a_typed_error_that_says_what_to_pass(linkage):
    trial, truth = linkage
    with pytest.raises(jaxskel.InputError, match="positions must be"):
        marker_scatter(trial.positions[..., :2], truth.marker_segment)
    with pytest.raises(jaxskel.InputError, match="one integer group per marker"):
        marker_scatter(trial.positions, truth.marker_segment[:-1])
    with pytest.raises(jaxskel.InputError, match="one integer group per marker"):
        marker_scatter(trial.positions, truth.marker_segment.astype(float))
