"""MJCF import: the Brax models load and run, unsupported elements are refused by name, and small
chains follow MuJoCo's own mj_step."""

import itertools
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from ci_cases import slow_except

import dbdjax as dbd
from dbdjax import diagnostics
from dbdjax import math as dm
from dbdjax.constraints import joints as joint_rows
from dbdjax.model import GIMBAL, JOINT_KIND_NAMES, SLIDER, UNIVERSAL
from dbdjax.solvers import dbd as dbd_solver

ASSETS = Path(__file__).parent / "assets"
BRAX_MODELS = ("humanoid", "ant", "hopper", "walker2d", "half_cheetah")
pytestmark = pytest.mark.filterwarnings("ignore:compiler attribute 'settotalmass' is deprecated")

# ----------------------------------------------------------------------------- Brax models
# (bodies, joint kinds, controls) after MuJoCo's fusestatic: the humanoid's two-hinge abdomen and
# shoulders become universal joints and its three-hinge hips gimbal joints, the 2-D walkers'
# slide-slide-hinge roots planar joints.
EXPECTED = {
    "humanoid": (
        11,
        ["universal", "hinge", "gimbal", "hinge", "gimbal", "hinge", "universal", "hinge", "universal", "hinge"],
        17,
    ),  # fmt: skip
    "ant": (9, ["hinge"] * 8, 8),
    "hopper": (4, ["planar", "hinge", "hinge", "hinge"], 3),
    "walker2d": (7, ["planar"] + ["hinge"] * 6, 6),
    "half_cheetah": (7, ["planar"] + ["hinge"] * 6, 6),
}


@pytest.mark.parametrize("name", BRAX_MODELS)
def test_brax_model_loads_with_its_structure_timestep_and_control_range(name):
    xml = ASSETS / f"{name}.xml"
    model = dbd.load_mjcf(xml)
    reference = mujoco.MjModel.from_xml_path(str(xml))
    bodies, kinds, controls = EXPECTED[name]
    assert model.num_bodies == bodies
    assert [JOINT_KIND_NAMES[k] for k in model.structure.joint_kind.array] == kinds
    assert model.num_controls == controls == reference.nu
    assert model.dt == pytest.approx(reference.opt.timestep)
    np.testing.assert_allclose(model.control_range, reference.actuator_ctrlrange)
    # mass is conserved by the conversion (fused bodies included)
    assert float(jnp.sum(model.bodies.mass)) == pytest.approx(float(np.sum(reference.body_mass)), rel=1e-6)


def test_finalize_kwargs_override_the_mjcf_timestep():
    model = dbd.load_mjcf(ASSETS / "hopper.xml", dt=0.01, substeps=4, iterations=3)
    assert (model.dt, model.options.substeps, model.options.iterations) == (0.01, 4, 3)


@pytest.mark.slow
@pytest.mark.parametrize("name", BRAX_MODELS)
def test_brax_model_simulates_100_steps_under_random_controls_without_nan(name):
    model = dbd.load_mjcf(ASSETS / f"{name}.xml")
    low, high = model.control_range[:, 0], model.control_range[:, 1]
    controls = jnp.asarray(np.random.default_rng(0).uniform(low, high, size=(100, model.num_controls)))
    _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), controls)
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    assert float(jnp.max(jnp.abs(trajectory.vel))) < 1e3  # no blow-up hiding behind finite numbers


@pytest.mark.slow
def test_ant_keeps_its_joints_together_under_random_control():
    # The ant's legs are light and its motors strong (gear 150); armature 1 on every hinge keeps
    # MuJoCo's joint-space inertia sane. Measured largest joint gap over 500 steps of uniform random
    # control (seed 0) at its dt: 0.73 m with armature ignored, 0.036 m with it mapped to rotor rows.
    model = dbd.load_mjcf(ASSETS / "ant.xml")
    low, high = model.control_range[:, 0], model.control_range[:, 1]
    controls = jnp.asarray(np.random.default_rng(0).uniform(low, high, size=(500, model.num_controls)), jnp.float32)
    _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), controls)
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    assert float(jnp.max(diagnostics.joint_gaps(model, trajectory))) < 0.05


def _ant_holding_its_build_pose(lift: float = 0.0) -> str:
    """ant.xml with its ankles' ranges widened to hold the build pose (in ant.xml the ankles start
    30 degrees outside their range), the torso `lift` m higher."""
    xml = (ASSETS / "ant.xml").read_text().replace('range="30 70"', 'range="-70 70"')
    xml = xml.replace('range="-70 -30"', 'range="-70 70"')
    return xml.replace('name="torso" pos="0 0 0.75"', f'name="torso" pos="0 0 {0.75 + lift}"')


def _dropped_ant(**finalize):
    """Brax's ant (armature 1 on every hinge: 40x the hips' own joint-space inertia, 120x the ankles')
    with its ankles' ranges widened to hold the build pose (in ant.xml the ankles start 30 degrees
    outside their range, and correcting that in one substep is a kick of its own), dropped from the
    build pose with zero control for 100 steps: (model, start, trajectory, energy (100,), its
    rotors' share (100,))."""
    model = dbd.load_mjcf(_ant_holding_its_build_pose(), **finalize)
    start = dbd.init(model)
    _, trajectory = jax.jit(dbd.rollout)(model, start, jnp.zeros((100, model.num_controls)))
    energy = np.asarray(diagnostics.energy(model, trajectory))
    rotors = np.asarray(diagnostics.rotor_energy(model, trajectory))
    return model, start, trajectory, energy, rotors


@pytest.mark.slow
def test_point_sweeps_close_the_joints_the_whole_joint_sweeps_leave_open():
    # Brax's ant 5 m up (its ankles' ranges widened to hold the build pose, as `_dropped_ant`), 10
    # steps of uniform random control at 1 x 4 (brax_comparison's setting): each joint's rows move
    # the light leg it shares with its neighbour (gear 150 on 40-70 g legs, armature 1), and the
    # four whole-joint sweeps left the ankles open by 5.7-9.8 mm over seeds 0-7; with 2 sweeps of
    # the points alone after them 0.67-1.25 mm, with 1 1.8-3.1 mm (measured; seed 0: 7.48, 0.87).
    gaps = {}
    for point_sweeps in (0, 2):
        model = dbd.load_mjcf(_ant_holding_its_build_pose(lift=5.0), iterations=4, point_sweeps=point_sweeps)
        low, high = model.control_range[:, 0], model.control_range[:, 1]
        controls = jax.random.uniform(jax.random.PRNGKey(0), (10, model.num_controls), minval=low, maxval=high)
        _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), controls)
        assert bool(jnp.all(dbd.is_finite(trajectory)))
        gaps[point_sweeps] = float(jnp.max(diagnostics.joint_gaps(model, trajectory)))
    print(f"\nant in the air at 1 x 4: largest joint gap {gaps[0] * 1e3:.2f} mm, with 2 point sweeps "
          f"{gaps[2] * 1e3:.2f} mm")  # fmt: skip
    assert gaps[0] > 0.005  # the scene opens the joints without the point sweeps
    assert gaps[2] < 0.0015


def test_dropped_ant_with_armature_gains_no_energy_at_four_substeps():
    # Contacts and joint damping only take energy out. Before the rotor rows' held step counted the
    # joint point's open gap (rows.angular_row), this ant gained 6.7 J -> 2,352 J by step 20 and tore
    # apart (gaps 0.62 m). Then its bodies kept their energy but its rotors took 106 J at landing
    # (step 38; 1 x 4: 95 J, 4 x 32: 62 J): the sweeps leave a heavy rotor's row unconverged beside
    # a foot's contact, and the light bodies' rate, which is the rotor's, had no impulse behind it.
    # The rotor pass (joints.project_rotor_momentum) takes that back: rotors at most 0.32 J, the
    # total never above its start (measured), as under the tree solve (below: 0.66 J).
    model, start, trajectory, energy, rotors = _dropped_ant(substeps=4, iterations=4)
    print(f"\nrotors' energy at most {rotors.max():.2f} J, total at most {energy.max():.2f} J")
    assert energy.max() < float(diagnostics.energy(model, start)) + 0.1
    assert float(jnp.max(diagnostics.joint_gaps(model, trajectory))) < 0.02


@pytest.mark.slow
def test_dropped_ant_under_the_impulse_solver_keeps_its_rotors_from_spinning_up():
    # The same drop under the impulse solver: its sweeps left the heavy rotor rows unconverged
    # beside the feet's contacts as the DBD sweeps did, and the rotors took 773 J by step 76 at
    # 1 x 4 (brax_comparison's setting; 4 x 4: 109,626 J by step 54) and 32.9 J at 1 x 16. The same
    # rotor pass, fed the velocity rows' residuals (velocity_rows.rotor_excess), keeps them at most
    # 0.70 J and 0.37 J (measured), and at 1 x 16 the total never rises above its start. But each
    # joint's pass moved bodies its neighbours share and opened their points: at 1 x 4 joint gaps up
    # to 64 mm, pulled shut by the Baumgarte bias (total up to 21 J). With the joints' points swept
    # after each of three passes (impulse.rotor_pass): gaps at most 11 mm, rotors 0.73 J and 0.08 J,
    # total up to 19.9 J at 1 x 4 (the bodies still gained energy after landing: the Baumgarte bias's
    # speed; at session 59's default beta 0.05 with the point's turn bias, no rise and gaps 2.1 mm).
    model, _, trajectory, energy, rotors = _dropped_ant(solver="impulse", substeps=1, iterations=4)
    gaps = np.asarray(diagnostics.joint_gaps(model, trajectory))
    print(f"\nimpulse 1 x 4: rotors' energy at most {rotors.max():.2f} J, total at most {energy.max():.2f} J, "
          f"joint gaps at most {gaps.max() * 1e3:.1f} mm")  # fmt: skip
    assert rotors.max() < 1.0
    assert gaps.max() < 0.02
    model, start, _, energy, rotors = _dropped_ant(solver="impulse", substeps=1, iterations=16)
    print(f"impulse 1 x 16: rotors' energy at most {rotors.max():.2f} J, total at most {energy.max():.2f} J")
    assert rotors.max() < 1.0
    assert energy.max() < float(diagnostics.energy(model, start)) + 0.1


@pytest.mark.slow
@pytest.mark.parametrize("substeps, iterations, largest_rise", [(1, 4, 0.1), (4, 4, 0.1), (4, 1, 10.0)])
def test_dropped_ant_on_the_impulse_solver_gains_no_energy_at_one_or_four_substeps(substeps, iterations,
                                                                                  largest_rise):  # fmt: skip
    # With Catto's beta = 0.2 (the default before session 59) the bias speed beta C / h, kept by the
    # bodies and by the rotors (armature 1) whose speed the next substep reads from them, threw this
    # ant: +13.2 J over its start at 1 x 4, +453 J (gaps 79 mm) at 4 x 4, and at 4 x 1 it blew up
    # (+2.7e9 J). At the default 0.05 with the point's turn bias: no rise at 1 x 4 and 4 x 4, +7.0 J
    # at 4 x 1 (one sweep a substep; measured; README, "The Baumgarte bias's default").
    model, start, trajectory, energy, _ = _dropped_ant(solver="impulse", substeps=substeps, iterations=iterations)
    gaps = np.asarray(diagnostics.joint_gaps(model, trajectory))
    rise = energy.max() - float(diagnostics.energy(model, start))
    print(f"\nimpulse {substeps} x {iterations}: energy rise {rise:.2f} J, "
          f"joint gaps at most {gaps.max() * 1e3:.1f} mm")  # fmt: skip
    assert rise < largest_rise
    assert gaps.max() < 0.01


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["dbd", "impulse"])
def test_the_rotor_pass_kind_by_kind_moves_the_humanoid_as_with_every_row_traced(
    float64, monkeypatch, optimised_compile, solver
):
    """The rotor residuals and the rotor pass trace each kind of joint with its own rows
    (`solvers.dbd.rotor_kinds`: the humanoid's hinges, and its universal and gimbal joints); the
    rows a kind lacks are inactive, so traced with every row for every joint (on the same colours)
    the steps must come out the same, to rounding."""
    model = dbd.load_mjcf(ASSETS / "humanoid.xml", substeps=1, iterations=2, solver=solver)
    kinds = dbd_solver.rotor_kinds(model)
    assert [len(members) for members, _ in kinds] == [5, 5]  # universal and gimbal share their rows
    assert sorted(len({"rotor_hinge", "rotor_euler"} & rows) for _, rows in kinds) == [1, 1]  # a kind's own rotor rows
    controls = jnp.asarray(np.random.default_rng(3).uniform(-0.4, 0.4, (30, model.num_controls)))
    # dbd.jit, not jax.jit: its options are the ones optimised_compile raises to level 3
    _, by_kind = dbd.jit(lambda s: dbd.rollout(model, s, controls))(dbd.init(model))
    every_row = joint_rows.rows_in_use(model.structure)
    for name in ("project_rotor_momentum", "rotor_excess"):
        traced = getattr(joint_rows, name)
        monkeypatch.setattr(joint_rows, name, lambda *args, traced=traced: traced(*args[:-1], every_row))
    _, all_rows = dbd.jit(lambda s: dbd.rollout(model, s, controls))(dbd.init(model))
    assert bool(jnp.all(dbd.is_finite(by_kind)))
    assert float(jnp.max(jnp.abs(by_kind.ang_vel))) > 1.0, "the humanoid should really move"
    for ours, reference in zip(jax.tree.leaves(by_kind), jax.tree.leaves(all_rows), strict=True):
        np.testing.assert_allclose(np.asarray(ours), np.asarray(reference), rtol=0, atol=1e-12)


@pytest.mark.slow
def test_joint_coordinates_kind_by_kind_are_those_measured_with_every_row(float64, monkeypatch):
    """`joints.joint_coordinates` (the rotor rows' offsets and references, the rotors' energy)
    measures each kind of joint with its own rows; on a bent humanoid its hinge and gimbal angles
    are those measured with every row for every joint, and zero for the kinds that lack them."""
    model = dbd.load_mjcf(ASSETS / "humanoid.xml")
    rng = np.random.default_rng(5)
    start = dbd.init(model)
    turns = dm.quat_exp(jnp.asarray(rng.normal(scale=0.4, size=start.pos.shape)))
    pos, quat = start.pos, dm.quat_multiply(turns, start.quat)
    hinge, _, euler, _ = joint_rows.joint_coordinates(model, pos, quat)
    monkeypatch.setattr(joint_rows, "variants", lambda s: [(np.arange(s.num_joints), joint_rows.rows_in_use(s))])
    every_hinge, _, every_euler, _ = joint_rows.joint_coordinates(model, pos, quat)
    flag = joint_rows.flags(model.structure)
    assert flag.rotor_hinge.sum() == 5 and flag.rotor_euler.any(axis=-1).sum() == 5
    np.testing.assert_array_equal(np.asarray(hinge)[flag.rotor_hinge], np.asarray(every_hinge)[flag.rotor_hinge])
    np.testing.assert_array_equal(np.asarray(euler)[flag.rotor_euler], np.asarray(every_euler)[flag.rotor_euler])
    assert np.all(np.abs(np.asarray(hinge)[flag.rotor_hinge]) > 1e-2), "the pose should bend every hinge"
    assert np.all(np.abs(np.asarray(euler)[flag.rotor_euler]) > 1e-2), "and every universal or gimbal hinge"
    assert not np.asarray(hinge)[~flag.rotor_hinge].any() and not np.asarray(euler)[~flag.rotor_euler].any()
    builder = dbd.ModelBuilder()  # no joints: no kinds, empty coordinates
    builder.add_body(mass=1.0, inertia=(0.1, 0.1, 0.1), pos=(0.0, 0.0, 1.0))
    alone = builder.finalize()
    empty = joint_rows.joint_coordinates(alone, dbd.init(alone).pos, dbd.init(alone).quat)
    assert [x.shape for x in empty] == [(0,), (0,), (0, 3), (0, 4)]


@pytest.mark.slow  # 38 s; the tree solve landing an ant with its rotors counted stays in CI (test_tree.py)
def test_dropped_ant_with_armature_gains_no_energy_with_its_rotors_under_the_tree_solve():
    # The same drop with tree_solve (1 sweep at 4 substeps): the whole solve takes the rotor rows
    # with the joints and contacts, and the rotors' energy stays under 0.7 J.
    model, start, _, energy, rotors = _dropped_ant(substeps=4, iterations=1, tree_solve=True)
    print(f"\nrotors' energy at most {rotors.max():.2f} J")
    assert energy.max() < float(diagnostics.energy(model, start)) + 0.1


def test_hinges_through_one_point_at_other_angles_still_load_as_a_ball_joint():
    xml = _wrap('<body pos="0 0 1"><joint name="a" axis="1 0 0"/><joint name="b" axis="1 1 0"/>'
                '<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body>')  # fmt: skip
    model = dbd.load_mjcf(xml)
    assert [JOINT_KIND_NAMES[k] for k in model.structure.joint_kind.array] == ["ball"]


# ----------------------------------------------------------------------------- refusals
def _wrap(body: str, extra: str = "") -> str:
    return f"<mujoco><worldbody>{body}</worldbody>{extra}</mujoco>"


LINK = '<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>'


@pytest.mark.parametrize(
    ("xml", "names"),
    [
        (_wrap('<body name="can"><freejoint/><geom name="tin" type="cylinder" size="0.1 0.2"/></body>'),
         ["geom 'tin'", "cylinder"]),
        (_wrap(f'<body name="arm"><joint name="h" axis="0 1 0"/><joint name="s" type="slide"/>{LINK}</body>'),
         ["body 'arm'", "'h'", "'s'"]),
        (_wrap(f'<body name="arm"><joint name="h" axis="0 1 0"/>{LINK}<site name="a"/></body>'
               '<site name="b" pos="0 0 1"/>',
               '<tendon><spatial name="cable"><site site="a"/><site site="b"/></spatial></tendon>'),
         ["tendon 'cable'"]),
        (_wrap(f'<body name="arm"><joint name="h" axis="0 1 0"/>{LINK}</body>',
               '<actuator><velocity name="spinner" joint="h" kv="1"/></actuator>'),
         ["actuator 'spinner'"]),
        (_wrap(f'<body name="arm"><joint name="h" axis="0 1 0" frictionloss="0.1"/>{LINK}</body>'),
         ["joint 'h'", "frictionloss"]),
        (_wrap(f'<body name="a"><freejoint/>{LINK}</body><body name="b"><freejoint/>{LINK}</body>',
               '<equality><weld name="glue" body1="a" body2="b"/></equality>'),
         ["equality 'glue'"]),
        (_wrap(f'<body name="raft"><freejoint/><geom name="deck" type="plane" size="1 1 0.1"/>{LINK}</body>'),
         ["'deck'", "plane"]),
    ],
    ids=["cylinder-geom", "hinge-plus-slide", "tendon", "velocity-actuator", "frictionloss", "equality",
         "plane-on-body"],
)  # fmt: skip
def test_unsupported_mjcf_element_is_refused_naming_it(xml, names):
    with pytest.raises(ValueError) as error:
        dbd.load_mjcf(xml)
    for name in names:
        assert name in str(error.value)


def test_visual_only_geoms_of_unsupported_types_are_ignored():
    xml = _wrap(f'<body><freejoint/>{LINK}<geom type="cylinder" size="0.1 0.1" contype="0" conaffinity="0"/></body>')
    model = dbd.load_mjcf(xml)
    assert model.structure.shape_kind.array.tolist() == [dbd.collision.CAPSULE]
    # its mass still counts: MuJoCo computed the body's inertia from both geoms
    assert float(model.bodies.mass[0]) == pytest.approx(float(mujoco.MjModel.from_xml_string(xml).body_mass[1]))


def test_missing_mujoco_raises_an_import_error_that_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match="pip install"):
        dbd.load_mjcf(_wrap(f"<body><freejoint/>{LINK}</body>"))


# ----------------------------------------------------------------------------- geometry
def test_geoms_keep_their_world_placement_in_the_inertial_frame():
    xml = _wrap(
        '<geom name="floor" type="plane" size="5 5 0.1" pos="0 0 0.3" zaxis="0 0.6 0.8"/>'
        '<body pos="0.2 0.1 1" euler="10 20 30"><freejoint/>'
        '<geom name="rod" type="capsule" fromto="0 0 0 0.3 0.1 -0.4" size="0.05"/>'
        '<geom name="block" type="box" pos="0.1 -0.2 0" euler="0 0 40" size="0.1 0.05 0.02"/></body>'
    )
    model = dbd.load_mjcf(xml)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    state = dbd.init(model)
    shapes = model.shapes
    for ours, theirs in ((1, 1), (2, 2)):
        world = state.pos[0] + dm.quat_rotate(state.quat[0], shapes.local_pos[ours])
        np.testing.assert_allclose(world, d.geom_xpos[theirs], atol=1e-6)
        matrix = dm.quat_to_matrix(dm.quat_multiply(state.quat[0], shapes.local_quat[ours]))
        np.testing.assert_allclose(matrix, d.geom_xmat[theirs].reshape(3, 3), atol=1e-6)
    plane_normal = dm.quat_rotate(shapes.local_quat[0], jnp.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(plane_normal, [0.0, 0.6, 0.8], atol=1e-6)
    assert float(jnp.dot(plane_normal, shapes.local_pos[0])) == pytest.approx(0.8 * 0.3, abs=1e-6)


# ----------------------------------------------------------------------------- against MuJoCo
# Small chains without contact, MuJoCo's default (semi-implicit Euler) integrator at the same dt.
# Measured max |q_dbdjax - q_mujoco| over 1 s at dt = 1e-3 (float64, 8 iterations; rad, m for the
# slide, for the ball the rotation angle between the two orientations; every hinge of a universal /
# gimbal joint its own coordinate): pendulum 1.01e-2, chain 1.49e-1, cartpole 9.4e-2, ball 1.05e-2,
# driven 8.3e-3, servo 6.5e-3, universal 8.8e-3, gimbal_driven 1.72e-2, universal_chain 2.68e-2,
# gimbal_armature 1.19e-2, slide_armature 9.23e-2. Halving dt halves every one of them (ratio
# 0.50-0.53): the gap is the first-order time discretisation of the two integrators (against
# MuJoCo's RK4 it is the same size), not a modelling difference, which would not shrink with dt.
# The bounds are the measured gaps plus 20 %.
SCENES = {
    "pendulum": (
        """<body pos="0 0 2" euler="0 50 0"><joint name="h" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body>""",
        "",
        [],
        1.2e-2,
    ),
    "chain": (
        """<body pos="0 0 2" euler="0 40 0"><joint name="h1" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04"/>
        <body pos="0 0 -0.4" euler="30 0 0"><joint name="h2" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.04"/>
        <body pos="0 0 -0.3" euler="0 -30 20"><joint name="h3" axis="0 1 1"/>
        <geom type="box" pos="0.05 0 -0.15" size="0.03 0.05 0.15"/></body></body></body>""",
        "",
        [],
        1.8e-1,
    ),
    "cartpole": (
        """<body pos="0 0 1" euler="0 20 0"><joint name="s" type="slide" axis="1 0 0"/>
        <geom type="box" size="0.2 0.1 0.05"/>
        <body euler="0 40 0"><joint name="p" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03"/></body></body>""",
        "",
        [],
        1.13e-1,
    ),
    "ball": (
        """<body pos="0 0 2" euler="35 25 10"><joint name="b" type="ball"/>
        <geom type="box" pos="0.02 0.03 -0.3" size="0.05 0.1 0.25"/></body>""",
        "",
        [],
        1.26e-2,
    ),
    # a heavy rotor on a ball joint (MuJoCo's armature on its three dofs, in the child's frame)
    "ball_armature": (
        """<body pos="0 0 2" euler="35 25 10"><joint name="b" type="ball" armature="0.5"/>
        <geom type="box" pos="0.02 0.03 -0.3" size="0.05 0.1 0.25"/></body>""",
        "",
        [],
        2.6e-2,
    ),
    # joint stiffness + damping (the drive row) and a motor (add_torque) on a hinge
    "driven": (
        """<body pos="0 0 2" euler="0 50 0"><joint name="h" axis="0 1 0" stiffness="3" damping="0.2"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body>""",
        '<actuator><motor joint="h" gear="2" ctrlrange="-1 1"/></actuator>',
        [0.5],
        1.0e-2,
    ),
    # slide damping (a passive force), a motor on a slide, a position servo (kp, kv) on a hinge
    "servo": (
        """<body pos="0 0 1" euler="0 20 0"><joint name="s" type="slide" axis="1 0 0" damping="0.5"/>
        <geom type="box" size="0.2 0.1 0.05"/>
        <body euler="0 40 0"><joint name="p" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03"/></body></body>""",
        '<actuator><motor joint="s" gear="3"/><position joint="p" kp="10" kv="0.5"/></actuator>',
        [1.0, 0.3],
        7.8e-3,
    ),
    # two perpendicular hinges on one body: a universal joint
    "universal": (
        """<body pos="0 0 2" euler="20 30 10"><joint name="u1" axis="1 0 0"/><joint name="u2" axis="0 1 0"/>
        <geom type="box" pos="0.05 0.08 -0.3" size="0.05 0.1 0.25"/></body>""",
        "",
        [],
        1.06e-2,
    ),
    # three hinges (left-handed), per-hinge stiffness and damping, a motor on every hinge: a gimbal joint
    "gimbal_driven": (
        """<body pos="0 0 2" euler="25 -20 15">
        <joint name="g1" axis="1 0 0" stiffness="4" damping="0.3"/>
        <joint name="g2" axis="0 0 1" stiffness="2" damping="0.1"/><joint name="g3" axis="0 1 0" damping="0.2"/>
        <geom type="box" pos="0.06 0.04 -0.3" size="0.04 0.12 0.25"/></body>""",
        '<actuator><motor joint="g1" gear="2"/><motor joint="g2" gear="1"/><motor joint="g3" gear="3"/></actuator>',
        [0.5, -0.4, 0.3],
        2.06e-2,
    ),
    # a universal joint (the humanoid's shoulder axes) on a swinging hinge link, spring and motor
    "universal_chain": (
        """<body pos="0 0 2" euler="0 40 0"><joint name="h" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04"/>
        <body pos="0 0 -0.4" euler="20 0 10">
        <joint name="u1" axis="2 1 1" stiffness="1" damping="0.05"/><joint name="u2" axis="0 -1 1"/>
        <geom type="box" pos="0.05 0 -0.15" size="0.03 0.05 0.15"/></body></body>""",
        '<actuator><motor joint="u2" gear="0.5"/></actuator>',
        [0.4],
        3.22e-2,
    ),
    # armature on each hinge of a gimbal joint, with motors (they act through the rotor rows)
    "gimbal_armature": (
        """<body pos="0 0 2" euler="25 -20 15">
        <joint name="g1" axis="1 0 0" armature="0.02" damping="0.1"/><joint name="g2" axis="0 0 1" armature="0.05"/>
        <joint name="g3" axis="0 1 0" armature="0.01"/>
        <geom type="box" pos="0.06 0.04 -0.3" size="0.04 0.12 0.25"/></body>""",
        '<actuator><motor joint="g1" gear="2"/><motor joint="g2" gear="1"/><motor joint="g3" gear="3"/></actuator>',
        [0.5, -0.4, 0.3],
        1.43e-2,
    ),
    # armature on a tilted slide (gravity pulls along it but not on the rotor) and on the hinge above it
    "slide_armature": (
        """<body pos="0 0 1" euler="0 20 0">
        <joint name="s" type="slide" axis="1 0 0" armature="0.5" damping="0.2"/>
        <geom type="box" size="0.2 0.1 0.05"/>
        <body euler="0 40 0"><joint name="p" axis="0 1 0" armature="0.01"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03"/></body></body>""",
        '<actuator><motor joint="s" gear="3"/><motor joint="p" gear="0.5"/></actuator>',
        [1.0, 0.3],
        1.11e-1,
    ),
}


def _joint_coordinates(model, state):
    """Hinge angles and slider travels from the build pose (MuJoCo's qpos - qpos0), one per MuJoCo
    dof in MuJoCo's order: 2 for a universal joint, 3 for a gimbal joint, 1 for the others."""
    structure, joints = model.structure, model.joints
    pos = jnp.concatenate([state.pos, jnp.zeros((1, 3), state.pos.dtype)])
    quat = jnp.concatenate([state.quat, dm.quat_identity((1,)).astype(state.quat.dtype)])
    a, b = structure.joint_body_a.array, structure.joint_body_b.array
    kind = structure.joint_kind.array
    relative = dm.quat_multiply(dm.quat_multiply(dm.quat_conjugate(quat[a]), quat[b]),
                                dm.quat_conjugate(joints.rest_rotation))  # fmt: skip
    angle = dm.quat_twist_angle(relative, joints.local_axis_a)
    point_a = pos[a] + dm.quat_rotate(quat[a], joints.local_anchor_a)
    point_b = pos[b] + dm.quat_rotate(quat[b], joints.local_anchor_b)
    travel = dm.dot(point_b - point_a, dm.quat_rotate(quat[a], joints.local_axis_a))
    euler, _ = dm.euler_angles(dm.quat_rotate(quat[a][:, None], joints.local_axes_a),
                               dm.quat_rotate(quat[b][:, None], joints.local_axes_b), kind == UNIVERSAL)  # fmt: skip
    single = jnp.where(kind == SLIDER, travel, angle)
    dofs = {UNIVERSAL: 2, GIMBAL: 3}
    return jnp.concatenate([euler[j, : dofs[k]] if k in dofs else single[j, None] for j, k in enumerate(kind)])


def _gap_to_mujoco(name: str, dt: float, solver: str = "dbd") -> float:
    """max over 1 s of |q - q_mujoco| (the orientation angle for the ball), both at step dt."""
    body, extra, control, _ = SCENES[name]
    xml = f'<mujoco><option timestep="{dt}"/><worldbody>{body}</worldbody>{extra}</mujoco>'
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.ctrl[:] = control
    steps = round(1.0 / dt)
    coordinates, orientations = [], []
    for _ in range(steps):
        mujoco.mj_step(m, d)
        coordinates.append(d.qpos.copy())
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.ximat[1])
        orientations.append(quat)
    model = dbd.load_mjcf(xml, iterations=8, solver=solver)
    controls = jnp.broadcast_to(jnp.asarray(control, jnp.float64), (steps, len(control)))
    _, trajectory = jax.jit(dbd.rollout)(model, dbd.init(model), controls)
    if name.startswith("ball"):
        cosine = np.abs(np.sum(np.asarray(trajectory.quat[:, 0]) * np.array(orientations), axis=-1))
        return float(np.max(2.0 * np.arccos(np.clip(cosine, 0.0, 1.0))))
    ours = np.unwrap(np.asarray(jax.vmap(lambda s: _joint_coordinates(model, s))(trajectory)), axis=0)
    return float(np.max(np.abs(ours - np.array(coordinates))))


# Slow (`make test-slow`): the armature on a slider and a gimbal (the hinge's and ball's stay in
# `make test`, the cartpole's slider too) and the servo (`test_a_saturated_position_servo_...`).
SLOW_SCENES = ("slide_armature", "gimbal_armature", "servo")


@pytest.mark.parametrize("name", slow_except(list(SCENES), kept=[n for n in SCENES if n not in SLOW_SCENES]))
def test_chain_follows_mujoco_within_the_measured_first_order_gap(float64, name):
    assert _gap_to_mujoco(name, 1e-3) < SCENES[name][3]


# The impulse solver on the scenes with universal and gimbal joints, springs, motors and armature: the
# largest |q - q_mujoco| over 1 s at dt = 1 ms, measured (the DBD solver's bounds are in SCENES).
IMPULSE_GAPS = {"universal": 6.5e-4, "gimbal_driven": 1.05e-2, "universal_chain": 3.0e-3, "gimbal_armature": 3.4e-3,
                "slide_armature": 2.3e-3, "ball_armature": 4.2e-3}  # fmt: skip


@pytest.mark.parametrize("name", slow_except(list(IMPULSE_GAPS), kept=["universal", "gimbal_driven"]))
def test_impulse_solver_follows_mujoco_on_universal_gimbal_and_armature_chains(float64, name):
    assert _gap_to_mujoco(name, 1e-3, solver="impulse") < IMPULSE_GAPS[name]


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_gap_to_mujoco_halves_with_the_timestep(float64, name):
    # a modelling error would stay as dt shrinks; the integrators' O(dt) difference halves
    assert 0.4 < _gap_to_mujoco(name, 5e-4) / _gap_to_mujoco(name, 1e-3) < 0.6


# ----------------------------------------------------------------------------- new builder parts
def test_hinge_torque_actuator_spins_a_wheel_at_gear_times_control_over_inertia(float64):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    wheel = b.add_body(pos=(0, 0, 1), mass=2.0, inertia=(0.3, 0.5, 0.3))
    joint = b.add_hinge_joint(dbd.WORLD, wheel, anchor=(0, 0, 1), axis=(0, 1, 0))
    controls = b.add_torque(joint, gear=4.0)
    model = b.finalize(dt=0.01)
    assert controls == slice(0, 1) and model.control_range.tolist() == [[-math.inf, math.inf]]
    final, _ = dbd.rollout(model, dbd.init(model), jnp.full((50, 1), 0.25))
    np.testing.assert_allclose(final.ang_vel[0], [0.0, 4.0 * 0.25 / 0.5 * 0.5, 0.0], atol=1e-9)  # tau / I * t


def test_slider_force_pair_moves_two_free_floating_bodies_apart_without_turning_them(float64):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    cart = b.add_body(pos=(0, 0, 0), mass=3.0, inertia=(0.1, 0.1, 0.1))
    load = b.add_body(pos=(0.2, 0, 0), mass=1.0, inertia=(0.1, 0.1, 0.1))
    joint = b.add_slider_joint(cart, load, anchor=(0.2, 0, 0), axis=(1, 0, 0))
    b.add_torque(joint, gear=2.0)
    model = b.finalize(dt=0.01, iterations=20)
    final, _ = dbd.rollout(model, dbd.init(model), jnp.ones((100, 1)))
    # momentum stays zero; the relative speed is F t (1/m_cart + 1/m_load) along the axis
    np.testing.assert_allclose(diagnostics.linear_momentum(model, final), 0.0, atol=1e-9)
    np.testing.assert_allclose(final.vel[1] - final.vel[0], [2.0 * 1.0 * (1 / 3 + 1), 0, 0], atol=1e-6)
    np.testing.assert_allclose(final.ang_vel, 0.0, atol=1e-6)


def test_planar_joint_keeps_a_body_in_its_plane_and_turning_about_the_normal(float64):
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    body = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.1, 0.2, 0.3), vel=(1.0, 0.5, 0.0), ang_vel=(0.3, 2.0, 0.0))
    b.add_planar_joint(dbd.WORLD, body, anchor=(0, 0, 1), normal=(0, 1, 0))
    model = b.finalize(dt=0.01, iterations=10)
    final, _ = dbd.rollout(model, dbd.init(model), steps=100)
    assert abs(float(final.pos[0, 1])) < 1e-6  # no motion along the normal
    np.testing.assert_allclose(final.pos[0, [0, 2]], [1.0, 1.0 - 0.5 * 9.81 * 1.0 - 0.5 * 9.81 * 0.01], atol=1e-6)
    np.testing.assert_allclose(dm.quat_rotate(final.quat[0], jnp.array([0.0, 1.0, 0.0])), [0, 1, 0], atol=1e-6)
    # the spin about the normal survives; the first step's gyroscopic coupling with the removed
    # x spin (before the axle row acts) moves it by O(h w_x w_y): 9e-6 measured
    assert float(final.ang_vel[0, 1]) == pytest.approx(2.0, rel=1e-4)


@pytest.mark.parametrize("name", ["ball_armature", "gimbal_armature", "slide_armature"])
def test_energy_counts_the_rotors_kinetic_energy_as_mujoco_does(float64, name):
    # MuJoCo's kinetic energy is 1/2 qdot^T (M + armature) qdot; dbdjax's bodies carry no rotor state,
    # so `diagnostics.energy` adds 1/2 armature qdot^2 with qdot read from the bodies' velocities.
    # After 0.3 s of MuJoCo's own motion (the armature scenes, driven), the two energies agree; without
    # the rotors' share they would not (it is printed).
    body, extra, control, _ = SCENES[name]
    option = '<option timestep="0.001"><flag energy="enable"/></option>'
    xml = f"<mujoco>{option}<worldbody>{body}</worldbody>{extra}</mujoco>"
    m = dbd.mujoco_model(xml)
    d = mujoco.MjData(m)
    d.ctrl[:] = control
    for _ in range(300):
        mujoco.mj_step(m, d)
    model = dbd.load_mjcf(xml)
    state = dbd.state_from_mujoco(model, m, d)
    energy, rotors = float(diagnostics.energy(model, state)), float(diagnostics.rotor_energy(model, state))
    print(f"\nMuJoCo {d.energy.sum():.6f} J, dbdjax {energy:.6f} J, its rotors' {rotors:.6f} J")
    assert energy == pytest.approx(d.energy.sum(), rel=1e-6, abs=1e-9)
    assert rotors > 0.2  # measured 0.22-2.4 J: far past the tolerance above


def _armature_and_damping(free: bool, joint: str = "hinge") -> str:
    """A light leg (40 g, 0.4 m) on a hinge (about z) or a ball joint with armature 1 kg m^2 and
    damping 1 N m s, on a base held by the world or free, without gravity."""
    root = "<freejoint/>" if free else ""
    kind = 'type="hinge" axis="0 0 1"' if joint == "hinge" else 'type="ball"'
    return f"""<mujoco><option timestep="0.001" gravity="0 0 0"/><worldbody>
      <body pos="0 0 5">{root}<geom type="sphere" size="0.25" mass="0.5"/>
        <body pos="0.3 0 0"><joint {kind} armature="1" damping="1"/>
          <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="0.04"/></body></body>
    </worldbody></mujoco>"""


def _light_leg_after_a_tenth_of_a_second(free: bool, joint: str, solver: str, iterations: int):
    """The leg of `_armature_and_damping` from 2 rad/s (hinge) or (2, -1, 0.5) rad/s in its frame
    (ball), its base from rest or moving, 100 steps of dt = 1 ms in dbdjax and in MuJoCo from the
    same state: (dbdjax's state as MuJoCo's MjData, MuJoCo's MjData, the leg's qvel and qpos
    sizes)."""
    xml = _armature_and_damping(free, joint)
    m = dbd.mujoco_model(xml)
    d = mujoco.MjData(m)
    spin = [2.0] if joint == "hinge" else [2.0, -1.0, 0.5]
    d.qvel[-len(spin) :] = spin
    if free:
        d.qvel[:6] = [0.1, 0.2, 0.0, 0.3, -0.2, 0.5]
    model = dbd.load_mjcf(xml, iterations=iterations, solver=solver)
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, steps=100))(dbd.state_from_mujoco(model, m, d))
    for _ in range(100):
        mujoco.mj_step(m, d)
    ours = dbd.state_to_mujoco(model, final, m)
    print(f"\nMuJoCo {d.qvel[-len(spin) :]}, dbdjax {ours.qvel[-len(spin) :]}")
    return ours, d, len(spin), 1 if joint == "hinge" else 4  # the ball's qpos: its quaternion


# In `make test`: the DBD hinge on a fixed base and the DBD ball on a free one.
@pytest.mark.parametrize(
    ("free", "joint", "solver"),
    slow_except(list(itertools.product([False, True], ["hinge", "ball"], ["dbd", "impulse"])),
                kept=[(False, "hinge", "dbd"), (True, "ball", "dbd")]),
)  # fmt: skip
def test_a_light_leg_with_a_rotor_and_damping_slows_as_in_mujoco_at_four_iterations(float64, free, joint, solver):
    # The rotor's time constant armature / damping is 1 s: from 2 rad/s MuJoCo's hinge is at 1.81
    # rad/s after 0.1 s. With the drive's damping row and the rotor row stepped one after the other
    # it was stopped (0.05 rad/s; 64 iterations were needed to match); the drive stepped beside its
    # rotor as one block (`rows.spring_row_beside_rotor`) matches to 1e-6 rad/s at 4 iterations.
    # The ball (`rows.angular_spring_beside_rotor`), from (2, -1, 0.5) rad/s in the leg's frame, was
    # at (0.0, -0.023, 0.012) rad/s on the held base; its spin about the leg's own axis, where the
    # leg's inertia is 3e-5 of the rotor's, was lost even at 64 iterations. On the free base its
    # rotor, which kept its rate in the world frame, ended 0.08 rad/s from MuJoCo's at any dt.
    # The impulse solver's rows one after the other were 0.07 (held hinge), 0.13 (free hinge) and
    # 1.6 rad/s (ball) from MuJoCo at 4 iterations, the ball still 0.24 rad/s at 64; as one block
    # (`velocity_rows.solve_drive_beside_rotor`, `solve_drive_block_beside_rotor`) 2e-8 to 2.2e-4 rad/s.
    ours, d, speeds, coordinates = _light_leg_after_a_tenth_of_a_second(free, joint, solver, iterations=4)
    assert d.qvel[-speeds] == pytest.approx(1.81, abs=0.005)
    # The ball on the free base is 1.0e-4 rad/s and 2.0e-5 (quaternion) from MuJoCo, first order in dt
    # (5.1e-5 and 9.9e-6 at dt = 0.5 ms, 2.5e-5 and 5.0e-6 at 0.25 ms): the two integrators, not the
    # solve. Its rotor keeps its rate in the leg's frame as MuJoCo's (`joints.rotor_offsets`). The
    # impulse solver's: 2.2e-4 and 2.1e-5, first order too (1.1e-4 and 9.9e-6 at 0.5 ms, 5.4e-5 and
    # 4.8e-6 at 0.25 ms).
    ball = joint == "ball" and free
    bound = (2e-4 if solver == "dbd" else 3e-4) if ball else 1e-4
    assert np.max(np.abs(ours.qvel[-speeds:] - d.qvel[-speeds:])) < bound
    assert np.max(np.abs(ours.qpos[-coordinates:] - d.qpos[-coordinates:])) < (4e-5 if ball else 1e-5)


@pytest.mark.parametrize(
    ("free", "joint"),
    slow_except(list(itertools.product([False, True], ["hinge", "ball"])), kept=[(False, "hinge")]),
)
def test_one_impulse_sweep_slows_a_light_leg_with_a_rotor_and_damping_as_in_mujoco(float64, free, joint):
    # With the drive stepped beside its rotor as one block, one sweep a step leaves the leg 2.9e-6
    # (held hinge), 3.0e-5 (free hinge), 1.7e-4 and 6.7e-4 rad/s (held and free ball) from MuJoCo.
    # At 4 iterations the sweeps converge without parts of the block; here the drive's update with
    # the held response K' instead of the rotor-relaxed K' / (1 + I_r K') was 7e-4 and 1.2e-3 rad/s
    # off on the hinge and 0.054 on the ball, and its push not scaled by the rotor's mix stopped the
    # leg (1.7-1.8 rad/s off).
    ours, d, speeds, _ = _light_leg_after_a_tenth_of_a_second(free, joint, "impulse", iterations=1)
    assert np.max(np.abs(ours.qvel[-speeds:] - d.qvel[-speeds:])) < (1e-4 if joint == "hinge" else 1e-3)


@pytest.mark.parametrize("solver", slow_except(["dbd", "impulse"], kept=["dbd"]))
def test_brax_ant_in_the_air_follows_mujoco_at_four_iterations(float64, solver):
    # Brax's ant (joint damping 1, armature 1 on every hinge) 5 m up, its hinges in the middle half
    # of their ranges, random velocities, 0.1 s at dt = 1 ms: the largest hinge angle gap to
    # MuJoCo 0.0014 rad (0.11 rad with its drive and rotor rows stepped one after the other). Seeds
    # 2-6 of the same scene: 0.00035-0.0057 rad (seed 4: 0.0057, 0.0030 and 0.0004 at 4, 16 and 64
    # iterations, no limit reached; 0.064 before): what the sweeps leave along each leg's chain of
    # rotors. The tree solve (dbd-tree-1) leaves 1e-5 rad on seeds 1 and 4, before and after.
    # The impulse solver: 0.0035 rad (0.060 with the rows one after the other), seeds 2-6
    # 0.0020-0.0128 (before 0.021-0.063); 3.2e-5 at 16 iterations (0.0042 before). With the joints'
    # points swept after its rotor pass (impulse.rotor_pass): 0.0035, seeds 2-6 0.0019-0.0108.
    xml = ASSETS / "ant.xml"
    m = dbd.mujoco_model(xml)
    m.opt.timestep = 0.001
    rng = np.random.default_rng(1)
    qpos, turn = m.qpos0.copy(), np.zeros(m.nv)
    turn[3:6] = rng.uniform(-0.5, 0.5, 3)
    mujoco.mj_integratePos(m, qpos, turn, 1.0)
    for j in range(1, m.njnt):
        low, high = m.jnt_range[j]
        qpos[m.jnt_qposadr[j]] = 0.5 * (low + high) + rng.uniform(-0.25, 0.25) * (high - low)
    qpos[2] += 5.0
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos, 0.5 * rng.standard_normal(m.nv)
    model = dbd.load_mjcf(xml, dt=0.001, iterations=4, solver=solver)
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, steps=100))(dbd.state_from_mujoco(model, m, d))
    for _ in range(100):
        mujoco.mj_step(m, d)
    assert d.ncon == 0
    gap = np.max(np.abs(dbd.state_to_mujoco(model, final, m).qpos[7:] - d.qpos[7:]))
    assert gap < 0.005, gap


@pytest.mark.parametrize("solver", slow_except(["dbd", "impulse"], kept=["dbd"]))
def test_a_saturated_position_servo_beside_a_rotor_turns_a_light_hinge_as_in_mujoco(float64, solver):
    # The drive's step clamped to its bound (a position actuator's forcerange) and the rotor's taken
    # given the clamped one (`rows.spring_row_beside_rotor`): the light leg of
    # `_armature_and_damping` without damping, driven toward 1 rad (kp 5, kv 1) from 2 rad/s, the
    # servo's 3 N m clamped to 0.3 N m throughout: MuJoCo's rate after 0.1 s is 2.02993 rad/s. A guard
    # of the clamped branch: the rows stepped one after the other gave the same.
    servo = '<position joint="hinge" kp="5" kv="1" forcelimited="true" forcerange="-0.3 0.3"/>'
    xml = _armature_and_damping(free=False).replace(' damping="1"', ' name="hinge"')
    xml = xml.replace("</mujoco>", f"<actuator>{servo}</actuator></mujoco>")
    m = dbd.mujoco_model(xml)
    d = mujoco.MjData(m)
    d.qvel[-1], d.ctrl[:] = 2.0, 1.0
    model = dbd.load_mjcf(xml, iterations=4, solver=solver)
    controls = jnp.ones((100, model.num_controls))
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, controls))(dbd.state_from_mujoco(model, m, d))
    for _ in range(100):
        mujoco.mj_step(m, d)
        assert d.actuator_force[0] == pytest.approx(0.3)  # saturated throughout
    ours = dbd.state_to_mujoco(model, final, m)
    assert abs(ours.qvel[-1] - d.qvel[-1]) < 1e-5 and abs(ours.qpos[-1] - d.qpos[-1]) < 1e-6
