"""Benchmark inverse kinematics: jaxskel's vmapped LM vs scipy ``least_squares`` per frame.

Data: ``jaxskel.synth.full_body`` (15 segments, 46 markers, 48 pose unknowns per frame),
calibration motion at 120 Hz, 2 mm noise, posed on the *true* skeleton (so both solvers
solve exactly the same problem). Every solver starts from the same per-frame Horn
initial guess and minimises the same energy (markers + the 1 mm/rad pose prior).

* ``jaxskel core``: the compiled solver (:func:`jaxskel.skeleton._ik_batch.solve`: Horn start,
  tree-eliminated Levenberg-Marquardt/Newton, frames vectorised in chunks), warm.
* ``jaxskel inverse_kinematics``: the public call (input checks, padding, host copies).
* ``scipy``: ``scipy.optimize.least_squares`` (trust-region reflective, 2-point Jacobian)
  frame by frame in a Python loop on a subset of frames; the figure is frames per second.
* ``optimistix``: ``optimistix.LevenbergMarquardt`` on the residual form (autodiff
  Jacobian, QR), vmapped over a small batch: what the fast path replaces.

Agreement: RMS difference of the joint centres between each reference and jaxskel.

Usage::

    python bench/bench_ik.py              # 30 s of motion (3,600 frames), prints a table
    python bench/bench_ik.py --quick      # small shapes for CI
    python bench/bench_ik.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import jaxskel  # noqa: E402
from jaxskel import synth  # noqa: E402
from jaxskel.skeleton._ik import (  # noqa: E402
    DEFAULT_PRIOR_WEIGHT,
    _relative_rotations,
    _residuals,
    forward_kinematics,
    ik_initial_guess,
    ik_model,
    inverse_kinematics,
)
from jaxskel.skeleton._ik_batch import batch_model, solve  # noqa: E402
from jaxskel._math.padding import bucket_size  # noqa: E402
from jaxskel._math.rotation import axis_angle_to_quat, quat_multiply  # noqa: E402
from jaxskel.skeleton._rigid_fit import Skeleton  # noqa: E402


def truth_skeleton(trial, truth) -> Skeleton:
    n_seg = len(truth.segment_names)
    return Skeleton(
        n_segments=n_seg, edges=truth.edges, root=truth.root, marker_labels=trial.labels,
        marker_segment=truth.marker_segment, marker_offsets=truth.marker_offsets,
        joint_offsets=truth.joint_offsets, bones=truth.bones, bone_lengths=truth.bone_lengths,
        bone_segment=truth.bone_segment, segment_lengths=np.full(n_seg, np.nan),
        marker_rms=np.zeros(trial.n_markers), nonrigid_markers=(), diagnostics={},
    )


def timed(fn, repeat=1):
    out = jax.block_until_ready(fn())
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return out, best


def scipy_ik(skeleton, x, mask, t0, q0, prior_weight):
    """Reference: one ``least_squares`` call per frame; the same energy in numpy."""
    edges = skeleton.edges
    parent = skeleton.parent
    n_seg = skeleton.n_segments
    path = np.asarray(jaxskel.skeleton._ik.kinematic_chain(jnp.asarray(edges)).path)
    seg = skeleton.marker_segment
    mo, jo = skeleton.marker_offsets, skeleton.joint_offsets

    def residual(y, xf, mf, r0, prior_rel):
        rot = Rotation.from_rotvec(y[3:].reshape(n_seg, 3)) * r0
        mats = rot.as_matrix()
        d = np.einsum("jab,jb->ja", mats[edges[:, 0]], jo[:, 0]) - np.einsum("jab,jb->ja", mats[edges[:, 1]], jo[:, 1])
        trans = y[:3] + path @ d
        pred = np.einsum("mab,mb->ma", mats[seg], mo) + trans[seg]
        r_m = (pred - xf)[mf].ravel()
        rel = Rotation.from_matrix(np.where((parent >= 0)[:, None, None], mats[np.maximum(parent, 0)], np.eye(3))).inv() * rot
        r_p = (prior_rel.inv() * rel).as_rotvec() * prior_weight
        return np.concatenate([r_m, r_p.ravel()])

    roots, rots = [], []
    for f in range(x.shape[0]):
        r0 = Rotation.from_quat(q0[f], scalar_first=True)
        mats0 = r0.as_matrix()
        prior_rel = Rotation.from_matrix(
            np.where((parent >= 0)[:, None, None], mats0[np.maximum(parent, 0)], np.eye(3))
        ).inv() * r0
        y0 = np.concatenate([t0[f], np.zeros(3 * n_seg)])
        sol = least_squares(residual, y0, args=(x[f], mask[f], r0, prior_rel), xtol=1e-10, ftol=1e-10)
        roots.append(sol.x[:3])
        rots.append((Rotation.from_rotvec(sol.x[3:].reshape(n_seg, 3)) * r0).as_quat(scalar_first=True))
    return np.asarray(roots), np.asarray(rots)


def optimistix_ik(model):
    """optimistix.LevenbergMarquardt per frame (autodiff Jacobian, QR), vmapped and jitted."""
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)

    def one(xf, mf, tf, qf, prior_weight):
        prior = _relative_rotations(qf, model.chain.parent)
        args = (xf, mf.astype(xf.dtype) * model.marker_weight, qf, model.joint_offsets, model.marker_offsets,
                model.chain, model.marker_segment, prior, prior_weight)
        y0 = (tf, jnp.zeros_like(qf[:, 1:]))
        sol = optx.least_squares(_residuals, solver, y0, args, max_steps=256, throw=False)
        t, delta = sol.value
        q = quat_multiply(axis_angle_to_quat(delta), qf)
        return t, q, sol.stats["num_steps"]

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None)))


def main() -> None:
    from jaxskel._runtime.own_process import own_process

    # jaxskel's own process: single-threaded Eigen before JAX starts, and float64 for the
    # script's own arrays and the private functions it calls as well as jaxskel's own
    own_process(x64=True)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small shapes (CI)")
    parser.add_argument("--json", help="write the figures to this JSON file")
    args = parser.parse_args()
    duration = 5.0 if args.quick else 30.0
    n_scipy = 20 if args.quick else 100
    n_optx = 8 if args.quick else 32

    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, "calibration", duration=duration, seed=0, noise=0.002)
    skeleton = truth_skeleton(trial, truth)
    x, mask = trial.to_arrays()
    n_frames = trial.n_frames
    f_pad, m_pad = bucket_size(n_frames), bucket_size(trial.n_markers, minimum=8)
    xp = np.zeros((f_pad, m_pad, 3))
    mp = np.zeros((f_pad, m_pad), bool)
    xp[:n_frames, : trial.n_markers] = x
    mp[:n_frames, : trial.n_markers] = mask
    model = ik_model(skeleton.edges, skeleton.joint_offsets, skeleton.marker_offsets, skeleton.marker_segment, n_markers=m_pad)
    n_seg = skeleton.n_segments
    pw = jnp.full((n_seg,), DEFAULT_PRIOR_WEIGHT)
    identity = jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0]), (f_pad, n_seg, 1))
    xj, mj = jnp.asarray(xp), jnp.asarray(mp)

    fast = batch_model(skeleton.edges, skeleton.joint_offsets, skeleton.marker_offsets, skeleton.marker_segment)

    def core():
        return solve(fast, xp[:n_frames], mp[:n_frames], None, None, None, np.asarray(pw), max_steps=100)

    start = time.perf_counter()
    core()
    compile_s = time.perf_counter() - start
    sol, core_s = timed(core, repeat=3)
    joints = sol["joint_positions"]
    steps = sol["num_steps"]
    _, public_s = timed(lambda: inverse_kinematics(skeleton, trial).joint_positions, repeat=2)

    # Same starting guesses for the references.
    t0, q0 = jax.vmap(ik_initial_guess, (0, 0, None, None))(xj, mj, model, identity[0])
    t0, q0 = np.asarray(t0), np.asarray(q0)
    pick = np.linspace(0, n_frames - 1, n_scipy).astype(int)
    start = time.perf_counter()
    s_root, s_rot = scipy_ik(skeleton, x[pick], mask[pick], t0[pick], q0[pick], DEFAULT_PRIOR_WEIGHT)
    scipy_s = time.perf_counter() - start
    _, s_joints, _ = forward_kinematics(
        jnp.asarray(s_root), jnp.asarray(s_rot), jnp.asarray(skeleton.joint_offsets),
        jnp.asarray(skeleton.marker_offsets), jnp.asarray(skeleton.edges), jnp.asarray(skeleton.marker_segment),
    )
    scipy_diff = float(np.sqrt(np.mean(np.sum((np.asarray(s_joints) - joints[pick]) ** 2, -1))))

    opick = pick[:n_optx] if n_optx <= len(pick) else np.linspace(0, n_frames - 1, n_optx).astype(int)
    oargs = (xj[opick], mj[opick], jnp.asarray(t0[opick]), jnp.asarray(q0[opick]), pw)
    solve_optx = optimistix_ik(model)
    (o_root, o_rot, o_steps), optx_s = timed(lambda: solve_optx(*oargs))
    _, o_joints, _ = forward_kinematics(
        o_root, o_rot, jnp.asarray(skeleton.joint_offsets), jnp.asarray(skeleton.marker_offsets),
        jnp.asarray(skeleton.edges), jnp.asarray(skeleton.marker_segment),
    )
    optx_diff = float(np.sqrt(np.mean(np.sum((np.asarray(o_joints) - joints[opick]) ** 2, -1))))

    figures = {
        "device": jax.devices()[0].platform,
        "frames": n_frames,
        "markers": trial.n_markers,
        "segments": n_seg,
        "jaxskel_core_fps": n_frames / core_s,
        "jaxskel_core_compile_s": compile_s,
        "jaxskel_public_fps": n_frames / public_s,
        "jaxskel_mean_steps": float(steps.mean()),
        "scipy_frames": len(pick),
        "scipy_fps": len(pick) / scipy_s,
        "scipy_joint_rms_diff_m": scipy_diff,
        "optimistix_frames": len(opick),
        "optimistix_fps": len(opick) / optx_s,
        "optimistix_mean_steps": float(np.mean(np.asarray(o_steps))),
        "optimistix_joint_rms_diff_m": optx_diff,
    }
    figures["speedup_vs_scipy"] = figures["jaxskel_core_fps"] / figures["scipy_fps"]
    figures["speedup_vs_optimistix"] = figures["jaxskel_core_fps"] / figures["optimistix_fps"]
    print(f"IK, full body ({n_seg} segments, {trial.n_markers} markers), {n_frames} frames, {figures['device']}")
    print(f"  jaxskel core (warm)          {figures['jaxskel_core_fps']:10.0f} frames/s  "
          f"(mean {figures['jaxskel_mean_steps']:.1f} LM steps; compile {compile_s:.1f} s)")
    print(f"  jaxskel inverse_kinematics   {figures['jaxskel_public_fps']:10.0f} frames/s")
    print(f"  optimistix LM (autodiff, QR) {figures['optimistix_fps']:10.0f} frames/s  "
          f"(joints differ by {1e6 * optx_diff:.2f} um RMS)")
    print(f"  scipy least_squares / frame  {figures['scipy_fps']:10.0f} frames/s  "
          f"(joints differ by {1e6 * scipy_diff:.2f} um RMS)")
    print(f"  speed-up: {figures['speedup_vs_scipy']:.0f}x vs scipy, {figures['speedup_vs_optimistix']:.0f}x vs optimistix")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(figures, handle, indent=2)


if __name__ == "__main__":
    main()
