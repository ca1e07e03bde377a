"""Marker segmentation (Kirk et al. §3.1) against synthetic ground truth."""

import dataclasses
import warnings

import numpy as np
import pytest
from helpers import (
    linkage_with_a_bending_marker,
    marker_artefact,
    markers_on_joints,
    partition,
    random_rotation,
    same_grouping_up_to_joint_markers,
    true_partition,
)

import jaxskel
from jaxskel import synth
from jaxskel.segment import distance_std
from jaxskel.segment._spectral import _mend, _pair_lone_markers, _pass_joint_marker, _score, white_noise


def test_distance_std_matches_numpy_and_masks():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 4, 3))
    mask = rng.random((50, 4)) > 0.2
    a, n = distance_std(np.where(mask[..., None], x, 0.0), mask)
    for i in range(4):
        for j in range(4):
            both = mask[:, i] & mask[:, j]
            d = np.linalg.norm(x[both, i] - x[both, j], axis=-1)
            assert n[i, j] == both.sum()
            if i != j:
                assert a[i, j] == pytest.approx(d.std(), abs=1e-12)


def test_linkage_three_groups_by_eigengap():
    trial, truth = synth.simulate(synth.linkage(), duration=30.0, seed=0, noise=0.001)
    seg = jaxskel.segment.segment_markers(trial)
    assert seg.n_segments == 3 == seg.eigengap_segments
    assert partition(trial.labels, seg.marker_segment) == true_partition(trial, truth)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_full_body_exact_segmentation_noise_soft_tissue_gaps(seed):
    """Exact grouping, except that a marker which moves less in a neighbouring segment's
    frame than every marker's own artefact (white noise and soft tissue, RMS in 3-D:
    sqrt(3 * 2^2 + 3^2) = 4.6 mm) may sit in either segment: distances cannot tell.
    Seed 1's elbow marker LELB (on the upper arm, 4-5 mm RMS in the forearm's frame) goes
    with the forearm since the white noise is taken out of A; the paper's score prefers that
    grouping both with and without the noise (36.49 against 36.84 mm, 57.84 against 58.06).
    Any other marker out of place fails."""
    body = synth.full_body(seed=seed)
    trial, truth = synth.simulate(
        body, duration=30.0, seed=seed, noise=0.002, soft_tissue=0.003, gaps=2
    )
    cleaned, _ = jaxskel.clean.clean(trial)
    seg = jaxskel.segment.segment_markers(cleaned)
    n_true = len(truth.segment_names)
    assert seg.eigengap_segments == n_true
    artefact = marker_artefact(0.002, 0.003)
    assert len(markers_on_joints(truth, artefact)) <= 2
    assert same_grouping_up_to_joint_markers(cleaned.labels, seg.marker_segment, truth, artefact)
    # the spectrum shows the gap: eigenvalue n is clearly above eigenvalue n+1
    ev = seg.eigenvalues
    assert ev[n_true - 1] - ev[n_true] > 2 * (ev[n_true] - ev[n_true + 1])


@pytest.mark.parametrize("rate", [60.0, 240.0])
def test_white_noise_is_read_from_the_recording(rate):
    """The 4th difference's robust scale gives the per-coordinate noise std the synthetic
    recording was made with, whatever the rate, through gaps and jumps, and not the
    motion (noiseless: < 0.01 mm); rotating the recording does not change it."""
    body = synth.full_body(seed=3)
    for noise in (0.0, 0.0005, 0.004):
        trial, _ = synth.simulate(body, duration=10.0, rate=rate, seed=3, noise=noise, gaps=3, jumps=4)
        assert white_noise(trial.positions) == pytest.approx(noise, rel=0.03, abs=1e-5)
    moved = trial.transformed(random_rotation(3), np.array([1.0, 2.0, -3.0]))
    assert white_noise(moved.positions) == pytest.approx(white_noise(trial.positions), rel=1e-9)
    assert white_noise(trial.positions[:4]) == 0.0  # too few frames for a 4th difference
    assert white_noise(np.full((50, 3, 3), np.nan)) == 0.0
    with pytest.raises(jaxskel.InputError, match=r"shape \(T, M, 3\), got shape \(50, 6\)"):
        white_noise(np.zeros((50, 6)))


@pytest.mark.parametrize("seed", [5, 8])
def test_high_white_noise_does_not_merge_segments(seed):
    """4 mm of white noise per coordinate (and 2 mm soft tissue): within a segment A is
    6 mm, across the wrists and ankles 6-33 mm (median 14-16). The affinity scale followed
    the noise floor up to 11 mm, the eigengap chose 10 (seed 5) or 5 (seed 8) and the
    rigidity limit, 34 mm, let the count stop at 11 and 10 with hand + forearm and foot +
    shank as one segment each. With the noise taken out of A the scale is the 3 mm floor
    and the grouping is exact. The result keeps A as measured, and its rigidity limit in
    the same terms: no group of the exact grouping is above it."""
    body = synth.full_body(seed=seed)
    trial, truth = synth.simulate(body, duration=30.0, seed=seed, noise=0.004, soft_tissue=0.002, gaps=2)
    cleaned, _ = jaxskel.clean.clean(trial)
    seg = jaxskel.segment.segment_markers(cleaned)
    assert seg.white_noise == pytest.approx(0.004, rel=0.03)
    assert seg.n_segments == len(truth.segment_names)
    keep = [trial.labels.index(lab) for lab in cleaned.labels]
    assert partition(cleaned.labels, seg.marker_segment) == partition(cleaned.labels, truth.marker_segment[keep])
    assert seg.sigma < 0.005
    assert seg.rigid_limit == pytest.approx(np.hypot(3.0 * seg.sigma, np.sqrt(2.0) * seg.white_noise))
    assert np.nanmin(seg.distance_std[~np.eye(cleaned.n_markers, dtype=bool)]) > 0.004  # as measured
    assert seg.nonrigid_groups() == []
    # The scale the raw floor gave (11 mm) is what went wrong: given it, the eigengap
    # alone falls short of 15 on the same data.
    assert jaxskel.segment.segment_markers(cleaned, sigma=0.0113, rigid_ratio=None).n_segments < 15


def test_invariant_to_rigid_motion_and_marker_order():
    body = synth.full_body(seed=3)
    trial, truth = synth.simulate(body, duration=20.0, seed=3, noise=0.002)
    ref = partition(trial.labels, jaxskel.segment.segment_markers(trial).marker_segment)
    moved = trial.transformed(random_rotation(7), np.array([3.0, -2.0, 0.5]))
    assert partition(moved.labels, jaxskel.segment.segment_markers(moved).marker_segment) == ref
    perm = np.random.default_rng(1).permutation(trial.n_markers)
    shuffled = trial.select_markers(perm)
    assert partition(shuffled.labels, jaxskel.segment.segment_markers(shuffled).marker_segment) == ref


def test_pairs_never_seen_together_are_unobserved_not_rigid():
    trial, _ = synth.simulate(synth.linkage(), duration=20.0, seed=0, noise=0.001)
    x = np.array(trial.positions)
    half = trial.n_frames // 2
    x[:half, 0] = np.nan
    x[half:, 8] = np.nan
    t2 = trial.replace(positions=x)
    seg = jaxskel.segment.segment_markers(t2, 3)
    assert (0, 8) in seg.unobserved_pairs
    assert np.isnan(seg.distance_std[0, 8])
    assert seg.affinity[0, 8] < 1e-6


def test_within_std_of_a_group_never_seen_together_is_nan_without_a_warning():
    """A two-marker group whose markers are never seen together (a sync light clustered with
    a hand) has no within-group statistic: NaN, not a RuntimeWarning of numpy's."""
    trial, _ = synth.simulate(synth.linkage(), duration=20.0, seed=0, noise=0.001)
    seg = jaxskel.segment.segment_markers(trial, 3)
    first = np.flatnonzero(seg.marker_segment == 0)[:2]
    pair = np.where(np.isin(np.arange(trial.n_markers), first), 0, np.maximum(seg.marker_segment, 1))
    std = seg.distance_std.copy()
    std[first[0], first[1]] = std[first[1], first[0]] = np.nan
    two = dataclasses.replace(seg, marker_segment=pair, distance_std=std)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        within = two.within_std()
    assert np.isnan(within[0])
    assert np.isfinite(within[1:]).all()


def _blocks(groups, within=0.002, across=0.1, seed=0):
    """Distance-std matrix of rigid groups: ``within`` inside a group, ``across`` between."""
    labels = np.repeat(np.arange(len(groups)), groups)
    rng = np.random.default_rng(seed)
    a = np.where(labels[:, None] == labels[None, :], within, across) * rng.uniform(0.8, 1.2, (len(labels),) * 2)
    a = 0.5 * (a + a.T)
    np.fill_diagonal(a, 0.0)
    return labels, a


def test_mend_moves_a_marker_chained_into_the_wrong_group():
    """numediart 03_rolling in miniature: marker 0 (group 0) is falsely rigid with two
    of the seven markers of group 1 (seen together only while nothing moved), and the
    spectral step put it in group 1, where the rest of the group shows 10 cm of
    distance std."""
    labels, a = _blocks([4, 7, 3])
    a[0, [4, 5]] = a[[4, 5], 0] = 0.002
    wrong = labels.copy()
    wrong[0] = 1
    assert _score(_mend(wrong, a, 0.004), a) < _score(wrong, a)
    np.testing.assert_array_equal(_mend(wrong, a, 0.004), labels)
    np.testing.assert_array_equal(_mend(labels, a, 0.004), labels)  # the right answer stays
    # unobserved pairs (NaN) are no evidence either way
    a_gap = a.copy()
    a_gap[0, 1:3] = a_gap[1:3, 0] = np.nan
    np.testing.assert_array_equal(_mend(wrong, a_gap, 0.004), labels)


def test_mend_leaves_markers_on_joints_and_rigid_markers_alone():
    labels, a = _blocks([4, 4, 4])
    joint = 3  # about as rigid with group 1 as with its own: a marker on the joint
    a[joint, 4:8] = a[4:8, joint] = [0.003, 0.0035, 0.0045, 0.005]
    a[joint, :3] = a[:3, joint] = [0.004, 0.0042, 0.0038]
    np.testing.assert_array_equal(_mend(labels, a, 0.003), labels)
    # a marker a little less rigid with its group than with another, all at the noise
    # scale (3 mm against 2.2 mm, under 1.5 times), is not moved either
    _, b = _blocks([4, 4, 4])
    b[0, 1:4] = b[1:4, 0] = 0.003
    b[0, 4:8] = b[4:8, 0] = 0.0022
    np.testing.assert_array_equal(_mend(labels, b, 0.004), labels)


def test_mend_moves_a_marker_far_more_rigid_with_another_group_under_sigma():
    """A marker near a joint put on the wrong side: A = 2.5 mm to its two group mates,
    under sigma (4 mm), but 1.4 mm (the noise floor) to every marker of its own
    segment. It moves; with one loose partner in the other group it stays (the largest
    A over h decides, not a quartile)."""
    labels, a = _blocks([2, 8, 4], within=0.0014)
    wrong = labels.copy()
    wrong[2] = 0  # marker 2 of group 1 in group 0
    a[2, :2] = a[:2, 2] = [0.0024, 0.0026]
    a[2, 3:10] = a[3:10, 2] = 0.0015
    np.testing.assert_array_equal(_mend(wrong, a, 0.004), labels)
    np.testing.assert_array_equal(_mend(labels, a, 0.004), labels)
    # one loose partner (3 mm) in group 1: its upper quartile is still 1.5 mm, its
    # largest value is 2 times what marker 2 shows with group 0
    loose = a.copy()
    loose[2, 9] = loose[9, 2] = 0.003
    np.testing.assert_array_equal(_mend(wrong, loose, 0.004), wrong)


def test_sixteen_segment_tree_marker_near_a_joint_lands_on_its_segment():
    """random_tree(16, seed=1): spectral clustering put one marker of segment 2 with
    segment 1 (A 2.4-2.6 mm there, 1.4 mm with its own segment); the mend's ratio
    reading moves it back, and the segmentation is the truth."""
    body = synth.random_tree(16, seed=1)
    trial, truth = synth.simulate(body, duration=20.0, seed=1, noise=0.001, gaps=2)
    seg = jaxskel.segment.segment_markers(trial)
    true_seg = truth.marker_segment[[trial.labels.index(lab) for lab in seg.labels]]
    assert partition(seg.labels, seg.marker_segment) == partition(seg.labels, true_seg)


def test_count_grows_from_the_eigengap_until_every_group_is_rigid():
    """A random 10-segment tree whose spectrum has its largest gap at 8: two pairs of
    segments that move little relative to each other are one cluster for the eigengap
    (the paper's count), each holding markers whose distance varies by > 3 sigma. The
    count grows to the first at which every group is rigid: 10, the exact segmentation."""
    trial, truth = synth.simulate(synth.random_tree(10, seed=2), duration=30.0, seed=2, noise=0.001)
    paper = jaxskel.segment.segment_markers(trial, rigid_ratio=None)
    assert paper.n_segments == paper.eigengap_segments == 8 and paper.count_rule == "eigengap"
    assert len(paper.nonrigid_groups()) == 0  # no limit without the check
    seg = jaxskel.segment.segment_markers(trial)
    assert seg.eigengap_segments == 8 and seg.count_rule == "rigid" and seg.n_segments == 10
    assert partition(trial.labels, seg.marker_segment) == true_partition(trial, truth)
    assert seg.rigid_limit == pytest.approx(np.hypot(3.0 * seg.sigma, np.sqrt(2) * seg.white_noise))
    assert seg.nonrigid_groups() == []
    # the eigengap's groups, judged by the same limit, name the markers that move apart
    judged = dataclasses.replace(paper, rigid_limit=seg.rigid_limit)
    named = judged.nonrigid_groups()
    assert named and all(a > seg.rigid_limit for *_, a in named)
    for _, first, second, _ in named:
        assert truth.marker_segment[trial.labels.index(first)] != truth.marker_segment[trial.labels.index(second)]
    # a count given by the user is kept as given
    given = jaxskel.segment.segment_markers(trial, 8)
    assert given.n_segments == 8 and given.count_rule == "given"


def test_a_rigid_count_that_leaves_a_marker_alone_is_reported_not_taken():
    """The first count whose groups are all rigid (4) leaves a marker alone: the eigengap's
    3 is kept, its non-rigid group named, and 4 is reported as the count to compare."""
    trial = linkage_with_a_bending_marker()
    seg = jaxskel.segment.segment_markers(trial, sigma=0.006)
    assert (seg.count_rule, seg.eigengap_segments, seg.n_segments, seg.rigid_count) == ("eigengap", 3, 3, 4)
    ((_, first, second, std),) = seg.nonrigid_groups()
    assert {first, second} == {"R3M1", "R3M3"}
    assert std > seg.rigid_limit == pytest.approx(np.hypot(0.018, np.sqrt(2) * seg.white_noise))
    four = jaxskel.segment.segment_markers(trial, 4, sigma=0.006)
    assert four.nonrigid_groups() == [] and 1 in four.segment_sizes
    # nothing to report where the count is given, or the check is off
    assert jaxskel.segment.segment_markers(trial, 3, sigma=0.006).rigid_count == 0
    assert jaxskel.segment.segment_markers(trial, sigma=0.006, rigid_ratio=None).rigid_count == 0


def _knee_costs(knee_to_thigh: float, knee_to_shank: float) -> np.ndarray:
    """Distance stds (m) of a thigh marker T (0), a knee marker K (1) and shank markers S1, S2
    (2, 3): T moves against the shank by 30 mm, S1-S2 are a cluster (1 mm)."""
    a = np.full((4, 4), 0.030)
    a[0, 1] = a[1, 0] = knee_to_thigh
    a[1, 2:] = a[2:, 1] = knee_to_shank
    a[2, 3] = a[3, 2] = 0.001
    np.fill_diagonal(a, 0.0)
    return a


def test_a_lone_marker_takes_the_marker_on_the_joint_next_to_it():
    """A grown count put the knee marker K with the shank and left the thigh marker T
    alone. K is about as rigid with T (10 mm) as with the shank (8 mm): it goes to T, and
    both groups stay rigid (limit 25 mm)."""
    alone = np.array([0, 1, 1, 1])
    paired = _pair_lone_markers(alone, _knee_costs(0.010, 0.008), 0.025)
    np.testing.assert_array_equal(paired, [0, 0, 1, 1])
    # 1.5 x its rigidity with its group is the edge (the mend's ratio): 12 mm is taken, 12.5 mm not
    np.testing.assert_array_equal(_pair_lone_markers(alone, _knee_costs(0.0119, 0.008), 0.025), [0, 0, 1, 1])
    np.testing.assert_array_equal(_pair_lone_markers(alone, _knee_costs(0.0125, 0.008), 0.025), alone)


def test_a_lone_marker_never_takes_a_cluster_marker_or_a_non_rigid_partner():
    alone = np.array([0, 1, 1, 1])
    # K far more rigid with its cluster (1 mm) than with T (6 mm): a cluster marker stays
    np.testing.assert_array_equal(_pair_lone_markers(alone, _knee_costs(0.006, 0.001), 0.025), alone)
    # the pair would not be rigid (30 mm over the 25 mm limit)
    np.testing.assert_array_equal(_pair_lone_markers(alone, _knee_costs(0.030, 0.025), 0.025), alone)
    # the donor would be left with one marker
    two = np.array([0, 1, 1, 2])
    np.testing.assert_array_equal(_pair_lone_markers(two, _knee_costs(0.010, 0.008), 0.025), two)
    # unobserved pairs (NaN) are no evidence
    a = _knee_costs(0.010, 0.008)
    a[0, 1] = a[1, 0] = np.nan
    np.testing.assert_array_equal(_pair_lone_markers(alone, a, 0.025), alone)


def _arm_costs(**changes: float) -> np.ndarray:
    """Distance stds (m) of an upper-arm marker U (0), an elbow marker E (1), a forearm
    marker F (2), two wrist markers W1, W2 (3, 4) and a trunk cluster (5-7): E is on the
    joint, rigid with U (8 mm) and F (6 mm); F is rigid with the wrist (4 and 5.7 mm)."""
    names = "U E F W1 W2".split()
    a = np.full((8, 8), 0.050)
    pairs = {("U", "E"): 0.008, ("E", "F"): 0.006, ("F", "W1"): 0.004, ("F", "W2"): 0.0057, ("W1", "W2"): 0.0014,
             ("U", "F"): 0.030, ("U", "W1"): 0.060, ("U", "W2"): 0.040, ("E", "W1"): 0.0105, ("E", "W2"): 0.0068}
    for key, value in changes.items():
        pairs[tuple(key.split("_"))] = value
    for (u, v), value in pairs.items():
        a[names.index(u), names.index(v)] = a[names.index(v), names.index(u)] = value
    a[5:, 5:] = 0.001
    np.fill_diagonal(a, 0.0)
    return a


def test_a_lone_marker_takes_a_joint_marker_whose_partner_joins_the_next_group():
    """The elbow marker clustered with the forearm marker, the upper-arm marker alone: the
    elbow goes to the upper arm and the forearm marker to the wrist pair (limit 9 mm), one
    lone marker and one segment fewer; :func:`_pair_lone_markers` leaves it, since the
    elbow's group would keep one marker."""
    given = np.array([0, 1, 1, 2, 2, 3, 3, 3])
    np.testing.assert_array_equal(_pair_lone_markers(given, _arm_costs(), 0.009), given)
    labels, moves = _pass_joint_marker(given, _arm_costs(), 0.009)
    np.testing.assert_array_equal(labels, [0, 0, 1, 1, 1, 2, 2, 2])
    assert moves == [(1, 0, 2)]  # the elbow (1) to the upper arm (0), its partner (2) to the wrist


def test_a_joint_marker_stays_where_its_partner_fits_nowhere_or_it_belongs_to_its_pair():
    given = np.array([0, 1, 1, 2, 2, 3, 3, 3])
    # the forearm marker is not rigid with the wrist pair (12 mm over the 9 mm limit)
    np.testing.assert_array_equal(_pass_joint_marker(given, _arm_costs(F_W2=0.012), 0.009)[0], given)
    # nor, under a looser limit (25 mm), about as rigid with it as with the elbow (10 mm over 1.5 x 6 mm)
    np.testing.assert_array_equal(_pass_joint_marker(given, _arm_costs(F_W1=0.010, F_W2=0.010), 0.025)[0], given)
    np.testing.assert_array_equal(_pass_joint_marker(given, _arm_costs(F_W1=0.0085, F_W2=0.0085), 0.025)[0],
                                  [0, 0, 1, 1, 1, 2, 2, 2])
    # the elbow far more rigid with the forearm (2 mm) than with the upper arm (8 mm): no joint marker
    np.testing.assert_array_equal(_pass_joint_marker(given, _arm_costs(E_F=0.002), 0.009)[0], given)
    # the upper arm and the elbow would not make a rigid pair (10 mm over the limit)
    np.testing.assert_array_equal(_pass_joint_marker(given, _arm_costs(U_E=0.010, E_F=0.008), 0.009)[0], given)
    # the donor is a group of three: _pair_lone_markers' case, not this one
    three = np.array([0, 1, 1, 1, 2, 3, 3, 3])
    np.testing.assert_array_equal(_pass_joint_marker(three, _arm_costs(), 0.009)[0], three)
    # nothing moves: the labels come back as given, not renumbered
    unordered = np.array([3, 1, 1, 2, 2, 0, 0, 0])
    labels, moves = _pass_joint_marker(unordered, _arm_costs(F_W2=0.012), 0.009)
    assert labels is unordered and moves == []


def test_count_candidates_stay_within_the_eigengap_search():
    """The eigengap searches k = 2..max_segments; its runners-up come from the same range,
    also when the trial has exactly max_segments + 2 markers (the spectrum is then all
    eigenvalues, and k = max_segments + 1 must not be listed)."""
    trial, _ = synth.simulate(synth.random_tree(4, seed=0), duration=20.0, seed=0, noise=0.001)
    for max_segments in (trial.n_markers - 2, trial.n_markers - 4, 5):
        seg = jaxskel.segment.segment_markers(trial, max_segments=max_segments, rigid_ratio=None)
        ks = [k for k, _ in seg.count_candidates(n=50)]
        assert ks[0] == seg.eigengap_segments
        assert sorted(ks) == list(range(2, max_segments + 1)), (max_segments, ks)


def test_bad_segment_counts():
    trial, _ = synth.simulate(synth.linkage(), duration=5.0, seed=0)
    with pytest.raises(jaxskel.InputError, match="n_segments"):
        jaxskel.segment.segment_markers(trial, 0)
    with pytest.raises(jaxskel.InputError, match="n_segments"):
        jaxskel.segment.segment_markers(trial, 10)
    for bad in (0.0, -1.0, "3"):
        with pytest.raises(jaxskel.InputError, match="rigid_ratio"):
            jaxskel.segment.segment_markers(trial, rigid_ratio=bad)


def _standing_still(seconds=6.0, noise=0.002):
    """The full body held in its first pose (a static trial): only marker noise moves."""
    trial, _ = synth.simulate(synth.full_body(seed=0), duration=seconds, seed=0, noise=0.0)
    x = np.asarray(trial.positions)
    still = np.repeat(x[:1], len(x), axis=0) + np.random.default_rng(1).normal(0.0, noise, x.shape)
    return trial.replace(positions=still)


def test_a_recording_that_moves_no_joint_is_one_segment_and_the_fit_says_why(tmp_path, capsys):
    """Standing still, every marker keeps its distances (3 mm std from 2 mm noise, under
    the rigidity limit): one rigid body. The eigengap alone (k >= 2) split it into two
    arbitrary halves with no feasible joint, and the fit returned "2 segments, 0 joints"
    with only a forest warning; now the count is 1 and the fit raises a typed error that
    says the recording exercises no joint. Moving, the same body is 15 segments."""
    still = _standing_still()
    seg = jaxskel.segment.segment_markers(still)
    assert (seg.n_segments, seg.count_rule) == (1, "rigid")
    assert np.nanmax(seg.distance_std) <= seg.rigid_limit
    with pytest.raises(jaxskel.DegenerateMotionError, match="one rigid body.*exercises no joint"):
        jaxskel.fit_skeleton(still)
    # the paper's eigengap alone still splits it, and no pair can then be jointed: said so
    assert jaxskel.segment.segment_markers(still, rigid_ratio=None).n_segments >= 2
    with pytest.raises(jaxskel.DegenerateMotionError, match="can be jointed.*not exercised"):
        jaxskel.fit_skeleton(still, rigid_ratio=None)
    # a given count is the user's: kept
    assert jaxskel.segment.segment_markers(still, 3).n_segments == 3
    moving, _ = synth.simulate(synth.full_body(seed=0), duration=6.0, seed=0, noise=0.002)
    assert jaxskel.segment.segment_markers(moving).n_segments == 15
    # the command line: one line on stderr, exit status 2, no result file
    from jaxskel.cli import main

    src = jaxskel.save_trial(still, tmp_path / "still.h5")
    assert main(["fit", str(src), "-o", str(tmp_path / "out.h5"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxskel: error:") and "exercises no joint" in err and "Traceback" not in err
    assert not (tmp_path / "out.h5").exists()
