"""The SVD-free Kabsch alignment (jaxskel._math.procrustes.closed_form_align) against the SVD one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxskel._math.procrustes import closed_form_align, procrustes
from jaxskel._math.rotation import horn_align

pytestmark = pytest.mark.usefixtures("float64")


def _objective(rot, t, src, tgt, w):
    return float(np.sum(w * np.sum((src @ np.asarray(rot).T + np.asarray(t) - tgt) ** 2, axis=-1)))


def _random_rotation(rng):
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    return q * np.sign(np.linalg.det(q))


def test_equals_the_svd_alignment_on_clouds_with_a_unique_answer():
    """Noisy clouds of 3 (planar), 4 and 8 points, masked points, weights, mirrored targets
    (the best proper rotation), sizes from millimetres to metres: the same rotation and shift."""
    rng = np.random.default_rng(0)
    align = jax.jit(closed_form_align)
    for trial in range(300):
        n = (3, 4, 8)[trial % 3]
        scale = 10.0 ** rng.uniform(-3, 0)
        src = rng.normal(size=(n, 3)) * scale
        tgt = src @ _random_rotation(rng).T + rng.normal(size=3) + rng.normal(size=(n, 3)) * 0.05 * scale
        if trial % 4 == 1:
            tgt = tgt * np.array([-1.0, 1.0, 1.0])  # a mirror image: no rotation fits exactly
        w = rng.uniform(0.2, 2.0, size=n)
        if n == 8 and trial % 2:
            w[:3] = 0.0  # masked points
        got_r, got_t = align(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(w))
        want_r, want_t = horn_align(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(w))
        got_r = np.asarray(got_r)
        np.testing.assert_allclose(got_r.T @ got_r, np.eye(3), atol=1e-12)
        assert np.linalg.det(got_r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(got_r, np.asarray(want_r), atol=1e-7, err_msg=f"trial {trial}")
        np.testing.assert_allclose(np.asarray(got_t), np.asarray(want_t), atol=1e-7 * max(1.0, scale))
        assert _objective(got_r, got_t, src, tgt, w) <= _objective(want_r, want_t, src, tgt, w) * (1 + 1e-9) + 1e-24


def test_exact_motion_is_recovered_exactly():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(5, 3)) * 0.05
    rot = _random_rotation(rng)
    got_r, got_t = closed_form_align(jnp.asarray(src), jnp.asarray(src @ rot.T + [0.3, -1.0, 2.0]), jnp.ones(5))
    np.testing.assert_allclose(np.asarray(got_r), rot, atol=1e-12)
    np.testing.assert_allclose(np.asarray(got_t), [0.3, -1.0, 2.0], atol=1e-12)


def test_degenerate_clouds_give_a_proper_minimiser_and_no_nan():
    """Two points, collinear points and a single point leave the rotation partly free:
    the answer is a rotation that fits as well as the SVD's; no weight at all gives the identity."""
    rng = np.random.default_rng(2)
    line = np.outer(rng.normal(size=4), rng.normal(size=3))
    for src, w in (
        (rng.normal(size=(2, 3)), np.ones(2)),
        (line, np.ones(4)),
        (rng.normal(size=(4, 3)), np.array([0.0, 0.0, 1.0, 1.0])),
        (rng.normal(size=(3, 3)), np.array([0.0, 1.0, 0.0])),
    ):
        tgt = src @ _random_rotation(rng).T + 1.0
        got_r, got_t = closed_form_align(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(w))
        got_r = np.asarray(got_r)
        assert np.all(np.isfinite(got_r)) and np.all(np.isfinite(np.asarray(got_t)))
        np.testing.assert_allclose(got_r.T @ got_r, np.eye(3), atol=1e-10)
        assert np.linalg.det(got_r) == pytest.approx(1.0, abs=1e-10)
        want_r, want_t = horn_align(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(w))
        want = _objective(want_r, want_t, src, tgt, w)
        assert _objective(got_r, got_t, src, tgt, w) == pytest.approx(want, abs=1e-18)
    got_r, got_t = closed_form_align(jnp.ones((3, 3)), jnp.zeros((3, 3)), jnp.zeros(3))
    np.testing.assert_array_equal(np.asarray(got_r), np.eye(3))


def test_procrustes_recovers_the_poses_of_a_noisy_rigid_cloud():
    """Generalised Procrustes (which aligns with the closed form) on frames of one rigid
    4-point cloud: the mean cloud is the cloud up to one pose, every frame's alignment maps it
    there, and the scatter is the noise's."""
    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(4, 3)) * 0.05
    n_frames, noise = 400, 1e-3
    rots = np.stack([_random_rotation(rng) for _ in range(n_frames)])
    frames = np.einsum("fij,pj->fpi", rots, cloud) + rng.normal(size=(n_frames, 1, 3))
    frames = frames + rng.normal(size=frames.shape) * noise
    pts, w = jnp.asarray(frames[:, None]), jnp.ones((n_frames, 1, 4))
    mean, rot, t, rms = procrustes(pts, w, pts[0], w[0])
    mapped = np.einsum("fij,fpj->fpi", np.asarray(rot)[:, 0], frames) + np.asarray(t)[:, 0, None]
    np.testing.assert_allclose(mapped, np.broadcast_to(np.asarray(mean)[0], mapped.shape), atol=6 * noise)
    # The mean cloud is the true one up to a rigid motion.
    r, s = horn_align(jnp.asarray(cloud), mean[0], jnp.ones(4))
    np.testing.assert_allclose(cloud @ np.asarray(r).T + np.asarray(s), np.asarray(mean)[0], atol=2e-4)
    assert 0.3 * noise < float(np.median(np.asarray(rms))) < 2.0 * noise
