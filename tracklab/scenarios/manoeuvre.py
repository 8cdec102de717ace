"""A manoeuvring target: straight legs, N-g coordinated turns and longitudinal accelerations.

The standard manoeuvre set of tracker evaluation. The flight is a sequence of
``segments`` ``(duration_s, turn_g, accel)`` flown one after another from t = 0;
after the last one the target flies straight at constant velocity. Within a
segment the velocity v obeys

    v̇ = accel · v/|v| + turn_g · g · n̂,    n̂ = ẑ × v_h/|v_h|,

a level coordinated turn of turn_g g (positive: left, counter-clockwise seen
from above; turn rate ω = turn_g g / |v_h|) combined with a longitudinal
acceleration ``accel`` (m/s², along the full velocity). In 3-D the turn is
horizontal: the vertical velocity changes only through ``accel``. (0, 0) is
straight flight.

The truth, in CV layout [x, ẋ, y, ẏ(, z, ż)] (east, north, up; m, m/s), starts
at ``initial`` at the prior epoch t = 0 and is the same in every run. Each
sample period is integrated with ``SUBSTEPS`` classical Runge–Kutta steps, each
flown wholly in the segment active at its midpoint, so segment boundaries take
effect to within dt / SUBSTEPS (exactly when they fall on sub-step edges). The
speed must stay positive (a zero velocity has no direction: the accelerations
are then taken as zero); that is checked where scenarios are configured.

The dynamics are deterministic: for the PCRLB, ``linear_gaussian`` gives the
one-step Jacobians F_k along the truth and Q = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.pytree import static
from tracklab.scenarios.kind import Scenario, ScenarioKind, numbers

G = 9.80665  # standard gravity, m/s²
SUBSTEPS = 8  # RK4 steps per sample period


def coordinated_turn_rate(speed, turn_g):
    """Turn rate (rad/s, positive left) of a level turn_g-g coordinated turn at horizontal ``speed`` (m/s)."""
    return turn_g * G / speed


def _unit(v):
    """v/|v|, and 0 where v = 0 (finite, with finite derivatives, at 0)."""
    s2 = jnp.sum(v * v)
    ok = s2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, s2, 1.0)), 0.0)


def acceleration(velocity, turn_g, accel):
    """Acceleration (dim,) of a target with ``velocity`` (dim,) flying (turn_g, accel)."""
    u = _unit(velocity)
    uh = _unit(velocity[:2])
    normal = jnp.concatenate([jnp.stack([-uh[1], uh[0]]), jnp.zeros_like(velocity[2:])])
    return accel * u + turn_g * G * normal


def _derivative(state, turn_g, accel):
    v = state[1::2]
    return jnp.stack([v, acceleration(v, turn_g, accel)], axis=-1).reshape(-1)


def _controls(segments, dtype):
    """(segment ends (S,), turn_g (S + 1,), accel (S + 1,)); the extra last entry is the final straight leg."""
    if not segments:
        z = jnp.zeros((1,), dtype)
        return jnp.zeros((0,), dtype), z, z
    seg = jnp.stack([jnp.stack([jnp.asarray(v, dtype) for v in s]) for s in segments])  # (S, 3)
    zero = jnp.zeros((1,), dtype)
    return jnp.cumsum(seg[:, 0]), jnp.concatenate([seg[:, 1], zero]), jnp.concatenate([seg[:, 2], zero])


def propagate(state, t0, dt, segments):
    """The state at t0 + dt from ``state`` at t0 (RK4, SUBSTEPS steps), flying ``segments`` from t = 0."""
    ends, turns, accels = _controls(segments, state.dtype)
    h = dt / SUBSTEPS

    def substep(x, i):
        k = jnp.sum(t0 + (i + 0.5) * h >= ends)  # segments finished at the sub-step's midpoint
        d = lambda y: _derivative(y, turns[k], accels[k])  # noqa: E731
        k1 = d(x)
        k2 = d(x + 0.5 * h * k1)
        k3 = d(x + 0.5 * h * k2)
        k4 = d(x + h * k3)
        return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    x, _ = jax.lax.scan(substep, state, jnp.arange(SUBSTEPS, dtype=state.dtype))
    return x


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Manoeuvre(Scenario):
    dt: float = static()
    steps: int = static()
    initial: tuple = ()  # CV layout, 2·dim values
    segments: tuple = ()  # ((duration_s, turn_g, accel), ...), flown in order from t = 0

    per_run = False  # the same truth in every run
    gaussian = True  # deterministic dynamics: PCRLB with the Jacobians along the truth, Q = 0

    @property
    def dim(self) -> int:
        return len(self.initial) // 2

    def initial_state(self):
        return jnp.stack([jnp.asarray(v) for v in self.initial])

    def problem(self) -> str | None:
        """Why this manoeuvre cannot be flown (None if it can): ``initial`` not 4 or 6 finite
        numbers, a horizontal velocity of zero, a segment not (duration > 0, turn_g, accel), or
        a speed brought to zero or below."""
        init = np.asarray(self.initial, float)
        if init.shape not in ((4,), (6,)) or not np.all(np.isfinite(init)):
            return f"initial {tuple(self.initial)}: expected 4 or 6 finite numbers [x, vx, y, vy(, z, vz)]"
        if np.hypot(init[1], init[3]) <= 0:
            return "initial: the horizontal velocity (vx, vy) must not be zero"
        speed = float(np.linalg.norm(init[1::2]))
        for j, seg in enumerate(self.segments):
            seg = np.asarray(seg, float) if np.ndim(seg) == 1 else None
            if seg is None or seg.shape != (3,) or not np.all(np.isfinite(seg)) or seg[0] <= 0:
                return (f"segments[{j}] = {self.segments[j]!r}: expected (duration_s > 0, turn_g, accel), "
                        f"e.g. (20.0, 4.0, 0.0) for a 4 g left turn of 20 s")
            speed += seg[2] * seg[0]  # a turn is perpendicular to the velocity: only accel changes the speed
            if speed <= 0:
                return f"segments[{j}]: accel {seg[2]:g} m/s² brings the speed to zero or below"
        return None

    def transition(self, state, k):
        """The state at t = k·dt from ``state`` at (k − 1)·dt."""
        return propagate(state, (k - 1) * self.dt, self.dt, self.segments)

    def truth(self):
        s0 = self.initial_state()

        def step(s, k):
            s = self.transition(s, k)
            return s, s

        _, path = jax.lax.scan(step, s0, jnp.arange(1, self.steps + 1, dtype=s0.dtype))
        return jnp.concatenate([s0[None], path])

    def simulate(self, key):
        """Truth states (steps + 1, 2·dim) in CV layout; row 0 is the prior epoch. ``key`` is unused."""
        return self.truth()

    def linear_gaussian(self):
        """(F, Q): F (steps, n, n) with F[k − 1] = ∂truth_k/∂truth_{k−1} along the truth, Q = 0 (n, n)."""
        n = 2 * self.dim
        return np.asarray(_jacobians_along_truth(self)), np.zeros((n, n))


@jax.jit
def _jacobians_along_truth(scenario: Manoeuvre):
    """The one-step Jacobians along a manoeuvre's truth, one program per shape (its numbers are
    arguments): eagerly, its scans and Jacobians took about 0.6 s of every results table."""
    x = scenario.truth()
    ks = jnp.arange(1, scenario.steps + 1, dtype=x.dtype)
    return jax.vmap(jax.jacfwd(scenario.transition))(x[:-1], ks)


def _manoeuvre(context, n, fields):
    """initial [x, vx, y, vy(, z, vz)] and segments, a list of at least one table {duration (s),
    turn_g (g, + left), accel (m/s², along the velocity)}; what the flight as a whole must keep (a
    moving target) is the scenario's own check (``problem``)."""
    init = numbers(fields.get("initial"), (4, 6))
    if init is None:
        raise fields.error("initial", fields.get("initial"), "must be 4 or 6 finite numbers [x, vx, y, vy(, z, vz)]")
    if context.dim is not None and len(init) // 2 != context.dim:
        raise fields.error("initial", list(init), f"is {len(init) // 2}-D: the sensors observe {context.dim}-D positions")
    table = fields.get("segments")
    if not isinstance(table, list) or not table:
        raise fields.error("segments", table, "must be a list of at least one table {duration, turn_g, accel} (a "
                           "straight flight: kind = \"constant_velocity\")")
    segments = []
    for j, seg in enumerate(table, start=1):
        ss = fields.table(f"segments[{j}]", seg)
        segments.append((ss.number("duration", required=True, positive=True),
                         ss.number("turn_g", 0.0, lo=-100.0, hi=100.0), ss.number("accel", 0.0, lo=-1000.0, hi=1000.0)))
        ss.check_unknown()
    scenario = Manoeuvre(dt=context.dt, steps=context.steps, initial=init, segments=tuple(segments))
    why = scenario.problem()
    if why:
        at_start = why.startswith("initial")
        raise fields.error("initial" if at_start else "segments", list(init) if at_start else table, why)
    return scenario


MANOEUVRE = ScenarioKind(
    "manoeuvre", "straight legs, N-g coordinated turns, longitudinal accelerations: initial, segments (2-D or 3-D)",
    {}, _manoeuvre)
