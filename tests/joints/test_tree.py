"""Tree utilities of the joints stage on hand-made graphs (jaxskel.joints._tree, the rival
pairs of jaxskel.joints._near_ties): minimum spanning tree, rooting, paths, cuts."""

import numpy as np

from jaxskel.joints._near_ties import rival_edges
from jaxskel.joints._tree import mst_edges, root_tree, tree_path


def undirected(edges):
    return {frozenset(map(int, e)) for e in edges}


def test_mst_and_rooting_on_a_known_graph():
    inf = np.inf
    cost = np.array(
        [
            [inf, 1.0, 5.0, inf],
            [1.0, inf, 2.0, 9.0],
            [5.0, 2.0, inf, 0.0],  # a zero cost must still be an edge
            [inf, 9.0, 0.0, inf],
        ]
    )
    edges = mst_edges(cost)
    assert undirected(edges) == {frozenset((0, 1)), frozenset((1, 2)), frozenset((2, 3))}
    directed, roots = root_tree(4, edges)
    assert roots in ([1], [2])  # a path of 4 has two centres
    parents = {int(c): int(p) for p, c in directed}
    assert len(parents) == 3 and roots[0] not in parents
    directed, roots = root_tree(4, edges, root=0)
    assert roots == [0] and [tuple(e) for e in directed] == [(0, 1), (1, 2), (2, 3)]


def test_rival_edges_are_the_cheapest_pairs_across_each_cut():
    inf = np.inf
    cost = np.array(
        [
            [inf, 1.0, 5.0, inf],
            [1.0, inf, 2.0, 9.0],
            [5.0, 2.0, inf, 0.5],
            [inf, 9.0, 0.5, inf],
        ]
    )
    edges = mst_edges(cost)  # 0-1, 1-2, 2-3
    rivals = dict(zip(map(tuple, edges.tolist()), rival_edges(cost, edges)))
    # without 0-1 only 0-2 crosses; without 1-2 the cheapest of 0-2 (5) and 1-3 (9); 2-3: 1-3
    assert {k: tuple(sorted(v)) for k, v in rivals.items()} == {(0, 1): (0, 2), (1, 2): (0, 2), (2, 3): (1, 3)}
    cost[0, 2] = cost[2, 0] = inf  # no other pair reaches segment 0
    assert rival_edges(cost, edges)[0] is None


def test_disconnected_graph_gives_forest():
    inf = np.inf
    cost = np.array([[inf, 1, inf, inf], [1, inf, inf, inf], [inf, inf, inf, 2], [inf, inf, 2, inf]])
    directed, roots = root_tree(4, mst_edges(cost))
    assert len(roots) == 2 and len(directed) == 2
    edges = mst_edges(cost)
    assert tree_path(4, edges, 0, 1) == [0, 1] and tree_path(4, edges, 0, 2) == []
    star = np.array([[0, 1], [1, 2], [1, 3], [3, 4]])
    assert tree_path(5, star, 2, 4) == [2, 1, 3, 4] and tree_path(5, star, 4, 4) == [4]
