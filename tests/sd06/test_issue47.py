"""SD06 on protocol + free movement (issue 47): branch continuity, calibration windows.

Ground truth: ``sd06_truth`` (synthetic body, generator angles known exactly).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from calibration_motions import main_movements, truth_arrays
from sd06_truth import compare, protocol_and_free

from jaxskel import InputError, synth
from jaxskel.sd06 import parameterize, parameterize_arrays

BODY = synth.full_body(seed=0)
KIND = np.array(BODY.joint_types)
RATE = 30.0


def _param(rec, **kw):
    return parameterize_arrays(rec.joints, BODY.edges, rec.quats, root=BODY.root, segment_translations=rec.trans, **kw)


# ------------------------------------------------------------------ item 1: branch
def sweep_recording():
    """Protocol, then every hinge / universal angle swept alone to +-170 degrees with the other at 30 degrees."""
    angles, root_rot, root_trans = main_movements(BODY, rate=RATE, seed=0)
    n_p = angles[0].shape[0]
    ramp = np.sin(np.linspace(0, 2 * np.pi, 120))  # 0 -> +1 -> 0 -> -1 -> 0
    pieces = []
    for j, kind in enumerate(KIND):
        if kind == "ball":
            continue
        for k in range(angles[j].shape[1]):
            block = [np.zeros((120, a.shape[1])) for a in angles]
            block[j][:, k] = np.radians(170.0) * ramp
            if angles[j].shape[1] == 2:
                block[j][:, 1 - k] = np.radians(30.0) * np.clip(4 * np.abs(ramp), 0, 1)
            pieces.append(block)
    sweep = [np.concatenate([a] + [p[j] for p in pieces]) for j, a in enumerate(angles)]
    n = sweep[0].shape[0]
    root = np.concatenate([root_rot, np.repeat(root_rot[-1:], n - n_p, axis=0)])
    trans = np.concatenate([root_trans, np.repeat(root_trans[-1:], n - n_p, axis=0)])
    joints, quats, rot, trans = truth_arrays(BODY, tuple(sweep), root, trans)
    return SimpleNamespace(angles=sweep, joints=joints, quats=quats, rot=rot, trans=trans, protocol=(0, n_p))


@pytest.fixture(scope="module")
def swept():
    rec = sweep_recording()
    # the sweep bends the knees both ways and has no feet or walking: nothing in the body tells
    # front from back, so the subject's facing (the pelvis' +x at the start) is given
    rec.param = _param(rec, calibration=rec.protocol, facing=rec.rot[0, BODY.root][:, 0])
    return rec


def _wrapped_deg(x):
    return np.degrees(np.abs(np.angle(np.exp(1j * x))))


def test_sweeping_each_joint_through_170_degrees_has_no_jumps(swept):
    """Hinge: angle = generator angle; universal: (alpha, beta) = (child-axis, parent-axis) angles, exactly.

    The circle intersection has two solutions; the far one turns both angles by
    ~180 degrees. Continuity from the rest pose keeps the true one through the
    whole sweep, and the default pose is 0.
    """
    rec, param = swept, swept.param
    norm = param.normalization
    assert np.all(param.rest_frame == norm.default_frame)
    np.testing.assert_allclose(param.angles[norm.default_frame], 0.0, atol=1e-9)
    for j, kind in enumerate(KIND):
        if kind == "ball":
            continue
        true_axes = BODY.joint_axes[j] @ norm.limb_frames_local[BODY.edges[j, 0]]
        if kind == "hinge":
            sign = np.sign(param.axes[j, 0] @ true_axes[0])
            expected = np.stack([sign * rec.angles[j][:, 0], 0 * rec.angles[j][:, 0]], 1)
        else:
            # axes[j, 0] acts first (moves with the child: generator axis 1), axes[j, 1] second.
            s0 = np.sign(param.axes[j, 0] @ true_axes[1])
            s1 = np.sign(param.axes[j, 1] @ true_axes[0])
            assert abs(param.axes[j, 0] @ true_axes[1]) > 0.999 and abs(param.axes[j, 1] @ true_axes[0]) > 0.999
            expected = np.stack([s0 * rec.angles[j][:, 1], s1 * rec.angles[j][:, 0]], 1)
        err = _wrapped_deg(param.angles[:, j, :2] - expected)
        assert err.max() < 1e-6, (BODY.joint_names[j], err.max(), int(np.argmax(err.max(1))))
        np.testing.assert_allclose(param.angles[:, j, 2], 0.0, atol=1e-7)  # no twist in hinges / universals


# ------------------------------------------------------------------ item 2: calibration window
@pytest.fixture(scope="module")
def session():
    """Protocol then 20 s of free movement (every degree of freedom at once), IK-like noise 0.3 deg."""
    return protocol_and_free(BODY, rate=RATE, free_seconds=20.0, seed=1, noise_deg=0.3)


def test_calibration_window_gives_every_joint_its_axes_and_twist(session):
    rec = session
    param = _param(rec, calibration=rec.protocol)
    c = compare(param, rec, BODY)
    print("\naxis error (deg):", np.round(c.axis_err, 2))
    print("angle RMS (deg) alpha/beta/twist:\n", np.round(c.angle_rms, 2))
    assert c.axis_err.max() < 3.0
    assert c.angle_rms[:, 2].max() < 5.0  # twist, every joint
    assert c.angle_rms[:, :2].max() < 5.0
    np.testing.assert_array_equal(param.n_axes, np.where(KIND == "hinge", 1, 2))
    # Axes and default pose from the window only; angles for every frame.
    start, stop = rec.protocol
    assert start <= param.normalization.default_frame < stop
    assert not param.calibration[stop:].any() and param.calibration.shape == (rec.joints.shape[0], BODY.n_joints)
    assert param.calibration_source == "given"
    assert param.angles.shape[0] == rec.joints.shape[0]
    np.testing.assert_allclose(param.angles[param.normalization.default_frame], 0.0, atol=1e-9)


def test_every_frame_as_calibration_spoils_the_axes(session):
    """The same recording with every frame as calibration ("all"): free movement pulls the axes away."""
    param = _param(session, calibration="all")
    assert param.calibration_source == "all" and param.calibration.all()
    assert compare(param, session, BODY).axis_err.max() > 10.0


@pytest.fixture(scope="module")
def long_free_session():
    """Protocol then 40 s of free movement at 60 Hz, noise-free: free movement twice as long as the protocol."""
    return protocol_and_free(BODY, rate=60.0, free_seconds=40.0, seed=2)


@pytest.mark.parametrize("recording", ["session", "long_free_session"])
def test_without_a_window_the_main_movements_are_found(recording, request):
    """The default (no window): each joint's main movements are detected, and from them every joint's axes
    come within 3 degrees and its angles within 5 degrees RMS, as with the protocol given as a window."""
    rec = request.getfixturevalue(recording)
    param = _param(rec, rate=rec.rate)
    assert param.calibration_source == "automatic"
    c = compare(param, rec, BODY)
    print("\naxis error (deg):", np.round(c.axis_err, 2), "\nangle RMS (deg):\n", np.round(c.angle_rms, 2))
    assert c.axis_err.max() < 3.0
    assert c.angle_rms.max() < 5.0
    np.testing.assert_array_equal(param.n_axes, np.where(KIND == "hinge", 1, 2))
    # The chosen frames of the joints with two axes are the protocol's: free movement turns them about
    # drifting mixtures of their axes, or about one axis from another posture.
    stop = rec.protocol[1]
    two = KIND != "hinge"
    chosen = param.calibration[:, two]
    assert (chosen[:stop].sum(0) >= 0.8 * chosen.sum(0)).all()
    assert (chosen.sum(0) >= 30).all()


def test_free_movement_alone_falls_back_to_every_frame():
    """No main movement to find (free movement only): a joint with two axes calibrates on every frame."""
    from scipy.spatial.transform import Rotation

    _, truth = synth.simulate(BODY, "calibration", duration=20.0, rate=RATE, seed=9)
    rot = truth.segment_rotations
    quats = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(*rot.shape[:2], 4)
    param = parameterize_arrays(truth.joint_positions, BODY.edges, quats, root=BODY.root,
                                segment_translations=truth.segment_translations, rate=RATE)
    assert param.calibration_source == "automatic"
    assert param.calibration[:, KIND != "hinge"].all()


def test_calibration_window_forms_agree(session):
    """Frames, seconds, a mask and a separate calibration recording give the same axes."""
    rec = session
    start, stop = rec.protocol
    by_frames = _param(rec, calibration=(start, stop))
    by_seconds = _param(rec, calibration=(start / RATE, stop / RATE), rate=RATE)
    mask = np.zeros(rec.joints.shape[0], bool)
    mask[start:stop] = True
    by_mask = _param(rec, calibration=mask)
    for other in (by_seconds, by_mask):
        np.testing.assert_allclose(other.axes, by_frames.axes, atol=1e-12)
        np.testing.assert_allclose(other.angles, by_frames.angles, atol=1e-12)
    # A separate calibration trial: the protocol alone, then the free movement as the motion.
    cal = SimpleNamespace(joint_positions=rec.joints[:stop], rotations=rec.quats[:stop], segment_translations=rec.trans[:stop])
    skeleton = SimpleNamespace(edges=BODY.edges, root=BODY.root)
    motion = SimpleNamespace(joint_positions=rec.joints[stop:], rotations=rec.quats[stop:],
                             segment_translations=rec.trans[stop:], rate=RATE)
    trial = parameterize(skeleton, motion, calibration=cal)
    assert trial.calibration_source == "trial" and trial.angles.shape[0] == rec.joints.shape[0] - stop
    assert np.all(trial.rest_frame == -1) and trial.normalization.default_frame == -1
    np.testing.assert_allclose(trial.axes, by_frames.axes, atol=1e-9)
    # Angles differ only where the free movement's first frames restart the branch walk from rest.
    diff = _wrapped_deg(trial.angles - by_frames.angles[stop:])
    assert np.median(diff) < 1e-6
    position = np.linalg.norm(trial.pose().joint_positions - rec.joints[stop:], axis=-1)
    assert position.mean() < 2e-3  # what the model leaves out: the noise off the hinge axes


def test_calibration_frames_are_written(session, tmp_path):
    import h5py

    from jaxskel.sd06._parameterize import write_parameters

    param = _param(session, calibration=session.protocol)
    with h5py.File(tmp_path / "r.h5", "w") as f:
        write_parameters(f.create_group("parameters"), param)
    with h5py.File(tmp_path / "r.h5", "r") as f:
        np.testing.assert_array_equal(f["parameters/calibration"][()], param.calibration)
        assert f["parameters"].attrs["calibration_source"] == "given"


def test_bad_calibration_windows_are_reported(session):
    rec = session
    with pytest.raises(InputError, match="at least 3"):
        _param(rec, calibration=(5, 6))
    with pytest.raises(InputError, match="main_s > 0"):
        _param(rec, main_s=float("nan"))
    with pytest.raises(InputError, match="frame rate"):
        _param(rec, calibration=(0.0, 10.0))
    with pytest.raises(InputError, match="one entry per frame"):
        _param(rec, calibration=np.ones(7, bool))
    with pytest.raises(InputError, match="calibration must be"):
        _param(rec, calibration="protocol")
