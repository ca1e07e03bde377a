"""Joint costs between all segment pairs, MST topology, full-frame tree joints.

Kirk et al. 2005, §3.2, as a host-side orchestrator over the JAX joint solver
(:mod:`jaxskel.joints._cost`):

1. :func:`joint_costs` — for every pair of segments, the joint position per
   frame that keeps marker–joint distances constant, on a subsample of frames
   (``max_frames``) with the distance prior ``alpha``. All pairs are solved in
   one vmapped, jit-compiled call on padded arrays, each from the algebraic start,
   or, for pairs that never show five markers, the consistency start
   (:mod:`jaxskel.joints._cost_init`). Pairs that cannot carry a joint get an
   infinite cost and a reason: fewer than 4 markers in total, markers never seen
   together, or no relative motion (joint never exercised). :func:`untested_joints`
   names tree attachments that a pair with too few markers could not check.
2. :func:`fit_topology` — minimum spanning tree over the costs, one-marker
   segments hung as leaves from their most rigid segment (:mod:`jaxskel.joints._attachments`);
   between segments of three or more markers its joints are checked as points fixed
   in both segments' poses, edges to segments of one or two markers by those markers
   about a centre fixed in the other's pose, and one the poses reject is exchanged
   (:mod:`jaxskel.joints._pose_check`); rooted at the tree's centre (or the user's root);
   edges parent -> child.
3. The tree's joints are re-solved on *all* frames, warm-started from the first
   pass, with ``alpha_tree``: 0 (the paper) for well-determined joints, and the
   prior kept for joints the first pass found poorly determined (a hinge's
   centre slides along its axis without it) when ``alpha_tree="auto"``, and
   stopping tolerances (``TREE_RTOL``, ``TREE_ATOL``) that end the crawl along hinge
   axes without moving the determined joints.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConvergenceWarning, DegenerateMotionError, InputError
from .._math.padding import bucket_size
from .._runtime import program_cache as _program_cache
from .._runtime.backend import uses_cpu
from .._runtime.precision import float64_scope
from ..io import Trial
from ..segment import Segmentation
from ._attachments import Attachment, attachment_tree
from ._cost import _settings, _solve_batch
from ._cost_init import algebraic_start, consistency_start_batched
from ._near_ties import cost_variance, residual_dof
from ._pose_check import (
    PoseExchange,
    fixed_centre_errors,
    misfit_from_errors,
    pose_checked_edges,
    segment_poses,
    sphere_misfit,
)
from ._tree import root_tree, tree_path

__all__ = [
    "PairCosts", "Topology", "UntestedJoint", "joint_costs", "fit_topology", "pair_arrays", "solve_chunked",
    "untested_joints",
]

#: Below this many frames with >= 3 of a pair's markers present, a pair is infeasible.
MIN_PAIR_FRAMES = 10
#: MST weights of the all-pairs pass (see :class:`PairCosts`).
PAIR_WEIGHTS = ("normalized", "objective", "variance")
#: Segment pairs solved per vmapped call in the all-pairs pass (accelerators; on CPU
#: ``PAIR_CHUNK_CPU``: a vmapped while loop runs until its slowest pair stops and every
#: step costs as much for a finished pair as for a running one, while one pair's frames
#: already fill the SIMD lanes of a CPU; so on a CPU each pair is its own call and pays
#: only its own steps).
PAIR_CHUNK = 64
PAIR_CHUNK_CPU = 1
#: Stopping tolerances of the full-frame (tree) pass in float64: a step that lowers the
#: cost by at most ``TREE_RTOL`` relative (and whose model predicts no more), or moves
#: nothing by more than ``TREE_ATOL`` metres, ends the solve. The solver's float64
#: defaults (1e-10, 1 nm) serve the all-pairs costs that the MST compares; here they only
#: slide hinge centres along their axes, a direction the rigid stage places by itself
#: (:mod:`jaxskel.skeleton._hinge_centres`). 1e-7 is far below the sampling noise of the cost, a
#: variance over F x K >= 10^4 samples (relative std ~sqrt(2 / (F K)) >= 10^-3), and 1 um
#: far below marker noise; the solve ends in far fewer steps with the same joints and
#: bones (measured: docs/bench/evidence_from_docstrings.md).
#: (float32 solves keep the solver's defaults, 1e-5 and 1 um, looser already.)
TREE_RTOL, TREE_ATOL = 1e-7, 1e-6


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
    (see ``reasons``) and on the diagonal. ``objective`` is always Kirk's
    Q = V + alpha D (V: mean over markers of the marker-joint distance variance, D:
    mean distance). ``weight`` chooses ``cost``:

    * ``"normalized"`` (default): Q / f, where f = sum_t (K_t - 3) / sum_t K_t is
      the fraction of residual degrees of freedom left once a joint position (3
      numbers) is fitted to the K_t markers present in frame t. Under the joint
      hypothesis with marker noise sigma, E[V] = f sigma^2, so V / f estimates sigma^2
      for every pair alike; raw Q does not (a 4-marker pair keeps a quarter of its
      residual, an 8-marker pair 5/8), and so favours joints between sparsely marked
      segments whatever their motion. The prior is divided by f too: where few
      redundant distances constrain the joint, a false joint hides far away at a low
      variance, and the prior must weigh more. (Measured on real recordings:
      docs/bench/evidence_from_docstrings.md.)
    * ``"objective"``: Q itself (the paper).
    * ``"variance"``: V alone (favours single-marker segments: the joint sits on
      that marker at no cost).

    ``dof_fraction`` holds f (S, S). ``too_few_markers`` (S, S) marks the pairs whose
    two segments carry fewer markers than a joint needs (infeasible whatever the
    motion; see :func:`untested_joints`). Solver diagnostics are per pair (S, S):
    ``steps``, ``result`` (optimistix result code, 0 = success), ``uncertainty``
    (metres, how far the joint can slide at no cost; large = poorly exercised).
    """

    cost: np.ndarray
    objective: np.ndarray
    dof_fraction: np.ndarray
    weight: str
    reasons: dict[tuple[int, int], str]
    steps: np.ndarray
    result: np.ndarray
    uncertainty: np.ndarray
    undetermined: np.ndarray
    frames: np.ndarray
    alpha: float
    positions: dict[tuple[int, int], np.ndarray]
    radii: dict[tuple[int, int], np.ndarray]
    too_few_markers: np.ndarray | None = None


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
    fixed_misfit
        (S, S) fixed-centre misfit of every pair of posed segments (m^2, ``inf`` where
        either has fewer than three markers); see :mod:`jaxskel.joints._pose_check`.
    pose_exchanges
        MST edges the pose check replaced (:class:`jaxskel.joints.PoseExchange`).
    attachments
        One-marker segments hung as leaves from their most rigid segment
        (:class:`jaxskel.joints.Attachment`, :mod:`jaxskel.joints._attachments`).
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
    fixed_misfit: np.ndarray | None = None
    pose_exchanges: tuple[PoseExchange, ...] = ()
    attachments: tuple[Attachment, ...] = ()

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


# ----------------------------------------------------------------- chunked batched solve
@functools.partial(jax.jit, static_argnames=("settings", "start"))
def _chunk_solve(xs, ms, alpha, c0, r0, given, controls, *, settings, start):
    """One fixed-shape chunk: (optionally) the algebraic start for the pairs not
    ``given`` a start, then the vmapped solve."""
    if start:
        ca, ra = jax.vmap(algebraic_start)(xs, ms)
        c0 = jnp.where(given[:, None, None], c0, ca)
        r0 = jnp.where(given[:, None], r0, ra)
    sol = _solve_batch(xs, ms, alpha, c0, r0, True, True, controls, settings=settings)
    return {f.name: getattr(sol, f.name) for f in dataclasses.fields(sol)}  # a dict: exportable


def solve_chunked(
    xs: np.ndarray,
    ms: np.ndarray,
    alpha: np.ndarray,
    *,
    method: str,
    max_steps: int,
    chunk: int,
    c0: np.ndarray | None = None,
    r0: np.ndarray | None = None,
    given: np.ndarray | None = None,
    devices: Sequence[Any] | None = None,
    in_flight: int = 2,
    rtol: float | None = None,
    atol: float | None = None,
) -> dict[str, np.ndarray]:
    """Solve P padded pairs ``(P, F, K, 3)`` in chunks of ``chunk`` pairs; numpy out.

    Every chunk has the same shape (the last is padded with empty pairs), so one
    compiled solver serves any number of pairs, from one trial or from many trials
    concatenated (:func:`jaxskel.fit_batch`). Each pair's solve is independent of the
    other pairs in its chunk (a vmapped while loop freezes finished pairs), so the
    result of a pair does not depend on how pairs are grouped. ``c0``/``r0`` ``None``
    takes the algebraic start, computed inside the chunk; with ``given`` (P,) bool, the
    rows of ``c0``/``r0`` where it is True are used and the others take the algebraic
    start. Chunks go round-robin to
    ``devices`` (default: the default device) and are dispatched asynchronously, at
    most ``in_flight`` per device at a time, so several accelerators work at once. On
    CPU devices one chunk runs at a time: concurrent XLA:CPU executions of batched LAPACK
    kernels can deadlock its intra-op pool (``ParallelBatchMap``, :mod:`jaxskel._math.linalg`;
    the observed hang: docs/bench/evidence_from_docstrings.md); the solver calls none now,
    and on a CPU a second execution has no spare core anyway.

    ``rtol``/``atol``: the solver's stopping tolerances (``None``: its defaults for the
    dtype, :func:`jaxskel.joints.solve_joints`). They are traced, so changing them does not
    recompile the LM solver.

    Returns the :class:`jaxskel.joints.JointSolution` fields as numpy arrays with P rows.
    """
    n = len(xs)
    settings, controls = _settings(method, max_steps, rtol, atol, xs.dtype)
    start = c0 is None or given is not None
    if c0 is None:
        c0 = np.zeros(xs.shape[:2] + (3,), xs.dtype)
        r0 = np.zeros(xs.shape[:1] + xs.shape[2:3], xs.dtype)
    given = np.zeros(n, bool) if given is None else np.asarray(given, bool)
    on_cpu = uses_cpu(devices)
    devices = list(devices) if devices else [None]
    if on_cpu:
        # XLA:CPU: one execution at a time (see the docstring).
        in_flight = 1
        devices_in_flight = 1
    else:
        devices_in_flight = len(devices)
    alpha = np.broadcast_to(np.asarray(alpha, xs.dtype), (n,))

    def part(arr: np.ndarray, lo: int, hi: int) -> np.ndarray:
        piece = arr[lo:hi]
        if len(piece) == chunk:
            return piece
        return np.concatenate([piece, np.zeros((chunk - len(piece),) + piece.shape[1:], piece.dtype)])

    pending: list[tuple[int, Any]] = []
    done: list[tuple[int, dict[str, np.ndarray]]] = []

    def collect() -> None:
        lo, out = pending.pop(0)
        take = min(chunk, n - lo)
        done.append((lo, {k: np.asarray(v)[:take] for k, v in out.items()}))

    for i, lo in enumerate(range(0, n, chunk)):
        hi = min(lo + chunk, n)
        args = [part(a, lo, hi) for a in (xs, ms, alpha, c0, r0, given)]
        device = devices[i % len(devices)]
        if device is not None:
            args = [jax.device_put(a, device) for a in args]
            ctrl = jax.device_put(controls, device)
        else:
            ctrl = controls
        if device is None:  # saved programs are for the default device
            out = _program_cache.call(_chunk_solve, *args, ctrl, settings=settings, start=start)
        else:
            out = _chunk_solve(*args, ctrl, settings=settings, start=start)
        pending.append((lo, out))
        if len(pending) >= in_flight * devices_in_flight:
            collect()
    while pending:
        collect()
    done.sort(key=lambda item: item[0])
    if not done:
        return {}
    return {k: np.concatenate([d[k] for _, d in done]) for k in done[0][1]}


# --------------------------------------------------------------------- all-pairs pass
@dataclasses.dataclass(frozen=True)
class AllPairsProblem:
    """Host-side all-pairs problem of one trial: feasibility and padded pair arrays.

    ``xs`` (P, f_pad, k_pad, 3) and ``ms`` (P, f_pad, k_pad) hold the P candidate
    pairs (``pairs`` (P, 2)); infeasible pairs are only in ``reasons``.
    """

    n_segments: int
    frames: np.ndarray
    sizes: np.ndarray
    reasons: dict[tuple[int, int], str]
    pairs: np.ndarray
    xs: np.ndarray
    ms: np.ndarray
    alpha: float
    method: str
    max_steps: int
    weight: str
    min_pair_markers: int = 4

    @property
    def shape_key(self) -> tuple[int, int]:
        """(f_pad, k_pad): problems with the same key can share chunks."""
        return int(self.xs.shape[1]), int(self.xs.shape[2])


def all_pairs_problem(
    trial: Trial,
    segmentation: Segmentation,
    *,
    alpha: float = 1e-5,
    max_frames: int = 300,
    method: str = "lm",
    max_steps: int = 100,
    exercised_ratio: float = 1.5,
    min_pair_markers: int = 4,
    weight: str = "normalized",
) -> AllPairsProblem:
    """Feasibility tests and padded arrays of :func:`joint_costs` (no solve)."""
    seg = _check_segmentation(trial, segmentation)
    if weight not in PAIR_WEIGHTS:
        raise InputError(f"weight must be one of {PAIR_WEIGHTS}, got {weight!r}")
    s = segmentation.n_segments
    if s < 2:
        if segmentation.count_rule == "rigid":
            raise DegenerateMotionError(
                f"all {trial.n_markers} markers move as one rigid body (largest distance std "
                f"{np.nanmax(segmentation.distance_std) * 1000:.1f} mm, under the rigidity limit "
                f"{segmentation.rigid_limit * 1000:.1f} mm): the recording exercises no joint. Fit a trial in "
                "which the joints move (e.g. a range-of-motion trial), or give n_segments"
            )
        raise DegenerateMotionError("only one segment: there is no joint to fit")
    x, mask = trial.to_arrays()
    # evenly spaced among the frames that show any marker (a still trial fitted with a moving
    # one is blanked out of the joint stages: jaxskel.pipeline.moving_frames)
    shown = np.flatnonzero(mask.any(axis=1))
    stride = max(1, int(np.ceil(shown.size / max_frames)))
    frames = shown[::stride]
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

    pairs = np.asarray(candidates, dtype=int).reshape(-1, 2)
    kmax = max((int(sizes[a] + sizes[b]) for a, b in candidates), default=4)
    k_pad = bucket_size(kmax, minimum=4, steps_per_octave=1)
    # a subsample of exactly max_frames frames (the usual case) keeps its count: one shape, no padding
    f_pad = len(frames) if len(frames) == max_frames else bucket_size(len(frames))
    xs, ms = pair_arrays(x, mask, seg, pairs, frames, k_pad, f_pad)
    return AllPairsProblem(
        n_segments=s, frames=frames, sizes=sizes, reasons=reasons, pairs=pairs, xs=xs, ms=ms,
        alpha=float(alpha), method=method, max_steps=int(max_steps), weight=weight,
        min_pair_markers=int(min_pair_markers),
    )


def pair_costs_from(problem: AllPairsProblem, sol: dict[str, np.ndarray]) -> PairCosts:
    """Assemble :class:`PairCosts` from the solutions of ``problem.pairs`` (rows in order)."""
    s = problem.n_segments
    cost = np.full((s, s), np.inf)
    objective = np.full((s, s), np.inf)
    steps = np.zeros((s, s), dtype=int)
    result = np.zeros((s, s), dtype=int)
    unc = np.full((s, s), np.inf)
    undetermined = np.full((s, s), 3, dtype=int)
    positions: dict[tuple[int, int], np.ndarray] = {}
    radii: dict[tuple[int, int], np.ndarray] = {}
    dof = np.zeros((s, s))
    reasons = dict(problem.reasons)
    n_frames = len(problem.frames)
    # Markers present per frame and pair; frames with < 3 markers carry no residual.
    k_t = problem.ms.sum(axis=2)
    k_t = np.where(k_t >= 3, k_t, 0)
    fraction = (np.maximum(k_t - 3, 0).sum(axis=1) / np.maximum(k_t.sum(axis=1), 1)).tolist()
    for p, (a, b) in enumerate(problem.pairs.tolist()):
        k = int(problem.sizes[a] + problem.sizes[b])
        variance, objective_p = float(sol["variance"][p]), float(sol["cost"][p])
        weight = {
            "objective": objective_p,
            "variance": variance,
            # f = 0 (never more than 3 markers at once): no residual to judge by.
            "normalized": objective_p / fraction[p] if fraction[p] > 0 else np.inf,
        }[problem.weight]
        if not np.isfinite(weight):
            reasons[(a, b)] = (
                f"segments {a} and {b} never show more than 3 markers in one frame: any marker-joint "
                "distances fit exactly, so the cost cannot judge the joint"
            )
        for u, v in ((a, b), (b, a)):
            cost[u, v] = weight
            objective[u, v] = objective_p
            dof[u, v] = fraction[p]
            steps[u, v] = int(sol["steps"][p])
            result[u, v] = int(sol["result"][p])
            unc[u, v] = float(sol["uncertainty"][p])
            undetermined[u, v] = int(sol["undetermined_dims"][p])
        positions[(a, b)] = np.asarray(sol["positions"][p, :n_frames])
        radii[(a, b)] = np.asarray(sol["radii"][p, :k])
    sizes = np.asarray(problem.sizes)
    too_few = (sizes[:, None] + sizes[None, :]) < problem.min_pair_markers
    np.fill_diagonal(too_few, False)
    return PairCosts(
        too_few_markers=too_few,
        cost=cost,
        objective=objective,
        dof_fraction=dof,
        weight=problem.weight,
        reasons=reasons,
        steps=steps,
        result=result,
        uncertainty=unc,
        undetermined=undetermined,
        frames=problem.frames,
        alpha=problem.alpha,
        positions=positions,
        radii=radii,
    )


@float64_scope
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
    weight: str = "normalized",
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

    The candidate pairs are solved in fixed chunks of ``PAIR_CHUNK`` pairs
    (``PAIR_CHUNK_CPU`` on CPU; :func:`solve_chunked`), each starting from the
    closed-form algebraic fit.
    """
    problem = all_pairs_problem(
        trial, segmentation, alpha=alpha, max_frames=max_frames, method=method, max_steps=max_steps,
        exercised_ratio=exercised_ratio, min_pair_markers=min_pair_markers, weight=weight,
    )
    sol = solve_pairs([problem])[0]
    return pair_costs_from(problem, sol)


def _consistency_starts(xs: np.ndarray, ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starts of the pairs that never show five markers in a frame, where the algebraic
    start has nothing to solve (:func:`jaxskel.joints._cost_init.consistency_start`).

    Returns ``c0`` (P, F, 3), ``r0`` (P, K) and ``given`` (P,): True where a
    consistency start was computed (the other rows take the algebraic start).
    """
    c0 = np.zeros(xs.shape[:2] + (3,), xs.dtype)
    r0 = np.zeros(xs.shape[:1] + xs.shape[2:3], xs.dtype)
    most = ms.sum(axis=2).max(axis=1)  # most markers any frame of the pair shows
    need = np.flatnonzero((most >= 4) & (most < 5))
    given = np.zeros(len(xs), bool)
    if need.size:
        # Pad the subset to a bucket size: one compiled start for any number of such pairs.
        rows = np.concatenate([need, np.full(bucket_size(need.size, minimum=4) - need.size, need[0])])
        starts = _program_cache.call(consistency_start_batched, xs[rows], ms[rows])
        c, r, ok = (np.asarray(v)[: need.size] for v in starts)
        c0[need], r0[need], given[need] = c, r, ok
    return c0, r0, given


def solve_pairs(
    problems: Sequence[AllPairsProblem], *, devices: Sequence[Any] | None = None
) -> list[dict[str, np.ndarray]]:
    """Solve the candidate pairs of several trials together.

    Problems with the same padded shape, method and step cap are concatenated and
    go through one chunked solve (pairs of different trials share chunks); the
    solutions are split back per problem.
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in problems]
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(problems):
        groups.setdefault((p.shape_key, p.method, p.max_steps, p.xs.dtype.str), []).append(i)
    for members in groups.values():
        xs = np.concatenate([problems[i].xs for i in members])
        ms = np.concatenate([problems[i].ms for i in members])
        alpha = np.concatenate([np.full(len(problems[i].pairs), problems[i].alpha) for i in members])
        first = problems[members[0]]
        c0, r0, given = _consistency_starts(xs, ms)
        sol = solve_chunked(
            xs, ms, alpha, method=first.method, max_steps=first.max_steps,
            chunk=PAIR_CHUNK_CPU if uses_cpu(devices) else PAIR_CHUNK, c0=c0, r0=r0, given=given, devices=devices,
        )
        lo = 0
        for i in members:
            hi = lo + len(problems[i].pairs)
            out[i] = {k: v[lo:hi] for k, v in sol.items()}
            lo = hi
    return out


# ------------------------------------------------------------------------- tree joints
@dataclasses.dataclass(frozen=True)
class TreeProblem:
    """Host-side full-frame problem of one trial's tree joints (J joints, all frames)."""

    edges: np.ndarray
    roots: tuple[int, ...]
    n_frames: int
    alphas: np.ndarray
    ks: np.ndarray
    xs: np.ndarray
    ms: np.ndarray
    c0: np.ndarray
    r0: np.ndarray
    first_steps: np.ndarray
    method: str
    max_steps: int
    pair_costs: PairCosts
    fixed_misfit: np.ndarray
    pose_exchanges: tuple[PoseExchange, ...]
    attachments: tuple[Attachment, ...] = ()

    @property
    def shape_key(self) -> tuple[int, int]:
        return int(self.xs.shape[1]), int(self.xs.shape[2])

    @property
    def tolerances(self) -> tuple[float | None, float | None]:
        """(rtol, atol) of the solve: ``TREE_RTOL``/``TREE_ATOL`` in float64, else the solver's."""
        return (TREE_RTOL, TREE_ATOL) if self.xs.dtype == np.float64 else (None, None)


def _centroid_start(x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start of a joint with no first-pass solution: the centroid of its markers present
    in each frame (held over frames with none), and the median distances to it."""
    n = m.sum(axis=1, keepdims=True)
    c = np.where(n > 0, (x * m[..., None]).sum(axis=1) / np.maximum(n, 1), np.nan)
    seen = np.flatnonzero(n[:, 0] > 0)
    if seen.size == 0:
        return np.zeros((len(x), 3)), np.zeros(x.shape[1])
    idx = np.arange(len(x))
    c = np.stack([np.interp(idx, seen, c[seen, d]) for d in range(3)], axis=1)
    d = np.where(m, np.linalg.norm(x - c[:, None], axis=-1), np.nan)
    with np.errstate(all="ignore"):
        r = np.nan_to_num(np.nanmedian(d, axis=0))
    return c, r


def _sphere_check_matrices(
    x: np.ndarray, mask: np.ndarray, seg: np.ndarray, s: int, frames: np.ndarray,
    poses: tuple[np.ndarray, np.ndarray, np.ndarray], attachments: Sequence[Attachment],
) -> tuple[np.ndarray, np.ndarray]:
    """The second pose check's misfits (:mod:`jaxskel.joints._pose_check`): the anchored sphere
    misfit of every pair, the better of its two directions, as rivals; judged are only the
    edges the fixed-centre check cannot judge (a segment of one or two markers). One-marker
    attachments are leaves by construction and take no part."""
    directed = sphere_misfit(x, mask, seg, s, frames, MIN_PAIR_FRAMES, poses=poses)
    sphere = np.minimum(directed, directed.T)
    hung = [a.segment for a in attachments]
    sphere[hung, :] = np.inf
    sphere[:, hung] = np.inf
    framed = poses[2].any(axis=0)
    judged = np.where(framed[:, None] & framed[None, :], np.inf, sphere)
    return sphere, judged


def tree_problem(
    trial: Trial,
    segmentation: Segmentation,
    pair_costs: PairCosts,
    *,
    root: int | str | None = None,
    alpha: float = 1e-5,
    alpha_tree: float | str = "auto",
    method: str = "lm",
    max_steps: int = 500,
    pose_check: bool = True,
) -> TreeProblem:
    """MST, pose check, rooting and the padded warm-started arrays of :func:`fit_topology` (no solve)."""
    seg = _check_segmentation(trial, segmentation)
    s = segmentation.n_segments
    if isinstance(root, str):
        root = int(seg[trial.marker_index(root)[0]])
    if root is not None and not 0 <= int(root) < s:
        raise InputError(f"root segment {root} out of range for {s} segments")
    sizes = np.bincount(seg[seg >= 0], minlength=s)
    undirected, attachments, _ = attachment_tree(
        pair_costs.cost, seg, segmentation.distance_std, pair_costs.too_few_markers
    )
    if not len(undirected):
        shown = "; ".join(list(pair_costs.reasons.values())[:3])
        more = len(pair_costs.reasons) - 3
        raise DegenerateMotionError(
            f"no pair of the {s} segments can be jointed: {shown}"
            + (f" (and {more} more pairs)" if more > 0 else "")
            + ". Fit a trial in which the joints move, or check the segmentation (n_segments)"
        )
    x, mask = trial.to_arrays()
    poses = segment_poses(x, mask, seg, s, pair_costs.frames)
    errors = fixed_centre_errors(x, mask, seg, s, pair_costs.frames, poses=poses)
    misfit = misfit_from_errors(*errors, MIN_PAIR_FRAMES)
    exchanges: tuple[PoseExchange, ...] = ()
    if pose_check:
        undirected, exchanges = pose_checked_edges(undirected, misfit, pair_costs.cost)
        sphere, judged = _sphere_check_matrices(x, mask, seg, s, pair_costs.frames, poses, attachments)
        undirected, more = pose_checked_edges(undirected, sphere, pair_costs.cost, judged=judged, test="sphere")
        exchanges += more
        # a joint between posed segments against rivals with a segment of one or two markers,
        # which the fixed-centre check cannot pose: by the same sphere misfit
        posed_pair = np.isinf(judged) & np.isfinite(sphere)
        undirected, more = pose_checked_edges(undirected, np.where(posed_pair, np.inf, sphere), pair_costs.cost,
                                              judged=np.where(posed_pair, sphere, np.inf), test="sphere")
        exchanges += more
        # near ties: where the costs cannot tell a joint from a rival, the poses decide
        tie_noise = cost_variance(residual_dof(mask[pair_costs.frames], seg, s))
        undirected, more = pose_checked_edges(undirected, misfit, pair_costs.cost, factor=1.0,
                                              tie_noise=tie_noise, errors=errors, test="near_tie")
        exchanges += more
    edges, roots = root_tree(s, undirected, None if root is None else int(root), weight=sizes)
    if len(roots) > 1:
        warnings.warn(
            f"the joint-cost graph is disconnected ({len(roots)} components): some segment pairs "
            "are infeasible (see topology.pair_costs.reasons); the skeleton is a forest",
            ConvergenceWarning,
            stacklevel=4,  # fit_topology's caller (3 is float64_scope's wrapper)
        )
    j = len(edges)
    n_frames = trial.n_frames
    key = [tuple(sorted((int(p), int(c)))) for p, c in edges]
    # an attachment to a two-marker host has no first-pass solution: prior, centroid start
    unsolved = np.array([kk not in pair_costs.positions for kk in key], dtype=bool)
    undetermined1 = np.array([3 if u else pair_costs.undetermined[a, b] for (a, b), u in zip(key, unsolved)], dtype=int)
    if alpha_tree == "auto":
        alphas = np.where(undetermined1 > 0, alpha, 0.0)
    else:
        alphas = np.full(j, float(alpha_tree))
    alphas = np.where(unsolved & (alphas <= 0), alpha, alphas)  # only the prior places those
    ks = np.array([int(sizes[a] + sizes[b]) for a, b in key], dtype=int)
    k_pad = bucket_size(int(ks.max(initial=4)), minimum=4, steps_per_octave=1)
    # Four sizes per octave (<= 19 % padding, against 41 % with two): every padded
    # frame costs a full share of each of the hundreds of steps a hinge joint takes.
    f_pad = bucket_size(n_frames, steps_per_octave=4)
    frames = np.arange(n_frames)
    xs, ms = pair_arrays(x, mask, seg, np.asarray(key, dtype=int).reshape(-1, 2), frames, k_pad, f_pad)
    # Warm start: first-pass joints interpolated in time, first-pass radii.
    t1 = pair_costs.frames
    c0 = np.zeros((j, f_pad, 3))
    r0 = np.zeros((j, k_pad))
    for i, kk in enumerate(key):
        if unsolved[i]:
            c0[i, :n_frames], r0[i, : ks[i]] = _centroid_start(xs[i, :n_frames, : ks[i]], ms[i, :n_frames, : ks[i]])
            continue
        p1 = pair_costs.positions[kk]
        for d in range(3):
            c0[i, :n_frames, d] = np.interp(frames, t1, p1[:, d])
        r0[i, : ks[i]] = pair_costs.radii[kk]
    first_steps = np.array([pair_costs.steps[a, b] for a, b in key], dtype=int)
    return TreeProblem(
        edges=edges, roots=tuple(roots), n_frames=n_frames, alphas=alphas, ks=ks, xs=xs, ms=ms, c0=c0, r0=r0,
        first_steps=first_steps, method=method, max_steps=int(max_steps), pair_costs=pair_costs,
        fixed_misfit=misfit, pose_exchanges=exchanges, attachments=attachments,
    )


def solve_trees(
    problems: Sequence[TreeProblem], *, devices: Sequence[Any] | None = None, chunk: int | None = None
) -> list[dict[str, np.ndarray]]:
    """Solve the tree joints of several trials together (shared chunks per padded shape).

    Joints of the same padded shape are pooled, sorted by their first-pass step
    count and solved ``chunk`` joints per vmapped call. A vmapped while loop runs
    until its slowest joint has converged, and every step costs as much for a
    finished joint as for a running one, so a chunk costs its size times its
    slowest joint's steps. On a CPU, where one joint's frames already fill the
    cores, the default chunk is therefore 1 and each joint pays only its own steps
    (a hinge joint takes several times the steps of a ball joint; timings:
    docs/bench/evidence_from_docstrings.md). On accelerators, which need the
    width, it is the bucket of the largest tree, slow joints sorted together. A
    joint's solution does not depend on the chunking.
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in problems]
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(problems):
        if len(p.edges):
            groups.setdefault((p.shape_key, p.method, p.max_steps, p.xs.dtype.str), []).append(i)
    for members in groups.values():
        owner = np.concatenate([np.full(len(problems[i].edges), i) for i in members])
        row = np.concatenate([np.arange(len(problems[i].edges)) for i in members])
        widest = bucket_size(max(len(problems[i].edges) for i in members), minimum=4, steps_per_octave=1)
        size = chunk or (1 if uses_cpu(devices) else widest)
        steps = np.concatenate([problems[i].first_steps for i in members])
        # one joint per call: the order does not matter, and one trial's arrays go as they are
        order = np.argsort(-steps, kind="stable") if size > 1 else np.arange(steps.size)

        def pooled(name: str, members=members, order=order, size=size) -> np.ndarray:
            if len(members) == 1 and size == 1:
                return getattr(problems[members[0]], name)
            return np.concatenate([getattr(problems[i], name) for i in members])[order]

        first = problems[members[0]]
        rtol, atol = first.tolerances
        sol = solve_chunked(
            pooled("xs"), pooled("ms"), pooled("alphas"), method=first.method, max_steps=first.max_steps,
            chunk=size, c0=pooled("c0"), r0=pooled("r0"), devices=devices, rtol=rtol, atol=atol,
        )
        for i in members:
            sel = np.flatnonzero(owner[order] == i)
            sel = sel[np.argsort(row[order][sel])]
            out[i] = {k: v[sel] for k, v in sol.items()}
    return out


def topology_from(problem: TreeProblem, sol: dict[str, np.ndarray]) -> Topology:
    """Assemble :class:`Topology` from the tree joints' solutions (rows = edges)."""
    j = len(problem.edges)
    n_frames = problem.n_frames
    if j == 0:
        return Topology(
            edges=problem.edges, root=problem.roots[0], roots=problem.roots,
            joint_positions=np.zeros((n_frames, 0, 3)), joint_cost=np.zeros(0), radii=(),
            uncertainty=np.zeros(0), undetermined=np.zeros(0, int), alpha=np.zeros(0), steps=np.zeros(0, int),
            result=np.zeros(0, int), converged=np.zeros(0, bool), pair_costs=problem.pair_costs,
            fixed_misfit=problem.fixed_misfit, pose_exchanges=problem.pose_exchanges,
            attachments=problem.attachments,
        )
    valid = sol["valid_frames"][:, :n_frames]
    pos = sol["positions"][:, :n_frames]
    joint_positions = np.where(valid[..., None], pos, np.nan).transpose(1, 0, 2)
    converged = np.asarray(sol["converged"])
    if not converged.all():
        warnings.warn(
            f"{int((~converged).sum())} of {j} tree joints did not converge in {problem.max_steps} steps; "
            "see topology.steps / topology.result",
            ConvergenceWarning,
            stacklevel=4,  # fit_topology's caller (3 is float64_scope's wrapper)
        )
    return Topology(
        edges=problem.edges,
        root=problem.roots[0],
        roots=problem.roots,
        joint_positions=joint_positions,
        joint_cost=np.asarray(sol["cost"]),
        radii=tuple(np.asarray(sol["radii"][i, : problem.ks[i]]) for i in range(j)),
        uncertainty=np.asarray(sol["uncertainty"]),
        undetermined=np.asarray(sol["undetermined_dims"]),
        alpha=problem.alphas,
        steps=np.asarray(sol["steps"]),
        result=np.asarray(sol["result"]),
        converged=converged,
        pair_costs=problem.pair_costs,
        fixed_misfit=problem.fixed_misfit,
        pose_exchanges=problem.pose_exchanges,
        attachments=problem.attachments,
    )


class UntestedJoint(NamedTuple):
    """A sparsely marked segment jointed where the data cannot confirm it (:func:`untested_joints`).

    ``segment`` is jointed to ``jointed_to`` in the tree but moves more rigidly with
    ``untested`` (median distance std-dev between their markers, metres: ``std_untested``
    against ``std_jointed``), and the pair (``segment``, ``untested``) carries too few
    markers for a joint to be tested.
    """

    segment: int
    jointed_to: int
    untested: int
    std_untested: float
    std_jointed: float


def untested_joints(segmentation: Segmentation, topology: Topology) -> list[UntestedJoint]:
    """Tree attachments that the joint costs could not check against the likelier neighbour.

    A joint needs ``min_pair_markers`` (4) markers on its two segments: with three, any
    marker-joint distances fit exactly and the cost says nothing. So a segment with one
    marker can never be jointed to a two-marker neighbour (a lone hand marker next to a
    forearm with two), and the spanning tree attaches it wherever a joint *can* be
    tested, often one segment too far (the upper arm). The distance std-dev matrix of
    the segmentation still shows what moves together. For every such untestable pair
    ``(s, p)``, joining them would close a cycle with the tree path from ``s`` to ``p``;
    of the path's two end edges (``s``'s and ``p``'s attachments) the one whose segments
    move least together (largest median distance std-dev between their markers; the
    median, as a marker placed on a joint is rigid with both sides) is reported when the
    pair moves more rigidly together than it. Nothing is changed: the tree keeps the
    tested joint, and the caller is told which attachment to distrust.
    """
    if not isinstance(segmentation, Segmentation) or not isinstance(topology, Topology):
        raise InputError(
            "untested_joints(segmentation, topology) takes a jaxskel.segment.Segmentation and a jaxskel.joints.Topology "
            f"(got {type(segmentation).__name__}, {type(topology).__name__}); for a fit, call "
            "result.untested_joints()"
        )
    too_few = topology.pair_costs.too_few_markers
    if too_few is None or not too_few.any():
        return []
    seg = segmentation.marker_segment
    a = segmentation.distance_std
    n_seg = segmentation.n_segments

    def together(u: int, v: int) -> float:
        block = a[np.ix_(seg == u, seg == v)]
        return float(np.nanmedian(block)) if np.isfinite(block).any() else np.inf

    edges = np.asarray(topology.edges).reshape(-1, 2)

    found: list[UntestedJoint] = []
    for s, p in zip(*np.nonzero(np.triu(too_few))):
        route = tree_path(n_seg, edges, int(s), int(p))
        if len(route) < 3:  # adjacent in the tree, or not connected: nothing to replace
            continue
        ends = [(route[0], route[1], route[-1]), (route[-1], route[-2], route[0])]
        segment, jointed, untested = max(ends, key=lambda e: together(e[0], e[1]))
        std_pair, std_edge = together(int(s), int(p)), together(segment, jointed)
        if std_pair < std_edge:
            found.append(UntestedJoint(segment, jointed, untested, std_pair, std_edge))
    return found


@float64_scope
def fit_topology(
    trial: Trial,
    segmentation: Segmentation,
    pair_costs: PairCosts | None = None,
    *,
    root: int | str | None = None,
    alpha: float = 1e-5,
    alpha_tree: float | str = "auto",
    method: str = "lm",
    max_steps: int = 500,
    topology_frames: int = 300,
    pose_check: bool = True,
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
    pose_check
        Exchange tree joints the segments' poses reject (:mod:`jaxskel.joints._pose_check`;
        reported in ``pose_exchanges``): between segments of three or more markers by
        a centre fixed in both poses, then edges to segments of one or two markers by
        their markers about a centre fixed in the other's pose. ``False``: the minimum
        spanning tree of the joint costs as it is (the paper's, with one-marker
        segments as attachments, :mod:`jaxskel.joints._attachments`); the fixed-centre misfits
        are computed either way.

    One-marker segments hang as leaves from the segment they are most rigid with
    (``attachments``), never as hubs.
    """
    if pair_costs is None:
        pair_costs = joint_costs(
            trial, segmentation, alpha=alpha, max_frames=topology_frames, method=method
        )
    problem = tree_problem(
        trial, segmentation, pair_costs, root=root, alpha=alpha, alpha_tree=alpha_tree, method=method,
        max_steps=max_steps, pose_check=pose_check,
    )
    return topology_from(problem, solve_trees([problem])[0])
