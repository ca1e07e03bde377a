"""Reference cleaning and segmentation (Kirk et al. 2005, §3.1) in numpy/scipy/scikit-learn.

Cleaning (a simple version of the same rules): a sample further than
``max(2 cm, 8 robust std)`` from the running median of its trajectory
(``scipy.ndimage.median_filter``, 0.1 s window) is a jump; ``trim_s`` is trimmed at
gap edges; markers whose longest run is under 0.5 s are dropped.

Segmentation: standard deviation over jittered sampled frames (every 0.5 s +- 0.1 s)
of every pairwise marker distance (masked numpy), Gaussian affinity with
``sigma = max(3 mm, 2 x noise floor)``, the number of segments at the largest
eigengap of the normalised affinity, ``sklearn.cluster.SpectralClustering`` on each
of ``n_samplings`` samplings, and the clustering with the lowest within-segment
spread on the median std-dev matrix is kept (the paper's RANSAC-style choice).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import median_filter

__all__ = ["clean", "distance_std", "segment"]


def _runs(present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop indices of the True runs of a 1-D boolean array."""
    p = np.concatenate([[False], present, [False]]).astype(np.int8)
    d = np.diff(p)
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def clean(
    x: np.ndarray, mask: np.ndarray, rate: float, *, trim_s: float = 0.02, min_run_s: float = 0.5,
    jump_threshold: float = 0.02, window_s: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, mask, kept marker indices) after jump rejection, gap-edge trimming and short-marker removal."""
    mask = mask.copy()
    half = max(2, int(round(0.5 * window_s * rate)))
    filled = np.where(mask[..., None], x, np.nan)
    # fill gaps by the previous sample so the running median stays defined (simple, host-side)
    for m in range(x.shape[1]):
        idx = np.where(mask[:, m], np.arange(x.shape[0]), 0)
        np.maximum.accumulate(idx, out=idx)
        filled[:, m] = x[idx, m]
    med = median_filter(filled, size=(2 * half + 1, 1, 1), mode="nearest")
    dev = np.linalg.norm(filled - med, axis=-1)
    dev = np.where(mask, dev, np.nan)
    centre = np.nanmedian(dev, axis=0)
    spread = 1.4826 * np.nanmedian(np.abs(dev - centre), axis=0)
    mask &= ~(dev > np.maximum(jump_threshold, centre + 8 * spread))
    trim = max(1, int(round(trim_s * rate))) if trim_s > 0 else 0
    keep = []
    for m in range(x.shape[1]):
        starts, stops = _runs(mask[:, m])
        for a, b in zip(starts, stops):
            lo = a + trim if a > 0 else a
            hi = b - trim if b < x.shape[0] else b
            mask[a:max(lo, a), m] = False
            mask[min(hi, b):b, m] = False
            if hi <= lo:
                mask[a:b, m] = False
        starts, stops = _runs(mask[:, m])
        if len(starts) and (stops - starts).max() >= min_run_s * rate:
            keep.append(m)
    keep = np.asarray(keep, int)
    return np.where(mask[..., None], x, 0.0)[:, keep], mask[:, keep], keep


def distance_std(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Std-dev over frames of every pairwise distance (M, M) and the frame counts, masked."""
    d = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=-1)
    w = (mask[:, :, None] & mask[:, None, :]).astype(float)
    n = w.sum(0)
    mean = (w * d).sum(0) / np.maximum(n, 1)
    var = (w * (d - mean) ** 2).sum(0) / np.maximum(n, 1)
    return np.sqrt(var), n


def _sample(n_frames: int, rate: float, rng: np.random.Generator, min_samples: int = 40) -> np.ndarray:
    step = 0.5 * rate
    if n_frames / step < min_samples:
        step = max(1.0, n_frames / min_samples)
    base = np.arange(0.5 * step, n_frames, step)
    jitter = min(0.1 * rate, 0.45 * step)
    return np.unique(np.clip(np.rint(base + rng.uniform(-jitter, jitter, base.shape)).astype(int), 0, n_frames - 1))


def segment(
    x: np.ndarray, mask: np.ndarray, rate: float, n_segments: int | None = None, *,
    n_samplings: int = 8, min_cooccur: int = 5, max_segments: int = 30, seed: int = 0,
) -> np.ndarray:
    """(M,) segment index of every marker, numbered in order of first marker."""
    from sklearn.cluster import SpectralClustering

    m = x.shape[1]
    rng = np.random.default_rng(seed)
    stds, counts = [], []
    for _ in range(n_samplings):
        frames = _sample(x.shape[0], rate, rng)
        a, n = distance_std(x[frames], mask[frames])
        stds.append(a)
        counts.append(n)
    stds, counts = np.asarray(stds), np.asarray(counts)
    observed_all = counts >= min_cooccur
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a_med = np.nanmedian(np.where(observed_all, stds, np.nan), axis=0)
    observed = ~np.isnan(a_med) | np.eye(m, dtype=bool)
    a_med = np.where(observed, np.nan_to_num(a_med), 0.0)
    off = np.where(observed & ~np.eye(m, dtype=bool), a_med, np.inf).min(1)
    sigma = max(0.003, 2.0 * float(np.median(off[np.isfinite(off)])))

    def affinity(a, obs):
        w = np.where(obs, np.exp(-0.5 * (a / sigma) ** 2), 0.0)
        np.fill_diagonal(w, 1.0)
        return w + 1e-9

    if n_segments is None:
        w = affinity(a_med, observed)
        dinv = 1.0 / np.sqrt(w.sum(1))
        ev = np.linalg.eigvalsh(dinv[:, None] * w * dinv[None])[::-1][: min(m, max_segments + 2)]
        kmax = min(max_segments, len(ev) - 1)
        n_segments = int(np.argmax(ev[1:kmax] - ev[2 : kmax + 1])) + 2
    best, best_score = None, np.inf
    for r in range(n_samplings):
        obs_r = observed_all[r] | np.eye(m, dtype=bool)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            labels = SpectralClustering(
                n_clusters=n_segments, affinity="precomputed", assign_labels="cluster_qr", random_state=seed + r
            ).fit_predict(affinity(np.where(obs_r, stds[r], 0.0), obs_r))
        score = 0.0
        for g in np.unique(labels):
            idx = np.flatnonzero(labels == g)
            block = a_med[np.ix_(idx, idx)]
            score += block[np.triu_indices(len(idx), 1)].sum() / len(idx)
        if score < best_score:
            best, best_score = labels, score
    order: dict[int, int] = {}
    for lab in best:
        order.setdefault(int(lab), len(order))
    return np.array([order[int(lab)] for lab in best], int)
