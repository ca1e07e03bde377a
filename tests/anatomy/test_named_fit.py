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
def fitted(body):
    trial, _ = synth.simulate(body, motion="calibration", duration=8.0, noise=0.0005, seed=2)
    return jaxskel.fit_skeleton(trial)


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
