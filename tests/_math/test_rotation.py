"""The rotation kit (jaxskel._math.rotation, jaxskel._math.rotation_planes) against
scipy.spatial.transform.Rotation as an independent reference, its three forms against
each other, and its derivatives against finite differences."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from jaxskel._math import rotation, rotation_planes

# jaxskel's private JAX functions run inside the float64 scope of the public functions
# that call them (jaxskel._runtime.precision): these tests give them the same.
pytestmark = pytest.mark.usefixtures("float64")

N = 64

# The kit's functions compiled whole: eagerly, each of their operations would be compiled
# on its own, which is most of the time of these small tests.
rot = SimpleNamespace(**{n: getattr(rotation, n) if n.endswith("_np") else jax.jit(getattr(rotation, n))
                         for n in rotation.__all__})
rp = SimpleNamespace(**{n: jax.jit(getattr(rotation_planes, n), static_argnums=2 if n == "horn_quat" else ())
                        for n in rotation_planes.__all__})


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def _scipy_quats(rng, n=N) -> np.ndarray:
    """Random unit quaternions (w, x, y, z), either sign of w."""
    q = Rotation.random(n, rng=rng).as_quat(scalar_first=True)
    return q * rng.choice([-1.0, 1.0], size=(n, 1))


def _same_rotation(q, r, atol=1e-12):
    """Quaternions equal up to sign."""
    q, r = np.asarray(q), np.asarray(r)
    err = np.minimum(np.abs(q - r).max(axis=-1), np.abs(q + r).max(axis=-1))
    assert err.max() < atol, err.max()


def _planes(a):
    return tuple(jnp.asarray(np.moveaxis(np.asarray(a), -1, 0)))


def _unplanes(t):
    return np.stack([np.asarray(c) for c in t], axis=-1)


def _rotvecs(rng, n=N):
    """Rotation vectors of angles across [0, pi), plus tiny and zero ones."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = rng.uniform(0.0, np.pi - 1e-3, size=(n, 1))
    angle[:4, 0] = [0.0, 1e-9, 1e-7, 3e-6]  # the Taylor branch and both sides of its edge
    return axis * angle


# ------------------------------------------------------------ against scipy
def test_conventions():
    """Active rotations, (w, x, y, z), Hamilton order: a quarter turn about z takes x to y."""
    q = rot.axis_angle_to_quat(jnp.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], atol=1e-15)
    np.testing.assert_allclose(rot.quat_to_matrix(q) @ jnp.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rot.quat_rotate(q, jnp.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0], atol=1e-15)
    # p q applies q first: a quarter turn about x, then about z.
    qx = rot.axis_angle_to_quat(jnp.array([np.pi / 2, 0.0, 0.0]))
    np.testing.assert_allclose(rot.quat_rotate(rot.quat_multiply(q, qx), jnp.array([0.0, 1.0, 0.0])), [0.0, 0.0, 1.0],
                               atol=1e-15)


def test_quat_to_matrix_matches_scipy(rng):
    q = _scipy_quats(rng)
    scale = rng.uniform(0.2, 5.0, size=(N, 1))  # the scale is divided out
    expected = Rotation.from_quat(q, scalar_first=True).as_matrix()
    np.testing.assert_allclose(rot.quat_to_matrix(jnp.asarray(q * scale)), expected, atol=1e-14)


def test_matrix_to_quat_matches_scipy_including_half_turns(rng):
    axes = rng.normal(size=(N, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, N // 2), np.pi - np.geomspace(1e-12, 1e-3, N // 4), np.full(N // 4, np.pi)])
    r = Rotation.from_rotvec(axes * angles[:, None])
    q = np.asarray(rot.matrix_to_quat(jnp.asarray(r.as_matrix())))
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    _same_rotation(q, r.as_quat(scalar_first=True), atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_matrix(jnp.asarray(q)), r.as_matrix(), atol=1e-14)


def test_axis_angle_round_trips_match_scipy(rng):
    v = _rotvecs(rng)
    r = Rotation.from_rotvec(v)
    q = np.asarray(rot.axis_angle_to_quat(jnp.asarray(v)))
    np.testing.assert_allclose(q, r.as_quat(scalar_first=True), atol=1e-15)  # angle < pi: w > 0 in both
    back = np.asarray(rot.quat_to_axis_angle(jnp.asarray(q)))
    np.testing.assert_allclose(back, v, atol=1e-13)
    # quat -> rotation vector of scipy's quaternions (either sign) is scipy's rotation vector.
    qs = _scipy_quats(rng)
    np.testing.assert_allclose(rot.quat_to_axis_angle(jnp.asarray(qs)),
                               Rotation.from_quat(qs, scalar_first=True).as_rotvec(), atol=1e-12)


def test_composition_rotate_and_inverse_match_scipy(rng):
    p, q = _scipy_quats(rng), _scipy_quats(rng)
    rp_, rq = Rotation.from_quat(p, scalar_first=True), Rotation.from_quat(q, scalar_first=True)
    pq = np.asarray(rot.quat_multiply(jnp.asarray(p), jnp.asarray(q)))
    _same_rotation(pq, (rp_ * rq).as_quat(scalar_first=True), atol=1e-14)
    np.testing.assert_allclose(rot.quat_to_matrix(jnp.asarray(pq)), rp_.as_matrix() @ rq.as_matrix(), atol=1e-14)
    v = rng.normal(size=(N, 3))
    np.testing.assert_allclose(rot.quat_rotate(jnp.asarray(p), jnp.asarray(v)), rp_.apply(v), atol=1e-14)
    inv = np.asarray(rot.quat_conjugate(jnp.asarray(p)))
    _same_rotation(inv, rp_.inv().as_quat(scalar_first=True), atol=1e-15)
    ident = np.asarray(rot.quat_multiply(jnp.asarray(p), jnp.asarray(inv)))
    _same_rotation(ident, np.tile([1.0, 0.0, 0.0, 0.0], (N, 1)), atol=1e-15)


def test_normalize_gives_unit_quaternion_with_nonnegative_w(rng):
    q = rng.normal(size=(N, 4)) * rng.uniform(0.1, 10.0, size=(N, 1))
    n = np.asarray(rot.quat_normalize(jnp.asarray(q)))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-15)
    assert (n[:, 0] >= 0).all()
    _same_rotation(n, q / np.linalg.norm(q, axis=-1, keepdims=True), atol=1e-15)
    np.testing.assert_array_equal(rot.quat_normalize(jnp.zeros(4)), np.zeros(4))  # safe at 0


def test_slerp_matches_scipy(rng):
    a, b = _scipy_quats(rng, 8), _scipy_quats(rng, 8)
    alpha = np.linspace(0.0, 1.0, 5)
    got = np.asarray(rot.slerp(jnp.asarray(a)[:, None], jnp.asarray(b)[:, None], jnp.broadcast_to(alpha, (8, 5))))
    for k in range(8):
        ends = Rotation.from_quat(np.stack([a[k], b[k]]), scalar_first=True)
        _same_rotation(got[k], Slerp([0.0, 1.0], ends)(alpha).as_quat(scalar_first=True), atol=1e-13)
    np.testing.assert_allclose(got[:, 0], a, atol=1e-15)  # alpha = 0 is a itself


def test_twist_angle_is_the_closest_rotation_about_the_axis(rng):
    q = jnp.asarray(_scipy_quats(rng, 16))
    axis = rng.normal(size=(16, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    tau = np.asarray(rot.quat_twist_angle(q, jnp.asarray(axis)))
    assert (np.abs(tau) <= np.pi).all()
    # |q . twist(t)| is largest at t = tau over a fine sweep of angles about the axis.
    sweep = np.linspace(-np.pi, np.pi, 20001)
    twists = Rotation.from_rotvec(sweep[:, None, None] * axis[None]).as_quat(scalar_first=True)  # (T, 16, 4)
    best = sweep[np.argmax(np.abs(np.sum(twists * np.asarray(q)[None], -1)), axis=0)]
    np.testing.assert_allclose(np.angle(np.exp(1j * (tau - best))), 0.0, atol=1e-3)
    # A rotation about the axis is its own twist.
    pure = rot.axis_angle_to_quat(jnp.asarray(axis * 0.7))
    np.testing.assert_allclose(rot.quat_twist_angle(pure, jnp.asarray(axis)), 0.7, atol=1e-14)


def test_inverse_right_jacobian_linearises_the_log(rng):
    """``log(exp(e) exp(d)) = e + Jr^-1(e) d + O(d^2)``, with scipy's exp and log."""
    e = _rotvecs(rng, 12)
    e[4] = [1e-5, -2e-5, 3e-6]  # the series branch
    jac = np.asarray(rot.inverse_right_jacobian(jnp.asarray(e)))
    h = 1e-6
    for k in range(len(e)):
        cols = []
        for i in range(3):
            d = np.zeros(3)
            d[i] = h
            plus = (Rotation.from_rotvec(e[k]) * Rotation.from_rotvec(d)).as_rotvec()
            minus = (Rotation.from_rotvec(e[k]) * Rotation.from_rotvec(-d)).as_rotvec()
            cols.append((plus - minus) / (2 * h))
        np.testing.assert_allclose(jac[k], np.stack(cols, axis=1), atol=1e-8)


def test_skew_and_det3(rng):
    a, b = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rot.skew(jnp.asarray(a)), b), np.cross(a, b), atol=1e-14)
    m = rng.normal(size=(N, 3, 3))
    np.testing.assert_allclose(rot.det3(jnp.asarray(m)), np.linalg.det(m), atol=1e-13)


# ------------------------------------------------------------------ alignment
def test_horn_align_recovers_a_known_rotation(rng):
    true = Rotation.random(rng=rng)
    src = rng.normal(size=(12, 3))
    t = np.array([0.3, -1.2, 2.0])
    dst = true.apply(src) + t
    weights = np.ones(12)
    dst[9:] += rng.normal(size=(3, 3))  # outliers, masked out
    weights[9:] = 0.0
    r, tt = rot.horn_align(jnp.asarray(src), jnp.asarray(dst), jnp.asarray(weights))
    np.testing.assert_allclose(r, true.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(tt, t, atol=1e-12)
    # A mirrored target still gives a proper rotation.
    r, _ = rot.horn_align(jnp.asarray(src), jnp.asarray(src * [1.0, 1.0, -1.0]))
    assert abs(float(np.linalg.det(np.asarray(r))) - 1.0) < 1e-12


def test_horn_alignment_is_a_proper_rotation_even_for_mirrored_clouds(rng):
    """Kabsch's sign correction (det3 of U and V^T) on clouds of 3-6 points: the exact pose
    is recovered, and a mirrored cloud, which the unconstrained SVD solution would fit
    by a reflection (det -1), still gets a rotation. det3 agrees with numpy's LU det."""
    m = rng.normal(size=(200, 3, 3))
    np.testing.assert_allclose(rot.det3(jnp.asarray(m)), np.linalg.det(m), rtol=1e-10, atol=1e-12)
    for n in (3, 4, 6):
        src = rng.normal(size=(n, 3))
        true = Rotation.random(rng=rng).as_matrix()
        dst = src @ true.T + np.array([0.1, -0.2, 0.3])
        r, _ = (np.asarray(v) for v in rot.horn_align(jnp.asarray(src), jnp.asarray(dst)))
        np.testing.assert_allclose(r, true, atol=1e-9)
        r, _ = (np.asarray(v) for v in rot.horn_align(jnp.asarray(src), jnp.asarray(dst * [1.0, 1.0, -1.0])))
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-9)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)


def _mcov(src, dst):
    s, d = src - src.mean(0), dst - dst.mean(0)
    return tuple(jnp.asarray(np.sum(s[:, a] * d[:, b])) for a in range(3) for b in range(3))


def test_horn_quat_recovers_a_known_rotation_and_keeps_the_prior_where_free(rng):
    true = Rotation.random(rng=rng)
    ident = tuple(jnp.asarray(c) for c in (1.0, 0.0, 0.0, 0.0))
    src = rng.normal(size=(8, 3))
    q = np.array([float(c) for c in rp.horn_quat(_mcov(src, true.apply(src)), ident, 10)])
    _same_rotation(q, true.as_quat(scalar_first=True), atol=1e-12)
    assert q[0] >= 0
    # The same rotation as the SVD alignment.
    r, _ = rot.horn_align(jnp.asarray(src), jnp.asarray(true.apply(src)))
    np.testing.assert_allclose(rot.quat_to_matrix(jnp.asarray(q)), r, atol=1e-12)
    # A prior orthogonal to the answer (a half turn from it): the largest column is taken.
    far = tuple(jnp.asarray(c) for c in (0.0, 0.0, 0.0, 1.0))
    q = np.array([float(c) for c in rp.horn_quat(_mcov(src, src), far, 10)])
    _same_rotation(q, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    # Collinear points leave the turn about their line free: any prior that maps the line
    # right is kept.
    line = np.outer(np.linspace(-1.0, 1.0, 5), [0.0, 0.0, 1.0])
    prior = true * Rotation.from_rotvec([0.0, 0.0, 0.8])
    q = rp.horn_quat(_mcov(line, true.apply(line)), tuple(jnp.asarray(c) for c in prior.as_quat(scalar_first=True)), 10)
    _same_rotation(np.array([float(c) for c in q]), prior.as_quat(scalar_first=True), atol=1e-10)
    # No data: the prior, normalised.
    zero = tuple(jnp.asarray(0.0) for _ in range(9))
    q = rp.horn_quat(zero, tuple(jnp.asarray(c) for c in (-2.0, 0.0, 0.0, 0.0)), 10)
    np.testing.assert_allclose([float(c) for c in q], [1.0, 0.0, 0.0, 0.0], atol=1e-15)


# -------------------------------------------------------- the forms agree
def test_planes_form_equals_array_form(rng):
    p, q = _scipy_quats(rng), _scipy_quats(rng)
    v = _rotvecs(rng)
    raw = rng.normal(size=(N, 4)) * rng.uniform(0.1, 10.0, size=(N, 1))
    jp, jq, jv = jnp.asarray(p), jnp.asarray(q), jnp.asarray(v)
    close = {"rtol": 1e-13, "atol": 1e-14}
    np.testing.assert_array_equal(_unplanes(rp.quat_multiply(_planes(p), _planes(q))), rot.quat_multiply(jp, jq))
    np.testing.assert_array_equal(_unplanes(rp.quat_conjugate(_planes(p))), rot.quat_conjugate(jp))
    np.testing.assert_allclose(_unplanes(rp.quat_normalize(_planes(raw))), rot.quat_normalize(jnp.asarray(raw)), **close)
    mat = _unplanes(rp.unit_quat_to_matrix(_planes(p))).reshape(N, 3, 3)
    np.testing.assert_allclose(mat, rot.quat_to_matrix(jp), **close)
    np.testing.assert_allclose(_unplanes(rp.axis_angle_to_quat(_planes(v))), rot.axis_angle_to_quat(jv), **close)
    np.testing.assert_allclose(_unplanes(rp.quat_to_axis_angle(_planes(p))), rot.quat_to_axis_angle(jp), **close)
    jac = _unplanes(rp.inverse_right_jacobian(_planes(v))).reshape(N, 3, 3)
    np.testing.assert_allclose(jac, rot.inverse_right_jacobian(jv), **close)


def test_host_form_equals_jax_form(rng):
    v = _rotvecs(rng)
    expected = np.asarray(rot.quat_to_matrix(rot.axis_angle_to_quat(jnp.asarray(v))))
    got = rot.axis_angle_to_matrix_np(v)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64
    np.testing.assert_allclose(got, expected, atol=1e-14)
    np.testing.assert_allclose(got, Rotation.from_rotvec(v).as_matrix(), atol=1e-14)
    np.testing.assert_array_equal(rot.axis_angle_to_matrix_np(np.zeros(3)), np.eye(3))
    # any batch shape, and lists
    np.testing.assert_allclose(rot.axis_angle_to_matrix_np(v.reshape(4, 16, 3)), expected.reshape(4, 16, 3, 3), atol=1e-14)
    np.testing.assert_allclose(rot.axis_angle_to_matrix_np([0.0, 0.0, np.pi / 2]) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                               atol=1e-15)
    a = rng.normal(size=(N, 3))
    np.testing.assert_array_equal(rot.skew_np(a), rot.skew(jnp.asarray(a)))


def test_host_quat_to_matrix_equals_jax_form_for_any_scale(rng):
    q = rng.normal(size=(4, 16, 4)) * rng.uniform(0.1, 10.0, size=(4, 16, 1))  # not unit: scale divided out
    q[0, 0] = 0.0  # the zero quaternion: no division by zero in either form
    got = rot.quat_to_matrix_np(q)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64 and got.shape == (4, 16, 3, 3)
    np.testing.assert_allclose(got, rot.quat_to_matrix(jnp.asarray(q)), rtol=0, atol=1e-15)
    unit = q[1:] / np.linalg.norm(q[1:], axis=-1, keepdims=True)
    np.testing.assert_allclose(got[1:], Rotation.from_quat(unit.reshape(-1, 4), scalar_first=True).as_matrix()
                               .reshape(3, 16, 3, 3), atol=1e-14)


# ---------------------------------------------------------------- gradients
def _fd_jacobian(f, x, h=1e-6):
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d.flat[i] = h
        cols.append((np.asarray(f(jnp.asarray(x + d))) - np.asarray(f(jnp.asarray(x - d)))) / (2 * h))
    return np.stack(cols, axis=-1).reshape(np.shape(f(jnp.asarray(x))) + x.shape)


def _ik_chain(delta, q0, prior):
    """The rotation chain of ik_solve's residuals: ``q = exp(delta) q0``, its matrix and
    ``log(prior^-1 q)``."""
    q = rotation.quat_multiply(rotation.axis_angle_to_quat(delta), q0)
    e = rotation.quat_to_axis_angle(rotation.quat_multiply(rotation.quat_conjugate(prior), q))
    return jnp.concatenate([rotation.quat_to_matrix(q).ravel(), e])


_chain = jax.jit(_ik_chain)
_chain_fwd = jax.jit(jax.jacfwd(_ik_chain))
_chain_rev = jax.jit(jax.jacrev(_ik_chain))


@pytest.mark.parametrize("at", ["zero", "small", "generic"])
def test_ik_residual_rotation_chain_gradient(rng, at):
    """ik_solve differentiates this chain (optimistix, implicit adjoint), at ``delta = 0``
    (the Taylor branch of the exponential) in every step."""
    q0, prior = (jnp.asarray(_scipy_quats(rng, 1)[0]) for _ in range(2))
    delta = {"zero": np.zeros(3), "small": np.array([2e-7, -1e-7, 3e-7]), "generic": rng.normal(size=3) * 0.5}[at]
    h = 1e-8 if at != "generic" else 1e-6  # stay inside the Taylor branch near 0
    fwd = _chain_fwd(jnp.asarray(delta), q0, prior)
    np.testing.assert_allclose(fwd, _fd_jacobian(lambda d: _chain(d, q0, prior), delta, h), atol=1e-7)
    np.testing.assert_allclose(_chain_rev(jnp.asarray(delta), q0, prior), fwd, atol=1e-13)


def test_log_of_product_gradient_is_the_inverse_right_jacobian(rng):
    """d/dd log(exp(e) exp(d)) at d = 0, by autodiff through the kit, is Jr^-1(e)."""
    e = jnp.asarray(_rotvecs(rng, 6)[3:])

    def log_of_product(d, e):
        return rot.quat_to_axis_angle(rot.quat_multiply(rot.axis_angle_to_quat(e), rot.axis_angle_to_quat(d)))

    jac = jax.jit(jax.vmap(jax.jacfwd(log_of_product), (None, 0)))(jnp.zeros(3), e)
    np.testing.assert_allclose(jac, rot.inverse_right_jacobian(e), atol=1e-12)


def test_horn_align_gradient(rng):
    """Procrustes (learn's functional fit) differentiates through horn_align."""
    true = Rotation.random(rng=rng)
    src = rng.normal(size=(6, 3))
    dst = true.apply(src) + rng.normal(size=(6, 3)) * 0.05 + [0.1, 0.2, 0.3]
    w = jnp.asarray(rng.uniform(0.5, 1.5, size=6))
    probe = jnp.asarray(rng.normal(size=(3, 3)))

    def f(x):
        r, t = rot.horn_align(x.reshape(6, 3), jnp.asarray(dst), w)
        return jnp.sum(r * probe) + jnp.sum(t * probe[0])

    grad = jax.jit(jax.grad(f))(jnp.asarray(src.ravel()))
    np.testing.assert_allclose(grad, _fd_jacobian(jax.jit(f), src.ravel()), atol=1e-7)
