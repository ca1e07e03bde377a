"""How well a recording determines joint centres and bone lengths (jaxskel.joints._determination).

The arithmetic is checked on hand-made diagnostics with known answers; the whole chain on
synthetic bodies lives with the fits it reads (tests/test_topology.py, walk and full body)
and on real recordings in tests/test_real_skeleton.py.
"""

from types import SimpleNamespace

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.joints._anchored_centres import MIN_EXERCISE_DEG
from jaxskel.joints._determination import UNDETERMINED_RESOLUTION

NAN3 = [np.nan] * 3


def _skeleton(resolution, cosines, *, placed=(), exercise=None, bones=((0, 1), (1, 2))):
    """A stand-in for a fitted Skeleton: three joints, the diagnostics the module reads."""
    n = len(resolution)
    axis = np.full((n, 3), np.nan)
    axis[list(placed)] = [0.0, 0.0, 1.0]
    anchored = {
        "resolution": np.asarray(resolution, float),
        "bone_cosines": np.asarray(cosines, float),
        "exercise": np.full(n, 20.0) if exercise is None else np.asarray(exercise, float),
    }
    return SimpleNamespace(
        n_joints=n, bones=np.asarray(bones), diagnostics={"anchored": anchored, "hinge_axis": axis.tolist()}
    )


def _cosines(n=3):
    """Joint j's three eigen-directions against the bone to joint i: (J, J, 3), NaN off-bone."""
    cos = np.full((n, n, 3), np.nan)
    cos[0, 1] = [0.6, 0.8, 0.0]
    cos[1, 0] = [1.0, 0.0, 0.0]
    cos[1, 2] = [0.0, 0.0, 1.0]
    cos[2, 1] = [0.0, 1.0, 0.0]
    return cos


def test_resolution_is_the_weakest_direction_nothing_else_fixes():
    """A ball joint reads its largest resolution; a hinge the rigid stage placed on its axis
    (its weakest direction fixed by that placement) reads its next one; no fit: unknown."""
    res = [[0.30, 0.05, 0.01], [0.40, 0.02, 0.01], NAN3]
    sk = _skeleton(res, _cosines(), placed=[1])
    np.testing.assert_allclose(jaxskel.joints.joint_resolution(sk), [0.30, 0.02, np.nan])


def test_bone_uncertainty_projects_each_joints_resolutions_on_the_bone():
    """sqrt(e_a^2 + e_b^2), e_j = sqrt(sum_k (r_k |v_k . u|)^2), by hand. The placed hinge's
    axis (its weakest direction, 0.40 m) runs along bone 0-1 as seen from joint 1 and adds
    nothing; a joint with no fit adds nothing either, leaving a lower bound."""
    res = [[0.30, 0.05, 0.01], [0.40, 0.02, 0.01], [0.03, 0.02, 0.01]]
    sk = _skeleton(res, _cosines(), placed=[1])
    e01 = np.hypot(0.30 * 0.6, 0.05 * 0.8)
    e10 = 0.0  # only the axis lies along the bone
    e12, e21 = 0.01, 0.02
    np.testing.assert_allclose(jaxskel.joints.bone_uncertainty(sk), [np.hypot(e01, e10), np.hypot(e12, e21)])
    unplaced = _skeleton(res, _cosines())
    assert jaxskel.joints.bone_uncertainty(unplaced)[0] == pytest.approx(np.hypot(e01, 0.40))
    res[2] = NAN3
    partial = _skeleton(res, _cosines(), placed=[1])
    np.testing.assert_allclose(jaxskel.joints.bone_uncertainty(partial), [np.hypot(e01, e10), e12])
    res[1] = NAN3
    none = _skeleton(res, _cosines())
    assert np.isnan(jaxskel.joints.bone_uncertainty(none)[1])


def test_undetermined_joints_are_those_beyond_the_limit_that_the_motion_exercises():
    res = [[0.30, 0.05, 0.01], [0.40, 0.02, 0.01], [0.50, 0.2, 0.1]]
    # joint 1: a placed hinge (0.02 m past its axis); joint 2: not exercised (its own warning)
    sk = _skeleton(res, _cosines(), placed=[1], exercise=[10.0, 10.0, 0.5 * MIN_EXERCISE_DEG])
    assert jaxskel.joints.undetermined_joints(sk) == [jaxskel.joints.UndeterminedJoint(0, 0.30)]
    assert jaxskel.joints.undetermined_joints(sk, limit=0.35) == []
    assert [u.joint for u in jaxskel.joints.undetermined_joints(sk, limit=0.01)] == [0, 1]
    assert UNDETERMINED_RESOLUTION == 0.1


@pytest.mark.parametrize("function", [jaxskel.joints.joint_resolution, jaxskel.joints.bone_uncertainty, jaxskel.joints.undetermined_joints])
def test_anything_but_a_skeleton_is_refused_with_a_clear_error(function):
    with pytest.raises(jaxskel.InputError, match=rf"{function.__name__}\(\) takes the rigid skeleton of a fit"):
        function("result.h5")


def test_a_fit_reports_resolutions_and_bounds_on_the_linkage():
    """The 3-link chain, 10 s of calibration motion: both joints have an anchor, are
    determined to a few centimetres, and the middle rod's length error (truth known) lies
    within the bound the resolutions give it. A bone on a joint's anchor keeps one
    direction in the anchor's frame, so its cosines are a unit vector's components."""
    trial, truth = synth.simulate(synth.linkage(), duration=10.0, seed=1, noise=0.001)
    result = jaxskel.fit_skeleton(trial, 3, ik=False)
    report = result.skeleton.diagnostics["anchored"]
    resolution = result.joint_resolutions()
    assert np.isfinite(resolution).all() and resolution.max() < 0.05, resolution
    assert result.undetermined_joints() == []
    for j, i in ((0, 1), (1, 0)):
        if report["anchor"][j] in set(result.edges[i].tolist()):  # the bone lies on j's anchor
            assert np.sum(report["bone_cosines"][j, i] ** 2) == pytest.approx(1.0, abs=1e-9)
        assert np.all((report["bone_cosines"][j, i] >= 0) & (report["bone_cosines"][j, i] <= 1))
    (bound,) = jaxskel.joints.bone_uncertainty(result.skeleton)
    (length,) = result.skeleton.bone_lengths
    middle = truth.bone_lengths[np.argmax(truth.bone_lengths)]
    assert abs(length - middle) < bound < 0.05
    (name,) = result.bone_lengths()
    assert result.bone_uncertainties() == {name: pytest.approx(bound)}
    assert "resolution [mm]" in result.summary() and "undetermined" not in result.summary()


def test_the_least_determined_direction_is_read_against_the_markers():
    """radial_share: the cosine of the weakest free direction with the lines to the other
    segment's markers (a placed hinge's next direction); loose_directions: how many free
    directions pass the limit."""
    res = [[0.30, 0.05, 0.01], [0.40, 0.20, 0.01], [0.50, 0.2, 0.1]]
    sk = _skeleton(res, _cosines(), placed=[1])
    sk.diagnostics["anchored"]["radial_cosines"] = np.array([[0.9, 0.1, 0.1], [0.2, 0.3, 0.9], NAN3])
    np.testing.assert_allclose(jaxskel.joints._determination.radial_share(sk), [0.9, 0.3, np.nan])
    np.testing.assert_array_equal(jaxskel.joints._determination.loose_directions(sk), [1, 1, 2])


@pytest.fixture(scope="module")
def short_arc():
    """The linkage with its second joint turned through 7 % of its range: that joint is
    undetermined (a 4.5 degree sweep, resolution 142 mm measured), the first is not."""
    trial, _ = synth.simulate(synth.linkage(), duration=10.0, seed=1, noise=0.001, joint_range={"joint2": 0.07})
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="undetermined") as caught:
        result = jaxskel.fit_skeleton(trial, 3)
    return result, [str(w.message) for w in caught if "undetermined" in str(w.message)]


def test_an_undetermined_joint_is_never_printed_as_a_length(short_arc, tmp_path):
    """The joints table says undetermined instead of the resolution, the bone ending at the
    joint undetermined instead of its bound, and the summary and warning say which motion
    is missing; the result file keeps the numbers."""
    result, (message,) = short_arc
    (u,) = result.undetermined_joints()
    name = result.joint_name(u.joint)
    assert u.resolution > UNDETERMINED_RESOLUTION and name == "R2M-R3M"
    text = result.summary()
    row, lack_line = [line for line in text.splitlines() if line.strip().startswith(f"{name}:")]
    assert row.endswith("undetermined") and f"{1000 * u.resolution:.1f}" not in text
    (bone,) = [line for line in text.splitlines() if line.startswith("  R2M (")]
    assert bone.endswith(f"undetermined (joint {name})")
    assert "> 10 m" not in text and "10 m" not in message
    lack = (f"{name}: needs a larger range of rotation of R3M about its joint with R2M: the recorded sweep "
            f"({result.skeleton.diagnostics['anchored']['exercise'][u.joint]:.1f} deg RMS) is too short an arc")
    assert lack_line.strip().startswith(lack) and lack in message
    (other,) = {0, 1} - {u.joint}
    assert f"{1000 * result.joint_resolutions()[other]:7.1f}" in text  # a determined joint keeps its number
    result.save(tmp_path / "r.h5")
    back = jaxskel.load_result(tmp_path / "r.h5")
    np.testing.assert_allclose(back.joints.resolution, result.joint_resolutions())
    assert back.joints.undetermined.tolist() == [u.joint]


def test_the_summary_says_how_the_tree_was_chosen_and_how_close_the_runner_up_came(short_arc):
    result, _ = short_arc
    text = result.summary()
    assert "tree: minimum spanning tree of the joint costs, the pose check exchanged none; rooted at its centre" in text
    best = jaxskel.joints._near_ties.runner_up(result.topology)
    (p, c), (a, b) = best.edge, best.rival
    names = result.segment_names
    swap = f"{names[a]}-{names[b]} instead of {names[p]}-{names[c]}"
    assert f"runner-up: {swap}, MST weight {100 * best.margin:+.1f} %" in text
