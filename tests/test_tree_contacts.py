"""The contacts in `tree_solve`'s direct solves (solvers/tree_contacts.py): rows to the fixed world
that carry the load they should, stick inside the friction cone and slide on it, let go rather than
pull, and keep their gradients finite and right."""

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd
from dbdjax import collision, integrator, ragdoll
from dbdjax.envs import ragdoll_envs
from dbdjax.solvers import dbd as dbd_solver

ASSETS = Path(__file__).parent / "assets"

GRAVITY = 9.81


def contact_force(model, state, control=None):
    """N: the contact groups' normal multipliers after one substep from `state`, sum lambda_n / h^2."""
    h = model.options.dt / model.options.substeps
    predicted = integrator.predict(model, state, h, control)
    slots = collision.detect(model, state, predicted, h)
    _, _, normal, _ = dbd_solver.solve(model, predicted, control, slots, h, start=state)
    return sum(jnp.sum(n) for n in normal) / h**2


def stacked_cubes(angle_degrees=0.0, friction=0.9, dynamic_friction=None, **finalize):
    """A 0.2 m cube of 3 kg fixed on top of a 0.4 x 0.4 x 0.1 m slab of 1 kg (a joint tree of two
    bodies, wide enough not to tip on the slopes here), resting on a plane tilted by
    `angle_degrees` about y; only the slab touches it. Returns (model, start position of the
    slab's centre, the slope's downhill direction)."""
    angle = np.radians(angle_degrees)
    normal = np.array([-np.sin(angle), 0.0, np.cos(angle)])
    turn = (np.cos(-angle / 2), 0.0, np.sin(-angle / 2), 0.0)
    material = dict(friction=friction, dynamic_friction=dynamic_friction)
    b = dbd.ModelBuilder()
    slab = b.add_body(pos=0.05 * normal, quat=turn, mass=1.0)
    b.add_box(slab, (0.2, 0.2, 0.05), **material)
    cube = b.add_body(pos=0.2 * normal, quat=turn, mass=3.0)
    b.add_box(cube, (0.1, 0.1, 0.1), contype=0, conaffinity=0)
    b.add_fixed_joint(slab, cube, 0.1 * normal)
    b.add_plane(normal=normal, **material)
    downhill = np.array([-np.cos(angle), 0.0, -np.sin(angle)])
    return b.finalize(**finalize), 0.05 * normal, downhill


@pytest.mark.slow  # 80 s; the stack on slopes below and above the friction angle stays in CI
def test_tree_solve_contacts_carry_the_whole_weight_of_a_jointed_stack():
    # The hold that stood in for contact rows (session 24) took the upper cube's weight itself: the
    # contacts carried 9.82 N, the lower cube's alone. As rows they carry all 39.24 N.
    model, _, _ = stacked_cubes(dt=1 / 60, substeps=1, iterations=1, tree_solve=True)
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, steps=60))(dbd.init(model))
    force = float(contact_force(model, final))
    print(f"\ncontact force {force:.4f} N, weight {4 * GRAVITY:.4f} N")
    assert abs(force - 4 * GRAVITY) < 1e-3 * 4 * GRAVITY
    assert float(jnp.max(jnp.abs(final.pos - model.bodies.initial_pos))) < 1e-4


# The stack without a dynamic coefficient in the slow suite (40 s on CI): with one, both coefficients are read.
@pytest.mark.parametrize(
    "angle, static, dynamic", [pytest.param(20.0, 0.5, None, marks=pytest.mark.slow), (25.0, 0.5, 0.3)]
)
def test_tree_solve_keeps_a_jointed_stack_below_the_friction_angle_in_place(angle, static, dynamic):
    # With the hold the friction bound was mu times the slab's weight alone and the stack slid
    # (4.5 m and 7.0 m in 2 s); measured now: 0.1 mm and 0.06 mm at 1 x 1 (at 4 x 8 the second
    # creeps 1.3 mm over 2 s, its speed down to 1e-5 m/s by then: a `/tmp` probe).
    assert math.tan(math.radians(angle)) < static
    model, start, _ = stacked_cubes(angle, static, dynamic, dt=1 / 60, substeps=1, iterations=1, tree_solve=True)
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, steps=120))(dbd.init(model))
    assert float(jnp.linalg.norm(final.pos[0] - start)) < 1e-3


@pytest.mark.parametrize(
    "angle, static, dynamic", [pytest.param(35.0, 0.5, None, marks=pytest.mark.slow), (35.0, 0.5, 0.4)]
)
@pytest.mark.parametrize("substeps, iterations", [(1, 1), pytest.param(2, 4, marks=pytest.mark.slow)])
def test_tree_solve_slides_a_jointed_stack_above_the_friction_angle_at_g_sin_minus_mu_d_cos(
    angle, static, dynamic, substeps, iterations
):
    # A sliding point's friction is mu lambda_n along its slip as lambda_n changes in the solve (its
    # normal row pushes along J_n + mu s J_t); left at the sweeps' lambda_n it was too weak (1.76
    # and 3.35 m/s^2 against 1.61 and 2.41 at 1 x 1). With the hold: 4.6 and 4.8 m/s^2. Measured
    # now: within 0.06%. The spin: a transient of up to 0.22-0.45 rad/s around 0.1 s, where the
    # points go from sticking to sliding (their speed passes g h); at 1 x 1, mu 0.5, 8e-5 rad/s at
    # 0.18 s and below 1e-5 from 0.35 s.
    model, start, downhill = stacked_cubes(angle, static, dynamic, dt=1 / 60, substeps=substeps,
                                           iterations=iterations, tree_solve=True)  # fmt: skip
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=120))(dbd.init(model))
    travelled = (np.asarray(trajectory.pos[:, 0]) - start) @ downhill
    time = np.arange(1, 121) / 60
    acceleration = 2.0 * np.polyfit(time, travelled, 2)[0]
    mu = static if dynamic is None else dynamic
    expected = GRAVITY * (math.sin(math.radians(angle)) - mu * math.cos(math.radians(angle)))
    print(f"\nacceleration {acceleration:.4f} m/s^2, expected {expected:.4f}")
    assert abs(acceleration - expected) < 2e-3 * expected
    assert float(jnp.max(jnp.linalg.norm(trajectory.ang_vel[30:], axis=-1))) < 1e-3  # slides, does not tip


@pytest.mark.slow  # 136 s; the quiet standing doll below stays in CI
def test_tree_solve_holds_a_leaning_ragdoll_on_its_feet_with_its_weight_on_them():
    # The standing doll leaning forwards on its ankles (target -0.036 rad, ramped in over 1 s) at
    # 2 x 4. With the hold its feet carried 29 N of its weight, its heels rose and it toppled forwards
    # between 2 and 3 s (docs/brax_comparison.md, session 26). Now its feet carry its 686.7 N, and its ankles hold
    # the drive's own static sag (-0.0375 rad: the 11.8 N m each carries at 8000 N m/rad).
    builder, doll = ragdoll.build()
    model = builder.finalize(dt=ragdoll.DT, substeps=2, iterations=4, tree_solve=True)
    steps = int(round(4.0 / ragdoll.DT))
    lean = ragdoll.pose_control(doll, {"ankle_l": -0.036, "ankle_r": -0.036})
    ramp = np.minimum(np.arange(steps) * ragdoll.DT, 1.0)[:, None]
    controls = np.zeros((steps, model.num_controls))
    controls[:, doll.control_slice] = ramp * lean
    final, trajectory = jax.jit(lambda s, c: dbd.rollout(model, s, c))(dbd.init(model), jnp.asarray(controls))
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    weight = float(jnp.sum(model.bodies.mass)) * GRAVITY
    force = float(contact_force(model, final, jnp.asarray(controls[-1])))
    shin, foot = (final.quat[doll.bodies[name]] for name in ("shin_l", "foot_l"))
    ankle = float(2.0 * (shin[0] * foot[2] - foot[0] * shin[2] + shin[1] * foot[3] - shin[3] * foot[1]))  # about y
    pelvis = np.asarray(trajectory.pos[:, doll.bodies["pelvis"]])
    print(f"\nleaning doll at 4 s: contacts {force:.1f} N of {weight:.1f} N, ankle {ankle:.5f} rad, "
          f"pelvis height {pelvis[:, 2].min():.4f}-{pelvis[:, 2].max():.4f} m")  # fmt: skip
    assert abs(force - weight) < 5e-3 * weight
    assert abs(ankle - (-0.0375)) < 5e-4
    assert np.ptp(pelvis[:, 2]) < 2e-3


@pytest.mark.slow
def test_gradients_through_sliding_and_sticking_contact_rows_match_finite_differences(float64):
    # Two 1 kg capsules fixed side by side (a joint tree), lying across a 35-degree slope (mu_s 0.5,
    # mu_d 0.4), pushed uphill at 0.8 m/s: they slide up, stop after 5 steps and start down, each
    # point's rows sliding, sticking and switching between them. (Capsules: two points a pair, so
    # the float64 gradient compiles in a fraction of the boxes' time.) Over longer rollouts the
    # travel has small jumps where a point switches (central differences with steps 1e-4, 1e-6 and
    # 1e-8 over 30 steps: -0.43402, -0.43444, -0.398; the gradient -0.43402).
    angle = np.radians(35.0)
    normal = np.array([-np.sin(angle), 0.0, np.cos(angle)])
    downhill = np.array([-np.cos(angle), 0.0, -np.sin(angle)])
    material = dict(friction=0.5, dynamic_friction=0.4)
    b = dbd.ModelBuilder()
    across = (np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0)  # the capsule's axis along y
    left = b.add_body(pos=0.05 * normal + 0.06 * downhill, mass=1.0)
    right = b.add_body(pos=0.05 * normal - 0.06 * downhill, mass=1.0)
    for body in (left, right):
        b.add_capsule(body, radius=0.05, half_length=0.15, quat=across, **material)
    b.add_fixed_joint(left, right, 0.05 * normal)
    b.add_plane(normal=normal, **material)
    model = b.finalize(dt=1 / 60, substeps=1, iterations=1, tree_solve=True)
    start = dbd.init(model)

    def travel(speed):
        state = dataclasses.replace(start, vel=start.vel - jnp.asarray(downhill) * speed)  # uphill
        final, _ = dbd.rollout(model, state, steps=8)
        return jnp.dot(final.pos[1], jnp.asarray(downhill))

    speed = 0.8
    travel_and_gradient = jax.jit(jax.value_and_grad(travel))  # one program for the gradient and the differences
    gradient = float(travel_and_gradient(speed)[1])
    step = 1e-5
    numeric = float((travel_and_gradient(speed + step)[0] - travel_and_gradient(speed - step)[0]) / (2 * step))
    print(f"\nd travel / d speed: {gradient:.8f}, central differences {numeric:.8f}")
    assert np.isfinite(gradient)
    assert abs(gradient - numeric) < 1e-5 * max(1.0, abs(numeric))


@pytest.mark.slow
def test_tree_solve_keeps_a_quiet_standing_doll_quiet_when_one_foot_point_slides():
    # A state of RagdollStand-v0 at 2 substeps x 2 iterations with tree_solve (dt 1/60 s), met by a
    # PPO policy 179 steps into an episode, no push: every body slower than 0.22 m/s, both feet
    # down. One point of the left foot slides in the second solve of a substep: its normal row
    # pushes along J_n + mu s J_t, and with the foot held by the rows around it the solve is in
    # Painleve's case (its lambda_n went from 0.0098 to -0.285). Until session 29 the left leg
    # then moved at 12-40 m/s two steps later (4 x 8 sweeps: 0.24 m/s at most); now that solve
    # jams (`tree_contacts.jammed`) and the largest speed is 0.243 m/s.
    model = ragdoll_envs.RagdollStand(substeps=2, iterations=2, tree_solve=True).model
    saved = np.load(ASSETS / "ragdoll_tree_solve_sliding_blowup.npz")
    state = dataclasses.replace(
        dbd.init(model), **{name: jnp.asarray(saved[name]) for name in ("pos", "quat", "vel", "ang_vel")}
    )
    control = jnp.asarray(saved["control"])
    assert float(jnp.max(jnp.linalg.norm(state.vel, axis=-1))) < 0.22
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, jnp.broadcast_to(control, (2, control.shape[0]))))(state)
    speed = float(jnp.max(jnp.linalg.norm(final.vel, axis=-1)))
    print(f"\nlargest body speed after two steps: {speed:.3f} m/s")
    assert speed < 1.0


def test_settle_lets_a_pulling_point_go_and_slides_a_point_past_its_cone():
    # One pair of three points on a floor (n = z, rows along z, x, y), mu_s = 0.5, all sticking.
    # Point 0 would pull (total lambda_n -1): it lets go, its multipliers back to 0. Point 1's friction
    # (0.9, 0) would leave its cone (0.5 x 1.5): it slides, its friction on the cone of its
    # lambda_n so far (0.5 x 1) along the solve's direction. Point 2 stays inside its cone and the
    # pair's friction within the sum of its points' cones: unchanged.
    from dbdjax.solvers import tree_contacts

    slots = collision.ContactSlots(
        local_a=jnp.zeros((1, 3, 3)), local_b=jnp.zeros((1, 3, 3)), normal=jnp.tile(jnp.array([0.0, 0, 1]), (1, 3, 1)),
        offset=jnp.zeros((1, 3, 3)), approach=jnp.zeros((1, 3)), sliding=jnp.zeros((1, 3), bool),
        active=jnp.ones((1, 3), bool), friction=jnp.array([0.5]), dynamic_friction=jnp.array([0.3]),
        restitution=jnp.zeros(1), allowed_depth=jnp.zeros((1, 3)), pushout_speed=jnp.zeros((1, 3)),
    )  # fmt: skip
    lam = jnp.array([[1.0, 0.0, 0.0], [1.0, 0.4, 0.0], [4.0, 0.2, 0.0]])
    steps = jnp.array([[-2.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.0, 0.1, 0.0]])
    along = jnp.tile(jnp.eye(6)[np.array([2, 0, 1])], (3, 1))  # each point's rows: z, x, y
    rows = tree_contacts.ContactRows(
        body=np.zeros(9, int), jacobian=along, push=along, compliance=jnp.ones(9), residual=jnp.zeros(9),
        on=jnp.ones(9, bool), multipliers=lam.reshape(-1), slide=jnp.zeros(9), gap=jnp.zeros(9),
        touches=jnp.ones(9, bool),
    )  # fmt: skip
    touching = tree_contacts.Touching((slots,), (jnp.zeros((1, 12)),), 0.0)
    settled = tree_contacts.settle(touching, rows, steps.reshape(-1), jnp.zeros((1, 6)))
    np.testing.assert_array_equal(np.asarray(settled.off).reshape(3, 3), [[True] * 3, [False] * 3, [False] * 3])
    np.testing.assert_array_equal(np.asarray(settled.sliding).reshape(3, 3)[:, 0], [False, True, False])
    np.testing.assert_allclose(
        np.asarray(settled.load).reshape(3, 3), [[-1.0, 0, 0], [0, 0.1, 0], [0, 0, 0]], atol=1e-7
    )
    np.testing.assert_allclose(np.asarray(settled.direction).reshape(3, 3)[1], [0, 1, 0], atol=1e-7)
    assert bool(settled.changed)
