"""Soft joint limits (`ModelBuilder.set_limit_softness`, MJCF solreflimit): a limit row past its
bound is a spring and damper per unit effective mass that only pushes, as MuJoCo's soft limits;
and limit angles measured from the middle of the range, so a joint pushed past pi keeps its bound."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes
from derivatives import gradient_and_central_difference, relative_error

import dbdjax as dbd
from dbdjax import diagnostics
from dbdjax import math as dm

mujoco = pytest.importorskip("mujoco")
ASSETS = Path(__file__).parent / "assets"
BOUND = np.radians(10.0)  # the lower bound of `_pendulum_xml`'s range; qpos0 = 0 lies 10 degrees below it


def _pendulum_xml(dt: float, solref: str, armature: float = 0.0) -> str:
    """A rod on a hinge about y, no gravity, built 10 degrees below its range's lower bound."""
    return f"""<mujoco><option timestep="{dt}" gravity="0 0 0"/><worldbody>
    <body pos="0 0 1"><joint type="hinge" axis="0 1 0" limited="true" range="10 60" solreflimit="{solref}"
    armature="{armature}"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/></body></worldbody></mujoco>"""


def _one_sided_oscillator(time_constant: float, damping_ratio: float, violation: float, times: np.ndarray):
    """The violation r(t) of a limit that pushes with r'' = max(0, -(omega^2 r + 2 zeta omega r'))
    while r < 0 (omega = 1 / (time_constant damping_ratio)), from rest; fine explicit steps."""
    omega, damping = 1.0 / (time_constant * damping_ratio), 2.0 / time_constant
    fine = 2e-6
    r, v, out, t = violation, 0.0, [], 0.0
    for target in times:
        while t < target - 1e-12:
            v += (max(0.0, -(omega**2 * r + damping * v)) if r < 0.0 else 0.0) * fine
            r += v * fine
            t += fine
        out.append(r)
    return np.array(out)


def _gap_to_mujoco(
    dt: float, solref: str, seconds: float, armature: float = 0.0
) -> tuple[float, np.ndarray, np.ndarray]:
    """(max |q - q_mujoco| over `seconds`, our q, the sample times), both stepped at dt."""
    xml = _pendulum_xml(dt, solref, armature)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    steps = round(seconds / dt)
    theirs = []
    for _ in range(steps):
        mujoco.mj_step(m, d)
        theirs.append(d.qpos[0])
    model = dbd.load_mjcf(xml, iterations=8)
    _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), jnp.zeros((steps, 0)))
    ours = scenes.hinge_angles(model, trajectory.quat)[:, 0, 0]
    return float(np.max(np.abs(ours - np.array(theirs)))), ours, dt * np.arange(1, steps + 1)


# measured largest |q - q_mujoco| over 0.3 s at dt = 1 ms (MuJoCo's own Euler step and ours differ to
# first order; the gap fell 4x at dt = 0.25 ms: 0.0084, 0.0276, 0.0014 rad)
SOLREFS = {"0.02 1": 3.4e-2, "0.02 0.5": 1.05e-1, "0.05 1": 5.5e-3}
# measured largest |q - r(t)| over the first 0.1 s against the one-sided oscillator (0.0063, 0.0499,
# 0.0006 rad)
ODE_GAPS = {"0.02 1": 7e-3, "0.02 0.5": 5.5e-2, "0.05 1": 7e-4}


@pytest.mark.parametrize("solref", list(SOLREFS))
def test_a_pose_built_past_a_soft_limit_eases_back_as_mujoco_does(float64, solref):
    gap, ours, times = _gap_to_mujoco(1e-3, solref, 0.3)
    assert gap < SOLREFS[solref]
    # and both follow the one-sided oscillator MuJoCo's soft limit is, while inside the range's
    # first 0.1 s (the rod then coasts on towards the upper bound)
    time_constant, damping_ratio = (float(v) for v in solref.split())
    early = times <= 0.1
    exact = BOUND + _one_sided_oscillator(time_constant, damping_ratio, -BOUND, times[early])
    assert np.max(np.abs(ours[early] - exact)) < ODE_GAPS[solref]


# the same with armature 4 kg m^2 on the hinge, 10x the rod's own 0.40 kg m^2 about it (measured:
# 0.0275, 0.1200, 0.0053 rad; before the limit's effective mass counted the armature, 0.48, 0.67 and
# 0.21 rad: the spring was 11x too soft)
ARMATURE_GAPS = {"0.02 1": 3.4e-2, "0.02 0.5": 1.3e-1, "0.05 1": 5.5e-3}


@pytest.mark.parametrize("solref", list(SOLREFS))
def test_a_soft_limit_on_a_hinge_with_armature_eases_back_as_mujoco_does(float64, solref):
    # MuJoCo's soft limit is a spring per unit of the joint-space mass, armature included; the rotor
    # row carries the armature's inertia, and the limit row's effective mass must count it too.
    gap, ours, times = _gap_to_mujoco(1e-3, solref, 0.3, armature=4.0)
    assert gap < ARMATURE_GAPS[solref]
    time_constant, damping_ratio = (float(v) for v in solref.split())
    early = times <= 0.1
    exact = BOUND + _one_sided_oscillator(time_constant, damping_ratio, -BOUND, times[early])
    assert np.max(np.abs(ours[early] - exact)) < ODE_GAPS[solref]


@pytest.mark.slow
@pytest.mark.parametrize("solref", list(SOLREFS))
def test_soft_limit_gap_to_mujoco_shrinks_with_the_timestep(float64, solref):
    # a modelling error would stay as dt shrinks; the two Euler steps' O(dt) difference shrinks 4x
    fine, coarse = (_gap_to_mujoco(dt, solref, 0.3)[0] for dt in (2.5e-4, 1e-3))
    assert fine < 0.35 * coarse


def test_a_soft_limit_sags_under_a_steady_torque_by_torque_over_omega_squared_inertia(float64):
    # A rod on a hinge resting on its soft upper bound under gravity: the limit is a spring of
    # stiffness omega^2 I per unit angle, I the rod's inertia about the hinge, so it sags past the
    # bound by m g l / (omega^2 I) (the damper is idle at rest).
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = builder.add_body(pos=(0.5, 0.0, 1.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    hinge = builder.add_hinge_joint(dbd.WORLD, rod, anchor=(0.0, 0.0, 1.0), axis=(0.0, 1.0, 0.0), limits=(-0.3, 0.3))
    builder.set_limit_softness(hinge, time_constant=0.05, damping_ratio=1.0)
    model = builder.finalize(dt=1e-3, iterations=8)
    final, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=3000))(dbd.init(model))
    angle = scenes.hinge_angles(model, trajectory.quat)[-1, 0, 0]  # gravity turns it towards the upper bound
    omega = 1.0 / 0.05
    inertia = 0.01 + 1.0 * 0.5**2
    torque = 1.0 * 9.81 * 0.5 * np.cos(angle)
    assert angle - 0.3 == pytest.approx(torque / (omega**2 * inertia), rel=0.02)
    assert float(jnp.max(jnp.abs(final.ang_vel))) < 1e-3


def test_rigid_limits_hold_the_bound_under_the_same_torque(float64):
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = builder.add_body(pos=(0.5, 0.0, 1.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    builder.add_hinge_joint(dbd.WORLD, rod, anchor=(0.0, 0.0, 1.0), axis=(0.0, 1.0, 0.0), limits=(-0.3, 0.3))
    model = builder.finalize(dt=1e-3, iterations=8)
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=3000))(dbd.init(model))
    assert scenes.hinge_angles(model, trajectory.quat)[-1, 0, 0] == pytest.approx(0.3, abs=1e-4)


@pytest.mark.parametrize("solver", ["dbd", "impulse"])
def test_a_hinge_turned_past_pi_beyond_its_bound_is_pushed_back_to_that_bound(float64, solver):
    # Limits (-3.0, -0.5); the rod starts turned to -3.3 rad, 0.3 past the lower bound and beyond
    # -pi. Measured from zero and wrapped, -3.3 reads +2.98, 3.48 past the upper bound, and the rod
    # was driven back the long way, through the excluded arc; measured from the middle of the range
    # it is 0.3 past the lower bound, and the limit turns it back to that bound.
    builder = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    rod = builder.add_body(pos=(0.5, 0.0, 0.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    builder.add_hinge_joint(dbd.WORLD, rod, anchor=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), limits=(-3.0, -0.5))
    model = builder.finalize(dt=1e-3, iterations=8, solver=solver)
    turn = dm.quat_exp(jnp.array([[0.0, -3.3, 0.0]]))  # about the hinge, through the origin
    state = dbd.init(model)
    state = dataclasses.replace(state, pos=dm.quat_rotate(turn, state.pos), quat=dm.quat_multiply(turn, state.quat))
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=50))(state)
    angles = scenes.hinge_angles(model, trajectory.quat)[:5, 0, 0]
    past = np.asarray(dm.wrap_angle(jnp.asarray(angles) + 3.0))  # from the bound
    # the short way back: from 0.3 below the bound up through it (the correction's speed then
    # carries the rod on into its range, a rigid limit's kick), never down into the excluded arc
    assert past[0] > -0.3 and np.all(np.diff(past) > 0.0)


@pytest.mark.parametrize("name", [pytest.param("humanoid", marks=pytest.mark.slow), "ant"])  # humanoid: 60 s
def test_mjcf_model_built_past_its_limits_starts_no_faster_than_mujoco(name):
    # Brax's humanoid starts with its knees 2 degrees outside their range, the ant with its ankles
    # 30 degrees outside. Rigid limits snapped them back within the first step: the largest angular
    # speed after it was 6.5 rad/s (humanoid) and 31 rad/s (ant). MuJoCo's soft limits ease them
    # back: after its first step 0.13 rad/s (humanoid) and 12.96 rad/s (the ant's ankles, whose
    # 1 kg m^2 rotors the limit accelerates at omega^2 = 2500 / s^2 times 30 degrees); ours 0.08
    # and 5.8 rad/s at 1 x 8 (8.7-10 rad/s converged, at 128-512 iterations). Brax positional's
    # humanoid: 0.58 rad/s.
    model = dbd.load_mjcf(ASSETS / f"{name}.xml")
    state = jax.jit(lambda s: dbd.step(model, s, jnp.zeros(model.num_controls)))(dbd.init(model))
    reference = mujoco.MjModel.from_xml_path(str(ASSETS / f"{name}.xml"))
    data = mujoco.MjData(reference)
    mujoco.mj_step(reference, data)
    mujoco.mj_forward(reference, data)
    theirs = float(np.max(np.linalg.norm(data.cvel[1:, :3], axis=-1)))
    assert float(jnp.max(jnp.linalg.norm(state.ang_vel, axis=-1))) < 1.2 * theirs + 0.5
    rigid = dbd.load_mjcf(ASSETS / f"{name}.xml", soft_limits=False)
    state = jax.jit(lambda s: dbd.step(rigid, s, jnp.zeros(rigid.num_controls)))(dbd.init(rigid))
    assert float(jnp.max(jnp.linalg.norm(state.ang_vel, axis=-1))) > 5.0


@pytest.mark.slow  # 59 s; the ant built past its limits against MuJoCo (below) and the soft
# limit's gradient stay in CI
def test_dropped_humanoid_gains_no_energy_with_soft_limits():
    # Zero control, 1 s from the build pose at 1 substep x 4 iterations (brax_comparison.py's
    # accuracy task): contacts, joint damping and the limits' dampers only take energy out. With
    # rigid limits the first step's knee correction added 6.75 J; measured now: -0.017 J at most.
    model = dbd.load_mjcf(ASSETS / "humanoid.xml", substeps=1, iterations=4)
    start = dbd.init(model)
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, jnp.zeros((333, model.num_controls))))(start)
    energy = np.asarray(jax.vmap(lambda state: diagnostics.energy(model, state))(trajectory))
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    assert energy.max() < float(diagnostics.energy(model, start)) + 0.1


@pytest.mark.slow
def test_dropped_ant_stands_on_its_soft_limits():
    # Brax's ant has armature 1 kg m^2 on every hinge, far above its legs' own inertia: a soft limit
    # per unit of the bodies' effective mass alone was too soft to carry the ant, whose ankles
    # folded 1.0-1.2 rad past their bounds until the torso lay below the floor (-0.22 m after 3 s at
    # 16 iterations; its sphere does not collide). Counting the armature in that mass, measured:
    # torso 0.35 m, every hinge within 0.06 rad of its range (MuJoCo: 0.59 m at 3 s with the ankles
    # inside their ranges, still folding at the pace of its joint damping; 0.3625 m at 60 s with
    # the ankles on their limits; rigid limits: 0.60 m).
    model = dbd.load_mjcf(ASSETS / "ant.xml", substeps=1, iterations=16)
    final, trajectory = jax.jit(lambda s: dbd.rollout(model, s, jnp.zeros((300, model.num_controls))))(dbd.init(model))
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    assert float(final.pos[0, 2]) > 0.3
    angles = scenes.hinge_angles(model, final.quat[None])[0, :, 0]
    lower, upper = np.asarray(model.joints.lower), np.asarray(model.joints.upper)
    outside = np.maximum(lower - angles, angles - upper)
    assert outside.max() < 0.1, outside


def test_gradient_through_a_soft_limit_matches_finite_differences(float64):
    # The rod swings into its soft upper bound and is pushed back: d(final angle)/d(initial spin,
    # time constant) by reverse mode against central differences.
    def final_angle(parameters):
        spin, time_constant = parameters[0], parameters[1]
        builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        rod = builder.add_body(pos=(0.5, 0.0, 1.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
        hinge = builder.add_hinge_joint(dbd.WORLD, rod, anchor=(0.0, 0.0, 1.0), axis=(0.0, 1.0, 0.0),
                                        limits=(-0.3, 0.3))  # fmt: skip
        builder.set_limit_softness(hinge, time_constant=0.05, damping_ratio=0.7)
        model = builder.finalize(dt=2e-3, iterations=4)
        scale = time_constant / 0.05  # the time constant as a differentiable parameter of the model
        joints = dataclasses.replace(model.joints, limit_stiffness=model.joints.limit_stiffness / scale**2,
                                     limit_damping=model.joints.limit_damping / scale)  # fmt: skip
        model = dataclasses.replace(model, joints=joints)
        state = dbd.init(model)
        state = dataclasses.replace(state, ang_vel=state.ang_vel.at[0, 1].set(spin),
                                    vel=state.vel.at[0, 2].set(-0.5 * spin))  # fmt: skip
        final, _ = dbd.rollout(model, state, steps=150)
        return jnp.arctan2(-(final.pos[0, 2] - 1.0), final.pos[0, 0])

    parameters = np.array([2.0, 0.05])
    gradient, numeric = gradient_and_central_difference(final_angle, jnp.asarray(parameters))
    assert np.all(np.isfinite(np.asarray(gradient)))
    assert relative_error(gradient, numeric) < 1e-4


def test_mjcf_limits_map_solreflimit_and_a_full_turn_range_maps_to_no_limit():
    xml = """<mujoco><option timestep="0.004"/><worldbody>
    <body><joint name="wide" type="hinge" axis="0 1 0" range="-200 200" limited="true"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/>
    <body pos="0.5 0 0"><joint name="knee" type="hinge" axis="0 1 0" range="-90 0" solreflimit="0.005 0.5"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/></body></body></worldbody></mujoco>"""
    model = dbd.load_mjcf(xml)
    assert list(model.structure.joint_soft_limits.array) == [False, True]
    # the time constant 0.005 s is below 2 dt: MuJoCo's refsafe raises it to 0.008 s
    omega = 1.0 / (0.008 * 0.5)
    assert float(model.joints.limit_stiffness[1]) == pytest.approx(omega**2)
    assert float(model.joints.limit_damping[1]) == pytest.approx(2.0 / 0.008)
    rigid = dbd.load_mjcf(xml, soft_limits=False)
    assert not rigid.structure.joint_soft_limits.array.any()


def test_set_limit_softness_refuses_a_joint_without_limits_and_non_positive_parameters():
    builder = dbd.ModelBuilder()
    rod = builder.add_body(pos=(0.5, 0.0, 0.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    free = builder.add_hinge_joint(dbd.WORLD, rod, anchor=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), name="free")
    with pytest.raises(ValueError, match="hinge joint 0 .'free'. has no limits"):
        builder.set_limit_softness(free, 0.02)
    other = builder.add_body(pos=(1.5, 0.0, 0.0), mass=1.0, inertia=(0.01, 0.01, 0.01))
    limited = builder.add_hinge_joint(rod, other, anchor=(1.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), limits=(-1, 1))
    with pytest.raises(ValueError, match="time_constant and damping_ratio must be positive"):
        builder.set_limit_softness(limited, 0.0)
    with pytest.raises(ValueError, match="time_constant and damping_ratio must be positive"):
        builder.set_limit_softness(limited, 0.02, damping_ratio=-1.0)
    with pytest.raises(ValueError, match="NaN"):
        builder.set_limit_softness(limited, float("nan"))
