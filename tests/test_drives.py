"""Drives (DBD 9) and motors (SI 2.3.6, 2.4.6): targets reached, limits obeyed, analytic sag."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ci_cases import slow_except

import dbdjax as dbd
from dbdjax import math


def hinge_angle_about(quat, axis):
    """Rotation angle (rad) of a body that started at the identity, about a fixed world axis."""
    return np.asarray(math.quat_twist_angle(jnp.asarray(quat), jnp.asarray(axis, dtype=jnp.asarray(quat).dtype)))


def run(model, control, seconds, state=None):
    steps = int(round(seconds / model.dt))
    controls = jnp.broadcast_to(jnp.asarray(control), (steps, model.num_controls))
    start = dbd.init(model) if state is None else state
    return jax.jit(dbd.rollout)(model, start, controls)


def test_hinge_drive_reaches_its_target_angle():
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    door = b.add_body(pos=(0.5, 0, 0), mass=2.0, inertia=(0.02, 0.2, 0.2))
    hinge = b.add_hinge_joint(dbd.WORLD, door, anchor=(0, 0, 0), axis=(0, 0, 1))  # gravity along the axle
    controls = b.add_drive(hinge, stiffness=50.0, damping=10.0)
    model = b.finalize(dt=1 / 60, iterations=8)
    assert model.num_controls == 1 and controls == slice(0, 1)

    final, trajectory = run(model, [0.7], seconds=4.0)
    angles = hinge_angle_about(trajectory.quat[:, 0], (0, 0, 1))
    print(f"\nhinge drive: angle after 4 s = {angles[-1]:.6f} rad (target 0.7)")
    assert abs(angles[-1] - 0.7) < 1e-3
    assert np.all(np.isfinite(np.asarray(final.pos)))


def test_hinge_drive_wraps_targets_beyond_pi():
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    wheel = b.add_body(pos=(0, 0, 0), mass=1.0, inertia=(0.1, 0.1, 0.1))
    hinge = b.add_hinge_joint(dbd.WORLD, wheel, anchor=(0, 0, 0), axis=(0, 0, 1))
    b.add_drive(hinge, stiffness=20.0, damping=5.0)
    model = b.finalize(dt=1 / 60, iterations=4)
    # A target of 3 pi / 2 is the same pose as -pi / 2: the drive takes the short way round.
    _, trajectory = run(model, [1.5 * np.pi], seconds=4.0)
    angles = hinge_angle_about(trajectory.quat[:, 0], (0, 0, 1))
    assert abs(angles[-1] + 0.5 * np.pi) < 1e-3
    assert np.all(angles <= 1e-6)  # it never went the long way through +pi


def test_ball_drive_reaches_its_target_orientation():
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    torso = b.add_body(pos=(0, 0, 0), mass=5.0, inertia=(0.3, 0.3, 0.2))
    arm = b.add_body(pos=(0.3, 0, 0), mass=1.0, inertia=(0.002, 0.03, 0.03), quat=(0.9, 0.1, 0.2, 0.3))
    b.add_ball_joint(dbd.WORLD, torso, anchor=(0, 0, 0))
    shoulder = b.add_ball_joint(torso, arm, anchor=(0.1, 0, 0))
    b.add_drive(0, stiffness=200.0, damping=40.0)  # holds the torso at its build pose
    controls = b.add_drive(shoulder, stiffness=30.0, damping=4.0, max_torque=50.0)
    model = b.finalize(dt=1 / 60, iterations=8)
    assert controls == slice(3, 6) and model.num_controls == 6

    target = np.array([0.3, -0.4, 0.5])
    final, _ = run(model, np.concatenate([np.zeros(3), target]), seconds=5.0)
    rest = math.quat_multiply(math.quat_conjugate(model.bodies.initial_quat[0]), model.bodies.initial_quat[1])
    relative = math.quat_multiply(math.quat_conjugate(final.quat[0]), final.quat[1])
    reached = np.asarray(math.quat_log(math.quat_multiply(relative, math.quat_conjugate(rest))))
    print(f"\nball drive: reached rotation vector {reached} (target {target})")
    np.testing.assert_allclose(reached, target, atol=2e-3)


def test_drive_too_weak_for_its_load_sags_by_the_predicted_angle():
    """A horizontal arm (mass m, centre L from a horizontal hinge) held by a stiff drive whose
    max torque tau is below m g L. The clamped drive is a constant torque tau, so energy gives the
    lowest point of the first swing: m g L sin(theta) = tau theta (DBD (114))."""
    mass, length, g = 1.0, 0.5, 9.81
    tau = 0.6 * mass * g * length
    b = dbd.ModelBuilder(gravity=(0, 0, -g))
    arm = b.add_body(pos=(length, 0, 0), mass=mass, inertia=(1e-4, 1e-3, 1e-3))
    hinge = b.add_hinge_joint(dbd.WORLD, arm, anchor=(0, 0, 0), axis=(0, -1, 0))  # positive angle = up
    b.add_drive(hinge, stiffness=1e4, damping=0.0, max_torque=tau)
    model = b.finalize(dt=1 / 240, substeps=2, iterations=8)

    _, trajectory = run(model, [0.0], seconds=1.5)
    sag = -hinge_angle_about(trajectory.quat[:, 0], (0, -1, 0))
    first_swing = sag[: np.argmax(np.diff(sag) < 0) + 1]  # until it turns back
    low, high = 0.1, np.pi  # solve m g L sin(theta) = tau theta by bisection
    for _ in range(60):
        theta = 0.5 * (low + high)
        low, high = (theta, high) if mass * g * length * np.sin(theta) > tau * theta else (low, theta)
    print(f"\nweak drive: lowest point of the first swing {first_swing.max():.4f} rad, predicted {theta:.4f}")
    assert abs(first_swing.max() - theta) < 0.01 * theta


@pytest.mark.parametrize("initial_guess", ["zero", "tree"])
def test_drive_on_a_light_arm_applies_its_torque_about_the_pivot(initial_guess):
    """A spring drive (k = 10 N m/rad, 0.5 rad from its target) on an arm pinned 0.5 m from its
    centre whose own inertia (1e-3 kg m^2) is small against m L^2 = 0.25: one step changes the
    angular velocity by -k theta h / (m L^2 + I). The drive row turns the arm about its centre;
    unless the joint point is held while it does (rows.PointHold), the point block turns it back
    and the sweeps settle on 1.5 times that change, a fixed point that depends on the guess."""
    mass, length, inertia, stiffness, angle, spin, h = 1.0, 0.5, 1e-3, 10.0, 0.5, 2.0, 1 / 240
    with jax.enable_x64(True):
        b = dbd.ModelBuilder(gravity=(0, 0, 0))
        arm = b.add_body(pos=(length, 0, 0), mass=mass, inertia=(1e-4, inertia, inertia))
        hinge = b.add_hinge_joint(dbd.WORLD, arm, anchor=(0, 0, 0), axis=(0, -1, 0))
        b.add_drive(hinge, stiffness=stiffness, damping=0.0)
        model = b.finalize(dt=h, iterations=8, initial_guess=initial_guess)
        # The arm 0.5 rad below its target (horizontal), turning down at 2 rad/s.
        pos = jnp.array([[length * np.cos(angle), 0.0, -length * np.sin(angle)]])
        ang_vel = jnp.array([[0.0, spin, 0.0]])
        state = dbd.State(
            pos=pos, quat=jnp.array([[np.cos(angle / 2), 0.0, np.sin(angle / 2), 0.0]]),
            vel=jnp.cross(ang_vel, pos), ang_vel=ang_vel,
        )  # fmt: skip
        change = float(dbd.step(model, state, jnp.zeros(1)).ang_vel[0, 1]) - spin
    expected = -stiffness * angle * h / (mass * length**2 + inertia)
    print(f"\nlight arm, {initial_guess} guess: d omega {change:.5f} rad/s, expected {expected:.5f}")
    assert abs(change - expected) < 0.03 * abs(expected)


def test_hinge_motor_reaches_its_speed_without_exceeding_its_torque():
    inertia, max_torque, speed = 0.2, 0.5, 3.0
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    wheel = b.add_body(pos=(0, 0, 0), mass=1.0, inertia=(inertia, inertia, 0.3))
    hinge = b.add_hinge_joint(dbd.WORLD, wheel, anchor=(0, 0, 0), axis=(1, 0, 0))
    b.add_motor(hinge, max_force=max_torque)
    model = b.finalize(dt=1 / 120, iterations=4)

    _, trajectory = run(model, [speed], seconds=2.0)
    spin = np.asarray(trajectory.ang_vel[:, 0, 0])
    time = model.dt * np.arange(1, len(spin) + 1)
    limit = max_torque / inertia * time  # the fastest the torque limit allows
    print(
        f"\nhinge motor: spin at 0.5 s {spin[59]:.4f} (limit {limit[59]:.4f}), at 2 s {spin[-1]:.6f} (target {speed})"
    )
    assert np.all(spin <= limit * (1 + 1e-3) + 1e-9)
    reach = speed * inertia / max_torque
    np.testing.assert_allclose(spin[time < reach - 0.05], limit[time < reach - 0.05], rtol=1e-3)
    np.testing.assert_allclose(spin[time > reach + 0.05], speed, rtol=1e-4)


@pytest.mark.parametrize("max_force", [30.0, 5.0])
def test_slider_motor_lifts_at_its_speed_or_sinks_when_too_weak(max_force):
    """A 1 kg block on a vertical slider, motor target 0.5 m/s up. 30 N can lift it (reaches the
    speed); 5 N cannot hold 9.81 N, so it accelerates down at exactly g - F / m."""
    g = 9.81
    b = dbd.ModelBuilder(gravity=(0, 0, -g))
    block = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.01, 0.01, 0.01))
    slider = b.add_slider_joint(dbd.WORLD, block, anchor=(0, 0, 1), axis=(0, 0, 1))
    b.add_motor(slider, max_force=max_force)
    model = b.finalize(dt=1 / 120, iterations=4)

    _, trajectory = run(model, [0.5], seconds=1.0)
    velocity = np.asarray(trajectory.vel[:, 0, 2])
    acceleration = np.diff(velocity) / model.dt
    assert np.all(acceleration <= max_force - g + 1e-3 * max_force)  # F - m g with m = 1
    if max_force > g:
        np.testing.assert_allclose(velocity[-10:], 0.5, rtol=1e-4)
    else:
        np.testing.assert_allclose(acceleration, max_force - g, rtol=1e-4)


@pytest.mark.parametrize(
    ("solver", "kind"), slow_except([("dbd", "hinge"), ("dbd", "ball"), ("impulse", "hinge"), ("impulse", "ball")],
                                    kept=[("dbd", "hinge"), ("dbd", "ball")])
)  # fmt: skip
def test_a_saturated_drive_beside_a_rotor_turns_a_light_body_at_its_bound_over_body_plus_rotor(float64, kind, solver):
    # A light sphere (I = 1.6e-4 kg m^2) on a joint at its centre with armature 1, spinning about z at
    # 1 rad/s, driven toward 3 rad about z (stiffness 100, damping 1): the drive asks 300 N m and is
    # clamped to 0.5 N m, so the spin rises at 0.5 / (I + 1) rad/s^2. The drive steps beside its rotor
    # as one block (`rows.spring_row_beside_rotor`, `rows.angular_spring_beside_rotor`): its clamped
    # step, then the rotor's share given it. A guard of the bound: the rows stepped one after the
    # other gave the same.
    radius, mass, armature, bound = 0.1, 0.04, 1.0, 0.5
    inertia = 0.4 * mass * radius**2
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    ball = b.add_body(pos=(0, 0, 0), mass=mass, inertia=(inertia,) * 3, ang_vel=(0, 0, 1.0))
    if kind == "hinge":
        joint = b.add_hinge_joint(dbd.WORLD, ball, anchor=(0, 0, 0), axis=(0, 0, 1))
    else:
        joint = b.add_ball_joint(dbd.WORLD, ball, anchor=(0, 0, 0))
    b.add_drive(joint, stiffness=100.0, damping=1.0, max_torque=bound)
    b.add_armature(joint, armature)
    model = b.finalize(dt=1e-3, iterations=4, solver=solver)
    target = [3.0] if kind == "hinge" else [0.0, 0.0, 3.0]
    final, _ = run(model, target, seconds=0.5)
    spin = np.asarray(final.ang_vel[0])
    expected = 1.0 + bound * 0.5 / (inertia + armature)
    print(f"\n{kind}: spin after 0.5 s {spin}, 1 + tau_max t / (I + I_r) = {expected:.6f}")
    assert abs(spin[2] - expected) < 1e-6 and np.max(np.abs(spin[:2])) < 1e-9
