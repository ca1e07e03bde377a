"""merge_labels: passive-marker correspondence (Kirk et al. §4) against ground truth and real data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import REAL, horn_align, partition, random_rotation
from scipy.optimize import linear_sum_assignment

import jaxskel
from jaxskel import DegenerateMotionError, InputError, synth
from jaxskel.relabel import needs_merging
from jaxskel.relabel._assign import ChainProblem, spectral_clusters
from jaxskel.relabel._fragments import split_fragments
from jaxskel.relabel._distance import sampled_min_distance

AUTO = REAL / "auto_marker_label"


def label_accuracy(predicted: np.ndarray, truth: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Fraction of labels (optionally weighted) assigned to the right physical marker.

    Predicted markers are matched one-to-one to true ones (Hungarian, maximum
    overlap), so splitting a marker in two or merging two counts as wrong; a
    label is right if its predicted marker is matched to its true marker, or if
    both are -1 (a ghost dropped).
    """
    w = np.ones(truth.size) if weights is None else np.asarray(weights, float)
    pred_ids, true_ids = np.unique(predicted[predicted >= 0]), np.unique(truth[truth >= 0])
    overlap = np.array([[w[(predicted == p) & (truth == t)].sum() for t in true_ids] for p in pred_ids])
    rows, cols = linear_sum_assignment(-overlap)
    right = overlap[rows, cols].sum() + w[(predicted < 0) & (truth < 0)].sum()
    return float(right / w.sum())


def assert_no_cooccurring_merge(trial: jaxskel.Trial, mapping) -> None:
    """No physical marker holds two fragments seen in the same frame."""
    for p in range(mapping.n_physical):
        members = np.flatnonzero(mapping.fragment_physical == p)
        order = members[np.argsort(mapping.fragment_start[members])]
        assert np.all(mapping.fragment_start[order[1:]] >= mapping.fragment_stop[order[:-1]])
    seen = (~np.isnan(trial.positions[..., 0])).astype(int)
    per_marker = np.zeros((trial.n_frames, mapping.n_physical), int)
    for k in range(mapping.n_fragments):
        if mapping.fragment_physical[k] >= 0:
            s, e = mapping.fragment_start[k], mapping.fragment_stop[k]
            per_marker[s:e, mapping.fragment_physical[k]] += seen[s:e, mapping.fragment_label[k]]
    assert per_marker.max() <= 1


@pytest.fixture(scope="module")
def relabelled_body():
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(
        body, motion="walk", duration=10.0, seed=0, noise=0.001, soft_tissue=0.005,
        gaps=3, ghosts=6, relabel=True,
    )  # fmt: skip
    merged, mapping = jaxskel.relabel.merge_labels(trial)
    return body, trial, truth, merged, mapping


def test_synthetic_full_body_labels_merged_to_the_right_marker(relabelled_body):
    body, trial, truth, merged, mapping = relabelled_body
    assert trial.n_markers > 3 * body.n_markers  # really relabelled: ~4 labels per marker plus ghosts
    assert label_accuracy(mapping.physical, truth.physical) >= 0.99
    assert mapping.n_physical == body.n_markers
    # Ghosts (physical -1 in the truth) are the dropped labels.
    assert set(np.flatnonzero(mapping.physical < 0)) == set(np.flatnonzero(truth.physical < 0))
    # The merged trajectories are the true markers' positions wherever seen.
    right = linear_sum_assignment(
        -np.array([[np.sum((mapping.physical == p) & (truth.physical == t)) for t in range(body.n_markers)]
                   for p in range(mapping.n_physical)])
    )[1]  # fmt: skip
    clean = truth.clean_positions[:, np.array([np.flatnonzero(truth.physical == t)[0] for t in right])]
    seen = merged.mask
    seen_true = np.stack([trial.mask[:, truth.physical == t].any(axis=1) for t in right], axis=1)
    np.testing.assert_array_equal(seen, seen_true)  # every sample of every marker is kept
    assert np.abs(merged.positions[seen] - clean[seen]).max() < 0.03  # noise + soft tissue
    # Merged labels are input labels, each physical marker named once.
    assert set(merged.labels) <= set(trial.labels) and len(set(merged.labels)) == merged.n_markers
    assert needs_merging(trial) and not needs_merging(merged)
    for p in range(mapping.n_physical):
        assert set(mapping.members(p)) == {trial.labels[i] for i in np.flatnonzero(mapping.physical == p)}
    assert mapping.link_confidence.min() >= 0 and mapping.link_confidence.max() <= 1
    assert np.median(mapping.link_confidence) > 0.8
    # Kinematic confirmation: each lost marker predicted across its gap (0.05-0.5 s) from
    # its co-moving neighbours lands near where it reappears.
    assert np.isfinite(mapping.link_error).mean() > 0.9
    assert np.nanmedian(mapping.link_error) < 0.015


def test_cooccurring_labels_never_merge(relabelled_body):
    _, trial, _, _, mapping = relabelled_body
    assert_no_cooccurring_merge(trial, mapping)


def test_cannot_link_beats_a_tiny_distance():
    """A duplicate reconstruction 1 mm from a marker, seen with it, must not merge into it."""
    body = synth.full_body(seed=1)
    trial, truth = synth.simulate(body, motion="walk", duration=6.0, seed=1, gaps=1, relabel=True)
    pos = np.array(trial.positions)
    source = int(np.flatnonzero(truth.physical == 3)[0])
    seen = np.flatnonzero(~np.isnan(pos[:, source, 0]))
    duplicate = np.full((trial.n_frames, 1, 3), np.nan)
    span = seen[10:80]  # 70 frames, inside the source's first run
    duplicate[span, 0] = pos[span, source] + 0.001
    dup = trial.replace(positions=np.concatenate([pos, duplicate], axis=1), labels=(*trial.labels, "dup"))
    _, mapping = jaxskel.relabel.merge_labels(dup)
    assert mapping.physical[-1] != mapping.physical[source]
    assert_no_cooccurring_merge(dup, mapping)


def test_invariant_to_label_order_and_rigid_motion(relabelled_body):
    _, trial, _, _, mapping = relabelled_body
    perm = np.random.default_rng(3).permutation(trial.n_markers)
    moved = trial.select_markers(perm).transformed(random_rotation(4), np.array([2.0, -1.0, 0.5]))
    _, moved_mapping = jaxskel.relabel.merge_labels(moved)
    assert partition(moved.labels, moved_mapping.physical) == partition(trial.labels, mapping.physical)


@pytest.mark.usefixtures("float64")  # a private JAX function, as its public callers run it
def test_sampled_distance_matches_brute_force():
    """The tiled coarse kernel equals min over frame pairs of |x_a[i] - A_ab x_b[j]| done naively."""
    rng = np.random.default_rng(0)
    n_samples, n_markers = 11, 9
    base = rng.normal(size=(n_markers, 3))
    rot = np.stack([random_rotation(s) for s in range(n_samples)])
    x = np.einsum("sij,mj->smi", rot, base) + rng.normal(size=(n_samples, 1, 3))
    x += 0.01 * rng.normal(size=x.shape)
    present = rng.random((n_samples, n_markers)) < 0.7
    present[:, :4] = True  # always enough shared markers
    brute = np.full((n_markers, n_markers), np.inf)
    for a in range(n_samples):
        for b in range(n_samples):
            if a == b:
                continue
            r, t = (np.asarray(v) for v in horn_align(x[b], x[a], (present[a] & present[b]).astype(float)))
            d = np.linalg.norm(x[a][:, None] - (x[b] @ r.T + t)[None], axis=-1)
            d[~(present[a][:, None] & present[b][None])] = np.inf
            brute = np.minimum(brute, d)
    # Blocks of 4 samples; padding sample n_samples and marker n_markers are empty.
    xs = np.zeros((n_samples + 1, n_markers + 1, 3))
    ms = np.zeros((n_samples + 1, n_markers + 1), bool)
    xs[:n_samples, :n_markers], ms[:n_samples, :n_markers] = x, present
    blocks = np.full((4, 4), n_samples, np.int32)
    blocks.ravel()[:n_samples] = np.arange(n_samples)
    alive = np.full((4, n_markers + 1), n_markers, np.int32)
    for b in range(3):
        live = np.flatnonzero(ms[blocks[b]].any(axis=0))
        alive[b, : live.size] = live
    pairs = np.array([(a, b) for a in range(3) for b in range(a, 3)] + [(3, 3)], np.int32)
    d, fi, fj = (np.asarray(v) for v in sampled_min_distance(xs, ms, blocks, alive, pairs, min_common=4))
    d = d[:n_markers, :n_markers]
    off_diag = ~np.eye(n_markers, dtype=bool)
    np.testing.assert_allclose(d[off_diag], brute[off_diag], rtol=1e-9, atol=1e-12)
    # The argmin frames reproduce the distance.
    i, j = 2, 7
    a, b = fi[i, j], fj[i, j]
    r, t = (np.asarray(v) for v in horn_align(x[b], x[a], (present[a] & present[b]).astype(float)))
    assert np.isclose(np.linalg.norm(x[a, i] - (r @ x[b, j] + t)), d[i, j])


def test_assignment_is_global_drops_ghosts_and_counts_markers():
    """A1, B1 then A2, B2 (two markers), and a short ghost G seen with A1 and B1."""
    start, stop = np.array([0, 0, 12, 12, 5]), np.array([10, 10, 20, 20, 7])
    d = np.full((5, 5), np.inf)
    d[0, 3] = 0.0005  # A1's nearest is B2, but taking it forces B1 -> A2 (50 mm)
    d[0, 2], d[1, 3], d[1, 2] = 0.001, 0.001, 0.05
    d[4, 2] = d[4, 3] = 0.1
    droppable = np.array([False, False, False, False, True])
    problem = ChainProblem.build(start, stop, d, droppable, drop_cost=0.03, n_max=3, chain_cost=1.0)
    chains = problem.solve()
    assert chains.successor.tolist() == [2, 3, -1, -1, -1] and chains.dropped.tolist() == [0, 0, 0, 0, 1]
    assert chains.n_chains == 2  # n' = 3 markers are seen in frame 5, one is a ghost
    # Forbidding A1 -> A2 costs 48.5 mm more, against its own 1 mm.
    conf = problem.confidence(chains, np.array([[0, 2], [4, 4]]))
    np.testing.assert_allclose(conf[0], 0.0485 / 0.0495)
    # With exactly three markers the ghost becomes the third instead of splitting A or B.
    exact = ChainProblem.build(start, stop, d, droppable, 0.03, n_max=3, chain_cost=1.0, exact=True).solve()
    assert exact.n_chains == 3 and exact.successor.tolist() == [2, 3, -1, -1, -1]


def test_spectral_clusters_separate_markers():
    """Three markers, each seen in three time slots; D ~ 1 mm within a marker, 10 cm across."""
    slot = np.repeat(np.arange(3), 3)  # fragment -> time slot
    marker = np.tile(np.arange(3), 3)  # fragment -> marker
    rng = np.random.default_rng(0)
    d = np.where(marker[:, None] == marker[None], 0.001, 0.1) * (1 + 0.1 * rng.random((9, 9)))
    d = np.minimum(d, d.T)
    labels = spectral_clusters(d, slot[:, None] == slot[None], 3, scale=0.003)
    assert partition(range(9), labels) == partition(range(9), marker)


def test_split_fragments_at_gaps_and_jumps():
    present = np.ones((10, 2), bool)
    present[4, 0] = False
    x = np.zeros((10, 2, 3))
    x[7:, 1, 0] = 1.0  # marker 1 jumps by 1 m between frames 6 and 7
    frags = split_fragments(present, x, max_step=0.1)
    assert frags.label.tolist() == [0, 0, 1, 1]
    assert frags.start.tolist() == [0, 5, 0, 7]
    assert frags.stop.tolist() == [4, 10, 7, 10]


def test_nothing_to_merge_is_identity():
    body = synth.linkage()
    trial, _ = synth.simulate(body, duration=3.0, seed=0, noise=0.001)
    unseen = np.full((trial.n_frames, 1, 3), np.nan)
    with_unseen = trial.replace(
        positions=np.concatenate([trial.positions, unseen], axis=1), labels=(*trial.labels, "x")
    )
    assert not needs_merging(with_unseen)
    merged, mapping = jaxskel.relabel.merge_labels(with_unseen)
    assert merged.labels == trial.labels and mapping.n_physical == trial.n_markers
    np.testing.assert_array_equal(mapping.physical, [*range(trial.n_markers), -1])
    np.testing.assert_array_equal(merged.positions, trial.positions)
    assert mapping.link_from.size == 0
    assert np.all(mapping.confidence[:-1] == 1.0) and np.isnan(mapping.confidence[-1])


def test_exact_marker_count_is_honoured(relabelled_body):
    body, trial, truth, _, mapping = relabelled_body
    _, forced = jaxskel.relabel.merge_labels(trial, n_physical=body.n_markers + 2)
    assert forced.n_physical == body.n_markers + 2
    assert_no_cooccurring_merge(trial, forced)
    with pytest.raises(InputError, match="n_physical"):
        jaxskel.relabel.merge_labels(trial, n_physical=10)


def test_every_marker_lost_at_once_fails_clearly():
    body = synth.linkage()
    trial, _ = synth.simulate(body, duration=4.0, seed=0, gaps=1, relabel=True)
    pos = np.array(trial.positions)
    pos[200:205] = np.nan  # the subject leaves the volume
    with pytest.raises(DegenerateMotionError, match="frame 200"):
        jaxskel.relabel.merge_labels(trial.replace(positions=pos))


def test_too_few_shared_markers_fails_clearly():
    pos = np.random.default_rng(0).normal(size=(100, 4, 3))
    pos[50:, 0] = np.nan  # marker 0 is lost and comes back as marker 3:
    pos[:50, 3] = np.nan  # never four markers to align frames on
    with pytest.raises(DegenerateMotionError, match="no frame has 4 markers"):
        jaxskel.relabel.merge_labels(jaxskel.Trial(pos, list("abcd"), 100.0))


def test_bad_arguments():
    trial = jaxskel.Trial(np.zeros((5, 4, 3)), list("abcd"), 100.0)
    with pytest.raises(InputError, match="Trial"):
        jaxskel.relabel.merge_labels(np.zeros((5, 4, 3)))
    with pytest.raises(InputError, match="sample_interval_s"):
        jaxskel.relabel.merge_labels(trial, sample_interval_s=0.0)
    with pytest.raises(InputError, match="no marker samples"):
        jaxskel.relabel.merge_labels(trial.replace(positions=np.full((5, 4, 3), np.nan)))


# ------------------------------------------------------------------ real data
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="needs ../shared/data/real")


def _load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # these files do not state their units
        return jaxskel.load(path)


@needs_real
def test_real_raw_slots_merge_to_62_rigidly_moving_markers():
    """S01: 76 Vicon slots (205 runs) of the 62-marker set; a slot may hold different markers."""
    trial = _load(AUTO / "S01_Pronetokneel01_mksrem.c3d")
    merged, mapping = jaxskel.relabel.merge_labels(trial)
    assert mapping.n_fragments > 200  # slots cut at every gap
    assert mapping.n_physical == 62
    assert_no_cooccurring_merge(trial, mapping)
    # A wrong merge moves a marker to another segment, where nothing keeps a constant distance
    # to it. In the labelled recordings of this marker set every marker has two partners
    # whose distance varies by less than 13 mm (std); so must the merged markers.
    assert _second_rigid_partner_std(merged).max() < 0.02
    assert _second_rigid_partner_std(_load(AUTO / "PronetoRun01.c3d")).max() < 0.02


def _second_rigid_partner_std(trial) -> np.ndarray:
    pos = trial.positions
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    shared = (~np.isnan(d)).sum(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        spread = np.nanstd(d, axis=0)
    spread[(shared < 50) | np.eye(trial.n_markers, dtype=bool)] = np.inf
    return np.sort(spread, axis=1)[:, 1]


@needs_real
def test_real_labelled_recording_relabelled_after_every_gap():
    """PronetoRun01 (labelled, 124 runs over 62 markers): give every run a new label and merge back."""
    trial = _load(AUTO / "PronetoRun01.c3d")
    x, present = trial.to_arrays()
    runs = split_fragments(present, x, np.inf)
    pos = np.full((trial.n_frames, runs.label.size, 3), np.nan)
    for k in range(runs.label.size):
        pos[runs.start[k] : runs.stop[k], k] = trial.positions[runs.start[k] : runs.stop[k], runs.label[k]]
    raw = trial.replace(positions=pos, labels=tuple(f"*{k}" for k in range(runs.label.size)))
    merged, mapping = jaxskel.relabel.merge_labels(raw)
    assert mapping.n_physical == 62
    assert_no_cooccurring_merge(raw, mapping)
    # Weighted by samples: the last 30 frames (the subject runs off, 10-20 markers lost at
    # once, runs of 1-10 frames) hold the few hard cases. (One "error" is the source's own:
    # LSHPP ends at frame 1248 and LSHPA continues it 0.2 mm away.)
    assert label_accuracy(mapping.physical, runs.label, weights=runs.length) >= 0.995
    assert label_accuracy(mapping.physical, runs.label) >= 0.9


@needs_real
def test_real_unlabelled_trajectories_of_a_gait_trial():
    """pyCGM Movement_trial: 42 unlabelled '*' trajectories beside the 39 labelled markers."""
    trial = _load(REAL / "pycgm" / "Movement_trial.c3d")
    stars = trial.select_markers([lab for lab in trial.labels if lab.startswith("*")])
    assert stars.n_markers == 42
    merged, mapping = jaxskel.relabel.merge_labels(stars)
    assert mapping.n_physical == 39
    # *127 and *145 come back after gaps under the same slot and are rejoined; *153 (78
    # frames in 46 pieces, far from the body), *155 (12 frames) and *156 (7) are ghosts.
    dropped = {mapping.labels[i] for i in np.flatnonzero(mapping.physical < 0)}
    assert dropped == {"*153", "*155", "*156"}
    assert_no_cooccurring_merge(stars, mapping)
