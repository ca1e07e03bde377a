"""Movement filtering and movement-axis extraction on the joint sphere (Sar Dessai et al. 2006, §4.1-4.3).

Every function here works on ONE joint: its samples ``p_f`` (F, 3) are the unit
direction of the child limb in the parent joint frame, one per frame, plus a
``valid`` mask for padded frames. Callers vmap over joints. No NaN enters: padded
frames are masked.

Filtering (§4.1)
    The per-frame speed ``v_f = |p_f - p_{f-1}|`` is histogrammed in ``n_bins``
    uniform bins over ``[0, max v]``. Stationary phases give a peak at low speeds.
    Small bars are eliminated: with ``tol = min_prominence * (tallest bar)``, a peak
    counts only if its prominence (height above the higher of its two bases) is at
    least ``tol``, and bars within ``tol`` of the lowest bar between the low-speed
    peak and the next significant peak (or the end) are all "the valley". The
    threshold is the first of them, so on a flat stretch of slow movement the
    threshold stays just after the stationary peak. A first peak above
    ``low_speed_fraction`` of the speed range means the limb never rests: every
    sample is then a movement sample.

Axis extraction (§4.2). An axis plane is a plane through the joint centre ``o``
(the origin here); a main direction with centre ``c`` and direction ``d`` has the
axis ``a = (c - o) x d``.

* Direction joining (the paper's method): windowed stratification keeps a new
  representative whenever the trajectory has moved ``cell`` (chord length on the
  unit sphere) from the previous one, so noise on slow movement cannot fake
  directions; stationary samples end a run. Consecutive movement steps
  ``v = p_i - p_{i-1}`` whose axis planes ``v x c`` make an angle below ``delta``
  with the current group's plane ``d_j x c_j`` join it (``d_j``, ``c_j`` running
  means; ``v`` is sign-aligned with ``d_j`` so a back-and-forth swing stays one
  group); otherwise a new group starts. The ``max_groups`` largest groups are then
  merged agglomeratively (most similar pair first, plane normals averaged with
  their sample counts as weights) while the most similar pair is within
  ``delta``. The largest cluster is the first main direction, the largest one
  whose plane is at least 30 degrees from it the second; each axis is then the
  least-squares normal of the plane of its cluster's samples
  (:func:`circle_plane`), which also finds the axis when the limb is not
  orthogonal to it (samples on a small circle, where ``(c - o) x d`` is tilted),
  refitted once on all movement samples near that circle rather than on the
  stratified steps alone.
* PCA (baseline): one representative per occupied cell of a uniform grid (global
  stratification, side ``cell``), principal directions ``e_1, e_2`` of the
  representatives, axes ``a_k = c x e_k`` with ``c`` their centroid.
* EM (baseline): from the PCA planes, alternately assign each representative to
  the closest axis plane and refit every plane by least squares, until the
  assignment stops changing.

Rest position (§4.3): the point where the axis planes cut the joint sphere
(``+-(a_1 x a_2)`` for two axes, the projection of the centroid onto the plane for
one), nearest to the samples' centroid; the rest sample is the sample closest to it.

Axis signs are a convention (:func:`orient_axes`): the largest component of each
axis, in the parent joint frame, is positive, so the same joint gets the same
signs in every recording.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "speeds",
    "speed_threshold",
    "circle_plane",
    "circle_distance",
    "cell_keys",
    "join_directions",
    "pca_axes",
    "em_axes",
    "rest_target",
    "orient_axes",
]

_TINY = 1e-12
#: Largest ratio of the smallest to the middle covariance eigenvalue for which an
#: arc of samples defines its own (possibly small) circle; see :func:`circle_plane`.
FLATNESS = 0.05


def _unit(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > _TINY, n, 1.0)


def _plane_normal(scatter: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """Least-squares normal of a plane through the origin: smallest eigenvector of ``sum p p^T``."""
    _, vecs = jnp.linalg.eigh(scatter)
    return vecs[:, 0]


# ------------------------------------------------------------------ filtering
def speeds(p: Float[Array, "F 3"], valid: Bool[Array, " F"]) -> tuple[Float[Array, " F"], Bool[Array, " F"]]:
    """Speed ``|p_f - p_{f-1}|`` per frame (frame 0 copies frame 1) and where it is defined."""
    step = jnp.linalg.norm(p[1:] - p[:-1], axis=-1)
    ok = valid[1:] & valid[:-1]
    speed = jnp.concatenate([step[:1], step])
    defined = jnp.concatenate([ok[:1], ok])
    return jnp.where(defined, speed, 0.0), defined


def _prominences(h: Float[Array, " B"]) -> Float[Array, " B"]:
    """Prominence of every bar that is a local maximum (0 for the others).

    Base on each side: the lowest bar between the peak and the nearest strictly
    higher bar on that side, or the histogram's end; prominence = height minus
    the higher of the two bases (as ``scipy.signal.peak_prominences``). The
    histogram is seen as surrounded by empty bars, so a peak in the first bin
    (a limb at rest most of the time) has its full height as prominence.
    """
    h = jnp.concatenate([jnp.zeros(1, h.dtype), h, jnp.zeros(1, h.dtype)])
    n = h.shape[0]
    i = jnp.arange(n)[:, None]
    j = jnp.arange(n)[None, :]
    higher = h[None, :] > h[:, None]
    left = jnp.max(jnp.where(higher & (j < i), j, 0), axis=1)
    right = jnp.min(jnp.where(higher & (j > i), j, n - 1), axis=1)
    inf = jnp.asarray(jnp.inf, h.dtype)
    left_base = jnp.min(jnp.where((j >= left[:, None]) & (j <= i), h[None, :], inf), axis=1)
    right_base = jnp.min(jnp.where((j >= i) & (j <= right[:, None]), h[None, :], inf), axis=1)
    is_max = (h[1:-1] >= h[:-2]) & (h[1:-1] >= h[2:]) & (h[1:-1] > 0)
    return jnp.where(is_max, (h - jnp.maximum(left_base, right_base))[1:-1], 0.0)


def speed_threshold(
    speed: Float[Array, " F"],
    defined: Bool[Array, " F"],
    n_bins: int = 100,
    min_prominence: float = 0.05,
    low_speed_fraction: float = 0.2,
) -> tuple[Float[Array, ""], Float[Array, " B"], Float[Array, ""]]:
    """Movement threshold at the valley after the low-speed peak of the speed histogram.

    Returns ``(threshold, counts, top)``: samples faster than ``threshold`` are
    movement samples; ``counts`` (n_bins,) is the histogram over ``[0, top]``.
    See the module docstring for the valley rule.
    """
    top = jnp.max(jnp.where(defined, speed, 0.0))
    width = jnp.where(top > 0, top / n_bins, 1.0)
    bins = jnp.clip(jnp.floor(speed / width).astype(jnp.int32), 0, n_bins - 1)
    counts = jax.ops.segment_sum(defined.astype(speed.dtype), bins, num_segments=n_bins)
    tol = min_prominence * jnp.max(counts)
    index = jnp.arange(n_bins)
    significant = _prominences(counts) >= jnp.maximum(tol, _TINY)
    peak = jnp.argmax(significant)
    later_peaks = significant & (index > peak)
    stop = jnp.where(jnp.any(later_peaks), jnp.argmax(later_peaks), n_bins)
    between = (index > peak) & (index < stop)
    lowest = jnp.min(jnp.where(between, counts, jnp.inf))
    valley_bars = between & (counts <= lowest + tol)
    valley = jnp.where(jnp.any(valley_bars), jnp.argmax(valley_bars), peak)
    resting = peak < low_speed_fraction * n_bins
    threshold = jnp.where(resting & (top > 0), (valley + 0.5) * width, 0.0)
    return threshold, counts, top


# ------------------------------------------------------------------ circles
def circle_distance(
    p: Float[Array, "F 3"], normal: Float[Array, " 3"], offset: Float[Array, ""]
) -> Float[Array, " F"]:
    """Angle (radians, along the sphere) from unit samples to the circle ``normal . x = offset``.

    The plane distance ``|n . p - h|`` would understate it by the factor
    ``sin(angle to n)``: a compact 2-D patch of samples lies close to some plane
    (the sphere is nearly flat there) but far from that plane's small circle.
    """
    cone = jnp.arccos(jnp.clip(offset, -1.0, 1.0))
    return jnp.abs(jnp.arccos(jnp.clip(p @ normal, -1.0, 1.0)) - cone)


def circle_plane(
    p: Float[Array, "F 3"], weight: Float[Array, " F"], flatness: float = FLATNESS
) -> tuple[Float[Array, " 3"], Float[Array, ""]]:
    """Plane ``n . x = h`` of the circle that weighted samples move on about one axis.

    A rotation about a fixed axis ``n`` keeps ``n . p`` constant: a great circle
    (``h = 0``) when the limb is orthogonal to the axis, a small circle otherwise.
    The paper's axis plane through the joint centre (smallest eigenvector of
    ``sum p p^T``) is the default. The centred fit (smallest eigenvector of the
    samples' covariance) finds a small circle too; it is used only when the arc
    is curved enough to define a plane (smallest covariance eigenvalue below
    ``flatness`` times the middle one) and it halves the RMS angle of the
    samples from the circle, so noise on a short arc cannot tilt the axis.
    """
    total = jnp.maximum(jnp.sum(weight), 1.0)
    mean = jnp.sum(weight[:, None] * p, 0) / total
    centred = p - mean
    vals, vecs = jnp.linalg.eigh(jnp.einsum("f,fi,fj->ij", weight, centred, centred) / total)
    great = _plane_normal(jnp.einsum("f,fi,fj->ij", weight, p, p))
    small, offset = vecs[:, 0], vecs[:, 0] @ mean

    def rms(normal, h):
        return jnp.sqrt(jnp.sum(weight * circle_distance(p, normal, h) ** 2) / total)

    curved = (vals[0] < flatness * vals[1]) & (rms(small, offset) < 0.5 * rms(great, jnp.zeros_like(offset)))
    return jnp.where(curved, small, great), jnp.where(curved, offset, 0.0)


# ---------------------------------------------------------- direction joining
def _group_steps(
    p: Float[Array, "F 3"], movement: Bool[Array, " F"], cell: float, cos_delta: float
) -> tuple[Int[Array, " F"], Float[Array, "F 3"], Float[Array, "F 3"]]:
    """Windowed stratification + sequential grouping (one scan over frames).

    Returns per frame the group id of the step that ends there (-1: no step), the
    sign-aligned step vector ``v`` and its midpoint ``c``.
    """
    zero = jnp.zeros(3, p.dtype)

    def step(carry, x):
        rep, has_rep, d_g, c_g, count, gid = carry
        sample, moving = x
        v = sample - rep
        take = moving & has_rep & (jnp.linalg.norm(v) >= cell)
        mid = 0.5 * (sample + rep)
        normal = _unit(jnp.cross(v, mid))
        group_normal = _unit(jnp.cross(d_g, c_g))
        same = (count > 0) & (jnp.abs(normal @ group_normal) >= cos_delta)
        v_al = jnp.where(same & (v @ d_g < 0), -v, v)
        k = count.astype(p.dtype)
        new = (
            jnp.where(same, (k * d_g + v_al) / (k + 1), v),
            jnp.where(same, (k * c_g + mid) / (k + 1), mid),
            jnp.where(same, count + 1, 1),
            jnp.where(same, gid, gid + 1),
        )
        d_g, c_g, count, gid = (jnp.where(take, a, b) for a, b in zip(new, (d_g, c_g, count, gid)))
        rep = jnp.where(moving & (take | ~has_rep), sample, rep)
        out = (jnp.where(take, gid, -1), v_al, mid)
        return (rep, moving, d_g, c_g, count, gid), out

    init = (zero, jnp.asarray(False), zero, zero, jnp.asarray(0), jnp.asarray(-1))
    _, (gid, v, mid) = jax.lax.scan(step, init, (p, movement))
    return gid, v, mid


def _merge_groups(
    normals: Float[Array, "K 3"], weights: Float[Array, " K"], cos_delta: float
) -> tuple[Int[Array, " K"], Float[Array, "K 3"], Float[Array, " K"], Int[Array, ""]]:
    """Agglomerative merging of axis planes while the most similar pair is within ``delta``.

    Returns each group's cluster (the index of the group it was merged into),
    the cluster normals and weights (zero for merged-away groups) and the number
    of merges.
    """
    k = weights.shape[0]
    eye = jnp.eye(k, dtype=bool)

    def best_pair(state):
        normals, weights, _, _ = state
        active = weights > 0
        sim = jnp.abs(normals @ normals.T)
        sim = jnp.where(active[:, None] & active[None, :] & ~eye, sim, -1.0)
        flat = jnp.argmax(sim)
        return flat // k, flat % k, sim.reshape(-1)[flat]

    def cond(state):
        return best_pair(state)[2] >= cos_delta

    def body(state):
        normals, weights, label, merges = state
        a, b, _ = best_pair(state)
        sign = jnp.sign(normals[a] @ normals[b])
        merged = _unit(weights[a] * normals[a] + sign * weights[b] * normals[b])
        normals = normals.at[a].set(merged)
        weights = weights.at[a].add(weights[b]).at[b].set(0.0)
        label = jnp.where(label == b, a, label)
        return normals, weights, label, merges + 1

    state = (normals, weights, jnp.arange(k), jnp.asarray(0))
    normals, weights, label, merges = jax.lax.while_loop(cond, body, state)
    return label, normals, weights, merges


def _largest(counts: Float[Array, " N"], k: int) -> tuple[Int[Array, " k"], Bool[Array, " k"]]:
    """Indices of the ``k`` largest integer-valued ``counts`` (ties: earliest first; unordered).

    Returns ``(indices, ok)``; when N < k the surplus entries have ``ok`` False.

    A bisection on the count threshold (~log2 N passes) and a compaction; on long
    recordings this is much cheaper than sorting every group (``lax.top_k``).
    """

    def bisect(_, bounds):
        lo, hi = bounds  # at least k counts >= lo; fewer than k counts >= hi
        mid = (lo + hi) // 2
        enough = jnp.sum(counts >= mid) >= k
        return jnp.where(enough, mid, lo), jnp.where(enough, hi, mid)

    top = jnp.max(counts).astype(jnp.int32) + 1
    steps = max(1, int(math.ceil(math.log2(counts.shape[0] + 2))))
    threshold, _ = jax.lax.fori_loop(0, steps, bisect, (jnp.asarray(0, jnp.int32), top))
    above = jnp.nonzero(counts > threshold, size=k, fill_value=-1)[0]
    at = jnp.nonzero(counts == threshold, size=k, fill_value=-1)[0]
    n_above = jnp.sum(above >= 0)
    picked = jnp.where(jnp.arange(k) < n_above, above, at[jnp.clip(jnp.arange(k) - n_above, 0, k - 1)])
    return jnp.maximum(picked, 0), picked >= 0


def join_directions(
    p: Float[Array, "F 3"],
    movement: Bool[Array, " F"],
    n_axes: Int[Array, ""],
    *,
    cell: float,
    delta: float,
    max_groups: int,
    min_separation: float = math.radians(30.0),
) -> tuple[Float[Array, "2 3"], Float[Array, " 2"], Int[Array, ""]]:
    """Direction joining: the axes of the two largest main directions.

    Returns ``(axes, offsets, merges)``: each main direction's samples lie on
    ``axes[k] . p = offsets[k]``. The second main direction is the largest
    cluster at least ``min_separation`` away from the first; without one (or with
    ``n_axes`` 1) the second axis completes the first to a right angle through
    the samples' centroid.
    """
    n = p.shape[0]
    cos_delta = math.cos(delta)
    gid, v, mid = _group_steps(p, movement, cell, cos_delta)
    seg = jnp.where(gid >= 0, gid, n)
    took = (gid >= 0).astype(p.dtype)
    counts = jax.ops.segment_sum(took, seg, num_segments=n + 1)[:n]
    d_sum = jax.ops.segment_sum(v, seg, num_segments=n + 1)[:n]
    c_sum = jax.ops.segment_sum(mid, seg, num_segments=n + 1)[:n]
    top, ok = _largest(counts, max_groups)
    top_counts = jnp.where(ok, counts[top], 0.0)
    normals = _unit(jnp.cross(d_sum[top], c_sum[top]))
    label, normals, cluster_weight, merges = _merge_groups(normals, top_counts, cos_delta)

    # Each step's cluster (-1 for steps in groups too small to be among the top).
    slot = jnp.full(n + 1, -1).at[jnp.where(ok, top, n)].set(jnp.arange(max_groups))[seg]
    cluster = jnp.where(slot >= 0, label[jnp.maximum(slot, 0)], -1)
    # The second main direction is the largest cluster whose axis is at least
    # ``min_separation`` from the first: nearly parallel axes could not reach the
    # directions in between.
    first = jnp.argmax(cluster_weight)
    apart = jnp.abs(normals @ normals[first]) <= math.cos(min_separation)
    second_weight = jnp.where(apart, cluster_weight, 0.0)
    second = jnp.argmax(second_weight)

    def fit(c):
        return circle_plane(p, ((cluster == c) & (gid >= 0)).astype(p.dtype))

    a1, h1 = fit(first)
    a2, h2 = fit(second)
    two = (n_axes > 1) & (second_weight[second] > 0)

    # Refit each axis on every movement sample that lies near its circle (nearer
    # than to the other one, within three times the RMS of those and at least
    # 1 degree), not only on the stratified steps of its cluster.
    dist = jnp.stack([circle_distance(p, a1, h1), jnp.where(two, circle_distance(p, a2, h2), jnp.inf)], axis=1)
    nearest = jnp.argmin(dist, axis=1)
    near = jnp.min(dist, axis=1)

    def refit(k, axis, offset):
        member = (movement & (nearest == k)).astype(p.dtype)
        rms = jnp.sqrt(jnp.sum(member * near**2) / jnp.maximum(jnp.sum(member), 1.0))
        keep = member * (near <= jnp.maximum(3.0 * rms, math.radians(1.0)))
        refitted = circle_plane(p, keep)
        enough = jnp.sum(keep) >= 3
        return jnp.where(enough, refitted[0], axis), jnp.where(enough, refitted[1], offset)

    a1, h1 = refit(0, a1, h1)
    b2, g2 = refit(1, a2, h2)
    # Noise can pull the weaker direction's refit onto the stronger one: keep the separation.
    apart = jnp.abs(b2 @ a1) <= math.cos(min_separation)
    a2, h2 = jnp.where(apart, b2, a2), jnp.where(apart, g2, h2)
    centroid = jnp.sum(jnp.where(movement[:, None], p, 0.0), axis=0)
    a2 = jnp.where(two, a2, _unit(jnp.cross(a1, centroid)))
    h2 = jnp.where(two, h2, 0.0)
    return jnp.stack([a1, a2]), jnp.stack([h1, h2]), merges


# ------------------------------------------------------------- PCA / EM
def cell_keys(u: Float[Array, "F 3"], cell: float, offset: float = 0.0) -> tuple[Int[Array, " F"], int]:
    """Grid cells of side ``cell`` over the cube ``[-1, 1]^3`` holding the unit sphere: each point's cell
    ``floor((u + 1) / cell + offset)`` per coordinate, flattened to one key, and the number of keys.

    Keys order as their cells lexicographically; ``offset`` (in cells) shifts the grid."""
    side = int(math.ceil(2.0 / cell)) + 2
    ijk = jnp.clip(jnp.floor((u + 1.0) / cell + offset).astype(jnp.int32), 0, side - 1)
    return (ijk[:, 0] * side + ijk[:, 1]) * side + ijk[:, 2], side**3


def _grid_representatives(
    p: Float[Array, "F 3"], movement: Bool[Array, " F"], cell: float
) -> tuple[Float[Array, "F 3"], Float[Array, " F"]]:
    """Global stratification: one sample per occupied grid cell (weights 1, others 0)."""
    key = jnp.where(movement, cell_keys(p, cell)[0], jnp.iinfo(jnp.int32).max)
    order = jnp.argsort(key)
    sorted_key = key[order]
    first = jnp.concatenate([jnp.ones(1, bool), sorted_key[1:] != sorted_key[:-1]])
    weight = (first & movement[order]).astype(p.dtype)
    return p[order], weight


def _pca_from_reps(reps: Float[Array, "F 3"], weight: Float[Array, " F"]) -> Float[Array, "2 3"]:
    total = jnp.maximum(jnp.sum(weight), 1.0)
    centroid = jnp.sum(weight[:, None] * reps, axis=0) / total
    centred = reps - centroid
    cov = jnp.einsum("f,fi,fj->ij", weight, centred, centred) / total
    _, vecs = jnp.linalg.eigh(cov)
    return _unit(jnp.cross(centroid, jnp.stack([vecs[:, 2], vecs[:, 1]])))


def pca_axes(p: Float[Array, "F 3"], movement: Bool[Array, " F"], *, cell: float) -> Float[Array, "2 3"]:
    """Principal-direction axes ``c x e_1``, ``c x e_2`` of the grid-stratified movement samples."""
    reps, weight = _grid_representatives(p, movement, cell)
    return _pca_from_reps(reps, weight)


#: Distances to the two axis planes (on the unit sphere) closer than this are a tie in EM's E-step.
EM_TIE = 1e-9


def em_axes(
    p: Float[Array, "F 3"],
    movement: Bool[Array, " F"],
    n_axes: Int[Array, ""],
    *,
    cell: float,
    max_steps: int,
) -> tuple[Float[Array, "2 3"], Int[Array, ""], Bool[Array, ""]]:
    """EM refinement of the PCA planes: returns ``(axes, steps, converged)``.

    E-step: each representative goes to the axis plane it is closest to
    (``|a_k . p|``; only the first plane when ``n_axes`` is 1), and stays with its
    plane when the two are equally close to within :data:`EM_TIE` (a sample where the
    circles cross, e.g. the rest pose, would otherwise swap planes on round-off and
    never let the assignment settle). M-step: each plane is the least-squares plane
    through the joint centre of its representatives (an empty plane keeps its axis).
    Stops when no assignment changes.
    """
    reps, weight = _grid_representatives(p, movement, cell)
    axes0 = _pca_from_reps(reps, weight)

    def assign(axes, labels):
        dist = jnp.abs(reps @ axes.T)
        dist = dist.at[:, 1].set(jnp.where(n_axes > 1, dist[:, 1], jnp.inf))
        tie = jnp.abs(dist[:, 0] - dist[:, 1]) <= EM_TIE
        return jnp.where(tie, labels, jnp.argmin(dist, axis=1))

    def refit(axes, labels):
        def one(k, axis):
            w = weight * (labels == k)
            fitted = _plane_normal(jnp.einsum("f,fi,fj->ij", w, reps, reps))
            return jnp.where(jnp.sum(w) >= 2, fitted, axis)

        return jax.vmap(one)(jnp.arange(2), axes)

    def cond(state):
        _, _, steps, changed = state
        return changed & (steps < max_steps)

    def body(state):
        axes, labels, steps, _ = state
        axes = refit(axes, labels)
        new_labels = assign(axes, labels)
        changed = jnp.any((new_labels != labels) & (weight > 0))
        return axes, new_labels, steps + 1, changed

    state = (axes0, assign(axes0, jnp.zeros(reps.shape[0], jnp.int32)), jnp.asarray(0), jnp.asarray(True))
    axes, _, steps, changed = jax.lax.while_loop(cond, body, state)
    return axes, steps, ~changed


# ------------------------------------------------------------- rest position
def rest_target(
    axes: Float[Array, "2 3"], n_axes: Int[Array, ""], centroid: Float[Array, " 3"]
) -> Float[Array, " 3"]:
    """Point where the axis planes cut the unit joint sphere, nearest the samples' centroid."""
    line = _unit(jnp.cross(axes[0], axes[1]))
    two = jnp.where(line @ centroid < 0, -line, line)
    one = _unit(centroid - (centroid @ axes[0]) * axes[0])
    return jnp.where(n_axes > 1, two, one)


def orient_axes(
    axes: Float[Array, "2 3"], offsets: Float[Array, " 2"]
) -> tuple[Float[Array, "2 3"], Float[Array, " 2"]]:
    """Sign convention: each axis has a positive largest-magnitude component (in the parent joint frame)."""
    dominant = jnp.take_along_axis(axes, jnp.argmax(jnp.abs(axes), axis=1)[:, None], axis=1)[:, 0]
    flip = jnp.where(dominant < 0, -1.0, 1.0).astype(axes.dtype)
    return flip[:, None] * axes, flip * offsets
