"""The pipeline case: jaxskel and the reference on one recording, stage by stage and whole.

jaxskel, in a fresh process (so the first call compiles):

* with the whole fit selected: ``fit_skeleton`` twice; the first call's
  ``result.timings`` are the *cold* stage times (tracing + XLA compilation + run),
  the second call's the *warm* ones, and the second call's wall time is the warm
  whole fit;
* otherwise the public stage functions (``clean``, ``segment_markers``,
  ``joint_costs``, ``fit_topology``, ``fit_rigid``, ``inverse_kinematics``) are
  called in the same order with the same arguments as ``fit_skeleton`` uses, twice.

The reference (:mod:`bench.reference`) runs once (numpy has nothing to compile)
on the same trial, in the same process, after jaxskel. Wall and CPU seconds are
both recorded: on a shared machine the CPU time says how much work a call is.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from .accuracy import evaluate, same_topology
from .memory import PeakRSS, device_peak_mb

__all__ = ["STAGES", "run_case"]

#: Stages of the chain, in order, with jaxskel's ``result.timings`` names.
STAGES = {
    "clean": "clean",
    "segment": "segment",
    "joint_costs": "joint costs",
    "tree_joints": "tree joints",
    "rigid": "rigid",
    "ik": "ik",
}
ALPHA = 1e-5
TOPOLOGY_FRAMES = 300


def _clock():
    return time.perf_counter(), time.process_time()


def _since(start) -> tuple[float, float]:
    return time.perf_counter() - start[0], time.process_time() - start[1]


def _jaxskel_stages(trial, upto: str) -> tuple[dict, dict, dict]:
    """Run the stages up to ``upto`` by their public functions; (outputs, wall s, cpu s)."""
    import jaxskel as js
    from jaxskel.skeleton._rigid_fit import SOLVED_JOINT_WEIGHT

    order = list(STAGES)
    stop = order.index(upto)
    out, wall, cpu = {}, {}, {}

    def timed(name, fn):
        start = _clock()
        value = fn()
        wall[name], cpu[name] = _since(start)
        return value

    cleaned, _ = timed("clean", lambda: js.clean.clean(trial))
    out["trial"] = cleaned
    out["segmentation"] = seg = timed("segment", lambda: js.segment.segment_markers(cleaned, None, seed=0))
    if stop >= 2:
        out["pairs"] = pairs = timed(
            "joint_costs", lambda: js.joints.joint_costs(cleaned, seg, alpha=ALPHA, max_frames=TOPOLOGY_FRAMES)
        )
    if stop >= 3:
        out["topology"] = topo = timed("tree_joints", lambda: js.joints.fit_topology(cleaned, seg, pairs, alpha=ALPHA))
    if stop >= 4:
        out["skeleton"] = sk = timed(
            "rigid",
            lambda: js.skeleton.fit_rigid(  # as fit_skeleton calls it
                cleaned, seg.marker_segment, topo.edges, topo.joint_positions, root=topo.root,
                sliding_joints=topo.undetermined > 0, joint_weight=SOLVED_JOINT_WEIGHT,
            ),
        )
    if stop >= 5:
        out["motion"] = timed("ik", lambda: js.skeleton.inverse_kinematics(sk, cleaned))
    return out, wall, cpu


def run_jaxskel(trial, upto: str, whole: bool) -> dict:
    """Cold and warm timings, memory and outputs of jaxskel on ``trial``."""
    import jaxskel as js

    res: dict = {"stages": {}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if whole:
            with PeakRSS() as mem_cold:
                start = _clock()
                cold = js.fit_skeleton(trial, seed=0, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES)
                cold_s, cold_cpu = _since(start)
            with PeakRSS() as mem_warm:
                start = _clock()
                warm = js.fit_skeleton(trial, seed=0, alpha=ALPHA, topology_frames=TOPOLOGY_FRAMES)
                warm_s, warm_cpu = _since(start)
            res["fit"] = {"cold_s": cold_s, "warm_s": warm_s, "cold_cpu_s": cold_cpu, "warm_cpu_s": warm_cpu}
            for name, key in STAGES.items():
                res["stages"][name] = {"cold_s": cold.timings[key], "warm_s": warm.timings[key]}
            outputs = {
                "trial": warm.trial, "segmentation": warm.segmentation, "pairs": warm.topology.pair_costs,
                "topology": warm.topology, "skeleton": warm.skeleton, "motion": warm.motion,
            }
        else:
            with PeakRSS() as mem_cold:
                _, cold_wall, _ = _jaxskel_stages(trial, upto)
            with PeakRSS() as mem_warm:
                outputs, warm_wall, warm_cpu = _jaxskel_stages(trial, upto)
            for name in warm_wall:
                res["stages"][name] = {"cold_s": cold_wall[name], "warm_s": warm_wall[name], "warm_cpu_s": warm_cpu[name]}
    res["memory"] = {"cold": mem_cold.as_dict(), "warm": mem_warm.as_dict(), "device_peak_mb": device_peak_mb()}
    res["outputs"] = outputs
    return res


def run_reference(trial, upto: str, options: dict) -> dict:
    """Timings, memory and outputs of the reference chain on ``trial``."""
    from .reference import fit_reference

    stages = tuple(list(STAGES)[: list(STAGES).index(upto) + 1])
    with PeakRSS() as mem:
        start = _clock()
        out = fit_reference(
            np.asarray(trial.positions, dtype=np.float64), trial.rate, alpha=ALPHA,
            topology_frames=TOPOLOGY_FRAMES, stages=stages, seed=0, **options,
        )
        total, total_cpu = _since(start)
    res = {
        "stages": {
            name: {"s": out["timings"][name], "cpu_s": out["cpu"][name], "extrapolated": out["extrapolated"].get(name)}
            for name in stages
            if name in out["timings"]
        },
        "memory": mem.as_dict(),
        "outputs": out,
    }
    res["fit"] = {
        "s": sum(v["s"] for v in res["stages"].values()),
        "cpu_s": sum(v["cpu_s"] for v in res["stages"].values()),
        "measured_s": total,
        "extrapolated": "; ".join(f"{k} {v}" for k, v in out["extrapolated"].items()) or None,
    }
    return res


def _jaxskel_accuracy(outputs: dict, truth) -> dict:
    t = outputs["trial"]
    seg = outputs["segmentation"]
    kw: dict = {}
    if "topology" in outputs:
        topo = outputs["topology"]
        kw.update(edges=topo.edges, joint_positions=topo.joint_positions)
    if outputs.get("skeleton") is not None:
        sk = outputs["skeleton"]
        kw.update(bones=sk.bones, bone_lengths=sk.bone_lengths)
    if outputs.get("motion") is not None:
        mo = outputs["motion"]
        kw.update(ik_joints=mo.joint_positions, ik_marker_rms=mo.marker_rms)
    return evaluate(truth, t.labels, seg.marker_segment, **kw)


def _reference_accuracy(out: dict, trial, truth) -> dict:
    labels = [trial.labels[i] for i in out["kept_markers"]]
    kw: dict = {}
    if "joint_positions" in out:
        kw.update(edges=out["edges"], joint_positions=out["joint_positions"], joint_frames=out["joint_frames"])
    if "skeleton" in out:
        sk = out["skeleton"]
        kw.update(bones=sk.bones, bone_lengths=sk.bone_lengths)
    if "motion" in out:
        mo = out["motion"]
        kw.update(ik_joints=mo["joints"], ik_frames=mo["frames"], ik_marker_rms=mo["marker_rms"])
    return evaluate(truth, labels, out["marker_segment"], **kw)


def _agreement(jx: dict, ref: dict, trial) -> dict:
    """Do jaxskel and the reference find the same grouping, tree and pair costs?"""
    from sklearn.metrics import adjusted_rand_score

    seg = jx["segmentation"]
    ref_labels = [trial.labels[i] for i in ref["kept_markers"]]
    common = [lab for lab in seg.labels if lab in set(ref_labels)]
    j_of = dict(zip(seg.labels, seg.marker_segment))
    r_of = dict(zip(ref_labels, ref["marker_segment"]))
    out = {
        "markers_kept": [len(seg.labels), len(ref_labels)],
        "segmentation_ari": round(float(adjusted_rand_score([j_of[c] for c in common], [r_of[c] for c in common])), 4),
    }
    if "topology" in jx and "edges" in ref:
        # name every segment by the other implementation's segment holding most of its markers
        r_map = np.zeros(int(max(r_of.values())) + 1, int)
        for s in range(len(r_map)):
            votes = [j_of[lab] for lab in common if r_of[lab] == s]
            r_map[s] = np.bincount(votes).argmax() if votes else -1
        ident = np.arange(seg.n_segments)
        out["same_topology"] = bool(
            len(set(r_map.tolist())) == len(r_map) and same_topology(jx["topology"].edges, ident, ref["edges"], r_map)
        )
        j_cost = jx["pairs"].cost
        rel = []
        for a in range(len(r_map)):
            for b in range(a + 1, len(r_map)):
                ja, jb = r_map[a], r_map[b]
                if min(ja, jb) >= 0 and np.isfinite(ref["pair_cost"][a, b]) and np.isfinite(j_cost[ja, jb]):
                    rel.append((ref["pair_cost"][a, b] - j_cost[ja, jb]) / j_cost[ja, jb])
        if rel:
            rel = np.asarray(rel)
            out["pair_cost_rel_diff"] = {
                "median": round(float(np.median(rel)), 4),
                "reference_lower_fraction": round(float(np.mean(rel < -1e-3)), 3),
                "jaxskel_lower_fraction": round(float(np.mean(rel > 1e-3)), 3),
            }
    return out


def run_case(spec: dict, only: set[str] | None) -> dict:
    """Run one pipeline case (spec from :mod:`bench.cases`)."""
    from .cases import make_trial

    trial, truth = make_trial(spec)
    upto = spec.get("stages_upto", "ik")
    if only:
        chosen = [s for s in STAGES if s in only]
        if chosen and "fit" not in only:
            upto = chosen[-1] if list(STAGES).index(chosen[-1]) < list(STAGES).index(upto) else upto
    whole = upto == "ik" and (not only or "fit" in only or not ({*STAGES} & only))
    record: dict = {
        "data": {
            "frames": trial.n_frames, "markers": trial.n_markers, "segments": len(truth.segment_names),
            "rate_hz": trial.rate, "duration_s": trial.n_frames / trial.rate,
        },
    }
    jx = run_jaxskel(trial, upto, whole)
    ref = run_reference(trial, upto, spec.get("ref", {}))
    record["jaxskel"] = {k: v for k, v in jx.items() if k != "outputs"}
    record["reference"] = {k: v for k, v in ref.items() if k != "outputs"}
    record["jaxskel"]["accuracy"] = _jaxskel_accuracy(jx["outputs"], truth)
    record["reference"]["accuracy"] = _reference_accuracy(ref["outputs"], trial, truth)
    record["agreement"] = _agreement(jx["outputs"], ref["outputs"], trial)
    topo = jx["outputs"].get("topology")
    if topo is not None:
        record["jaxskel"]["solver"] = {
            "pair_steps_max": int(np.max(jx["outputs"]["pairs"].steps)),
            "tree_steps": [int(s) for s in topo.steps],
            "tree_converged": int(np.sum(topo.converged)),
        }
    mo = jx["outputs"].get("motion")
    if mo is not None:
        record["jaxskel"]["ik_frames_per_s"] = trial.n_frames / record["jaxskel"]["stages"]["ik"]["warm_s"]
        ref_ik = record["reference"]["stages"].get("ik")
        if ref_ik:
            record["reference"]["ik_frames_per_s"] = trial.n_frames / ref_ik["s"]
    return record
