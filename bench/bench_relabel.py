"""Benchmark merge_labels (Kirk et al. §4): a relabelled 30 s full-body recording on 2 CPU cores.

Data: ``jaxskel.synth.full_body`` (46 markers) walking for 30 s at 120 Hz with 2 gaps
per marker, every marker relabelled after each gap (a passive tracker), 1 mm noise,
5 mm soft-tissue artefact and 10 ghost markers: about 150 labels.

Figures:

* ``merge_labels cold``: the first call in the process, JIT compilation included.
* ``merge_labels warm``: the same call again (compiled kernels reused).
* ``coarse D (jax)`` vs ``coarse D (numpy)``: the paper's all-pairs pass over the
  sampled frames -- jaxskel's tiled, jit-compiled kernel against a plain numpy
  version of the same sum (batched SVD Horn per frame pair, dense (M, M) distances),
  on the same samples; their results must agree.
* accuracy: fraction of labels assigned to the right physical marker (one-to-one
  matching of merged to true markers; a dropped ghost counts as right).

The process is pinned to ``--cores`` cores (default 2) before JAX starts.

Usage::

    python bench/bench_relabel.py              # 30 s recording, prints a table
    python bench/bench_relabel.py --quick      # 8 s recording, for CI
    python bench/bench_relabel.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import time


def _pin(cores: int) -> None:
    if hasattr(os, "sched_setaffinity"):
        available = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, set(available[:cores]))


def numpy_coarse_distance(xs: "np.ndarray", ms: "np.ndarray", min_common: int) -> "np.ndarray":
    """Reference: min over all pairs of sampled frames of |x_a[i] - A_ab x_b[j]| in plain numpy."""
    import numpy as np

    n_samples, n_markers = ms.shape
    best = np.full((n_markers, n_markers), np.inf)
    for a in range(n_samples):  # numpy reference: vectorised over b, looped over a
        b = np.arange(n_samples)
        b = b[b != a]
        w = (ms[a][None] & ms[b]).astype(float)  # (B, M)
        wn = w / np.maximum(w.sum(axis=1, keepdims=True), 1.0)
        mu_t = wn @ xs[a]  # (B, 3)
        mu_s = np.einsum("bm,bmi->bi", wn, xs[b])
        cov = np.einsum("bm,bmi,bmj->bij", wn, xs[a][None] - mu_t[:, None], xs[b] - mu_s[:, None])
        u, _, vt = np.linalg.svd(cov)
        d = np.sign(np.linalg.det(u @ vt))
        rot = np.einsum("bij,bj,bjk->bik", u, np.stack([np.ones_like(d), np.ones_like(d), d], -1), vt)
        moved = np.einsum("bij,bmj->bmi", rot, xs[b] - mu_s[:, None]) + mu_t[:, None]
        dist = np.linalg.norm(xs[a][None, :, None] - moved[:, None, :, :], axis=-1)  # (B, M, M)
        ok = ms[a][None, :, None] & ms[b][:, None, :] & (w.sum(axis=1) >= min_common)[:, None, None]
        best = np.minimum(best, np.where(ok, dist, np.inf).min(axis=0))
    return np.minimum(best, best.T)


def measure(duration: float = 30.0) -> dict:
    """Figures of one run (see the module docstring) on a ``duration`` s relabelled walk."""
    import numpy as np
    from scipy.optimize import linear_sum_assignment

    import jaxskel
    from jaxskel import synth
    from jaxskel.relabel._fragments import fragment_arrays, split_fragments
    from jaxskel.relabel._search import sampled_distance

    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(
        body, motion="walk", duration=duration, rate=120.0, seed=0, noise=0.001,
        soft_tissue=0.005, gaps=2, ghosts=10, relabel=True,
    )  # fmt: skip

    start = time.perf_counter()
    merged, mapping = jaxskel.relabel.merge_labels(trial)
    cold = time.perf_counter() - start
    start = time.perf_counter()
    merged, mapping = jaxskel.relabel.merge_labels(trial)
    warm = time.perf_counter() - start

    pred, true = mapping.physical, truth.physical
    overlap = np.array(
        [[np.sum((pred == p) & (true == t)) for t in range(body.n_markers)]
         for p in range(mapping.n_physical)]
    )
    rows, cols = linear_sum_assignment(-overlap)
    accuracy = (overlap[rows, cols].sum() + np.sum((pred < 0) & (true < 0))) / true.size

    # The coarse pass on its own, jax vs numpy, on the same sampled frames.
    x, present = trial.to_arrays()
    frags = split_fragments(present, x, 15.0 / trial.rate)
    xf, mf = fragment_arrays(x, frags)
    interval = round(0.25 * trial.rate)
    sampled_distance(xf, mf, frags, interval, 4)  # compile
    start = time.perf_counter()
    d_jax, _, _, n_samples = sampled_distance(xf, mf, frags, interval, 4)
    coarse_jax = time.perf_counter() - start
    grid = np.arange(0, xf.shape[0], interval)
    missed = ~mf[grid].any(axis=0)
    samples = np.unique(np.concatenate([grid, (frags.start + frags.stop)[missed] // 2]))
    samples = samples[mf[samples].sum(axis=1) >= 4]
    start = time.perf_counter()
    d_np = numpy_coarse_distance(xf[samples], mf[samples], 4)
    coarse_np = time.perf_counter() - start
    # Compare where the fragments never co-occur (the only entries merging uses).
    apart = (frags.start[:, None] >= frags.stop[None]) | (frags.start[None] >= frags.stop[:, None])
    finite = np.isfinite(d_np) & apart
    agreement = float(np.abs(d_jax[finite] - d_np[finite]).max())

    return {
        "recording_s": duration,
        "rate_hz": trial.rate,
        "labels": trial.n_markers,
        "fragments": mapping.n_fragments,
        "physical_true": body.n_markers,
        "physical_found": mapping.n_physical,
        "accuracy": float(accuracy),
        "merge_cold_s": cold,
        "merge_warm_s": warm,
        "coarse_jax_s": coarse_jax,
        "coarse_numpy_s": coarse_np,
        "coarse_speedup": coarse_np / coarse_jax,
        "coarse_max_abs_diff_m": agreement,
        "sampled_frames": n_samples,
        "candidate_pairs": mapping.diagnostics["n_candidate_pairs"],
        "passes": mapping.diagnostics["passes"],
        **{f"stage_{k}_s": v for k, v in mapping.diagnostics["seconds"].items()},
    }


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="8 s recording")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()
    _pin(args.cores)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    figures = {**measure(8.0 if args.quick else 30.0), "cores": args.cores}
    width = max(map(len, figures))
    for key, value in figures.items():
        print(f"{key:<{width}}  {value:.4g}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=2)


if __name__ == "__main__":
    main()
