"""Tree utilities on the host: minimum spanning tree, tree centre, rooting.

The skeleton's topology is the minimum spanning tree of the joint-cost graph
(Kirk et al. 2005, §3.2): nodes are segments, edge weights the joint costs.
Infeasible pairs (infinite cost) are never edges; if they disconnect the graph
the result is a forest and every component is rooted separately.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree

__all__ = ["mst_edges", "tree_centre", "root_tree", "topological_order", "tree_path"]


def mst_edges(cost: np.ndarray) -> np.ndarray:
    """Undirected MST (or forest) edges (E, 2) of a symmetric cost matrix.

    ``inf``/NaN entries are absent edges. scipy treats 0 as "no edge", so costs
    are shifted by a positive constant first (the MST is invariant to a shift).
    """
    c = np.array(cost, dtype=float)
    n = c.shape[0]
    finite = np.isfinite(c) & ~np.eye(n, dtype=bool)
    if not finite.any():
        return np.zeros((0, 2), dtype=int)
    shift = 1.0 + np.abs(c[finite]).max()
    w = np.where(finite, c + shift, 0.0)
    w = np.triu(np.maximum(w, w.T), 1)
    t = minimum_spanning_tree(w).tocoo()
    edges = np.stack([t.row, t.col], axis=1).astype(int)
    return edges[np.lexsort((edges[:, 1], edges[:, 0]))]


def _adjacency(n: int, edges: np.ndarray) -> list[list[int]]:
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in edges:
        adj[int(a)].append(int(b))
        adj[int(b)].append(int(a))
    return adj


def _bfs(adj: list[list[int]], start: int) -> tuple[dict[int, int], dict[int, int]]:
    """Hops from ``start`` and the breadth-first parent of every node reached."""
    dist, parent = {start: 0}, {start: start}
    queue = deque([start])
    while queue:
        u = queue.popleft()
        for v in adj[u]:
            if v not in dist:
                dist[v] = dist[u] + 1
                parent[v] = u
                queue.append(v)
    return dist, parent


def tree_path(n: int, edges: np.ndarray, u: int, v: int) -> list[int]:
    """Nodes on the tree path ``u -> v`` (both included); ``[]`` in different components."""
    parent = _bfs(_adjacency(n, edges), u)[1]
    if v not in parent:
        return []
    path = [v]
    while path[-1] != u:
        path.append(parent[path[-1]])
    return path[::-1]


def tree_centre(n: int, edges: np.ndarray, component: list[int], weight: np.ndarray | None = None) -> int:
    """Centre of one tree component: minimal eccentricity in hops.

    Ties (a tree has at most two centres) go to the node with the larger
    ``weight`` (e.g. marker count), then the smaller index.
    """
    adj = _adjacency(n, edges)
    ecc = {u: max(_bfs(adj, u)[0].values()) for u in component}
    best = min(ecc.values())
    cands = [u for u in component if ecc[u] == best]
    if weight is not None:
        cands.sort(key=lambda u: (-float(weight[u]), u))
    return cands[0]


def root_tree(
    n: int, edges: np.ndarray, root: int | None = None, weight: np.ndarray | None = None
) -> tuple[np.ndarray, list[int]]:
    """Direct undirected tree/forest edges parent -> child.

    Returns ``(directed (E, 2), roots)``: one root per connected component, the
    given ``root`` for its component and the tree centre elsewhere. Edges are
    listed in breadth-first order from the roots, so a parent always precedes
    its children.
    """
    adj = _adjacency(n, edges)
    seen: set[int] = set()
    components: list[list[int]] = []
    order = ([root] if root is not None else []) + list(range(n))
    for s in order:
        if s not in seen:
            comp = sorted(_bfs(adj, s)[0])
            seen.update(comp)
            components.append(comp)
    roots, directed = [], []
    for comp in components:
        r = root if (root is not None and root in comp) else tree_centre(n, edges, comp, weight)
        roots.append(r)
        queue, visited = deque([r]), {r}
        while queue:
            u = queue.popleft()
            for v in sorted(adj[u]):
                if v not in visited:
                    visited.add(v)
                    directed.append((u, v))
                    queue.append(v)
    return np.asarray(directed, dtype=int).reshape(-1, 2), roots


def topological_order(n: int, edges: np.ndarray, roots: list[int]) -> list[int]:
    """Segments ordered so that every parent precedes its children."""
    children: list[list[int]] = [[] for _ in range(n)]
    for p, c in edges:
        children[int(p)].append(int(c))
    out, queue = [], deque(roots)
    while queue:
        u = queue.popleft()
        out.append(u)
        queue.extend(children[u])
    return out
