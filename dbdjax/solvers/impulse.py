"""SI: velocity-level sequential impulses with Baumgarte bias, semi-implicit Euler.

One substep of h seconds (pipeline.substep with solver="impulse"):

    V* = V + h M^-1 F_ext                     SI (12), `predict`: gravity, actuators, user forces
    slots = collision.detect(X, X + h V*)     contact points found where the bodies are headed
    rows at the start pose X                  constraints/velocity_rows.py: J, K, bias (17), (40)
    warm start: V* += M^-1 J^T lambda_prev    the last substep's impulses (State.impulses)
    repeat `iterations` times:                (lax.scan)
        for each colour, in order:            the colouring of the DBD solver (Structure.colours)
            every node of each family at once (jax.vmap): its rows in turn, each impulse
            accumulated and clamped (SI (20)-(23), (32)-(33), (126); lambda_n >= 0)
    with armature, ROTOR_PASS_ROUNDS times:   `rotor_pass`
        the rotor pass on V* + dV             solvers.dbd.rotor_pass: the rotors' unpaid spin back
        one sweep of the joints' points       their bodies with their rotors' inertia
    V' = V* + dV                              `solved_velocities`
    X' = X + h V'                             SI (12), `integrate`

The colour sweep is `solvers.dbd.gauss_seidel` itself, fed velocity rows instead of positional
ones: the BodySet fields dx, dtheta carry the velocity changes. Only velocities are solved; the
position error a step leaves behind is corrected by the bias of the next (Baumgarte, SI (17)),
not projected away, which is the difference to DBD this solver exists to measure.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from dbdjax import colouring, constraints, integrator, math
from dbdjax.collision import ContactSlots
from dbdjax.constraints import Family
from dbdjax.constraints import velocity_rows as velocity
from dbdjax.constraints.rows import BodyPair
from dbdjax.indexing import segment_sum, take
from dbdjax.model import Model, State
from dbdjax.solvers import dbd

# Rounds of the rotor pass and the joints' points after it (`rotor_pass`). Brax's ant dropped at
# 1 substep x 4 iterations (tests/test_mjcf.py), its rotors' energy at most / joint gap at most:
# the pass alone 0.72 J / 64 mm; 1, 2, 3, 4 rounds 183 J / 117 mm, 3.8 J / 18 mm, 0.73 J / 11 mm,
# 0.12 J / 10 mm. Each round costs one sweep of the rotor joints and one of the joints' points.
ROTOR_PASS_ROUNDS = 3


def impulse_shapes(model: Model) -> list[tuple[int, int]]:
    """(M_f, m_f) of every family's impulses, in family order (the layout of State.impulses)."""
    structure = model.structure
    tables = structure.family_bodies()
    per_node = [velocity.JOINT_IMPULSES, 1, 1, 1, 1] + [0] * len(structure.force_groups) + [0]  # + IK targets
    per_node += [velocity.CONTACT_IMPULSES_PER_POINT * group.num_points for group in structure.contact_groups]
    return [(len(table), size) for table, size in zip(tables, per_node, strict=True)]


def initial_impulses(model: Model, dtype=None) -> tuple[jnp.ndarray, ...]:
    """Zero impulses for every family: a cold start."""
    dtype = model.bodies.mass.dtype if dtype is None else dtype
    return tuple(jnp.zeros(shape, dtype) for shape in impulse_shapes(model))


def predict(model: Model, state: State, h: float, control: jnp.ndarray | None) -> State:
    """V* = V + h M^-1 F_ext (SI (12)), and X* = X + h V* where the bodies would go unconstrained.

    integrator.predict gives gravity, torque actuators and the implicit gyroscopic term; user forces
    (`add_force`) are added here explicitly, evaluated at the start of the substep: the
    semi-implicit Euler of SI (12) (a stiff user force needs a small step, unlike in the DBD solver,
    which solves them implicitly).
    """
    predicted = integrator.predict(model, state, h, control)
    structure = model.structure
    if not structure.force_groups:
        return predicted
    n = structure.num_bodies
    force = jnp.zeros_like(state.pos)
    torque = jnp.zeros_like(state.pos)
    for group, params in zip(structure.force_groups, model.forces, strict=True):
        bodies = group.bodies.array  # (M, k), no world (add_force refuses it)
        pieces = [take(column, bodies) for column in (state.pos, state.quat, state.vel, state.ang_vel)]
        f, t = jax.vmap(group.function)(*pieces, params)
        force = force + segment_sum(f.reshape(-1, 3), bodies.reshape(-1), n)
        torque = torque + segment_sum(t.reshape(-1, 3), bodies.reshape(-1), n)
    rotation = math.quat_to_matrix(state.quat)
    inv_inertia = jnp.einsum("nij,nj,nkj->nik", rotation, 1.0 / model.bodies.inertia, rotation)
    vel = predicted.vel + h * force / model.bodies.mass[:, None]
    ang_vel = predicted.ang_vel + h * math.matvec(inv_inertia, torque)
    return State(pos=state.pos + h * vel, quat=integrator.displaced_quat(state.quat, h * ang_vel), vel=vel,
                 ang_vel=ang_vel)  # fmt: skip


def solve(
    model: Model, state: State, predicted: State, control: jnp.ndarray | None, contacts: tuple[ContactSlots, ...],
    h: float,
) -> tuple[jnp.ndarray, jnp.ndarray, tuple[jnp.ndarray, ...], jnp.ndarray | None]:  # fmt: skip
    """Velocity changes (dv (N, 3), dw (N, 3)) that satisfy the velocity constraints from V*.

    state: the start of the substep (its pose is where the rows are taken; its impulses, or zeros
    for None, warm-start the solve). predicted: V* (`predict`). contacts: this substep's slots.
    Returns dv, dw (the rotor pass's included), every family's accumulated impulses
    (State.impulses' layout) and the rotor residuals (R, 3) the sweeps left, which the pass took
    back (`velocity_rows.rotor_excess`, of the joints `solvers.dbd.rotor_joints`; None without such
    joints).
    """
    structure, options = model.structure, model.options
    n = structure.num_bodies
    dtype = state.pos.dtype
    stored = state.impulses if state.impulses is not None else initial_impulses(model, dtype)
    start = State(pos=state.pos, quat=state.quat, vel=predicted.vel, ang_vel=predicted.ang_vel)
    table = dbd.body_table(model, start, h)
    prepared, impulses = [], []
    warm_dv = warm_dw = jnp.zeros((n + 1, 3), dtype)
    families = velocity.families(model, control, contacts, h, dtype, state)
    for family, lam in zip(families, stored, strict=True):
        lam = jnp.asarray(lam, dtype)
        if len(family.bodies):
            bodies = jax.tree.map(lambda column, f=family: take(column, f.bodies), table)  # (M, S, ...)
            rows, lam, dv, dw = jax.vmap(family.prepare)(family.params, family.static, bodies, lam)
            index = family.bodies.reshape(-1)
            warm_dv = warm_dv + segment_sum(dv.reshape(-1, 3), index, n + 1)
            warm_dw = warm_dw + segment_sum(dw.reshape(-1, 3), index, n + 1)
        else:
            rows = None
        prepared.append(Family(family.name, family.bodies, rows, family.static, family.solve, family.num_impulses,
                               family.variants))  # fmt: skip
        impulses.append(lam)
    if not any(len(f.bodies) for f in prepared):
        zero = jnp.zeros((n, 3), dtype)
        return zero, zero, tuple(impulses), None
    table = table._replace(dx=warm_dv, dtheta=warm_dw)  # the world's row stays 0: its inverse mass is 0
    if options.jacobi:
        dv, dw, impulses = dbd.jacobi(prepared, table, options.iterations, impulses)
    else:
        dv, dw, impulses = dbd.gauss_seidel(structure.colours, prepared, table, options.iterations, impulses)
    excess = None
    rotor_joints = dbd.rotor_joints(model)
    if rotor_joints.size:  # what the sweeps left of the rotor rows, taken back by the rotor pass
        joint_family = constraints.gather(prepared[0], rotor_joints)
        bodies = jax.tree.map(lambda column: column[joint_family.bodies], table._replace(dx=dv, dtheta=dw))
        excess = jax.vmap(functools.partial(velocity.rotor_excess, h=h))(
            joint_family.params, model.joints.armature[rotor_joints], bodies, impulses[0][rotor_joints]
        )
        solved = solved_velocities(state, predicted, dv[:n], dw[:n])
        dv, dw, impulses[0] = rotor_pass(model, solved, prepared[0], table._replace(dx=dv, dtheta=dw), impulses[0],
                                         excess, h)  # fmt: skip
    for f, family in enumerate(families):  # what the next substep starts from
        if family.store is not None and len(family.bodies):
            impulses[f] = jax.vmap(family.store)(prepared[f].params, impulses[f])
    return dv[:n], dw[:n], tuple(impulses), excess


def rotor_pass(model: Model, solved: State, joint_family: Family, table, joint_impulses: jnp.ndarray,
               excess: jnp.ndarray, h: float) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:  # fmt: skip
    """The rotor pass (`solvers.dbd.rotor_pass`: the rotors' spin the sweeps gave with no impulse
    behind it, `excess` (R, 3), taken back) and the joints' points held after it, ROTOR_PASS_ROUNDS
    times. Each joint's pass holds its own point, but it moves bodies that other joints share (an
    ant's upper leg, between hip and ankle), and the velocity error it leaves at their points has
    no position solve after it here: X' = X + h V' keeps it, and only the Baumgarte bias of the
    next substeps pulls it back. Brax's ant under random control (gear 150 on 40-70 g legs,
    armature 1) opened its hips by 46 mm in the air that way (13 mm with no pass; after the first
    step's pass its hips' points parted at 0.76-0.88 m/s, 0-0.43 before it). So a sweep of the
    joints' point blocks follows each pass; the next pass takes the rates back to its targets,
    the next sweep the points. In the point sweeps each body b carries its joints' rotors
    (`solvers.dbd.with_rotors`, on body b): a rotor turns with the child it drives, and so the
    sweep closes a point by moving the light bodies rather than by spinning them back up. With
    the bodies' own inertia the dropped ant's rotors took 6.3 J at landing in three rounds (54 J
    in one); with the rotors on both bodies of each joint the sweep also resisted the whole ant's
    common turn, and the ant in the air drifted further from MuJoCo (0.0069 rad against 0.0035 on
    seed 1 of tests/test_mjcf.py's scene).

    solved: the start pose with the sweeps' velocities V* + dV. joint_family: the joints' prepared
    velocity family. table: the sweeps' body table (velocities V*, dx/dtheta their dV (N + 1, 3)).
    joint_impulses: (J, JOINT_IMPULSES). Returns (dv, dw) (N + 1, 3) and the joints' impulses, the
    point blocks' with what the point sweeps added."""
    structure = model.structure
    pass_table = dbd.body_table(model, solved, h)
    heavy = dbd.with_rotors(model, solved, table, on_body_a=False)
    bodies = jax.tree.map(lambda column: column[joint_family.bodies], heavy)
    points = jax.vmap(_point_block)(jax.vmap(BodyPair.of)(bodies), joint_family.params.point)
    family = Family("joint points", joint_family.bodies, points, joint_family.static, _solve_point,
                    velocity.JOINT_IMPULSES)  # fmt: skip
    colours = colouring.colour_groups([family.bodies], structure.num_bodies)
    swept_dv, swept_dw = table.dx, table.dtheta

    def round_(carry, _):  # one pass, then the points; a scan, so that the rounds compile once
        dv, dw, joint_impulses = carry
        changes = pass_table._replace(dx=dv - swept_dv, dtheta=dw - swept_dw)
        pass_dv, pass_dw = dbd.rotor_pass(model, changes, excess, h)
        moved = heavy._replace(dx=swept_dv + pass_dv, dtheta=swept_dw + pass_dw)
        dv, dw, (joint_impulses,) = dbd.gauss_seidel(colours, [family], moved, 1, [joint_impulses])
        return (dv, dw, joint_impulses), None

    (dv, dw, joint_impulses), _ = jax.lax.scan(round_, (swept_dv, swept_dw, joint_impulses), None,
                                               length=ROTOR_PASS_ROUNDS)  # fmt: skip
    return dv, dw, joint_impulses


def _point_block(pair: BodyPair, point: velocity.Block) -> velocity.Block:
    """A joint's point block (its Jacobian and Baumgarte bias as prepared) with the masses of
    `pair` (the bodies with their rotors). Its rows are the projector P of a slider's or planar
    joint's point (the identity for the others), so K is inverted on range(P) as prepared."""
    return velocity.block(pair, point.linear, point.angular_a, point.angular_b, point.bias, True,
                          projector=point.linear)  # fmt: skip


def _solve_point(point: velocity.Block, _, bodies, impulses: jnp.ndarray):
    """One update of a joint's point block alone (`rotor_pass`'s sweep). impulses: (JOINT_IMPULSES,)."""
    pair, value = velocity.solve_block(BodyPair.of(bodies), point, impulses[velocity.POINT])
    return *pair.displacements(), impulses.at[velocity.POINT].set(value)


def solved_velocities(state: State, predicted: State, dv: jnp.ndarray, dw: jnp.ndarray) -> State:
    """V' = V* + dV at the start pose X (where the rows were taken), for the rotor pass."""
    return State(pos=state.pos, quat=state.quat, vel=predicted.vel + dv, ang_vel=predicted.ang_vel + dw)


def integrate(solved: State, impulses, h: float) -> State:
    """SI (12): X' = X + h V', q' = exp(h w' / 2) q, from `solved` (the start pose X, the solved
    velocities V'); the impulses are kept."""
    vel, ang_vel = solved.vel, solved.ang_vel
    return State(pos=solved.pos + h * vel, quat=integrator.displaced_quat(solved.quat, h * ang_vel), vel=vel,
                 ang_vel=ang_vel, impulses=tuple(impulses))  # fmt: skip
