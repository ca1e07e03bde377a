"""Joint costs between all segment pairs, MST topology, full-frame tree joints.

Kirk et al. 2005, §3.2, as a host-side orchestrator over the JAX joint solver
(:mod:`jaxskel._jointcost`):

1. :func:`joint_costs` — for every pair of segments, the joint position per
   frame that keeps marker–joint distances constant, on a subsample of frames
   (``max_frames``) with the distance prior ``alpha``. All pairs are solved in
   one vmapped, jit-compiled call on padded arrays. Pairs that cannot carry a
   joint get an infinite cost and a reason: fewer than 3 markers in total,
   markers never seen together, or no relative motion (joint never exercised).
2. :func:`fit_topology` — minimum spanning tree over the costs, rooted at the
   tree's centre (or the user's root); edges parent -> child.
3. The tree's joints are re-solved on *all* frames, warm-started from the first
   pass, with ``alpha_tree``: 0 (the paper) for well-determined joints, and the
   prior kept for joints the first pass found poorly determined (a hinge's
   centre slides along its axis without it) when ``alpha_tree="auto"``.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import ConvergenceWarning, DegenerateMotionError, InputError
from ._jointcost import solve_joints
from ._jointcost_init import algebraic_start_batched
from ._padding import bucket_size
from ._segment import Segmentation
from ._tree import mst_edges, root_tree
from ._trial import Trial

__all__ = ["PairCosts", "Topology", "joint_costs", "fit_topology", "pair_arrays"]

#: Below this many frames with >= 3 of a pair's markers present, a pair is infeasible.
MIN_PAIR_FRAMES = 10
#: Segment pairs solved per vmapped call in the all-pairs pass.
PAIR_CHUNK = 64


def pair_arrays(
    x: np.ndarray,
    mask: np.ndarray,
    marker_segment: np.ndarray,
    pairs: np.ndarray,
    frames: np.ndarray,
    k_pad: int,
    f_pad: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Stack each pair's markers: ``(P, f_pad, k_pad, 3)`` positions and masks.

    Padding slots (extra markers, extra frames) are absent in the mask.
    """
    p_count = len(pairs)
    xs = np.zeros((p_count, f_pad, k_pad, 3))
    ms = np.zeros((p_count, f_pad, k_pad), dtype=bool)
    xf, mf = x[frames], mask[frames]
    for p, (a, b) in enumerate(pairs):  # host-side gather, P ~ S^2/2 small arrays
        idx = np.flatnonzero((marker_segment == a) | (marker_segment == b))
        xs[p, : len(frames), : len(idx)] = xf[:, idx]
        ms[p, : len(frames), : len(idx)] = mf[:, idx]
    return xs, ms


@dataclasses.dataclass(frozen=True)
class PairCosts:
    """Result of the all-pairs pass.

    ``cost`` is symmetric (S, S), the MST weight, ``inf`` for infeasible pairs
    (see ``reasons``) and on the diagonal: Kirk's Q (``weight="objective"``, the
    default) or only its variance part (``weight="variance"``). ``objective`` is
    always Q. Measured on real recordings, the variance alone favours pairs with a
    single-marker segment (the joint sits on that marker at no cost), so the
    paper's Q is the default. Solver diagnostics are per pair (S, S):
    ``steps``, ``result`` (optimistix result code, 0 = success), ``uncertainty``
    (metres, how far the joint can slide at no cost; large = poorly exercised).
    """

    cost: np.ndarray
    objective: np.ndarray
    reasons: dict[tuple[int, int], str]
    steps: np.ndarray
    result: np.ndarray
    uncertainty: np.ndarray
    undetermined: np.ndarray
    frames: np.ndarray
    alpha: float
    positions: dict[tuple[int, int], np.ndarray]
    radii: dict[tuple[int, int], np.ndarray]


@dataclasses.dataclass(frozen=True)
class Topology:
    """The skeleton's tree and its joints on every frame.

    Attributes
    ----------
    edges
        (J, 2) int (parent, child) segment indices; parents precede children.
    root
        Root segment (of the first component when the graph is a forest).
    roots
        One root per connected component (a forest arises only when infeasible
        pairs disconnect the cost graph).
    joint_positions
        (F, J, 3) joint centre per frame, row j <-> edge j; NaN where fewer than
        3 of the joint's markers were present.
    joint_cost
        (J,) cost of each tree joint on all frames (Kirk's Q).
    radii
        list of (K_j,) constant marker–joint distances per joint.
    uncertainty
        (J,) metres the joint can slide along its weakest direction.
    undetermined
        (J,) directions the data leave free (0 determined, 1 hinge axis, 3 no motion).
    alpha
        (J,) distance prior each joint was solved with.
    steps, result, converged
        (J,) solver diagnostics of the full-frame pass.
    pair_costs
        The all-pairs pass.
    """

    edges: np.ndarray
    root: int
    roots: tuple[int, ...]
    joint_positions: np.ndarray
    joint_cost: np.ndarray
    radii: tuple[np.ndarray, ...]
    uncertainty: np.ndarray
    undetermined: np.ndarray
    alpha: np.ndarray
    steps: np.ndarray
    result: np.ndarray
    converged: np.ndarray
    pair_costs: PairCosts

    @property
    def n_joints(self) -> int:
        return int(len(self.edges))


def _check_segmentation(trial: Trial, seg: Segmentation) -> np.ndarray:
    if tuple(seg.labels) != tuple(trial.labels):
        raise InputError(
            "the segmentation was computed for different markers than this trial; "
            "run segment_markers on the same (cleaned) trial"
        )
    return np.asarray(seg.marker_segment)


def joint_costs(
    trial: Trial,
    segmentation: Segmentation,
    *,
    alpha: float = 1e-5,
    max_frames: int = 300,
    method: str = "lm",
    max_steps: int = 100,
    exercised_ratio: float = 1.5,
    min_pair_markers: int = 4,
    weight: str = "objective",
) -> PairCosts:
    """Approximate joint cost for every pair of segments (the topology pass).

    ``max_frames`` evenly spaced frames are used (the paper subsamples
    drastically here; the exact solve is for tree joints only). A pair is
    infeasible when its segments together have fewer than ``min_pair_markers``
    markers (with three, any radii fit exactly: the variance term is zero and
    only the prior places the joint, so the cost says nothing), are seen
    together (>= 3 markers present) in fewer than ``MIN_PAIR_FRAMES`` frames, or
    never move relative to each other: the largest cross-segment distance std-dev
    is below ``exercised_ratio`` times the noise floor of the segmentation.
    """
    seg = _check_segmentation(trial, segmentation)
    if weight not in ("objective", "variance"):
        raise InputError(f"weight must be 'objective' or 'variance', got {weight!r}")
    s = segmentation.n_segments
    if s < 2:
        raise DegenerateMotionError("only one segment: there is no joint to fit")
    n_frames = trial.n_frames
    stride = max(1, int(np.ceil(n_frames / max_frames)))
    frames = np.arange(0, n_frames, stride)
    x, mask = trial.to_arrays()
    sizes = np.bincount(seg[seg >= 0], minlength=s)
    noise = float(np.nanmedian(segmentation.within_std())) if (sizes > 1).any() else 0.0

    reasons: dict[tuple[int, int], str] = {}
    candidates = []
    for a in range(s):
        for b in range(a + 1, s):
            ia, ib = np.flatnonzero(seg == a), np.flatnonzero(seg == b)
            if len(ia) + len(ib) < min_pair_markers:
                reasons[(a, b)] = (
                    f"segments {a} and {b} have {len(ia) + len(ib)} markers in total; a joint needs >= "
                    f"{min_pair_markers} (with 3, any marker-joint distances fit exactly and only the prior "
                    "places the joint)"
                )
                continue
            both = mask[:, np.concatenate([ia, ib])]
            usable = (both.sum(1) >= min(3, min_pair_markers)) & both[:, : len(ia)].any(1) & both[:, len(ia) :].any(1)
            if usable.sum() < MIN_PAIR_FRAMES:
                reasons[(a, b)] = f"segments {a} and {b} are seen together in only {int(usable.sum())} frames"
                continue
            cross = segmentation.distance_std[np.ix_(ia, ib)]
            if noise > 0 and np.isfinite(cross).any() and np.nanmax(cross) < exercised_ratio * noise:
                reasons[(a, b)] = (
                    f"segments {a} and {b} never move relative to each other (largest distance std "
                    f"{np.nanmax(cross) * 1000:.1f} mm vs noise {noise * 1000:.1f} mm): the joint is not exercised"
                )
                continue
            candidates.append((a, b))

    cost = np.full((s, s), np.inf)
    objective = np.full((s, s), np.inf)
    steps = np.zeros((s, s), dtype=int)
    result = np.zeros((s, s), dtype=int)
    unc = np.full((s, s), np.inf)
    undetermined = np.full((s, s), 3, dtype=int)
    positions: dict[tuple[int, int], np.ndarray] = {}
    radii: dict[tuple[int, int], np.ndarray] = {}
    if candidates:
        pairs = np.asarray(candidates)
        kmax = max(int(sizes[a] + sizes[b]) for a, b in candidates)
        k_pad = bucket_size(kmax, minimum=4, steps_per_octave=1)
        f_pad = bucket_size(len(frames))
        xs, ms = pair_arrays(x, mask, seg, pairs, frames, k_pad, f_pad)
        # The closed-form start: the objective is non-convex, the centroid is a poor start.
        c0, r0 = algebraic_start_batched(jnp.asarray(xs), jnp.asarray(ms))
        c0, r0 = np.asarray(c0), np.asarray(r0)
        # Solve in fixed-size chunks of pairs (padded with empty pairs): one compiled
        # shape for any segment count, and XLA's CPU runtime was measured to hang for
        # good on a single vmapped solve over >= ~128 pairs (92 were fine).
        chunks = []
        for start in range(0, len(pairs), PAIR_CHUNK):
            stop = min(start + PAIR_CHUNK, len(pairs))

            def chunk(arr: np.ndarray) -> jnp.ndarray:
                part = arr[start:stop]
                pad = np.zeros((PAIR_CHUNK - len(part),) + part.shape[1:], part.dtype)
                return jnp.asarray(np.concatenate([part, pad]))

            out = solve_joints(
                chunk(xs), chunk(ms), alpha=alpha, method=method, max_steps=max_steps,
                c0=chunk(c0), r0=chunk(r0),
            )
            chunks.append(jax.tree_util.tree_map(lambda leaf, n=stop - start: np.asarray(leaf)[:n], out))
        sol = jax.tree_util.tree_map(lambda *leaves: np.concatenate(leaves), *chunks)
        for p, (a, b) in enumerate(pairs):
            k = int(sizes[a] + sizes[b])
            pair_variance = float(sol.variance[p])
            for u, v in ((a, b), (b, a)):
                cost[u, v] = pair_variance if weight == "variance" else float(sol.cost[p])
                objective[u, v] = float(sol.cost[p])
                steps[u, v] = int(sol.steps[p])
                result[u, v] = int(sol.result[p])
                unc[u, v] = float(sol.uncertainty[p])
                undetermined[u, v] = int(sol.undetermined_dims[p])
            positions[(a, b)] = np.asarray(sol.positions[p, : len(frames)])
            radii[(a, b)] = np.asarray(sol.radii[p, :k])
    return PairCosts(
        cost=cost,
        objective=objective,
        reasons=reasons,
        steps=steps,
        result=result,
        uncertainty=unc,
        undetermined=undetermined,
        frames=frames,
        alpha=alpha,
        positions=positions,
        radii=radii,
    )


def fit_topology(
    trial: Trial,
    segmentation: Segmentation,
    pair_costs: PairCosts | None = None,
    *,
    root: int | str | None = None,
    alpha: float = 1e-5,
    alpha_tree: float | str = "auto",
    method: str = "lm",
    max_steps: int = 200,
    topology_frames: int = 300,
) -> Topology:
    """MST topology and the tree's joints solved on every frame.

    Parameters
    ----------
    root
        Root segment index, or a marker label whose segment becomes the root.
        Default: the tree's centre.
    alpha_tree
        Distance prior of the full-frame pass: a number, or ``"auto"``: 0 (the
        paper) for joints the first pass found fully determined, ``alpha`` for
        joints with an undetermined direction (a hinge's centre slides along its
        axis; the prior then places it nearest the markers, as the paper notes).
    """
    seg = _check_segmentation(trial, segmentation)
    s = segmentation.n_segments
    if pair_costs is None:
        pair_costs = joint_costs(
            trial, segmentation, alpha=alpha, max_frames=topology_frames, method=method
        )
    if isinstance(root, str):
        root = int(seg[trial.marker_index(root)[0]])
    if root is not None and not 0 <= int(root) < s:
        raise InputError(f"root segment {root} out of range for {s} segments")
    sizes = np.bincount(seg[seg >= 0], minlength=s)
    undirected = mst_edges(pair_costs.cost)
    edges, roots = root_tree(s, undirected, None if root is None else int(root), weight=sizes)
    if len(roots) > 1:
        warnings.warn(
            f"the joint-cost graph is disconnected ({len(roots)} components): some segment pairs "
            "are infeasible (see topology.pair_costs.reasons); the skeleton is a forest",
            ConvergenceWarning,
            stacklevel=2,
        )
    j = len(edges)
    n_frames = trial.n_frames
    x, mask = trial.to_arrays()
    if j == 0:
        return Topology(
            edges=edges, root=roots[0], roots=tuple(roots),
            joint_positions=np.zeros((n_frames, 0, 3)), joint_cost=np.zeros(0), radii=(),
            uncertainty=np.zeros(0), undetermined=np.zeros(0, int), alpha=np.zeros(0), steps=np.zeros(0, int),
            result=np.zeros(0, int), converged=np.zeros(0, bool), pair_costs=pair_costs,
        )

    key = [tuple(sorted((int(p), int(c)))) for p, c in edges]
    undetermined1 = np.array([pair_costs.undetermined[a, b] for a, b in key])
    if alpha_tree == "auto":
        alphas = np.where(undetermined1 > 0, alpha, 0.0)
    else:
        alphas = np.full(j, float(alpha_tree))
    ks = np.array([int(sizes[a] + sizes[b]) for a, b in key])
    k_pad = bucket_size(int(ks.max()), minimum=4, steps_per_octave=1)
    f_pad = bucket_size(n_frames)
    frames = np.arange(n_frames)
    xs, ms = pair_arrays(x, mask, seg, np.asarray(key), frames, k_pad, f_pad)
    # Warm start: first-pass joints interpolated in time, first-pass radii.
    t1 = pair_costs.frames
    c0 = np.zeros((j, f_pad, 3))
    r0 = np.zeros((j, k_pad))
    for i, kk in enumerate(key):
        p1 = pair_costs.positions[kk]
        for d in range(3):
            c0[i, :n_frames, d] = np.interp(frames, t1, p1[:, d])
        r0[i, : ks[i]] = pair_costs.radii[kk]
    # Pad the joint count to a bucket (masked, empty joints) so compiled shapes are reused.
    j_pad = bucket_size(j, minimum=4, steps_per_octave=1)

    def padded(arr: np.ndarray) -> jnp.ndarray:
        return jnp.asarray(np.concatenate([arr, np.zeros((j_pad - j,) + arr.shape[1:], arr.dtype)]))

    sol = solve_joints(
        padded(xs), padded(ms), alpha=padded(alphas), method=method, max_steps=max_steps,
        c0=padded(c0), r0=padded(r0),
    )
    sol = jax.tree_util.tree_map(lambda leaf: np.asarray(leaf)[:j], sol)
    valid = np.asarray(sol.valid_frames)[:, :n_frames]
    pos = np.asarray(sol.positions)[:, :n_frames]
    joint_positions = np.where(valid[..., None], pos, np.nan).transpose(1, 0, 2)
    converged = np.asarray(sol.converged)
    if not converged.all():
        warnings.warn(
            f"{int((~converged).sum())} of {j} tree joints did not converge in {max_steps} steps; "
            "see topology.steps / topology.result",
            ConvergenceWarning,
            stacklevel=2,
        )
    return Topology(
        edges=edges,
        root=roots[0],
        roots=tuple(roots),
        joint_positions=joint_positions,
        joint_cost=np.asarray(sol.cost),
        radii=tuple(np.asarray(sol.radii[i, : ks[i]]) for i in range(j)),
        uncertainty=np.asarray(sol.uncertainty),
        undetermined=np.asarray(sol.undetermined_dims),
        alpha=alphas,
        steps=np.asarray(sol.steps),
        result=np.asarray(sol.result),
        converged=converged,
        pair_costs=pair_costs,
    )
