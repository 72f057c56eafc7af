"""States carried between dbdjax and MuJoCo (`dbdjax.mujoco_state`): body by body from MuJoCo, a
least-squares fit to MuJoCo's coordinates, the same energy counted on both sides."""

from pathlib import Path

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from ci_cases import slow_except
from test_mjcf import SCENES  # small chains: slides, balls, universal and gimbal joints, armature

import dbdjax as dbd
from dbdjax import diagnostics

ASSETS = Path(__file__).parent / "assets"
MODELS = {name: ASSETS / f"{name}.xml" for name in ("ant", "humanoid", "hopper", "walker2d", "half_cheetah")}
MODELS["ragdoll"] = Path(dbd.__file__).parent / "assets" / "ragdoll.xml"  # 3 hinges merged into ball joints


def _random_state(m, seed: int) -> mujoco.MjData:
    """MuJoCo's data at qpos0 moved by uniform draws in [-0.4, 0.4] along every dof (rad, m), with
    velocities drawn from N(0, 0.5^2)."""
    rng = np.random.default_rng(seed)
    d = mujoco.MjData(m)
    qpos = m.qpos0.copy()
    mujoco.mj_integratePos(m, qpos, rng.uniform(-0.4, 0.4, m.nv), 1.0)
    d.qpos[:], d.qvel[:] = qpos, 0.5 * rng.standard_normal(m.nv)
    return d


def _mujoco_energy(m, d) -> tuple[float, float]:
    """(kinetic in joint space with armature plus gravity's potential, the armature's share) J:
    what `diagnostics.energy` counts. Not MuJoCo's own `d.energy` (flag `energy`): its potential
    also holds the joint springs' (humanoid.xml, half_cheetah.xml), which `energy` leaves out."""
    momentum = np.zeros(m.nv)
    mujoco.mj_forward(m, d)
    mujoco.mj_mulM(m, d, momentum, d.qvel)
    potential = -np.sum(m.body_mass[:, None] * m.opt.gravity[None] * d.xipos)
    return 0.5 * float(d.qvel @ momentum) + float(potential), 0.5 * float(np.sum(m.dof_armature * d.qvel**2))


@pytest.mark.parametrize("name", list(MODELS))
def test_mujocos_qpos0_at_rest_is_dbdjaxs_build_pose(name):
    model = dbd.load_mjcf(MODELS[name])
    m = dbd.mujoco_model(MODELS[name])
    state, built = dbd.state_from_mujoco(model, m, mujoco.MjData(m)), dbd.init(model)
    np.testing.assert_allclose(state.pos, built.pos, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(state.quat) * np.asarray(built.quat), -1)), 1.0, atol=1e-6)
    assert float(jnp.max(jnp.abs(state.vel))) == 0.0 and float(jnp.max(jnp.abs(state.ang_vel))) == 0.0


@pytest.mark.parametrize("name", list(MODELS))
def test_a_mujoco_state_carried_to_dbdjax_and_back_is_the_same_qpos_and_qvel(name):
    model = dbd.load_mjcf(MODELS[name])
    m = dbd.mujoco_model(MODELS[name])
    d = _random_state(m, seed=0)
    back = dbd.state_to_mujoco(model, dbd.state_from_mujoco(model, m, d), m)
    # (a float32 state between: rounding of 1e-7 m, rad; the fit converges to 1e-10)
    np.testing.assert_allclose(back.qpos, d.qpos, atol=2e-6)
    np.testing.assert_allclose(back.qvel, d.qvel, atol=2e-6)


@pytest.mark.parametrize("name", slow_except(list(MODELS), kept=["humanoid", "half_cheetah", "ragdoll"]))
def test_dbdjax_counts_the_energy_of_a_mujoco_state_as_mujoco_does(float64, name):
    # The bodies' kinetic energy at their centres, their rotors' (armature: 1/2 a qdot^2 per dof,
    # `diagnostics.rotor_energy`, with qdot read from the bodies) and gravity's potential: equal to
    # MuJoCo's 1/2 qdot^T M qdot + potential on every model. (The ragdoll's rotors: none; the ant's
    # are most of its energy at these speeds.)
    model = dbd.load_mjcf(MODELS[name])
    m = dbd.mujoco_model(MODELS[name])
    d = _random_state(m, seed=1)
    energy, rotors = _mujoco_energy(m, d)
    state = dbd.state_from_mujoco(model, m, d)
    assert float(diagnostics.energy(model, state)) == pytest.approx(energy, rel=1e-9, abs=1e-9)
    assert float(diagnostics.rotor_energy(model, state)) == pytest.approx(rotors, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("name", list(SCENES))
def test_the_chains_states_go_both_ways_with_the_same_energy(float64, name):
    # Every joint kind the import maps (ball joints' quaternions, slides, the universal and gimbal
    # joints' successive hinges) and the rotors on slides, balls and gimbals. In float64 the way
    # back is exact to 1e-12 (measured: 2e-15 at most).
    body, extra, _, _ = SCENES[name]
    xml = f"<mujoco><worldbody>{body}</worldbody>{extra}</mujoco>"
    model, m = dbd.load_mjcf(xml), dbd.mujoco_model(xml)
    d = _random_state(m, seed=2)
    state = dbd.state_from_mujoco(model, m, d)
    back = dbd.state_to_mujoco(model, state, m)
    np.testing.assert_allclose(back.qpos, d.qpos, atol=1e-12)
    np.testing.assert_allclose(back.qvel, d.qvel, atol=1e-12)
    energy, rotors = _mujoco_energy(m, d)
    assert float(diagnostics.energy(model, state)) == pytest.approx(energy, rel=1e-12)
    assert float(diagnostics.rotor_energy(model, state)) == pytest.approx(rotors, rel=1e-12, abs=1e-15)


def test_state_to_mujoco_refuses_a_batch_and_another_files_mujoco_model():
    model = dbd.load_mjcf(MODELS["ant"])
    state = dbd.init(model)
    batched = dbd.State(*(jnp.stack([x, x]) for x in (state.pos, state.quat, state.vel, state.ang_vel)))
    with pytest.raises(ValueError, match="one state at a time"):
        dbd.state_to_mujoco(model, batched, dbd.mujoco_model(MODELS["ant"]))
    unfused = mujoco.MjModel.from_xml_path(str(MODELS["ant"]))  # its four jointless bodies kept: 13 besides the world
    with pytest.raises(ValueError, match="13 bodies besides the world, the dbdjax model 9"):
        dbd.state_to_mujoco(model, state, unfused)
    with pytest.raises(ValueError, match="mujoco_model"):
        dbd.state_from_mujoco(model, unfused, mujoco.MjData(unfused))


def test_state_to_mujoco_warns_where_its_pose_fit_does_not_converge(monkeypatch):
    # Two Gauss-Newton steps from qpos0 are not enough for a state 0.4 rad away on every dof.
    model = dbd.load_mjcf(MODELS["humanoid"])
    m = dbd.mujoco_model(MODELS["humanoid"])
    state = dbd.state_from_mujoco(model, m, _random_state(m, seed=3))
    monkeypatch.setattr(dbd.mujoco_state, "_MAX_ITERATIONS", 2)
    with pytest.warns(UserWarning, match="the pose fit did not converge in 2 Gauss-Newton steps"):
        dbd.state_to_mujoco(model, state, m)
