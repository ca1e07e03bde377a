"""The rigid refinement's device alternation (jaxskel.skeleton._rigid_sweeps) against the host loop
it replaces, and its device-side pieces against their host counterparts."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxskel import synth
from jaxskel._math.anderson import anderson_step, anderson_step_buffered
from jaxskel._runtime.backend import to_device
from jaxskel.skeleton import _ik_batch as ik_batch
from jaxskel.skeleton import _rigid_fit as rigid_fit
from jaxskel.skeleton import _rigid_sweeps as sweeps
from jaxskel.skeleton._ik import _host_relative, kinematic_chain
from jaxskel.skeleton._rigid_fit import SOLVED_JOINT_WEIGHT, fit_rigid


def _host_refine(marker_theta, joint_theta, obs, present, obs_segment, obs_base_weight, edges, coef, unknown_segment,
                 start, prior_weight, xtol, refine, *, max_sweeps, max_steps):
    """The alternation as a host loop (what the device program replaced): a host call of the
    chunked IK per sweep, the model rebuilt on the host, the offset update and Anderson's
    step (host lists) between sweeps. Same signature and return as ``_rigid_fit._refine``."""
    n_m = marker_theta.shape[0]
    parent = kinematic_chain(np.asarray(edges)).parent
    slots, columns = ik_batch.solver_shape(obs_segment[:n_m], edges, n_m)
    pad = ((0, 0), (0, columns - obs.shape[1]))
    obs_in, observed = np.pad(obs, (*pad, (0, 0))), np.pad(present > 0, pad)

    def sweep(m_th, j_th, sol):
        model = ik_batch.batch_model(
            edges, np.stack([j_th, np.zeros_like(j_th)], axis=1), np.concatenate([m_th, np.zeros_like(j_th)]),
            obs_segment, obs_base_weight, slots=slots,
        )
        if sol is None:
            return ik_batch.solve(model, obs_in, observed, None, None, None, prior_weight, max_steps=max_steps)
        q = sol["rotations"]
        return ik_batch.solve(model, obs_in, observed, sol["root_position"], q, _host_relative(q, parent),
                              prior_weight, max_steps=max_steps)

    m_th, j_th = marker_theta, joint_theta
    sol = sweep(m_th, j_th, start)
    history, steps, met, iterates, images = [], [], False, [], []
    args = tuple(to_device(a) for a in (obs, present * obs_base_weight, coef, unknown_segment,
                                        *sweeps.offset_pairs(coef, unknown_segment)))
    update = jax.jit(sweeps.offset_update)
    while refine and len(history) < max_sweeps and not met:
        theta_old = np.concatenate([m_th, j_th]).reshape(-1)
        theta, cost = update(to_device(sol["rotations"]), to_device(sol["root_position"]), *args,
                             to_device(theta_old))
        cost, theta = float(cost), np.asarray(theta).reshape(-1)
        step = float(np.max(np.abs(theta - theta_old)))
        rose = bool(history) and cost > history[-1]
        met = bool(history) and not rose and step <= xtol
        if rose:
            iterates, images = [], []
        history.append(cost)
        steps.append(step)
        iterates = [*iterates, theta_old][-(rigid_fit._ANDERSON_MEMORY + 1):]
        images = [*images, theta][-(rigid_fit._ANDERSON_MEMORY + 1):]
        if not met:
            theta = anderson_step(iterates, images)
        theta = theta.reshape(-1, 3)
        m_th, j_th = theta[:n_m], theta[n_m:]
        sol = sweep(m_th, j_th, sol)
    return m_th, j_th, sol, history, steps, met


@pytest.fixture(scope="module")
def small_trial():
    body = synth.random_tree(5, seed=3)
    trial, truth = synth.simulate(body, "calibration", duration=3.0, seed=3, noise=0.002, soft_tissue=0.003)
    joints = truth.joint_positions + np.random.default_rng(3).normal(0.0, 0.002, truth.joint_positions.shape)
    return trial, truth, joints


def test_device_alternation_reaches_the_host_loops_fixed_point(small_trial, monkeypatch):
    trial, truth, joints = small_trial
    kw = dict(max_frames=150, joint_weight=SOLVED_JOINT_WEIGHT)
    device = fit_rigid(trial, truth.marker_segment, truth.edges, joints, **kw)
    monkeypatch.setattr(rigid_fit, "_refine", _host_refine)
    host = fit_rigid(trial, truth.marker_segment, truth.edges, joints, **kw)
    d, h = device.diagnostics, host.diagnostics
    assert d["result"] == h["result"] == 0
    assert d["sweeps"] > 3  # a real alternation, not a first-update stop
    # the same iteration (up to rounding in the IK's order of operations): same sweeps, costs, offsets
    assert abs(d["sweeps"] - h["sweeps"]) <= 2
    np.testing.assert_allclose(d["cost_history"][:3], h["cost_history"][:3], rtol=1e-6)
    np.testing.assert_allclose(device.joint_offsets, host.joint_offsets, rtol=0, atol=2e-5)
    np.testing.assert_allclose(device.marker_offsets, host.marker_offsets, rtol=0, atol=2e-5)
    np.testing.assert_allclose(device.bone_lengths, host.bone_lengths, rtol=0, atol=2e-5)
    assert d["residual_rms"] == pytest.approx(h["residual_rms"], rel=1e-4)
    assert d["ik_steps_max"] >= 1 and d["frames_used"] == h["frames_used"]


def test_device_alternation_reports_running_out_of_sweeps(small_trial):
    trial, truth, joints = small_trial
    with pytest.warns(Warning, match="max_sweeps=2"):
        sk = fit_rigid(trial, truth.marker_segment, truth.edges, joints, max_frames=150, max_sweeps=2,
                       joint_weight=SOLVED_JOINT_WEIGHT)
    d = sk.diagnostics
    assert d["sweeps"] == 2 and len(d["cost_history"]) == len(d["offset_steps"]) == 2
    assert d["result"] != 0 and d["offset_steps"][-1] > 1e-6


@pytest.mark.usefixtures("float64")
def test_model_rebuilt_on_the_device_equals_the_host_model():
    body = synth.random_tree(6, seed=1)
    rng = np.random.default_rng(0)
    edges, seg = body.edges, body.marker_segment
    n_m, n_j = seg.size, edges.shape[0]
    obs_segment = np.concatenate([seg, edges[:, 1]])
    weight = np.concatenate([np.ones(n_m), np.full(n_j, 0.01)])
    slots, _ = ik_batch.solver_shape(seg, edges, n_m)

    def host(m_th, j_th):
        return ik_batch.batch_model(edges, np.stack([j_th, np.zeros_like(j_th)], axis=1),
                                    np.concatenate([m_th, np.zeros_like(j_th)]), obs_segment, weight, slots=slots)

    start = host(rng.normal(size=(n_m, 3)), rng.normal(size=(n_j, 3)))
    m_th, j_th = rng.normal(size=(n_m, 3)), rng.normal(size=(n_j, 3))
    want = host(m_th, j_th)
    got = jax.jit(ik_batch.with_offsets)(start, to_device(j_th), to_device(m_th))
    for name in ("joint_parent", "joint_child", "marker_offsets", "shape_moment"):
        for a, b in zip(getattr(got, name), getattr(want, name)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.usefixtures("float64")
def test_device_frame_sweep_equals_the_host_chunked_solve(small_trial):
    trial, truth, joints = small_trial
    sk = fit_rigid(trial, truth.marker_segment, truth.edges, joints, max_frames=150)
    x, mask = trial.to_arrays()
    x, mask = x[:100], mask[:100]  # not a multiple of the chunk: padded frames
    bm = ik_batch.batch_model(sk.edges, sk.joint_offsets, sk.marker_offsets, sk.marker_segment)
    pw = np.full(sk.n_segments, 0.01)
    host = ik_batch.solve(bm, x, mask, None, None, None, pw, max_steps=50, threads=1)
    n, s = x.shape[0], sk.n_segments
    ident = np.broadcast_to(np.array([1.0, 0, 0, 0]), (n, s, 4))
    dev = jax.jit(ik_batch.solve_frames)(bm, to_device(x), to_device(mask), to_device(np.zeros((n, 3))),
                                         to_device(ident), to_device(ident), to_device(pw), to_device(True),
                                         to_device(50, np.int32))
    for key in ("root_position", "rotations", "num_steps", "rms"):
        np.testing.assert_allclose(np.asarray(dev[key]), host[key], rtol=1e-9, atol=1e-12, err_msg=key)


@pytest.mark.usefixtures("float64")
@pytest.mark.parametrize("count", [1, 2, 4, 6])
def test_buffered_anderson_step_equals_the_host_step(count):
    rng = np.random.default_rng(count)
    history, n = 6, 9
    xs, gs = rng.normal(size=(history, n)), rng.normal(size=(history, n))
    # the invalid rows hold garbage: they must not matter
    want = anderson_step(list(xs[history - count:]), list(gs[history - count:]))
    got = np.asarray(jax.jit(anderson_step_buffered)(to_device(xs), to_device(gs), to_device(count, np.int32)))
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    if count == 1:
        np.testing.assert_array_equal(got, gs[-1])
