"""Universal and gimbal joints (two or three successive hinges through one point, MuJoCo's
multi-hinge bodies) and joint armature: geometry against mujoco's own kinematics, the joint's
rows, per-hinge limits, torques and springs, rotor inertia, gradients."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import dbdjax as dbd
from dbdjax import diagnostics
from dbdjax import math as dm
from dbdjax.constraints import joints
from dbdjax.model import GIMBAL, JOINT_KIND_NAMES, UNIVERSAL
from dbdjax.solvers import dbd as dbd_solver

quick_jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


# ----------------------------------------------------------------------------- the angles
def _mujoco_body(axes: list[str]) -> str:
    joints = "".join(f'<joint name="h{k}" axis="{axis}"/>' for k, axis in enumerate(axes))
    return (f'<mujoco><worldbody><body pos="0.1 -0.2 1.5" euler="20 -35 50">{joints}'
            '<geom type="box" pos="0.05 0.03 -0.2" size="0.04 0.07 0.2"/></body></worldbody></mujoco>')  # fmt: skip


def _our_angles(model, quat):
    """Hinge angles of joint 0 (world to body 0) with body 0 at orientation `quat`."""
    axes_a = model.joints.local_axes_a[0]  # the world side: world coordinates
    axes_b = dm.quat_rotate(quat[None], model.joints.local_axes_b[0])
    return dm.euler_angles(axes_a, axes_b, model.structure.joint_kind.array[0] == UNIVERSAL)


@pytest.mark.parametrize(
    "axes", [["1 0 0", "0 1 0"], ["2 1 1", "0 -1 1"], ["0 0 1", "0 1 0", "1 0 0"], ["1 0 0", "0 0 1", "0 1 0"]],
    ids=["universal", "universal-tilted", "gimbal-right-handed", "gimbal-left-handed"],
)  # fmt: skip
def test_hinge_angles_match_mujoco_kinematics_for_random_joint_positions(float64, axes):
    # MuJoCo composes the hinges of one body in order, each axis in the frame the previous ones
    # left: xquat = parent * body_quat * q(axis1, q1) * q(axis2, q2) * q(axis3, q3).
    xml = _mujoco_body(axes)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    model = dbd.load_mjcf(xml)
    assert JOINT_KIND_NAMES[model.structure.joint_kind.array[0]] == ("universal" if len(axes) == 2 else "gimbal")
    rng = np.random.default_rng(len(axes))
    for _ in range(20):
        d.qpos[:] = rng.uniform(-1.4, 1.4, size=len(axes))  # the gimbal's middle angle within (-pi/2, pi/2)
        mujoco.mj_kinematics(m, d)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.ximat[1])  # the inertial frame, our body frame
        angles, _ = _our_angles(model, jnp.asarray(quat))
        np.testing.assert_allclose(angles[: len(axes)], d.qpos, atol=1e-9)


def test_angle_directions_are_the_gradients_of_the_angles(float64):
    # g_k = d t_k / d delta for a small world rotation delta of b: central differences.
    rng = np.random.default_rng(5)
    for universal, handedness in ((False, 1.0), (False, -1.0), (True, 1.0)):
        frame = np.linalg.qr(rng.normal(size=(3, 3)))[0].T
        frame[2] = handedness * np.cross(frame[0], frame[1])
        angles = rng.uniform(-1.3, 1.3, size=3) * (np.array([1, 1, 0]) if universal else 1)
        relative = jnp.array([1.0, 0.0, 0.0, 0.0])
        for k in range(3):
            relative = dm.quat_multiply(relative, dm.quat_exp(angles[k] * jnp.asarray(frame[k])))
        axes_a = jnp.asarray(frame)

        def measure(delta, relative=relative, axes_a=axes_a, universal=universal):
            turned = dm.quat_multiply(dm.quat_exp(delta), relative)
            return dm.euler_angles(axes_a, dm.quat_rotate(turned[None], axes_a), universal)

        values, directions = measure(jnp.zeros(3))
        np.testing.assert_allclose(values, angles, atol=1e-12)
        numeric = np.stack([(measure(e * 1e-6)[0] - measure(-e * 1e-6)[0]) / 2e-6 for e in np.eye(3)], axis=-1)
        used = 2 if universal else 3
        np.testing.assert_allclose(directions[:used], numeric[:used], atol=1e-8)


def test_angles_and_directions_stay_finite_at_the_gimbal_singularity():
    axes = jnp.eye(3)
    locked = dm.quat_exp(jnp.array([0.0, jnp.pi / 2, 0.0]))  # middle angle 90 degrees: axes 1 and 3 align
    gradient = jax.jacobian(lambda q: dm.euler_angles(axes, dm.quat_rotate(q[None], axes), False)[1])(locked)
    angles, directions = dm.euler_angles(axes, dm.quat_rotate(locked[None], axes), False)
    assert float(angles[1]) == pytest.approx(math.pi / 2, abs=1e-3)
    for value in (angles, directions, gradient):
        assert np.all(np.isfinite(np.asarray(value)))


# ----------------------------------------------------------------------------- the joints
def _thrown_pair(kind: str, limits=None, **finalize):
    """A rod hanging off a second rod by a universal or gimbal joint, the upper rod on a ball joint
    to the world, both thrown with generic velocities."""
    rng = np.random.default_rng(2)
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    upper = b.add_body(pos=(0, 0, -0.2), mass=1.0, inertia=(0.013, 0.013, 0.002), ang_vel=rng.normal(size=3))
    lower = b.add_body(pos=(0.02, 0.01, -0.6), mass=0.7, inertia=(0.009, 0.01, 0.002),
                       vel=rng.normal(size=3), ang_vel=3.0 * rng.normal(size=3))  # fmt: skip
    b.add_ball_joint(dbd.WORLD, upper, anchor=(0, 0, 0))
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    if kind == "universal":
        joint = b.add_universal_joint(upper, lower, anchor=(0, 0, -0.4), axes=axes[:2], limits=limits)
    else:
        joint = b.add_gimbal_joint(upper, lower, anchor=(0, 0, -0.4), axes=axes, limits=limits)
    return b.finalize(**{"dt": 1 / 120, "substeps": 2, "iterations": 8, **finalize}), joint


@pytest.mark.parametrize("kind", ["universal", "gimbal"])
def test_joint_keeps_its_point_and_the_universal_its_locked_direction(kind):
    model, joint = _thrown_pair(kind)
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=240))(dbd.init(model))
    assert float(jnp.max(diagnostics.joint_gaps(model, trajectory)[:, joint])) < 2e-3
    if kind == "universal":  # axis 1 carried by the upper rod stays perpendicular to axis 2 on the lower one
        first = dm.quat_rotate(trajectory.quat[:, 0], model.joints.local_axes_a[joint, 0])
        second = dm.quat_rotate(trajectory.quat[:, 1], model.joints.local_axes_b[joint, 1])
        assert float(jnp.max(jnp.abs(dm.dot(first, second)))) < 5e-3  # radians off 90 degrees
    spin = jnp.max(jnp.abs(trajectory.ang_vel[:, 1]))
    assert float(spin) > 2.0, "the lower rod should really move"


def _limited_scene(kind: str, limits):
    """Body 0 on a universal / gimbal joint to the world, a torque actuator on every hinge, no gravity."""
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    body = b.add_body(pos=(0.05, 0.03, -0.3), mass=1.0, inertia=(0.02, 0.025, 0.01))
    axes = [(0, 0, 1), (0, 1, 0), (1, 0, 0)] if kind == "gimbal" else [(1, 0, 0), (0, 1, 1)]
    add = b.add_gimbal_joint if kind == "gimbal" else b.add_universal_joint
    joint = add(dbd.WORLD, body, anchor=(0, 0, 0), axes=axes, limits=limits)
    for k in range(len(axes)):
        b.add_torque(joint, gear=1.0, dof=k)
    return b.finalize(dt=1 / 120, iterations=8)


@pytest.mark.parametrize(
    "kind, limits",
    [("universal", [(-0.4, 0.3), (-0.2, 0.5)]), ("gimbal", [(-0.5, 0.3), (-0.35, 0.25), (-0.3, 0.45)])],
)
def test_each_hinge_stops_at_each_of_its_limits(kind, limits):
    model = _limited_scene(kind, limits)
    count = len(limits)
    # one run per (hinge, direction): a torque of 2 N m drives that hinge alone into its bound
    pushes = np.concatenate([np.eye(count), -np.eye(count)]) * 2.0
    steps = 150

    def angles_over_time(push):
        _, trajectory = dbd.rollout(model, dbd.init(model), jnp.broadcast_to(push, (steps, count)))
        return jax.vmap(lambda quat: _our_angles(model, quat)[0])(trajectory.quat[:, 0])

    angles = np.asarray(jax.jit(jax.vmap(angles_over_time))(jnp.asarray(pushes)))[..., :count]  # (runs, T, hinges)
    lower, upper = np.array(limits).T
    for run, push in enumerate(pushes):
        k = int(np.argmax(np.abs(push)))
        bound = upper[k] if push[k] > 0 else lower[k]
        assert abs(angles[run, -1, k] - bound) < 0.01, f"hinge {k} should rest on {bound}, not {angles[run, -1, k]}"
        # every hinge stays inside its own box (the others move too: the joint-space inertia couples them)
        assert np.all(angles[run] >= lower - 0.01) and np.all(angles[run] <= upper + 0.01)


def test_torque_on_one_hinge_is_the_generalised_force_on_that_hinge_alone(float64):
    # The gimbal starts tilted 0.8 rad at its middle hinge, so hinge axes 1 and 3 are not orthogonal
    # and a torque about a hinge's own axis would also drive the other. From rest with no gravity,
    # one step's angle velocities over dt must be M^-1 Q (M the joint-space inertia, Q = gear u
    # on each hinge): MuJoCo's qacc.
    xml = """<mujoco><option gravity="0 0 0" timestep="0.0005"/><worldbody><body pos="0 0 1" euler="10 20 30">
        <joint name="a" axis="0 0 1"/><joint name="b" axis="0 1 0"/><joint name="c" axis="1 0 0"/>
        <geom type="box" pos="0.05 0.02 -0.2" size="0.04 0.07 0.2"/></body></worldbody>
        <actuator><motor joint="a" gear="1"/><motor joint="b" gear="2"/><motor joint="c" gear="0.5"/></actuator>
        </mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = [0.3, 0.8, -0.4]
    d.ctrl[:] = [0.3, -0.2, 0.4]
    mujoco.mj_forward(m, d)
    model = dbd.load_mjcf(xml, iterations=30)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, d.ximat[1])
    start = dataclasses.replace(dbd.init(model), pos=jnp.asarray(d.xipos[1:2]), quat=jnp.asarray(quat)[None])
    state = dbd.step(model, start, jnp.asarray(d.ctrl))
    _, directions = _our_angles(model, state.quat[0])
    rates = directions @ state.ang_vel[0]
    np.testing.assert_allclose(rates / model.dt, d.qacc, rtol=2e-3)
    # the hinges' own axes would not do: the first and last are 0.8 rad from orthogonal
    assert abs(float(dm.dot(directions[0], directions[2]))) > 0.1


def test_per_hinge_springs_pull_each_hinge_with_its_own_stiffness(float64):
    # Small free oscillation of each hinge alone: period 2 pi sqrt(I_k / k_k) with I_k the joint-space
    # inertia of that hinge; three hinges, three periods.
    xml = """<mujoco><option gravity="0 0 0" timestep="0.002"/><worldbody><body pos="0 0 1">
        <joint name="a" axis="1 0 0" stiffness="2"/><joint name="b" axis="0 1 0" stiffness="5"/>
        <joint name="c" axis="0 0 1" stiffness="0.5"/>
        <geom type="box" size="0.05 0.1 0.2"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    np.testing.assert_allclose(m.body_iquat[1], [1, 0, 0, 0])  # principal axes = the hinge axes here
    diagonal = m.body_inertia[1]  # the joint-space inertia of each hinge (the joint sits at the centre)
    model = dbd.load_mjcf(xml, iterations=8)
    run = jax.jit(
        lambda s: jax.vmap(lambda q: _our_angles(model, q)[0])(dbd.rollout(model, s, steps=2100)[1].quat[:, 0])
    )
    for k, stiffness in enumerate((2.0, 5.0, 0.5)):
        kick = np.zeros(3)
        kick[k] = 0.05  # rad/s about hinge k (the hinges are the world axes at rest)
        period = 2 * np.pi * np.sqrt(diagonal[k] / stiffness)  # 0.9 - 1.7 s: 2100 steps hold 2.5 of them
        angles = np.asarray(run(dataclasses.replace(dbd.init(model), ang_vel=jnp.asarray(kick)[None])))
        crossings = np.where((angles[:-1, k] < 0) & (angles[1:, k] >= 0))[0]
        measured = np.mean(np.diff(crossings)) * model.dt
        assert measured == pytest.approx(period, rel=0.02)
        assert np.max(np.abs(np.delete(angles, k, axis=1))) < 1e-6, "the other hinges stay still"


# ----------------------------------------------------------------------------- armature
@pytest.mark.parametrize("kind", ["hinge", "slider"])
def test_armature_adds_to_the_inertia_a_torque_accelerates(float64, kind):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    body = b.add_body(pos=(0, 0, 1), mass=2.0, inertia=(0.1, 0.2, 0.3))
    add = b.add_hinge_joint if kind == "hinge" else b.add_slider_joint
    joint = add(dbd.WORLD, body, anchor=(0, 0, 1), axis=(1, 0, 0))
    b.add_armature(joint, 0.5)
    b.add_torque(joint, gear=3.0)
    model = b.finalize(dt=0.01, iterations=8)
    final, _ = dbd.rollout(model, dbd.init(model), jnp.ones((100, 1)))
    speed = final.ang_vel[0, 0] if kind == "hinge" else final.vel[0, 0]
    inertia = 0.1 if kind == "hinge" else 2.0
    assert float(speed) == pytest.approx(3.0 * 1.0 / (inertia + 0.5), rel=1e-9)  # gear u t / (I + armature)


def test_armature_on_a_joint_between_free_bodies_spins_their_relative_motion_as_mujoco(float64):
    # MuJoCo's armature is inertia on the joint coordinate, not on the child: with a free parent the
    # rotor's reaction turns both bodies. No gravity, a motor on the hinge; at 40 sweeps the
    # Gauss-Seidel error is gone (8 sweeps: 4e-3 rad of the 0.44 rad swing, measured) and what is
    # left is the integrators' difference, 6.5e-7 rad measured.
    xml = """<mujoco><option gravity="0 0 0" timestep="0.001"/><worldbody>
        <body pos="0 0 2" euler="10 20 30"><freejoint/><geom type="box" size="0.1 0.15 0.2"/>
        <body pos="0 0.1 -0.2"><joint name="h" axis="1 1 0" armature="0.5"/>
        <geom type="capsule" fromto="0 0 0 0.1 0 -0.4" size="0.04"/></body></body></worldbody>
        <actuator><motor joint="h" gear="1"/></actuator></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.ctrl[:] = 0.5
    angles = []
    for _ in range(1000):
        mujoco.mj_step(m, d)
        angles.append(d.qpos[7])
    model = dbd.load_mjcf(xml, iterations=40)
    _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), jnp.full((1000, 1), 0.5))
    relative = dm.quat_multiply(dm.quat_multiply(dm.quat_conjugate(trajectory.quat[:, 0]), trajectory.quat[:, 1]),
                                dm.quat_conjugate(model.joints.rest_rotation[0]))  # fmt: skip
    ours = dm.quat_twist_angle(relative, model.joints.local_axis_a[0])
    assert float(np.max(np.abs(np.asarray(ours) - np.array(angles)))) < 1e-5
    assert abs(angles[-1]) > 0.4


@pytest.mark.parametrize(
    ("excess", "expected"),
    [(0.01, "merged"), (-0.01, "unchanged"), (0.05, "stopped"), (0.0, "unchanged")],
    ids=["slower", "faster", "past-zero", "converged"],
)  # fmt: skip
def test_rotor_pass_takes_back_unpaid_spin_at_the_merged_rate_and_never_adds_any(float64, excess, expected):
    # A light bob (0.1 kg, 0.2 m below its hinge, inertia 0.001) on a hinge with armature 1 spinning
    # at 2 rad/s. The sweeps left the rotor row a residual `excess` (rad): the rotor's momentum says
    # 2 - excess / h. Rotor and bob meet at 2 - s excess / h, s = a w / (1 + a w), w = 1 / (I + m d^2)
    # the bob's response about the hinge with its point held; that rate is taken only toward zero.
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    bob = b.add_body(pos=(0, 0, 0.8), mass=0.1, inertia=(0.001, 0.001, 0.001), ang_vel=(2.0, 0, 0), vel=(0, 0.4, 0))
    b.add_armature(b.add_hinge_joint(dbd.WORLD, bob, anchor=(0, 0, 1), axis=(1, 0, 0)), 1.0)
    h = 0.01
    model = b.finalize(dt=h)
    pair = np.array([model.num_bodies, bob])  # (world, bob): the joint's (a, b)
    bodies = jax.tree.map(lambda column: column[pair], dbd_solver.body_table(model, dbd.init(model), h))
    joint = jax.tree.map(lambda x: x[0], model.joints)
    flag = jax.tree.map(lambda x: x[0], joints.flags(model.structure))
    dv, dw, _ = joints.project_rotor_momentum(joint, flag, jnp.array([excess, 0.0, 0.0]), bodies, jnp.zeros(3), h,
                                              joints.rows_in_use(model.structure))  # fmt: skip
    share = 1.0 / (1.0 + (0.001 + 0.1 * 0.2**2))  # a w / (1 + a w) with a = 1
    rate = 2.0 + float(dw[1, 0])
    wanted = {"merged": 2.0 - share * excess / h, "unchanged": 2.0, "stopped": 0.0}[expected]
    assert rate == pytest.approx(wanted, rel=1e-9, abs=1e-12)
    point_speed = dv[1] + jnp.cross(dw[1], jnp.array([0.0, 0.0, 0.2]))  # the hinge point, 0.2 m above the bob
    assert float(jnp.max(jnp.abs(point_speed))) < 1e-12
    assert float(jnp.max(jnp.abs(dw[1, 1:]))) < 1e-12


# ----------------------------------------------------------------------------- gradients
def _universal_pendulum(armature: bool):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    bob = b.add_body(pos=(0.1, 0.05, -0.4), mass=1.0, inertia=(0.02, 0.022, 0.004), ang_vel=(0.7, -0.4, 0.3))
    limits = [(-1.0, 1.0), (-1.0, 1.0)] if armature else None  # (not reached: inactive rows)
    joint = b.add_universal_joint(dbd.WORLD, bob, anchor=(0, 0, 0), axes=[(1, 0, 0), (0, 1, 0)], limits=limits)
    b.add_joint_spring(joint, stiffness=[2.0, 1.0], damping=[0.05, 0.1])
    if armature:
        b.add_armature(joint, [0.01, 0.02])
    return b.finalize(dt=1 / 60, iterations=6)


@pytest.mark.parametrize("armature", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_gradient_through_a_universal_joint_pendulum_matches_finite_differences(float64, armature):
    # A universal-joint pendulum with per-hinge springs (and armature and limits), thrown:
    # d(final tip) / d(initial angular velocity, per-hinge stiffness, armature) against central
    # differences. Measured relative errors 5e-9, 7e-10, 3e-10.
    model = _universal_pendulum(armature)
    names = ("axis_stiffness", "armature") if armature else ("axis_stiffness",)

    def loss(ang_vel, *values):
        joints = dataclasses.replace(model.joints, **dict(zip(names, values, strict=True)))
        start = dataclasses.replace(dbd.init(model), ang_vel=ang_vel)
        final, _ = dbd.rollout(dataclasses.replace(model, joints=joints), start, steps=20)
        tip = final.pos[0] + dm.quat_rotate(final.quat[0], jnp.array([0.0, 0.0, -0.2]))
        return tip[0] + 2.0 * tip[1] + 0.5 * tip[2]

    args = [dbd.init(model).ang_vel] + [getattr(model.joints, name) for name in names]
    value_and_gradient = quick_jit(jax.value_and_grad(loss, argnums=tuple(range(len(args)))))
    analytic = value_and_gradient(*args)[1]

    def fast(*values):  # the same program gives the differences: no second compile of the rollout
        return value_and_gradient(*values)[0]

    for index, value in enumerate(args):
        numeric = np.zeros(value.shape)
        for position in np.ndindex(value.shape):
            if index and position[-1] > 1:
                continue  # the universal joint's third hinge slot is unused
            step = jnp.zeros(value.shape).at[position].set(1e-6)
            plus = fast(*[v + step if i == index else v for i, v in enumerate(args)])
            minus = fast(*[v - step if i == index else v for i, v in enumerate(args)])
            numeric[position] = (plus - minus) / 2e-6
        gradient = np.asarray(analytic[index])
        error = np.linalg.norm(gradient - numeric) / max(np.linalg.norm(numeric), 1e-12)
        assert np.all(np.isfinite(gradient))
        assert error < 1e-4, (index, gradient, numeric)
        assert np.linalg.norm(numeric) > 1e-3  # the loss depends on it


# ----------------------------------------------------------------------------- refusals
def test_builder_refuses_bad_multi_hinge_joints_naming_the_problem():
    b = dbd.ModelBuilder()
    body = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="perpendicular"):
        b.add_universal_joint(dbd.WORLD, body, anchor=(0, 0, 1), axes=[(1, 0, 0), (1, 1, 0)])
    with pytest.raises(ValueError, match="needs 3 axes"):
        b.add_gimbal_joint(dbd.WORLD, body, anchor=(0, 0, 1), axes=[(1, 0, 0), (0, 1, 0)])
    with pytest.raises(ValueError, match="middle axis"):
        b.add_gimbal_joint(dbd.WORLD, body, anchor=(0, 0, 1), axes=np.eye(3), limits=[None, (-2.0, 0.0), None])
    joint = b.add_universal_joint(dbd.WORLD, body, anchor=(0, 0, 1), axes=[(1, 0, 0), (0, 1, 0)])
    with pytest.raises(ValueError, match="dof"):
        b.add_torque(joint, gear=1.0)
    with pytest.raises(ValueError, match="one per hinge"):
        b.add_joint_spring(joint, stiffness=[1.0, 2.0, 3.0])
    ball = b.add_ball_joint(body, b.add_body(pos=(0, 0, 0), mass=1.0, inertia=(0.1, 0.1, 0.1)), anchor=(0, 0, 0.5))
    b.add_armature(ball, 0.1)
    b.add_torque(ball, axis=(0, 0, 1))
    with pytest.raises(ValueError, match="armature and a torque"):
        b.finalize()


def test_gimbal_kind_constant_names_the_gimbal():
    assert JOINT_KIND_NAMES[GIMBAL] == "gimbal" and JOINT_KIND_NAMES[UNIVERSAL] == "universal"
