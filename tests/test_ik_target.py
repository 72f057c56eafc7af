"""IK as a constraint inside the simulation step (DBD 11, last paragraph): `add_ik_target`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from derivatives import central_difference, relative_error

import dbdjax as dbd

LINK = 0.3


def chain(links=5, gravity=9.81, max_force=200.0, stiffness=None, damping=0.0, joint_damping=0.0, planar=False):
    """A chain of `links` links along x from the world, hinges about z, y, z, ... (every one about
    z if planar); an IK target at the tip. Returns (builder, tip body, tip point (world, build
    time))."""
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -gravity))
    parent = dbd.WORLD
    for k in range(links):
        body = builder.add_body(pos=((k + 0.5) * LINK, 0.0, 0.0), mass=1.0, inertia=(0.0008, 0.0075, 0.0075))
        axis = (0.0, 0.0, 1.0) if planar or k % 2 == 0 else (0.0, 1.0, 0.0)
        joint = builder.add_hinge_joint(parent, body, anchor=(k * LINK, 0.0, 0.0), axis=axis)
        if joint_damping:
            builder.add_joint_spring(joint, 0.0, joint_damping)
        parent = body
    tip = (links * LINK, 0.0, 0.0)
    builder.add_ik_target(parent, tip, stiffness=stiffness, damping=damping, max_force=max_force, name="tip")
    return builder, parent, np.asarray(tip)


def hold(model, offset, steps):
    controls = jnp.broadcast_to(jnp.asarray(offset, model.bodies.mass.dtype), (steps, model.num_controls))
    return jax.jit(lambda c: dbd.rollout(model, dbd.init(model), c))(controls)


def test_rigid_target_puts_the_tip_on_a_reachable_goal_and_keeps_the_joints_closed():
    """Under gravity, with the chain's joints in the same sweeps: the tip sits on the goal
    within 0.1 mm once it has arrived, and the joints stay within 2 mm. The target moves there from
    the tip's build position over the first second, starting and stopping smoothly (a target
    jumping 1.1 m at once yanks the chain: 25 mm joint gaps in the first steps; a linear ramp,
    starting at full speed, 2.6 mm). With max_force = 200 N instead of no limit, the
    swinging chain briefly needs more and the tip slips by 15 mm."""
    builder, _, tip = chain(max_force=None)
    model = builder.finalize(dt=1 / 60, substeps=4, iterations=16)
    goal = np.array([0.6, 0.5, 0.4])  # 0.88 m from the root, the chain reaches 1.5 m
    u = np.minimum(np.arange(1, 181) / 60.0, 1.0)
    ramp = (3 * u**2 - 2 * u**3)[:, None] * (goal - tip)
    final, trajectory = jax.jit(lambda c: dbd.rollout(model, dbd.init(model), c))(jnp.asarray(ramp, jnp.float32))
    assert bool(dbd.is_finite(final))
    errors = np.asarray(
        jax.vmap(lambda s: dbd.diagnostics.ik_target_errors(model, s, jnp.asarray(goal - tip)))(trajectory)
    )
    print(f"\nrigid target: tip error over the last 2 s {1e3 * errors[60:].max():.4f} mm")
    assert errors[60:].max() < 1e-4
    gaps = np.asarray(jax.vmap(lambda s: dbd.diagnostics.joint_gaps(model, s))(trajectory))
    print(f"largest joint gap {1e3 * gaps.max():.2f} mm, after the first quarter second {1e3 * gaps[15:].max():.2f} mm")
    # The target closes a loop, root to tip, which the sweeps close slowly: 1.57 mm at step 3 as
    # the chain starts to move, 0.39 mm from then on (measured at 4 x 16).
    assert gaps.max() < 2e-3
    assert gaps[15:].max() < 1e-3


def test_force_limited_target_out_of_reach_stretches_the_chain_toward_it_without_tearing_it():
    """A goal 2.2 m away from a 1.5 m planar chain, a soft target whose pull is capped at 20 N:
    after 10 s the chain lies straight toward the goal (every link along the line from the root to the
    goal) and the joints hold. (A rigid target with the same cap spends it along the chain,
    where the straight chain resists most, and turns it toward the goal only slowly. With hinges
    about z and y in turn, bent poses exist where the pull has no moment about any hinge axis;
    in the plane the straight one is the only stable rest.)"""
    builder, _, tip = chain(gravity=0.0, stiffness=100.0, max_force=20.0, joint_damping=5.0, planar=True)
    model = builder.finalize(dt=1 / 60, substeps=4, iterations=16)
    goal = np.array([-1.0, 2.0, 0.0])
    final, trajectory = hold(model, goal - tip, 600)  # the heavy root turns last: 5.7 mm off the line at 5 s
    assert bool(dbd.is_finite(final))
    toward = goal / np.linalg.norm(goal)
    centres = np.asarray(final.pos)
    along = centres @ toward
    across = np.linalg.norm(centres - along[:, None] * toward, axis=1)
    print(f"\nunreachable target: link centres off the line {across.max():.2e} m")
    np.testing.assert_allclose(along, (np.arange(5) + 0.5) * LINK, atol=2e-3)
    assert across.max() < 2e-3  # 0.55 mm measured
    gaps = np.asarray(jax.vmap(lambda s: dbd.diagnostics.joint_gaps(model, s))(trajectory))
    assert gaps.max() < 1e-3


def test_soft_target_holds_a_hanging_body_at_the_spring_sag():
    """A free 2 kg body hung from a soft target of stiffness k sags m g / k below it (DBD 8.1's
    implicit spring, zero rest length), with damping to let it settle."""
    mass, stiffness, g = 2.0, 400.0, 9.81
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -g))
    body = builder.add_body(pos=(0.0, 0.0, 1.0), mass=mass, inertia=(0.01, 0.01, 0.01))
    builder.add_ik_target(body, (0.0, 0.0, 1.0), stiffness=stiffness, damping=40.0)
    model = builder.finalize(dt=1 / 60, substeps=2, iterations=4)
    final, _ = hold(model, [0.3, -0.2, 0.5], 300)
    expected = np.array([0.3, -0.2, 1.5 - mass * g / stiffness])
    np.testing.assert_allclose(np.asarray(final.pos[0]), expected, atol=1e-4)


def test_target_pulling_a_ball_into_the_floor_loses_to_the_contact():
    """A target 0.5 m below the floor pulls a ball with at most 30 N: the contact holds it on
    the floor (solved in the same sweeps), nothing sinks."""
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_plane()
    ball = builder.add_body(pos=(0.0, 0.0, 0.1), mass=1.0, inertia=(0.004, 0.004, 0.004))
    builder.add_sphere(ball, 0.1)
    builder.add_ik_target(ball, (0.0, 0.0, 0.1), max_force=30.0)
    model = builder.finalize(dt=1 / 60, substeps=2, iterations=8)
    final, trajectory = hold(model, [0.0, 0.0, -0.5], 120)
    heights = np.asarray(trajectory.pos[:, 0, 2])
    assert heights.min() > 0.1 - 1e-3
    assert abs(float(final.pos[0, 2]) - 0.1) < 1e-3


@pytest.mark.slow  # reverse mode through the rollout compiles for about a minute here
def test_gradient_of_the_tip_wrt_the_target_matches_finite_differences(float64):
    """d(tip position after 10 steps) / d(target offset), soft target, float64."""
    builder, tip_body, tip = chain(links=2, gravity=9.81, max_force=None, stiffness=300.0, damping=20.0)
    model = builder.finalize(dt=1 / 60, substeps=2, iterations=8)
    local_tip = jnp.asarray([LINK / 2, 0.0, 0.0])

    @jax.jit
    def tip_after(offset):
        final, _ = dbd.rollout(model, dbd.init(model), jnp.broadcast_to(offset, (10, 3)))
        return final.pos[tip_body] + dbd.math.quat_rotate(final.quat[tip_body], local_tip)

    weights = jnp.asarray([1.0, -2.0, 0.5])  # a scalar of the tip position
    loss = jax.jit(lambda offset: jnp.dot(weights, tip_after(offset)))
    offset = np.array([-0.2, 0.3, 0.2])
    analytic = np.asarray(jax.grad(loss)(jnp.asarray(offset)))
    numeric = central_difference(lambda x: float(loss(jnp.asarray(x))), offset, 1e-6)
    assert np.all(np.isfinite(analytic))
    print(f"\ntip gradient: relative error {relative_error(analytic, numeric):.2e}")
    assert relative_error(analytic, numeric) < 1e-4


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(body=dbd.WORLD), "not a body index"),
        (dict(stiffness=0.0), "stiffness must be positive"),
        (dict(max_force=-1.0), "max_force must be positive"),
        (dict(point=(0.0, float("nan"), 0.0)), "point"),
    ],
)
def test_bad_ik_targets_are_refused_naming_the_target(kwargs, message):
    builder = dbd.ModelBuilder()
    body = builder.add_body(pos=(0.0, 0.0, 0.0), mass=1.0, inertia=(0.1, 0.1, 0.1))
    arguments = dict(body=body, point=(0.0, 0.0, 0.0)) | kwargs
    with pytest.raises(ValueError, match=message) as error:
        builder.add_ik_target(**arguments, name="hand")
    assert "IK target 0" in str(error.value)


def test_impulse_solver_refuses_ik_targets():
    builder = dbd.ModelBuilder()
    body = builder.add_body(pos=(0.0, 0.0, 0.0), mass=1.0, inertia=(0.1, 0.1, 0.1))
    builder.add_ik_target(body, (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="IK target 0"):
        builder.finalize(dt=1 / 60, solver="impulse")
