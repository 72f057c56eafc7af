"""Gradients through rollouts: finite differences in float64, and no NaN at singular poses."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes

import dbdjax as dbd


def central_difference(function, x, epsilon=1e-6):
    x = np.asarray(x, dtype=np.float64)
    gradient = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        step = np.zeros_like(x)
        step[index] = epsilon
        gradient[index] = (function(x + step) - function(x - step)) / (2 * epsilon)
    return gradient


def relative_error(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(np.asarray(b)), 1e-12))


@pytest.fixture
def float64():
    with jax.enable_x64(True):
        yield


def swinging_chain(**finalize):
    """A 3-link chain thrown with generic velocities.

    A smooth scene: the magnitude form |p_a - p_b| of the ball joint is a cone at zero gap, so
    a start where every prediction keeps the gaps exactly zero (a chain merely dropped) is a kink
    of the step map that finite differences straddle. Generic velocities avoid that point.
    """
    velocities = np.random.default_rng(7).normal(scale=0.5, size=(3, 3))
    return scenes.chain(3, dt=1 / 60, substeps=2, iterations=6, velocities=velocities, **finalize)


def tip_height_after(model, start, steps=20):
    final, _ = dbd.rollout(model, start, steps=steps)
    return final.pos[-1, 2] + 0.3 * final.pos[-1, 0]


def test_gradient_wrt_initial_velocity_matches_finite_differences(float64):
    model = swinging_chain()
    start = dbd.init(model)
    assert start.pos.dtype == jnp.float64

    def loss(velocity):
        return tip_height_after(model, dataclasses.replace(start, vel=velocity))

    analytic = jax.jit(jax.grad(loss))(start.vel)
    numeric = central_difference(jax.jit(loss), start.vel)
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
    analytic_mass = jax.jit(jax.grad(loss, argnums=0))(mass, anchor)
    numeric_mass = central_difference(jax.jit(lambda m: loss(m, anchor)), mass)
    assert relative_error(analytic_mass, numeric_mass) < 1e-4


@pytest.mark.xfail(
    strict=True,
    reason="open (issue 2): d/d local_anchor_b disagrees with central differences (relative error "
    "0.95, worst on the component along the rod); mass, velocity and gravity gradients agree",
)
def test_gradient_wrt_joint_anchor_matches_finite_differences(float64):
    model = swinging_chain()
    start = dbd.init(model)

    def loss(anchor):
        joints = dataclasses.replace(model.joints, local_anchor_b=anchor)
        return tip_height_after(dataclasses.replace(model, joints=joints), start)

    anchor = model.joints.local_anchor_b
    analytic = jax.jit(jax.grad(loss))(anchor)
    numeric = central_difference(jax.jit(loss), anchor)
    assert relative_error(analytic, numeric) < 1e-4


def test_gradient_wrt_gravity_and_limits_is_finite_and_matches(float64):
    b = dbd.ModelBuilder()
    door = b.add_body(pos=(0.3, 0.0, 0.0), mass=2.0, inertia=(0.02, 0.08, 0.07), ang_vel=(0.0, 1.0, 0.0))
    b.add_hinge_joint(dbd.WORLD, door, anchor=(0, 0, 0), axis=(0, 1, 0), limits=(-1.0, 1.0))
    model = b.finalize(dt=1 / 60, iterations=6)

    def loss(gravity):
        final, _ = dbd.rollout(dataclasses.replace(model, gravity=gravity), dbd.init(model), steps=20)
        return final.pos[0, 0]

    analytic = jax.grad(loss)(model.gravity)
    numeric = central_difference(jax.jit(loss), model.gravity)
    assert relative_error(analytic, numeric) < 1e-4


@pytest.mark.parametrize("kind", ["straight chain", "exact joints", "every joint kind at rest"])
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

    state_gradient, model_gradient = jax.jit(jax.grad(loss, argnums=(0, 1)))(start, model)
    for leaf in jax.tree.leaves((state_gradient, model_gradient)):
        assert np.all(np.isfinite(np.asarray(leaf)))
