"""The summary's lines about the tree and about undetermined joints, on hand-made
topologies and skeletons (jaxskel.result._summary, with the runner-up of
jaxskel.joints._near_ties and the attachments of jaxskel.joints._attachments as their input).

Unit tests of the result stage's internals: they belong in tests/result/, beside that
stage, and wait here (moved unchanged from tests/test_topology.py and
tests/test_determination.py, now tests/joints/) until that folder's owner takes them in. The summary's
wording is also checked end to end through ``SkeletonResult.summary()`` in
tests/test_topology.py and tests/joints/test_determination.py.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from jaxskel.joints import PoseExchange
from jaxskel.joints._attachments import attachment_tree
from jaxskel.joints._near_ties import runner_up
from jaxskel.result._summary import pose_exchange_text as _pose_exchange_text
from jaxskel.result._summary import tree_lines, undetermined_lines

NAN3 = [np.nan] * 3


def test_the_runner_up_tree_swaps_the_joint_with_the_smallest_margin_and_the_summary_says_so():
    """Of the trees differing in one joint, the runner-up swaps the joint whose rival costs the
    least more, relatively (1-2 -> 0-2: +150 %; 0-1 -> 0-2 is +400 %, 2-3 -> 1-3 +1700 %); a
    rival the pose check overruled is passed over, and the summary's tree line says how the
    tree was chosen."""
    inf = np.inf
    cost = np.array(
        [
            [inf, 1.0, 5.0, inf],
            [1.0, inf, 2.0, 9.0],
            [5.0, 2.0, inf, 0.5],
            [inf, 9.0, 0.5, inf],
        ]
    )
    edges = np.array([[0, 1], [1, 2], [2, 3]])
    topology = SimpleNamespace(edges=edges, pair_costs=SimpleNamespace(cost=cost), pose_exchanges=())
    best = runner_up(topology)
    assert (best.joint, best.edge, tuple(sorted(best.rival))) == (1, (1, 2), (0, 2))
    assert best.margin == pytest.approx(1.5)
    names = ("A", "B", "C", "D")
    assert tree_lines(topology, names, {"root": None}) == [
        "tree: minimum spanning tree of the joint costs, the pose check exchanged none; rooted at its centre",
        "  runner-up: A-C instead of B-C, MST weight +150.0 % (5000000.000 against 2000000.000 mm^2): the "
        "smallest margin of any joint over the cheapest other pair across its cut",
    ]
    exchange = PoseExchange(removed=(0, 2), added=(1, 2), misfit=(1.0, 0.1), cost=(5.0, 2.0))
    checked = SimpleNamespace(edges=edges, pair_costs=SimpleNamespace(cost=cost), pose_exchanges=(exchange,))
    # 0-2, the rival of 0-1 and 1-2, was overruled: never a rival, the next cheapest pair across the cut is
    # (1-2 -> 1-3, +350 %; 0-1 has none left)
    best = runner_up(checked)
    assert (best.edge, tuple(sorted(best.rival)), best.margin) == ((1, 2), (1, 3), pytest.approx(3.5))
    # a joint the pose check placed may cost more than a pair across its cut: a margin below zero, said so
    # (here 0-2, 5, where 1-2 costs 2: -60 %)
    dear = SimpleNamespace(edges=np.array([[0, 1], [0, 2]]), pair_costs=SimpleNamespace(cost=cost[:3, :3]),
                           pose_exchanges=(exchange._replace(removed=(1, 2), added=(0, 2)),))
    assert runner_up(dear) is None  # 1-2 overruled: no other pair crosses either cut
    dear.pose_exchanges = ()  # a tree that is not the costs' MST, however it came about
    (line,) = tree_lines(dear, names[:3], {"pose_check": True})[1:]
    assert "A-C, MST weight -60.0 %" in line and line.endswith("(below zero: the pose check jointed the dearer pair)")
    lines = tree_lines(checked, names, {"root": 0, "pose_check": True})
    assert lines[0] == (
        "tree: minimum spanning tree of the joint costs, then 1 joint(s) exchanged by the pose check (below); "
        "rooted as given"
    )
    sphere = exchange._replace(test="sphere", misfit=(45e-6, 12.8e-6))
    assert _pose_exchange_text(sphere, names) == (
        "pose check: B-C jointed instead of A-C: one segment's markers about a centre fixed in the other's pose fit "
        "12.8 against 45.0 mm^2 (joint costs 2000000.000 against 5000000.000 mm^2)"
    )
    assert "a centre fixed in both segments fits" in _pose_exchange_text(exchange, names)
    alone = SimpleNamespace(edges=edges[:1], pair_costs=SimpleNamespace(cost=cost[:2, :2]), pose_exchanges=())
    assert tree_lines(alone, names[:2], {"pose_check": False}) == [
        "tree: minimum spanning tree of the joint costs, no pose check; rooted at its centre",
        "  runner-up: none (no joint chosen by cost has another feasible pair across its cut)",
    ]


def test_an_attachment_is_named_in_the_tree_line_and_has_no_runner_up():
    """Segment 3, one marker, hangs from segment 2 (the most rigid) by rigidity, not cost:
    its pair with segment 1 is cheaper than the tree's joints (a negative margin on the
    joint costs) but is no runner-up; on the core's costs (3 left out, 1-2 bridged by 3's cost with 1) the
    runner-up swaps 0-1 for 0-2 (+400 %)."""
    inf = np.inf
    cost = np.array([[inf, 1.0, 5.0, 9.0], [1.0, inf, 2.0, 0.05], [5.0, 2.0, inf, 0.1], [9.0, 0.05, 0.1, inf]])
    marker_segment = np.array([0, 0, 1, 1, 2, 2, 3])
    distance_std = np.full((7, 7), 0.05)
    distance_std[6, 4:6] = distance_std[4:6, 6] = 0.002  # the lone marker moves with segment 2
    distance_std[6, 2:4] = distance_std[2:4, 6] = 0.01  # then with segment 1
    segmentation = SimpleNamespace(marker_segment=marker_segment, distance_std=distance_std)
    edges, attachments, _ = attachment_tree(cost, marker_segment, distance_std)
    assert attachments[0][:3] == (3, 2, 1)
    topology = SimpleNamespace(
        edges=edges, pair_costs=SimpleNamespace(cost=cost, too_few_markers=None), pose_exchanges=(),
        attachments=attachments,
    )
    plain = runner_up(topology)  # the joint costs alone: 1-3, cheaper than the tree's joints
    assert 3 in plain.rival and plain.margin < 0
    lines = tree_lines(topology, ("A", "B", "C", "D"), {}, segmentation)
    assert lines[0] == (
        "tree: minimum spanning tree of the joint costs between segments of two or more markers, 1 one-marker "
        "segment(s) hung from the most rigid, the pose check exchanged none; rooted at its centre"
    )
    assert lines[1].startswith("  runner-up: A-C instead of A-B, MST weight +400.0 %")


@pytest.mark.parametrize(
    ("resolution", "radial", "exercise", "words"),
    [
        ([0.3, 0.05, 0.01], 0.95, 20.0, "needs a larger range of rotation of B about its joint with A: the recorded "
         "sweep (20.0 deg RMS) is too short an arc to fix how far the centre lies from the markers of B"),
        ([0.3, 0.05, 0.01], 0.2, 20.0, "needs rotation of B about its joint with A in more directions: the recorded "
         "sweep (20.0 deg RMS) turns it mainly about one axis, along which the centre can slide"),
        ([0.3, 0.2, 0.01], 0.95, 20.0, "needs rotation of B about its joint with A over a larger range and in more "
         "directions: the recorded sweep (20.0 deg RMS) leaves the centre loose along two directions"),
        ([0.3, 0.05, 0.01], 0.7, 20.0, "loose along a direction neither along nor across its markers"),
        ([0.3, 0.2, 0.1], 0.95, 1.0, "needs rotation of B about its joint with A: the recording barely turns it "
         "(sweep 1.0 deg RMS)"),
    ],
)
def test_an_undetermined_joint_is_told_the_motion_it_lacks(resolution, radial, exercise, words):
    """Two segments A (the anchor) and B: the words follow the weakest direction's reading."""
    sk = SimpleNamespace(
        n_joints=1, bones=np.zeros((0, 2), int), edges=np.array([[0, 1]]),
        diagnostics={"hinge_axis": [NAN3], "anchored": {
            "resolution": np.array([resolution]), "bone_cosines": np.full((1, 1, 3), np.nan),
            "exercise": np.array([exercise]), "anchor": np.array([0]), "radial_cosines": np.array([[radial, 0, 0]]),
        }},
    )
    lines = undetermined_lines([0], ("A", "B"), sk)
    assert lines[0].startswith("undetermined: the recording fixes these centres only to within more than 100 mm")
    assert lines[1].startswith("  A-B: ") and words in lines[1]
    assert "range-of-motion trial" in lines[-1]
