"""Readable segment names from marker labels (jaxskel.segment._names): the rule, uniqueness, and
that a fit names its segments by it without its labels changing the skeleton."""

import dataclasses
import re
import warnings

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.segment import names_from_markers
from jaxskel.segment._names import group_name, segment_names


@pytest.mark.parametrize(
    ("labels", "name"),
    [
        (["RTHPA", "RTHPP", "RTHDP", "RTHDA"], "RTH"),  # a common prefix
        (["R1M1", "R1M2", "R1M3"], "R1M"),  # trailing digits left out of the prefix
        (["LFWT", "RFWT", "LBWT", "RBWT"], "LFWT+RFWT+LBWT+RBWT"),  # no prefix: the markers
        (["LKNE", "LTHI"], "LKNE+LTHI"),  # "L" is a side, not a part
        (["L_ASIS", "L_PSIS"], "L_ASIS+L_PSIS"),  # nor is "L_"
        (["LeftKnee", "LeftHip"], "LeftKnee+LeftHip"),  # nor "Left"
        (["T1", "T10"], "T1+T10"),  # "T1" would name a marker, not the group
        (["*12", "*13"], "*12+*13"),
        (["LFHD", "RFHD", "LBHD", "RBHD", "C7"], "LFHD+RFHD+LBHD+2more"),  # long lists cut to three
        (["C7"], "C7"),  # one marker: its label
        (["Sam:RTHPA", "Sam:RTHPP"], "RTHP"),  # subject prefixes read past
        (["Sam:C7"], "C7"),
        (["left knee"], "left_knee"),  # one token
    ],
)
def test_a_segment_is_named_after_its_markers(labels, name):
    assert group_name(labels) == name


def test_names_are_unique_and_single_tokens():
    """A prefix two segments share names them by their markers instead; a name still taken
    (the same label on two subjects) gets a number; a segment without markers its index."""
    groups = [["RTHPA", "RTHDA"], ["RTHPP", "RTHDP"], ["A:C7"], ["B:C7"], ["C7"], [], ["LTOE", "LHEE", "LMT5"]]
    names = segment_names(groups)
    assert names == ("RTHPA+RTHDA", "RTHPP+RTHDP", "C7", "C7_2", "C7_3", "seg5", "LTOE+LHEE+LMT5")
    rng = np.random.default_rng(0)
    alphabet = list("LRABT7_ :*")
    for _ in range(200):
        groups = [["".join(rng.choice(alphabet, rng.integers(1, 5))) for _ in range(rng.integers(0, 6))]
                  for _ in range(rng.integers(1, 8))]
        names = segment_names(groups)
        assert len(set(names)) == len(names) == len(groups), groups
        assert all(name and not re.search(r"\s", name) for name in names), names


def test_names_from_marker_segments():
    labels = ["R1M1", "R2M1", "R1M2", "X"]
    assert names_from_markers(labels, np.array([0, 1, 0, -1]), 3) == ("R1M", "R2M1", "seg2")


@pytest.fixture(scope="module")
def body_fit():
    trial, truth = synth.simulate(synth.full_body(seed=0), duration=12.0, seed=0, noise=0.002, gaps=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return trial, truth, jaxskel.fit_skeleton(trial, rigid=False, ik=False)


def test_a_fitted_body_is_named_from_its_marker_labels(body_fit):
    """The synthetic full body (Plug-in-gait-like labels, no two of a segment sharing more
    than their side letter): every segment is named by its markers, the names are unique,
    and the summary and joint names use them."""
    trial, truth, result = body_fit
    groups = result.segmentation.groups
    assert result.segment_names == segment_names(groups)
    assert len(set(result.segment_names)) == result.n_segments
    assert "LASI+RASI+LPSI+RPSI" in result.segment_names  # the pelvis
    text = result.summary()
    for name, group in zip(result.segment_names, groups):
        assert f"{name}: {', '.join(group)}" in text
    for j, (p, c) in enumerate(result.edges):
        assert result.joint_name(j) == f"{result.segment_names[p]}-{result.segment_names[c]}"
        assert result.joint_name(j) in text
    assert not re.search(r"\bseg\d+\b", text)


def test_labels_name_segments_but_never_change_the_fit(body_fit):
    """The same recording under other labels (a subject prefix, then the labels reversed):
    the same groups and tree, the names follow the labels, and given names still win."""
    trial, truth, result = body_fit
    prefixed = jaxskel.Trial(trial.positions, tuple(f"Sam:{lab}" for lab in trial.labels), trial.rate)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = jaxskel.fit_skeleton(prefixed, rigid=False, ik=False)
    assert again.segment_names == result.segment_names
    np.testing.assert_array_equal(again.segmentation.marker_segment, result.segmentation.marker_segment)
    np.testing.assert_array_equal(again.edges, result.edges)
    renamed = jaxskel.Trial(trial.positions, tuple(lab[::-1] for lab in trial.labels), trial.rate)
    given = [f"part{i}" for i in range(result.n_segments)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        other = jaxskel.fit_skeleton(renamed, rigid=False, ik=False, segment_names=given)
    np.testing.assert_array_equal(other.segmentation.marker_segment, result.segmentation.marker_segment)
    np.testing.assert_array_equal(other.edges, result.edges)
    np.testing.assert_allclose(other.topology.joint_cost, result.topology.joint_cost)
    assert other.segment_names == tuple(given)


def test_plots_label_segments_by_name(body_fit, tmp_path):
    """The joint-cost matrix's axes, the distance std-dev blocks, the 3-D legend and the
    tree diagram."""
    _, _, result = body_fit
    names = list(result.segment_names)
    costs = jaxskel.plots.plot_joint_costs(result)
    assert [t.get_text() for t in costs.get_xticklabels()] == names
    blocks = jaxskel.plots.plot_distance_std(result)
    (top,) = [child for child in blocks.get_children() if type(child).__name__ == "SecondaryAxis"]
    assert sorted(t.get_text() for t in top.get_xticklabels()) == sorted(names)
    legend = jaxskel.plots.plot_skeleton_3d(result).get_legend()
    assert [t.get_text() for t in legend.get_texts()] == names
    tree = jaxskel.plots.plot_tree(result)  # the hierarchy: every segment once, the root on top
    boxes = {t.get_text(): t.get_position() for t in tree.texts}
    assert sorted(boxes) == sorted(names)
    root = names[result.topology.root]
    assert boxes[root][1] == max(y for _, y in boxes.values())
    for p, c in result.edges.tolist():  # a child one level below its parent
        assert boxes[names[c]][1] == boxes[names[p]][1] - 1
    jaxskel.plots.plot_summary(result, tmp_path / "summary.png")
    assert (tmp_path / "summary.png").stat().st_size > 10_000


def test_the_3d_plot_draws_a_segment_with_markers_missing_in_its_frame(body_fit):
    """A four-marker segment with two markers missing in the drawn frame: matplotlib read
    the segment's one RGBA colour as four colours for the two points left and raised
    (numediart's 03_rolling stopped `jaxskel fit --plot` with a traceback); its two seen
    markers are drawn, in the segment's colour."""
    import matplotlib.pyplot as plt

    _, _, result = body_fit
    seg = result.segmentation.marker_segment
    s = int(np.flatnonzero(np.bincount(seg) == 4)[0])
    frame = 10
    x = np.array(result.trial.positions)
    x[frame, np.flatnonzero(seg == s)[:2]] = np.nan
    broken = dataclasses.replace(result, trial=result.trial.replace(positions=x))
    ax = jaxskel.plots.plot_skeleton_3d(broken, frame=frame)
    (points,) = [c for c in ax.collections if c.get_label() == result.segment_names[s]]
    assert len(points.get_offsets()) == 2
    np.testing.assert_allclose(points.get_facecolor()[0][:3], plt.get_cmap("tab20")(s % 20)[:3], atol=1e-6)
