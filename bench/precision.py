"""Float32 vs float64: does each stage honour float32 input, how fast is it, how accurate?

jaxskel turns on JAX's 64-bit mode on import and documents that float32 inputs
compute in float32. Here the same recording is fitted stage by stage twice, once
from a float64 :class:`jaxskel.Trial` and once from the same positions as float32
(each stage gets the previous stage's float32-chain output). Per stage:

* ``output_dtype``: the floating dtype of the stage's main output array;
* ``float32_honoured``: the output is float32 (a float64 output from float32 input
  means the stage converted to float64 somewhere, e.g. ``Trial.to_arrays()``,
  whose default dtype is float64);
* ``max_abs_diff``: largest difference of that output between the two chains
  (0 = the float32 chain computed exactly what the float64 one did);
* warm wall seconds of both chains (each chain runs twice; the second is timed);
* accuracy of both chains against the ground truth.

Because the public stages turned out to convert to float64 (see the record), the
numerical kernels are also timed directly in both precisions, on the arrays the
float64 chain built: the all-pairs joint solve (``jaxskel.joints.solve_joints`` on the
first 64 candidate pairs x 300 frames, as one chunk of ``joint_costs``), the tree
joints on all frames (``solve_joints``), and the IK core (``jaxskel.skeleton._ik._ik_frames``
with an ``ik_model`` of that dtype). Per kernel: warm seconds, output dtype, and the
result's difference from float64 (pair costs: largest relative difference; joints:
largest distance in metres; IK: largest joint-centre distance).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from .accuracy import evaluate
from .pipeline import ALPHA, TOPOLOGY_FRAMES

__all__ = ["run_precision"]


def _chain(trial):
    """The stages in fit_skeleton's order; (outputs, warm seconds) of the second of two runs."""
    import jaxskel as js
    from jaxskel.skeleton._rigid_fit import SOLVED_JOINT_WEIGHT

    for _ in range(2):
        times, out = {}, {}

        def timed(name, fn):
            start = time.perf_counter()
            value = fn()
            times[name] = time.perf_counter() - start
            return value

        cleaned, _ = timed("clean", lambda: js.clean.clean(trial))
        seg = timed("segment", lambda: js.segment.segment_markers(cleaned, None, seed=0))
        pairs = timed("joint_costs", lambda: js.joints.joint_costs(cleaned, seg, alpha=ALPHA, max_frames=TOPOLOGY_FRAMES))
        topo = timed("tree_joints", lambda: js.joints.fit_topology(cleaned, seg, pairs, alpha=ALPHA))
        sk = timed("rigid", lambda: js.skeleton.fit_rigid(
            cleaned, seg.marker_segment, topo.edges, topo.joint_positions, root=topo.root,
            sliding_joints=topo.undetermined > 0, joint_weight=SOLVED_JOINT_WEIGHT,
        ))
        motion = timed("ik", lambda: js.skeleton.inverse_kinematics(sk, cleaned))
        out = {"trial": cleaned, "segmentation": seg, "pairs": pairs, "topology": topo, "skeleton": sk, "motion": motion}
    return out, times


def _main_array(stage: str, out: dict) -> np.ndarray:
    return {
        "clean": lambda: out["trial"].positions,
        "segment": lambda: out["segmentation"].distance_std,
        "joint_costs": lambda: np.asarray([v for v in out["pairs"].positions.values()]),
        "tree_joints": lambda: out["topology"].joint_positions,
        "rigid": lambda: out["skeleton"].marker_offsets,
        "ik": lambda: out["motion"].joint_positions,
    }[stage]()


def _best_of(fn, repeat: int = 2):
    import jax

    out = jax.block_until_ready(fn())  # compile
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return out, best


def kernel_precision(out: dict) -> dict:
    """The joint-solve and IK kernels called directly with float32 and float64 arrays."""

    import jaxskel as js
    from jaxskel.skeleton._ik import DEFAULT_PRIOR_WEIGHT
    from jaxskel.skeleton._ik_batch import batch_model, solve
    from jaxskel.joints._topology import PAIR_CHUNK, pair_arrays
    from jaxskel._math.padding import bucket_size

    trial, seg, topo, sk = out["trial"], out["segmentation"], out["topology"], out["skeleton"]
    x, mask = trial.to_arrays()
    ms = np.asarray(seg.marker_segment)
    sizes = np.bincount(ms, minlength=seg.n_segments)
    pairs = np.array([(a, b) for a in range(seg.n_segments) for b in range(a + 1, seg.n_segments)
                      if sizes[a] + sizes[b] >= 4][:PAIR_CHUNK])
    stride = max(1, int(np.ceil(trial.n_frames / TOPOLOGY_FRAMES)))
    frames = np.arange(0, trial.n_frames, stride)
    k_pad = bucket_size(int(max(sizes[a] + sizes[b] for a, b in pairs)), minimum=4, steps_per_octave=1)
    xs, mks = pair_arrays(x, mask, ms, pairs, frames, k_pad, bucket_size(len(frames)))
    edges = np.sort(np.asarray(topo.edges), axis=1)
    k_tree = bucket_size(int(max(sizes[a] + sizes[b] for a, b in edges)), minimum=4, steps_per_octave=1)
    xt, mt = pair_arrays(x, mask, ms, edges, np.arange(trial.n_frames), k_tree, bucket_size(trial.n_frames))
    labels = list(sk.marker_labels)
    xi, mi = trial.select_markers(labels).to_arrays()
    m_pad = bucket_size(len(labels), minimum=8)
    f_pad = bucket_size(trial.n_frames)
    xip = np.zeros((f_pad, m_pad, 3))
    mip = np.zeros((f_pad, m_pad), bool)
    xip[: trial.n_frames, : len(labels)], mip[: trial.n_frames, : len(labels)] = xi, mi

    results: dict = {}
    for dtype in (np.float64, np.float32):
        name = np.dtype(dtype).name
        pair_sol, pair_s = _best_of(lambda: js.joints.solve_joints(xs.astype(dtype), mks, alpha=ALPHA, max_steps=100))
        tree_sol, tree_s = _best_of(lambda: js.joints.solve_joints(xt.astype(dtype), mt, alpha=ALPHA, max_steps=200))
        model = batch_model(sk.edges, sk.joint_offsets, sk.marker_offsets, sk.marker_segment, dtype=dtype)
        prior_weight = np.full((sk.n_segments,), DEFAULT_PRIOR_WEIGHT, dtype)
        ik_out, ik_s = _best_of(lambda: solve(model, xip.astype(dtype), mip, None, None, None, prior_weight,
                                              max_steps=100))
        results[name] = {
            "pairs": (np.asarray(pair_sol.cost), pair_s, str(pair_sol.cost.dtype)),
            "tree": (np.asarray(tree_sol.positions)[:, : trial.n_frames], tree_s, str(tree_sol.positions.dtype)),
            "ik": (ik_out["joint_positions"][: trial.n_frames], ik_s, str(ik_out["joint_positions"].dtype)),
        }
    a, b = results["float64"], results["float32"]
    cost64, cost32 = a["pairs"][0], b["pairs"][0].astype(float)
    ok = np.abs(cost64) > 0
    return {
        "pairs": {"pairs": len(pairs), "frames": len(frames), "warm_s_float64": a["pairs"][1], "warm_s_float32": b["pairs"][1],
                  "output_dtype_float32": b["pairs"][2],
                  "max_rel_cost_diff": float(np.max(np.abs(cost32[ok] - cost64[ok]) / cost64[ok]))},
        "tree": {"joints": len(edges), "frames": trial.n_frames, "warm_s_float64": a["tree"][1], "warm_s_float32": b["tree"][1],
                 "output_dtype_float32": b["tree"][2],
                 "max_joint_diff_m": float(np.nanmax(np.linalg.norm(a["tree"][0] - b["tree"][0].astype(float), axis=-1)))},
        "ik": {"frames": trial.n_frames, "warm_s_float64": a["ik"][1], "warm_s_float32": b["ik"][1],
               "output_dtype_float32": b["ik"][2],
               "max_joint_diff_m": float(np.nanmax(np.linalg.norm(a["ik"][0] - b["ik"][0].astype(float), axis=-1)))},
    }


def run_precision(spec: dict) -> dict:
    """Run both chains on one case (``duration`` s full body) and compare them."""
    import jaxskel as js

    from .cases import make_trial

    trial, truth = make_trial(spec)
    trial32 = js.Trial(
        positions=np.asarray(trial.positions, dtype=np.float32), labels=trial.labels, rate=trial.rate,
        up_axis=trial.up_axis, source=trial.source,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out64, t64 = _chain(trial)
        out32, t32 = _chain(trial32)
    stages = {}
    for stage in t64:
        a64, a32 = _main_array(stage, out64), _main_array(stage, out32)
        same_shape = a64.shape == a32.shape
        diff = float(np.nanmax(np.abs(a64.astype(np.float64) - a32.astype(np.float64)))) if same_shape and a64.size else None
        stages[stage] = {
            "output_dtype": str(a32.dtype),
            "float32_honoured": a32.dtype == np.float32,
            "max_abs_diff": diff,
            "warm_s_float64": t64[stage],
            "warm_s_float32": t32[stage],
        }

    def accuracy(out):
        sk, mo, topo = out["skeleton"], out["motion"], out["topology"]
        return evaluate(
            truth, out["trial"].labels, out["segmentation"].marker_segment, edges=topo.edges,
            joint_positions=topo.joint_positions, bones=sk.bones, bone_lengths=sk.bone_lengths,
            ik_joints=mo.joint_positions, ik_marker_rms=mo.marker_rms,
        )

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kernels = kernel_precision(out64)
    return {
        "data": {"frames": trial.n_frames, "markers": trial.n_markers},
        "stages": stages,
        "kernels": kernels,
        "accuracy_float64": accuracy(out64),
        "accuracy_float32": accuracy(out32),
    }
