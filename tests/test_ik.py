"""Inverse kinematics (DBD section 11): reaching, unreachable targets, Fig. 10, gradients, limits,
chains read from a Model."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd
from dbdjax import diagnostics, ik, math

REACH = 1.5  # m, every test chain below


@pytest.fixture
def float64():
    with jax.enable_x64(True):
        yield


def hinge_chain(links=6, **kwargs):
    """A uniform 3D chain of hinges (yaw, pitch, yaw, ...), 1.5 m long, 1 kg slender rods."""
    return ik.Chain.from_links(np.full(links, REACH / links), **kwargs)


def planar_chain(links=8):
    """The uniform chain of Fig. 10: every hinge about z, moving in the xy plane."""
    return ik.Chain.from_links(np.full(links, REACH / links), axes=(0.0, 0.0, 1.0))


def ball_chain():
    return ik.Chain.from_links([0.5, 0.4, 0.3, 0.3], kinds="ball")


CHAINS = {"hinge": hinge_chain, "planar": planar_chain, "ball": ball_chain}


ITERATIONS = 64  # one compiled solver per (chain structure, method) serves every test below


@functools.cache
def batched_solver(method="dbd", inertia="per_iteration", constraint="point"):
    """jit(vmap(solve)) over starts and targets; the chain is an argument, so chains of one
    structure share the compilation. An update depends only on the angles it starts from (lambda
    restarts at 0, and so does the per-frame inertia), so calling it again continues the solve."""
    solve = functools.partial(
        ik.solve, method=method, iterations=ITERATIONS, inertia=inertia, constraint=constraint, return_error=True
    )
    return jax.jit(jax.vmap(solve, in_axes=(None, 0, 0)))


batched_end_effector = jax.jit(jax.vmap(ik.end_effector, in_axes=(None, 0)))


def reachable_problems(chain, count, seed, spread=1.0):
    """Start poses, and targets the chain reaches at start + up to `spread` rad per angle."""
    rng = np.random.default_rng(seed)
    starts = rng.uniform(-0.5, 0.5, size=(count, chain.num_dofs))
    goals = starts + rng.uniform(-spread, spread, size=starts.shape)
    dtype = chain.mass.dtype
    return jnp.asarray(starts, dtype), batched_end_effector(chain, jnp.asarray(goals, dtype))


def solve_all(chain, starts, targets, calls=1, **options):
    """calls x ITERATIONS updates from every start toward its target: (angles, distance before
    each update (B, calls x ITERATIONS), final distance (B,))."""
    angles, errors = starts, []
    for _ in range(calls):
        angles, error = batched_solver(**options)(chain, angles, targets)
        errors.append(np.asarray(error))
    final = np.linalg.norm(np.asarray(batched_end_effector(chain, angles) - targets), axis=-1)
    return angles, np.concatenate(errors, axis=1), final


def iterations_to(errors, tolerance):
    """Per problem, the first update after which the distance is below `tolerance` (-1: never)."""
    below = np.concatenate([errors[:, 1:], np.full((errors.shape[0], 1), np.inf)], axis=1) < tolerance
    return np.where(below.any(axis=1), np.argmax(below, axis=1) + 1, -1)


# ------------------------------------------------------------------------------------ reaching
@pytest.mark.parametrize("method", ["dbd", "pinv"])
@pytest.mark.parametrize("kind, dtype", [("hinge", "float64"), ("hinge", "float32"), ("ball", "float64")])
def test_reachable_targets_are_reached_within_a_millimetre(method, kind, dtype):
    with jax.enable_x64(dtype == "float64"):
        chain = CHAINS[kind]().astype(jnp.dtype(dtype))
        starts, targets = reachable_problems(chain, count=12, seed=1)
        angles, errors, final = solve_all(chain, starts, targets, method=method)
        assert angles.dtype == jnp.dtype(dtype)
    needed = iterations_to(errors, 1e-3)
    print(
        f"\n{kind} chain, {method}, {dtype}: updates to 1 mm {needed.tolist()}, final distance max {final.max():.1e} m"
    )
    assert np.all(np.isfinite(np.asarray(angles)))
    assert np.all(final < 1e-3)
    assert np.all(needed > 0)


def test_per_frame_inertia_and_distance_constraint_also_reach_targets(float64):
    chain = hinge_chain()
    starts, targets = reachable_problems(chain, count=8, seed=2)
    _, errors, per_frame = solve_all(chain, starts, targets, inertia="per_frame")
    _, distance_errors, distance = solve_all(chain, starts, targets, calls=4, constraint="distance")
    print(f"\nper-frame inertia: updates to 1 mm {iterations_to(errors, 1e-3).tolist()}; "
          f"distance constraint (131): {iterations_to(distance_errors, 1e-3).tolist()}")  # fmt: skip
    assert np.all(per_frame < 1e-3)
    assert np.all(distance < 1e-3)


def test_batched_solve_matches_one_problem_at_a_time(float64):
    chain = hinge_chain()
    starts, targets = reachable_problems(chain, count=3, seed=3)
    batched, _, _ = solve_all(chain, starts, targets)
    for i in range(3):
        one = ik.solve(chain, starts[i], targets[i], iterations=ITERATIONS)
        np.testing.assert_allclose(np.asarray(one), np.asarray(batched[i]), atol=1e-12)


# ------------------------------------------------------------------------------------ unreachable
@pytest.mark.parametrize("method, calls", [("dbd", 16), ("pinv", 4)])
@pytest.mark.parametrize("kind", ["planar", "ball"])
def test_unreachable_target_ends_with_the_chain_straight_toward_it(float64, method, calls, kind):
    chain = CHAINS[kind]()
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(6, 3))
    if kind == "planar":
        directions[:, 2] = 0.0
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    targets = jnp.asarray(1.5 * REACH * directions)
    starts = jnp.asarray(rng.uniform(-0.5, 0.5, size=(6, chain.num_dofs)))
    angles, errors, _ = solve_all(chain, starts, targets, calls=calls, method=method)
    poses = jax.vmap(ik.forward_kinematics, in_axes=(None, 0))(chain, angles)
    joints = np.concatenate([np.asarray(poses.pivot), np.asarray(poses.end_effector)[:, None]], axis=1)
    links = np.diff(joints, axis=1)
    links /= np.linalg.norm(links, axis=-1, keepdims=True)
    misalignment = np.arccos(np.clip(np.einsum("bki,bi->bk", links, directions), -1.0, 1.0))  # rad, every link
    shortfall = REACH - np.linalg.norm(np.asarray(poses.end_effector), axis=-1)
    print(f"\n{kind}, {method}, {calls * ITERATIONS} updates: largest link misalignment {misalignment.max():.1e} rad, "
          f"reach shortfall {shortfall.max():.1e} m")  # fmt: skip
    assert np.all(np.isfinite(np.asarray(angles))) and np.all(np.isfinite(errors))
    assert np.all(np.diff(errors, axis=1) <= 1e-12)  # the line search never lets the distance grow
    assert misalignment.max() < 1e-2
    assert shortfall.max() < 1e-4


def path_objective(chain, start, target, method):
    """A smooth scalar of the whole solve: fixed weights on the solved angles and end effector."""
    angles = ik.solve(chain, start, target, method=method, iterations=ITERATIONS)
    weights = jnp.linspace(-1.0, 1.0, chain.num_dofs)
    return jnp.dot(weights, angles) + jnp.dot(jnp.asarray([0.3, -0.2, 0.1]), ik.end_effector(chain, angles))


@functools.partial(jax.jit, static_argnames="method")
def directional_derivative(chain, start, target, tangents, method):
    """Forward mode: the derivative of `path_objective` along one direction in every input."""
    return jax.jvp(lambda c, s, t: path_objective(c, s, t, method), (chain, start, target), tangents)[1]


def random_tangents(chain, start, target, seed):
    leaves, tree = jax.tree_util.tree_flatten((chain, start, target))
    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_unflatten(tree, [jnp.asarray(rng.normal(size=leaf.shape)) for leaf in leaves])


@pytest.mark.parametrize("method", ["dbd", "pinv"])
def test_straight_singular_pose_gives_finite_angles_and_gradients(float64, method):
    """Zero angles: the chain lies straight along +x, where J M^-1 J^T has no x row (135)."""
    chain = hinge_chain()
    end = ik.end_effector(chain, chain.zero_angles())
    targets = jnp.stack([0.5 * end, 2.0 * end, end])  # on the axis: reachable, unreachable, already there
    straight = jnp.zeros((3, chain.num_dofs))
    angles, errors, _ = solve_all(chain, straight, targets, method=method)
    assert np.all(np.isfinite(np.asarray(angles))) and np.all(np.isfinite(errors))
    # Pointing straight at an unreachable target is where the solve ends: it stays there.
    np.testing.assert_allclose(np.asarray(angles[1]), 0.0, atol=1e-12)
    # A random direction through every input (chain leaves, start, target): a NaN in any partial
    # derivative would show. Reverse mode at this pose: the slow test below.
    for i, target in enumerate(targets):
        tangents = random_tangents(chain, straight[i], target, seed=i)
        assert np.isfinite(float(directional_derivative(chain, straight[i], target, tangents, method=method)))


# ------------------------------------------------------------------------------------ Fig. 10
def test_dbd_bends_the_tip_more_and_the_root_less_than_the_pseudo_inverse(float64):
    chain = planar_chain(8)
    rng = np.random.default_rng(5)
    start = jnp.full((8,), 0.15)  # a gentle arc
    targets = batched_end_effector(chain, start + jnp.asarray(rng.uniform(-0.6, 0.6, size=(16, 8))))
    starts = jnp.broadcast_to(start, (16, 8))
    ratios = {}
    for method, inertia in (("dbd", "per_iteration"), ("dbd", "per_frame"), ("pinv", "per_iteration")):
        angles, _, final = solve_all(chain, starts, targets, method=method, inertia=inertia)
        assert np.all(final < 1e-3)
        change = np.abs(np.asarray(angles - start))
        ratio = ratios[method, inertia] = change[:, 4:].sum(axis=1) / change[:, :4].sum(axis=1)  # tip / root half
        print(f"\n{method} ({inertia}): |d theta| per joint, root to tip, mean over targets "
              f"{np.round(change.mean(axis=0), 3).tolist()}; tip/root ratio median {np.median(ratio):.2f} "
              f"(range {ratio.min():.2f}..{ratio.max():.2f})")  # fmt: skip
    pinv = ratios["pinv", "per_iteration"]
    for inertia in ("per_iteration", "per_frame"):
        assert np.all(ratios["dbd", inertia] > pinv)
        assert np.median(ratios["dbd", inertia]) > 1.0 > np.median(pinv)


# ------------------------------------------------------------------------------------ gradients
def relative_error(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(np.asarray(b)), 1e-12))


@pytest.mark.parametrize("method", ["dbd", "pinv"])
def test_gradient_of_solved_end_effector_wrt_target_matches_finite_differences(float64, method):
    chain = hinge_chain()
    starts, targets = reachable_problems(chain, count=2, seed=6)
    epsilon = 1e-6

    def solved(target, start):
        angles = ik.solve(chain, start, target, method=method, iterations=ITERATIONS)
        return ik.end_effector(chain, angles), angles

    jacobians = jax.jit(jax.vmap(jax.jacfwd(solved), in_axes=(0, 0)))(targets, starts)
    # Central differences from the same solver: targets +- epsilon e_i, solved in one batch.
    offsets = np.concatenate([np.eye(3), -np.eye(3)]) * epsilon
    for b in range(2):
        shifted = targets[b] + jnp.asarray(offsets)
        angles, _, _ = solve_all(chain, jnp.broadcast_to(starts[b], (6, chain.num_dofs)), shifted, method=method)
        ends = batched_end_effector(chain, angles)
        numeric_end = np.asarray(ends[:3] - ends[3:]).T / (2 * epsilon)
        numeric_angles = np.asarray(angles[:3] - angles[3:]).T / (2 * epsilon)
        end_jacobian, angles_jacobian = np.asarray(jacobians[0][b]), np.asarray(jacobians[1][b])
        print(f"\n{method}: |d x_end/d x_T - 1| = {np.abs(end_jacobian - np.eye(3)).max():.1e}; relative error to "
              f"finite differences: end effector {relative_error(end_jacobian, numeric_end):.1e}, "
              f"angles {relative_error(angles_jacobian, numeric_angles):.1e}")  # fmt: skip
        assert np.linalg.norm(np.asarray(ends[0] - shifted[0])) < 1e-9  # converged
        assert relative_error(end_jacobian, numeric_end) < 1e-4
        # Converged, the end effector follows the target: d x_end / d x_T is the identity.
        assert np.abs(end_jacobian - np.eye(3)).max() < 1e-6
        # The angles depend on the whole path of the solve; forward mode through the scan agrees.
        assert relative_error(angles_jacobian, numeric_angles) < 1e-4


@pytest.mark.slow
def test_reverse_mode_gradient_matches_finite_differences_and_is_finite_at_the_singular_pose(float64):
    """jax.grad through the whole solve w.r.t. the chain's float leaves, the start and the target.
    The DBD path, and so the pose it ends in, depends on the masses (133); it is smooth in them."""
    chain = hinge_chain(masses=np.linspace(2.0, 0.5, 6))
    reverse_gradient = jax.jit(jax.grad(path_objective, argnums=(0, 1, 2)), static_argnames="method")
    straight = chain.zero_angles()
    for target in ik.end_effector(chain, straight) * jnp.asarray([[0.5], [2.0], [1.0]]):
        for gradient in jax.tree_util.tree_leaves(reverse_gradient(chain, straight, target, method="dbd")):
            assert np.all(np.isfinite(np.asarray(gradient)))

    starts, targets = reachable_problems(chain, count=1, seed=9)
    start, target = starts[0], targets[0]
    chain_gradient, start_gradient, target_gradient = reverse_gradient(chain, start, target, method="dbd")
    # Central differences, every perturbed (masses, start, target) in one batch.
    epsilon = 1e-6
    point = jnp.concatenate([chain.mass, start, target])
    steps = jnp.concatenate([jnp.eye(point.size), -jnp.eye(point.size)]) * epsilon

    def objective(x):
        masses, s, t = x[:6], x[6:12], x[12:]
        return path_objective(dataclasses.replace(chain, mass=masses), s, t, "dbd")

    values = np.asarray(jax.jit(jax.vmap(objective))(point + steps))
    numeric = (values[: point.size] - values[point.size :]) / (2 * epsilon)
    checks = (
        ("masses", chain_gradient.mass, numeric[:6]),
        ("start angles", start_gradient, numeric[6:12]),
        ("target", target_gradient, numeric[12:]),
    )
    for name, analytic, numeric in checks:
        print(f"\nd objective / d {name}: {np.round(np.asarray(analytic), 4).tolist()}, "
              f"relative error to finite differences {relative_error(analytic, numeric):.1e}")  # fmt: skip
        assert np.abs(np.asarray(analytic)).max() > 1e-3  # it matters
        assert relative_error(analytic, numeric) < 1e-4


# ------------------------------------------------------------------------------------ limits
@pytest.mark.parametrize("method", ["dbd", "pinv"])
def test_hinge_limits_are_respected(float64, method):
    limit = 0.6
    chain = hinge_chain(limits=(-limit, limit))
    free = hinge_chain()
    rng = np.random.default_rng(7)
    # Targets made with some joints right at a limit, from starts well inside: the unlimited
    # chain's solution leaves the limits, so the limited one has to hold joints at them.
    goals = rng.uniform(-limit, limit, size=(8, 6))
    goals[:, 1] = limit * np.sign(rng.normal(size=8))
    goals[:, 3] = limit * np.sign(rng.normal(size=8))
    targets = batched_end_effector(chain, jnp.asarray(goals))
    starts = jnp.asarray(rng.uniform(-0.2, 0.2, size=(8, 6)))
    angles, errors, final = solve_all(chain, starts, targets, calls=2, method=method)
    unlimited, _, _ = solve_all(free, starts, targets, calls=2, method=method)
    outside = int(np.sum(np.abs(np.asarray(unlimited)) > limit + 1e-6))
    at_limit = int(np.sum(np.isclose(np.abs(np.asarray(angles)), limit)))
    print(f"\n{method}: targets inside the limits reached to {final.max():.1e} m in "
          f"{iterations_to(errors, 1e-3).tolist()} updates; {at_limit} joints end at a limit; "
          f"without limits {outside} joints end outside them")  # fmt: skip
    assert outside > 0 and at_limit > 0  # the limits were in play
    assert np.all(np.abs(np.asarray(angles)) <= limit)
    assert np.all(final < 1e-3)
    # Targets the limits put out of reach: the angles still stay inside them.
    behind = jnp.asarray([[-1.0, 0.2, 0.3], [0.2, -1.2, 0.1], [0.1, 0.1, -1.4]])
    angles, errors, _ = solve_all(chain, jnp.zeros((3, 6)), behind, method=method)
    assert np.all(np.isfinite(np.asarray(angles)))
    assert np.all(np.abs(np.asarray(angles)) <= limit)
    assert np.all(errors[:, -1] < errors[:, 0])


def test_per_joint_limits_and_free_joints_together(float64):
    limits = [None, (-0.2, 0.1), None, (0.0, 0.5), None, None]
    chain = hinge_chain(limits=limits)
    assert chain.limited == (False, True, False, True, False, False)
    starts, targets = reachable_problems(chain, count=6, seed=8, spread=0.8)
    starts = jnp.clip(starts, chain.lower, chain.upper)
    angles, _, _ = solve_all(chain, starts, targets)
    a = np.asarray(angles)
    assert np.all(np.isfinite(a))
    assert np.all((a[:, 1] >= -0.2) & (a[:, 1] <= 0.1) & (a[:, 3] >= 0.0) & (a[:, 3] <= 0.5))


# ------------------------------------------------------------------------------------ the chain
def test_pivot_inertia_of_a_straight_rod_chain_matches_parallel_axis_sum(float64):
    """(133) for N uniform rods along x: about z, sum_i m l^2/12 + m ((i - k + 1/2) l)^2."""
    n, length, mass = 5, 0.3, 0.7
    chain = ik.Chain.from_links(np.full(n, length), masses=mass)
    poses = ik.forward_kinematics(chain, chain.zero_angles())
    inertia = np.asarray(jax.jit(ik.pivot_inertias)(chain, poses.pivot, poses.quat, poses.com))
    radius = length / 20
    for k in range(n):
        offsets = (np.arange(k, n) - k + 0.5) * length
        across = np.sum(mass * length**2 / 12 + mass * offsets**2)
        np.testing.assert_allclose(np.diag(inertia[k]), [(n - k) * mass * radius**2 / 2, across, across], rtol=1e-12)
        np.testing.assert_allclose(inertia[k] - np.diag(np.diag(inertia[k])), 0.0, atol=1e-15)


def test_chain_is_a_pytree_of_float_leaves_with_static_structure():
    chain = ik.Chain.from_links([0.4, 0.3], kinds=("hinge", "ball"), limits=[(-1.0, 1.0), None])
    leaves = jax.tree_util.tree_leaves(chain)
    assert all(jnp.issubdtype(leaf.dtype, jnp.floating) for leaf in leaves)
    assert chain.num_dofs == 4 and chain.dof_offsets == (0, 1)
    rebuilt = jax.tree_util.tree_map(lambda x: x * 1.0, chain)
    assert rebuilt.kinds == ("hinge", "ball") and rebuilt.limited == (True, False)


def test_bad_chain_descriptions_are_refused():
    with pytest.raises(ValueError, match="lengths must be positive"):
        ik.Chain.from_links([0.3, -0.1])
    with pytest.raises(ValueError, match="joint 1 limits"):
        ik.Chain.from_links([0.3, 0.3], limits=[None, (0.5, -0.5)])
    with pytest.raises(ValueError, match="hinge 0 has a zero axis"):
        ik.Chain.from_links([0.3], axes=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="positive definite"):
        ik.Chain.from_links([0.3], inertias=[(0.1, 0.0, 0.1)])
    chain = ik.Chain.from_links([0.3, 0.3])
    with pytest.raises(ValueError, match="angles must have shape"):
        ik.solve(chain, jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="method"):
        ik.solve(chain, jnp.zeros(2), jnp.zeros(3), method="ccd")


# ------------------------------------------------------------------------------------ from_model
def quat_about(angle, axis):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def small_model():
    """Hinge (limited) from the world, a hinge entered from its body b side, a ball, and a body
    welded to the middle link; bodies turned away from the world axes."""
    b = dbd.ModelBuilder()
    first = b.add_body(pos=(0.2, 0, 1), quat=quat_about(0.3, (0, 0, 1)), mass=1.0, inertia=(0.01, 0.03, 0.03))
    middle = b.add_body(pos=(0.6, 0.1, 1.1), quat=quat_about(-0.5, (1, 1, 0)), mass=0.5, inertia=(0.004, 0.01, 0.012))
    last = b.add_body(pos=(0.9, 0.1, 1.3), mass=0.25, inertia=(0.002, 0.003, 0.004))
    welded = b.add_body(pos=(0.6, 0.3, 1.1), mass=0.3, inertia=(0.001, 0.001, 0.001))
    b.add_hinge_joint(dbd.WORLD, first, anchor=(0, 0, 1), axis=(0, 0, 1), limits=(-1.0, 1.0), name="base")
    b.add_hinge_joint(middle, first, anchor=(0.4, 0.05, 1.05), axis=(0, 1, 0.2), name="elbow")
    b.add_ball_joint(middle, last, anchor=(0.75, 0.1, 1.2), name="wrist")
    b.add_fixed_joint(middle, welded, anchor=(0.6, 0.2, 1.1))
    return b.finalize(), (first, middle, last), welded


def engine_state(model, chain, angles, path, welded):
    """A State with the chain's links at their IK poses and the welded body riding along."""
    poses = ik.forward_kinematics(chain, angles)
    bodies = model.bodies
    index = jnp.asarray(path)
    pos = bodies.initial_pos.at[index].set(poses.origin)
    quat = bodies.initial_quat.at[index].set(poses.quat)
    middle = path[1]
    offset = math.quat_rotate_inverse(
        bodies.initial_quat[middle], bodies.initial_pos[welded] - bodies.initial_pos[middle]
    )
    relative = math.quat_multiply(math.quat_conjugate(bodies.initial_quat[middle]), bodies.initial_quat[welded])
    pos = pos.at[welded].set(poses.origin[1] + math.quat_rotate(poses.quat[1], offset))
    quat = quat.at[welded].set(math.quat_multiply(poses.quat[1], relative))
    return dbd.State(pos=pos, quat=quat, vel=jnp.zeros_like(pos), ang_vel=jnp.zeros_like(pos))


def test_chain_from_model_matches_the_engine_poses_and_joint_angles(float64):
    model, path, welded = small_model()
    chain = ik.Chain.from_model(model, path[-1], tip=(0.1, 0.0, 0.0))
    assert chain.kinds == ("hinge", "hinge", "ball") and chain.names == ("base", "elbow", "wrist")
    assert chain.limited == (True, False, False)
    np.testing.assert_allclose(np.asarray(chain.mass), [1.0, 0.8, 0.25])  # the welded body joins the middle link

    # Zero angles: the poses the model was built in.
    poses = ik.forward_kinematics(chain, chain.zero_angles())
    initial = np.asarray(path)
    np.testing.assert_allclose(np.asarray(poses.origin), np.asarray(model.bodies.initial_pos[initial]), atol=1e-14)
    quat_error = np.minimum(
        np.abs(np.asarray(poses.quat) - np.asarray(model.bodies.initial_quat[initial])).max(axis=-1),
        np.abs(np.asarray(poses.quat) + np.asarray(model.bodies.initial_quat[initial])).max(axis=-1),
    )
    assert quat_error.max() < 1e-14
    np.testing.assert_allclose(np.asarray(poses.end_effector), [1.0, 0.1, 1.3], atol=1e-14)

    # Any angles: every joint of the engine is satisfied, and its angles are the chain's.
    angles = jnp.asarray([0.4, -0.7, 0.2, 0.3, -0.5])
    state = engine_state(model, chain, angles, path, welded)
    assert float(jnp.max(diagnostics.joint_gaps(model, state))) < 1e-14
    joints, structure = model.joints, model.structure
    for j, expected in ((0, 0.4), (1, -0.7)):
        body_a, body_b = int(structure.joint_body_a.array[j]), int(structure.joint_body_b.array[j])
        quat_a = math.quat_identity() if body_a == model.num_bodies else state.quat[body_a]
        relative = math.quat_multiply(math.quat_conjugate(quat_a), state.quat[body_b])
        relative = math.quat_multiply(relative, math.quat_conjugate(joints.rest_rotation[j]))
        np.testing.assert_allclose(float(math.quat_twist_angle(relative, joints.local_axis_a[j])), expected, atol=1e-12)
        swing = math.quat_log(relative) - expected * joints.local_axis_a[j]
        assert float(jnp.linalg.norm(swing)) < 1e-12  # a pure hinge rotation
    relative = math.quat_multiply(math.quat_conjugate(state.quat[path[1]]), state.quat[path[2]])
    relative = math.quat_multiply(relative, math.quat_conjugate(joints.rest_rotation[2]))
    np.testing.assert_allclose(np.asarray(math.quat_log(relative)), [0.2, 0.3, -0.5], atol=1e-12)

    # The solver works on it, and its answer is a pose the engine accepts.
    target = ik.end_effector(chain, jnp.asarray([0.7, -0.2, -0.3, 0.5, 0.4]))
    solved = ik.solve(chain, chain.zero_angles(), target, iterations=64)
    assert float(jnp.linalg.norm(ik.end_effector(chain, solved) - target)) < 1e-3
    assert float(jnp.max(diagnostics.joint_gaps(model, engine_state(model, chain, solved, path, welded)))) < 1e-12
    assert -1.0 <= float(solved[0]) <= 1.0


def test_chain_from_model_refuses_what_it_cannot_express():
    b = dbd.ModelBuilder()
    a = b.add_body(pos=(0, 0, 1))
    c = b.add_body(pos=(0, 0, 0))
    free = b.add_body(pos=(3, 0, 0))
    b.add_hinge_joint(dbd.WORLD, a, anchor=(0, 0, 1.5), axis=(0, 1, 0))
    b.add_slider_joint(a, c, anchor=(0, 0, 0.5), axis=(0, 0, 1), name="piston")
    model = b.finalize()
    with pytest.raises(ValueError, match="'piston' is a slider joint"):
        ik.Chain.from_model(model, c)
    with pytest.raises(ValueError, match="not connected to the world"):
        ik.Chain.from_model(model, free)

    b = dbd.ModelBuilder()
    a = b.add_body(pos=(0, 0, 1))
    b.add_ball_joint(dbd.WORLD, a, anchor=(0, 0, 1.5), cone_limit=0.5, name="shoulder")
    with pytest.raises(ValueError, match="'shoulder' has cone or twist limits"):
        ik.Chain.from_model(b.finalize(), a)
