"""Benchmark of normalisation and parameterisation (Sar Dessai et al. 2006, §5).

The paper: a full body of 11 joints and 12 limbs, 24,000 frames: normalisation
0.955 s (0.449 s of it per-frame reorientation), parameterisation 37.2 s (28.1 s
per-frame angles), on a 2.8 GHz Pentium 4.

Here: the synthetic adult without head and hands (12 segments, 11 joints), 200 s
at 120 Hz. Timings are warm (compiled) medians; the first call (tracing and
compiling) is reported separately. A plain numpy reference of the same per-frame
work (default-pose cost, limb-frame propagation; swing/twist angles with a Python
loop for the smooth candidate choice) runs in the same process for a ratio and
an agreement check. An accuracy table compares direction joining with the
PCA and EM baselines on paper-style calibrations (main movements one at a time,
IK-like rotation noise).

    python bench/bench_params.py            # full run
    python bench/bench_params.py --quick    # 2,400 frames, one seed (CI)
    python bench/bench_params.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # calibration_motions

from calibration_motions import main_movements, perturbed, truth_arrays  # noqa: E402
from jaxskel import synth  # noqa: E402
from jaxskel._math.rotation import matrix_to_quat, quat_conjugate, quat_multiply  # noqa: E402
from jaxskel.sd06._normalize import normalize_arrays, tree_arrays  # noqa: E402
from jaxskel.sd06._parameterize import parameterize_normalized  # noqa: E402

DROPPED = ("head", "l_hand", "r_hand")


def paper_skeleton(n_frames: int, seed: int = 0):
    """Joint centres, edges and quaternions of an 11-joint, 12-limb body (the paper's setup)."""
    body = synth.full_body(seed=seed)
    _, truth = synth.simulate(body, "calibration", duration=n_frames / 120.0, rate=120.0, seed=seed)
    keep = [s for s, name in enumerate(body.segment_names) if name not in DROPPED]
    index = {s: k for k, s in enumerate(keep)}
    joints = [j for j, (p, c) in enumerate(body.edges) if c in index]
    edges = np.array([[index[body.edges[j, 0]], index[body.edges[j, 1]]] for j in joints])
    quats = np.asarray(matrix_to_quat(truth.segment_rotations[:, keep]))
    return truth.joint_positions[:, joints], edges, quats


def timed(fn, repeats: int) -> tuple[float, float, float, object]:
    """(first call seconds, warm median wall seconds, warm median CPU seconds of this process, result).

    On a shared machine the CPU time (summed over this process' threads) says how
    much work a call is, whatever the other processes do to the wall time.
    """
    start = time.perf_counter()
    out = fn()
    first = time.perf_counter() - start
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return first, statistics.median(wall), statistics.median(cpu), out


# ------------------------------------------------------------------ numpy reference
def reference_normalization(x, edges, quats, up=np.array([0.0, 0.0, 1.0]), weights=(10.0, 1.0, 1.0), tolerance=0.02):
    """Plain numpy: default-pose cost, candidate frames, leaf tie-break, limb frames for every frame."""
    from scipy.spatial.transform import Rotation

    tree = tree_arrays(edges, 0)
    n_frames, n_joints = x.shape[:2]
    centred = x - x.mean(1, keepdims=True)
    vals, vecs = np.linalg.eigh(np.einsum("fji,fjk->fik", centred, centred) / n_joints)
    extent = np.ptp(np.einsum("fji,fik->fjk", centred, vecs[:, :, 1:]), axis=1)
    terms = np.stack(
        [np.maximum(vals[:, 0], 0), extent.min(1) / extent.max(1), np.linalg.norm(centred, axis=-1).mean(1)], 1
    )
    scale = np.sort(terms[:, 2])[(n_frames - 1) // 2]
    cost = (terms / [scale**2, 1.0, scale]) @ np.asarray(weights)
    rot = Rotation.from_quat(np.roll(quats, -1, axis=-1).reshape(-1, 4)).as_matrix().reshape(n_frames, -1, 3, 3)
    origins = np.einsum("sj,fjk->fsk", tree.origin_weights, x)
    parent = np.full(n_joints + 1, -1)
    parent[edges[:, 1]] = edges[:, 0]
    candidate = cost <= cost.min() + tolerance
    toward = x[:, np.maximum(tree.proximal, 0)] - origins[:, np.maximum(parent, 0)]
    toward /= np.linalg.norm(toward, axis=-1, keepdims=True)
    seen = np.einsum("fski,fsk->fsi", rot, toward)
    typical = np.array(
        [[np.sort(seen[candidate, s, k])[(candidate.sum() - 1) // 2] for k in range(3)] for s in range(n_joints + 1)]
    )
    typical /= np.linalg.norm(typical, axis=-1, keepdims=True)
    off = (((seen - typical) ** 2).sum(-1) * tree.leaf).sum(-1)
    d = int(np.argmin(np.where(candidate, off + 1e-3 * (cost - cost.min()) / tolerance, np.inf)))
    return d, cost, rot


def reference_angles(q_rel, samples, axes, rest_direction, rest_rotation):
    """Plain numpy swing/twist angles of one two-axis joint; Python loop for the smooth candidate."""
    from scipy.spatial.transform import Rotation

    a, b = axes
    r = rest_direction
    c = a @ b
    h1, h2 = a @ r, samples @ b
    x0 = ((h1 - c * h2)[:, None] * a + (h2 - c * h1)[:, None] * b) / (1 - c * c)
    line = np.cross(a, b) / np.linalg.norm(np.cross(a, b))
    t = np.sqrt(np.maximum(1 - (x0 * x0).sum(-1), 0))[:, None]
    plus, minus = x0 + t * line, x0 - t * line
    x = np.empty_like(x0)
    prev = r
    for f in range(len(x0)):
        prev = plus[f] if ((plus[f] - prev) ** 2).sum() <= ((minus[f] - prev) ** 2).sum() else minus[f]
        x[f] = prev
    x /= np.linalg.norm(x, axis=-1, keepdims=True)

    def about(axis, u, v):
        return np.arctan2(np.cross(u, v) @ axis, (u * v).sum(-1) - (u @ axis) * (v @ axis))

    alpha, beta = about(a, np.broadcast_to(r, x.shape), x), about(b, x, samples)
    swing = Rotation.from_rotvec(beta[:, None] * b) * Rotation.from_rotvec(alpha[:, None] * a)
    rest = Rotation.from_quat(np.roll(rest_rotation, -1))
    m = (Rotation.from_quat(np.roll(q_rel, -1, axis=-1)) * (swing * rest).inv()).as_quat()  # x, y, z, w
    d = swing.apply(np.array(r))
    sign = np.where(m[:, 3] < 0, -1.0, 1.0)
    tau = 2 * np.arctan2(sign * (m[:, :3] * d).sum(-1), sign * m[:, 3])
    return np.stack([alpha, beta, tau], -1)


def relative_rotation(angles, axes, rest_direction, rest_rotation):
    """``R_B(beta) R_A(alpha) R_r(tau) Q_rest`` (scipy) of one joint's angles (F, 3)."""
    from scipy.spatial.transform import Rotation

    swing = Rotation.from_rotvec(angles[:, 1:2] * axes[1]) * Rotation.from_rotvec(angles[:, :1] * axes[0])
    twist = Rotation.from_rotvec(angles[:, 2:3] * rest_direction)
    return swing * twist * Rotation.from_quat(np.roll(rest_rotation, -1))


# ------------------------------------------------------------------ accuracy
def accuracy_table(seeds: list[int], noise_deg: float) -> dict:
    body = synth.full_body(seed=0)
    kinds = np.array(body.joint_types)
    joints = np.flatnonzero(kinds != "ball")
    out: dict[str, dict[str, float]] = {}
    errors: dict[str, list] = {m: [] for m in ("joining", "pca", "em")}
    reposed: dict[str, list] = {m: [] for m in errors}
    for seed in seeds:
        angles, root_rot, root_trans = main_movements(body, rate=30.0, seed=seed)
        _, _, rot, trans = truth_arrays(body, angles, root_rot, root_trans)
        x, q, _, t = perturbed(body, rot, trans, np.random.default_rng(seed), noise_deg)
        norm = normalize_arrays(x, body.edges, q, segment_translations=t)
        for method in errors:
            param = parameterize_normalized(norm, method=method)
            for j in joints:
                true = body.joint_axes[j] @ norm.limb_frames_local[body.edges[j, 0]]
                est = param.axes[j, : param.n_axes[j]]
                errors[method] += list(np.degrees(np.arccos(np.clip(np.abs(true @ est.T).max(1), 0, 1))))
            reposed[method].append(np.linalg.norm(param.pose().joint_positions - x, axis=-1).mean())
    for method, err in errors.items():
        err = np.asarray(err)
        out[method] = {
            "axis_error_mean_deg": float(err.mean()),
            "axis_error_max_deg": float(err.max()),
            "axes_over_3deg": float((err > 3).mean()),
            "repose_mean_mm": 1000 * float(np.mean(reposed[method])),
        }
    return out


def measure(n_frames: int = 24000, seeds: list[int] | None = None, repeats: int = 5) -> dict:
    """Timings, agreement with the numpy reference and axis accuracy (module docstring)."""
    seeds = [1, 2, 3, 4, 5, 6] if seeds is None else seeds
    x, edges, quats = paper_skeleton(n_frames)
    yardstick = np.random.default_rng(0).normal(size=(1000, 1000))
    start = time.perf_counter()
    yardstick @ yardstick
    matmul_s = time.perf_counter() - start

    n_first, n_warm, n_cpu, norm = timed(lambda: normalize_arrays(x, edges, quats), repeats)
    p_first, p_warm, p_cpu, param = timed(lambda: parameterize_normalized(norm), repeats)
    m_first, m_warm, m_cpu, _ = timed(lambda: parameterize_normalized(norm, method="pca"), repeats)
    e_first, e_warm, e_cpu, _ = timed(lambda: parameterize_normalized(norm, method="em"), repeats)
    r_first, r_warm, r_cpu, pose = timed(lambda: param.pose(), repeats)

    start = time.perf_counter()
    ref_frame, ref_cost, _ = reference_normalization(x, edges, quats)
    ref_norm_s = time.perf_counter() - start
    two = [j for j in range(param.n_joints) if param.n_axes[j] == 2]
    limb = matrix_to_quat(norm.limb_frames)
    q_rel = np.asarray(quat_multiply(quat_conjugate(limb[:, edges[:, 0]]), limb[:, edges[:, 1]]))
    start = time.perf_counter()
    ref_angles = [
        reference_angles(q_rel[:, j], param.samples[:, j], param.axes[j], param.rest_direction[j], param.rest_rotation[j])
        for j in two
    ]
    ref_angles_s = time.perf_counter() - start
    # After a tangency (both candidates coincide) the two implementations may continue on
    # different, equally exact branches: compare the rotations the angles produce.
    rotation_diff, same = 0.0, []
    for ref, j in zip(ref_angles, two, strict=True):
        mine, theirs = (
            relative_rotation(a, param.axes[j], param.rest_direction[j], param.rest_rotation[j])
            for a in (param.angles[:, j], ref)
        )
        rotation_diff = max(rotation_diff, float((mine.inv() * theirs).magnitude().max()))
        same.append(np.abs(np.angle(np.exp(1j * (ref - param.angles[:, j])))).max(1) < 1e-6)

    results = {
        "frames": n_frames,
        "joints": int(edges.shape[0]),
        "limbs": int(edges.shape[0] + 1),
        "machine": f"{platform.machine()} {os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}",
        "numpy_matmul_1000_s": matmul_s,
        "normalize": {"warm_s": n_warm, "warm_cpu_s": n_cpu, "first_s": n_first, "numpy_reference_s": ref_norm_s},
        "parameterize_joining": {"warm_s": p_warm, "warm_cpu_s": p_cpu, "first_s": p_first},
        "parameterize_pca": {"warm_s": m_warm, "warm_cpu_s": m_cpu, "first_s": m_first},
        "parameterize_em": {"warm_s": e_warm, "warm_cpu_s": e_cpu, "first_s": e_first},
        "pose_from_angles": {"warm_s": r_warm, "warm_cpu_s": r_cpu, "first_s": r_first},
        "angles_numpy_reference_s": ref_angles_s,
        "agreement": {
            "default_frame_equal": ref_frame == norm.default_frame,
            "cost_max_abs_diff": float(np.abs(ref_cost - norm.cost).max()),
            "joint_rotation_max_diff_rad": rotation_diff,
            "frames_with_identical_angles": float(np.mean(same)),
        },
        "this_motion": {
            "note": "synth calibration: every angle at once, no main movements",
            "repose_mean_mm": 1000 * float(np.linalg.norm(pose.joint_positions - x, axis=-1).mean()),
            "two_axis_residual_mean_deg": float(np.degrees(param.residual[:, two].mean())),
        },
        "accuracy_noise_0.3deg": accuracy_table(seeds, 0.3),
        "seeds": seeds,
        "two_axis_joints": len(two),
    }
    return results


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="2,400 frames and one accuracy seed")
    ap.add_argument("--frames", type=int, default=24000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()
    n_frames = 2400 if args.quick else args.frames
    results = measure(n_frames, [1] if args.quick else None, args.repeats)
    edges_n, seeds = results["joints"], results["seeds"]
    matmul_s = results["numpy_matmul_1000_s"]
    n_warm, n_cpu, n_first = (results["normalize"][k] for k in ("warm_s", "warm_cpu_s", "first_s"))
    ref_norm_s = results["normalize"]["numpy_reference_s"]
    p_warm, p_cpu, p_first = (results["parameterize_joining"][k] for k in ("warm_s", "warm_cpu_s", "first_s"))
    m_warm, m_cpu, m_first = (results["parameterize_pca"][k] for k in ("warm_s", "warm_cpu_s", "first_s"))
    e_warm, e_cpu, e_first = (results["parameterize_em"][k] for k in ("warm_s", "warm_cpu_s", "first_s"))
    r_warm, r_cpu, r_first = (results["pose_from_angles"][k] for k in ("warm_s", "warm_cpu_s", "first_s"))
    ref_angles_s = results["angles_numpy_reference_s"]
    two = range(results["two_axis_joints"])
    print(f"{n_frames} frames, {edges_n} joints, {edges_n + 1} limbs; {results['machine']}")
    print(f"(1000x1000 numpy matmul: {matmul_s:.3f} s; an idle 2-core machine takes ~0.03-0.05 s)")
    print(f"{'stage':24}{'warm s':>9}{'warm cpu s':>12}{'first s':>9}{'numpy ref s':>13}{'paper s':>9}")
    print(f"{'normalize':24}{n_warm:9.3f}{n_cpu:12.3f}{n_first:9.2f}{ref_norm_s:13.3f}{0.955:9.3f}")
    print(f"{'parameterize (joining)':24}{p_warm:9.3f}{p_cpu:12.3f}{p_first:9.2f}{ref_angles_s:13.3f}{37.2:9.1f}")
    print(f"{'parameterize (pca)':24}{m_warm:9.3f}{m_cpu:12.3f}{m_first:9.2f}")
    print(f"{'parameterize (em)':24}{e_warm:9.3f}{e_cpu:12.3f}{e_first:9.2f}")
    print(f"{'pose from angles':24}{r_warm:9.3f}{r_cpu:12.3f}{r_first:9.2f}")
    print(f"numpy reference of the angles covers the {len(two)} two-axis joints only")
    print("agreement with the numpy reference:", results["agreement"])
    print("this (uncalibrated) motion:", results["this_motion"])
    print(f"\naxis accuracy on main-movement calibrations ({len(seeds)} seeds, 0.3 deg IK-like noise)")
    print(f"{'method':10}{'mean deg':>10}{'max deg':>10}{'> 3 deg':>10}{'re-pose mm':>12}")
    for method, row in results["accuracy_noise_0.3deg"].items():
        print(
            f"{method:10}{row['axis_error_mean_deg']:10.2f}{row['axis_error_max_deg']:10.2f}"
            f"{row['axes_over_3deg']:10.1%}{row['repose_mean_mm']:12.2f}"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
