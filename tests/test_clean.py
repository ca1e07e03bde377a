"""Cleaning: jump rejection, gap-edge trimming, short-marker dropping, and its report."""

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.segment import combine_trials


def smooth_trial(rate=120.0, seconds=6.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(int(rate * seconds)) / rate
    base = np.stack([0.3 * np.sin(2 * np.pi * 1.3 * t), 0.3 * np.cos(2 * np.pi * 0.7 * t), 1 + 0.1 * t], -1)
    x = base[:, None, :] + np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])[None]
    x = x + rng.normal(0, 0.001, x.shape)
    return x, rate


def test_jumps_are_rejected_and_nothing_else_on_fast_smooth_motion():
    x, rate = smooth_trial()
    x[200:202, 1] += np.array([0.04, 0.0, 0.0])  # a 2-frame, 4 cm jump
    x[400, 2] += np.array([0.0, 0.0, 0.05])  # a 1-frame, 5 cm jump
    trial = jaxskel.Trial(x, ["a", "b", "c", "d"], rate)
    cleaned, report = jaxskel.clean.clean(trial, trim_s=0)
    assert report.jump_samples.tolist() == [0, 2, 1, 0]
    assert not cleaned.mask[200:202, 1].any() and not cleaned.mask[400, 2]
    assert cleaned.mask.sum() == trial.mask.sum() - 3


def test_gap_edges_trimmed_but_not_recording_ends():
    x, rate = smooth_trial()
    x[300:330, 0] = np.nan
    trial = jaxskel.Trial(x, ["a", "b", "c", "d"], rate)
    cleaned, report = jaxskel.clean.clean(trial, trim_s=3 / rate, reject_jumps=False)
    m = cleaned.mask[:, 0]
    assert not m[297:333].any() and m[296] and m[333]
    assert m[0] and m[-1]  # recording boundaries are not gap edges
    assert report.trimmed_samples[0] == 6 and report.trimmed_samples[1:].sum() == 0



def test_trials_fitted_together_are_cleaned_each_on_its_own_frames():
    """The junction of combined trials is neither a jump (the second recording starts 2 m away)
    nor a gap edge, while a real jump and a real gap inside the second trial still are."""
    x, rate = smooth_trial()
    y, _ = smooth_trial(seed=1)
    y = y + np.array([2.0, 0.0, 0.0])
    y[100:102, 1] += np.array([0.04, 0.0, 0.0])
    y[300:330, 0] = np.nan
    labels = ["a", "b", "c", "d"]
    both = combine_trials([jaxskel.Trial(x, labels, rate), jaxskel.Trial(y, labels, rate)])
    cleaned, report = jaxskel.clean.clean(both, trim_s=3 / rate)
    n = len(x)
    assert cleaned.mask[n - 5 : n + 5].all()
    assert report.jump_samples.tolist() == [0, 2, 0, 0]
    assert report.trimmed_samples.tolist() == [6, 6, 0, 0]  # the gap, and the jump's hole
    assert report.longest_run_s[2] == pytest.approx(n / rate)

def test_short_lived_and_absent_markers_dropped_with_reasons():
    x, rate = smooth_trial()
    x[:, 1] = np.nan
    x[10:40, 1] = 0.5  # present for 0.25 s only
    x[:, 3] = np.nan
    trial = jaxskel.Trial(x, ["a", "b", "c", "d"], rate)
    cleaned, report = jaxskel.clean.clean(trial)
    assert cleaned.labels == ("a", "c")
    assert "0.5" in report.dropped["b"] and report.dropped["d"] == "never present"
    assert "dropped b" in report.summary()
    # the input trial is untouched
    assert trial.n_markers == 4 and np.isfinite(trial.positions[10, 1]).all()


def test_synthetic_jumps_found():
    body = synth.full_body(seed=1)
    trial, truth = synth.simulate(body, duration=10.0, seed=1, noise=0.001, jumps=20)
    cleaned, report = jaxskel.clean.clean(trial, trim_s=0)
    jumped = truth.jumped & trial.mask
    big = jumped & (np.linalg.norm(trial.positions - truth.clean_positions, axis=-1) > 0.03)
    removed = trial.mask & ~cleaned.mask
    # at least 90 % of the large jump samples are removed, and few good samples are lost
    assert removed[big].mean() >= 0.9
    assert removed[~jumped].mean() < 0.002


def test_clean_rejects_non_trial():
    with pytest.raises(jaxskel.InputError):
        jaxskel.clean.clean(np.zeros((3, 2, 3)))


def test_a_marker_stored_twice_is_merged_into_its_named_label():
    """HDM05's files carry unnamed copies (``*0``) of named markers. The copy is merged
    into the named label, fills that label's gap, and is reported; markers 2 mm apart
    (closer than any two physical markers, so beyond the tolerance only when it is
    lowered), a copy seen together for under ``duplicate_min_s`` and one that departs
    once are all kept."""
    x, rate = smooth_trial()
    copy = x[:, 1].copy()
    x[300:330, 1] = np.nan  # the named marker's gap, covered by its copy
    near = x[:, 2] + np.array([0.0005, 0.0, 0.0])  # 0.5 mm off marker c
    brief = np.full_like(copy, np.nan)
    brief[:30] = x[:30, 3]  # a copy of d for 0.25 s only
    departs = x[:, 0].copy()
    departs[500] += 0.005  # a copy of a, 5 mm off in one frame
    trial = jaxskel.Trial(np.concatenate([np.stack([copy, near, brief, departs], 1), x], 1),
                          ["*0", "*1", "*2", "*3", "a", "b", "c", "d"], rate)
    cleaned, report = jaxskel.clean.clean(trial, trim_s=0, reject_jumps=False, min_run_s=0)
    assert report.duplicates == {"*0": "b", "*1": "c"}
    assert cleaned.labels == ("*2", "*3", "a", "b", "c", "d")
    b = cleaned.marker_index("b")[0]
    np.testing.assert_array_equal(cleaned.positions[:, b], copy)  # the gap is filled from the copy
    assert report.present_before[5] == len(x) - 30 and report.present_after[5] == len(x)
    assert "duplicate of b" in report.dropped["*0"] and "2 duplicate labels merged" in report.summary()
    # a tighter tolerance than the 0.5 mm offset keeps c's neighbour; 0 disables the step
    assert jaxskel.clean.clean(trial, min_run_s=0, duplicate_tolerance=0.0003)[1].duplicates == {"*0": "b"}
    assert jaxskel.clean.clean(trial, min_run_s=0, duplicate_tolerance=0)[1].duplicates == {}
    # the copy of d is one when its 0.25 s are enough
    assert jaxskel.clean.clean(trial, min_run_s=0, duplicate_min_s=0.2)[1].duplicates["*2"] == "d"
    with pytest.raises(jaxskel.InputError, match="duplicate_tolerance"):
        jaxskel.clean.clean(trial, duplicate_tolerance=-1.0)


def test_duplicates_are_found_whatever_the_marker_order():
    x, rate = smooth_trial()
    trial = jaxskel.Trial(np.concatenate([x, x[:, 2:3]], 1), ["a", "b", "c", "d", "c2"], rate)
    for order in ([0, 1, 2, 3, 4], [4, 3, 2, 1, 0], [2, 4, 0, 3, 1]):
        _, report = jaxskel.clean.clean(trial.select_markers(order))
        # equal sample counts, both named: the first of the two in the given order is kept
        first = "c" if order.index(2) < order.index(4) else "c2"
        assert report.duplicates == {({"c", "c2"} - {first}).pop(): first}


# --- the running-median kernel against a naive reference ---------------------------------

import contextlib  # noqa: E402
import warnings  # noqa: E402

from jaxskel.clean import _clean as clean_module  # noqa: E402


def naive_deviation(x, present, half):
    """The jump test's deviation written out with whole windows and numpy's nanmedian
    (the definition :func:`_running_median_deviation` computes without forming them)."""
    xp = np.where(present[:, None], x, np.nan)
    nan_row = np.full((1, 3), np.nan)
    prev, nxt = np.concatenate([nan_row, xp[:-1]]), np.concatenate([xp[1:], nan_row])
    width, pad = 2 * half + 1, ((half, half), (0, 0))

    def windows(a):
        return np.lib.stride_tricks.sliding_window_view(np.pad(a, pad, constant_values=np.nan), width, axis=0)

    with _quiet():
        v = np.nan_to_num(np.nanmedian(windows(0.5 * (nxt - prev)), axis=-1))
        a = np.nan_to_num(np.nanmedian(windows(nxt - 2.0 * xp + prev), axis=-1))
        k = np.arange(-half, half + 1, dtype=float)
        pred = windows(xp) - k * v[..., None] - 0.5 * k * k * a[..., None]
        pred[..., half] = np.nan
        med = np.nanmedian(pred, axis=-1)
    seen = ~np.isnan(windows(xp)[:, 0, :])
    need = max(1, half // 2)
    two_sided = (seen[:, :half].sum(-1) >= need) & (seen[:, half + 1:].sum(-1) >= need)
    return np.where(two_sided, np.linalg.norm(xp - med, axis=-1), 0.0)


@contextlib.contextmanager
def _quiet():
    """numpy's nanmedian warns on all-NaN windows (inside gaps): expected here."""
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


@pytest.mark.parametrize("width", range(1, 17))
def test_sorting_network_sorts_every_zero_one_input(width):
    # the 0-1 principle: a comparator network that sorts every 0/1 input sorts every input
    bits = (np.arange(2**width)[:, None] >> np.arange(width)[None]) & 1
    wires = bits.astype(float).T.copy()
    for i, j in clean_module._sorting_network(width):
        wires[i], wires[j] = np.minimum(wires[i], wires[j]), np.maximum(wires[i], wires[j])
    assert np.array_equal(wires.T, np.sort(bits, axis=1))


@pytest.mark.parametrize("width", [1, 2, 3, 5, 12, 13, 16])
def test_nanmedian_columns_is_the_sorted_median_exactly(width):
    rng = np.random.default_rng(width)
    values = rng.normal(size=(400, 3, width)).round(1)  # ties on purpose
    values[rng.random(values.shape) < 0.15] = np.nan
    values[:20] = np.nan  # all-NaN windows
    got = clean_module._nanmedian_columns([values[..., j] for j in range(width)])
    with _quiet():
        want = np.nanmedian(values, axis=-1)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(got, clean_module._nanmedian_last(values), equal_nan=True)


@pytest.mark.parametrize("n_frames", [1, 2, 3, 7, 13, 40, 500])
def test_running_median_deviation_matches_the_naive_windows(n_frames):
    rng = np.random.default_rng(n_frames)
    t = np.arange(n_frames) / 120.0
    x = np.stack([np.sin(3 * t), np.cos(2 * t), t], -1)[:, None] + rng.normal(0, 0.002, (n_frames, 5, 3))
    x[rng.integers(0, n_frames, 4), rng.integers(0, 5, 4)] += 0.05  # jumps
    present = rng.random((n_frames, 5)) > 0.1
    present[:, 3] = False  # never seen
    present[n_frames // 3 : n_frames // 3 + 20, 1] = False  # a gap longer than the window
    batched = clean_module._running_median_deviation(x, present, 6)  # every marker at once
    for m in range(5):
        want = naive_deviation(x[:, m], present[:, m], 6)
        assert np.array_equal(batched[:, m], want, equal_nan=True)
        assert np.array_equal(clean_module._running_median_deviation(x[:, m], present[:, m], 6), want, equal_nan=True)
