"""confirm_merges: the fitted skeleton confirms and corrects label merges (beyond Kirk et al. §4)."""

from __future__ import annotations

import dataclasses
import types
import warnings

import numpy as np
import pytest
from helpers import REAL, partition, quat_to_matrix
from test_relabel import AUTO, _load, assert_no_cooccurring_merge, label_accuracy

import jaxskel
from jaxskel import synth
from jaxskel.relabel._confirm import fragment_offsets, skeleton_link_cost
from jaxskel.relabel._fragments import split_fragments


@pytest.fixture(scope="module")
def fitted_relabelled_body():
    """A relabelled calibration recording, merged from markers, and a skeleton fitted to the merge."""
    body = synth.full_body(seed=1)
    trial, truth = synth.simulate(
        body, motion="calibration", duration=15.0, seed=1, noise=0.002, soft_tissue=0.005,
        gaps=4, ghosts=6, relabel=True,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxskel.ConvergenceWarning)
        result = jaxskel.fit_skeleton(trial, clean_data=False, merge_labels=True, confirm_merges=False)
    return trial, truth, result.label_mapping, result


def _fragment_truth(truth, mapping) -> np.ndarray:
    return np.asarray(truth.physical)[np.asarray(mapping.fragment_label)]


def _misgrouped(result, truth) -> int:
    """Pure merged markers not in the majority true segment of their fitted segment."""
    mapping = result.label_mapping
    tf = _fragment_truth(truth, mapping)
    fp = np.asarray(mapping.fragment_physical)
    column = {lab: i for i, lab in enumerate(result.trial.labels)}
    fitted, true = [], []
    for p in range(mapping.n_physical):
        lab = mapping.physical_labels[p]
        if len(set(tf[fp == p])) == 1 and lab in column:
            fitted.append(int(result.segmentation.marker_segment[column[lab]]))
            true.append(int(truth.marker_segment[np.flatnonzero(mapping.physical == p)[0]]))
    fitted, true = np.array(fitted), np.array(true)
    return int(sum((fitted == g).sum() - np.bincount(true[fitted == g]).max() for g in np.unique(fitted)))


def test_skeleton_confirms_correct_merges(fitted_relabelled_body):
    trial, truth, mapping, result = fitted_relabelled_body
    merged, confirmed = jaxskel.relabel.confirm_merges(trial, mapping, result)
    info = confirmed.diagnostics["skeleton"]
    assert info["applied"] and info["explained_fraction"] > 0.95
    before = label_accuracy(mapping.physical, truth.physical)
    after = label_accuracy(confirmed.physical, truth.physical)
    print(f"synthetic relabelled body: labels right {100 * before:.1f} % -> {100 * after:.1f} %")
    assert after > before and after >= 0.98
    assert_no_cooccurring_merge(trial, confirmed)
    # Every merge is predicted by the skeleton to within noise + soft tissue.
    assert confirmed.link_confirmed is not None and confirmed.link_confirmed.mean() > 0.95
    assert np.isfinite(confirmed.link_error).mean() > 0.9  # judged by the skeleton
    assert np.nanmedian(confirmed.link_error) < 0.006
    assert 0 <= confirmed.link_confidence.min() and confirmed.link_confidence.max() <= 1
    assert np.median(confirmed.link_confidence) > 0.9
    assert merged.n_markers == confirmed.n_physical and not jaxskel.relabel.needs_merging(merged)


def _swap_continuations(phys, start, stop, link_from, link_to, seg, avoid):
    """Markers A, B on one segment, lost at a1 -> b1 and a2 -> b2: A continues as B's b2... and B as A's b1..."""
    for a1, b1 in zip(link_from, link_to):
        for a2, b2 in zip(link_from, link_to):
            big_a, big_b = phys[a1], phys[a2]
            if big_a == big_b or seg[a1] != seg[a2] or {big_a, big_b} & avoid:
                continue
            if start[b2] >= stop[a1] and start[b1] >= stop[a2]:
                out = phys.copy()
                out[(phys == big_a) & (start >= start[b1])] = big_b
                out[(phys == big_b) & (start >= start[b2])] = big_a
                return out, {big_a, big_b}
    raise AssertionError("test setup: no two markers to swap")


def test_skeleton_corrects_wrong_merges(fitted_relabelled_body):
    """Swap the continuations of two pairs of markers on one segment; the skeleton puts them back."""
    trial, truth, mapping, result = fitted_relabelled_body
    tf = _fragment_truth(truth, mapping)
    start, stop = np.asarray(mapping.fragment_start), np.asarray(mapping.fragment_stop)
    seg = np.asarray(truth.marker_segment)[np.asarray(mapping.fragment_label)]
    phys, used = np.asarray(mapping.fragment_physical), set()
    for _ in range(2):
        phys, pair = _swap_continuations(phys, start, stop, mapping.link_from, mapping.link_to, seg, used)
        used |= pair
    chains = [np.flatnonzero(phys == m)[np.argsort(start[phys == m])] for m in np.unique(phys[phys >= 0])]
    link_from = np.concatenate([c[:-1] for c in chains])
    link_to = np.concatenate([c[1:] for c in chains])
    longest = {}
    for k in np.argsort(stop - start):  # a label maps to its longest fragment's marker
        longest[int(mapping.fragment_label[k])] = phys[k]
    wrong = dataclasses.replace(
        mapping, fragment_physical=phys, link_from=link_from, link_to=link_to,
        physical=np.array([longest.get(k, -1) for k in range(mapping.n_labels)]),
    )  # fmt: skip
    assert sum(len(set(tf[phys == m])) > 1 for m in np.unique(phys[phys >= 0])) >= 4  # really wrong now
    _, fixed = jaxskel.relabel.confirm_merges(trial, wrong, result)
    info = fixed.diagnostics["skeleton"]
    assert info["applied"] and info["links_added"] >= 4 and info["fragments_moved"] >= 4
    assert (~fixed.link_confirmed).sum() >= 4  # the corrections are reported as such

    def mixed(fragment_physical):
        return sum(len(set(tf[fragment_physical == m])) > 1 for m in np.unique(fragment_physical[fragment_physical >= 0]))

    # The answer does not depend on the links it was given: the same as from the good mapping.
    _, from_good = jaxskel.relabel.confirm_merges(trial, mapping, result)
    assert partition(range(mapping.n_fragments), fixed.fragment_physical) == partition(
        range(mapping.n_fragments), from_good.fragment_physical
    )
    assert mixed(np.asarray(fixed.fragment_physical)) <= mixed(np.asarray(mapping.fragment_physical))


def test_unexplained_skeleton_leaves_merges_alone(fitted_relabelled_body):
    trial, _, mapping, result = fitted_relabelled_body
    motion = result.motion
    # A skeleton frozen in one pose explains no moving marker.
    still = types.SimpleNamespace(
        rotations=np.broadcast_to(motion.rotations[:1], motion.rotations.shape),
        segment_translations=np.broadcast_to(motion.segment_translations[:1], motion.segment_translations.shape),
        segment_observed=motion.segment_observed,
    )  # fmt: skip
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="explains only"):
        merged, same = jaxskel.relabel.confirm_merges(
            trial, mapping, types.SimpleNamespace(motion=still, skeleton=result.skeleton, trial=result.trial)
        )
    assert not same.diagnostics["skeleton"]["applied"]
    np.testing.assert_array_equal(same.physical, mapping.physical)
    reference, _ = jaxskel.relabel.merge_labels(trial)
    np.testing.assert_array_equal(merged.positions, reference.positions)
    assert merged.labels == reference.labels


@pytest.mark.usefixtures("float64")  # a private JAX function, as its public callers run it
def test_fragment_offsets_match_brute_force():
    rng = np.random.default_rng(0)
    f, k, s = 30, 4, 3
    x = rng.normal(size=(f, k, 3))
    present = rng.random((f, k)) > 0.3
    posed = rng.random((f, s)) > 0.3
    posed[:, 2] = False  # a segment never posed
    q = rng.normal(size=(f, s, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    p = rng.normal(size=(f, s, 3))
    n, offset, mean_sq = (
        np.asarray(a) for a in fragment_offsets(np.where(present[..., None], x, 0.0), present, q, p, posed)
    )
    rot = quat_to_matrix(q)
    for kk in range(k):
        for ss in range(2):
            t = np.flatnonzero(present[:, kk] & posed[:, ss])
            y = np.einsum("tji,tj->ti", rot[t, ss], x[t, kk] - p[t, ss])
            assert n[kk, ss] == t.size
            np.testing.assert_allclose(offset[kk, ss], y.mean(axis=0), atol=1e-10)
            np.testing.assert_allclose(mean_sq[kk, ss], ((y - y.mean(axis=0)) ** 2).sum(axis=1).mean(), atol=1e-9)
    assert (n[:, 2] == 0).all() and np.isinf(mean_sq[:, 2]).all()
    # Two halves of one marker cost ~their offset difference; another marker costs its distance;
    # a fragment that fits the segment worse than its best one pays the excess.
    offsets = np.array([[[0, 0, 0], [0, 0, 0]], [[0, 0, 0.001], [0, 0, 0]], [[0.05, 0, 0], [0, 0, 0]]])
    cost = skeleton_link_cost(offsets, np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]]))
    np.testing.assert_allclose(cost[0, 1], 0.001, atol=1e-12)
    np.testing.assert_allclose(cost[0, 2], 0.05, atol=1e-12)
    cost = skeleton_link_cost(offsets, np.array([[0.0, 1.0], [4e-4, 0.0], [0.0, 1.0]]))
    np.testing.assert_allclose(cost[0, 1], np.sqrt(1e-6 + 4e-4), atol=1e-12)


def test_bad_arguments(fitted_relabelled_body):
    trial, _, mapping, result = fitted_relabelled_body
    with pytest.raises(jaxskel.InputError, match="labels differ"):
        jaxskel.relabel.confirm_merges(trial.select_markers(list(range(5))), mapping, result)
    with pytest.raises(jaxskel.InputError, match="same frames"):
        short = types.SimpleNamespace(rotations=result.motion.rotations[:10])
        jaxskel.relabel.confirm_merges(trial, mapping, dataclasses.replace(result, motion=short))
    with pytest.raises(jaxskel.InputError, match="inverse kinematics"):
        jaxskel.relabel.confirm_merges(trial, mapping, dataclasses.replace(result, motion=None))


@pytest.mark.extended  # about 3 min on 2 cores; the confirmation is tested on synthetic merges by default
@pytest.mark.skipif(not REAL.is_dir(), reason="needs ../shared/data/real")
def test_real_relabelled_recording_is_improved_by_the_skeleton():
    """PronetoRun01 with a new label after every gap: the skeleton rejoins fragments the markers alone lost."""
    trial = _load(AUTO / "PronetoRun01.c3d")
    x, present = trial.to_arrays()
    runs = split_fragments(present, x, np.inf)
    pos = np.full((trial.n_frames, runs.label.size, 3), np.nan)
    for k in range(runs.label.size):
        pos[runs.start[k] : runs.stop[k], k] = trial.positions[runs.start[k] : runs.stop[k], runs.label[k]]
    raw = trial.replace(positions=pos, labels=tuple(f"*{k}" for k in range(runs.label.size)))
    merged, mapping = jaxskel.relabel.merge_labels(raw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxskel.ConvergenceWarning)
        fit = jaxskel.fit_skeleton(merged, merge_labels=False)
    _, confirmed = jaxskel.relabel.confirm_merges(raw, mapping, fit)
    before = label_accuracy(mapping.physical, runs.label)
    after = label_accuracy(confirmed.physical, runs.label)
    print(f"PronetoRun01 relabelled: labels right {100 * before:.1f} % -> {100 * after:.1f} %")
    assert confirmed.diagnostics["skeleton"]["applied"]
    assert after >= before + 0.02 and after >= 0.95
    assert label_accuracy(confirmed.physical, runs.label, weights=runs.length) >= 0.999
    assert confirmed.n_physical == 62
    assert_no_cooccurring_merge(raw, confirmed)


def test_fit_skeleton_confirms_merges_and_refits(fitted_relabelled_body):
    """fit_skeleton(merge_labels=...) runs the confirmation and, when it corrects merges, fits again."""
    trial, truth, mapping, first = fitted_relabelled_body
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxskel.ConvergenceWarning)
        result = jaxskel.fit_skeleton(trial, clean_data=False, merge_labels=True)
    _, expected = jaxskel.relabel.confirm_merges(trial, mapping, first)
    got = result.label_mapping
    assert got.diagnostics["skeleton"]["applied"] and "confirm merges" in result.timings
    assert partition(range(got.n_fragments), got.fragment_physical) == partition(
        range(expected.n_fragments), expected.fragment_physical
    )
    # The refit used the corrected markers: the result's trial is the corrected merge, and its
    # segmentation is at least as right as the first fit's (counted on merged markers made of
    # one true marker's labels).
    assert set(result.trial.labels) == set(got.physical_labels)
    wrong_now, wrong_first = _misgrouped(result, truth), _misgrouped(first, truth)
    print(f"markers grouped apart from their true segment: first fit {wrong_first}, after confirmation {wrong_now}")
    assert wrong_now <= min(wrong_first, 1)
    # Every input label points at the column of its physical marker in the result's trial.
    column = result.physical_input()
    for i in np.flatnonzero(got.physical >= 0):
        assert result.trial.labels[column[i]] == got.physical_labels[got.physical[i]]
    assert result.motion is not None and np.median(result.motion.marker_rms) < 0.008
