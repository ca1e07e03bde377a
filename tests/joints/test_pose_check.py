"""The pose check of the tree (jaxskel.joints._pose_check): joints as points fixed in both segments."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import random_rotation

from jaxskel import synth

from jaxskel.joints import PoseExchange
from jaxskel.joints._near_ties import residual_dof
from jaxskel.joints._pose_check import (
    MISFIT_BLOCKS,
    MISFIT_FACTOR,
    TIE_Z,
    fixed_centre_errors,
    fixed_centre_misfit,
    misfit_drop_z,
    misfit_from_errors,
    pose_checked_edges,
    segment_poses,
    sphere_misfit,
)
from jaxskel.joints._topology import MIN_PAIR_FRAMES

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")


@pytest.fixture(scope="module")
def body():
    """Full body, 20 s calibration motion, 1 mm noise, the true segments; every 8th frame."""
    trial, truth = synth.simulate(synth.full_body(seed=0), duration=20.0, seed=0, noise=0.001)
    x, mask = trial.to_arrays()
    return x, mask, truth, np.arange(0, trial.n_frames, 8)


def test_true_joints_fit_and_other_pairs_do_not(body):
    """Measured (seeds 0, 1): the 12 true joints between segments of three or more markers
    11-13 mm^2 (a few mm of disagreement: noise on a lever arm), the 66 other such pairs
    2,000 mm^2 or more; the two-marker segments (the hands) have no pose and no misfit."""
    x, mask, truth, frames = body
    s = truth.n_segments
    misfit = fixed_centre_misfit(x, mask, truth.marker_segment, s, frames, MIN_PAIR_FRAMES)
    sizes = np.bincount(truth.marker_segment, minlength=s)
    posed = sizes >= 3
    assert (~posed).sum() == 2 and np.isinf(misfit[~posed]).all() and np.isinf(misfit[:, ~posed]).all()
    assert np.isinf(np.diag(misfit)).all() and np.array_equal(misfit, misfit.T)
    true = {frozenset(map(int, e)) for e in truth.edges}
    joints = [misfit[a, b] for a, b in truth.edges if posed[a] and posed[b]]
    others = [misfit[a, b] for a in range(s) for b in range(a + 1, s)
              if posed[a] and posed[b] and frozenset((a, b)) not in true]
    assert len(joints) == 12 and len(others) == 66
    assert max(joints) < 50e-6 and min(others) > 500e-6, (max(joints), min(others))


def test_misfit_is_invariant_to_pose_and_marker_order(body):
    x, mask, truth, frames = body
    s = truth.n_segments
    misfit = fixed_centre_misfit(x, mask, truth.marker_segment, s, frames, MIN_PAIR_FRAMES)
    rot = random_rotation(3)
    moved = np.where(mask[..., None], x @ rot.T + np.array([1.5, -2.0, 0.7]), np.nan)
    order = np.random.default_rng(4).permutation(x.shape[1])
    again = fixed_centre_misfit(
        moved[:, order], mask[:, order], truth.marker_segment[order], s, frames, MIN_PAIR_FRAMES
    )
    finite = np.isfinite(misfit)
    assert np.array_equal(finite, np.isfinite(again))
    np.testing.assert_allclose(again[finite], misfit[finite], rtol=1e-6)


def test_too_few_frames_posing_both_leave_a_pair_unjudged(body):
    x, mask, truth, frames = body
    head = truth.segment_names.index("head")
    hidden = mask.copy()
    hidden[frames[MIN_PAIR_FRAMES - 1]:, truth.marker_segment == head] = False  # posed in 9 of the frames
    misfit = fixed_centre_misfit(x, hidden, truth.marker_segment, truth.n_segments, frames, MIN_PAIR_FRAMES)
    assert np.isinf(misfit[head]).all()
    assert np.isfinite(misfit[truth.segment_names.index("torso"), truth.segment_names.index("pelvis")])


def _sphere_reference(x, mask, seg, s, frames, a, b):
    """m[a, b] by a plain geometric check: each of b's markers in a's frame, one shared
    centre that minimises the mean variance of their distances to it (scipy's least
    squares, started from the algebraic fit |p|^2 = 2 p.c + d_k, per-marker d_k)."""
    from scipy.optimize import least_squares

    rot, t, posed = segment_poses(x, mask, seg, s, frames)
    markers = np.flatnonzero(seg == b)
    rows, rhs, paths = [], [], []
    for i, m in enumerate(markers):
        ok = posed[:, a] & mask[frames, m]
        p = np.einsum("fij,fj->fi", rot[ok, a], x[frames][ok, m]) + t[ok, a]
        r = np.zeros((len(p), 3 + len(markers)))
        r[:, :3], r[:, 3 + i] = 2 * p, 1.0
        rows.append(r), rhs.append((p**2).sum(1)), paths.append(p)
    c = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0][:3]

    def spread(c):  # residuals whose mean square is the mean variance
        return np.concatenate([(d - d.mean()) / np.sqrt(len(d) * len(paths))
                               for d in (np.linalg.norm(p - c, axis=1) for p in paths)])

    c = least_squares(spread, c, xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    return np.mean([np.var(np.linalg.norm(p - c, axis=1)) for p in paths])


def _arc(degrees, radius, noise=0.001, frames=600):
    """A posed segment (three markers, still) and a two-marker segment turning about the
    origin by +-``degrees`` (and half of it about a second axis), its markers ``radius``
    and ``radius - 0.1`` m from the joint; white noise on every marker."""
    phase = np.linspace(0, 6 * np.pi, frames)
    a, b = np.deg2rad(degrees) * np.sin(phase), np.deg2rad(degrees / 2) * np.cos(2 * phase / 3)
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    zero, one = np.zeros(frames), np.ones(frames)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, ca, -sa], -1), np.stack([zero, sa, ca], -1)], 1)
    ry = np.stack([np.stack([cb, zero, sb], -1), np.stack([zero, one, zero], -1), np.stack([-sb, zero, cb], -1)], 1)
    local = np.array([[0.0, 0.0, -radius], [0.03, 0.0, 0.1 - radius]])
    x = np.concatenate([np.broadcast_to([[0.1, 0.0, 0.05], [-0.1, 0.05, 0.0], [0.0, -0.08, 0.1]], (frames, 3, 3)),
                        np.einsum("fij,kj->fki", rx @ ry, local)], axis=1)
    x = x + np.random.default_rng(1).normal(0.0, noise, x.shape)
    return x, np.ones(x.shape[:2], bool), np.array([0, 0, 0, 1, 1]), np.arange(frames)


def test_sphere_misfit_reads_a_short_arc_at_the_noise(monkeypatch):
    """Over a short arc the algebraic sphere fit's centre lies off the one that keeps the
    distances most constant (the algebraic error weighs points by |p|, not by distance):
    read at it, a true joint turned by +-6 degrees costs 5.4 mm^2 with 1 mm of noise. From
    there Gauss-Newton reaches the centre of least variance: 1.4 mm^2, the noise's level
    (the markers' 1 mm^2 and the still segment's pose), as on a wide arc."""
    from jaxskel.joints import _pose_check

    def misfit(degrees):
        x, mask, seg, frames = _arc(degrees, 0.35)
        return sphere_misfit(x, mask, seg, 2, frames, MIN_PAIR_FRAMES)[0, 1], _sphere_reference(
            x, mask, seg, 2, frames, 0, 1)

    (wide, _), (short, reference) = misfit(12), misfit(6)
    assert 1e-6 < short < 1.6e-6 and short == pytest.approx(wide, rel=0.05)
    assert short == pytest.approx(reference, rel=1e-4)
    monkeypatch.setattr(_pose_check, "SPHERE_STEPS", 0)  # the algebraic centre alone
    assert misfit(6)[0] > 3 * short


@pytest.fixture(scope="module")
def sparse():
    """One marker per hand, two per forearm and on the head: segments a pose cannot test."""
    body = synth.full_body(seed=1, markers_per_segment={"l_hand": 1, "r_hand": 1, "l_forearm": 2,
                                                         "r_forearm": 2, "head": 2})
    trial, truth = synth.simulate(body, duration=20.0, seed=1, noise=0.001)
    x, mask = trial.to_arrays()
    return x, mask, truth, np.arange(0, trial.n_frames, 8)


def test_sphere_misfit_judges_joints_of_sparse_segments(sparse):
    """A segment of one or two markers has no pose; its markers about a centre fixed in
    the pose of its true neighbour keep their distances (measured 1.4-1.6 mm^2 for the neck
    and elbows), about any other segment's they do not (65 mm^2 and more). Equal to a
    plain per-pair solve."""
    x, mask, truth, frames = sparse
    s, seg = truth.n_segments, truth.marker_segment
    m = sphere_misfit(x, mask, seg, s, frames, MIN_PAIR_FRAMES)
    sizes = np.bincount(seg, minlength=s)
    posed = sizes >= 3
    assert np.isinf(m[~posed]).all() and np.isinf(np.diag(m)).all()
    true = {frozenset(map(int, e)) for e in truth.edges}
    joints = [m[a, b] for a, b in (*truth.edges, *truth.edges[:, ::-1]) if posed[a] and not posed[b]]
    others = [m[a, b] for a in range(s) for b in range(s)
              if posed[a] and not posed[b] and a != b and frozenset((a, b)) not in true]
    assert len(joints) == 3 and max(joints) < 5e-6 and min(others) > 30e-6, (max(joints), min(others))
    for a, b in ((0, 1), (int(np.flatnonzero(~posed)[0]), 0), (3, int(np.flatnonzero(~posed)[-1]))):
        if np.isfinite(m[a, b]):
            assert m[a, b] == pytest.approx(_sphere_reference(x, mask, seg, s, frames, a, b), rel=1e-4)


def test_sphere_misfit_is_invariant_to_pose_and_marker_order(sparse):
    x, mask, truth, frames = sparse
    s = truth.n_segments
    m = sphere_misfit(x, mask, truth.marker_segment, s, frames, MIN_PAIR_FRAMES)
    rot = random_rotation(5)
    moved = np.where(mask[..., None], x @ rot.T + np.array([-0.5, 3.0, 1.1]), 0.0)
    order = np.random.default_rng(7).permutation(x.shape[1])
    again = sphere_misfit(moved[:, order], mask[:, order], truth.marker_segment[order], s, frames, MIN_PAIR_FRAMES)
    finite = np.isfinite(m)
    assert np.array_equal(finite, np.isfinite(again))
    np.testing.assert_allclose(again[finite], m[finite], rtol=1e-5, atol=1e-12)


def _graph():
    """Segments 0-2 posed, 3 not. Joint costs make the MST 0-1, 1-2, 2-3."""
    cost = np.full((4, 4), np.inf)
    for (a, b), c in {(0, 1): 1.0, (1, 2): 2.0, (0, 2): 3.0, (2, 3): 1.0, (0, 3): 5.0, (1, 3): 5.0}.items():
        cost[a, b] = cost[b, a] = c
    misfit = np.full((4, 4), np.inf)
    for (a, b), m in {(0, 1): 10.0, (1, 2): 100.0, (0, 2): 5.0}.items():
        misfit[a, b] = misfit[b, a] = m
    return np.array([[0, 1], [1, 2], [2, 3]]), misfit, cost


def test_poses_overrule_the_joint_costs_between_posed_segments_and_keep_the_rest():
    edges, misfit, cost = _graph()
    new, exchanges = pose_checked_edges(edges, misfit, cost)
    assert new.tolist() == [[0, 1], [0, 2], [2, 3]]  # 2-3 (segment 3 has no pose) is kept
    assert exchanges == (PoseExchange(removed=(1, 2), added=(0, 2), misfit=(100.0, 5.0), cost=(2.0, 3.0)),)


def test_exchanges_repeat_worst_first_until_the_tree_is_settled():
    """A chain 0-1-2-3 of posed segments whose poses say 0-2, 0-3 and 1-3 are the joints:
    the worst edge (2-3) goes first, to the best pair across its cut (0-3); then 1-2 to
    0-2. The result is a tree in which no edge has a rival twice as good."""
    cost = np.ones((4, 4)) - np.eye(4)
    misfit = np.full((4, 4), 1000.0)
    for (a, b), m in {(0, 1): 10.0, (1, 2): 200.0, (2, 3): 400.0, (0, 2): 20.0, (0, 3): 5.0, (1, 3): 40.0}.items():
        misfit[a, b] = misfit[b, a] = m
    np.fill_diagonal(misfit, np.inf)
    new, exchanges = pose_checked_edges(np.array([[0, 1], [1, 2], [2, 3]]), misfit, cost)
    assert [(e.removed, e.added) for e in exchanges] == [((2, 3), (0, 3)), ((1, 2), (0, 2))]
    assert new.tolist() == [[0, 1], [0, 2], [0, 3]]


def test_poses_that_agree_or_an_infeasible_pair_change_nothing():
    edges, misfit, cost = _graph()
    agree = misfit.copy()
    agree[0, 2] = agree[2, 0] = 500.0
    new, exchanges = pose_checked_edges(edges, agree, cost)
    assert new.tolist() == edges.tolist() and exchanges == ()
    # a rival that fits better, but by less than the factor of two the poses need
    close = misfit.copy()
    close[0, 2] = close[2, 0] = 100.0 / MISFIT_FACTOR * 1.01
    new, exchanges = pose_checked_edges(edges, close, cost)
    assert new.tolist() == edges.tolist() and exchanges == ()
    infeasible = cost.copy()
    infeasible[0, 2] = infeasible[2, 0] = np.inf  # the joint costs found no joint there
    new, exchanges = pose_checked_edges(edges, misfit, infeasible)
    assert new.tolist() == edges.tolist() and exchanges == ()
    unposed = np.full((4, 4), np.inf)
    new, exchanges = pose_checked_edges(edges, unposed, cost)
    assert new.tolist() == edges.tolist() and exchanges == ()


def test_a_forest_stays_a_forest():
    """Joint costs that leave two components (infeasible pairs between them): an edge is
    only ever exchanged within its own component, however well a pair across fits."""
    cost = np.ones((4, 4)) - np.eye(4)
    misfit = np.full((4, 4), 1.0)
    misfit[0, 1] = misfit[1, 0] = misfit[2, 3] = misfit[3, 2] = 100.0
    np.fill_diagonal(misfit, np.inf)
    new, exchanges = pose_checked_edges(np.array([[0, 1], [2, 3]]), misfit, cost)
    assert new.tolist() == [[0, 1], [2, 3]] and exchanges == ()


def test_edges_only_the_sphere_test_can_judge_are_exchanged_with_a_label():
    """``judged`` limits the edges that may be exchanged; rivals come from ``misfit``."""
    edges, _, cost = _graph()
    sphere = np.full((4, 4), np.inf)
    sphere[2, 3] = sphere[3, 2] = 90.0
    sphere[0, 3] = sphere[3, 0] = 10.0
    judged = sphere.copy()
    new, exchanges = pose_checked_edges(edges, sphere, cost, judged=judged, test="sphere")
    assert {tuple(e) for e in new.tolist()} == {(0, 1), (1, 2), (0, 3)}
    assert exchanges == (PoseExchange((2, 3), (0, 3), (90.0, 10.0), (1.0, 5.0), "sphere"),)
    judged[2, 3] = judged[3, 2] = np.inf  # not judged: kept whatever its misfit
    assert pose_checked_edges(edges, sphere, cost, judged=judged)[1] == ()


def test_misfit_is_the_mean_of_its_per_frame_errors(body):
    x, mask, truth, frames = body
    s = truth.n_segments
    errors, both = fixed_centre_errors(x, mask, truth.marker_segment, s, frames)
    assert errors.shape == both.shape == (len(frames), s, s)
    misfit = fixed_centre_misfit(x, mask, truth.marker_segment, s, frames, MIN_PAIR_FRAMES)
    np.testing.assert_allclose(misfit_from_errors(errors, both, MIN_PAIR_FRAMES), misfit)
    a, b = map(int, truth.edges[0])
    np.testing.assert_allclose(errors[both[:, a, b] > 0, a, b].mean(), misfit[a, b], rtol=1e-6)


def _paired_errors(edge_series, rival_series):
    """Per-frame errors of a 3-segment graph: pair (0, 1) the edge, (0, 2) the rival."""
    f = len(edge_series)
    errors = np.zeros((f, 3, 3))
    errors[:, 0, 1] = errors[:, 1, 0] = edge_series
    errors[:, 0, 2] = errors[:, 2, 0] = rival_series
    return errors, np.ones((f, 3, 3))


def test_misfit_drop_is_measured_in_standard_errors_of_block_means():
    rng = np.random.default_rng(0)
    # a constant drop of 1 with independent unit noise: the block means of 30 frames
    # scatter by sqrt(2/30), so the drop is sqrt(10 * 30 / 2) ~ 12 standard errors
    edge = 2.0 + rng.standard_normal(300)
    rival = 1.0 + rng.standard_normal(300)
    z = misfit_drop_z(*_paired_errors(edge, rival), (0, 1), (0, 2))
    assert 8.0 < z < 17.0
    assert misfit_drop_z(*_paired_errors(rival, edge), (0, 1), (0, 2)) == pytest.approx(-z)
    # the same means, but the difference drifts slowly (correlated frames): the blocks
    # see it, and the drop is no longer significant although its mean is unchanged
    drift = 5.0 * np.sin(np.linspace(0, 4 * np.pi, 300, endpoint=False))  # mean 0
    slow = misfit_drop_z(*_paired_errors(edge + drift, rival), (0, 1), (0, 2))
    assert abs(slow) < TIE_Z
    # too few frames posing both pairs to form the blocks: no evidence
    few = _paired_errors(edge[: 2 * MISFIT_BLOCKS - 1], rival[: 2 * MISFIT_BLOCKS - 1])
    assert misfit_drop_z(*few, (0, 1), (0, 2)) == 0.0
    errors, both = _paired_errors(edge, rival)
    both[::2, 0, 2] = both[::2, 2, 0] = 0.0  # frames without the rival's poses are left out
    assert misfit_drop_z(errors, both, (0, 1), (0, 2)) == pytest.approx(
        misfit_drop_z(*_paired_errors(edge[1::2], rival[1::2]), (0, 1), (0, 2)))


def test_near_ties_are_decided_by_the_poses_only_where_the_costs_cannot_tell():
    """Tree 0-1, 1-2; the rival of 1-2 is 0-2. The near-tie pass exchanges 1-2 for 0-2 only
    where their costs lie within the sampling noise and the rival's misfit is lower by more
    than TIE_Z standard errors; the factor-of-two pass would not, the misfits being 1.5x apart."""
    rng = np.random.default_rng(1)
    f = 400
    errors = np.zeros((f, 3, 3))
    for (a, b), level in {(0, 1): 1.0, (1, 2): 3.0, (0, 2): 2.0}.items():
        errors[:, a, b] = errors[:, b, a] = level + 0.5 * rng.standard_normal(f)
    both = np.ones((f, 3, 3))
    misfit = misfit_from_errors(errors, both, 10)
    cost = np.array([[np.inf, 1.0, 1.05], [1.0, np.inf, 1.0], [1.05, 1.0, np.inf]])
    edges = np.array([[0, 1], [1, 2]])
    assert pose_checked_edges(edges, misfit, cost)[1] == ()  # 1.5x: not the factor of two
    noise = np.full((3, 3), 2.0 / 400)  # 2 / d with d = 400: 2 sqrt(2 * 0.005) = 20 %
    new, exchanges = pose_checked_edges(edges, misfit, cost, factor=1.0, tie_noise=noise, errors=(errors, both),
                                        test="near_tie")
    assert new.tolist() == [[0, 1], [0, 2]]
    assert [(e.removed, e.added, e.test) for e in exchanges] == [((1, 2), (0, 2), "near_tie")]
    # a rival the costs tell apart (50 % dearer, beyond the 20 % noise) is not a near tie
    dear = cost.copy()
    dear[0, 2] = dear[2, 0] = 1.5
    assert pose_checked_edges(edges, misfit, dear, factor=1.0, tie_noise=noise, errors=(errors, both))[1] == ()
    # pairs without residual degrees of freedom (infinite noise) are never near ties
    assert pose_checked_edges(edges, misfit, cost, factor=1.0, tie_noise=np.full((3, 3), np.inf),
                              errors=(errors, both))[1] == ()
    # a lower misfit that the frames do not establish (the difference drifts) changes nothing
    drifting = errors.copy()
    drifting[:, 1, 2] = drifting[:, 2, 1] = errors[:, 1, 2] + 5.0 * np.sin(np.linspace(0, 4 * np.pi, f, endpoint=False))
    drifting_misfit = misfit_from_errors(drifting, both, 10)
    assert drifting_misfit[1, 2] > drifting_misfit[0, 2]
    assert pose_checked_edges(edges, drifting_misfit, cost, factor=1.0, tie_noise=noise,
                              errors=(drifting, both))[1] == ()


def test_residual_dof_counts_the_redundant_distances_of_every_pair():
    """d = sum_t max(K_t - 3, 0) over the frames, K_t the pair's markers seen (a left-out
    marker, -1, counts for no segment)."""
    seg = np.array([0, 0, 1, 1, 1, 2, -1])
    mask = np.ones((5, 7), dtype=bool)
    mask[0, 2:5] = False  # frame 0: segment 1 unseen
    dof = residual_dof(mask, seg, 3)
    assert dof[0, 1] == 4 * 2 + 0  # 5 markers in 4 frames, 2 in frame 0
    assert dof[1, 2] == 4 * 1 + 0
    assert dof[0, 2] == 0  # 3 markers: no redundancy
    assert np.array_equal(dof, dof.T)


def test_segment_poses_on_frames_are_the_whole_recordings_rows(sparse):
    """Posing only the frames read gives, bit for bit, those rows of the poses of every
    frame (the mean clouds are the whole recording's; each frame is aligned on its own)."""
    from jaxskel.joints._anchored_centres import MAX_FRAMES, _segment_poses

    x, mask, truth, frames = sparse
    mask = mask.copy()
    mask[100:400, :5] = False  # gaps: frames where some segments are not posed
    s, seg = truth.n_segments, truth.marker_segment
    rot_all, t_all, posed_all = _segment_poses(x, mask, seg, s, MAX_FRAMES)
    rot, t, posed = segment_poses(x, mask, seg, s, frames)
    assert np.array_equal(posed, posed_all[frames]) and (~posed).any() and posed.any()
    assert np.array_equal(rot[posed], rot_all[frames][posed]) and np.array_equal(t[posed], t_all[frames][posed])
    assert np.array_equal(rot[~posed], np.broadcast_to(np.eye(3), rot[~posed].shape)) and not t[~posed].any()


def test_anchored_pose_rows_are_the_segment_poses_rows(sparse):
    """The anchored refit poses only the (segment, frame) rows its fits read, in one pass
    per request: the same poses as every segment on every frame (to rounding), also where
    gaps leave segments unposed, and a row asked for twice is posed once."""
    from jaxskel.joints import _anchored_centres as ac

    x, mask, truth, _ = sparse
    mask = mask.copy()
    mask[100:400, :5] = False
    s, seg = truth.n_segments, truth.marker_segment
    rot_all, t_all, posed_all = ac._segment_poses(x, mask, seg, s, ac.MAX_FRAMES)
    rows = ac._PoseRows(ac._mean_clouds(x, mask, seg, s, ac.MAX_FRAMES), x, mask)
    rng = np.random.default_rng(0)
    asked = [(int(rng.integers(s)), np.sort(rng.choice(x.shape[0], 50, replace=False))) for _ in range(6)]
    def keys(requests):
        return {(sg, int(f)) for sg, frames in requests for f in frames}

    rows.need(asked)
    assert rows._keys.size == len(keys(asked))  # each row posed once
    extra = (1, np.arange(90, 410))  # posed on demand by take
    for segment, frames in asked + [extra]:
        rot, t = rows.take(frames, segment)
        posed = posed_all[frames, segment]
        assert posed.any()
        np.testing.assert_allclose(rot[posed], rot_all[frames, segment][posed], atol=1e-12)
        np.testing.assert_allclose(t[posed], t_all[frames, segment][posed], atol=1e-12)
    rows.take(*asked[0][::-1])  # asked again: nothing new is posed
    assert rows._keys.size == len(keys(asked + [extra]))


def _sphere_misfit_einsum(x, mask, seg, s, frames, poses):
    """The anchored sphere misfit written with one einsum per sum over frames (F, S, M
    axes), the algebraic start and the Gauss-Newton steps exactly as documented."""
    from jaxskel.joints._pose_check import SPHERE_STEPS

    rot, t, posed = poses
    x, mask = x[frames], mask[frames]
    onehot = (seg[:, None] == np.arange(s)[None]).astype(float)
    p = np.einsum("faij,fmj->fami", rot, np.where(mask[..., None], x, 0.0)) + t[:, :, None, :]
    w = (posed[:, :, None] & mask[:, None, :]).astype(float)
    n = np.maximum(w.sum(axis=0), 1)
    sq = np.einsum("famj,famj->fam", p, p)
    pc = p - (np.einsum("fam,famj->amj", w, p) / n[..., None])[None]
    cov = np.einsum("fam,fami,famj->amij", w, pc, pc)
    g = np.einsum("fam,fami,fam->ami", w, pc, sq - (np.einsum("fam,fam->am", w, sq) / n)[None])
    centre = 0.5 * np.einsum("abij,abj->abi", np.linalg.pinv(np.einsum("amij,mb->abij", cov, onehot)),
                             np.einsum("ami,mb->abi", g, onehot))
    counts = np.maximum(onehot.sum(axis=0), 1)

    def about(c):
        off = p - c[:, seg][None]
        dist = np.linalg.norm(off, axis=-1)
        resid = dist - (np.einsum("fam,fam->am", w, dist) / n)[None]
        var = np.einsum("fam,fam->am", w, resid**2) / n
        return (var @ onehot) / counts[None], off / np.maximum(dist, 1e-12)[..., None], resid

    misfit, unit, resid = about(centre)
    for _ in range(SPHERE_STEPS):
        jac = unit - (np.einsum("fam,fami->ami", w, unit) / n[..., None])[None]
        normal = np.einsum("amij,mb->abij", np.einsum("fam,fami,famj->amij", w, jac, jac), onehot)
        step = np.einsum("abij,abj->abi", np.linalg.pinv(normal),
                         np.einsum("ami,mb->abi", np.einsum("fam,fami,fam->ami", w, jac, resid), onehot))
        trial_misfit, trial_unit, trial_resid = about(centre + step)
        better = trial_misfit < misfit
        if not better.any():
            break
        centre = np.where(better[..., None], centre + step, centre)
        misfit = np.where(better, trial_misfit, misfit)
        keep = better[:, seg][None]
        unit = np.where(keep[..., None], trial_unit, unit)
        resid = np.where(keep, trial_resid, resid)
    return misfit


def test_sphere_misfit_matches_the_per_frame_einsum_formulation(sparse):
    x, mask, truth, frames = sparse
    mask = mask.copy()
    mask[np.random.default_rng(3).random(mask.shape) < 0.1] = False  # scattered missing samples
    s, seg = truth.n_segments, truth.marker_segment
    poses = segment_poses(x, mask, seg, s, frames)
    m = sphere_misfit(x, mask, seg, s, frames, MIN_PAIR_FRAMES, poses=poses)
    want = _sphere_misfit_einsum(x, mask, seg, s, frames, poses)
    finite = np.isfinite(m)
    assert finite.sum() > s  # posed segments' pairs are judged
    np.testing.assert_allclose(m[finite], want[finite], rtol=1e-10, atol=0)
