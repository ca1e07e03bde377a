"""Batches of trials: inverse kinematics of B recordings of one subject in one call.

A skeleton is fitted once (``fit_skeleton`` on the first recording); then B
recordings of the same body (different motions, seeds 1..B) are posed:

* jaxskel: ``inverse_kinematics(skeleton, (x, mask))`` with x shaped (B, F, M, 3),
  one vmapped call (cold = first call for that B, warm = second);
* reference: :func:`bench.reference.ik.inverse_kinematics` frame by frame with the
  *same* skeleton (so both solve the same problem), timed on ``ref_frames`` frames
  of one recording and scaled to B x F frames (labelled as extrapolated: the
  reference has no batching, its time is linear in frames).

:func:`run_fit_batch` times whole fits of B trials with ``jaxskel.fit_batch``
where the package provides it.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from .memory import PeakRSS

__all__ = ["run_batch", "run_fit_batch", "as_reference_skeleton"]


def as_reference_skeleton(sk):
    """A :class:`bench.reference.rigid.RefSkeleton` with jaxskel's offsets."""
    from .reference.rigid import RefSkeleton

    return RefSkeleton(
        edges=np.asarray(sk.edges), root=int(sk.root), marker_segment=np.asarray(sk.marker_segment),
        marker_offsets=np.asarray(sk.marker_offsets, float), joint_offsets=np.asarray(sk.joint_offsets, float),
        bones=np.asarray(sk.bones), bone_lengths=np.asarray(sk.bone_lengths), bone_segment=np.asarray(sk.bone_segment),
    )


def run_batch(spec: dict) -> dict:
    import jaxskel as js

    from .cases import make_trial
    from .reference.ik import inverse_kinematics as ref_ik

    sizes = list(spec["sizes"])
    first, _ = make_trial(spec, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = js.fit_skeleton(first, seed=0)
    sk = fit.skeleton
    labels = list(sk.marker_labels)
    trials = [make_trial(spec, seed=s)[0] for s in range(1, max(sizes) + 1)]
    arrays = [t.select_markers(labels).to_arrays() for t in trials]
    x_all = np.stack([a[0] for a in arrays])
    m_all = np.stack([a[1] for a in arrays])
    n_frames = x_all.shape[1]

    ref_sk = as_reference_skeleton(sk)
    n_ref = min(int(spec.get("ref_frames", 300)), n_frames)
    start = time.perf_counter()
    ref_ik(ref_sk, x_all[0, :n_ref], m_all[0, :n_ref])
    ref_per_frame = (time.perf_counter() - start) / n_ref

    rows = []
    for b in sizes:
        xb, mb = x_all[:b], m_all[:b]
        with warnings.catch_warnings(), PeakRSS() as mem:
            warnings.simplefilter("ignore")
            start = time.perf_counter()
            js.skeleton.inverse_kinematics(sk, (xb, mb))
            cold = time.perf_counter() - start
            start = time.perf_counter()
            js.skeleton.inverse_kinematics(sk, (xb, mb))
            warm = time.perf_counter() - start
        row = {
            "batch": b, "frames_total": b * n_frames, "jaxskel_cold_s": cold, "jaxskel_warm_s": warm,
            "jaxskel_frames_per_s": b * n_frames / warm, "peak_rss_mb": round(mem.peak_mb, 1),
            "reference_s": ref_per_frame * b * n_frames,
            "reference_extrapolated": f"from {n_ref} frames of one trial",
        }
        row["ratio"] = row["reference_s"] / warm
        rows.append(row)
    return {"data": {"frames_per_trial": n_frames, "markers": len(labels)}, "rows": rows}


def run_fit_batch(spec: dict) -> dict:
    """Whole fits of B trials with ``jaxskel.fit_batch`` (when the package has it) vs B reference fits.

    The reference has no batching: one reference fit of one trial (same size) is
    timed and multiplied by B (labelled as extrapolated).
    """
    import jaxskel as js

    from .cases import make_trial
    from .reference import fit_reference

    try:
        fit_batch = js.fit_batch
    except (AttributeError, ImportError) as exc:
        return {"fit_batch_available": False, "reason": repr(exc), "rows": []}
    sizes = list(spec["sizes"])
    trials = [make_trial(spec, seed=s)[0] for s in range(1, max(sizes) + 1)]
    start = time.perf_counter()
    fit_reference(np.asarray(trials[0].positions), trials[0].rate, ik_frames=int(spec.get("ref_ik_frames", 300)))
    ref_one = time.perf_counter() - start
    rows = []
    for b in sizes:
        with warnings.catch_warnings(), PeakRSS() as mem:
            warnings.simplefilter("ignore")
            start = time.perf_counter()
            fit_batch(trials[:b], batch_size=b)
            cold = time.perf_counter() - start
            start = time.perf_counter()
            fit_batch(trials[:b], batch_size=b)
            warm = time.perf_counter() - start
        rows.append({"batch": b, "jaxskel_cold_s": cold, "jaxskel_warm_s": warm, "peak_rss_mb": round(mem.peak_mb, 1),
                     "reference_s": ref_one * b, "ratio": ref_one * b / warm,
                     "reference_extrapolated": "one reference fit (IK on 300 frames, scaled) x B"})
    return {"fit_batch_available": True, "data": {"frames_per_trial": trials[0].n_frames}, "rows": rows}
