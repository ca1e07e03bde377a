"""The joint cost of Kirk, O'Brien & Forsyth (2005, §3.2) and the joint it places.

Two marker groups with K markers in total, F frames, marker ``k`` present in the
``n_k`` frames where ``mask`` is true. For a joint trajectory ``c_f`` the cost is

    Q(c) = 1/K sum_k [ var_f |c_f - m_fk| + alpha mean_f |c_f - m_fk| ],

means and variances running over the frames where marker k is present. The joint
cost of the pair is ``min_c Q``. Introducing radii ``r_k`` (``var = min_r mean
(d - r)^2``) turns it into least squares over ``(c, r)`` with residuals

    e_fk = sqrt(w_fk/(K n_k)) (|c_f - m_fk| - r_k),
    p_fk = sqrt(alpha w_fk/(K n_k) / |c_f - m_fk|) (c_f - m_fk)   (|p|^2 = prior term),

whose sum of squares is exactly Q. A frame with fewer than three present markers
says nothing about ``c_f`` (a circle or sphere of equally good positions): it gets
zero weight, its ``c_f`` stays at the warm start, and ``valid_frames`` flags it.
Three markers are not enough either for the *pair*: any radii then fit exactly, so
the variance term determines nothing and only the prior places the joint. Four or
more markers and two rotational degrees of freedom exercised determine it.

Solvers
-------
``method="lm"`` (default): a Levenberg–Marquardt over ``(c, r)`` that eliminates
each frame's 3x3 block onto the K x K radii system (Schur complement), with
per-frame damping, and reseeding of frames stuck on a mirror branch; see
:mod:`jaxskel.joints._cost_lm` for the maths. True joints converge in far fewer steps
than pairs without a joint, which need hundreds (their costs are upper bounds when
capped, which only makes them look worse).

Why not variable projection inside optimistix (outer ``optx.LevenbergMarquardt`` on
the radii, inner vmapped ``optx.least_squares`` per frame)? The inner per-frame
trilaterations need many steps with optimistix's GaussNewton, LevenbergMarquardt and
Dogleg (no warm start across outer evaluations is possible
in a pure residual function, and the Gauss–Newton model of the square-root prior
residual is poor), and a hand-written variable projection with exact inner solves
converged to worse local minima on near-collinear marker sets than the joint
(c, r) iteration. The joint iteration with per-frame damping was both faster and
more robust, so it is what ``"lm"`` runs.

``method="ncg"``: the paper's nonlinear conjugate gradients on Q(c) (radii
eliminated in closed form) via ``optimistix.NonlinearCG``. The objective is scaled
to a per-observation sum (multiplied by K max_k n_k) before it is handed to
optimistix: on the mean-normalised Q the gradient is ~1/F and the backtracking line
search (first trial step 1) crawls without converging. Scaled, it converges, in more
steps and more time than LM, but it has no reseeding: it can stop at a genuine local
minimum with a few frames on the mirror branch, well above LM's cost.

Steps, timings and errors of both methods, and of variable projection, are in
docs/bench/evidence_from_docstrings.md.

Identifiability
---------------
The data-only information about the joint lives in the reduced (Schur) matrix on
the radii, ``S = C - sum_f B_f^T A_f^-1 B_f``, built from the Gauss–Newton matrix of
the distance residuals (no prior). A direction in which the joint can slide without
changing any marker's distance (variance) is a null vector of S in noise-free data:
none for an exercised ball or universal joint, one for a hinge (along its axis),
three when the segments never move relative to each other. With noise those
directions still get curvature, because noise turns the marker-to-joint unit
vectors; plain eigenvalue ratios of S then overlap between a weakly exercised ball
and a hinge (measured). So each direction's curvature is compared with the curvature
marker noise alone is expected to give it: noise of variance sigma^2 (the fitted mean
distance variance) turns ``u`` by ``(I - u u^T) eps / d``, which gives
``N = sigma^2 sum_f D_f^T [sum_k beta (I - u u^T)/d^2] D_f`` with ``D_f = A_f^-1 B_f``
the joint displacement per unit radius change. The generalised eigenvalues of
``(S, N)`` are signal-to-noise ratios: of order 1 to tens for directions only noise pins
(hinge axis, rigid pair), hundreds and more for directions the motion exercises (the
ranges measured: docs/bench/evidence_from_docstrings.md). Reported:

* ``identifiability``: the smallest signal-to-noise ratio (dimensionless);
* ``undetermined_dims``: how many directions have a ratio below 20
  (0 ball/universal, 1 hinge, 3 no relative motion). Pairs with only four markers or
  a single marker on one side are weakly determined and can land on either side;
* ``uncertainty``: the largest RMS joint displacement (metres) reachable by changing
  the radii while the mean distance variance rises by no more than its fitted value
  (at least (0.1 mm)^2): millimetres to a few centimetres for exercised joints,
  decimetres along an undetermined axis. It is a sensitivity, not a 1/sqrt(F)
  standard error, which would shrink with F even where only noise pins the joint.

Derivatives
-----------
The solution map ``markers, alpha -> (c, r)`` has a custom JVP from the implicit
function theorem on ``grad f = 0``: ``[dc; dr] = -H^-1 d(grad f)``, with the exact
block-arrow Hessian solved by the same Schur elimination (never a dense
(3F+K)^2 matrix). Reverse mode transposes it. The cost's gradient is then the
partial derivative at the optimum. Derivatives exist where the joint is determined
(or alpha > 0 pins it).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._errors import DegenerateMotionError, InputError
from .._math.linalg import generalised_eigvalsh
from .._runtime.backend import to_device
from .._runtime.precision import float64_scope
from ._cost_lm import PairProblem, block_solve, inv3, levenberg_marquardt

__all__ = ["JointSolution", "solve_joint", "solve_joints"]

_METHODS = ("lm", "ncg")
_DEFAULT_MAX_STEPS = {"lm": 256, "ncg": 20_000}
# Frames need this many present markers to place a joint.
_MIN_MARKERS_PER_FRAME = 3
# Motion must add this many times the curvature that marker noise alone gives a direction
# before the direction counts as determined (see "Identifiability" above).
_UNDETERMINED_SNR = 20.0
# Noise floor (metres) for the uncertainty measure, so noiseless data still gives finite values.
_NOISE_FLOOR = 1e-4
# optimistix result names by integer code, for readable reports
_RESULT_NAMES = {
    int(getattr(optx.RESULTS, name)._value): name
    for name in (
        "successful",
        "nonlinear_max_steps_reached",
        "nonlinear_divergence",
        "nonfinite",
        "max_steps_reached",
        "singular",
        "breakdown",
        "stagnation",
    )
    if hasattr(optx.RESULTS, name)
}


class JointSolution(eqx.Module):
    """Joint placed between two marker groups (leading batch axes when batched).

    Attributes
    ----------
    positions
        Joint centre per frame (..., F, 3), metres. Frames flagged invalid keep the
        warm start (see ``c0`` in :func:`solve_joints`).
    radii
        Mean distance of each marker to the joint (..., K); 0 for absent markers.
    cost
        Joint cost Q (...): mean over markers of the distance variance plus alpha times
        the mean distance (m^2).
    variance
        The variance part of ``cost`` alone (...), m^2: ~ the marker noise variance for a
        true joint. With alpha = 0.01 the prior term is ~100x larger than this for
        human-sized segments, so compare pairs by ``variance`` when alpha is large.
    distance_std
        Standard deviation of each marker's distance to the joint (..., K), metres.
    steps
        Solver steps taken (...).
    result
        optimistix ``RESULTS`` code as int (...); see :attr:`result_name`.
    converged
        ``result == successful`` *and* ``residual <= max(100 rtol, 1e-6) * cost`` (...).
        The second test catches a solver that meets its own step criterion while
        crawling, as optimistix's NCG can, well above the minimum.
    residual
        Cost decrease (m^2) a full Newton step would still predict at the returned
        point: ~0 at a minimum, the same yardstick for both methods.
    identifiability
        Smallest signal-to-noise ratio of the data-only information about the joint
        (...): >~100 well determined, ~1-20 undetermined (see module docstring).
    undetermined_dims
        Number of directions in which the data do not determine the joint (...):
        0 exercised ball/universal, 1 hinge, 3 no relative motion.
    uncertainty
        Largest RMS joint displacement (metres) that raises the mean distance variance
        by no more than its fitted value (...).
    valid_frames
        Frames with at least three present markers (..., F).
    """

    positions: Float[Array, "*batch F 3"]
    radii: Float[Array, "*batch K"]
    cost: Float[Array, "*batch"]
    variance: Float[Array, "*batch"]
    distance_std: Float[Array, "*batch K"]
    steps: Int[Array, "*batch"]
    result: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    residual: Float[Array, "*batch"]
    identifiability: Float[Array, "*batch"]
    undetermined_dims: Int[Array, "*batch"]
    uncertainty: Float[Array, "*batch"]
    valid_frames: Bool[Array, "*batch F"]

    @property
    def result_name(self) -> Any:
        """Readable optimistix result name(s): a str, or an array of str when batched."""
        codes = np.asarray(self.result)
        names = np.vectorize(lambda code: _RESULT_NAMES.get(int(code), f"code {int(code)}"), otypes=[object])(codes)
        return names.item() if names.ndim == 0 else names


def _problem(markers, mask, alpha):
    """Centre the markers, weight them and build the pair problem.

    Weights are the paper's ``w_fk / (K n_k)`` times ``K max_k n_k`` (so one observation
    weighs ~1 whatever F is); ``norm`` converts the scaled objective back to Q.
    """
    dtype = markers.dtype
    present = mask & (jnp.sum(mask, axis=1, keepdims=True) >= _MIN_MARKERS_PER_FRAME)
    w = present.astype(dtype)
    n = jnp.sum(w, axis=0)
    n_max = jnp.maximum(jnp.max(n), 1.0)
    k_eff = jnp.maximum(jnp.sum(n > 0), 1).astype(dtype)
    beta = w * (n_max / jnp.where(n > 0, n, 1.0))
    m = mask.astype(dtype)
    reference = jnp.sum(markers * m[..., None], axis=(0, 1)) / jnp.maximum(jnp.sum(m), 1.0)
    centred = jnp.where(mask[..., None], markers - reference, 0.0)
    return PairProblem(centred, beta, jnp.asarray(alpha, dtype)), reference, k_eff * n_max


def _default_start(problem: PairProblem, mask, c0, r0, has_c0, has_r0):
    """Warm start: per-frame marker centroid, and the mean marker distance from it.

    A frame missing some markers takes the centroid of its present markers plus the
    offset from that subset's centroid to the full centroid in the nearest frame (in
    index order) where every marker is present. The plain subset centroid would sit
    in the plane of e.g. three markers, where both mirror images of the joint are
    equally close and the solver picks one by chance.
    """
    x = problem.markers
    m = mask.astype(x.dtype)
    count = jnp.maximum(jnp.sum(m, axis=1), 1.0)
    centroid = jnp.sum(x * m[..., None], axis=1) / count[:, None]
    full = jnp.all(mask | ~jnp.any(mask, axis=0), axis=1) & (jnp.sum(mask, axis=1) >= _MIN_MARKERS_PER_FRAME)
    frames = x.shape[0]
    index = jnp.arange(frames)
    before = jax.lax.cummax(jnp.where(full, index, -1))
    after = jax.lax.cummin(jnp.where(full, index, frames), reverse=True)
    use_after = (after < frames) & ((before < 0) | (after - index < index - before))
    nearest = jnp.clip(jnp.where(use_after, after, before), 0, frames - 1)
    subset_there = jnp.sum(x[nearest] * m[..., None], axis=1) / count[:, None]
    offset = jnp.where(jnp.any(full), centroid[nearest] - subset_there, 0.0)
    c_start = jnp.where(has_c0, c0, centroid + offset)
    d, _, _ = problem.geometry(c_start)
    n = jnp.sum(problem.beta, axis=0)
    mean_d = jnp.sum(problem.beta * d, axis=0) / jnp.where(n > 0, n, 1.0)
    r_start = jnp.where(has_r0, r0, mean_d)
    return c_start, r_start


def _eliminated_objective(c, problem: PairProblem):
    """Scaled Q(c)/2 with the radii eliminated (r = weighted mean distance)."""
    d, _, _ = problem.geometry(c)
    n = jnp.sum(problem.beta, axis=0)
    mean_d = jnp.sum(problem.beta * d, axis=0) / jnp.where(n > 0, n, 1.0)
    e = d - mean_d
    return 0.5 * jnp.sum(problem.beta * (e * e + problem.alpha * d))


def _run_solver(problem: PairProblem, c0, r0, controls, settings):
    """``controls`` (max_steps, rtol, atol) are traced for LM, so changing them does not
    recompile; optimistix needs them static for NCG, where they are in ``settings``."""
    method = settings[0]
    if method == "lm":
        max_steps, rtol, atol, _ = controls
        c, r, steps, result = levenberg_marquardt(problem, c0, r0, max_steps=max_steps, rtol=rtol, atol=atol)
    else:
        _, max_steps, rtol, atol = settings
        sol = optx.minimise(
            _eliminated_objective,
            optx.NonlinearCG(rtol=rtol, atol=atol),
            c0,
            args=problem,
            max_steps=max_steps,
            throw=False,
        )
        c, steps, result = sol.value, sol.stats["num_steps"], sol.result
        d, _, _ = problem.geometry(c)
        n = jnp.sum(problem.beta, axis=0)
        r = jnp.sum(problem.beta * d, axis=0) / jnp.where(n > 0, n, 1.0)
    # optimistix keeps its result as an enumeration item; carry the int code
    return c, r, jnp.asarray(steps, jnp.int32), jnp.asarray(result._value, jnp.int32)


@functools.partial(jax.custom_jvp, nondiff_argnums=(6,))
def _argmin(markers, alpha, beta, c0, r0, controls, settings):
    """(c, r) minimising the joint cost; differentiable in (markers, alpha) implicitly."""
    return _run_solver(PairProblem(markers, beta, alpha), c0, r0, controls, settings)


@_argmin.defjvp
def _argmin_jvp(settings, primals, tangents):
    markers, alpha, beta, c0, r0, controls = primals
    d_markers, d_alpha = tangents[:2]
    out = _argmin(markers, alpha, beta, c0, r0, controls, settings)
    c, r = out[0], out[1]

    def gradient_at_solution(x, a):
        return PairProblem(x, beta, a).gradient(c, r)

    _, (dg_c, dg_r) = jax.jvp(gradient_at_solution, (markers, alpha), (d_markers, d_alpha))
    problem = PairProblem(markers, beta, alpha)
    a, b, c_diag, _, _ = problem.blocks(c, r, curvature="exact")
    # a relative ridge keeps exactly degenerate frames (alpha = 0) solvable
    a = a + 1e-10 * (jnp.trace(a, axis1=1, axis2=2) / 3.0)[:, None, None] * jnp.eye(3, dtype=a.dtype)
    dc, dr = block_solve(a, b, c_diag, -dg_c, -dg_r)
    dc = jnp.where(problem.valid_frames[:, None], dc, 0.0)
    dr = jnp.where(problem.valid_markers, dr, 0.0)
    integer_zero = np.zeros((), dtype=jax.dtypes.float0)
    return out, (dc, dr, integer_zero, integer_zero)


def _newton_decrement(problem: PairProblem, c, r):
    """``g^T H^-1 g`` with the LM model Hessian: the (scaled) cost a full Newton step
    would still remove, ~0 at a minimum. A tiny ridge keeps flat directions finite."""
    a, b, c_diag, g_c, g_r = problem.blocks(c, r, curvature="positive")
    ridge = 1e-9 * (jnp.trace(a, axis1=1, axis2=2) / 3.0)
    a = a + ridge[:, None, None] * jnp.eye(3, dtype=a.dtype)
    step_c, step_r = block_solve(a, b, c_diag * (1.0 + 1e-9), g_c, g_r)
    return jnp.sum(g_c * step_c) + jnp.sum(g_r * step_r)


def _identifiability(problem: PairProblem, c, r, noise_variance, norm):
    """(weakest signal-to-noise ratio, undetermined dims, uncertainty in metres).

    See the module docstring. ``norm`` converts the scaled objective of ``problem``
    back to Q (see :func:`_problem`); S, N and the cost rise below are all in the scaled
    units, so only the tolerated rise needs the factor.
    """
    dtype = c.dtype
    a, b, c_diag, _, _ = problem.blocks(c, r, curvature="none")
    a = a + 1e-9 * (jnp.trace(a, axis1=1, axis2=2) / 3.0)[:, None, None] * jnp.eye(3, dtype=dtype)
    valid_f, valid_m = problem.valid_frames, problem.valid_markers
    # joint displacement per unit radius change, dc_f = -A_f^-1 B_f dr (sign irrelevant below)
    disp = jnp.where(valid_f[:, None, None], inv3(a) @ b, 0.0)
    schur = jnp.diag(c_diag) - jnp.einsum("fik,fil->kl", b, disp)

    # expected curvature from marker noise alone: noise of variance sigma^2 turns each unit
    # vector u by (I - u u^T) eps / d, so a direction gains sigma^2 sum beta |(I - uu^T) dc|^2 / d^2
    _, u, inv_d = problem.geometry(c)
    across = jnp.eye(3, dtype=dtype) - u[..., :, None] * u[..., None, :]
    w_noise = jnp.einsum("fk,fkij->fij", problem.beta * inv_d**2, across)
    sigma2 = jnp.maximum(noise_variance, _NOISE_FLOOR**2)
    noise = sigma2 * jnp.einsum("fik,fij,fjl->kl", disp, w_noise, disp)

    # absent markers: decoupled directions made to look perfectly determined
    pair = valid_m[:, None] & valid_m[None, :]
    n_valid = jnp.maximum(jnp.sum(valid_m), 1)
    noise_fill = jnp.maximum(jnp.sum(jnp.where(valid_m, jnp.diag(noise), 0.0)) / n_valid, jnp.finfo(dtype).tiny)
    noise = jnp.where(pair, noise, 0.0) + jnp.diag(jnp.where(valid_m, 0.0, noise_fill))
    schur = jnp.where(pair, schur, 0.0) + jnp.diag(jnp.where(valid_m, 0.0, 1e12 * noise_fill))
    schur, noise = 0.5 * (schur + schur.T), 0.5 * (noise + noise.T)

    # Plain XLA (Cholesky + Jacobi, jaxskel._math.linalg), not jnp.linalg.eigh: as LAPACK
    # kernels these two independent problems can run concurrently and deadlock XLA:CPU's
    # intra-op pool (ParallelBatchMap; the observed hang: docs/bench/evidence_from_docstrings.md).
    snr = generalised_eigvalsh(schur, noise)
    undetermined = jnp.sum(snr < _UNDETERMINED_SNR).astype(jnp.int32)

    frames = jnp.maximum(jnp.sum(valid_f), 1)
    metric = jnp.einsum("fik,fil->kl", disp, disp) / frames
    # largest RMS displacement^2 per unit rise of the (scaled) cost: eig of (metric, schur)
    spread = generalised_eigvalsh(metric, schur)[-1]
    uncertainty = jnp.sqrt(jnp.maximum(spread, 0.0) * sigma2 * norm)
    return snr[0], undetermined, uncertainty


def _solve_pair(markers, mask, alpha, c0, r0, has_c0, has_r0, controls, settings) -> JointSolution:
    problem, reference, norm = _problem(markers, mask, alpha)
    c_start, r_start = _default_start(problem, mask, c0 - reference, r0, has_c0, has_r0)
    beta = problem.beta
    c, r, steps, result = _argmin(problem.markers, problem.alpha, beta, c_start, r_start, controls, settings)

    w = beta > 0
    d, _, _ = problem.geometry(c)
    n = jnp.sum(w, axis=0)
    safe_n = jnp.where(n > 0, n, 1)
    mean_d = jnp.sum(jnp.where(w, d, 0.0), axis=0) / safe_n
    variance = jnp.sum(jnp.where(w, (d - mean_d) ** 2, 0.0), axis=0) / safe_n
    valid_m = n > 0
    k_eff = jnp.maximum(jnp.sum(valid_m), 1)
    mean_variance = jnp.sum(jnp.where(valid_m, variance, 0.0)) / k_eff
    cost = mean_variance + problem.alpha * jnp.sum(jnp.where(valid_m, mean_d, 0.0)) / k_eff

    c_fixed, r_fixed = jax.lax.stop_gradient((c, mean_d))
    residual = _newton_decrement(problem, c_fixed, r_fixed) / norm
    # Noise level for the identifiability test. With alpha > 0 the fitted variance also
    # holds the prior's bias (centimetres), so subtract what a Newton step on the
    # variance alone would still remove.
    data_only = PairProblem(problem.markers, problem.beta, jnp.zeros_like(problem.alpha))
    noise_variance = jax.lax.stop_gradient(mean_variance - _newton_decrement(data_only, c_fixed, r_fixed) / norm)
    snr, undetermined, uncertainty = _identifiability(problem, c_fixed, r_fixed, noise_variance, norm)
    return JointSolution(
        positions=c + reference,
        radii=jnp.where(valid_m, mean_d, 0.0),
        cost=cost,
        variance=mean_variance,
        # double where: sqrt's derivative at 0 (absent markers) would turn into NaN
        distance_std=jnp.where(variance > 0, jnp.sqrt(jnp.where(variance > 0, variance, 1.0)), 0.0),
        steps=steps,
        result=result,
        converged=(result == int(optx.RESULTS.successful._value)) & (residual <= controls[3] * cost),
        residual=residual,
        identifiability=snr,
        undetermined_dims=undetermined,
        uncertainty=uncertainty,
        valid_frames=problem.valid_frames,
    )


@functools.partial(jax.jit, static_argnames=("settings",))
def _solve_batch(markers, mask, alpha, c0, r0, has_c0, has_r0, controls, *, settings) -> JointSolution:
    solve = functools.partial(_solve_pair, settings=settings)
    in_axes = (0, 0, 0, 0, 0, None, None, None)
    return jax.vmap(solve, in_axes=in_axes)(markers, mask, alpha, c0, r0, has_c0, has_r0, controls)


def _settings(method, max_steps, rtol, atol, dtype):
    if method not in _METHODS:
        raise InputError(f"method must be one of {_METHODS}, got {method!r}.")
    if max_steps is None:
        max_steps = _DEFAULT_MAX_STEPS[method]
    if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise InputError(f"max_steps must be a positive int, got {max_steps!r}.")
    double = jnp.dtype(dtype) == jnp.float64
    rtol = (1e-10 if double else 1e-5) if rtol is None else float(rtol)
    atol = (1e-9 if double else 1e-6) if atol is None else float(atol)
    if not (rtol >= 0 and atol >= 0 and math.isfinite(rtol) and math.isfinite(atol)):
        raise InputError(f"rtol and atol must be finite and >= 0, got rtol={rtol}, atol={atol}.")
    # converged also needs the Newton decrement below this fraction of the cost: a solver
    # can meet its own step criterion while crawling (NCG does, far from the minimum)
    optimality = to_device(max(100.0 * rtol, 1e-6), dtype)
    if method == "lm":
        controls = (to_device(max_steps, np.int32), to_device(rtol, dtype), to_device(atol, dtype), optimality)
        return ("lm",), controls
    unused = (to_device(0, np.int32), to_device(0.0, dtype), to_device(0.0, dtype))
    return (method, int(max_steps), rtol, atol), unused + (optimality,)


def _prepare(markers, mask, alpha, c0, r0):
    """Validate and convert inputs shaped (..., F, K, 3); NaNs only where mask is False.

    Concrete inputs are checked with numpy (cheap, and no per-op dispatch); traced inputs
    (inside jit/vmap/grad) get the shape checks only.
    """
    traced = any(isinstance(v, jax.core.Tracer) for v in (markers, mask, alpha, c0, r0))
    xp = jnp if traced else np
    markers = xp.asarray(markers)
    if not xp.issubdtype(markers.dtype, xp.floating):
        markers = markers.astype(float)
    if markers.ndim < 3 or markers.shape[-1] != 3:
        raise InputError(f"markers must be shaped (..., F, K, 3), got {markers.shape}.")
    frames, n_markers = markers.shape[-3], markers.shape[-2]
    if frames < 1 or n_markers < 1:
        raise InputError(f"markers need at least one frame and one marker, got shape {markers.shape}.")
    finite = xp.all(xp.isfinite(markers), axis=-1)
    if mask is None:
        mask = finite
    else:
        mask = xp.asarray(mask)
        if mask.shape != markers.shape[:-1]:
            raise InputError(f"mask must be shaped {markers.shape[:-1]} to match markers, got {mask.shape}.")
        mask = mask.astype(bool)
        if not traced and np.any(mask & ~finite):
            raise InputError(
                "markers contain NaN/inf where mask says the marker is present; "
                "pass mask=None to treat non-finite samples as missing."
            )
        mask = mask & finite
    markers = xp.where(mask[..., None], markers, 0.0)
    dtype = markers.dtype
    alpha = xp.asarray(alpha, dtype)
    if not traced and not bool(np.all((alpha >= 0) & np.isfinite(alpha))):
        raise InputError(f"alpha must be finite and >= 0, got {alpha}.")
    try:
        alpha = xp.broadcast_to(alpha, markers.shape[:-3])
    except ValueError:
        raise InputError(
            f"alpha must be a scalar or broadcast to the batch shape {markers.shape[:-3]}, got shape {alpha.shape}."
        ) from None
    if c0 is None:
        c0_arr, has_c0 = xp.zeros(markers.shape[:-2] + (3,), dtype), False
    else:
        c0_arr, has_c0 = xp.asarray(c0, dtype), True
        if c0_arr.shape != markers.shape[:-2] + (3,):
            raise InputError(f"c0 must be shaped {markers.shape[:-2] + (3,)}, got {c0_arr.shape}.")
        if not traced and not np.all(np.isfinite(c0_arr)):
            raise InputError("c0 contains NaN/inf; give a finite warm start (e.g. the previous solution).")
    if r0 is None:
        r0_arr, has_r0 = xp.zeros(markers.shape[:-3] + (n_markers,), dtype), False
    else:
        r0_arr, has_r0 = xp.asarray(r0, dtype), True
        if r0_arr.shape != markers.shape[:-3] + (n_markers,):
            raise InputError(f"r0 must be shaped {markers.shape[:-3] + (n_markers,)}, got {r0_arr.shape}.")
    return markers, mask, alpha, c0_arr, r0_arr, has_c0, has_r0


@float64_scope
def solve_joints(
    markers: Float[ArrayLike, "*batch F K 3"],
    mask: Bool[ArrayLike, "*batch F K"] | None = None,
    *,
    alpha: float = 0.01,
    method: str = "lm",
    max_steps: int | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    c0: Float[ArrayLike, "*batch F 3"] | None = None,
    r0: Float[ArrayLike, "*batch K"] | None = None,
) -> JointSolution:
    """Joint cost and joint trajectory for a batch of marker-group pairs.

    The batched core used by the topology pass: any leading axes (pairs, trials) are
    flattened and solved by one vmapped, jit-compiled solver, so shapes should be
    padded to bucket sizes (:func:`jaxskel._math.padding.bucket_size`) by the caller; padded frames,
    markers and whole pairs are simply masked out (a fully masked pair returns cost 0,
    no valid frames, ``converged`` True, and never NaN). Every pair iterates until the
    slowest converges, so cap ``max_steps`` for approximate all-pairs costs.
    Also works under ``jax.vmap`` and ``jax.grad`` (see :func:`solve_joint`).

    Parameters
    ----------
    markers
        Marker positions (..., F, K, 3) in metres; entries where ``mask`` is False are
        ignored (NaN allowed there).
    mask
        Presence (..., F, K); default: finite entries of ``markers``.
    alpha
        Weight of the mean-distance prior (1/m), a scalar or one per pair (broadcast to
        the batch shape). Biases the joint toward the markers (centimetres at 0.01 on
        human-sized segments, where alpha * mean distance also dwarfs the variance of a
        true joint); use 0 for the final pass on a known topology when the joint is
        well exercised.
    method
        ``"lm"`` (block-arrow Levenberg–Marquardt) or ``"ncg"`` (nonlinear CG).
    max_steps
        Step cap (default 256 for LM, 20,000 for NCG).
    rtol, atol
        LM: converged when a step moves nothing more than ``atol`` metres, or the cost
        stops decreasing relative to ``rtol``. NCG: optimistix's Cauchy criterion on
        the centred positions and the scaled cost. Defaults 1e-10/1e-9 (float64),
        1e-5/1e-6 (float32).
    c0, r0
        Warm start: joint positions (..., F, 3) and radii (..., K). Defaults: per-frame
        centroid of the markers (a frame missing some is completed from the nearest
        complete frame, so frames are assumed in time order for this only), and the
        mean marker distance from ``c0``.
    """
    markers, mask, alpha_arr, c0_arr, r0_arr, has_c0, has_r0 = _prepare(markers, mask, alpha, c0, r0)
    settings, controls = _settings(method, max_steps, rtol, atol, markers.dtype)
    batch = markers.shape[:-3]
    frames, n_markers = markers.shape[-3], markers.shape[-2]
    flat = _solve_batch(
        markers.reshape((-1, frames, n_markers, 3)),
        mask.reshape((-1, frames, n_markers)),
        alpha_arr.reshape((-1,)),
        c0_arr.reshape((-1, frames, 3)),
        r0_arr.reshape((-1, n_markers)),
        has_c0,
        has_r0,
        controls,
        settings=settings,
    )
    return jax.tree_util.tree_map(lambda leaf: leaf.reshape(batch + leaf.shape[1:]), flat)


@float64_scope
def solve_joint(
    markers: Float[ArrayLike, "F K 3"],
    mask: Bool[ArrayLike, "F K"] | None = None,
    *,
    alpha: float = 0.01,
    method: str = "lm",
    max_steps: int | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    c0: Float[ArrayLike, "F 3"] | None = None,
    r0: Float[ArrayLike, " K"] | None = None,
) -> JointSolution:
    """Place the joint between two marker groups by minimising the Kirk et al. joint cost.

    ``markers`` (F, K, 3) holds the markers of both groups (the cost does not need to
    know which group a marker belongs to); ``mask`` (F, K) their presence. Frames and
    markers are padded to bucket sizes internally so recordings of similar length
    share one compiled solver. Arguments as in :func:`solve_joints`.

    Differentiable: ``jax.grad`` of ``cost``, ``positions`` or ``radii`` with respect to
    ``markers`` (and ``alpha``) uses implicit differentiation through the optimum.

    Raises
    ------
    InputError
        Malformed shapes, NaN where ``mask`` says present, bad options.
    DegenerateMotionError
        No frame has three present markers, so there is nothing to fit.

    Examples
    --------
    >>> sol = solve_joint(markers, alpha=0.0)            # doctest: +SKIP
    >>> sol.cost, sol.converged, sol.undetermined_dims    # doctest: +SKIP
    """
    from .._math.padding import bucket_size

    markers, mask, _, c0, r0, has_c0, has_r0 = _prepare(markers, mask, alpha, c0, r0)
    if markers.ndim != 3:
        raise InputError(f"solve_joint takes one pair (F, K, 3); got {markers.shape}. Use solve_joints for batches.")
    frames, n_markers = markers.shape[:2]
    if not isinstance(mask, jax.core.Tracer):
        most = int(np.max(np.sum(mask, axis=1)))
        if most < _MIN_MARKERS_PER_FRAME:
            raise DegenerateMotionError(
                f"no frame has {_MIN_MARKERS_PER_FRAME} present markers (at most {most}); a joint cannot be "
                "placed. Combine groups with more markers, or fill gaps before fitting."
            )
    xp = np if isinstance(markers, np.ndarray) else jnp
    pad_f, pad_k = bucket_size(frames) - frames, bucket_size(n_markers, minimum=8) - n_markers
    padded = xp.pad(markers, ((0, pad_f), (0, pad_k), (0, 0)))
    padded_mask = xp.pad(mask, ((0, pad_f), (0, pad_k)))
    padded_c0 = xp.pad(c0, ((0, pad_f), (0, 0))) if has_c0 else None
    padded_r0 = xp.pad(r0, ((0, pad_k),)) if has_r0 else None
    sol = solve_joints(
        padded[None],
        padded_mask[None],
        alpha=alpha,
        method=method,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        c0=None if padded_c0 is None else padded_c0[None],
        r0=None if padded_r0 is None else padded_r0[None],
    )
    return JointSolution(
        positions=sol.positions[0, :frames],
        radii=sol.radii[0, :n_markers],
        cost=sol.cost[0],
        variance=sol.variance[0],
        distance_std=sol.distance_std[0, :n_markers],
        steps=sol.steps[0],
        result=sol.result[0],
        converged=sol.converged[0],
        residual=sol.residual[0],
        identifiability=sol.identifiability[0],
        undetermined_dims=sol.undetermined_dims[0],
        uncertainty=sol.uncertainty[0],
        valid_frames=sol.valid_frames[0, :frames],
    )
