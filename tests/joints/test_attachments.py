"""Single-marker segments as attachments (jaxskel.joints._attachments), on hand-made graphs."""

import numpy as np

from jaxskel.joints._attachments import attachment_tree
from jaxskel.joints._tree import mst_edges


def _graph():
    """Segments 0-3 of three markers each (markers 0-11) and one-marker segments 4 (marker
    12) and 5 (marker 13). A true chain 0-1-2-3; marker 12 sits on the 1-2 joint (rigid
    with 1, next with 2); marker 13 rides on 3. The joint costs make 4 a hub: cheap with
    0, 1 and 3, as a one-marker segment is."""
    seg = np.array([0] * 3 + [1] * 3 + [2] * 3 + [3] * 3 + [4, 5])
    a = np.full((14, 14), 0.05)
    for s in range(4):
        idx = np.flatnonzero(seg == s)
        a[np.ix_(idx, idx)] = 0.001
    a[12, seg == 1], a[12, seg == 2], a[12, seg == 0], a[12, seg == 3] = 0.004, 0.008, 0.03, 0.04
    a[13, seg == 3], a[13, seg == 2] = 0.003, 0.02
    a = np.minimum(a, a.T)
    np.fill_diagonal(a, 0.0)
    cost = np.full((6, 6), 20.0)
    cost[0, 1] = cost[2, 3] = 4.0
    cost[1, 2] = 9.0  # the true 1-2 joint is dear (soft tissue)
    cost[4, 0], cost[4, 1], cost[4, 3], cost[4, 2] = 2.0, 2.5, 3.0, 6.0  # the hub's cheap joints
    cost[5, 3], cost[5, 2] = 1.0, 7.0
    cost[4, 5] = np.inf
    cost = np.minimum(cost, cost.T)
    np.fill_diagonal(cost, np.inf)
    return seg, a, cost


def test_a_one_marker_segment_is_a_leaf_of_its_most_rigid_segment_and_bridges_its_joint():
    seg, a, cost = _graph()
    plain = {tuple(e) for e in mst_edges(cost).tolist()}
    assert sum(4 in e for e in plain) >= 3  # the paper's tree: segment 4 is a hub
    edges, attachments, core = attachment_tree(cost, seg, a)
    assert {tuple(e) for e in edges.tolist()} == {(0, 1), (1, 2), (2, 3), (1, 4), (3, 5)}
    assert [(t.segment, t.host, t.bridge) for t in attachments] == [(4, 1, 2), (5, 3, 2)]
    assert core[1, 2] == 6.0  # the attachment's cost with its second most rigid segment
    assert np.isinf(core[4]).all() and np.isinf(core[:, 5]).all()


def test_invariant_to_the_order_of_segments():
    seg, a, cost = _graph()
    perm = np.array([3, 5, 0, 4, 2, 1])  # new index -> old segment
    inverse = np.argsort(perm)
    edges, _, _ = attachment_tree(cost[np.ix_(perm, perm)], inverse[seg], a)
    assert {tuple(sorted(perm[e].tolist())) for e in edges} == {(0, 1), (1, 2), (2, 3), (1, 4), (3, 5)}


def test_without_one_marker_segments_it_is_the_minimum_spanning_tree():
    rng = np.random.default_rng(0)
    seg = np.repeat(np.arange(6), 2)
    a = rng.uniform(0.001, 0.05, (12, 12))
    a = (a + a.T) / 2
    cost = rng.uniform(1, 10, (6, 6))
    cost = (cost + cost.T) / 2
    np.fill_diagonal(cost, np.inf)
    edges, attachments, _ = attachment_tree(cost, seg, a)
    assert attachments == () and edges.tolist() == mst_edges(cost).tolist()


def test_a_host_of_two_markers_is_kept_when_only_the_marker_count_makes_the_joint_infeasible():
    """A lone hand marker most rigid with a two-marker forearm: three markers, no joint
    cost, yet the forearm is its host (the joint is placed by the prior); a pair that is
    infeasible for another reason (never seen together) is no host."""
    seg = np.array([0, 0, 0, 1, 1, 2])
    a = np.full((6, 6), 0.05)
    a[5, 3:5] = a[3:5, 5] = 0.01
    cost = np.full((3, 3), np.inf)
    cost[0, 1] = cost[1, 0] = 4.0
    cost[0, 2] = cost[2, 0] = 3.0
    too_few = np.zeros((3, 3), bool)
    too_few[1, 2] = too_few[2, 1] = True
    edges, attachments, _ = attachment_tree(cost, seg, a, too_few)
    assert {tuple(e) for e in edges.tolist()} == {(0, 1), (1, 2)} and attachments[0].host == 1
    edges, attachments, _ = attachment_tree(cost, seg, a)  # not for want of markers: as before
    assert attachments == () and {tuple(e) for e in edges.tolist()} == {(0, 1), (0, 2)}
