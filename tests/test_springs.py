"""Springs and dampers (DBD 8.1) and user forces (DBD 8): frequency, iteration independence, (109)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd


def oscillator(stiffness=100.0, damping=0.0, mass=1.0, stretch=0.1, dt=1 / 240, iterations=4, user_force=False):
    """A body on a spring to a world point, moving along x with no gravity."""
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    body = b.add_body(pos=(stretch, 0, 0), mass=mass, inertia=(0.01, 0.01, 0.01))
    if user_force:

        def spring_force(pos, quat, vel, ang_vel, params):
            force = -params["stiffness"] * pos - params["damping"] * vel
            return force, jnp.zeros_like(force)

        b.add_force([body], spring_force, params={"stiffness": stiffness, "damping": damping})
    else:
        b.add_spring(dbd.WORLD, body, anchor_a=(-1, 0, 0), anchor_b=(stretch, 0, 0), stiffness=stiffness,
                     damping=damping, rest_length=1.0)  # fmt: skip
    return b.finalize(dt=dt, iterations=iterations)


def positions(model, seconds):
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=int(round(seconds / model.dt))))(dbd.init(model))
    return np.asarray(trajectory.pos[:, :, 0])


def period_from_crossings(x, dt):
    """Mean period from the upward zero crossings (linear interpolation between samples)."""
    crossings = [i + x[i] / (x[i] - x[i + 1]) for i in range(len(x) - 1) if x[i] < 0.0 <= x[i + 1]]
    return float(np.mean(np.diff(crossings)) * dt)


def implicit_euler(stiffness, damping, mass, x, v, dt, steps):
    """The implicit update (109): f' = -k x' - nu v', v' = v + dt f' / m, x' = x + dt v'."""
    result = []
    for _ in range(steps):
        v = (v - dt * stiffness * x / mass) / (1.0 + dt * damping / mass + dt**2 * stiffness / mass)
        x = x + dt * v
        result.append(x)
    return np.asarray(result)


@pytest.mark.parametrize("user_force", [False, True], ids=["add_spring", "add_force"])
def test_spring_mass_oscillates_at_the_analytic_frequency(user_force):
    model = oscillator(stiffness=100.0, mass=1.0, dt=1 / 1000, user_force=user_force)
    x = positions(model, 3.0)[:, 0]
    period = period_from_crossings(x, model.dt)
    expected = 2 * np.pi / np.sqrt(100.0)
    print(f"\nspring-mass period {period:.5f} s, analytic {expected:.5f} s")
    assert abs(period - expected) < 0.01 * expected


@pytest.mark.parametrize("user_force", [False, True], ids=["add_spring", "add_force"])
def test_damped_spring_follows_the_implicit_update(float64, user_force):
    stiffness, damping, mass, dt = 50.0, 1.5, 2.0, 1 / 60
    model = oscillator(stiffness, damping, mass, stretch=0.2, dt=dt, user_force=user_force)
    x = positions(model, 2.0)[:, 0]
    expected = implicit_euler(stiffness, damping, mass, 0.2, 0.0, dt, len(x))
    # XPBD's gamma in place of (1 + gamma) would decay at a different rate (DBD (108)-(109)).
    np.testing.assert_allclose(x, expected, rtol=1e-7, atol=1e-10)
    assert abs(x[-1]) < 0.5 * 0.2  # it did decay


def test_spring_stiffness_does_not_depend_on_the_iteration_count():
    """Three masses in series on stiff springs: with 2 or 20 iterations the same slowest period."""

    def period(iterations):
        b = dbd.ModelBuilder(gravity=(0, 0, 0))
        previous, anchor = dbd.WORLD, np.zeros(3)
        for i in range(3):
            centre = np.array([(i + 1) * 1.0 + 0.05 * (i + 1), 0, 0])  # every spring stretched 5 cm
            body = b.add_body(pos=centre, mass=1.0, inertia=(0.01, 0.01, 0.01))
            b.add_spring(previous, body, anchor, centre, stiffness=400.0, rest_length=1.0)
            previous, anchor = body, centre
        model = b.finalize(dt=1 / 120, iterations=iterations)
        x = positions(model, 6.0)[:, 2] - 3.0  # the last mass, about its rest position
        return period_from_crossings(x, model.dt)

    # The slowest mode of three unit masses on unit springs has omega^2 = 2 - 2 cos(pi / 7) per k/m.
    expected = 2 * np.pi / np.sqrt(400.0 * (2 - 2 * np.cos(np.pi / 7)))
    few, many = period(2), period(20)
    print(f"\nseries springs: period {few:.4f} s with 2 iterations, {many:.4f} s with 20, analytic {expected:.4f}")
    assert abs(few - many) < 0.01 * many
    assert abs(many - expected) < 0.01 * expected


def test_user_force_constant_push_gives_acceleration_force_over_mass():
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    body = b.add_body(pos=(0, 0, 0), mass=2.0, inertia=(0.1, 0.1, 0.1))

    def push(pos, quat, vel, ang_vel, params):
        return jnp.broadcast_to(params, pos.shape), jnp.zeros_like(pos)

    b.add_force([body], push, params=np.array([3.0, 0.0, -1.0]))
    model = b.finalize(dt=1 / 60)
    final, _ = dbd.rollout(model, dbd.init(model), steps=60)
    np.testing.assert_allclose(np.asarray(final.vel[0]), np.array([1.5, 0.0, -0.5]), rtol=1e-5)


def test_user_torque_spring_oscillates_at_the_angular_frequency():
    """A torsion spring given as a user torque -k theta about z: period 2 pi sqrt(I / k)."""
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    angle0 = 0.1
    body = b.add_body(pos=(0, 0, 0), quat=(np.cos(angle0 / 2), 0, 0, np.sin(angle0 / 2)), mass=1.0,
                      inertia=(0.05, 0.05, 0.02))  # fmt: skip

    def torsion(pos, quat, vel, ang_vel, params):
        angle = dbd.math.quat_log(quat)  # rotation vector
        return jnp.zeros_like(pos), -params * angle

    b.add_force([body], torsion, params=np.asarray(0.5))
    model = b.finalize(dt=1 / 1000)
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=3000))(dbd.init(model))
    angle = np.asarray(2 * jnp.arctan2(trajectory.quat[:, 0, 3], trajectory.quat[:, 0, 0]))
    expected = 2 * np.pi * np.sqrt(0.02 / 0.5)
    assert abs(period_from_crossings(angle, model.dt) - expected) < 0.01 * expected
