"""One options object drives the API and the CLI: jaxskel.FitOptions, its validation,
its flat names, and the flags derived from it."""

import argparse
import dataclasses
import math

import numpy as np
import pytest

import jaxskel
from jaxskel import FitOptions, InputError, synth
from jaxskel.cli import add_setting_flags, options_from_args
from jaxskel.pipeline import CleanOptions, JointOptions, MotionOptions, SegmentOptions, StagePlan


def _other_value(info, default):
    """A valid value of a setting other than its default."""
    c = info.constraint
    candidates = [True, False, "auto", None, "per_frame", "prior", "ncg", "lm", "limb_plane", "anchored",
                  2, 3, 7, 12, 0.004, 0.5, 1.5, 4.0, "RTHPA"]
    for v in candidates:
        numbers = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (v, default))
        if v is default or (type(v) is type(default) and v == default) or (numbers and float(v) == float(default)):
            continue
        if c.accepts(v):
            return v
    raise AssertionError(f"no other value for {info.flat}")


def _settings():
    return list(FitOptions.settings())


def test_every_setting_has_one_flat_name_and_a_doc():
    flats = [info.flat for _, _, info, _ in _settings()]
    assert len(flats) == len(set(flats))
    assert all(info.doc and info.constraint.accepts(default) for _, _, info, default in _settings())
    # the settings fit_skeleton always had are all there
    for name in ("n_segments", "root", "clean_data", "merge_labels", "alpha", "alpha_tree", "method",
                 "topology_frames", "rigid", "ik", "seed", "confirm_merges", "hinge_centres", "joint_centres",
                 "ik_lowpass", "pose_check", "sigma", "mend", "min_run_s"):
        assert name in flats


def test_defaults_are_the_stage_functions_defaults():
    """A setting's default is the default of the stage function it is handed to."""
    import inspect

    clean_sig = inspect.signature(jaxskel.clean.clean).parameters
    for name, value in CleanOptions().kwargs().items():
        assert clean_sig[name].default == value, name
    seg_sig = inspect.signature(jaxskel.segment.segment_markers).parameters
    for name, value in SegmentOptions().kwargs().items():
        assert seg_sig[name].default == value, name
    topo_sig = inspect.signature(jaxskel.joints.fit_topology).parameters
    j = JointOptions()
    assert (topo_sig["alpha"].default, topo_sig["alpha_tree"].default, topo_sig["method"].default) == (
        j.alpha, j.alpha_tree, j.method)


@pytest.mark.parametrize("flat,value", [
    ("n_segments", 0), ("n_segments", 2.5), ("method", "gauss"), ("sigma", -0.01), ("sigma", math.nan),
    ("ik_lowpass", 0.0), ("ik_lowpass", "fast"), ("merge_labels", "yes"), ("rigid", 1), ("root", -1),
    ("topology_frames", 3), ("alpha_tree", "never"), ("seed", -1), ("trim_s", math.inf),
])
def test_bad_values_are_refused_naming_the_setting(flat, value):
    with pytest.raises(InputError, match=flat):
        FitOptions.from_settings(**{flat: value})


def test_unknown_setting_names_the_closest():
    with pytest.raises(InputError, match="did you mean 'sigma'"):
        FitOptions.from_settings(sigam=0.01)
    with pytest.raises(InputError, match="unknown setting"):
        jaxskel.fit_skeleton(synth.simulate(synth.linkage(), duration=2.0, seed=0)[0], segment_kwargs={})


def test_groups_are_validated_on_construction_and_frozen():
    with pytest.raises(InputError, match="n_segments"):
        SegmentOptions(n_segments=-3)
    with pytest.raises(InputError, match="FitOptions.motion"):
        FitOptions(motion=JointOptions())
    options = FitOptions(segment=SegmentOptions(n_segments=4), motion=MotionOptions(lowpass=None))
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.seed = 3
    assert options.get("n_segments") == 4 and options.get("ik_lowpass") is None


def test_replace_round_trips_every_setting():
    base = FitOptions()
    for group, field, info, default in _settings():
        value = _other_value(info, default)
        changed = base.replace(**{info.flat: value})
        assert changed.get(info.flat) == value or (value is None and changed.get(info.flat) is None)
        assert (getattr(changed, group) if group else changed) != (getattr(base, group) if group else base)
        assert FitOptions.from_settings(**changed.as_flat()) == changed
    assert base.replace() == base


def test_every_setting_is_a_flag_and_the_flags_give_the_same_options():
    parser = argparse.ArgumentParser()
    add_setting_flags(parser)
    assert options_from_args(parser.parse_args([])) == FitOptions()
    for _group, _field, info, default in _settings():
        value = _other_value(info, default)
        action = next(a for a in parser._actions if a.dest == info.flat)
        if isinstance(default, bool) and not info.cli_values:
            argv = [action.option_strings[0]]
        else:
            shown = {v: k for k, v in (info.cli_values or {}).items()}.get(value, value)
            argv = [action.option_strings[0], "none" if shown is None else str(shown)]
        got = options_from_args(parser.parse_args(argv))
        assert got == FitOptions.from_settings(**{info.flat: value}), argv


def test_a_bad_flag_value_is_a_clear_error(capsys):
    with pytest.raises(SystemExit):
        jaxskel.cli.main(["fit", "x.c3d", "-o", "y.h5", "--sigma", "wide"])
    assert "sigma must be" in capsys.readouterr().err


def test_stage_plan_lists_the_stages_the_options_run():
    assert StagePlan().stages == ("clean", "merge labels", "segment", "joint costs", "tree joints", "rigid", "ik",
                                  "anatomy")
    assert StagePlan(FitOptions.from_settings(ik=False)).stages[-2:] == ("rigid", "anatomy")
    assert StagePlan(FitOptions.from_settings(anatomy=False)).stages[-1] == "ik"
    assert "rigid" not in StagePlan(FitOptions.from_settings(rigid=False)).stages


def test_fit_batch_takes_every_setting_fit_skeleton_takes(tmp_path):
    """Segment and cleaning settings reach the batch's stages as they reach fit_skeleton's
    (before the options object, fit_batch had no segment settings at all)."""
    trial, truth = synth.simulate(synth.linkage(), duration=6.0, seed=5, noise=0.001)
    options = FitOptions.from_settings(n_segments=3, sigma=0.006, n_samplings=3, rigid=False)
    single = jaxskel.fit_skeleton(trial, options=options)
    batch = jaxskel.fit_batch([trial], options=options, keep_results=True)
    (outcome,) = batch.outcomes if hasattr(batch, "outcomes") else list(batch)
    assert outcome.status == "ok"
    for r in (single, outcome.result):
        assert r.segmentation.sigma == pytest.approx(0.006)
        assert r.segmentation.n_segments == 3 and r.skeleton is None
    np.testing.assert_array_equal(single.segmentation.marker_segment, outcome.result.segmentation.marker_segment)
    np.testing.assert_allclose(single.topology.joint_positions, outcome.result.topology.joint_positions,
                               rtol=1e-6, atol=1e-9)
