"""The tree initial guess (solvers/tree.py): an exact linear solve that moves the converged solution
only at second order, and the schedule it runs on."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxprs
import mujoco
import numpy as np
import pytest
import scenes

import dbdjax as dbd
from dbdjax import collision, constraints, integrator, math, ragdoll
from dbdjax.constraints import joints
from dbdjax.model import BALL
from dbdjax.solvers import dbd as dbd_solver
from dbdjax.solvers import tree

ASSETS = Path(__file__).parent / "assets"


def branching_model(floating=False, **finalize):
    """Every case the schedule meets: a world-rooted tree that branches three ways at body 1, a
    floating tree (bodies 5-6), a joint closing a loop (1-4-3), a slider, a hinge and a fixed
    joint, regularisation on some joints and a joint whose body_a is the child. floating: body 0
    not joined to the world (joint 0 left out), so the first tree floats too."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    rng = np.random.default_rng(3)
    for _ in range(8):
        inertia = rng.uniform(0.02, 0.05, size=3)
        b.add_body(pos=rng.normal(size=3), mass=rng.uniform(0.5, 2.0), inertia=inertia, quat=rng.normal(size=4))
    anchor = lambda: rng.normal(size=3)  # noqa: E731
    world_anchor = anchor()
    if not floating:
        b.add_ball_joint(dbd.WORLD, 0, anchor=world_anchor)
    b.add_hinge_joint(0, 1, anchor=anchor(), axis=(0, 0, 1), regularization=0.3)
    b.add_ball_joint(1, 2, anchor=anchor())
    b.add_fixed_joint(3, 1, anchor=anchor())  # the child on side a
    b.add_ball_joint(1, 4, anchor=anchor(), regularization=0.05)
    b.add_ball_joint(4, 3, anchor=anchor())  # closes the loop 1-4-3-1
    b.add_ball_joint(5, 6, anchor=anchor())  # a floating pair
    b.add_slider_joint(6, 7, anchor=anchor(), axis=(1, 0, 0))
    return b.finalize(dt=1 / 60, **finalize)


def displaced_predicted_state(model, seed=0):
    """X* with every joint pulled apart (random displacements and rotations of the bodies)."""
    rng = np.random.default_rng(seed)
    state = dbd.init(model)
    turn = math.quat_exp(jnp.asarray(rng.normal(scale=0.3, size=(8, 3))))
    quat = math.quat_normalize(math.quat_multiply(turn, state.quat))
    return dbd.State(state.pos + rng.normal(scale=0.05, size=(8, 3)), quat, state.vel, state.ang_vel)


def test_schedule_puts_children_before_parents_and_cuts_loops_and_sliders():
    model = branching_model()
    s = model.structure
    joints, bodies, parents = tree.forest(s)
    world, num_joints = s.num_bodies, s.num_joints
    level_of = {int(b): k for k, row in enumerate(bodies) for b in row if b != world}
    assert sorted(level_of) == list(range(7))  # body 7 hangs on the slider alone: not in any tree
    tree_joints = sorted(int(j) for j in joints.ravel() if j != num_joints)
    assert tree_joints == [0, 1, 2, 3, 4, 6]  # 5 closes the loop, 7 is the slider
    for k, (row_j, row_b, row_p) in enumerate(zip(joints, bodies, parents, strict=True)):
        for j, child, parent in zip(row_j, row_b, row_p, strict=True):
            if child == world:
                continue
            if parent != world:
                assert level_of[int(parent)] > k
            if j != num_joints:
                assert {int(child), int(parent)} == {int(s.joint_body_a.array[j]), int(s.joint_body_b.array[j])}
    assert level_of[1] > max(level_of[2], level_of[3], level_of[4])  # body 1 waits for its three children


def _narrowest_width_by_search(parent: list[int], count: int) -> int:
    """The least width of any assignment of the bodies (parent[b] their parent, -1 a root) to
    `count` levels with every body above its children: every assignment tried, roots first."""
    bodies = sorted(range(len(parent)), key=lambda b: _depth(parent, b))  # parents before children
    best = len(parent)

    def place(k: int, level_of: dict, widths: list[int]) -> None:
        nonlocal best
        if max(widths) >= best:
            return
        if k == len(bodies):
            best = max(widths)
            return
        body = bodies[k]
        top = count if parent[body] < 0 else level_of[parent[body]]
        for level in range(top):
            widths[level] += 1
            place(k + 1, {**level_of, body: level}, widths)
            widths[level] -= 1

    place(0, {}, [0] * count)
    return best


def _depth(parent: list[int], body: int) -> int:
    return 0 if parent[body] < 0 else 1 + _depth(parent, parent[body])


def test_schedule_levels_are_as_narrow_as_any_of_as_many_levels_can_be():
    # Brax's humanoid: the leaves-first levels were 4, 4, 1, 1, 1 wide (knees and elbows, hips and
    # shoulders, then the abdomen's two and the torso); an arm can wait beside the pelvis.
    model = dbd.load_mjcf(ASSETS / "humanoid.xml")
    joints_, bodies, _ = tree.forest(model.structure)
    assert joints_.shape == (5, 3)
    slots = tree._slots(model.structure)  # the torso, a floating root alone in the last level, after them
    assert slots.indices.shape[:2] == (4, 3) and slots.roots.tolist() == [int(bodies[-1][0])]
    assert sorted(int(b) for b in bodies.ravel() if b != model.num_bodies) == list(range(model.num_bodies))
    # Random forests of 7 bodies (world-rooted and floating trees), against a search of every
    # assignment; each body's level above its children's, the floating roots alone in the last.
    rng = np.random.default_rng(0)
    for _ in range(40):
        parent = [-1 if b == 0 or rng.uniform() < 0.15 else int(rng.integers(0, b)) for b in range(7)]
        # A root is attached to the world or floats with children (a lone body is in no tree).
        attached = [bool(rng.uniform() < 0.5) or b not in parent for b in range(7)]
        body_a = [7 if parent[b] < 0 else parent[b] for b in range(7) if parent[b] >= 0 or attached[b]]
        body_b = [b for b in range(7) if parent[b] >= 0 or attached[b]]
        kind = np.full(len(body_a), BALL)
        joints_, bodies, parents = tree.schedule(np.array(body_a), np.array(body_b), kind, 7)
        floating = [b for b in range(7) if parent[b] < 0 and not attached[b]]
        jointed = [b for b in range(7) if b not in floating]  # a floating root's children: roots among them
        up = [jointed.index(parent[b]) if parent[b] >= 0 and parent[b] not in floating else -1 for b in jointed]
        height = max(_depth(up, k) for k in range(len(jointed))) + 1
        assert len(bodies) == height + bool(floating)
        widest = max(int(np.sum(row != 7)) for row in bodies[:height])
        assert widest == _narrowest_width_by_search(up, height)
        if floating:
            assert sorted(int(b) for b in bodies[-1] if b != 7) == floating
        level_of = {int(b): k for k, row in enumerate(bodies) for b in row if b != 7}
        assert sorted(level_of) == list(range(7))
        for b in range(7):
            if parent[b] >= 0:
                assert level_of[parent[b]] > level_of[b]


def _tree_guess_against_a_dense_solve(model, tree_joints):
    """The tree's initial guess at a displaced X* of `model`, checked against the dense solve of
    the linearised point constraints of `tree_joints`; returns the guess's multipliers (J, 3)."""
    predicted = displaced_predicted_state(model)
    spin = jnp.asarray(np.random.default_rng(1).normal(size=(8, 3)))
    predicted = dbd.State(predicted.pos, predicted.quat, predicted.vel, spin)
    table = dbd_solver.body_table(model, predicted, 1 / 60)
    dx, dtheta, kappa = tree.initial_guess(model, table)

    # Brute force: assemble J (3 rows per tree joint, vector form DBD (65)) and M~^-1, solve densely.
    delta, arm_a, arm_b = tree.point_gaps(model, table)
    s = model.structure
    n = s.num_bodies
    jacobian = np.zeros((3 * len(tree_joints), 6 * n))
    for row, j in enumerate(tree_joints):
        for body, arm, sign in ((s.joint_body_a.array[j], arm_a[j], 1.0), (s.joint_body_b.array[j], arm_b[j], -1.0)):
            if body < n:
                jacobian[3 * row : 3 * row + 3, 6 * body : 6 * body + 3] = sign * np.eye(3)
                jacobian[3 * row : 3 * row + 3, 6 * body + 3 : 6 * body + 6] = -sign * np.asarray(math.skew(arm))
    inverse_mass = np.zeros((6 * n, 6 * n))
    for body in range(n):
        inverse_mass[6 * body : 6 * body + 3, 6 * body : 6 * body + 3] = np.eye(3) * float(table.inv_mass[body])
        inverse_mass[6 * body + 3 : 6 * body + 6, 6 * body + 3 : 6 * body + 6] = np.asarray(table.inv_inertia[body])
    alpha = np.repeat(np.asarray(model.joints.regularization)[tree_joints], 3)
    system = jacobian @ inverse_mass @ jacobian.T + np.diag(alpha)
    expected_kappa = np.linalg.solve(system, -np.asarray(delta)[tree_joints].ravel())
    expected = (inverse_mass @ jacobian.T @ expected_kappa).reshape(n, 6)

    assert np.abs(np.asarray(delta)[tree_joints]).max() > 0.01  # the joints really are apart
    np.testing.assert_allclose(np.asarray(kappa)[tree_joints].ravel(), expected_kappa, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(dx)[:n], expected[:, :3], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(dtheta)[:n], expected[:, 3:], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(dx)[n], 0.0)
    return np.asarray(kappa)


def test_tree_guess_is_the_exact_solution_of_the_linearised_point_constraints(float64):
    model = branching_model(velocity_dependent_inertia=True)
    kappa = _tree_guess_against_a_dense_solve(model, [0, 1, 2, 3, 4, 6])
    np.testing.assert_allclose(kappa[[5, 7]], 0.0)  # loop and slider: left to the iterations


@pytest.mark.slow
def test_tree_guess_is_exact_with_the_floating_roots_taken_after_the_levels(float64):
    # With body 0 floating, the schedule's last level holds floating roots alone: they are
    # eliminated after the levels' scan, not as a level of it (`tree._slots`).
    model = branching_model(floating=True, velocity_dependent_inertia=True)
    assert 0 in tree._slots(model.structure).roots
    kappa = _tree_guess_against_a_dense_solve(model, [0, 1, 2, 3, 5])
    np.testing.assert_allclose(kappa[[4, 6]], 0.0)  # loop and slider


def ball_tree(initial_guess):
    """Five well-proportioned bodies on ball joints, branching at body 1."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    for i in range(5):
        b.add_body(pos=(0.2 * (i + 1), 0.05 * i, 0), mass=1.0 + 0.2 * i, inertia=(0.02, 0.03, 0.025))
    for a, c, anchor in ((dbd.WORLD, 0, (0.1, 0, 0)), (0, 1, (0.3, 0, 0)), (1, 2, (0.5, 0.05, 0)),
                         (1, 3, (0.7, 0.1, 0.05)), (3, 4, (0.9, 0.15, 0))):  # fmt: skip
        b.add_ball_joint(a, c, anchor=anchor)
    return b.finalize(dt=1 / 60, iterations=300, initial_guess=initial_guess)


@pytest.mark.slow  # 29 s; the guess's exactness (above) stays in CI
def test_tree_guess_moves_the_converged_solution_only_at_second_order(float64):
    # The constraints' solution set is a manifold, so where the non-linear iterations end depends on
    # where they start; a correct linear guess shifts it only at second order in the correction.
    differences = _shift_of_the_converged_end(ball_tree, ("zero", "tree"), seed=0)
    assert differences[1] < 0.3 * differences[0]  # halving the correction quarters the shift (linear: halves)


def _shift_of_the_converged_end(make_model, settings, seed: int) -> list[float]:
    """How far apart the solves of one displaced prediction end under the two `settings`
    (make_model(setting) -> model), at corrections of about 0.02 and 0.01; every end closes the joints."""
    differences = []
    for scale in (0.02, 0.01):
        ends = []
        for setting in settings:
            model = make_model(setting)
            predicted = _displaced(dbd.init(model), np.random.default_rng(seed), scale)
            dx, dtheta, _, _ = dbd_solver.solve(model, predicted, None, (), 1 / 60)
            after = integrator.apply(predicted, dx, dtheta, 1 / 60)
            assert float(jnp.max(dbd.diagnostics.joint_gaps(model, after))) < 1e-9
            ends.append(np.concatenate([np.asarray(dx), np.asarray(dtheta)]))
        assert np.abs(ends[0]).max() > scale / 2  # a real correction
        differences.append(float(np.abs(ends[1] - ends[0]).max()))
    return differences


def test_zero_guess_is_still_available_and_unknown_guesses_are_refused():
    model = scenes.chain(3, dt=1 / 60, initial_guess="zero")
    assert model.options.initial_guess == "zero"
    with pytest.raises(ValueError, match="finalize: unknown initial_guess 'warm'"):
        scenes.chain(3, dt=1 / 60, initial_guess="warm")


def universal_and_gimbal_chain(**finalize):
    """Three bodies hung from the world by a ball, a universal and a gimbal joint (MJCF's hips and
    abdomen: several hinges on one body)."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    for i in range(3):
        b.add_body(pos=(0.3 * (i + 1), 0.0, 0.0), mass=1.0 + 0.5 * i, inertia=(0.02, 0.03, 0.025))
    b.add_ball_joint(dbd.WORLD, 0, anchor=(0.15, 0.0, 0.0))
    b.add_universal_joint(0, 1, anchor=(0.45, 0.0, 0.0), axes=((0, 0, 1), (0, 1, 0)))
    b.add_gimbal_joint(1, 2, anchor=(0.75, 0.0, 0.0), axes=((1, 0, 0), (0, 0, 1), (0, 1, 0)))
    return b.finalize(dt=1 / 60, **finalize)


def _displaced(start, rng, scale):
    """`start` with every body moved and turned by about `scale` (m, rad)."""
    n = start.pos.shape[0]
    turn = math.quat_exp(jnp.asarray(rng.normal(scale=scale, size=(n, 3))))
    quat = math.quat_normalize(math.quat_multiply(turn, start.quat))
    return dbd.State(start.pos + rng.normal(scale=scale, size=(n, 3)), quat, start.vel, start.ang_vel)


def test_tree_holds_universal_and_gimbal_points(float64):
    # Their point constraint is a full 3-D one like a ball's: they belong in the tree (they were
    # left to the iterations, which left the MJCF humanoid's hips and abdomen out of it).
    model = universal_and_gimbal_chain(iterations=1)
    joints, _, _ = tree.forest(model.structure)
    assert sorted(int(j) for j in joints.ravel() if j != model.structure.num_joints) == [0, 1, 2]
    rng = np.random.default_rng(2)
    start = dbd.init(model)
    gaps = []
    for scale in (1e-2, 1e-3):
        predicted = _displaced(start, rng, scale)
        table = dbd_solver.body_table(model, predicted, 1 / 60)
        dx, dtheta, _ = tree.initial_guess(model, table)
        after = integrator.apply(predicted, dx[:3], dtheta[:3], 1 / 60)
        before = float(jnp.max(dbd.diagnostics.joint_gaps(model, predicted)))
        gaps.append(float(jnp.max(dbd.diagnostics.joint_gaps(model, after))))
        assert gaps[-1] < 0.05 * before  # closed to second order
    assert gaps[1] < 0.03 * gaps[0]  # a tenth of the displacement: about a hundredth of the gap


@pytest.mark.slow  # 50 s; the heavy-rotor pendulum's match with converged sweeps (below) stays in CI
def test_tree_solve_moves_where_the_sweeps_converge_only_at_second_order(float64):
    # The points' solution set is a manifold, so where the iterations end depends on the path; with
    # a correct linearisation the direct steps shift that end only at second order in the
    # correction (as the tree guess does, above), and every end closes the joints.
    differences = _shift_of_the_converged_end(
        lambda tree_solve: universal_and_gimbal_chain(iterations=400, tree_solve=tree_solve), (False, True), seed=4
    )
    print(f"\nshift of the end by tree_solve: {differences[0]:.2e} at scale 0.02, {differences[1]:.2e} at 0.01")
    assert differences[1] < 0.3 * differences[0]


@pytest.mark.slow
def test_tree_solve_holds_a_whipping_chain_at_one_substep():
    # 20 links at dt = 1/30 with one substep of 10 sweeps: the sweeps alone open the joints by
    # 170 mm as the free end whips (8 substeps: 2.8 mm); the direct solve after each sweep keeps
    # them within float32 rounding of closed.
    steps = 150
    gaps = {}
    for tree_solve in (False, True):
        model = scenes.chain(20, dt=1 / 30, substeps=1, iterations=10, tree_solve=tree_solve)
        _, trajectory = jax.jit(lambda s, m=model: dbd.rollout(m, s, steps=steps))(dbd.init(model))
        assert np.all(np.isfinite(np.asarray(trajectory.pos)))
        gaps[tree_solve] = float(jnp.max(dbd.diagnostics.joint_gaps(model, trajectory)))
        energy = np.asarray(jax.vmap(lambda s, m=model: dbd.diagnostics.energy(m, s))(trajectory))
        assert energy.max() - float(dbd.diagnostics.energy(model, dbd.init(model))) < 1e-3  # J: none made
    print(f"\n20-link chain, dt=1/30, 1 x 10: largest gap {gaps[False] * 1e3:.1f} mm, with tree_solve "
          f"{gaps[True] * 1e3:.4f} mm")  # fmt: skip
    assert gaps[False] > 0.1
    assert gaps[True] < 1e-5


@pytest.mark.parametrize("iterations, sweeps, runs", [(3, None, 3), (3, 2, 2), (4, 1, 1), (1, 0, 0), (2, 5, 2)])
def test_a_tree_step_ends_only_the_first_sweeps_it_is_given(iterations, sweeps, runs):
    # With angular rows the whole-joint solve follows the last sweep, and takes the points and
    # contacts again: the points' solve is given the sweeps before it only. A step that moves
    # body 0 by 1 m, over no constraints, moves it once per sweep it ends.
    model = scenes.chain(2, dt=1 / 60)
    table = dbd_solver.body_table(model, dbd.init(model), 1 / 60)
    step = dbd_solver.TreeStep(lambda dx, dtheta, lams: (jnp.ones_like(dx), jnp.zeros_like(dtheta), []), (), sweeps)
    dx, _, _ = dbd_solver.gauss_seidel((), [], table, iterations, [], step)
    assert float(dx[0, 0]) == runs


def test_tree_solve_with_whole_joints_skips_the_points_solve_after_the_last_sweep(monkeypatch):
    # Brax's ant has angular rows (its rotors and limits): at one sweep its step traces no points'
    # solve inside the sweeps, only the whole-joint one after them. Each traced `direct_step` says
    # whether it solves the joints whole (its `targets`).
    model = dbd.load_mjcf(ASSETS / "ant.xml", iterations=1, tree_solve=True)
    whole = []
    original = tree.direct_step

    def counted(model, bodies, touching=None, multipliers=None, targets=None, close=False):
        whole.append(targets is not None)
        return original(model, bodies, touching, multipliers, targets, close)

    monkeypatch.setattr(tree, "direct_step", counted)
    jax.eval_shape(lambda s: dbd.step(model, s), dbd.init(model))
    assert whole == [True]  # the whole-joint solve alone


@pytest.mark.parametrize("asset", ["ant.xml", "humanoid.xml"])
def test_the_whole_joint_solve_traces_its_second_solve_as_its_first_run_again(asset, monkeypatch):
    # The active-set step's second solve (a contact point let go or slid, a drive saturated) runs
    # the first one's traced program a second time (a scan of two turns) instead of a copy of it:
    # the step's program holds one factorisation of the tree. Both Brax models have contacts in the
    # solve, and at one sweep no points' solve inside the sweeps.
    model = dbd.load_mjcf(ASSETS / asset, iterations=1, tree_solve=True)
    original = tree.factor

    def factorisation(*args, **kwargs):
        return original(*args, **kwargs)._replace(indices=None, joint=None, empty=None, roots=None)

    def factor(model, *args, **kwargs):  # a call of `factorisation` in the program, the slots' layout static
        return jax.jit(factorisation)(model, *args, **kwargs)._replace(**tree._slots(model.structure)._asdict())

    monkeypatch.setattr(tree, "factor", factor)
    jaxpr = jax.make_jaxpr(lambda s: dbd.step(model, s))(dbd.init(model)).jaxpr
    jitted = [
        equation.params["name"] for equation in jaxprs.equations(jaxpr) if equation.primitive.name in ("jit", "pjit")
    ]  # (named pjit in older JAX)
    assert jitted.count("factorisation") == 1


def test_tree_solve_is_refused_by_the_impulse_solver():
    with pytest.raises(ValueError, match="finalize: tree_solve is a step of the DBD solver's iterations"):
        scenes.chain(3, dt=1 / 60, solver="impulse", tree_solve=True)


# 60 s on CI (a 10 s rollout). A standing doll with tree_solve stays in CI through
# test_tree_contacts.py's quiet standing doll whose foot point slides.
@pytest.mark.slow
def test_tree_solve_keeps_the_standing_ragdoll_on_its_feet():
    # Without the feet's contacts in the direct solve each direct step pulled the light feet back
    # toward the body and the doll (2 x 8, zero control) collapsed: a body 458 mm from its build
    # pose after 2 s (sweeps alone: 6.4 mm). With them (session 24: a hold along their normals;
    # now rows, tests/test_tree_contacts.py) the feet stay and the body above moves to close the joints. Over
    # 10 s: with its rigid knee limits in the whole-joint solve it crept up and fell
    # (1.7 m at 10 s); they stay with the sweeps (`tree._row_groups`): 0.88 mm (sweeps alone: 11.6 mm at 4 s).
    builder, doll = ragdoll.build()
    model = builder.finalize(dt=ragdoll.DT, substeps=ragdoll.SUBSTEPS, iterations=ragdoll.ITERATIONS,
                             tree_solve=True)  # fmt: skip
    steps = int(round(10.0 / ragdoll.DT))
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, jnp.zeros((steps, doll.num_controls))))(dbd.init(model))
    assert bool(jnp.all(dbd.is_finite(trajectory)))
    moved = float(jnp.max(jnp.abs(trajectory.pos - model.bodies.initial_pos)))
    gap = float(jnp.max(dbd.diagnostics.joint_gaps(model, trajectory)))
    print(
        f"\nstanding ragdoll with tree_solve, 10 s: largest move {moved * 1e3:.2f} mm, largest gap {gap * 1e3:.4f} mm"
    )
    assert moved < 5e-3
    assert gap < 1e-5


def _substep_parts(model, state):
    """What `dbd_solver.solve` starts from for one substep of `model` from `state`: the body table at
    X*, the constraint families and the contact slots (zero control)."""
    h = model.options.dt / model.options.substeps
    predicted = integrator.predict(model, state, h, None)
    slots = collision.detect(model, state, predicted, h)
    families = constraints.families(model, None, slots, h, predicted.pos.dtype, predicted=predicted, start=state)
    return dbd_solver.body_table(model, predicted, h), families, h


@pytest.mark.slow
def test_direct_solve_of_whole_joints_is_a_newton_step_the_sweeps_agree_with(float64):
    # Brax's ant at its third step (every hinge's armature 1, ankles past their soft limits): the
    # direct solve of every joint's point, axle alignment, rotor and active limit is exact for the
    # linearised rows, so repeating it converges quadratically, and one Gauss-Seidel sweep from where
    # it converges barely moves (it solves the same equations: a sign or a residual that differs
    # from the sweeps' rows would show here as a sweep undoing it).
    model = dbd.load_mjcf(ASSETS / "ant.xml", iterations=4, tree_solve=True)
    state = dbd.init(model)
    step = dbd.jit(dbd.step)  # 22 s against 77 s run op by op
    for _ in range(2):
        state = step(model, state)
    table, families, h = _substep_parts(model, state)
    targets = (families[0].params[1], h)
    multipliers = jnp.zeros((model.structure.num_joints, joints.NUM_MULTIPLIERS))
    rows = tree.angular_rows(model, table, multipliers, *targets)
    # Rows on: locks, then the springs along each hinge (rotors, limits, drives: the ant's joint
    # damping is a drive without stiffness) merged into one row each (`tree.AngularRows`).
    assert np.asarray(rows.on).sum(axis=0).tolist() == [8, 8, 0, 8, 0, 0]
    assert np.asarray(rows.spring_on).sum(axis=1).tolist() == [[8, 0, 0], [4, 0, 0], [8, 0, 0]]
    gaps = []
    direct_step = jax.jit(tree.direct_step)  # compiled once for the three solves
    for _ in range(3):
        dx, dtheta, increments, _ = direct_step(model, table, None, multipliers, targets)
        table = table._replace(dx=table.dx + dx, dtheta=table.dtheta + dtheta)
        multipliers = multipliers + increments
        gaps.append(float(jnp.max(jnp.abs(tree.point_gaps(model, table)[0]))))
        after = tree.angular_rows(model, table, multipliers, *targets)
        assert float(jnp.max(jnp.abs(jnp.where(rows.on, after.residual, 0.0)))) < 1e-8
        # each spring of a merged row on its own too (the split is exact)
        assert float(jnp.max(jnp.abs(jnp.where(rows.spring_on, after.spring_residual, 0.0)))) < 1e-8
    assert gaps[0] < 1e-8 and gaps[2] < 1e-14  # from 1.2 mm: 1.7e-9 m, then rounding
    start = [jnp.zeros((len(f.bodies), f.num_multipliers)) for f in families]
    start[0] = multipliers
    dx, dtheta, _ = dbd_solver.gauss_seidel(model.structure.colours, families, table, 1, start)
    assert float(jnp.max(jnp.abs(dtheta - table.dtheta))) < 1e-4  # measured 1.4e-5 rad (3.5e-2 without the locks)


@pytest.mark.slow
def test_the_tree_solves_joint_rows_and_their_gradient_read_and_place_rows_without_scattering():
    """`angular_rows` and `point_gaps` gather each joint's two bodies and place each group's rows
    among the joints through `indexing`, so neither they nor their gradient (in the poses and in the
    drives' and rotors' targets) holds a scatter: XLA:CPU runs each as a loop of kernels a row
    (Brax's humanoid at one sweep: 39 of the 117 scatters of the tree step, 120 of the 289 of its
    gradient, were these)."""
    model = dbd.load_mjcf(ASSETS / "humanoid.xml", iterations=1, tree_solve=True)
    table, families, h = _substep_parts(model, dbd.init(model))
    multipliers = jnp.zeros((model.structure.num_joints, joints.NUM_MULTIPLIERS))

    def loss(table, targets):
        rows = tree.angular_rows(model, table, multipliers, targets, h)
        residual = jnp.where(rows.on, rows.residual, 0.0)
        return jnp.sum(residual**2) + jnp.sum(rows.directions**2) + jnp.sum(tree.point_gaps(model, table)[0] ** 2)

    targets = families[0].params[1]
    assert float(jax.jit(loss)(table, targets)) > 0.0  # the rows are there to be read
    for f in (loss, jax.grad(loss, argnums=(0, 1), allow_int=True)):
        text = jax.jit(f).lower(table, targets).as_text()
        assert "scatter" not in text, [line for line in text.splitlines() if "scatter" in line][:3]


@pytest.mark.slow
def test_tree_solve_steps_a_pendulum_with_heavy_rotors_as_converged_sweeps_do(float64):
    # Two links on hinges with armature 0.5 and 0.3 kg m^2 (50 and 30 x the links' own inertia):
    # one sweep and the direct solve land within 1e-8 of 512 sweeps, where 4 sweeps miss by 1.6e-5 m.
    def pendulum(**finalize):
        b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
        upper = b.add_body(pos=(0.5, 0, 1), mass=1.0, inertia=(0.01, 0.01, 0.01), ang_vel=(0, 1.0, 0))
        lower = b.add_body(pos=(1.5, 0, 1), mass=1.0, inertia=(0.01, 0.01, 0.01))
        b.add_armature(b.add_hinge_joint(dbd.WORLD, upper, anchor=(0, 0, 1), axis=(0, 1, 0)), 0.5)
        b.add_armature(b.add_hinge_joint(upper, lower, anchor=(1.0, 0, 1), axis=(0, 1, 0)), 0.3)
        return b.finalize(dt=1 / 60, **finalize)

    reference = pendulum(iterations=512)
    state = dbd.init(reference)
    step = dbd.jit(dbd.step)
    for _ in range(3):
        state = step(reference, state)
    converged = step(reference, state)
    swept = step(pendulum(iterations=4), state)
    solved = step(pendulum(iterations=1, tree_solve=True), state)
    assert float(jnp.max(jnp.abs(swept.pos - converged.pos))) > 1e-5
    assert float(jnp.max(jnp.abs(solved.pos - converged.pos))) < 1e-8


# 110 s on CI (three engines' 100-step programs). The landing ant's tree solve stays in CI through
# the closing-step test below and the three saved landing states after it.
@pytest.mark.slow
def test_tree_solve_lands_the_ant_as_many_sweeps_do():
    # Brax's ant dropped with zero control (armature 40-120 x its legs' inertia, soft limits): with
    # 4 sweeps alone it sags to 0.27 m at landing and gains 0.66 J; with tree_solve at 1 and 4
    # sweeps it lands as 32 sweeps do (-3.78 J against -3.90 J, torso 0.369 m against 0.354 m at 1 s;
    # session 26, with the contact hold: -3.84 J, 0.362 m).
    results = {}
    for name, finalize in {"sweeps 32": {"iterations": 32}, "tree 1": {"iterations": 1, "tree_solve": True},
                           "tree 4": {"iterations": 4, "tree_solve": True}}.items():  # fmt: skip
        model = dbd.load_mjcf(ASSETS / "ant.xml", **finalize)
        start = dbd.init(model)
        _, trajectory = jax.jit(lambda s, m=model: dbd.rollout(m, s, steps=100))(start)
        energy = np.asarray(jax.vmap(lambda s, m=model: dbd.diagnostics.energy(m, s))(trajectory))
        energy = energy - float(dbd.diagnostics.energy(model, start))
        results[name] = (energy[-1], energy[40:].max(), float(trajectory.pos[-1, 0, 2]))
    print(results)
    reference_energy, _, reference_height = results["sweeps 32"]
    for name in ("tree 1", "tree 4"):
        final, after_landing, height = results[name]
        assert abs(final - reference_energy) < 0.3 and after_landing < final + 0.3  # no rebound
        assert abs(height - reference_height) < 0.03


@pytest.mark.slow
def test_tree_solve_keeps_the_resting_ant_at_rest_for_thirty_seconds():
    """Brax's ant at 1 x 4 under zero control, 8 starts (its build pose, every body's velocity
    perturbed by 1 mm/s N(0, 1)), 30 s each: settled at MuJoCo's own rest (0.362 m, its ankles on
    their lower bounds), it gains no energy and its joints stay closed. Before the tree's blocks
    were inverted by Gauss-Jordan (`math.gauss_jordan_inverse`), the float32 inverse of a leg's
    block by 3x3 Schur complements could come out wrong by thousands of times, a sweep's direct
    solve spun the leg 0.47 rad: on that code these 8 ants gained 45 MJ and flew apart (in a /tmp
    probe, one ant at a time with other kicks, 3 of 8 jumped by 19-371 J at steps 723-2863)."""
    model = dbd.load_mjcf(ASSETS / "ant.xml", iterations=4, tree_solve=True)
    start = dbd.init(model)
    kicks = 1e-3 * jax.random.normal(jax.random.PRNGKey(0), (8,) + start.vel.shape)
    starts = jax.vmap(lambda kick: dbd.State(start.pos, start.quat, start.vel + kick, start.ang_vel))(kicks)

    def run(state):
        _, trajectory = dbd.rollout(model, state, steps=3000)
        energy = jax.vmap(lambda s: dbd.diagnostics.energy(model, s))(trajectory)
        gaps = jax.vmap(lambda s: jnp.max(dbd.diagnostics.joint_gaps(model, s)))(trajectory)
        return energy, gaps, trajectory.pos[-1, 0, 2]

    energy, gaps, height = (np.asarray(x) for x in jax.jit(jax.vmap(run))(starts))
    settled = energy[:, 200:]  # after 2 s
    rise = (settled - np.minimum.accumulate(settled, axis=1)).max(axis=1)  # above its lowest so far
    print(f"\nlargest energy rise after 2 s {rise.max():.4f} J, joint gap after 1 s "
          f"{gaps[:, 100:].max() * 1e3:.4f} mm, height {height.min():.4f}-{height.max():.4f} m")  # fmt: skip
    assert rise.max() < 0.1
    assert gaps[:, 100:].max() < 1e-5
    assert np.all(np.abs(height - 0.362) < 0.002)


@pytest.mark.slow
def test_tree_solve_closes_what_its_linearisation_leaves_of_the_landing_ants_joints():
    # Brax's ant dropped at its dt = 0.01, one substep and one sweep (the benchmark's dbd-tree-1):
    # at landing (step 29) the sweep's solve turns its legs 0.089 rad and the whole solve 0.088 rad
    # back, each leaving the second order of that turn: 1.0 mm of joint gap without the chord step
    # that ends the whole solve (`tree._closing_step`), 0.046 mm with it (session 31).
    model = dbd.load_mjcf(ASSETS / "ant.xml", substeps=1, iterations=1, tree_solve=True)
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=40))(dbd.init(model))
    gaps = np.asarray(jax.vmap(lambda s: jnp.max(dbd.diagnostics.joint_gaps(model, s)))(trajectory))
    assert trajectory.pos[-1, 0, 2] < 0.4  # it has landed (0.75 m at the start)
    assert gaps.max() < 0.2e-3, gaps.max()


_step = jax.jit(dbd.step)  # the model an argument: the saved states at one substep share one compile


def _step_a_saved_ant(name, substeps=1, saved_control=True):
    """Brax's ant at dbd-tree-1 (1 sweep, tree_solve; 1 substep unless asked) from a state and
    control saved in tests/assets/<name>.npz (or zero control): (model, that state, the state one
    step later)."""
    model = dbd.load_mjcf(ASSETS / "ant.xml", substeps=substeps, iterations=1, tree_solve=True)
    saved = np.load(ASSETS / f"{name}.npz")
    state = dbd.State(**{field: jnp.asarray(saved[field]) for field in ("pos", "quat", "vel", "ang_vel")})
    control = jnp.asarray(saved["control"]) if saved_control else jnp.zeros(model.num_controls)
    return model, state, _step(model, state, control)


@pytest.mark.slow
def test_tree_solve_takes_its_second_solve_where_the_first_was_when_landing_feet_let_go():
    # Brax's ant under random controls (`benchmarks/random_controls.py --model ant`, copy 13 at 607c410, the
    # state after step 25, just after its feet touched down; session 32): the whole solve's
    # active-set step changes its contacts and takes a second solve. When that solve first moved the
    # bodies by their free response to the changes' loads and was linearised there, the step left
    # 0.61 mm of joint gap; linearised where the first solve was, the loads on its right-hand side,
    # 0.0069 mm.
    model, _, after = _step_a_saved_ant("ant_landing_two_feet_let_go")
    gap = float(jnp.max(dbd.diagnostics.joint_gaps(model, after)))
    assert np.isfinite(np.asarray(after.vel)).all()
    assert gap < 0.05e-3, gap


@pytest.mark.slow
def test_tree_solve_gives_way_where_a_sliding_foots_friction_would_push_it_along_its_slip():
    # The same ant two steps later (session 32): in the whole solve two feet let go and `settle`
    # turns a third to sliding, its friction along where the first solve's sticking friction
    # pointed; the second solve then slid that foot 0.27 m along its friction, and the step took the
    # ant's bodies from 6.5 J to 77 J. A solve whose sliding friction pushes with the slip gives way
    # as a jammed one does (`tree_contacts.slides_with_its_friction`). Without that rule now: the
    # bodies at 40-49 J, the fastest at 16-19 m/s, in every draw below that takes the rule's branch.
    # The step is on a knife edge (session 55): a sweep's point lets go or not on a total of -3e-6,
    # and the whole solve's active set then differs. Velocities changed by 1e-6 m/s give one of three
    # outcomes (40 draws, alike before and after the sweeps' poses skipped their renormalisation):
    # the bodies at 7.0 J, the total at 141 J (the second solve slides with its friction and gives
    # way to the first, most draws); 26 J and 126 J (a second solve with two sliding feet, kept, 8-13
    # draws); 9.7 J and 166 J (the sweep's solve too keeps its first solve, one draw). So every draw
    # is checked, against MuJoCo's own 10 ms step from the same state with the same control (its soft
    # contacts, `dbd.state_to_mujoco`): the bodies at 23.6 J, the fastest at 7.8 m/s, the total at
    # 146 J (at dt = 1 ms: 10.7 J, 4.8 m/s, 148 J). The margin of a quarter is for two contact models
    # meeting one landing at this dt. The total is not bounded by the start's 165.9 J: the motors
    # work on the legs.
    # (Its rotors, armature 1 kg m^2 on every hinge, hold another 159 J: `energy` counts them
    # since session 34.)
    model, state, _ = _step_a_saved_ant("ant_landing_foot_slides_with_its_friction")
    control = jnp.asarray(np.load(ASSETS / "ant_landing_foot_slides_with_its_friction.npz")["control"])
    rotors, before = float(dbd.diagnostics.rotor_energy(model, state)), float(dbd.diagnostics.energy(model, state))
    assert abs(before - rotors - 6.45) < 0.01 and abs(rotors - 159.46) < 0.05

    m = dbd.mujoco_model(ASSETS / "ant.xml")
    d = dbd.state_to_mujoco(model, state, m)  # a fit: the state's joints are open by up to 0.23 mm
    assert abs(dbd.diagnostics.energy(model, dbd.state_from_mujoco(model, m, d)) - before) < 0.5
    d.ctrl[:] = np.asarray(control)
    mujoco.mj_step(m, d)
    carried = dbd.state_from_mujoco(model, m, d)
    total = float(dbd.diagnostics.energy(model, carried))
    mujoco_bodies = total - float(dbd.diagnostics.rotor_energy(model, carried))
    mujoco_fastest = float(jnp.max(jnp.linalg.norm(carried.vel, axis=-1)))

    rng = np.random.default_rng(0)
    outcomes = []
    for draw in range(9):
        vel, ang_vel = (x + (draw > 0) * 1e-6 * rng.standard_normal(x.shape) for x in (state.vel, state.ang_vel))
        start = dataclasses.replace(state, vel=vel, ang_vel=ang_vel)
        after = _step(model, start, control)
        energy = float(dbd.diagnostics.energy(model, after))
        bodies = energy - float(dbd.diagnostics.rotor_energy(model, after))
        fastest = float(jnp.max(jnp.linalg.norm(after.vel, axis=-1)))
        outcomes.append((energy, bodies, fastest))
    print(f"\nMuJoCo: total {total:.2f} J, bodies {mujoco_bodies:.2f} J, fastest {mujoco_fastest:.2f} m/s")
    print("dbdjax (total J, bodies J, fastest m/s):")
    print("\n".join(f"  {energy:.2f}, {bodies:.2f}, {fastest:.2f}" for energy, bodies, fastest in outcomes))
    for _, bodies, fastest in outcomes:
        assert bodies < 1.25 * mujoco_bodies and fastest < 1.25 * mujoco_fastest


@pytest.mark.slow
def test_tree_solve_lands_an_ant_with_a_foot_in_the_floor_without_gaining_energy_at_four_substeps():
    # The state above, with zero control, stepped at 4 substeps (h = 2.5 ms). One foot begins it 47 mm
    # in the floor and the ant's energy is mostly its rotors' (159 J of 166 J). MuJoCo from the same
    # state (dt = 1 ms, its soft contacts): 142 J after 0.01 s, torso rising at 4.2 m/s. Before session
    # 34 this step made 1,015 J, the torso at 10 m/s: the whole solve pushed the foot out in one
    # substep (47 mm / h), and the restitution pass, pulling feet back through their own bodies, spun
    # a knee from -3.6 to 43 rad/s against its rotor. Now the foot comes out at `depenetration_speed`
    # and the pass counts the rotors (`joints.rotor_inertia`): 123.2 J, torso at 4.6 m/s.
    model, state, after = _step_a_saved_ant("ant_landing_foot_slides_with_its_friction", 4, saved_control=False)
    before, energy = (float(dbd.diagnostics.energy(model, s)) for s in (state, after))
    print(f"\nenergy {before:.1f} J -> {energy:.1f} J, torso rising at {float(after.vel[0, 2]):.2f} m/s")
    assert energy < before
    assert float(after.vel[0, 2]) < 6.0


def driven_arm(kinds, max_torque=1e4, damping=100.0, **finalize):
    """A horizontal arm of 0.5 m, 2 kg links from the world, each joint of `kinds` ("hinge",
    "ball", "universal") driven toward its build pose with stiffness 2000 N m/rad."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    parent, joint_indices = dbd.WORLD, []
    for i, kind in enumerate(kinds):
        body = b.add_body(pos=(0.5 * i + 0.25, 0, 1), mass=2.0, inertia=(0.001, 2.0 * 0.5**2 / 12, 2.0 * 0.5**2 / 12))
        anchor = (0.5 * i, 0, 1)
        if kind == "hinge":
            joint = b.add_hinge_joint(parent, body, anchor=anchor, axis=(0, 1, 0))
        elif kind == "ball":
            joint = b.add_ball_joint(parent, body, anchor=anchor)
        else:
            joint = b.add_universal_joint(parent, body, anchor=anchor, axes=((0, 0, 1), (0, 1, 0)))
        b.add_drive(joint, stiffness=2000.0, damping=damping, max_torque=max_torque)
        joint_indices.append(joint)
        parent = body
    return b.finalize(dt=1 / 60, **finalize)


def _static_sag(num_links, length=0.5, mass=2.0, stiffness=2000.0, g=9.81):
    """Each joint's angle (rad) where every drive's torque k theta carries the links beyond it."""
    theta = np.zeros(num_links)
    for _ in range(100):  # fixed point of theta = tau(theta) / k
        heading = np.cumsum(theta)
        joint_x = np.concatenate([[0.0], np.cumsum(length * np.cos(heading))])[:num_links]
        centre_x = joint_x + 0.5 * length * np.cos(heading)
        theta = np.array([mass * g * np.sum(centre_x[i:] - joint_x[i]) for i in range(num_links)]) / stiffness
    return theta


def _settled_sag(model, seconds=5.0):
    """Each link's pitch below its parent's (rad) after `seconds` with zero control, and the largest
    angular speed then (rad/s)."""
    steps = round(seconds / model.options.dt)
    final, _ = jax.jit(lambda s: dbd.rollout(model, s, jnp.zeros((steps, model.num_controls))))(dbd.init(model))
    forward = np.asarray(math.quat_rotate(final.quat, jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0]), final.pos.shape)))
    heading = np.arctan2(-forward[:, 2], forward[:, 0])  # pitch below the horizontal
    return np.diff(np.concatenate([[0.0], heading])), float(jnp.abs(final.ang_vel).max())


@pytest.mark.slow  # 40 s; the drive's torque limit in the direct solve (below) stays in CI
def test_tree_solve_holds_a_driven_arm_at_its_static_sag(float64):
    # The whole-joint solve takes the drives (DBD 9) as spring rows beside the points: a horizontal
    # arm of three links on a hinge, a ball and a universal joint settles where each drive's torque
    # k theta carries the links beyond it (0.022, 0.0098, 0.0025 rad). One sweep and the solve land
    # within 1.1e-6 rad of it (measured); 4 sweeps alone sag 0.27 rad too far at the root; the
    # solve without the drives (before) let the root sag 0.61 rad.
    expected = _static_sag(3)
    solved, speed = _settled_sag(driven_arm(("hinge", "ball", "universal"), iterations=1, tree_solve=True))
    swept, _ = _settled_sag(driven_arm(("hinge", "ball", "universal"), iterations=4))
    print(f"\nsag {expected} rad; tree_solve 1 iteration {solved}; 4 sweeps {swept}")
    assert np.abs(solved - expected).max() < 1e-5 and speed < 1e-6
    assert np.abs(swept - expected).max() > 0.1


def test_tree_solve_keeps_a_drive_within_its_torque_limit(float64):
    # One link whose drive's torque limit (2 N m) is below its weight's moment (4.9 N m): it swings
    # down and about where its limit's torque meets gravity, as 64 sweeps have it (1.0839 rad at
    # 10 s); one sweep and the solve follow them within 1e-5 rad. Had the solve taken the drive as
    # a linear row past its limit it would hold the link up (0.0025 rad: 2.5 times the limit).
    ends = {}
    for name, finalize in {"sweeps": {"iterations": 64}, "tree": {"iterations": 1, "tree_solve": True}}.items():
        ends[name], _ = _settled_sag(driven_arm(("hinge",), max_torque=2.0, damping=20.0, **finalize), seconds=10.0)
    print(f"\nangle at 10 s: 64 sweeps {ends['sweeps'][0]:.7f} rad, tree_solve 1 iteration {ends['tree'][0]:.7f}")
    assert ends["sweeps"][0] > 0.9  # fallen far below the horizontal
    assert abs(ends["tree"][0] - ends["sweeps"][0]) < 1e-5


@pytest.mark.slow  # 135 s (compiling its float64 grad); the FD check of gradients through the
# tree solve's contact rows (test_tree_contacts.py) stays in CI
def test_gradients_through_a_saturated_drive_beside_an_unlimited_one_match_finite_differences(float64):
    # A two-link arm: the root's drive at its torque limit (3 N m against the links' 19.6 N m), the
    # elbow's unlimited (its bound inf). The active-set step reads the bound only where a drive is
    # saturated: read everywhere, the elbow's inf gave NaN gradients (found in review).
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    upper = b.add_body(pos=(0.25, 0, 1), mass=2.0, inertia=(0.001, 0.04, 0.04))
    lower = b.add_body(pos=(0.75, 0, 1), mass=2.0, inertia=(0.001, 0.04, 0.04))
    shoulder = b.add_hinge_joint(dbd.WORLD, upper, anchor=(0, 0, 1), axis=(0, 1, 0))
    elbow = b.add_hinge_joint(upper, lower, anchor=(0.5, 0, 1), axis=(0, 1, 0))
    b.add_drive(shoulder, stiffness=2000.0, damping=20.0, max_torque=3.0)
    b.add_drive(elbow, stiffness=500.0, damping=5.0)
    model = b.finalize(dt=1 / 60, iterations=1, tree_solve=True)

    def height(targets):
        final, _ = dbd.rollout(model, dbd.init(model), jnp.broadcast_to(targets, (20, model.num_controls)))
        return final.pos[1, 2]

    targets = jnp.array([0.1, -0.2])
    height_and_gradient = jax.jit(jax.value_and_grad(height))  # one program for the gradient and the differences
    gradient = np.asarray(height_and_gradient(targets)[1])
    step = 1e-6

    def value(t):
        return float(height_and_gradient(t)[0])

    central = np.array([(value(targets + step * e) - value(targets - step * e)) / (2 * step) for e in np.eye(2)])
    assert np.all(np.isfinite(gradient))
    np.testing.assert_allclose(gradient, central, rtol=1e-5, atol=1e-8)


@pytest.mark.slow  # 3.3 minutes alone and 5 GB (the float64 grad of the ant's whole-joint solve compiles slowly)
def test_gradients_through_tree_solve_match_finite_differences(float64):
    # Brax's ant in the air with tree_solve (its whole joints in the last direct solve: locks, rotors,
    # the ankles' active soft limits): d(torso height after 5 steps) / d(controls), against central
    # differences. Every step here has the same rows active, so the step map is smooth.
    model = dbd.load_mjcf(ASSETS / "ant.xml", iterations=2, tree_solve=True)
    start = dbd.init(model)
    controls = jnp.asarray(np.random.default_rng(0).uniform(-0.5, 0.5, size=(5, model.num_controls)))

    def height(controls):
        final, _ = dbd.rollout(model, start, controls)
        return final.pos[0, 2] + 0.1 * jnp.sum(final.ang_vel[1:] ** 2)

    gradient = np.asarray(jax.jit(jax.grad(height))(controls))
    assert np.all(np.isfinite(gradient)) and np.abs(gradient).max() > 1e-6
    value = jax.jit(height)
    direction = np.random.default_rng(1).normal(size=controls.shape)
    epsilon = 1e-6
    numeric = (value(controls + epsilon * direction) - value(controls - epsilon * direction)) / (2 * epsilon)
    print(f"directional derivative: finite differences {float(numeric):.8f}, grad {np.sum(gradient * direction):.8f}")
    assert abs(float(numeric) - float(np.sum(gradient * direction))) < 1e-5 * max(1.0, abs(float(numeric)))
