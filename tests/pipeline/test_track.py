"""Calibrate once, track many: jaxskel.track on a saved skeleton.

The skeleton is the synthetic body's own (no solver), so each test checks tracking alone
against the ground truth: joint centres, gap filling, the markers a trial lacks or adds,
the segments it cannot pose. The skeleton's round trip through a fit's result file and
the command line are checked on a fitted linkage.
"""

from __future__ import annotations

import dataclasses
import warnings

import h5py
import numpy as np
import pytest
from helpers import truth_skeleton

import jaxskel
from jaxskel import synth
from jaxskel.cli import main
from jaxskel.pipeline._track import match_markers, posable_segments, posed_segments


@pytest.fixture(scope="module")
def body():
    return synth.full_body(seed=0)


@pytest.fixture(scope="module")
def calibration(body):
    trial, truth = synth.simulate(body, motion="calibration", duration=2.0, noise=0.0005, seed=0)
    return truth_skeleton(trial, truth, segment_names=truth.segment_names)


@pytest.fixture(scope="module")
def walk(body):
    return synth.simulate(body, motion="walk", duration=3.0, noise=0.0005, seed=1)


def _track_one(skeleton, trial, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batch = jaxskel.track(skeleton, trial, **kwargs)
    (outcome,) = batch
    assert outcome.status == "ok", outcome.error
    return outcome.result, [w for w in caught if issubclass(w.category, jaxskel.TrackingWarning)]


def _joint_error(tracked, truth, frames=slice(None)):
    return np.linalg.norm(tracked.motion.joint_positions[frames] - truth.joint_positions[frames], axis=-1)


def test_a_new_trial_is_posed_on_the_saved_skeleton(calibration, walk):
    trial, truth = walk
    tracked, caught = _track_one(calibration, trial)
    assert not caught and tracked.missing_markers == () and tracked.extra_markers == ()
    assert tracked.segment_posed.all() and tracked.motion.converged
    # 0.5 mm of noise per axis on the true skeleton: joints within 2 mm, the residual the
    # noise's 3-D RMS less what the pose absorbs
    assert np.median(_joint_error(tracked, truth)) < 0.002
    assert np.median(tracked.motion.marker_rms) == pytest.approx(0.0005 * np.sqrt(3), rel=0.1)
    # the skeleton is the calibration's, not a copy that could drift
    assert tracked.skeleton is calibration


def test_missing_markers_are_tracked_without_and_reported(calibration, walk):
    trial, truth = walk
    dropped = list(trial.labels[3:6])
    tracked, caught = _track_one(calibration, trial.drop_markers(dropped))
    assert tracked.missing_markers == tuple(dropped)
    assert len(caught) == 1 and all(lab in str(caught[0].message) for lab in dropped)
    assert np.median(_joint_error(tracked, truth)) < 0.003
    # the missing markers are still predicted by the skeleton
    column = list(tracked.trial.labels).index(dropped[0])
    assert np.isfinite(tracked.motion.fitted_markers[:, column]).all()


def test_extra_markers_are_ignored_and_reported(calibration, walk):
    trial, truth = walk
    ghost = np.full((trial.n_frames, 1, 3), 0.5)
    extra = trial.replace(positions=np.concatenate([trial.positions, ghost], axis=1), labels=(*trial.labels, "PROP"))
    tracked, caught = _track_one(calibration, extra)
    assert tracked.extra_markers == ("PROP",) and tracked.missing_markers == ()
    assert tracked.input_labels[-1] == "PROP" and "PROP" not in tracked.trial.labels
    assert "ignored 1 markers the skeleton does not know: PROP" in tracked.summary()
    assert np.median(_joint_error(tracked, truth)) < 0.002


def test_a_gap_is_filled(calibration, walk):
    trial, truth = walk
    m = 10
    positions = np.array(trial.positions)
    gap = slice(100, 160)  # half a second
    positions[gap, m] = np.nan
    tracked, caught = _track_one(calibration, trial.replace(positions=positions))
    assert not caught and tracked.segment_posed.all()
    filled = tracked.motion.fitted_markers[gap, m]
    assert np.isfinite(filled).all()
    assert np.linalg.norm(filled - truth.clean_positions[gap, m], axis=-1).max() < 0.01


def test_prefixed_and_differently_cased_labels_are_matched(calibration, walk):
    trial, truth = walk
    labels = tuple(f"Subject:{lab}" for lab in trial.labels[:20]) + tuple(lab.lower() for lab in trial.labels[20:])
    tracked, caught = _track_one(calibration, trial.replace(labels=labels))
    assert not caught and tracked.missing_markers == () and tracked.extra_markers == ()
    assert tracked.matched[trial.labels[0]] == f"Subject:{trial.labels[0]}"
    assert len(tracked.matched) == trial.n_markers - sum(lab == lab.lower() for lab in trial.labels[20:])
    assert np.median(_joint_error(tracked, truth)) < 0.002


def test_match_markers_takes_each_label_once_and_leaves_ambiguity_alone():
    m = match_markers(["A", "B", "C", "D"], ["x:A", "b", "B", "c", "C ", "d", "D"])
    assert m.columns.tolist() == [0, 2, 4, 6]  # exact first, then the prefix, then case
    assert m.extra == ("b", "c", "d") and m.missing == ()
    m = match_markers(["a", "X"], ["A", "a2"])
    assert m.columns.tolist() == [0, -1] and m.missing == ("X",) and m.extra == ("a2",)


def test_a_segment_without_markers_is_reported_unposed_by_name(calibration, walk):
    trial, _ = walk
    names = calibration.names()
    leaf = next(s for s in range(calibration.n_segments) if s not in calibration.edges[:, 0])
    on_leaf = [lab for lab, s in zip(calibration.marker_labels, calibration.marker_segment) if s == leaf]
    # the leaf's markers gone for good, another segment's for the first 50 frames
    other = int(calibration.edges[0, 1])
    on_other = [m for m, s in enumerate(calibration.marker_segment) if s == other]
    positions = np.array(trial.positions)
    positions[:50, on_other] = np.nan
    # (no cleaning: it would trim the gap's edge by a few frames)
    tracked, caught = _track_one(calibration, trial.replace(positions=positions).drop_markers(on_leaf),
                                 clean_data=False)
    assert not tracked.segment_posed[:, leaf].any()
    assert not tracked.segment_posed[:50, other].any() and tracked.segment_posed[50:, other].all()
    others = np.ones(calibration.n_segments, bool)
    others[[leaf, other]] = False
    assert tracked.segment_posed[:, others].all()
    unposed = tracked.unposed_segments()
    assert unposed == {names[leaf]: trial.n_frames, names[other]: 50}
    text = " ".join(str(w.message) for w in caught)
    assert f"{names[leaf]} (all frames; no data for" in text and f"{names[other]} (50 frames" in text
    # markers of an unposed segment are not invented
    column = list(tracked.trial.labels).index(on_leaf[0])
    assert np.isnan(tracked.motion.fitted_markers[:, column]).all()


def test_posable_and_posed_segments_follow_the_markers_and_the_joints(calibration):
    member = np.asarray(calibration.marker_segment)
    seg = int(np.argmax(np.bincount(member[member >= 0])))  # the best-marked segment
    visible = np.ones((6, calibration.n_markers), bool)
    on = np.flatnonzero(member == seg)
    visible[1, on[:2]] = False  # fewer than three of its markers, one joint or more: still three points
    visible[2:4, on] = False  # none
    posable = posable_segments(calibration, visible)
    degree = np.bincount(calibration.edges.ravel(), minlength=calibration.n_segments)[seg]
    assert posable[0, seg] and not posable[2:4, seg].any()
    assert posable[1, seg] == (len(on) - 2 >= 3 or len(on) - 2 + degree >= 3)
    posed = posed_segments(posable)
    assert posed[:, seg].all()  # an inner gap is filled
    assert not posed_segments(posable[2:])[:2, seg].any()  # a gap at the start is not


def test_trials_tracked_together_equal_trials_tracked_alone(calibration, walk, body):
    other, _ = synth.simulate(body, motion="calibration", duration=2.0, noise=0.0005, seed=3)
    together = jaxskel.track(calibration, [walk[0], other])
    alone = [jaxskel.track(calibration, t)[0] for t in (walk[0], other)]
    for a, b in zip(together, alone):
        np.testing.assert_allclose(a.result.motion.joint_positions, b.result.motion.joint_positions, atol=1e-6)
        np.testing.assert_allclose(a.result.motion.marker_rms, b.result.motion.marker_rms, atol=1e-7)


def test_a_trial_with_too_few_markers_fails_alone_naming_them(calibration, walk):
    trial, _ = walk
    few = trial.select_markers(list(trial.labels[:2]))
    batch = jaxskel.track(calibration, [few, trial])
    assert [o.status for o in batch] == ["failed", "ok"]
    assert "2 of the skeleton's 46 markers" in batch[0].error and trial.labels[0] in batch[0].error


@pytest.mark.parametrize("kwargs, message", [
    ({"n_segments": 5}, "fit setting"),
    ({"ik": False}, "inverse kinematics"),
    ({"batch_size": 0}, "batch_size"),
    ({"bvh": True}, "give outdir"),
    ({"ik_lowpass": -1.0}, "ik_lowpass"),
])
def test_bad_arguments_are_refused_before_any_work(calibration, walk, kwargs, message):
    with pytest.raises(jaxskel.InputError, match=message):
        jaxskel.track(calibration, walk[0], **kwargs)


def test_not_a_skeleton_is_refused(tmp_path, walk):
    with pytest.raises(jaxskel.InputError, match="no such result file"):
        jaxskel.track(tmp_path / "none.h5", walk[0])
    trial_file = tmp_path / "trial.h5"
    jaxskel.save_trial(walk[0], trial_file)
    with pytest.raises(jaxskel.InputError, match="not a jaxskel result file"):
        jaxskel.load_skeleton(trial_file)
    with pytest.raises(jaxskel.InputError, match="Skeleton, a SkeletonResult or the path"):
        jaxskel.track(42, walk[0])


# ------------------------------------------------------- a fitted skeleton, its file and the CLI
@pytest.fixture(scope="module")
def fitted_linkage(tmp_path_factory):
    """A linkage fitted from a calibration trial, saved; two more trials of it as C3D files."""
    tmp = tmp_path_factory.mktemp("track")
    link = synth.linkage()
    cal, _ = synth.simulate(link, duration=8.0, seed=5, noise=0.0005)
    result = jaxskel.fit_skeleton(cal)
    result.save(tmp / "subject.h5")
    files = []
    for seed in (6, 7):
        trial, _ = synth.simulate(link, duration=4.0, seed=seed, noise=0.0005, gaps=1)
        path = tmp / f"take{seed}.c3d"
        jaxskel.save_trial(trial, path)
        files.append(path)
    return result, tmp / "subject.h5", files


def test_the_skeleton_round_trip_is_exact(fitted_linkage):
    result, path, files = fitted_linkage
    fitted, back = result.skeleton, jaxskel.load_skeleton(path)
    for field in dataclasses.fields(fitted):
        a, b = getattr(fitted, field.name), getattr(back, field.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), field.name
        elif field.name == "diagnostics":
            assert set(a) == set(b) and a["residual_rms"] == b["residual_rms"]
        else:
            assert a == b, field.name
    assert back.segment_names == result.segment_names
    trial = jaxskel.load(files[0])
    one, two = (jaxskel.track(s, trial)[0].result.motion for s in (fitted, back))
    np.testing.assert_array_equal(one.rotations, two.rotations)
    np.testing.assert_array_equal(one.joint_positions, two.joint_positions)


def test_track_command_writes_one_rig_for_every_take(fitted_linkage, tmp_path, capsys):
    import bvh as bvh_package

    result, path, files = fitted_linkage
    out = tmp_path / "tracked"
    assert main(["track", str(path), *map(str, files), "-o", str(out), "--bvh", "--trc", "--quiet"]) == 0
    with h5py.File(path) as f:
        bones = f["skeleton/bone_lengths"][()]
    offsets = []
    for file in files:
        stem = file.stem
        with h5py.File(out / f"{stem}.h5") as f:
            assert f.attrs["kind"] == "tracked" and f.attrs["calibration"] == str(path)
            assert f["skeleton/bone_lengths"][()].tobytes() == bones.tobytes()  # to the bit
            n = f["motion/joint_positions"].shape[0]
            assert f["motion/marker_rms"].shape == (n,) and np.isfinite(f["motion/fitted_markers"][()]).all()
        again = jaxskel.load_skeleton(out / f"{stem}.h5")
        assert again.bone_lengths.tobytes() == bones.tobytes()
        # the BVH of each take: the calibration's hierarchy and offsets (the independent parser)
        with open(out / f"{stem}.bvh") as fh:
            mocap = bvh_package.Bvh(fh.read())
        offsets.append([mocap.joint_offset(name) for name in mocap.get_joints_names()])
        trc = jaxskel.load(out / f"{stem}.trc")
        assert trc.labels == result.skeleton.marker_labels and np.isfinite(trc.positions).all()
    assert offsets[0] == offsets[1]
    calibration_bvh = tmp_path / "cal.bvh"
    result.export_bvh(calibration_bvh)
    with open(calibration_bvh) as fh:
        mocap = bvh_package.Bvh(fh.read())
    assert offsets[0] == [mocap.joint_offset(name) for name in mocap.get_joints_names()]
    # again without --overwrite: refused before any work, the files untouched
    before = (out / f"{files[0].stem}.h5").stat().st_mtime_ns
    assert main(["track", str(path), str(files[0]), "-o", str(out), "--quiet"]) == 2
    assert "exists; pass overwrite=True (--overwrite)" in capsys.readouterr().err
    assert (out / f"{files[0].stem}.h5").stat().st_mtime_ns == before


def test_track_command_refuses_fit_settings_and_colliding_outputs(fitted_linkage, tmp_path, capsys):
    _, path, files = fitted_linkage
    with pytest.raises(SystemExit):
        main(["track", str(path), str(files[0]), "-o", str(tmp_path), "--segments", "3"])
    copy = tmp_path / "other"
    copy.mkdir()
    twin = copy / files[0].name
    twin.write_bytes(files[0].read_bytes())
    assert main(["track", str(path), str(files[0]), str(twin), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    assert "the same file name" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    # the calibration file is never an output, overwrite or not
    same_name = tmp_path / f"{path.stem}.c3d"
    same_name.write_bytes(files[0].read_bytes())
    before = path.read_bytes()
    code = main(["track", str(path), str(same_name), "-o", str(path.parent), "--overwrite", "--quiet"])
    assert code == 2 and str(path) in capsys.readouterr().err
    assert path.read_bytes() == before


def test_track_on_dask_workers_writes_the_same_files_and_names_each_trials_warnings(fitted_linkage, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    result, path, files = fitted_linkage
    lacking = tmp_path / "lacking.c3d"
    take = jaxskel.load(files[1])
    jaxskel.save_trial(take.drop_markers([take.labels[0]]), lacking)
    local = tmp_path / "local"
    assert main(["track", str(path), str(files[0]), "-o", str(local), "--quiet"]) == 0
    capsys.readouterr()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        out = tmp_path / "dask"
        code = main(["track", str(path), str(files[0]), str(lacking), "-o", str(out), "--quiet",
                     "--scheduler", cluster.scheduler_address])
    assert code == 0
    err = capsys.readouterr().err
    assert f"jaxskel: warning (TrackingWarning) [lacking]: the trial lacks 1 of the skeleton's markers ({take.labels[0]})" in err
    with h5py.File(local / f"{files[0].stem}.h5") as a, h5py.File(out / f"{files[0].stem}.h5") as b:
        np.testing.assert_array_equal(a["motion/joint_positions"][()], b["motion/joint_positions"][()])
    with h5py.File(out / "lacking.h5") as f:
        assert [v.decode() for v in f["markers/missing"][()]] == [take.labels[0]]
