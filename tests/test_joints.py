"""Each joint kind and limit, checked against physics and geometry."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes

import dbdjax as dbd
from dbdjax import math
from dbdjax.constraints import joints as joint_rows


def simulate(model, steps, state=None):
    state = dbd.init(model) if state is None else state
    return jax.jit(lambda s: dbd.rollout(model, s, steps=steps))(state)


def upward_crossing_times(x, dt):
    index = np.where((x[:-1] < 0) & (x[1:] >= 0))[0]
    return (index + 1 + (-x[index]) / (x[index + 1] - x[index])) * dt


@pytest.mark.parametrize("joint", ["hinge", "ball"])
@pytest.mark.parametrize("dt, substeps", [(1 / 60, 1), (1 / 240, 1), (1 / 60, 4)])
def test_pendulum_period_matches_analytic_value(joint, dt, substeps):
    length, amplitude, radius = 1.0, 0.05, 0.1
    model = scenes.pendulum(joint, length, amplitude, radius, dt=dt, substeps=substeps, iterations=8)
    _, trajectory = simulate(model, int(12 / dt))
    crossings = upward_crossing_times(np.asarray(trajectory.pos[:, 0, 0]), dt)
    measured = np.mean(np.diff(crossings))
    pivot_inertia = 0.4 * radius**2 + length**2  # m = 1
    analytic = 2 * np.pi * np.sqrt(pivot_inertia / (9.81 * length)) * (1 + amplitude**2 / 16)
    assert abs(measured - analytic) / analytic < 0.01


def hinge_scene(limits=None, spin=0.0):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    # A plate hanging off a hinge along y, kicked so that it swings and twists.
    door = b.add_body(pos=(0.3, 0.0, 0.0), mass=2.0, inertia=(0.02, 0.08, 0.07), ang_vel=(spin, 4.0, spin))
    b.add_hinge_joint(dbd.WORLD, door, anchor=(0, 0, 0), axis=(0, 1, 0), limits=limits)
    return b.finalize(dt=1 / 60, substeps=2, iterations=8)


def test_hinge_axes_stay_aligned_and_anchor_stays_put():
    model = hinge_scene(spin=3.0)
    _, trajectory = simulate(model, 240)
    axis = math.quat_rotate(trajectory.quat[:, 0], model.joints.local_axis_b[0])
    misalignment = np.degrees(np.arccos(np.clip(np.abs(np.asarray(axis[:, 1])), 0, 1)))
    assert misalignment.max() < 0.5
    assert float(jnp.max(dbd.diagnostics.joint_gaps(model, trajectory))) < 2e-3


def test_hinge_angle_limits_hold():
    lower, upper = -0.4, 0.6
    model = hinge_scene(limits=(lower, upper))
    _, trajectory = simulate(model, 240)
    relative = math.quat_multiply(trajectory.quat[:, 0], math.quat_conjugate(model.joints.rest_rotation[0]))
    angle = np.asarray(math.quat_twist_angle(relative, jnp.array([0.0, 1.0, 0.0])))
    assert angle.max() > upper - 0.05, "the kick should reach the upper limit"
    assert angle.min() >= lower - 0.02 and angle.max() <= upper + 0.02


def test_slider_moves_only_along_its_axis_and_stops_at_its_limits():
    axis = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    carriage = b.add_body(pos=(0, 0, 0), mass=1.0, inertia=(0.01, 0.02, 0.03), vel=(1.0, 2.0, 0.5), ang_vel=(1, 2, 3))
    b.add_slider_joint(dbd.WORLD, carriage, anchor=(0, 0, 0), axis=axis, limits=(-0.3, 0.2))
    model = b.finalize(dt=1 / 60, substeps=2, iterations=8)
    _, trajectory = simulate(model, 180)
    pos = np.asarray(trajectory.pos[:, 0])
    travel = pos @ axis
    across = pos - travel[:, None] * axis
    assert np.abs(across).max() < 1e-3
    assert travel.min() >= -0.3 - 5e-3 and travel.max() <= 0.2 + 5e-3
    assert travel.min() < -0.29, "gravity should pull the carriage onto its lower stop"
    rotation = np.asarray(math.quat_log(trajectory.quat[:, 0]))
    assert np.abs(rotation).max() < 1e-3, "a slider does not let its body turn"


def test_fixed_joint_welds_two_bodies():
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    upper = b.add_body(pos=(0, 0, 0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    lower = b.add_body(pos=(0.2, 0, 0), mass=1.0, inertia=(0.01, 0.02, 0.02))
    b.add_ball_joint(dbd.WORLD, upper, anchor=(-0.1, 0, 0))
    b.add_fixed_joint(upper, lower, anchor=(0.1, 0, 0))
    model = b.finalize(dt=1 / 60, substeps=4, iterations=8)
    _, trajectory = simulate(model, 120)
    relative = math.quat_multiply(math.quat_conjugate(trajectory.quat[:, 0]), trajectory.quat[:, 1])
    assert np.degrees(np.abs(np.asarray(math.quat_log(relative))).max()) < 0.5
    separation = np.linalg.norm(np.asarray(trajectory.pos[:, 1] - trajectory.pos[:, 0]), axis=-1)
    assert np.abs(separation - 0.2).max() < 2e-3


def test_ball_cone_and_twist_limits_hold():
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    # A rod hanging down from a ball joint, kicked sideways and spun about its own axis.
    rod = b.add_body(pos=(0, 0, -0.25), mass=1.0, inertia=(0.02, 0.02, 0.002), vel=(3.0, 0, 0), ang_vel=(0, 0, 20.0))
    cone, twist = 0.5, (-0.3, 0.3)
    b.add_ball_joint(dbd.WORLD, rod, anchor=(0, 0, 0), cone_limit=cone, twist_limits=twist)
    model = b.finalize(dt=1 / 60, substeps=2, iterations=8)
    _, trajectory = simulate(model, 180)
    down = np.asarray(math.quat_rotate(trajectory.quat[:, 0], jnp.array([0.0, 0.0, -1.0])))
    swing = np.arccos(np.clip(-down[:, 2], -1, 1))
    assert swing.max() > cone - 0.05, "the kick should reach the cone"
    assert swing.max() < cone + 0.02
    twist_angle = np.asarray(math.quat_twist_angle(trajectory.quat[:, 0], jnp.array([0.0, 0.0, -1.0])))
    assert np.abs(twist_angle).max() > 0.25, "the spin should reach a twist limit"
    assert twist_angle.min() > twist[0] - 0.02 and twist_angle.max() < twist[1] + 0.02


def test_ball_joint_pulls_separated_anchors_together_without_blowing_up():
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    first = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.01, 0.01, 0.01))
    second = b.add_body(pos=(0.5, 0, 1), mass=1.0, inertia=(0.01, 0.01, 0.01))
    b.add_ball_joint(dbd.WORLD, first, anchor=(0, 0, 1.1))
    joint = b.add_ball_joint(first, second, anchor=(0, 0, 1))
    model = b.finalize(dt=1 / 60, iterations=8)
    # The joint's anchor on `second` sits at its own centre: 0.5 m from the anchor on `first`.
    local = model.joints.local_anchor_b.at[joint].set(jnp.zeros(3))
    model = dataclasses.replace(model, joints=dataclasses.replace(model.joints, local_anchor_b=local))
    assert float(dbd.diagnostics.joint_gaps(model, dbd.init(model))[joint]) == pytest.approx(0.5)
    _, trajectory = simulate(model, 60)
    gaps = np.asarray(dbd.diagnostics.joint_gaps(model, trajectory))[:, joint]
    assert gaps[4] < 0.01, f"gap after 5 steps: {gaps[4]}"
    assert gaps[10:].max() < 5e-3
    assert np.all(np.isfinite(np.asarray(trajectory.pos)))
    speed = np.linalg.norm(np.asarray(trajectory.vel[-1]), axis=-1)
    assert speed.max() < 10.0, "the recovery must not fling the bodies"


def test_ball_joint_closes_a_small_gap_in_any_direction_in_one_projection():
    # Two slender rods end to end: the effective mass of the joint point is far larger along the
    # rods than across them. The point constraint is one block of three rows with that full 3x3
    # effective mass (DBD (64)-(66)), so one projection removes a small gap in any direction up to
    # second order; a single row along the gap (the magnitude form (54)) leaves a residual across
    # it of the order of the gap itself.
    with jax.enable_x64(True):
        b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        first = b.add_body(pos=(-0.05, 0, 0), mass=scenes.LINK_MASS, inertia=scenes.LINK_INERTIA)
        second = b.add_body(pos=(0.05, 0, 0), mass=scenes.LINK_MASS, inertia=scenes.LINK_INERTIA)
        b.add_ball_joint(first, second, anchor=(0, 0, 0))
        model = b.finalize(dt=1 / 60, iterations=1)
        offset = 1e-6 * np.array([0.6, -0.48, 0.64])  # |offset| = 1e-6 m, along no axis of K
        joints = dataclasses.replace(model.joints, local_anchor_b=model.joints.local_anchor_b + offset)
        model = dataclasses.replace(model, joints=joints)
        start = dbd.init(model)
        before = float(dbd.diagnostics.joint_gaps(model, start)[0])
        after = float(dbd.diagnostics.joint_gaps(model, dbd.step(model, start))[0])
    assert before == pytest.approx(1e-6)
    assert after < 1e-3 * before, f"gap {before:.3e} m -> {after:.3e} m after one projection"


@pytest.mark.parametrize("kind", ["hinge", "fixed", "universal", "gimbal"])
def test_driven_chain_damps_a_tiny_perturbation_instead_of_amplifying_it(float64, kind):
    """A 1e-9 m nudge of one link changes the next state by about as much, not by rad/s.

    Five links in a chain from the world with drives (hinges about z, y, z, ...; universal joints
    about (z, y), gimbal joints about (z, y, x), each hinge driven; or fixed joints with the
    drives left out), 16 substeps x 16 iterations. When the hinge's axle alignment was a single
    row along the normalised cross product of the two axes, that direction was rounding noise
    where the axes agree, and the sweeps amplified it: the nudge changed the angular velocities
    after one step by 13 rad/s (0.16 rad/s with fixed joints, whose lock was a row along the
    normalised rotation vector). The block form of the rotation lock changes them by about 1e-8;
    the universal joint's lock row (c = m1_a . m2_b) has a unit direction where it holds."""
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    parent = dbd.WORLD
    for k in range(5):
        body = builder.add_body(pos=((k + 0.5) * 0.3, 0.0, 0.0), mass=1.0, inertia=(0.0008, 0.0075, 0.0075))
        anchor, axis = (k * 0.3, 0.0, 0.0), ((0.0, 0.0, 1.0) if k % 2 == 0 else (0.0, 1.0, 0.0))
        if kind == "hinge":
            joint = builder.add_hinge_joint(parent, body, anchor=anchor, axis=axis, limits=(-2.0, 2.0))
            builder.add_drive(joint, 300.0, 30.0, 200.0)
        elif kind == "universal":
            axes = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0)]
            joint = builder.add_universal_joint(parent, body, anchor=anchor, axes=axes, limits=[(-2.0, 2.0)] * 2)
            builder.add_drive(joint, 300.0, 30.0, 200.0)
        elif kind == "gimbal":
            axes = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]
            limits = [(-2.0, 2.0), (-1.2, 1.2), (-2.0, 2.0)]
            joint = builder.add_gimbal_joint(parent, body, anchor=anchor, axes=axes, limits=limits)
            builder.add_drive(joint, 300.0, 30.0, 200.0)
        else:
            builder.add_fixed_joint(parent, body, anchor=anchor)
        parent = body
    model = builder.finalize(dt=1 / 60, substeps=16, iterations=16)
    targets = [1.2, -0.9, 1.4, 0.3, -1.1, 0.7, -0.4, 0.9, -1.0, 0.5, 0.2, -0.6, 1.1, -0.3, 0.8]
    control = jnp.asarray(targets[: model.control_range.shape[0]], jnp.float64)
    step = jax.jit(lambda s: dbd.step(model, s, control))
    start = dbd.init(model)
    nudged = dataclasses.replace(start, pos=start.pos.at[2, 1].add(1e-9))
    reference, moved = step(start), step(nudged)
    assert start.pos.dtype == jnp.float64
    assert float(jnp.abs(reference.ang_vel - moved.ang_vel).max()) < 1e-6
    assert float(jnp.abs(reference.vel - moved.vel).max()) < 1e-6


@pytest.mark.slow  # 50 s on CI: a guard of how the sweeps are traced (every kind's rows give the same steps)
@pytest.mark.parametrize("solver", ["dbd", "impulse"])
def test_projecting_each_kind_of_joint_with_its_own_rows_changes_no_result(float64, monkeypatch, solver):
    """Both solvers take the joints kind by kind (`joint_rows.variants`), each kind traced with its
    own rows only; the rows a kind lacks are inactive, so this must give what one projection (one
    velocity pass) of every row for every joint gives, to rounding."""
    model = scenes.mixed_tree(solver=solver)
    assert len(joint_rows.variants(model.structure)) == 5  # universal and gimbal share their rows
    _, by_kind = jax.jit(lambda s: dbd.rollout(model, s, steps=60))(dbd.init(model))
    every_joint = lambda structure: [(np.arange(len(structure.joint_kind.array)), joint_rows.rows_in_use(structure))]  # noqa: E731
    monkeypatch.setattr(joint_rows, "variants", every_joint)
    _, all_rows = jax.jit(lambda s: dbd.rollout(model, s, steps=60))(dbd.init(model))
    assert bool(jnp.all(dbd.is_finite(by_kind)))
    assert float(jnp.max(jnp.abs(by_kind.ang_vel))) > 1.0, "the tree should really move"
    for ours, reference in zip(jax.tree.leaves(by_kind), jax.tree.leaves(all_rows), strict=True):
        np.testing.assert_allclose(np.asarray(ours), np.asarray(reference), rtol=0, atol=1e-12)
