"""Trial: validation, immutability, selection, (x, mask) arrays, padding, up-axis conversion."""

import numpy as np
import pytest

from jaxskel import InputError, Trial
from jaxskel.io import rotation_between_axes


def make(f=10, m=4, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(f, m, 3))
    x[2, 1] = np.nan
    return Trial(x, [f"m{i}" for i in range(m)], 100.0, up_axis="z", source="test")


def test_basic_properties_and_mask():
    t = make()
    assert (t.n_frames, t.n_markers) == (10, 4)
    assert t.duration == pytest.approx(0.1)
    assert t.mask.sum() == 39 and not t.mask[2, 1]
    np.testing.assert_allclose(t.times[:3], [0, 0.01, 0.02])


def test_immutable_and_input_not_aliased():
    x = np.zeros((3, 2, 3))
    t = Trial(x, ["a", "b"], 10)
    x[0, 0, 0] = 5.0  # the caller's array changes...
    assert t.positions[0, 0, 0] == 0.0  # ...the trial does not
    with pytest.raises(ValueError):
        t.positions[0, 0, 0] = 1.0
    with pytest.raises(AttributeError):
        t.rate = 3  # type: ignore[misc]


def test_partial_nan_sample_is_missing_as_a_whole():
    x = np.ones((2, 1, 3))
    x[0, 0, 1] = np.nan
    t = Trial(x, ["a"], 1)
    assert np.isnan(t.positions[0, 0]).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(positions=np.zeros((3, 2)), labels=["a", "b"], rate=1), "shape"),
        (dict(positions=np.zeros((3, 2, 3)), labels=["a"], rate=1), "labels"),
        (dict(positions=np.zeros((3, 2, 3)), labels=["a", "a"], rate=1), "unique"),
        (dict(positions=np.zeros((3, 2, 3)), labels=["a", "b"], rate=0), "positive"),
        (dict(positions=np.full((3, 2, 3), np.inf), labels=["a", "b"], rate=1), "infinite"),
        (dict(positions=np.zeros((3, 2, 3)), labels=["a", "b"], rate=1, up_axis="w"), "up_axis"),
    ],
)
def test_validation_errors(kwargs, match):
    with pytest.raises(InputError, match=match):
        Trial(**kwargs)


def test_selection():
    t = make()
    s = t.select_markers(["m2", "m0"])
    assert s.labels == ("m2", "m0")
    np.testing.assert_array_equal(s.positions, t.positions[:, [2, 0]])
    assert t.drop_markers("m1").labels == ("m0", "m2", "m3")
    assert t[2:5].n_frames == 3
    assert t.between(0.0, 0.05).n_frames == 5
    with pytest.raises(InputError, match="no marker labelled"):
        t.select_markers(["nope"])


def test_selecting_frames_of_combined_trials_keeps_their_bounds_true():
    """``trial_bounds`` (trials fitted together) follow a frame selection: cleaning and IK
    read them, and stale ranges would cut or bridge the wrong frames."""
    from jaxskel.segment import combine_trials

    both = combine_trials([make(10), make(5, seed=1), make(10, seed=2)])
    assert both.metadata["trial_bounds"] == ((0, 10), (10, 15), (15, 25))
    assert both[8:18].metadata["trial_bounds"] == ((0, 2), (2, 7), (7, 10))
    assert both[::7].metadata["trial_bounds"] == ((0, 2), (2, 3), (3, 4))  # frames 0 7 | 14 | 21
    assert both.select_frames(np.r_[12, 3]).metadata["trial_bounds"] == ((0, 1), (1, 2))
    assert "trial_bounds" not in both[2:8].metadata  # one recording
    np.testing.assert_array_equal(both[8:18].positions, both.positions[8:18], strict=True)


def test_arrays_have_no_nan_and_padding_keeps_data():
    t = make()
    x, mask = t.to_arrays()
    assert np.isfinite(x).all() and (x[~mask] == 0).all()
    xp, mp = t.padded()
    assert xp.shape == (16, 8, 3)  # 10 frames, 4 markers: the smallest buckets, 16 and 8
    np.testing.assert_array_equal(xp[:10, :4], x)
    assert mp[:10, :4].sum() == mask.sum() and mp.sum() == mask.sum()
    with pytest.raises(InputError):
        t.padded(n_frames=5)


@pytest.mark.parametrize("src", ["x", "y", "z", "-x", "-y", "-z"])
@pytest.mark.parametrize("dst", ["z", "y", "-z"])
def test_rotation_between_axes_is_proper_and_maps_axis(src, dst):
    axis = dict(zip(("x", "y", "z"), np.eye(3))) | {f"-{k}": -v for k, v in zip(("x", "y", "z"), np.eye(3))}
    r = rotation_between_axes(src, dst)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ axis[src], axis[dst], atol=1e-12)


def test_to_up_axis_preserves_distances():
    t = make().replace(up_axis="y")
    z = t.to_up_axis("z")
    assert z.up_axis == "z"
    d0 = np.linalg.norm(t.positions[:, 0] - t.positions[:, 2], axis=-1)
    d1 = np.linalg.norm(z.positions[:, 0] - z.positions[:, 2], axis=-1)
    np.testing.assert_allclose(d0, d1)
    with pytest.raises(InputError, match="unknown"):
        make().replace(up_axis="unknown").to_up_axis("z")


def test_bucket_sizes_are_few_and_sufficient():
    # the frame counts Trial.padded() rounds up to (its bucket sizes)
    bucket = {n: Trial(np.zeros((n, 1, 3)), ["m"], 100.0).padded()[0].shape[0] for n in range(1, 5000)}
    sizes = set(bucket.values())
    assert all(bucket[n] >= n for n in range(1, 5000))
    assert len(sizes) <= 2 * 9 + 1  # two per octave from 16 to 8192
