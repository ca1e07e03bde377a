"""Joint costs, MST topology and full-frame joints (Kirk et al. §3.2) on synthetic ground truth."""

import numpy as np
import pytest
from helpers import off_axis_rmse, partition, random_rotation, segment_map, true_joint_index, true_partition
from soft_tissue_floor import fitted_errors, floor_skeleton

import jaxskel
from jaxskel import synth


def undirected(edges):
    return {frozenset(map(int, e)) for e in edges}


def mapped_edges(result, trial, truth):
    m = segment_map(result, trial, truth)
    return {frozenset((m[int(p)], m[int(c)])) for p, c in result.edges}


def cheapest_pairs_across_cuts(cost, edges):
    """For each tree edge, the cheapest other finite pair across the cut the edge's removal
    leaves (``None`` where there is none), by brute force: the rival each joint has."""
    out = []
    for e, (a, b) in enumerate(edges.tolist()):
        others = [tuple(f) for k, f in enumerate(edges.tolist()) if k != e]
        side, grown = {a}, True
        while grown:
            reach = {v for u, w in others for v in (u, w) if u in side or w in side}
            grown, side = not reach <= side, side | reach
        pairs = [(i, k) for i in sorted(side) for k in range(len(cost)) if k not in side and {i, k} != {a, b}]
        best = min(pairs, key=lambda pair: cost[pair], default=None)
        out.append(best if best is not None and np.isfinite(cost[best]) else None)
    return out


# ----------------------------------------------------------------------------- linkage
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_linkage_topology_and_middle_rod_length(seed):
    trial, truth = synth.simulate(synth.linkage(), duration=30.0, seed=seed, noise=0.001)
    result = jaxskel.fit_skeleton(trial, rigid=False, ik=False, seed=seed)
    assert result.n_segments == 3
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)
    (length,) = result.bone_lengths().values()
    assert abs(length - 0.341) / 0.341 < 0.003, length


# ----------------------------------------------------------------------------- full body
@pytest.fixture(scope="module")
def body_fit():
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, duration=30.0, seed=0, noise=0.002, soft_tissue=0.003, gaps=2)
    return trial, truth, jaxskel.fit_skeleton(trial)


def test_full_body_exact_topology(body_fit):
    trial, truth, result = body_fit
    assert result.n_segments == len(truth.segment_names)
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)
    m = segment_map(result, trial, truth)
    assert truth.segment_names[m[result.topology.root]] in ("pelvis", "torso")
    # joint costs and segment poses agree on every joint: the pose check exchanges nothing
    assert result.topology.pose_exchanges == () and "pose check:" not in result.summary()
    posed = np.bincount(result.segmentation.marker_segment, minlength=result.n_segments) >= 3
    checked = [result.topology.fixed_misfit[p, c] for p, c in result.edges if posed[p] and posed[c]]
    assert len(checked) == 12 and np.isfinite(checked).all()
    # edges are parent -> child with parents first
    seen = {result.topology.root}
    for p, c in result.edges:
        assert p in seen
        seen.add(int(c))


def test_full_body_tree_has_no_near_ties_and_every_rival_costs_more(body_fit):
    """Calibration motion settles every joint: no rival within the costs' sampling noise
    (the closest is 5 standard errors away on this family of bodies). The cut property of
    the minimum spanning tree: every rival costs at least its joint, so a zero noise
    allowance reports nothing and an unbounded one reports every joint but those whose
    rival the poses reject (a fixed-centre misfit over twice the joint's)."""
    trial, truth, result = body_fit
    assert result.near_ties() == []
    everything = jaxskel.joints.near_ties(result.trial, result.segmentation, result.topology, z=1e9)
    reported = [t.joint for t in everything]
    assert reported == sorted(reported) and len(reported) >= 1
    misfit = result.topology.fixed_misfit
    rivals = cheapest_pairs_across_cuts(result.topology.pair_costs.cost, result.edges)
    for j, (edge, rival) in enumerate(zip(result.edges.tolist(), rivals)):
        rejected = misfit[rival] > 2.0 * misfit[tuple(edge)]
        assert (j in reported) != rejected, (j, edge, rival)
    assert all(t.margin >= 0 and t.rival_cost >= t.cost for t in everything)
    assert jaxskel.joints.near_ties(result.trial, result.segmentation, result.topology, z=0.0) == []
    assert "near tie" not in result.summary()


def joint_rmse(result, trial, truth, j, positions):
    """RMSE (m) of joint j; for hinges only the part off the hinge axis (the part markers determine)."""
    tj = true_joint_index(result, trial, truth, j)
    return tj, off_axis_rmse(positions[:, j], truth, tj)


def bone_length_errors(result, truth, joint_of):
    """Relative error of every fitted bone against the true bone between the same joints
    (``joint_of``: fitted joint -> true joint)."""
    true_length = {frozenset(map(int, b)): length for b, length in zip(truth.bones, truth.bone_lengths)}
    return [
        abs(length / true_length[frozenset((joint_of[int(a)], joint_of[int(b)]))] - 1)
        for (a, b), length in zip(result.skeleton.bones, result.skeleton.bone_lengths)
    ]


def test_full_body_joint_centres(body_fit):
    """2 mm noise + 3 mm soft tissue, rigid-skeleton joints in 3-D (hinges along their axis
    included). Measured (seed 0): ball 2.2-4.4 mm, hinges 4.7-8.6 mm, wrists/ankles
    4.8-9.2 mm (before hinge placement and the light joint pin: hinges 42-57 mm, ankles
    12-52 mm). Per-frame (topology) ball joints: 4-8 mm."""
    trial, truth, result = body_fit
    for j in range(len(result.edges)):
        tj, per_frame = joint_rmse(result, trial, truth, j, result.joint_positions)
        err = result.motion.joint_positions[:, j] - truth.joint_positions[:, tj]
        rigid = np.sqrt(np.nanmean(np.sum(err**2, -1)))
        kind = truth.joint_types[tj]
        if kind == "ball":
            assert rigid < 0.006 and per_frame < 0.010, (truth.joint_names[tj], rigid, per_frame)
            assert result.topology.undetermined[j] == 0
        else:
            assert rigid < 0.013, (truth.joint_names[tj], rigid)
        if kind == "hinge":
            # along the axis the centre is not identifiable from markers; the fit says so
            assert result.topology.undetermined[j] >= 1


def test_full_body_calibration_determines_every_joint_and_bounds_every_bone(body_fit):
    """A calibration motion turns every joint about every axis it has: each centre is fixed
    to a few centimetres (measured, seed 0 with 3 mm soft tissue: 15-47 mm, knees and
    elbows past their axis), nothing is named undetermined, and every bone's error against
    the truth lies within the bound its joints' resolutions give it (0.4-5 mm against
    14-50 mm: a bound on what an artefact of the misfit's size could do, not an error bar)."""
    trial, truth, result = body_fit
    resolution = result.joint_resolutions()
    assert np.isfinite(resolution).all() and resolution.max() < 0.06, resolution
    assert result.undetermined_joints() == [] and "undetermined" not in result.summary()
    joint_of = {j: true_joint_index(result, trial, truth, j) for j in range(len(result.edges))}
    true_length = {frozenset(map(int, b)): length for b, length in zip(truth.bones, truth.bone_lengths)}
    bound = jaxskel.joints.bone_uncertainty(result.skeleton)
    assert np.isfinite(bound).all() and bound.max() < 0.06, bound
    for name, (a, b), length, u in zip(result.bone_lengths(), result.skeleton.bones, result.skeleton.bone_lengths,
                                       bound):
        error = abs(length - true_length[frozenset((joint_of[int(a)], joint_of[int(b)]))])
        assert error < u, (name, error, u)


@pytest.mark.parametrize(
    ("seed", "soft_tissue"), [(0, 0.0), (0, 0.001), (1, 0.001), (2, 0.001), (3, 0.001)]
)
def test_full_body_meets_the_accuracy_target(seed, soft_tissue):
    """The issue's numbers on several seeds: the calibration body with 2 mm noise and gaps,
    exact topology, joint-centre RMSE < 5 mm (over every joint and frame, in 3-D, hinges
    along their axis included), mean bone-length error < 0.5 %. Every ball joint and hinge
    is also held to 5 mm on its own; the 2-DOF wrists and ankles, which turn least, to
    6 mm. Measured (RMSE pooled; ball/hinge; wrist/ankle; bones): seed 0 without soft
    tissue 0.5-1.3 mm, 0.06 %; with 1 mm RMS per marker, seed 0 0.8-3.3 mm, 0.28 %;
    seed 1 3.9 mm worst joint, 0.21 %; seed 2 2.3 mm; 0.8-1.7; 2.3-5.0 mm; 0.39 %; seed 3
    3.0 mm worst, 0.26 % (seeds 4, 5: 2.2, 1.9 mm pooled, worst an ankle at 4.5, 3.9 mm).
    The wrists' and ankles' error is a constant offset in the parent's frame (seed 2, right
    ankle: 4.8 of its 5.0 mm; 0.3 mm without soft tissue): skin motion that follows a small
    joint range shifts the centre, and the oracle of ``tests/soft_tissue_floor.py`` does no
    better on ankles (seed 2: 4.3-5.1 mm, seed 4: 5.0-6.9 mm).
    Before the IK's input was low-passed, seed 0's joints were 1.2-2.5 mm and 1.6-4.0 mm.
    Above ~1.5 mm of soft tissue the error grows with the artefact like the oracle's floor
    (3 mm: 2-9 mm, 0.8 %; the tests above and below, ``bench/bench_soft_tissue.py``)."""
    trial, truth = synth.simulate(
        synth.full_body(seed=seed), duration=30.0, seed=seed, noise=0.002, soft_tissue=soft_tissue, gaps=2
    )
    result = jaxskel.fit_skeleton(trial)
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)
    joint_of, squared = {}, []
    for j in range(len(result.edges)):
        tj = true_joint_index(result, trial, truth, j)
        joint_of[j] = tj
        err = np.sum((result.motion.joint_positions[:, j] - truth.joint_positions[:, tj]) ** 2, -1)
        squared.append(err)
        rmse = np.sqrt(np.nanmean(err))
        limit = 0.006 if truth.joint_types[tj] == "universal" else 0.005
        assert rmse < limit, (truth.joint_names[tj], rmse)
    assert np.sqrt(np.nanmean(np.concatenate(squared))) < 0.005
    errors = bone_length_errors(result, truth, joint_of)
    assert len(errors) == len(truth.bone_lengths)
    assert np.mean(errors) < 0.005, errors


def test_soft_tissue_floor_oracle_is_exact_without_artefact():
    """The oracle (tests/soft_tissue_floor.py) recovers every joint it can pose exactly from
    clean markers, and reports no floor for the 2-marker hands."""
    trial, truth = synth.simulate(synth.full_body(seed=1), duration=10.0, seed=1)
    floor = floor_skeleton(trial, truth)
    hands = [j for j, name in enumerate(truth.joint_names) if "wrist" in name]
    posable = np.setdiff1d(np.arange(truth.n_joints), hands)
    assert np.isnan(floor["joint_rmse"][hands]).all()
    assert np.nanmax(floor["joint_rmse"][posable]) < 1e-9
    assert np.isfinite(floor["bone_error"]).sum() == 15 and np.nanmax(floor["bone_error"]) < 1e-9


def test_full_body_soft_tissue_error_is_within_the_oracle_floor(body_fit):
    """3 mm soft tissue moving with the joint angles: to first order indistinguishable from
    shifted joint centres, so no marker-only fit can remove it. The oracle, given every
    marker's true segment and offset and the true tree, poses each cluster and solves each
    joint by least squares; the articulated fit, given none of that, must reach the same
    scale on the same 12 joints and 15 bones. Measured (seed 0): bones 0.73 % vs floor
    1.25 %, joints 3.7 vs 6.3 mm mean. ``bench/bench_soft_tissue.py`` (0-5 mm, seeds 0-2):
    joints always below the floor (per-frame cluster poses jitter with the noise), bones
    0.55-0.89 of it on seeds 0-1 and 0.98-1.50 on seed 2, so the bone bound is 1.2x."""
    trial, truth, result = body_fit
    floor = floor_skeleton(trial, truth)
    fit = fitted_errors(result, trial, truth)
    joints, bones = np.isfinite(floor["joint_rmse"]), np.isfinite(floor["bone_error"])
    assert joints.sum() == 12 and bones.sum() == 15
    assert np.isfinite(fit["joint_rmse"]).all() and np.isfinite(fit["bone_error"]).all()
    assert np.mean(fit["bone_error"][bones]) < 1.2 * np.mean(floor["bone_error"][bones])
    assert np.mean(fit["joint_rmse"][joints]) < np.mean(floor["joint_rmse"][joints])
    # the floor is real: well above what noise alone leaves (0.06 %, 1.2-2.5 mm)
    assert np.mean(floor["bone_error"][bones]) > 0.005


def test_full_body_long_bone_lengths(body_fit):
    """3 mm soft tissue: thigh and upper arm (ball joint to hinge) within 1.5 % (measured
    0.3-1.0 %), the mean over all 17 bones under 1.5 % (0.83 %)."""
    trial, truth, result = body_fit
    lengths = dict(zip([truth.segment_names[s] for s in truth.bone_segment], truth.bone_lengths))
    joint_of = {j: true_joint_index(result, trial, truth, j) for j in range(len(result.edges))}
    checked = 0
    for (j0, j1), length in zip(result.skeleton.bones, result.skeleton.bone_lengths):
        pair = {truth.joint_names[joint_of[j0]], truth.joint_names[joint_of[j1]]}
        for side in "lr":
            for seg, ends in ((f"{side}_thigh", {f"{side}_hip", f"{side}_knee"}),
                              (f"{side}_upperarm", {f"{side}_shoulder", f"{side}_elbow"})):
                if pair == ends:
                    assert abs(length - lengths[seg]) / lengths[seg] < 0.015, (seg, length, lengths[seg])
                    checked += 1
    assert checked == 4
    errors = bone_length_errors(result, truth, joint_of)
    assert len(errors) == 17 and np.mean(errors) < 0.015, errors


def test_pairs_with_too_few_markers_are_infeasible_with_reason():
    """One marker on each hand and on the head: the right tree, pairs of one-marker segments
    infeasible with their reason, and every joint reported with its resolution. A
    one-marker segment's joint is fixed by that marker's path in its neighbour's frame
    (measured: neck 21 mm, wrists 16 mm, against 5-18 mm elsewhere), and each joint's
    error lies within it (neck 4.3 mm, wrists 1.6-3.1 mm)."""
    body = synth.full_body(seed=2, markers_per_segment={"l_hand": 1, "r_hand": 1, "head": 1})
    trial, truth = synth.simulate(body, duration=20.0, seed=2, noise=0.001)
    result = jaxskel.fit_skeleton(trial, len(truth.segment_names))
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)
    resolution = result.joint_resolutions()
    assert np.isfinite(resolution).all() and resolution.max() < 0.05 and result.undetermined_joints() == []
    for j in range(len(result.edges)):
        tj = true_joint_index(result, trial, truth, j)
        err = result.motion.joint_positions[:, j] - truth.joint_positions[:, tj]
        assert np.sqrt(np.nanmean(np.sum(err**2, -1))) < resolution[j], truth.joint_names[tj]
    assert result.untested_joints() == []  # the 1-marker segments' neighbours carry 4: all tested
    sizes = result.segmentation.segment_sizes
    one = np.flatnonzero(sizes == 1)
    reasons = result.topology.pair_costs.reasons
    for a in one:
        for b in one:
            if a < b:
                assert np.isinf(result.topology.pair_costs.cost[a, b])
                assert ">= 4" in reasons[(int(a), int(b))]


def test_two_markers_per_segment_give_the_exact_tree():
    """Two markers per segment (30 markers, several on joints: shoulder, elbow, knee, ankle),
    2 mm noise, 3 mm soft tissue, gaps. Every pair then has four markers, where the
    algebraic start has nothing to solve; started at the marker centroid the hips stopped
    in local minima 3-6 times their cost at the true joint and the thighs were jointed
    to each other (seeds 0-3). From the consistency start the tree is exact."""
    body = synth.full_body(seed=1, markers_per_segment=2)
    trial, truth = synth.simulate(body, duration=30.0, seed=1, noise=0.002, soft_tissue=0.003, gaps=1)
    result = jaxskel.fit_skeleton(trial, rigid=False, ik=False)
    assert partition(result.trial.labels, result.segmentation.marker_segment) == true_partition(trial, truth)
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)


def test_lone_hand_marker_next_to_a_two_marker_forearm_is_its_attachment(tmp_path):
    """One marker per hand, two per forearm (the sparse body of issue 42): hand + forearm
    carry three markers, too few for a joint cost, and the plain spanning tree jointed each
    hand to the upper arm, where a cost can be computed. The hand marker is most rigid with
    the forearm's markers (median distance std 13-16 mm against 65-91 mm to the upper
    arm's), so it hangs from the forearm as an attachment (jaxskel.joints._attachments), its joint
    placed by the distance prior alone: the tree is exact, nothing is left untested, and
    the attachments are reported and saved."""
    body = synth.full_body(seed=0, markers_per_segment={"l_hand": 1, "r_hand": 1, "l_forearm": 2, "r_forearm": 2})
    trial, truth = synth.simulate(body, duration=30.0, seed=0, noise=0.002, soft_tissue=0.003, gaps=1)
    result = jaxskel.fit_skeleton(trial, rigid=False, ik=False)
    assert mapped_edges(result, trial, truth) == undirected(truth.edges)
    assert result.untested_joints() == []
    m = segment_map(result, trial, truth)
    names = truth.segment_names
    found = {(names[m[a.segment]], names[m[a.host]], names[m[a.bridge]]) for a in result.topology.attachments}
    assert found == {(f"{s}_hand", f"{s}_forearm", f"{s}_upperarm") for s in "lr"}
    for a in result.topology.attachments:
        assert a.rigidity < 0.02
    # the prior places the wrist near the hand and forearm markers, as it should
    for j, (p, c) in enumerate(result.edges.tolist()):
        if {names[m[p]], names[m[c]]} in ({"l_hand", "l_forearm"}, {"r_hand", "r_forearm"}):
            assert np.isfinite(result.joint_positions[:, j]).any()
    result.save(tmp_path / "r.h5")
    loaded = jaxskel.load_result(tmp_path / "r.h5")
    assert loaded.topology.untested.shape == (0, 3)
    with pytest.raises(jaxskel.InputError, match="result.untested_joints"):
        jaxskel.joints.untested_joints(result, result.topology)
    # With two markers on each hand no segment is an attachment
    dense = synth.full_body(seed=0, markers_per_segment={"l_forearm": 2, "r_forearm": 2})
    trial, _ = synth.simulate(dense, duration=20.0, seed=0, noise=0.002, soft_tissue=0.003, gaps=1)
    dense_fit = jaxskel.fit_skeleton(trial, rigid=False, ik=False)
    assert dense_fit.untested_joints() == [] and dense_fit.topology.attachments == ()


def test_rigid_motion_and_marker_order_invariance():
    trial, truth = synth.simulate(synth.linkage(), duration=20.0, seed=4, noise=0.001)
    ref = jaxskel.fit_skeleton(trial, rigid=False, ik=False)
    rot, shift = random_rotation(3), np.array([1.5, -0.7, 2.0])
    moved = jaxskel.fit_skeleton(trial.transformed(rot, shift), rigid=False, ik=False)
    assert undirected(moved.edges) == undirected(ref.edges)
    np.testing.assert_allclose(
        moved.joint_positions, ref.joint_positions @ rot.T + shift, atol=2e-4
    )
    np.testing.assert_allclose(moved.topology.joint_cost, ref.topology.joint_cost, rtol=1e-3, atol=1e-9)
    perm = np.random.default_rng(0).permutation(trial.n_markers)
    shuffled = jaxskel.fit_skeleton(trial.select_markers(perm), rigid=False, ik=False)
    assert sorted(shuffled.bone_lengths().values()) == pytest.approx(sorted(ref.bone_lengths().values()), abs=1e-4)


@pytest.mark.extended  # about 2 min on 2 cores; test_a_walk_alone_names_the_joints_it_cannot_place runs by default
def test_walk_leaves_wrists_unjointed_and_a_calibration_trial_recovers_them():
    """The issue's walking case. In a walk the wrists barely turn (< 2 degrees), so the
    hand's markers are rigid with the forearm's: fitted alone, no segment separates a hand
    from its forearm and no wrist joint is invented (no confident wrong answer). Fitted
    together with a calibration trial of the same subject (the paper's recovery of wrists
    from walking data), the segmentation and tree are exact and the wrist centres, in the
    walking frames, are within 1 cm."""
    body = synth.full_body(seed=0)
    walk, walk_truth = synth.simulate(body, "walk", duration=12.0, seed=2, noise=0.002, gaps=1)
    calibration, _ = synth.simulate(body, duration=12.0, seed=3, noise=0.002, gaps=1)

    alone = jaxskel.fit_skeleton(walk, rigid=False, ik=False)
    names = walk_truth.segment_names
    idx = [walk.labels.index(lab) for lab in alone.trial.labels]
    true_seg = walk_truth.marker_segment[idx]
    for side in "lr":
        hand, forearm = names.index(f"{side}_hand"), names.index(f"{side}_forearm")
        groups = set(alone.segmentation.marker_segment[true_seg == hand])
        assert groups <= set(alone.segmentation.marker_segment[true_seg == forearm]), side
    assert alone.n_segments < len(names)

    both = jaxskel.fit_skeleton([walk, calibration])
    assert both.n_segments == len(names)
    assert mapped_edges(both, walk, walk_truth) == undirected(walk_truth.edges)
    start, stop = both.trial_bounds[0]
    assert (start, stop) == (0, walk.n_frames)
    # The junction of the two recordings is neither a jump nor a gap edge: cleaning keeps
    # the frames on both sides of it (it used to drop three on each side, which IK then
    # filled by interpolating from one recording into the other, metres off).
    assert both.trial.mask[stop - 3 : stop + 3].sum(axis=1).min() >= walk.n_markers - 4
    for j in range(len(both.edges)):
        tj = true_joint_index(both, walk, walk_truth, j)
        if walk_truth.joint_names[tj].endswith("wrist"):
            err = both.motion.joint_positions[start:stop, j] - walk_truth.joint_positions[:, tj]
            rmse = np.sqrt(np.nanmean(np.sum(err**2, -1)))
            print(walk_truth.joint_names[tj], f"{1e3 * rmse:.1f} mm")
            assert rmse < 0.01, (walk_truth.joint_names[tj], rmse)


@pytest.mark.extended  # about a minute on 2 cores; CI runs the rest
def test_a_walk_alone_names_the_joints_it_cannot_place():
    """The issue's "never a confident wrong answer" on the walk that used to say nothing
    (seed 15, 30 s, the bench's conditions: 2 mm noise, 1 mm soft tissue, gaps). Its
    wrists, elbows and neck hardly move, so each arm comes out as one group hanging off a
    trunk-pelvis-head group (9 segments, measured). The fit now names the joints the walk
    does not fix: both shoulders (resolutions 290-310 mm: where an arm-long group is
    jointed to the trunk is anyone's guess), both hips (138-145 mm: a walk turns them about
    one axis) and the ankles, in a DegenerateMotionWarning and the summary. The pelvis
    width, the hips' distance, is 134 mm short, and its bound says so (+-172 mm)."""
    body = synth.full_body(seed=15)
    trial, truth = synth.simulate(body, "walk", duration=30.0, seed=15, noise=0.002, soft_tissue=0.001, gaps=2)
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="undetermined") as caught:
        result = jaxskel.fit_skeleton(trial, ik=False)
    assert result.n_segments < len(truth.segment_names)
    named = {result.joint_name(u.joint) for u in result.undetermined_joints()}
    (message,) = [str(w.message) for w in caught if "undetermined" in str(w.message)]
    assert named and all(name in message for name in named)
    m = segment_map(result, trial, truth)
    arms = {truth.segment_names.index(f"{side}_{part}") for side in "lr" for part in ("upperarm", "forearm", "hand")}
    joints_to_arms = [j for j, (p, c) in enumerate(result.edges) if (m[int(p)] in arms) != (m[int(c)] in arms)]
    assert len(joints_to_arms) == 2 and {result.joint_name(j) for j in joints_to_arms} <= named
    pelvis = result.segmentation.marker_segment[result.trial.labels.index("LASI")]
    thighs = {truth.segment_names.index(f"{side}_thigh") for side in "lr"}
    hips = [j for j, (p, c) in enumerate(result.edges) if pelvis in (p, c) and m[int(p + c - pelvis)] in thighs]
    assert len(hips) == 2 and {result.joint_name(j) for j in hips} <= named
    text = result.summary()
    for name in named:  # its row says undetermined, not a length, and a line the motion it lacks
        row, lack = [line.strip() for line in text.splitlines() if line.strip().startswith(f"{name}:")]
        assert row.endswith("undetermined") and lack.startswith(f"{name}: needs ")
    assert "> 10 m" not in text
    (b,) = [b for b, pair in enumerate(result.skeleton.bones.tolist()) if set(pair) == set(hips)]
    bone = list(result.bone_lengths())[b]  # its name: bone_lengths() follows result.skeleton.bones
    (width,) = [line for line in text.splitlines() if line.startswith(f"  {bone}:")]
    assert "undetermined (joints " in width and all(result.joint_name(j) in width for j in hips)
    true_hips = [truth.joint_names.index(f"{side}_hip") for side in "lr"]
    true_width = np.linalg.norm(np.subtract(*truth.joint_positions[0, true_hips]))
    assert abs(result.skeleton.bone_lengths[b] - true_width) < jaxskel.joints.bone_uncertainty(result.skeleton)[b]
