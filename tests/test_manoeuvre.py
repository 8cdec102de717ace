"""The manoeuvring-target truth against closed forms: lines, circles, constant acceleration."""

import jax
import numpy as np
import pytest

from tracklab.scenarios.manoeuvre import G, Manoeuvre, coordinated_turn_rate


def truth64(scn):
    with jax.enable_x64(True):
        return np.asarray(scn.simulate(None))


def times(scn):
    return scn.dt * np.arange(scn.steps + 1)


def circle(p0, v, heading, omega, t):
    """Closed-form level turn at rate omega (rad/s, left positive) from p0 with speed v on heading (rad from +x)."""
    a = heading + omega * t
    pos = p0[None, :] + (v / omega) * np.stack([np.sin(a) - np.sin(heading), np.cos(heading) - np.cos(a)], -1)
    vel = v * np.stack([np.cos(a), np.sin(a)], -1)
    return pos, vel


@pytest.mark.parametrize("initial", [(100.0, 150.0, -200.0, 40.0), (1.0, -30.0, 2.0, 250.0, 3000.0, 12.0)])
def test_straight_segments_are_the_cv_line(initial):
    scn = Manoeuvre(dt=0.5, steps=30, initial=initial, segments=((4.0, 0.0, 0.0), (3.25, 0.0, 0.0)))
    x = truth64(scn)
    s0 = np.asarray(initial)
    t = times(scn)
    expect = np.tile(s0, (len(t), 1))
    expect[:, 0::2] += t[:, None] * s0[1::2][None, :]
    np.testing.assert_allclose(x, expect, rtol=1e-9, atol=1e-9 * np.abs(expect).max())
    with jax.enable_x64(True):
        F, Q = scn.linear_gaussian()
    n = len(initial)
    cv = np.kron(np.eye(n // 2), np.array([[1.0, scn.dt], [0.0, 1.0]]))
    assert F.shape == (scn.steps, n, n) and Q.shape == (n, n)
    np.testing.assert_allclose(F, np.broadcast_to(cv, F.shape), atol=1e-12)
    assert not Q.any()


@pytest.mark.parametrize("turn_g", [3.0, -5.0])
def test_coordinated_turn_is_a_circle(turn_g):
    v, heading, T, dt = 220.0, np.radians(30.0), 12.0, 0.5
    p0 = np.array([500.0, -800.0])
    initial = (p0[0], v * np.cos(heading), p0[1], v * np.sin(heading))
    scn = Manoeuvre(dt=dt, steps=int(T / dt), initial=initial, segments=((T, turn_g, 0.0),))
    x = truth64(scn)
    t = times(scn)
    omega = turn_g * G / v
    assert coordinated_turn_rate(v, turn_g) == pytest.approx(omega)
    R = v**2 / (abs(turn_g) * G)
    pos, vel = circle(p0, v, heading, omega, t)
    np.testing.assert_allclose(x[:, 0::2], pos, rtol=0, atol=1e-6 * R)
    np.testing.assert_allclose(x[:, 1::2], vel, rtol=0, atol=1e-6 * v)
    # the centre lies R to the left of the initial velocity for a left (positive) turn, to the right otherwise
    u = np.array([np.cos(heading), np.sin(heading)])
    centre = p0 + np.sign(turn_g) * R * np.array([-u[1], u[0]])
    np.testing.assert_allclose(np.linalg.norm(x[:, 0::2] - centre, axis=1), R, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(x[:, 1::2], axis=1), v, rtol=1e-6)
    turned = np.arctan2(x[-1, 3], x[-1, 1]) - heading
    assert np.angle(np.exp(1j * (turned - omega * T))) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("a", [4.0, -6.0])
def test_longitudinal_acceleration(a):
    v0, T = 180.0, 10.0
    u = np.array([0.6, -0.8])
    initial = (10.0, v0 * u[0], 20.0, v0 * u[1])
    scn = Manoeuvre(dt=1.0, steps=10, initial=initial, segments=((T, 0.0, a),))
    x = truth64(scn)
    t = times(scn)
    speed = np.linalg.norm(x[:, 1::2], axis=1)
    np.testing.assert_allclose(speed, v0 + a * t, rtol=1e-9)
    np.testing.assert_allclose(x[:, 1::2] / speed[:, None], np.broadcast_to(u, (len(t), 2)), atol=1e-12)
    d = x[:, 0::2] - np.array([10.0, 20.0])
    np.testing.assert_allclose(d @ u, v0 * t + a * t**2 / 2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d @ np.array([-u[1], u[0]]), 0.0, atol=1e-9)


def test_three_d_turn_keeps_the_climb_and_acceleration_is_along_the_3d_velocity():
    vx, vy, vz, z0, T = 200.0, 0.0, 15.0, 3000.0, 8.0
    initial = (0.0, vx, 0.0, vy, z0, vz)
    t = np.arange(17) * 0.5
    turn = truth64(Manoeuvre(dt=0.5, steps=16, initial=initial, segments=((T, 4.0, 0.0),)))
    np.testing.assert_allclose(turn[:, 4], z0 + vz * t, rtol=1e-12)
    np.testing.assert_allclose(turn[:, 5], vz, rtol=1e-12)
    vh = np.hypot(vx, vy)
    pos, vel = circle(np.zeros(2), vh, 0.0, 4.0 * G / vh, t)  # the turn rate of the horizontal speed
    np.testing.assert_allclose(turn[:, [0, 2]], pos, atol=1e-6 * vh**2 / (4 * G))
    np.testing.assert_allclose(turn[:, [1, 3]], vel, atol=1e-6 * vh)

    a = 5.0
    acc = truth64(Manoeuvre(dt=0.5, steps=16, initial=initial, segments=((T, 0.0, a),)))
    v0 = np.array([vx, vy, vz])
    s0 = np.linalg.norm(v0)
    scale = (s0 + a * t) / s0  # the velocity keeps its 3-D direction and grows by a t
    np.testing.assert_allclose(acc[:, 1::2], scale[:, None] * v0, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(acc[:, 4], z0 + vz / s0 * (s0 * t + a * t**2 / 2), rtol=1e-9)


def test_segments_in_sequence():
    v, T1, dt = 250.0, 6.0, 0.5
    initial = (0.0, 0.0, 0.0, v)  # heading north
    scn = Manoeuvre(dt=dt, steps=30, initial=initial, segments=((T1, 4.0, 0.0), (9.0, 0.0, 0.0)))
    x = truth64(scn)
    t = times(scn)
    k1 = int(T1 / dt)
    pos, vel = circle(np.zeros(2), v, np.pi / 2, 4.0 * G / v, t[: k1 + 1])
    np.testing.assert_allclose(x[: k1 + 1, 0::2], pos, atol=1e-6 * v**2 / (4 * G))
    np.testing.assert_allclose(x[: k1 + 1, 1::2], vel, atol=1e-6 * v)
    p1, v1 = x[k1, 0::2], x[k1, 1::2]
    after = t[k1:] - T1
    np.testing.assert_allclose(x[k1:, 0::2], p1 + after[:, None] * v1, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(x[k1:, 1::2], np.broadcast_to(v1, (len(after), 2)), rtol=1e-12)
    assert abs(v1[0]) > 0.5 * v  # it did turn (left, from north towards west)
    assert v1[0] < 0


def test_jacobians_match_finite_differences():
    scn = Manoeuvre(dt=1.0, steps=12, initial=(0.0, 180.0, 100.0, 60.0, 2000.0, -20.0),
                    segments=((3.0, 0.0, 0.0), (4.5, 6.0, 3.0), (2.0, -2.0, -4.0)))
    with jax.enable_x64(True):
        F, Q = scn.linear_gaussian()
        x = np.asarray(scn.truth())
        f = jax.jit(scn.transition)
        n = x.shape[1]
        assert F.shape == (scn.steps, n, n) and F.dtype == np.float64
        for k in range(1, scn.steps + 1):
            np.testing.assert_allclose(np.asarray(f(x[k - 1], float(k))), x[k], rtol=1e-12)
            fd = np.empty((n, n))
            for j in range(n):
                e = np.zeros(n)
                e[j] = 1e-3
                fd[:, j] = (np.asarray(f(x[k - 1] + e, float(k))) - np.asarray(f(x[k - 1] - e, float(k)))) / 2e-3
            np.testing.assert_allclose(F[k - 1], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    assert not np.allclose(F[4], F[0])  # the turn's Jacobian is not the CV one


def test_pytree_under_jit():
    scn = Manoeuvre(dt=0.5, steps=20, initial=(0.0, 200.0, 0.0, 0.0),
                    segments=((2.0, 0.0, 0.0), (5.0, 3.0, 1.0)))
    other = Manoeuvre(dt=0.5, steps=20, initial=(0.0, 200.0, 0.0, 0.0),
                      segments=((2.0, 0.0, 0.0), (5.0, -7.0, 1.0)))
    assert jax.tree_util.tree_structure(scn) == jax.tree_util.tree_structure(other)
    traces = []

    def sim(s):
        traces.append(1)
        return s.simulate(None)

    with jax.enable_x64(True):
        jitted = jax.jit(sim)
        np.testing.assert_allclose(np.asarray(jitted(scn)), truth64(scn), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(np.asarray(jitted(other)), truth64(other), rtol=1e-12, atol=1e-9)
    assert len(traces) == 1  # the turn is a leaf: no recompilation
    assert not np.allclose(truth64(scn), truth64(other))


def test_defaults_and_zero_speed():
    still = Manoeuvre(dt=1.0, steps=4, initial=(5.0, 0.0, 6.0, 0.0), segments=((3.0, 2.0, 1.0),))
    x = truth64(still)
    assert np.isfinite(x).all()
    with jax.enable_x64(True):
        F, _ = still.linear_gaussian()
    assert np.isfinite(F).all()
    plain = Manoeuvre(dt=1.0, steps=3, initial=(0.0, 10.0, 0.0, 0.0))  # no segments: straight
    np.testing.assert_allclose(truth64(plain)[:, 0], [0.0, 10.0, 20.0, 30.0])
    assert plain.dim == 2 and Manoeuvre.per_run is False and Manoeuvre.gaussian is True
    x32 = np.asarray(Manoeuvre(dt=0.5, steps=20, initial=(0.0, 200.0, 0.0, 0.0), segments=((10.0, 5.0, 0.0),))
                     .simulate(None))
    x64 = truth64(Manoeuvre(dt=0.5, steps=20, initial=(0.0, 200.0, 0.0, 0.0), segments=((10.0, 5.0, 0.0),)))
    np.testing.assert_allclose(x32, x64, rtol=1e-4, atol=0.05)
