"""Host-side assignment for label merging: spectral clustering and exact chain linking.

Fragments (contiguous runs of one label) are time intervals. Two fragments
that overlap in time are different physical markers (a cannot-link); one
physical marker is a sequence of non-overlapping fragments, a *chain*.

* :func:`spectral_clusters` is the paper's step (Kirk et al. §4): Gaussian
  affinities from the distance matrix D, zero affinity between co-occurring
  fragments, spectral clustering into n' groups. Spectral clustering honours
  cannot-links only softly, so its groups are used as a prior, not as the answer.
* :class:`ChainProblem` is the exact step: a minimum-cost assignment of each
  fragment's end to at most one later fragment's start. Links only go forward
  in time, so chains can never contain co-occurring fragments: the cannot-link
  constraint holds by construction. The assignment also chooses the number of
  chains (each costs ``chain_cost``; at most ``n_max``, or exactly ``n_max``)
  and which short fragments to drop as ghosts (each costs ``drop_cost``).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy.optimize import linear_sum_assignment

__all__ = ["spectral_clusters", "Chains", "ChainProblem"]

# Cost of a forbidden assignment: far above any sum of real costs (metres).
_FORBIDDEN = 1e6
# Affinity between any two compatible fragments (see spectral_clusters).
_AFFINITY_FLOOR = 1e-6


def spectral_clusters(
    distance: Float[np.ndarray, "K K"],
    cannot_link: Bool[np.ndarray, "K K"],
    n_clusters: int,
    scale: float,
) -> Int[np.ndarray, " K"]:
    """Spectral clustering of fragments on ``exp(-D^2 / (2 scale^2))`` affinities.

    Co-occurring and never-comparable pairs get zero affinity, other pairs at
    least _AFFINITY_FLOOR. Fragments with no
    affinity to anything (typically markers that are never lost) are their own
    clusters, and the remaining ``n_clusters - n_isolated`` clusters are found by
    scikit-learn's ``SpectralClustering`` (precomputed affinity, QR-based label
    assignment, which is deterministic).
    """
    from sklearn.cluster import SpectralClustering

    n = distance.shape[0]
    ok = ~cannot_link & np.isfinite(distance)
    np.fill_diagonal(ok, False)
    affinity = np.where(ok, np.exp(-0.5 * (np.where(ok, distance, 0.0) / scale) ** 2), 0.0)
    isolated = affinity.sum(axis=1) <= 1e-12
    labels = np.empty(n, dtype=int)
    labels[isolated] = np.arange(int(isolated.sum()))
    rest = np.flatnonzero(~isolated)
    k = min(max(n_clusters - int(isolated.sum()), 1), rest.size)
    if rest.size == 0:
        return labels
    if k == rest.size:
        labels[rest] = isolated.sum() + np.arange(rest.size)
        return labels
    # Physical markers are nearly disconnected components by design, which makes
    # the eigen-solver (ARPACK) fail; a floor far below any real affinity between
    # compatible fragments keeps the graph connected without changing the clusters.
    sub = affinity[np.ix_(rest, rest)] + _AFFINITY_FLOOR * ok[np.ix_(rest, rest)]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Graph is not fully connected")
        model = SpectralClustering(
            n_clusters=k, affinity="precomputed", assign_labels="cluster_qr", random_state=0
        ).fit(sub)
    labels[rest] = isolated.sum() + model.labels_
    return labels


@dataclasses.dataclass(frozen=True)
class Chains:
    """Result of :meth:`ChainProblem.solve`.

    Attributes
    ----------
    chain
        (K,) chain index of each fragment, -1 if dropped; chains numbered by the
        start frame of their first fragment.
    successor
        (K,) next fragment in the same chain, -1 at a chain's end or if dropped.
    dropped
        (K,) fragments the assignment dropped (its diagonal entries).
    n_chains
        Number of chains.
    cost
        Total cost of the assignment (metres).
    """

    chain: Int[np.ndarray, " K"]
    successor: Int[np.ndarray, " K"]
    dropped: Bool[np.ndarray, " K"]
    n_chains: int
    cost: float


@dataclasses.dataclass(frozen=True)
class ChainProblem:
    """Minimum-cost cover of K fragments by at most (or exactly) ``n_max`` chains.

    A linear assignment on a square matrix of size ``K + n_max``. Rows are the
    fragments' ends plus ``n_max`` chain sources, columns the fragments' starts
    plus ``n_max`` chain sinks:

    ========== ================================ ===============
    row \\ col  start of fragment j               sink
    ========== ================================ ===============
    end of i   ``link_cost[i, j]`` if j starts   0 (i ends a chain)
               after i stops; ``drop_cost`` on
               the diagonal if i is droppable
    source     ``chain_cost`` (j begins a chain)  0 (unused chain),
                                                  forbidden if ``exact``
    ========== ================================ ===============

    Every fragment is then either dropped or has exactly one predecessor
    (another fragment or a source) and one successor (another fragment or a
    sink), so the fragments form at most ``n_max`` chains ordered in time.
    """

    matrix: Float[np.ndarray, "N N"]
    start: Int[np.ndarray, " K"]

    @classmethod
    def build(
        cls,
        start: Int[np.ndarray, " K"],
        stop: Int[np.ndarray, " K"],
        link_cost: Float[np.ndarray, "K K"],
        droppable: Bool[np.ndarray, " K"],
        drop_cost: float,
        n_max: int,
        chain_cost: float,
        exact: bool = False,
    ) -> ChainProblem:
        k = start.size
        forward = start[None, :] >= stop[:, None]
        matrix = np.zeros((k + n_max, k + n_max))
        matrix[:k, :k] = np.where(forward & np.isfinite(link_cost), link_cost, _FORBIDDEN)
        matrix[np.arange(k), np.arange(k)] = np.where(droppable, drop_cost, _FORBIDDEN)
        matrix[k:, :k] = chain_cost
        matrix[k:, k:] = _FORBIDDEN if exact else 0.0
        return cls(matrix=matrix, start=start)

    def solve(self) -> Chains:
        """The optimal chains. Raises ``ValueError`` if every cover needs a forbidden entry
        (e.g. ``n_max`` is below the number of undroppable fragments seen in one frame)."""
        k = self.start.size
        rows, cols = linear_sum_assignment(self.matrix)
        total = float(self.matrix[rows, cols].sum())
        if total >= _FORBIDDEN:
            raise ValueError("no chain cover within the constraints")
        inner = (rows < k) & (cols < k)
        rows, cols = rows[inner], cols[inner]
        dropped = np.zeros(k, dtype=bool)
        dropped[rows[rows == cols]] = True
        successor = np.full(k, -1)
        successor[rows[rows != cols]] = cols[rows != cols]
        has_pred = np.zeros(k, dtype=bool)
        has_pred[cols[rows != cols]] = True
        chain = np.full(k, -1)
        heads = np.flatnonzero(~has_pred & ~dropped)
        heads = heads[np.argsort(self.start[heads], kind="stable")]
        for index, head in enumerate(heads):  # host-side walk over <= K fragments
            f = head
            while f >= 0:
                chain[f] = index
                f = successor[f]
        return Chains(chain=chain, successor=successor, dropped=dropped, n_chains=int(heads.size), cost=total)

    def confidence(self, chains: Chains, decisions: Int[np.ndarray, "D 2"]) -> Float[np.ndarray, " D"]:
        """Confidence of chosen decisions: links (i, j) or drops (i, i).

        The regret ``r`` of a decision is how much the optimal total cost rises
        when it is forbidden (one more assignment per decision); with ``c`` its
        own cost the confidence is ``r / (r + c)``: near 1 when every other
        arrangement is much worse, near 0 when another fits as well.
        """
        out = np.empty(decisions.shape[0])
        for n, (i, j) in enumerate(decisions):  # host loop: one K-sized assignment per decision
            matrix = self.matrix.copy()
            matrix[i, j] = _FORBIDDEN
            rows, cols = linear_sum_assignment(matrix)
            regret = max(float(matrix[rows, cols].sum()) - chains.cost, 0.0)
            out[n] = regret / (regret + self.matrix[i, j]) if regret + self.matrix[i, j] > 0 else 1.0
        return np.clip(out, 0.0, 1.0)
