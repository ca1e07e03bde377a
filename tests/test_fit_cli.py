"""fit_skeleton end to end: result object, HDF5 result file, command line, errors."""

import dataclasses
import json
import os
import subprocess
import sys
import warnings

import h5py
import numpy as np
import pytest

import jaxskel
from jaxskel.result._bvh import bvh_frame
from jaxskel import synth
from jaxskel.cli import main


@pytest.fixture(scope="module")
def linkage_trial():
    trial, truth = synth.simulate(synth.linkage(), duration=15.0, seed=5, noise=0.001, gaps=1)
    return trial, truth


@pytest.fixture(scope="module")
def fitted(linkage_trial):
    trial, _ = linkage_trial
    return jaxskel.fit_skeleton(trial)


def test_result_holds_every_stage(fitted, linkage_trial):
    trial, truth = linkage_trial
    r = fitted
    assert r.cleaning is not None and r.segmentation.n_segments == 3
    assert r.topology.edges.shape == (2, 2) and r.joint_positions.shape == (trial.n_frames, 2, 3)
    assert set(r.timings) >= {"clean", "segment", "joint costs", "tree joints"}
    assert r.topology.converged.all() and (r.topology.steps > 0).all()
    text = r.summary()
    assert "3 segments, 2 joints" in text and "bone lengths" in text
    # the spectrum behind the count: the eigengap's choice heads the candidates
    (k, gap), *others = r.segmentation.count_candidates()
    assert k == r.segmentation.eigengap_segments == 3
    assert all(gap > g for _, g in others)
    assert f"segment count: eigengap; largest eigengaps after k = 3 ({gap:.3f})" in text
    assert f"white noise {1e3 * r.segmentation.white_noise:.2f} mm (taken out of A)" in text


def test_spectrum_plot_marks_the_count(fitted):
    ax = jaxskel.plots.plot_spectrum(fitted)
    assert len(ax.lines[0].get_ydata()) == len(fitted.segmentation.eigenvalues)
    assert "eigengap: 3" in [t.get_text() for t in ax.get_legend().get_texts()]


def test_a_count_grown_to_the_most_rigid_is_said_in_the_summary_and_the_plot(fitted):
    """The summary and the spectrum plot say how a ``"most rigid"`` count was reached and name
    the rigid count passed over (the rule itself: tests/segment/test_grow_count.py)."""
    seg = dataclasses.replace(fitted.segmentation, count_rule="most rigid", eigengap_segments=2, rigid_count=5)
    grown = dataclasses.replace(fitted, segmentation=seg)
    assert (
        "segment count: grown from the eigengap's 2 to the count whose least rigid group is the most rigid, short "
        "of the first count with every group rigid (5), which leaves a marker alone"
    ) in grown.summary()
    ax = jaxskel.plots.plot_spectrum(grown)
    assert "used: 3 (grown to the most rigid)" in [t.get_text() for t in ax.get_legend().get_texts()]
    # no rigid count up to max_segments (rigid_count 0): the summary says so, and names no count
    seg = dataclasses.replace(seg, rigid_count=0, max_segments=7)
    text = dataclasses.replace(fitted, segmentation=seg).summary()
    assert (
        "segment count: grown from the eigengap's 2 to the count whose least rigid group is the most rigid, as no "
        "count up to 7 has every group rigid"
    ) in text
    assert "(0)" not in text


def test_result_file_schema_roundtrip(fitted, tmp_path):
    path = tmp_path / "out.h5"
    fitted.save(path)
    with pytest.raises(jaxskel.InputError, match="exists"):
        fitted.save(path)
    back = jaxskel.load_result(path)
    assert back.attrs["schema_version"] == 1 and back.attrs["units"] == "m"
    assert list(back.markers.labels) == list(fitted.input_labels)
    np.testing.assert_array_equal(back.topology.edges, fitted.edges)
    np.testing.assert_allclose(back.joints.positions, fitted.joint_positions, equal_nan=True)
    assert back.topology.joint_cost.shape == (3, 3) and np.isinf(back.topology.joint_cost[0, 0])
    assert int(back.topology.root) == fitted.topology.root
    # segments named from their markers (R1M1, R1M2, R1M3 -> R1M), in the file as in the result
    assert fitted.segment_names == ("R1M", "R2M", "R3M")
    assert list(back.segments.names) == list(fitted.segment_names)
    # the pose check: every linkage rod carries three markers, so every pair has a misfit;
    # the true joints fit (the MST kept), the rods' ends do not
    np.testing.assert_allclose(back.topology.fixed_misfit, fitted.topology.fixed_misfit)
    assert np.isfinite(back.topology.fixed_misfit[~np.eye(3, dtype=bool)]).all()
    assert back.topology.pose_exchanges.shape == (0, 4) == back.topology.pose_exchanges_values.shape
    seg_attrs = dict(back.segments.attrs)
    assert seg_attrs["count_rule"] == fitted.segmentation.count_rule == "eigengap"
    assert seg_attrs["max_segments"] == fitted.segmentation.max_segments
    # the recording's 1 mm of white noise, and the limit restated on A as measured
    assert seg_attrs["white_noise"] == fitted.segmentation.white_noise == pytest.approx(0.001, rel=0.05)
    assert seg_attrs["rigid_limit"] == pytest.approx(np.hypot(3.0 * fitted.segmentation.sigma, np.sqrt(2) * seg_attrs["white_noise"]))
    assert (back.markers.segment >= 0).all() and back.markers.physical.tolist() == list(range(9))
    assert "joints_steps" in back.diagnostics.keys()
    # the rigid stage's diagnostics come back as JSON (they were once written as a repr)
    rigid = json.loads(back.diagnostics.attrs["rigid"])
    assert rigid["sweeps"] == fitted.skeleton.diagnostics["sweeps"]
    assert len(rigid["hinge_shift"]) == len(fitted.edges)
    # how well the recording fixes each joint and bone (jaxskel.joints._determination)
    np.testing.assert_allclose(back.joints.resolution, fitted.joint_resolutions())
    assert np.isfinite(back.joints.resolution).all() and back.joints.undetermined.shape == (0,)
    np.testing.assert_allclose(back.skeleton.bone_uncertainty, jaxskel.joints.bone_uncertainty(fitted.skeleton))
    assert back.skeleton.bone_uncertainty.shape == back.skeleton.bone_lengths.shape
    # a reader of a newer schema refuses with a clear message
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(jaxskel.SchemaError, match="upgrade"):
        jaxskel.load_result(path)


def test_a_result_file_without_segment_names_still_loads_with_them(fitted, tmp_path, capsys):
    """A file written without /segments/names reads back with the names derived from its
    markers, the same as those written; bones by marker labels and `jaxskel info` work."""
    path = tmp_path / "old.h5"
    fitted.save(path)
    bone = ("R1M1", "R2M1", "R3M1")  # the linkage's one bone, its middle rod, by marker labels
    assert len(fitted.skeleton.bones) == 1
    length = jaxskel.pipeline.bone_length(jaxskel.load_result(path), bone)
    with h5py.File(path, "a") as f:
        del f["segments/names"]
    back = jaxskel.load_result(path)
    assert list(back.segments.names) == list(fitted.segment_names)
    assert np.isfinite(length) and jaxskel.pipeline.bone_length(back, bone) == length
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    root = fitted.segment_names[fitted.topology.root]
    assert f"root {root} (segment {fitted.topology.root})" in out and "segments: R1M, R2M, R3M" in out


def test_a_duplicated_marker_changes_nothing_and_maps_to_its_original(fitted, linkage_trial, tmp_path):
    """A marker stored a second time under an unnamed label (as in HDM05's files), the
    named one with a gap its copy covers: cleaning merges them into the recording the
    fit saw without a copy, so the skeleton is the same; the copy is reported and has
    its original's segment and physical marker in the result and the file."""
    trial, _ = linkage_trial
    x = np.concatenate([trial.positions, trial.positions[:, :1]], axis=1)
    x[100:160, 0] = np.nan
    twice = jaxskel.Trial(x, (*trial.labels, "*9"), trial.rate)
    result = jaxskel.fit_skeleton(twice)
    assert result.cleaning.duplicates == {"*9": trial.labels[0]}
    assert f"duplicate labels merged (one marker stored twice): *9 -> {trial.labels[0]}" in result.summary()
    np.testing.assert_array_equal(result.segmentation.marker_segment, fitted.segmentation.marker_segment)
    np.testing.assert_allclose(result.skeleton.bone_lengths, fitted.skeleton.bone_lengths, rtol=1e-9)
    segment = result.marker_segment_input()
    assert segment[-1] == segment[0] >= 0 and result.physical_input()[-1] == 0
    result.save(tmp_path / "twice.h5")
    back = jaxskel.load_result(tmp_path / "twice.h5")
    assert back.markers.segment[-1] == segment[0] and back.markers.physical[-1] == 0
    assert list(back.diagnostics.cleaning.duplicates) == ["*9"]
    assert list(back.diagnostics.cleaning.duplicate_of) == [trial.labels[0]]


@pytest.mark.extended  # about 2 min on 2 cores; the split search's other cases run by default
def test_a_count_that_does_not_help_does_not_end_the_split_search(capsys):
    """A random 10-segment tree where the eigengap (8) joins two pairs of segments, each
    joint moving its markers little. One more segment cuts one pair but leaves the other
    (as many flagged markers as before, so 9 is not kept); the search goes on to 10, which
    flags nothing: the true tree, no warning. (Before, the search stopped at 9 and kept 8
    groups with a wrong tree.) The progress bar counts the two refits' stages: it ends at
    its total, 6 + 2 x 4 stages (before, it ran past a total of 6 and lost it)."""
    import re

    from helpers import segment_map

    trial, truth = synth.simulate(synth.random_tree(10, seed=10), duration=20.0, seed=10, noise=0.001, gaps=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial, ik=False, progress=True)
    bar = [line for line in re.split(r"[\r\n]", capsys.readouterr().err) if line.startswith("fit_skeleton")][-1]
    assert re.search(r"\| (\d+)/(\d+) \[", bar).groups() == ("14", "14"), bar
    seg = result.segmentation
    assert (seg.count_rule, seg.eigengap_segments, seg.split_from, result.n_segments) == ("split", 8, 8, 10)
    assert result.skeleton.nonrigid_markers == ()
    assert not [w for w in caught if issubclass(w.category, jaxskel.NonRigidMarkerWarning)]
    named = segment_map(result, trial, truth)
    assert sorted(named.values()) == list(range(10))
    fitted = {frozenset((named[int(p)], named[int(c)])) for p, c in result.edges}
    assert fitted == {frozenset(map(int, e)) for e in truth.edges}


def test_a_hinge_turning_about_its_childs_own_axis_is_split_by_the_groups_scatter():
    """A random 4-segment tree whose hinge turns nearly about the child rod's own axis: its
    markers' distances to the parent's vary by under 5 mm, below the rigidity limit, and
    the eigengap (3) puts both segments in one group. The rigid skeleton fitted to that
    group does not flag two of its markers (the joined group bends the fit, and the median
    residual grows with it), but the group's own Procrustes scatter does: one more segment
    mends it, and the fit has the true groups and the true tree."""
    from helpers import partition, segment_map

    trial, truth = synth.simulate(synth.random_tree(4, seed=11), duration=20.0, seed=11, noise=0.001, gaps=2)
    result = jaxskel.fit_skeleton(trial, ik=False)
    seg = result.segmentation
    assert (seg.count_rule, seg.split_from, result.n_segments) == ("split", 3, 4)
    idx = [trial.labels.index(lab) for lab in result.trial.labels]
    assert partition(result.trial.labels, seg.marker_segment) == partition(
        result.trial.labels, truth.marker_segment[idx])
    named = segment_map(result, trial, truth)
    assert {frozenset((named[int(p)], named[int(c)])) for p, c in result.edges} == {
        frozenset(map(int, e)) for e in truth.edges}
    assert "grown from 3 (automatic)" in result.summary()


def test_a_joint_between_posed_segments_gives_way_to_a_two_marker_hub():
    """A random 8-segment tree whose two-marker segment 3 is a hub (jointed to 1, 4, 5 and
    6). The joint costs' spanning tree joins 4 to 1 instead of 3 to 1. The fixed-centre
    check cannot judge 1-3 (3 has no pose), and the sparse-segment check judges only
    edges to sparse segments; the pass that judges edges between posed segments against
    rivals with a sparse segment, by the sphere misfit about the centre of least variance,
    sees 4's markers keep 13 mm^2 about any centre fixed in 1 and 3's keep 2 mm^2 about
    one fixed in 1: it exchanges 1-4 for 1-3, and the tree is the true one."""
    from helpers import segment_map

    trial, truth = synth.simulate(synth.random_tree(8, seed=9), duration=20.0, seed=9, noise=0.001, gaps=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial, ik=False)
    named = segment_map(result, trial, truth)
    assert sorted(named.values()) == list(range(8))
    assert {frozenset((named[int(p)], named[int(c)])) for p, c in result.edges} == {
        frozenset(map(int, e)) for e in truth.edges}
    (exchange,) = result.topology.pose_exchanges
    assert exchange.test == "sphere" and exchange.misfit[1] * 2 < exchange.misfit[0]
    assert {frozenset(named[s] for s in exchange.removed), frozenset(named[s] for s in exchange.added)} == {
        frozenset((1, 4)), frozenset((1, 3))}
    assert frozenset(named[s] for s in exchange.added) == frozenset((1, 3))


@pytest.mark.extended  # 1-3 min on 2 cores; tests/pipeline/test_split_refit.py covers the split refit by default
def test_two_segments_clustered_as_one_are_split_after_the_rigid_fit(tmp_path):
    """A random 12-segment tree whose joint 9-10 moves its markers little against each
    other (largest distance std 7 mm, 5x the 1.4 mm noise floor but under the 9 mm
    rigidity limit): the eigengap (11, gap 0.32 against 0.20 at 12) puts both segments in
    one group. The rigid skeleton cannot hold that group (two of its markers flagged), so
    the automatic count grows to 12 and the fit runs again: the true groups, nothing
    flagged, the IK on the kept skeleton, the discarded fit's warning not shown. The joint
    costs' tree has one wrong joint, a near tie (5.04 against 5.12 mm^2 for the true
    joint); one of its segments carries two markers, and the sphere check (their markers
    about a centre fixed in the neighbour's pose) exchanges it for the true joint: the
    tree is exact and no near tie is left. Given ``n_segments=11`` the count stays, and
    the fit names the markers with the count to try."""
    from helpers import partition, segment_map

    trial, truth = synth.simulate(synth.random_tree(12, seed=3), duration=20.0, seed=3, noise=0.001, gaps=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial)
    assert not [w for w in caught if issubclass(w.category, jaxskel.NonRigidMarkerWarning)]
    seg = result.segmentation
    assert (seg.count_rule, seg.split_from, result.n_segments, seg.eigengap_segments) == ("split", 11, 12, 11)
    assert seg.split_markers and all(lab.startswith(("S9M", "S10M")) for lab in seg.split_markers)
    idx = [trial.labels.index(lab) for lab in result.trial.labels]
    assert partition(result.trial.labels, seg.marker_segment) == partition(
        result.trial.labels, truth.marker_segment[idx])
    assert result.skeleton.nonrigid_markers == () and "not rigid on their segment" not in result.summary()
    assert "grown from 11 (automatic)" in result.summary()
    named = segment_map(result, trial, truth)
    true_joints = {frozenset(map(int, e)) for e in truth.edges}
    fitted = {frozenset((named[int(p)], named[int(c)])) for p, c in result.edges}
    assert fitted == true_joints and result.near_ties() == []
    (exchange,) = result.topology.pose_exchanges
    assert exchange.test == "sphere" and exchange.misfit[1] * 2 < exchange.misfit[0]
    assert frozenset(named[s] for s in exchange.added) in true_joints
    assert frozenset(named[s] for s in exchange.removed) not in true_joints
    assert not [w for w in caught if issubclass(w.category, jaxskel.AmbiguousTreeWarning)]
    assert result.motion is not None and result.settings["ik"] is True
    assert result.motion.rotations.shape[1] == 12 and len(result.edges) == 11
    out = tmp_path / "split.h5"
    result.save(out)
    with h5py.File(out) as f:
        assert f["segments"].attrs["count_rule"] == "split" and f["segments"].attrs["split_from"] == 11
        assert [v.decode() for v in f["segments/split_markers"][()]] == list(seg.split_markers)
        assert f["topology/near_ties"][()].shape == (0, 3)
        assert f["topology/pose_exchanges"][()].tolist() == [[*exchange.removed, *exchange.added]]
        assert [v.decode() for v in f["topology/pose_exchanges_test"][()]] == ["sphere"]

    with pytest.warns(jaxskel.NonRigidMarkerWarning, match="n_segments=12") as caught:
        given = jaxskel.fit_skeleton(trial, 11, ik=False)
    assert given.n_segments == 11 and given.segmentation.count_rule == "given"
    flagged = set(given.skeleton.nonrigid_markers)
    assert len(flagged) >= 2 and all(lab.startswith(("S9M", "S10M")) for lab in flagged), flagged
    (named_markers,) = [w for w in caught if issubclass(w.category, jaxskel.NonRigidMarkerWarning)]
    assert all(lab in str(named_markers.message) for lab in flagged)
    assert "not rigid on their segment" in given.summary() and "n_segments=12" in given.summary()


def test_a_group_that_is_not_rigid_is_named_with_the_count_to_compare(tmp_path):
    """Where the automatic count keeps a non-rigid group (the first rigid count would leave
    a marker alone, tests/segment/test_segment.py), the fit warns with the group, its two markers and
    that count; the summary says the same and the file keeps the count."""
    from helpers import linkage_with_a_bending_marker

    trial = linkage_with_a_bending_marker()
    with pytest.warns(jaxskel.NonRigidMarkerWarning, match="compare n_segments=4") as caught:
        result = jaxskel.fit_skeleton(trial, sigma=0.006, ik=False)
    (groups,) = [w for w in caught if "segment(s) not rigid" in str(w.message)]
    message = str(groups.message)
    assert message.startswith("1 segment(s) not rigid") and "R3M1 and R3M3" in message
    assert "compare n_segments=4 (--segments 4)" in message
    assert groups.filename == __file__  # pointed at the caller's line
    assert result.segmentation.rigid_count == 4 and result.n_segments == 3
    assert "R3M1 and R3M3 move relative to each other" in result.summary()
    assert "compare n_segments=4 (--segments 4)" in result.summary()
    result.save(tmp_path / "bent.h5")
    with h5py.File(tmp_path / "bent.h5") as f:
        assert f["segments"].attrs["rigid_count"] == 4
    # the count it names makes every group rigid: no such warning then
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        four = jaxskel.fit_skeleton(trial, 4, sigma=0.006, ik=False)
    assert four.segmentation.nonrigid_groups() == []
    assert not [w for w in caught if "not rigid:" in str(w.message)]


def test_cli_fit_writes_outputs_and_refuses_overwrite(linkage_trial, tmp_path, capsys):
    trial, _ = linkage_trial
    src = tmp_path / "link.c3d"
    trial.save(src)
    out = tmp_path / "res.h5"
    fig = tmp_path / "fig.png"
    assert main(["fit", str(src), "-o", str(out), "--plot", str(fig), "--quiet", "--no-rigid"]) == 0
    assert out.is_file() and fig.stat().st_size > 10_000
    plain = tmp_path / "plain.h5"
    assert main(["fit", str(src), "-o", str(plain), "--quiet", "--no-rigid", "--no-pose-check"]) == 0
    for path, checked in ((out, True), (plain, False)):
        with h5py.File(path) as f:
            assert json.loads(f["diagnostics"].attrs["settings"])["pose_check"] is checked
    assert main(["fit", str(src), "-o", str(out), "--quiet", "--no-rigid"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["fit", str(src), "-o", str(src), "--quiet", "--overwrite"]) == 2
    assert jaxskel.load(src).n_markers == trial.n_markers  # the input survived
    bvh = tmp_path / "res.bvh"
    assert main(["fit", str(src), "-o", str(tmp_path / "joints.h5"), "--bvh", str(bvh), "--quiet", "--no-rigid"]) == 2
    assert "drop --no-rigid" in capsys.readouterr().err and not bvh.exists()
    assert not (tmp_path / "joints.h5").exists()  # refused before the fit, not after it
    assert main(["fit", str(src), "-o", str(tmp_path / "joints.h5"), "--trc", str(tmp_path / "m.trc"), "--quiet",
                 "--no-ik"]) == 2
    assert "--no-ik" in capsys.readouterr().err and not (tmp_path / "joints.h5").exists()
    model, trc = tmp_path / "full.osim", tmp_path / "full.trc"
    sto = tmp_path / "angles.sto"
    assert main(["fit", str(src), "-o", str(tmp_path / "full.h5"), "--bvh", str(bvh), "--osim", str(model), "--trc",
                 str(trc), "--angles", str(sto), "--quiet"]) == 2
    err = capsys.readouterr().err  # the linkage is not a human body: no angles, every other output written
    assert f"--angles {sto} was not written" in err and "human" in err and not sto.exists()
    data = jaxskel.result.read_bvh(bvh)
    assert data.n_frames == trial.n_frames and len(data.names) == 3
    assert data.frame_time == pytest.approx(1.0 / trial.rate)
    # --osim: the model (bodies and markers as fitted), and the TRC in its frame (Y up) for OpenSim's IK
    import xml.etree.ElementTree as ET

    root = ET.parse(model).getroot()
    assert len(root.findall("Model/BodySet/objects/Body")) == 3
    assert [m.get("name") for m in root.findall("Model/MarkerSet/objects/Marker")] == list(trial.labels)
    fitted = jaxskel.load_result(tmp_path / "full.h5").motion.fitted_markers
    exported = jaxskel.load(trc)
    assert exported.up_axis == "y"
    np.testing.assert_allclose(exported.positions, jaxskel.result.to_opensim_frame(fitted, trial.up_axis), atol=1e-5)


@pytest.mark.extended  # about a minute on 2 cores; CI runs the rest
def test_cli_warnings_are_one_labelled_message(tmp_path, capsys):
    """A fit that warns (the random tree of the test above, given one segment too few: the
    rigid skeleton names the markers it cannot hold) prints the warning as the tool's own
    line, with no Python file path or source line."""
    trial, _ = synth.simulate(synth.random_tree(12, seed=3), duration=20.0, seed=3, noise=0.001, gaps=2)
    src = tmp_path / "tree.c3d"
    trial.save(src)
    assert main(["fit", str(src), "-o", str(tmp_path / "out.h5"), "--segments", "11", "--quiet"]) == 0
    err = capsys.readouterr().err
    named = [line for line in err.splitlines() if line.startswith("jaxskel: warning (NonRigidMarkerWarning): markers")]
    assert len(named) == 1 and "n_segments=12" in named[0], err
    assert "cli.py" not in err and "fit_skeleton(" not in err


def test_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "broken.c3d"
    bad.write_bytes(b"not a c3d file at all")
    assert main(["fit", str(bad), "-o", str(tmp_path / "x.h5"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxskel: error:") and "broken.c3d" in err and "Traceback" not in err


def test_wrong_units_are_caught(linkage_trial):
    trial, _ = linkage_trial
    in_mm = trial.replace(positions=trial.positions * 1000)
    with pytest.raises(jaxskel.InputError, match="millimetres"):
        jaxskel.fit_skeleton(in_mm)


def test_too_few_markers_and_bad_arguments(linkage_trial):
    trial, _ = linkage_trial
    with pytest.raises(jaxskel.DegenerateMotionError, match="the recording has 2 markers; a skeleton needs at least 3"):
        jaxskel.fit_skeleton(trial.select_markers([0, 1]))
    with pytest.raises(jaxskel.InputError):
        jaxskel.fit_skeleton("walk.c3d")
    with pytest.raises(jaxskel.InputError, match="merge_labels"):
        jaxskel.fit_skeleton(trial, merge_labels="sometimes")


def test_a_segment_no_joint_can_reach_is_named_not_a_crash(linkage_trial):
    """The third rod is seen only while the other two are not: no joint can be fitted to
    it, the joint-cost graph is a forest and there is no single skeleton tree. This
    raised an InputError from inside the rigid fit ("edges refer to segments outside
    0..1"); it is a typed error that names the segment and says what to do, and
    ``rigid=False`` still returns the segmentation and the joints that can be fitted."""
    trial, _ = linkage_trial
    x = trial.positions.copy()
    third = [i for i, label in enumerate(trial.labels) if label.startswith("R3")]
    others = [i for i in range(trial.n_markers) if i not in third]
    half = trial.n_frames // 2
    x[:half, third] = np.nan
    x[half:, others] = np.nan
    apart = trial.replace(positions=x)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the forest's own warning, label merging
        with pytest.raises(jaxskel.DegenerateMotionError, match=r"1 of the 3 segments.*R3M \(3 markers\).*rigid=False"):
            jaxskel.fit_skeleton(apart, merge_labels=False)
        partial = jaxskel.fit_skeleton(apart, merge_labels=False, rigid=False)
    assert partial.n_segments == 3 and len(partial.edges) == 1 and partial.skeleton is None
    rod = partial.segmentation.marker_segment[third]
    assert len(set(rod.tolist())) == 1 and rod[0] not in partial.edges


def test_two_trials_fit_together_and_export_bvh_per_trial(linkage_trial, tmp_path):
    trial, truth = linkage_trial
    a, b = trial[: trial.n_frames // 2], trial[trial.n_frames // 2 :]
    r = jaxskel.fit_skeleton([a, b])
    assert r.trial_bounds == ((0, a.n_frames), (a.n_frames, trial.n_frames))
    assert r.n_segments == 3 and len(r.edges) == 2
    # BVH straight from the result: segment names, the recording's rate, one trial's frames, Y up in centimetres.
    assert not r.anatomy.humanoid  # a linkage: named by its segments, the lab frame turned to Y up
    second = jaxskel.result.read_bvh(r.export_bvh(tmp_path / "second.bvh", trial=1))
    assert set(second.names) == set(r.segment_names)
    assert second.n_frames == b.n_frames and second.frame_time == pytest.approx(1.0 / trial.rate)
    root = second.names.index(r.segment_names[r.skeleton.root])
    lab_to_bvh = bvh_frame(r.anatomy, r.trial.up_axis) * 100.0
    np.testing.assert_allclose(second.world_positions()[:, root], r.motion.root_position[a.n_frames :] @ lab_to_bvh.T,
                               atol=1e-4)
    assert jaxskel.result.read_bvh(r.export_bvh(tmp_path / "all.bvh")).n_frames == trial.n_frames
    with pytest.raises(jaxskel.InputError, match="trial must be an index 0..1"):
        r.export_bvh(tmp_path / "third.bvh", trial=2)
    with pytest.raises(jaxskel.InputError, match="rigid=True and ik=True"):
        dataclasses.replace(r, motion=None).export_bvh(tmp_path / "none.bvh")
    assert not (tmp_path / "third.bvh").exists() and not (tmp_path / "none.bvh").exists()


def test_console_script_version():
    out = subprocess.run([sys.executable, "-m", "jaxskel.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.startswith("jaxskel ")


def test_cli_parameterize_writes_normalized_and_parameters(tmp_path, monkeypatch, capsys):
    body = synth.full_body(seed=1)
    trial, _ = synth.simulate(body, duration=10.0, seed=1, noise=0.001)
    src = tmp_path / "body.c3d"
    trial.save(src)
    out = tmp_path / "body.h5"
    fitted = []
    fit = jaxskel.fit_skeleton

    def fit_once(*args, **kwargs):  # one fit serves every command below (the flags act after it)
        if not fitted:
            fitted.append(fit(*args, **kwargs))
        return fitted[0]

    monkeypatch.setattr(jaxskel, "fit_skeleton", fit_once)
    assert main(["fit", str(src), "-o", str(out), "--parameterize", "--calibration", "0:600", "--quiet"]) == 0
    back = jaxskel.load_result(out)
    n_segments = len(back.segments.names)
    assert back.normalized.limb_frames.shape == (trial.n_frames, n_segments, 3, 3)
    assert 0 <= int(back.normalized.default_frame) < 600  # inside the window
    assert back.parameters.angles.shape[0] == trial.n_frames
    assert np.isfinite(back.parameters.axes).any()
    assert back.parameters.attrs["calibration_source"] == "given"
    calibrated = np.asarray(back.parameters.calibration)
    assert calibrated[:600].all() and not calibrated[600:].any()
    # a separate calibration recording, posed on the fitted skeleton; the subject's facing given
    cal, _ = synth.simulate(body, duration=2.0, seed=2, noise=0.001)  # with the take: the take's frame bucket
    cal_file = tmp_path / "cal.c3d"
    cal.save(cal_file)
    out2 = tmp_path / "body2.h5"
    assert main(["fit", str(src), "-o", str(out2), "--parameterize", "--calibration-trial", str(cal_file),
                 "--facing=-y", "--quiet"]) == 0
    back = jaxskel.load_result(out2)
    assert back.parameters.attrs["calibration_source"] == "trial" and back.parameters.angles.shape[0] == trial.n_frames
    assert back.normalized.attrs["handedness"] == "facing"
    # refused before the fit: a setting of --parameterize without it, both calibrations, a bad window
    for extra, text in ((["--calibration", "0:10"], "add --parameterize"),
                        (["--axis-count", "data"], "add --parameterize"),
                        (["--parameterize", "--calibration", "0:10", "--calibration-trial", str(cal_file)], "not both")):
        assert main(["fit", str(src), "-o", str(tmp_path / "x.h5"), *extra, "--quiet"]) == 2
        assert text in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["fit", str(src), "-o", str(tmp_path / "x.h5"), "--parameterize", "--calibration", "10:5"])
    assert not (tmp_path / "x.h5").exists()
    capsys.readouterr()
    # a parameterisation that fails after the fit (a window past the recording's end) loses
    # nothing: the fit's outputs are written without it, and the error says so
    kept, bvh, unused = tmp_path / "kept.h5", tmp_path / "kept.bvh", tmp_path / "kept_angles.png"
    assert main(["fit", str(src), "-o", str(kept), "--bvh", str(bvh), "--parameterize", "--calibration",
                 "5000:6000", "--plot-angles", str(unused), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxskel: error: --parameterize failed: the calibration window") and "Traceback" not in err
    assert f"{kept} holds the fit without its parameterisation and {unused} was not written" in err
    back = jaxskel.load_result(kept)
    assert not hasattr(back, "parameters") and not hasattr(back, "normalized")
    assert list(back.segments.names) == list(jaxskel.load_result(out).segments.names)
    assert bvh.stat().st_size > 0 and not unused.exists()
    # no window: each joint's main movements, found automatically; --plot-angles draws the angles
    out3, angles_png = tmp_path / "body3.h5", tmp_path / "angles.png"
    assert main(["fit", str(src), "-o", str(out3), "--parameterize", "--plot-angles", str(angles_png), "--quiet"]) == 0
    back = jaxskel.load_result(out3)
    assert back.parameters.attrs["calibration_source"] == "automatic"
    # knees and elbows (found from the fitted skeleton's shape, the forearms' and shanks' markers
    # measuring any leaf) get one axis; the others count from the data
    source = np.asarray(back.parameters.axis_count_source).astype(str)
    assert (source == "anatomy").sum() == 4 and set(source) == {"anatomy", "data"}
    assert np.all(np.asarray(back.parameters.n_axes)[source == "anatomy"] == 1)
    assert back.parameters.attrs["axis_count"] == "anatomy"
    lengths = np.asarray(back.normalized.leaf_lengths)  # the leaves (feet, hands, head) measured by their markers
    assert lengths.shape == (n_segments,) and np.sum(lengths > 0.05) >= 5
    assert angles_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # --plot-angles is checked before the fit, and needs --parameterize; "--calibration all" is read
    assert jaxskel.cli._calibration_window("all") == "all" and jaxskel.cli._calibration_window("AUTO") == "auto"
    for extra, text in ((["--parameterize", "--plot-angles", str(angles_png)], "exists; pass --overwrite"),
                        (["--parameterize", "--plot-angles", str(tmp_path / "angles.h5")], "--plot-angles"),
                        (["--plot-angles", str(tmp_path / "a2.png")], "add --parameterize")):
        assert main(["fit", str(src), "-o", str(tmp_path / "y.h5"), *extra, "--quiet"]) == 2
        assert text in capsys.readouterr().err
    assert not (tmp_path / "y.h5").exists()


def test_no_output_is_ever_written_over_an_input(linkage_trial, tmp_path, capsys):
    """Issue 45, item 1: `--trc IN.trc --overwrite` (or --bvh, --plot, -o) named the input and
    replaced it after the fit. Every output is checked against every input before any work,
    --overwrite or not, and the input is left byte for byte; two outputs naming one file,
    an output that is a folder, and an unwritable folder are refused up front too. The
    API's save() refuses the input recording likewise."""
    import os
    import stat

    trial, _ = linkage_trial
    src = tmp_path / "in.trc"
    trial.save(src)
    before = src.read_bytes()
    out = tmp_path / "r.h5"
    for flag in ("--trc", "--bvh", "--plot"):
        assert main(["fit", str(src), "-o", str(out), flag, str(src), "--overwrite", "--quiet", "--no-rigid"]) == 2
        err = capsys.readouterr().err
        assert f"{flag} {src} is the input recording" in err and "never writes over an input" in err
        assert src.read_bytes() == before and not out.exists()
    link = tmp_path / "alias.trc"
    os.link(src, link)  # the same file under another name
    assert main(["fit", str(src), "-o", str(out), "--trc", str(link), "--overwrite", "--quiet"]) == 2
    assert src.read_bytes() == before
    assert main(["fit", str(src), "-o", str(out), "--bvh", str(out), "--quiet"]) == 2
    assert "both name" in capsys.readouterr().err
    assert main(["fit", str(src), "-o", str(tmp_path), "--quiet"]) == 2
    assert "is a folder" in capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        if not os.access(locked, os.W_OK):  # root may write anywhere: nothing to check then
            assert main(["fit", str(src), "-o", str(locked / "r.h5"), "--quiet"]) == 2
            assert "not writable" in capsys.readouterr().err
    finally:
        locked.chmod(stat.S_IRWXU)
    h5 = tmp_path / "in.h5"
    trial.save(h5)
    result = jaxskel.fit_skeleton(jaxskel.load(h5), rigid=False, ik=False)
    with pytest.raises(jaxskel.InputError, match="is the input recording"):
        result.save(h5, overwrite=True)
    assert jaxskel.load(h5).n_frames == trial.n_frames


def test_a_write_the_system_refuses_after_the_fit_is_one_line_and_leaves_the_old_file(
    fitted, linkage_trial, tmp_path, monkeypatch, capsys
):
    """Issue 45, item 2: the preflight cannot foresee a disk that fills during the fit. The
    save then fails as one line with status 1 (it was a traceback), the old result stays
    byte for byte, and no temporary file is left."""
    import errno
    import os

    trial, _ = linkage_trial
    src = tmp_path / "link.trc"
    trial.save(src)
    out = tmp_path / "r.h5"
    out.write_bytes(b"the old result")
    monkeypatch.setattr(jaxskel, "fit_skeleton", lambda *a, **k: fitted)  # the fit itself is tested above

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    assert main(["fit", str(src), "-o", str(out), "--overwrite", "--quiet"]) == 1
    assert capsys.readouterr().err == (
        "jaxskel: error: [Errno 28] No space left on device; no partial output was left behind\n"
    )
    assert out.read_bytes() == b"the old result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.trc", "r.h5"]


_COMMAND = """
import atexit, pathlib, sys, threading, time
mark = pathlib.Path(sys.argv[1])
atexit.register(lambda: mark.write_text("atexit ran"))
if sys.argv[2] == "--with-thread":  # a thread that is not a daemon, still running when main returns
    sys.argv.pop(2)
    threading.Thread(target=lambda: (time.sleep(3), mark.with_suffix(".thread").write_text("done"))).start()
sys.argv = ["jaxskel", *sys.argv[2:]]
from jaxskel.cli import run
run()
"""


def test_the_command_exits_fast_yet_flushes_its_output_and_runs_exit_handlers(linkage_trial, tmp_path):
    """``jaxskel`` (jaxskel.cli.run) ends with os._exit after the exit work: its printed
    report is complete, a handler registered with atexit still runs, and the exit code is
    main's, for success and for a refused input alike; a thread that is not a daemon and
    still runs is waited for."""
    trial, _ = linkage_trial
    src = tmp_path / "chain.c3d"
    trial.save(src)
    env = {**os.environ, "JAXSKEL_CACHE_DIR": ""}
    ok = subprocess.run([sys.executable, "-c", _COMMAND, str(tmp_path / "a.txt"), "info", str(src)],
                        capture_output=True, text=True, timeout=300, env=env)
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert f"labels: {', '.join(trial.labels)}" in ok.stdout and ok.stdout.rstrip().endswith("}")
    assert (tmp_path / "a.txt").read_text() == "atexit ran"
    bad = subprocess.run([sys.executable, "-c", _COMMAND, str(tmp_path / "b.txt"), "info", str(tmp_path / "no.c3d")],
                         capture_output=True, text=True, timeout=300, env=env)
    assert bad.returncode == 2 and "jaxskel: error:" in bad.stderr
    assert (tmp_path / "b.txt").read_text() == "atexit ran"
    # a thread that is not a daemon: Python's usual exit, which waits for it
    waits = subprocess.run([sys.executable, "-c", _COMMAND, str(tmp_path / "c.txt"), "--with-thread", "info",
                            str(src)], capture_output=True, text=True, timeout=300, env=env)
    assert waits.returncode == 0 and (tmp_path / "c.thread").read_text() == "done"


def test_a_recording_shorter_than_the_cleaning_keeps_says_so_and_what_to_change(linkage_trial):
    """A 0.3 s take: cleaning drops every marker (runs under min_run_s); the error says
    how many markers the recording had, why they went and which setting to change, and
    with that setting cleaning keeps them."""
    trial, _ = linkage_trial
    short = trial.select_frames(slice(0, int(0.3 * trial.rate)))
    with pytest.raises(jaxskel.DegenerateMotionError) as caught:
        jaxskel.fit_skeleton(short, ik=False)
    text = str(caught.value)
    assert f"only 0 of the recording's {trial.n_markers} markers remain after cleaning" in text
    assert f"Cleaning dropped {trial.n_markers} ({trial.labels[0]}: longest contiguous run 0.300 s" in text
    assert "min_run_s" in text and "--min-run-s" in text and "0.30 s long" in text
    kept, report = jaxskel.clean.clean(short, **jaxskel.CleanOptions(min_run_s=0.1).kwargs())
    assert report.dropped == {} and kept.n_markers == trial.n_markers
