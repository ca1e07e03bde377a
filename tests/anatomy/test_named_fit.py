"""A fit names its body: the result, its summary, its file, ``jaxskel info`` and a tracked take.

One synthetic full body, fitted with the defaults; the parts themselves are judged in
``test_identify.py``. Here: that the names reach everything that shows segments and joints,
and that they survive the result file and tracking.
"""

from __future__ import annotations

import numpy as np
import pytest
from truth import result_truth, score

import jaxskel
from jaxskel import synth
from jaxskel.cli import main


@pytest.fixture(scope="module")
def body():
    return synth.full_body(seed=2)


@pytest.fixture(scope="module")
def simulated(body):
    return synth.simulate(body, motion="calibration", duration=8.0, noise=0.0005, seed=2)


@pytest.fixture(scope="module")
def fitted(simulated):
    return jaxskel.fit_skeleton(simulated[0])


def rms_deg(a, b) -> float:
    return float(np.rad2deg(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2))))


HINGES = [(f"{side}_{joint}", f"{joint}_{side}_flexion") for side in "lr" for joint in ("knee", "elbow")]


@pytest.fixture(scope="module")
def saved(fitted, tmp_path_factory):
    path = tmp_path_factory.mktemp("named") / "subject.h5"
    fitted.save(str(path))
    return path


def test_the_fit_names_its_segments_and_joints_after_the_body_parts(fitted, body):
    anatomy = fitted.anatomy
    assert anatomy is not None and anatomy.humanoid
    right, scored, swapped = score(anatomy.parts, result_truth(fitted, body))
    assert swapped == 0 and right >= 0.95 * scored
    assert fitted.segment_names == anatomy.segment_names(jaxskel.segment.segment_names(fitted.segmentation.groups))
    assert fitted.skeleton.names() == fitted.segment_names  # what a tracked take inherits
    joints = {fitted.joint_name(j) for j in range(len(fitted.edges))}
    assert {"hip_l", "knee_l", "ankle_l", "hip_r", "knee_r", "ankle_r", "elbow_l", "elbow_r"} <= joints
    text = fitted.summary()
    assert "body: human, " in text and "  knee_r: " in text and "thigh_l (" in text


def test_a_fit_told_not_to_name_the_body_keeps_its_markers_names(fitted):
    trial = fitted.trial
    plain = jaxskel.fit_skeleton(trial, anatomy=False, ik=False)
    assert plain.anatomy is None and "anatomy" not in plain.timings
    assert "thigh_l" not in plain.segment_names and "body:" not in plain.summary()


def test_the_named_body_round_trips_through_the_result_file_and_info(fitted, saved, capsys):
    back = jaxskel.result.load_anatomy(saved)
    assert back.parts == fitted.anatomy.parts and back.humanoid
    np.testing.assert_allclose(back.confidence, fitted.anatomy.confidence)
    np.testing.assert_allclose(back.front, fitted.anatomy.front)
    stored = jaxskel.load_result(saved)
    assert [str(n) for n in stored.segments.names] == list(fitted.segment_names)
    assert bool(stored.anatomy.attrs["humanoid"])
    assert main(["info", str(saved)]) == 0
    out = capsys.readouterr().out
    named = sum(map(bool, fitted.anatomy.parts))
    assert f"body: human, {named} of {fitted.n_segments} segments named" in out and "thigh_r" in out


def test_a_tracked_take_inherits_the_names_and_the_body(fitted, saved, body, tmp_path):
    take, _ = synth.simulate(body, motion="walk", duration=2.0, noise=0.0005, seed=5)
    for source in (saved, fitted):  # the calibration's file, or its result in memory
        (outcome,) = jaxskel.track(source, take, outdir=tmp_path / type(source).__name__)
        assert outcome.status == "ok", outcome.error
        tracked = jaxskel.result.load_anatomy(outcome.output)
        assert tracked is not None and tracked.parts == fitted.anatomy.parts
        names = [str(n) for n in jaxskel.load_result(outcome.output).segments.names]
        assert names == list(fitted.segment_names)


def test_knee_and_elbow_flexion_of_the_fit_match_the_truth_within_two_degrees(fitted, simulated):
    truth = simulated[1]
    angles = fitted.joint_angles()
    for true_name, ours in HINGES:
        true = truth.joint_angles[truth.joint_names.index(true_name)][:, 0]
        assert rms_deg(angles[ours], true) < 2.0, ours
        assert angles.lateral[ours.rsplit("_", 1)[0]] == "functional"
    assert {"hip_l_flexion", "hip_r_adduction", "ankle_l_dorsiflexion", "shoulder_r_abduction"} <= set(angles.names)


def test_the_angles_are_in_the_result_file(fitted, saved):
    back = jaxskel.result.load_angles(saved)
    angles = fitted.joint_angles()
    assert back.names == angles.names and back.joints == angles.joints and back.lateral == angles.lateral
    np.testing.assert_allclose(back.values, angles.values)
    assert back.rate == fitted.trial.rate


def test_a_tracked_take_has_its_angles_in_its_file_and_its_storage_file(fitted, saved, body, tmp_path):
    take, truth = synth.simulate(body, motion="walk", duration=2.0, noise=0.0005, seed=5)
    jaxskel.save_trial(take, tmp_path / "walk.h5")
    assert main(["track", str(saved), str(tmp_path / "walk.h5"), "-o", str(tmp_path / "out"), "--angles",
                 "--quiet"]) == 0
    table = jaxskel.result.read_sto(tmp_path / "out" / "walk.sto")
    stored = jaxskel.result.load_angles(tmp_path / "out" / "walk.h5")
    np.testing.assert_allclose(table.values, stored.degrees, atol=1e-6)
    calibration = fitted.joint_angles()
    np.testing.assert_array_equal(stored.frames, calibration.frames)  # measured in the calibration's frames
    assert set(stored.lateral.values()) == {"given"} and stored.names == calibration.names
    for true_name, ours in HINGES[:1]:
        true = truth.joint_angles[truth.joint_names.index(true_name)][:, 0]
        assert np.ptp(true) > np.deg2rad(30)  # the walk bends the knee
        assert rms_deg(np.deg2rad(table.column(ours)), true) < 2.0


def test_angles_need_a_human_calibration_before_any_work(tmp_path, body):
    linkage = synth.linkage()
    trial, _ = synth.simulate(linkage, motion="calibration", duration=4.0, seed=0)
    plain = jaxskel.fit_skeleton(trial, ik=False, rigid=True)
    assert plain.anatomy is not None and not plain.anatomy.humanoid
    with pytest.raises(jaxskel.InputError, match="human"):
        jaxskel.track(plain, trial, outdir=tmp_path / "t", angles=True)
    assert not (tmp_path / "t").exists()


def test_cli_fit_writes_the_angles_as_a_storage_file_opensim_reads(body, tmp_path, capsys):
    import opensim

    trial, truth = synth.simulate(body, motion="calibration", duration=6.0, noise=0.0005, seed=7)
    source, out, sto = tmp_path / "take.h5", tmp_path / "fit.h5", tmp_path / "angles.sto"
    jaxskel.save_trial(trial, source)
    sto.write_text("keep me")
    assert main(["fit", str(source), "-o", str(out), "--angles", str(sto)]) == 2  # checked before the fit
    assert "exists" in capsys.readouterr().err and sto.read_text() == "keep me" and not out.exists()
    assert main(["fit", str(source), "-o", str(out), "--angles", str(sto), "--no-anatomy", "--overwrite"]) == 2
    assert "--no-anatomy" in capsys.readouterr().err and not out.exists()

    assert main(["fit", str(source), "-o", str(out), "--angles", str(sto), "--overwrite", "--quiet"]) == 0
    storage = opensim.TimeSeriesTable(str(sto))
    knee = np.deg2rad(storage.getDependentColumn("knee_r_flexion").to_numpy())
    true = truth.joint_angles[truth.joint_names.index("r_knee")][:, 0]
    assert storage.getNumRows() == trial.n_frames and rms_deg(knee, true) < 2.0
