"""Gradients through rollouts: finite differences in float64, and no NaN at singular poses."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes
from ci_cases import slow_except
from derivatives import central_difference, gradient_and_central_difference, quick_jit, relative_error

import dbdjax as dbd


def swinging_chain(**finalize):
    """A 3-link chain thrown with generic velocities: every joint is pulled its own way, and six
    sweeps leave small gaps, so derivatives go through unconverged projections."""
    velocities = np.random.default_rng(7).normal(scale=0.5, size=(3, 3))
    return scenes.chain(3, dt=1 / 60, substeps=2, iterations=6, velocities=velocities, **finalize)


def tip_height_after(model, start, steps=20):
    final, _ = dbd.rollout(model, start, steps=steps)
    return final.pos[-1, 2] + 0.3 * final.pos[-1, 0]


@pytest.mark.parametrize("point_sweeps", slow_except([0, 2], kept=[0]))
def test_gradient_wrt_initial_velocity_matches_finite_differences(float64, point_sweeps):
    model = swinging_chain(point_sweeps=point_sweeps)
    start = dbd.init(model)
    assert start.pos.dtype == jnp.float64

    def loss(velocity):
        return tip_height_after(model, dataclasses.replace(start, vel=velocity))

    analytic, numeric = gradient_and_central_difference(loss, start.vel)
    assert relative_error(analytic, numeric) < 1e-4


@pytest.mark.parametrize("checkpoint", [False, True])
def test_gradient_wrt_body_mass_matches_finite_differences(float64, checkpoint):
    model = swinging_chain(checkpoint=checkpoint)
    start = dbd.init(model)

    def loss(mass, anchor):
        bodies = dataclasses.replace(model.bodies, mass=mass)
        joints = dataclasses.replace(model.joints, local_anchor_b=anchor)
        return tip_height_after(dataclasses.replace(model, bodies=bodies, joints=joints), start)

    mass, anchor = model.bodies.mass, model.joints.local_anchor_b
    analytic_mass, numeric_mass = gradient_and_central_difference(lambda m: loss(m, anchor), mass)
    assert relative_error(analytic_mass, numeric_mass) < 1e-4


def test_gradient_wrt_joint_anchor_matches_finite_differences(float64):
    # With the magnitude form |p_a - p_b| of the point constraint (DBD (54)), a cone at zero gap,
    # this was 0.95 off central differences; the vector block (64)-(66) is linear in the gap.
    model = swinging_chain()
    start = dbd.init(model)

    def loss(anchor):
        joints = dataclasses.replace(model.joints, local_anchor_b=anchor)
        return tip_height_after(dataclasses.replace(model, joints=joints), start)

    anchor = model.joints.local_anchor_b
    analytic, numeric = gradient_and_central_difference(loss, anchor)
    assert relative_error(analytic, numeric) < 1e-4


def test_gradient_wrt_gravity_and_limits_is_finite_and_matches(float64):
    b = dbd.ModelBuilder()
    door = b.add_body(pos=(0.3, 0.0, 0.0), mass=2.0, inertia=(0.02, 0.08, 0.07), ang_vel=(0.0, 1.0, 0.0))
    b.add_hinge_joint(dbd.WORLD, door, anchor=(0, 0, 0), axis=(0, 1, 0), limits=(-1.0, 1.0))
    model = b.finalize(dt=1 / 60, iterations=6)

    def loss(gravity):
        final, _ = dbd.rollout(dataclasses.replace(model, gravity=gravity), dbd.init(model), steps=20)
        return final.pos[0, 0]

    analytic, numeric = gradient_and_central_difference(loss, model.gravity)
    assert relative_error(analytic, numeric) < 1e-4


@pytest.mark.parametrize(
    "kind",
    ["straight chain", "exact joints", pytest.param("every joint kind at rest", marks=pytest.mark.slow)],  # 140 s on CI
)
def test_no_nan_gradient_at_singular_configurations(kind):
    if kind == "every joint kind at rest":
        b = dbd.ModelBuilder(gravity=(0, 0, 0))
        bodies = [b.add_body(pos=(i, 0, 0), mass=1.0, inertia=(0.1, 0.1, 0.1)) for i in range(5)]
        b.add_ball_joint(dbd.WORLD, bodies[0], anchor=(0, 0, 0), cone_limit=0.5, twist_limits=(-0.1, 0.1))
        b.add_hinge_joint(bodies[0], bodies[1], anchor=(0.5, 0, 0), axis=(0, 0, 1), limits=(-0.5, 0.5))
        b.add_slider_joint(bodies[1], bodies[2], anchor=(1.5, 0, 0), axis=(1, 0, 0), limits=(-0.1, 0.1))
        b.add_fixed_joint(bodies[2], bodies[3], anchor=(2.5, 0, 0))
        b.add_ball_joint(bodies[3], bodies[4], anchor=(3.5, 0, 0))
        model = b.finalize(dt=1 / 60, iterations=4)
    else:
        # A straight chain with no gravity: every joint error is exactly zero and stays so.
        gravity = (0, 0, 0) if kind == "exact joints" else (0, 0, -9.81)
        model = scenes.chain(5, gravity=gravity, dt=1 / 60, iterations=4)
    start = dbd.init(model)

    def loss(state, model):
        final, _ = dbd.rollout(model, state, steps=5)
        return jnp.sum(final.pos**2) + jnp.sum(final.quat) + jnp.sum(final.ang_vel)

    state_gradient, model_gradient = quick_jit(jax.grad(loss, argnums=(0, 1)))(start, model)
    for leaf in jax.tree.leaves((state_gradient, model_gradient)):
        assert np.all(np.isfinite(np.asarray(leaf)))


def driven_arm():
    """Upper arm on a driven ball joint to the world, forearm on a driven hinge (elbow)."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    upper = b.add_body(pos=(0.15, 0, 0), mass=1.0, inertia=(0.002, 0.008, 0.008))
    fore = b.add_body(pos=(0.45, 0, 0), mass=0.6, inertia=(0.001, 0.005, 0.005))
    shoulder = b.add_ball_joint(dbd.WORLD, upper, anchor=(0, 0, 0))
    elbow = b.add_hinge_joint(upper, fore, anchor=(0.3, 0, 0), axis=(0, 1, 0))
    b.add_drive(shoulder, stiffness=40.0, damping=4.0)
    b.add_drive(elbow, stiffness=20.0, damping=2.0)
    return b.finalize(dt=1 / 60, substeps=2, iterations=6)


@pytest.mark.slow  # about 2 minutes of compiling on CI
def test_gradient_of_tracking_loss_wrt_drive_targets_and_stiffness(float64):
    model = driven_arm()
    steps = 15
    controls = jnp.asarray(np.random.default_rng(3).normal(scale=0.3, size=(steps, model.num_controls)))
    goal = jnp.array([0.3, 0.2, -0.3])

    def loss(controls, stiffness):
        joints = dataclasses.replace(model.joints, drive_stiffness=stiffness)
        _, trajectory = dbd.rollout(dataclasses.replace(model, joints=joints), dbd.init(model), controls)
        tip = trajectory.pos[:, 1] + math_rotate(trajectory.quat[:, 1], jnp.array([0.15, 0.0, 0.0]))
        return jnp.sum((tip - goal) ** 2)

    stiffness = model.joints.drive_stiffness
    analytic_controls, analytic_stiffness = quick_jit(jax.grad(loss, argnums=(0, 1)))(controls, stiffness)
    numeric_controls = central_difference(quick_jit(lambda c: loss(c, stiffness)), controls)
    numeric_stiffness = central_difference(quick_jit(lambda k: loss(controls, k)), stiffness)
    print(
        f"\ndriven arm: relative error d/d controls {relative_error(analytic_controls, numeric_controls):.2e}, "
        f"d/d stiffness {relative_error(analytic_stiffness, numeric_stiffness):.2e}"
    )
    assert relative_error(analytic_controls, numeric_controls) < 1e-4
    assert relative_error(analytic_stiffness, numeric_stiffness) < 1e-4


def math_rotate(quat, vector):
    return dbd.math.quat_rotate(quat, vector)


def soft_scene():
    """A spring, a rope and a tetrahedron's volume in one model, thrown with generic velocities."""
    rng = np.random.default_rng(11)
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    corners = [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.15, 0.26, 0.0), (0.15, 0.09, 0.25)]
    nodes = [b.add_body(pos=c, mass=0.5, inertia=(1e-3,) * 3, vel=rng.normal(scale=0.3, size=3)) for c in corners]
    b.add_spring(dbd.WORLD, nodes[3], (0.15, 0.09, 0.6), corners[3], stiffness=80.0, damping=1.0, rest_length=0.3)
    b.add_rope(nodes[:3], length=0.55)
    b.add_volume(nodes)
    return b.finalize(dt=1 / 60, iterations=6)


SOFT_PARAMETERS = [("springs", "stiffness"), ("springs", "damping"), ("springs", "rest_length"), ("ropes", "length"),
                   ("volumes", "rest_volume")]  # fmt: skip


def test_gradient_wrt_spring_rope_and_volume_parameters(float64):
    # All five parameters in one program (it was one test per parameter, each compiling the same
    # rollout's gradient again), each checked on its own.
    model = soft_scene()

    def loss(values):
        parts = {family: getattr(model, family) for family, _ in SOFT_PARAMETERS}
        for (family, field), value in zip(SOFT_PARAMETERS, values, strict=True):
            parts[family] = dataclasses.replace(parts[family], **{field: value})
        final, _ = dbd.rollout(dataclasses.replace(model, **parts), dbd.init(model), steps=20)
        return jnp.sum(final.pos[:, 2] * jnp.arange(1.0, 5.0)) + jnp.sum(final.pos[:, 0])

    values = [getattr(getattr(model, family), field) for family, field in SOFT_PARAMETERS]
    analytic, numeric = gradient_and_central_difference(loss, values)
    for parameter, gradient, difference in zip(SOFT_PARAMETERS, analytic, numeric, strict=True):
        assert np.all(np.isfinite(np.asarray(gradient))), parameter
        assert relative_error(gradient, difference) < 1e-4, parameter


def test_gradient_wrt_user_force_parameters(float64):
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    body = b.add_body(pos=(0.2, 0.1, 0), mass=1.0, inertia=(0.01, 0.02, 0.03), vel=(0.3, -0.2, 0.5))

    def drag(pos, quat, vel, ang_vel, params):
        speed = dbd.math.safe_norm(vel)[:, None]
        return -params["linear"] * vel - params["quadratic"] * speed * vel - params["spring"] * pos, -0.1 * ang_vel

    b.add_force([body], drag, params={"linear": 0.5, "quadratic": 0.2, "spring": 20.0})
    model = b.finalize(dt=1 / 60, iterations=4)

    def loss(params):
        final, _ = dbd.rollout(dataclasses.replace(model, forces=(params,)), dbd.init(model), steps=30)
        return jnp.sum(final.pos * jnp.array([1.0, 2.0, 3.0]))

    analytic, numeric = gradient_and_central_difference(loss, model.forces[0])
    for name in analytic:
        assert relative_error(analytic[name], numeric[name]) < 1e-4, name
