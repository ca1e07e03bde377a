"""The records of the rigid fit: :class:`RigidOptions` (validated settings),
:class:`RigidDiagnostics` (a typed record read as a mapping) and the retry loop over
what the fit leaves out (:class:`jaxskel.skeleton._rigid_fit.LeftOut`)."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings

import numpy as np
import pytest

import jaxskel
from jaxskel import InputError, synth
from jaxskel.result._format import jsonable
from jaxskel.skeleton import RigidDiagnostics, RigidOptions, Skeleton, fit_rigid
from jaxskel.skeleton._rigid_fit import LeftOut


def _entries(**extra):
    """A rigid fit's diagnostics as a plain dict, in the fit's order (two joints, three segments)."""
    entries = dict(
        sweeps=4, result=0, cost_history=[2e-6, 1e-6, 9e-7, 9e-7], offset_steps=[1e-3, 1e-4, 1e-5, 1e-7],
        residual_rms=9.5e-4, frames_used=300, frames_rejected=2, rest_frame=17, ik_steps_mean=3.5, ik_steps_max=9,
        ik_failures=0, procrustes_segments=[0, 1, 2], hinge_shift=[0.0, 0.012], hinge_placement=["", "limb plane"],
        hinge_axis=[[math.nan] * 3, [0.0, 1.0, 0.0]], procrustes_rms=[1e-3, 2e-3, math.nan],
        attachment_weight=[1.0, 1.0], attachment_scatter=[math.nan, math.nan],
    )
    return {**entries, **extra}


# ------------------------------------------------------------------ options
@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (dict(xtol=0.0), "xtol must be a positive length in metres and max_sweeps a whole number >= 1"),
        (dict(xtol="1e-6"), "xtol must be a positive length"),
        (dict(max_sweeps=2.5), "got xtol=1e-06, max_sweeps=2.5"),
        (dict(max_sweeps=True), "max_sweeps a whole number >= 1"),
        (dict(joint_weight=float("inf")), "joint_weight must be a positive number, got inf"),
        (dict(joint_weight=None), "joint_weight must be a positive number, got None"),
        (dict(max_steps=0), "max_steps must be a whole number >= 1, got 0"),
        (dict(max_frames=10.0), "max_frames must be a whole number >= 1, got 10.0"),
        (dict(prior_weight=-1e-3), "prior_weight must be a number >= 0"),
        (dict(nonrigid_factor=0), "nonrigid_factor must be a positive number, got 0"),
        (dict(refine="yes"), "refine must be True or False, got 'yes'"),
    ],
)
def test_bad_settings_are_refused_on_construction_with_fit_rigids_messages(bad, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(".", r"\.")):
        RigidOptions(**bad)


def test_options_accept_numpy_scalars_and_zero_prior_and_are_frozen():
    o = RigidOptions(max_steps=np.int64(50), max_sweeps=np.int32(3), xtol=np.float64(1e-5), prior_weight=0.0,
                     refine=np.bool_(False))
    assert (o.max_steps, o.max_sweeps, o.xtol, o.prior_weight) == (50, 3, 1e-5, 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.xtol = 1.0  # type: ignore[misc]


def test_options_and_keywords_together_are_refused_before_any_work():
    x, mask = np.zeros((5, 3, 3)), np.ones((5, 3), bool)
    with pytest.raises(InputError, match="either as options=RigidOptions"):
        fit_rigid((x, mask), np.zeros(3, int), np.zeros((0, 2), int), np.zeros((5, 0, 3)),
                  options=RigidOptions(xtol=1e-5), max_sweeps=3)


# -------------------------------------------------------------- diagnostics
def test_diagnostics_read_as_the_mapping_they_replace():
    entries = _entries(unplaced_markers=("SYNC",))
    d = RigidDiagnostics(**entries)
    assert list(d) == list(entries) and len(d) == len(entries)
    assert d["hinge_shift"] == [0.0, 0.012] and d.hinge_shift is d["hinge_shift"]
    assert d.get("hinges_unmoved") is None and "hinges_unmoved" not in d and "unplaced_markers" in d
    with pytest.raises(KeyError):
        d["hinges_unmoved"]
    assert d == entries and dict(d) == entries and {**d} == entries
    assert json.loads(json.dumps(jsonable(d))).keys() == entries.keys()
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.sweeps = 5  # type: ignore[misc]


def test_optional_entries_come_before_the_extra_ones_and_extras_cannot_shadow_fields():
    d = RigidDiagnostics(**_entries(hinges_unmoved=[1], unplaced_markers=("A",)), extra={"anchored": {"r": 1}})
    assert list(d)[-3:] == ["hinges_unmoved", "unplaced_markers", "anchored"]
    assert d["anchored"] == {"r": 1}
    with pytest.raises(TypeError):
        d.extra["more"] = 1  # type: ignore[index]
    with pytest.raises(InputError, match="clash"):
        RigidDiagnostics(**_entries(), extra={"sweeps": 1})


def test_a_plain_mapping_of_a_rigid_fit_becomes_the_record_and_any_other_stays_a_mapping():
    plain = _entries(hinges_unmoved=[1], anchored={"exercise": [0.2, 0.3]})
    record = RigidDiagnostics.from_mapping(plain)
    assert isinstance(record, RigidDiagnostics) and record == plain and list(record) == list(plain)
    assert record.hinges_unmoved == [1] and record.extra == {"anchored": {"exercise": [0.2, 0.3]}}
    assert RigidDiagnostics.from_mapping(record) is record
    partial = {k: v for k, v in plain.items() if k != "sweeps"}
    assert RigidDiagnostics.from_mapping(partial) is None
    reordered = {"anchored": plain["anchored"], **_entries()}  # not an order the record iterates in
    assert RigidDiagnostics.from_mapping(reordered) is None

    def skeleton(diagnostics):
        return Skeleton(
            n_segments=1, edges=np.zeros((0, 2), int), root=0, marker_labels=("A",), marker_segment=np.zeros(1, int),
            marker_offsets=np.zeros((1, 3)), joint_offsets=np.zeros((0, 2, 3)), bones=np.zeros((0, 2), int),
            bone_lengths=np.zeros(0), bone_segment=np.zeros(0, int), segment_lengths=np.full(1, np.nan),
            marker_rms=np.zeros(1), nonrigid_markers=(), diagnostics=diagnostics,
        )

    assert isinstance(skeleton(plain).diagnostics, RigidDiagnostics)
    other = skeleton({"residual_rms": 1e-3}).diagnostics
    assert not isinstance(other, RigidDiagnostics) and dict(other) == {"residual_rms": 1e-3}
    with pytest.raises(TypeError):
        other["residual_rms"] = 0.0  # type: ignore[index]


# ------------------------------------------------------------------ retries
def test_left_out_merges_markers_in_order_and_hinges_as_a_sorted_set():
    both = LeftOut(markers=(4,), hinges=(2,)) | LeftOut(markers=(1,), hinges=(0, 2))
    assert both == LeftOut(markers=(4, 1), hinges=(0, 2))
    seg = np.array([0, 1, 1, 2, 2, 0])
    np.testing.assert_array_equal(both.marker_segment(seg), [0, -1, 1, 2, -1, 0])
    np.testing.assert_array_equal(seg, [0, 1, 1, 2, 2, 0])  # a copy
    np.testing.assert_array_equal(both.sliding([True, True, True, False]), [False, True, False, False])
    assert LeftOut().sliding(None) is None


@pytest.fixture(scope="module")
def with_light():
    """A linkage whose third rod is hidden for the last quarter, while a light (a marker
    clustered with that rod) is seen: no frame shows the light with the rod."""
    trial, truth = synth.simulate(synth.linkage(), duration=3.0, seed=5, noise=0.001)
    pos = trial.positions.copy()
    quarter = trial.n_frames // 4
    pos[-quarter:, truth.marker_segment == 2] = np.nan
    light = np.full((trial.n_frames, 1, 3), np.nan)
    light[-quarter:, 0] = [1.0, 0.5, 1.0]
    trial = trial.replace(positions=np.concatenate([pos, light], axis=1), labels=(*trial.labels, "SYNC"))
    return trial, truth


def test_a_marker_never_seen_with_its_segment_is_left_out_and_the_rest_fitted_as_without_it(with_light):
    trial, truth = with_light
    options = RigidOptions(max_frames=150)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sk = fit_rigid(trial, np.append(truth.marker_segment, 2), truth.edges, truth.joint_positions, options=options)
    told = [w for w in caught if issubclass(w.category, jaxskel.DegenerateMotionWarning)]
    assert len(told) == 1 and "SYNC (segment 2) are never seen" in str(told[0].message)
    assert told[0].filename == __file__  # the caller's line, through the retry
    d = sk.diagnostics
    assert isinstance(d, RigidDiagnostics) and d.unplaced_markers == ("SYNC",) and d["unplaced_markers"] == ("SYNC",)
    assert d.hinges_unmoved is None and sk.marker_segment[-1] == -1 and np.isnan(sk.marker_offsets[-1]).all()
    without = fit_rigid(trial, np.append(truth.marker_segment, -1), truth.edges, truth.joint_positions, max_frames=150)
    np.testing.assert_array_equal(sk.marker_offsets, without.marker_offsets)
    np.testing.assert_array_equal(sk.joint_offsets, without.joint_offsets)
    np.testing.assert_array_equal(sk.marker_rms, without.marker_rms)
    rest = {k: v for k, v in d.items() if k != "unplaced_markers"}
    assert json.dumps(jsonable(rest)) == json.dumps(jsonable(without.diagnostics))  # NaN entries too
    # the fit itself is right: rod lengths of the linkage, within the noise
    np.testing.assert_allclose(sorted(sk.bone_lengths), [0.341], atol=2e-3)
