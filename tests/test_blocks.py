"""The building blocks of a Gaussian filter (``tracklab.filters.blocks``) against NumPy,
on tiny shapes: Joseph-form update, NaN masking, angle wrapping, the EKF's autodiff
Jacobian, gradients, and the assembled filter with nothing present."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.batching import runs_last
from tracklab.filters import Gaussian, Meas, ekf_update, innovation, kalman_filter, predict
from tracklab.filters import update as eager_update

N, M = 4, 3
update = jax.jit(eager_update, static_argnames="angles")  # one small program per shape, not one per operation


def spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@pytest.fixture
def problem():
    rng = np.random.default_rng(7)
    return dict(x=rng.normal(size=N), P=spd(rng, N), H=rng.normal(size=(M, N)), R=spd(rng, M), z=rng.normal(size=M))


def numpy_joseph(x, P, H, R, z):
    """The textbook update, Joseph form, in NumPy."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    nu = z - H @ x
    A = np.eye(len(x)) - K @ H
    return x + K @ nu, A @ P @ A.T + K @ R @ K.T, nu, S


def test_update_is_the_joseph_form_kalman_update(problem):
    p = problem
    u = update(Gaussian(jnp.asarray(p["x"]), jnp.asarray(p["P"])), jnp.asarray(p["z"]), jnp.asarray(p["H"]),
               jnp.asarray(p["R"]))
    want = numpy_joseph(p["x"], p["P"], p["H"], p["R"], p["z"])
    for got, ref in zip((u.x, u.P, u.nu, u.S), want):
        assert got.dtype == np.float64
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    assert np.asarray(u.used).all()
    np.testing.assert_array_equal(u.P, np.asarray(u.P).T)
    g = predict(Gaussian(u.x, u.P), jnp.asarray(p["P"]), jnp.asarray(p["R"][:1, :1] * np.eye(N)))  # any F, Q
    np.testing.assert_allclose(g.x, p["P"] @ np.asarray(u.x), rtol=1e-12)
    np.testing.assert_allclose(g.P, p["P"] @ np.asarray(u.P) @ p["P"].T + p["R"][0, 0] * np.eye(N), rtol=1e-12)


def test_a_nan_component_is_the_update_without_its_row(problem):
    p = problem
    g = Gaussian(jnp.asarray(p["x"]), jnp.asarray(p["P"]))
    z = p["z"].copy()
    z[1] = np.nan
    u = update(g, jnp.asarray(z), jnp.asarray(p["H"]), jnp.asarray(p["R"]))
    keep = [0, 2]
    x, P, nu, S = numpy_joseph(p["x"], p["P"], p["H"][keep], p["R"][np.ix_(keep, keep)], p["z"][keep])
    np.testing.assert_allclose(u.x, x, rtol=1e-12)
    np.testing.assert_allclose(u.P, P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    np.testing.assert_array_equal(u.used, [True, False, True])
    np.testing.assert_allclose(np.asarray(u.nu)[keep], nu, rtol=1e-12)
    assert u.nu[1] == 0.0
    np.testing.assert_allclose(np.asarray(u.S)[np.ix_(keep, keep)], S, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(u.S)[1], [0.0, 1.0, 0.0])  # decoupled, unit variance
    np.testing.assert_array_equal(np.asarray(u.S)[:, 1], [0.0, 1.0, 0.0])
    # the same flags given as ``present``, with the absent value anything finite
    v = update(g, jnp.asarray(np.nan_to_num(z)), jnp.asarray(p["H"]), jnp.asarray(p["R"]),
               present=jnp.array([True, False, True]))
    for a, b in zip(u, v):
        np.testing.assert_array_equal(a, b)


def test_a_bearing_innovation_across_pi_is_wrapped():
    x = jnp.array([-1000.0, 0.0, 1.0, 0.0])  # just above the −x axis: bearing ≈ π − 0.001
    H = jnp.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1e-3, 0.0]])
    z = jnp.array([1000.0, -jnp.pi + 0.002])  # just below it: the innovation is +0.001 rad, not −2π
    h_x = jnp.array([1000.0, jnp.pi - 0.001])
    g = Gaussian(x, jnp.eye(4))
    R = jnp.diag(jnp.array([1.0, 1e-6]))
    u = update(g, z, H, R, h_x=h_x, angles=(False, True))
    np.testing.assert_allclose(u.nu, [0.0, 0.003], atol=1e-12)
    ref = update(g, z.at[1].add(2 * jnp.pi), H, R, h_x=h_x)  # the same bearing, unwrapped by hand
    np.testing.assert_allclose(u.x, ref.x, rtol=1e-12)
    assert abs(update(g, z, H, R, h_x=h_x).nu[1]) > 6.0  # not flagged: not wrapped
    w = innovation(jnp.array([jnp.pi, -jnp.pi, 3.0]), jnp.array([-jnp.pi, jnp.pi, -3.0]), (True, True, True))
    assert np.all((np.asarray(w) > -np.pi) & (np.asarray(w) <= np.pi))


def range_bearing(x):
    return jnp.stack([jnp.hypot(x[0], x[2]), jnp.arctan2(x[2], x[0])])


def test_ekf_update_by_autodiff_equals_the_analytic_jacobian():
    x = np.array([3000.0, 20.0, -4000.0, 5.0])
    P = np.diag([100.0, 10.0, 100.0, 10.0]) ** 2
    px, py = x[0], x[2]
    r = np.hypot(px, py)
    H = np.array([[px / r, 0.0, py / r, 0.0], [-py / r**2, 0.0, px / r**2, 0.0]])
    z = np.array([5010.0, np.arctan2(py, px) + 0.01])
    R = np.diag([25.0**2, 0.003**2])
    g = Gaussian(jnp.asarray(x), jnp.asarray(P))
    auto = jax.jit(ekf_update, static_argnums=2, static_argnames="angles")(g, jnp.asarray(z), range_bearing,
                                                                           jnp.asarray(R), angles=(False, True))
    hand = update(g, jnp.asarray(z), jnp.asarray(H), jnp.asarray(R), h_x=range_bearing(jnp.asarray(x)),
                  angles=(False, True))
    for a, b in zip(auto[:4], hand[:4]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(np.asarray(b)).max())


def test_an_update_on_some_columns_is_the_full_update(problem):
    """H zero outside the state components ``columns`` names, given as those columns only: the
    same update as with the whole H, one run or many with the runs last, a component absent or
    not; the EKF's H formed on those columns; a columns tuple that does not fit refused."""
    p = problem
    cols = (0, 2)
    H = np.zeros((M, N))
    H[:, cols] = p["H"][:, cols]
    z = p["z"].copy()
    z[1] = np.nan
    rng = np.random.default_rng(3)
    xs = p["x"] + rng.normal(size=(6, N))

    def both(x, z):
        g = Gaussian(x, jnp.asarray(p["P"]))
        return (eager_update(g, z, jnp.asarray(H), jnp.asarray(p["R"])),
                eager_update(g, z, jnp.asarray(H[:, cols]), jnp.asarray(p["R"]), columns=cols))

    one = jax.jit(both)(jnp.asarray(p["x"]), jnp.asarray(z))
    many = jax.jit(runs_last(both, in_axes=(-1, None), size=6))(jnp.asarray(xs.T), jnp.asarray(p["z"]))
    for full, some in (one, many):
        for a, b in zip(full, some):
            np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-13 * np.abs(np.asarray(a)).max())
    want = numpy_joseph(xs[4], p["P"], H, p["R"], p["z"])
    np.testing.assert_allclose(many[1].P[..., 4], want[1], rtol=1e-12, atol=1e-12 * np.abs(want[1]).max())

    x = np.array([3000.0, 20.0, -4000.0, 5.0])
    g = Gaussian(jnp.asarray(x), jnp.asarray(np.diag([100.0, 10.0, 100.0, 10.0]) ** 2))
    ekf = jax.jit(ekf_update, static_argnums=2, static_argnames=("angles", "columns"))
    zr, R = jnp.array([5010.0, np.arctan2(x[2], x[0]) + 0.01]), jnp.diag(jnp.array([25.0**2, 0.003**2]))
    for a, b in zip(ekf(g, zr, range_bearing, R, angles=(False, True)),
                    ekf(g, zr, range_bearing, R, angles=(False, True), columns=(0, 2))):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-13 * np.abs(np.asarray(a)).max())
    for bad in ((2, 0), (0, 4), [0, 2], ()):
        with pytest.raises(ValueError, match="columns"):
            eager_update(Gaussian(jnp.asarray(p["x"]), jnp.asarray(p["P"])), jnp.asarray(p["z"]),
                         jnp.asarray(H[:, cols]), jnp.asarray(p["R"]), columns=bad)
    with pytest.raises(ValueError, match=r"expected \(m, 2\) for the columns \(0, 2\)"):
        eager_update(Gaussian(jnp.asarray(p["x"]), jnp.asarray(p["P"])), jnp.asarray(p["z"]), jnp.asarray(H),
                     jnp.asarray(p["R"]), columns=cols)


def test_the_gradient_through_update_is_the_finite_difference(problem):
    p = problem
    z = p["z"].copy()
    z[2] = np.nan  # through the masking too

    def loss(r, x0):
        u = update(Gaussian(x0, jnp.asarray(p["P"])), jnp.asarray(z), jnp.asarray(p["H"]), r * jnp.asarray(p["R"]))
        return jnp.sum(u.x**2) + jnp.trace(u.P) + jnp.sum(u.nu * u.S[:, 0])

    r, x0 = 1.3, jnp.asarray(p["x"])
    dr, dx = jax.jit(jax.grad(loss, argnums=(0, 1)))(r, x0)
    assert np.isfinite(dx).all()
    e = 1e-6
    steps = np.concatenate([[[e, 0, 0, 0, 0], [-e, 0, 0, 0, 0]], np.kron(np.eye(N + 1)[1:], [[e], [-e]])])
    values = np.asarray(jax.jit(jax.vmap(lambda d: loss(r + d[0], x0 + d[1:])))(jnp.asarray(steps)))
    fd = (values[0::2] - values[1::2]) / (2 * e)  # central differences: r, then each component of x0
    np.testing.assert_allclose(dr, fd[0], rtol=1e-6)
    np.testing.assert_allclose(dx, fd[1:], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(loss, argnums=1))(r, x0), dx, rtol=1e-10)


def test_nothing_present_keeps_the_prior_and_reports_dof_0(problem):
    p = problem
    g = Gaussian(jnp.asarray(p["x"]), jnp.asarray(p["P"]))
    u = update(g, jnp.full(M, jnp.nan), jnp.asarray(p["H"]), jnp.asarray(p["R"]))
    np.testing.assert_array_equal(u.x, g.x)
    np.testing.assert_array_equal(u.P, g.P)
    np.testing.assert_array_equal(u.nu, np.zeros(M))
    np.testing.assert_array_equal(u.S, np.eye(M))
    assert not np.asarray(u.used).any()

    F, Q = jnp.eye(N), 0.1 * jnp.eye(N)
    flt = kalman_filter({}, lambda params, g: predict(g, F, Q),
                        lambda params, g, z, present: update(g, z, jnp.asarray(p["H"]), jnp.asarray(p["R"]),
                                                             present=present))
    meas = Meas(jnp.full(M, jnp.nan), jnp.asarray(0.0), jnp.asarray(True))
    step, coast = jax.jit(flt.step), jax.jit(flt.coast)
    state, out = step({}, g, meas)
    assert out.dof == 0 and not out.valid
    np.testing.assert_array_equal(out.x, out.x_pred)
    np.testing.assert_array_equal(state.P, predict(g, F, Q).P)
    coasted, out_c = coast({}, g, meas)  # the cheap step: the same
    for a, b in zip(out, out_c):
        np.testing.assert_array_equal(a, b)
    state, out = step({}, g, meas._replace(z=jnp.asarray(p["z"])))
    assert out.dof == M and out.valid


def test_vmap_with_a_shared_pattern_and_float32(problem):
    """Under ``vmap`` over runs with the report pattern shared, the covariance comes out the same
    for every run; in float32 the update stays in float32, close to float64."""
    p = problem
    rng = np.random.default_rng(1)
    zs = p["z"] + rng.normal(size=(5, M))
    present = jnp.array([True, False, True])

    def run(z, x0):
        return update(Gaussian(x0, jnp.asarray(p["P"])), z, jnp.asarray(p["H"]), jnp.asarray(p["R"]), present=present)

    u = jax.jit(jax.vmap(run, in_axes=(0, None)))(jnp.asarray(zs), jnp.asarray(p["x"]))
    assert u.x.shape == (5, N)
    np.testing.assert_array_equal(u.P, np.broadcast_to(u.P[0], u.P.shape))
    with jax.enable_x64(False):
        f32 = lambda a: jnp.asarray(a, jnp.float32)
        v = update(Gaussian(f32(p["x"]), f32(p["P"])), f32(zs[0]), f32(p["H"]), f32(p["R"]), present=present)
        assert v.x.dtype == v.P.dtype == v.S.dtype == jnp.float32
    np.testing.assert_allclose(v.x, u.x[0], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(v.P, u.P[0], rtol=1e-4, atol=1e-5)
