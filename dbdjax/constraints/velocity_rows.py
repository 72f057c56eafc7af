"""Velocity rows of the impulse solver (SI): Jacobians, constraint masses, bias, clamps.

A velocity row is one scalar velocity constraint J v + b (SI (16)) with a Jacobian of the form

    J v = linear . (v_b - v_a) + angular_b . w_b - angular_a . w_a

(SI (28), (47), (109): every row of SI is "b minus a", like C = p_b - p_a (25), (45)); a
positional row at arms r_a, r_b along n has linear = n, angular_* = r_* x n, an angular row along
d has linear = 0, angular_a = angular_b = d. A row is solved for an impulse lambda (N s for
positional rows, N m s for angular ones, SI's lambda' = lambda dt (20)-(23)) that changes the
velocities by M^-1 J^T lambda, with K = J M^-1 J^T (rows.row_inverse_mass, the same effective mass
the DBD rows use). Sequential impulses keep the accumulated impulse of every row and clamp it,
not the increment (Catto 2005, SI [3]). One update rule serves every row:

    d lambda = -mass (J v + b) - mix lambda,   then  lower <= lambda + d lambda <= upper

  rigid  mass = 1 / K, mix = 0: J v + b = 0 after the update, b = beta C / h (Baumgarte, SI (17))
  soft   a spring-damper of stiffness k and damping c on the error C, taken implicitly over the
         substep (the impulse h (-k C(t + h) - c C'(t + h)) with C(t + h) = C + h J v):
         with s = h (h k + c), mass = s / (1 + s K), mix = 1 / (1 + s K), b = k C / (h k + c)
         (Catto's soft constraints; s = 0 makes the row release whatever it holds)
  motor  rigid with b = -target speed (SI (124)), |lambda| <= max force h (SI (126))
  rotor  armature I_r on a joint coordinate q with J v = qdot: a flywheel of inverse mass 1 / I_r
         on the row J v - u = 0, u = u* - lambda / I_r its speed after the impulses it gave the
         bodies, u* = qdot at the start of the substep + h tau / I_r (a torque actuator on q).
         SI (20) with 1 / I_r added to K: the soft update with s = I_r and b = -u*; what the
         sweeps leave of it (`rotor_excess`) the DBD solver's rotor pass takes back

Inequality rows (contacts (42), limits (120)-(121)) clamp lambda >= 0 and bias a row that is
not violated by C / h rather than beta C / h: the bodies may close the gap C within this substep
but no further (speculative: a limit or contact is always in the system, so no active set
switches on and off inside the differentiated step). Blocks of three rows with a 3x3 K are solved
at once: the joint point (SI (48)), an angular lock (SI (60), (134), or the hinge's two rows
(86)-(90) as the plane across its axle), a ball joint's drive and a ball joint's rotor. Universal
and gimbal joints (MuJoCo's two or three hinges on one body) have the point block, the
universal's lock row (axis 1 on a perpendicular to axis 2 on b) and, per hinge k, limit, drive
and rotor rows along g_k, the gradient of its angle t_k (`math.euler_angles`). A block's rows may be
restricted to the range of a projector P (a slider's plane across its axis, SI (51)): K is then
inverted as P K P + (1 - P), which maps range(P) to itself.

Each family has a `prepare` (once per substep, at the pose of the start of the substep: rows,
masses, bias, and the warm start: the previous substep's impulses, masked to what is still
active, applied to the velocities) and a `solve` (one Gauss-Seidel pass over the node's rows,
in the shape of `constraints.Family.project`, with the `BodyPair` fields dx, dtheta read as the
velocity changes dv, dw so far).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import integrator, math
from dbdjax.collision import ContactSlots
from dbdjax.constraints import joints, links, multibody
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.model import Distances, Joints, Model, Springs, State, with_world_row

# ------------------------------------------------------------------------------------ rows


class Rows(NamedTuple):
    """R scalar rows of one node (leading axis R on every field).

    linear, angular_a, angular_b: (R, 3) the Jacobian (module docstring). turn_a, turn_b: (R, 3)
    I_a^-1 angular_a, I_b^-1 angular_b. mass, mix, bias (m/s or rad/s), lower, upper: (R,).
    """

    linear: jnp.ndarray
    angular_a: jnp.ndarray
    angular_b: jnp.ndarray
    turn_a: jnp.ndarray
    turn_b: jnp.ndarray
    mass: jnp.ndarray
    mix: jnp.ndarray
    bias: jnp.ndarray
    lower: jnp.ndarray
    upper: jnp.ndarray


class Block(NamedTuple):
    """Three rows solved together. linear, angular_a, angular_b, turn_a, turn_b: (3, 3), row k
    on axis 0. mass, mix: (3, 3). bias: (3,). bound: () the largest |lambda| (inf for none)."""

    linear: jnp.ndarray
    angular_a: jnp.ndarray
    angular_b: jnp.ndarray
    turn_a: jnp.ndarray
    turn_b: jnp.ndarray
    mass: jnp.ndarray
    mix: jnp.ndarray
    bias: jnp.ndarray
    bound: jnp.ndarray


def baumgarte_bias(error, beta, h: float, inequality=False):
    """b of SI (17): beta C / h; for an inequality row that holds (C > 0), C / h (speculative)."""
    if inequality is False:
        return beta * error / h
    return jnp.where(inequality & (error > 0.0), error / h, beta * error / h)


def point_turn_bias(pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray, h: float) -> jnp.ndarray:
    """(3,) the bias (m/s) that keeps a joint point shut through the turn of its arms over the substep.

    The rows are taken at the start pose, J v = d/dt (p_b - p_a) there, but X' = X + h V' turns
    each arm r by exp(h w) (`integrator.displaced_quat`), which moves its end by R(h w) r - r, not
    h w x r: (h^2 / 2) w x (w x r) more, the centripetal part, to second order. b = that excess / h
    (of b's arm less a's, w from V*: the rows' best guess of w') beside the Baumgarte term closes
    the point to O(h^3) a substep where, without it, a turning joint opens by (h^2 / 2) |w|^2 |r| a
    substep and only the Baumgarte bias pulls it back, at the price of a speed the rotors keep
    (README, "The Baumgarte bias's default"). The exact turn, not its Taylor term: with w^2 the
    bias fed back on the unconverged chains of benchmarks/solver_comparison.py (2 sweeps at
    dt = 1/30) and they blew up in 16-29 steps; R(h w) r - r stays within 2 |r|."""

    def turn(ang_vel, arm):  # how far the arm's end moves beyond h w x r, per second
        return (math.quat_rotate(math.quat_exp(h * ang_vel), arm) - arm) / h - math.cross(ang_vel, arm)

    return turn(pair.ang_vel_b, arm_b) - turn(pair.ang_vel_a, arm_a)


def spring_softness(stiffness, damping, error, h: float):
    """(s, b) of a spring-damper row over a substep h: s = h (h k + c), b = k C / (h k + c)."""
    weight = h * stiffness + damping
    some = weight > 0.0
    return h * weight, jnp.where(some, stiffness * error / jnp.where(some, weight, 1.0), 0.0)


def scalar_rows(pair: BodyPair, linear, angular_a, angular_b, bias, lower, upper, active, softness=0.0,
                soft=False, held=0.0, relaxed=0.0) -> Rows:  # fmt: skip
    """Rows (R,) from their Jacobians (R, 3), bias, bounds and `active` (R,). soft: (R,) bool, the
    rows that are spring-dampers of softness s (R,); the others are rigid. held: (R,) what a point
    hold takes off K (`point_hold`; 0 for none). relaxed: (R,) the armature I_r of a rotor row
    stepped along (`solve_drive_beside_rotor`; 0 for none): the update's K becomes K / (1 + I_r K).
    Inactive rows, and rigid rows that move nothing (K = 0), get mass = mix = 0: they never move."""
    inverse_mass, turn_a, turn_b = row.row_inverse_mass(pair, angular_a, angular_b, math.dot(linear, linear))
    inverse_mass = jnp.maximum(inverse_mass - held, 0.0)
    inverse_mass = inverse_mass / (1.0 + relaxed * inverse_mass)
    bias, lower, upper = (jnp.broadcast_to(jnp.asarray(x, inverse_mass.dtype), inverse_mass.shape)
                          for x in (bias, lower, upper))  # fmt: skip
    solvable = active & (inverse_mass > 0.0)
    rigid_mass = jnp.where(solvable, 1.0 / jnp.where(solvable, inverse_mass, 1.0), 0.0)
    soft_mix = 1.0 / (1.0 + softness * inverse_mass)  # s, K >= 0
    mass = jnp.where(soft, jnp.where(active, softness * soft_mix, 0.0), rigid_mass)
    mix = jnp.where(soft & active, soft_mix, 0.0)
    return Rows(linear, angular_a, angular_b, turn_a, turn_b, mass, mix, bias, lower, upper)


def block(pair: BodyPair, linear, angular_a, angular_b, bias, active, projector=None, softness=None,
          bound=jnp.inf, held=None, relaxed=None) -> Block:  # fmt: skip
    """A block of three rows (3, 3) with K = J M^-1 J^T in full (SI (48), (60)). projector: P (3, 3)
    when the rows span only range(P) (rows and bias are already in it), None for all three.
    softness: s of a soft block (a three-axis spring-damper), None for a rigid one. held: (3, 3)
    what a point hold takes off K (`point_hold`), None for none. relaxed: () the armature I_r of
    a rotor block stepped along (`solve_drive_block_beside_rotor`): the update's K becomes
    K (1 + I_r K)^-1; None for none."""
    turn_a = math.matvec(pair.inv_inertia_a, angular_a)
    turn_b = math.matvec(pair.inv_inertia_b, angular_b)
    # K_ij = (1/m_a + 1/m_b) l_i . l_j + g_a,i . I_a^-1 g_a,j + g_b,i . I_b^-1 g_b,j
    coupling = (
        (pair.inv_mass_a + pair.inv_mass_b) * math.row_products(linear, linear)
        + math.row_products(angular_a, turn_a)
        + math.row_products(angular_b, turn_b)
    )
    if held is not None:
        coupling = coupling - held
    eye = jnp.eye(3, dtype=coupling.dtype)
    if relaxed is not None:
        coupling = math.matmul(coupling, math.inverse3(eye + relaxed * coupling))
    if softness is None:
        if projector is not None:
            coupling = coupling + (eye - projector)  # invert on range(P) only (module docstring)
        mass, _ = row.definite_inverse(coupling, active)  # singular only when neither side can move
        if projector is not None:
            mass = math.matmul(math.matmul(projector, mass), projector)
        mix = jnp.zeros_like(mass)
    else:
        mix = math.inverse3(eye + softness * coupling)
        mass = jnp.where(active, softness * mix, 0.0)
        mix = jnp.where(active, mix, 0.0)
    return Block(linear, angular_a, angular_b, turn_a, turn_b, mass, mix, bias, jnp.asarray(bound, coupling.dtype))


def _relative_speed(pair: BodyPair, linear, angular_a, angular_b):
    """J v of rows (..., 3) at the current velocities V* + dv (dx, dtheta hold dv, dw)."""
    v_a, v_b = pair.vel_a + pair.dx_a, pair.vel_b + pair.dx_b
    w_a, w_b = pair.ang_vel_a + pair.dtheta_a, pair.ang_vel_b + pair.dtheta_b
    return math.dot(linear, v_b - v_a) + math.dot(angular_b, w_b) - math.dot(angular_a, w_a)


def _push(pair: BodyPair, linear, turn_a, turn_b, impulse) -> BodyPair:
    """Apply impulses (K,) along rows (K, 3): M^-1 J^T lambda, +b and -a (SI (23))."""
    push = math.sum_small(impulse[:, None] * linear, axis=0)
    return pair.moved_by(
        dx_a=-pair.inv_mass_a * push,
        dx_b=pair.inv_mass_b * push,
        dtheta_a=-math.sum_small(impulse[:, None] * turn_a, axis=0),
        dtheta_b=math.sum_small(impulse[:, None] * turn_b, axis=0),
    )


class Push(NamedTuple):
    """What a unit impulse of each of K rows does to the bodies, where it is not the row's own
    M^-1 J^T: a row that pushes with the joint point held (`point_hold`) moves them by its own
    and its point impulses' together. linear, turn_a, turn_b: (K, 3) as `Rows`' (`_push`)."""

    linear: jnp.ndarray
    turn_a: jnp.ndarray
    turn_b: jnp.ndarray


def held_push(rows: Rows | Block, point: Block, hold: jnp.ndarray, scale=1.0) -> Push:
    """The `Push` of rows (K, 3) whose impulse moves the bodies by scale (K,) times their own and
    comes with the point impulses hold (K, 3) (per unit impulse)."""
    scale = jnp.reshape(scale, (-1, 1))
    return Push(*(scale * getattr(rows, name) + math.matmul(hold, getattr(point, name)) for name in Push._fields))


def solve_row(pair: BodyPair, rows: Rows, i: int, impulses: jnp.ndarray,
              push: Push | None = None) -> tuple[BodyPair, jnp.ndarray]:  # fmt: skip
    """One sequential-impulse update of scalar row i (static) of `rows`; impulses: (R,) accumulated.
    push: how the row moves the bodies (`Push` of this row, fields (3,)), if not as its own."""
    speed = _relative_speed(pair, rows.linear[i], rows.angular_a[i], rows.angular_b[i])
    candidate = impulses[i] - rows.mass[i] * (speed + rows.bias[i]) - rows.mix[i] * impulses[i]
    step = jnp.clip(candidate, rows.lower[i], rows.upper[i]) - impulses[i]
    along = Push(rows.linear[i], rows.turn_a[i], rows.turn_b[i]) if push is None else push
    pair = _push(pair, along.linear[None], along.turn_a[None], along.turn_b[None], step[None])
    return pair, impulses.at[i].add(step)


def solve_block(pair: BodyPair, rows: Block, impulse: jnp.ndarray,
                push: Push | None = None) -> tuple[BodyPair, jnp.ndarray]:  # fmt: skip
    """One update of a block (3,): d lambda = -mass (J v + b) - mix lambda, |lambda| <= bound.
    push: how the rows move the bodies, if not as their own (`Push`)."""
    speed = _relative_speed(pair, rows.linear, rows.angular_a, rows.angular_b)
    candidate = impulse - math.matvec(rows.mass, speed + rows.bias) - math.matvec(rows.mix, impulse)
    step = math.clamp_norm(candidate, rows.bound) - impulse
    along = rows if push is None else push
    return _push(pair, along.linear, along.turn_a, along.turn_b, step), impulse + step


# A drive stepped beside its rotor. A drive row (soft, s = h (h k + c)) and the rotor row of the
# same coordinate (soft, s = I_r) share their Jacobian J; stepped one after the other, a light
# body's drive stops it, the rotor row pushes it back, a little less each sweep (the light legs of
# tests/test_mjcf.py were 0.07-1.6 rad/s from MuJoCo at 4 iterations). So the drive is stepped
# right after its rotor, the two as one block: from the rotor's residual rho_r = J v + b_r +
# lambda_r / I_r (zero after its own update), the bodies step by X along J (with the point held,
# K' the held response) and the impulses by x_d (drive) and X - x_d (rotor), keeping rho_r where
# it is: K' X + (X - x_d) / I_r = 0, X = x_d / (1 + I_r K') = mix_r x_d, mix_r the rotor row's
# mix. The drive's update is then the soft row's with the rotor-relaxed response
# K' / (1 + I_r K') (the Schur complement of the rotor row: `scalar_rows`' relaxed), which leaves
# its residual at zero; its bound clamps x_d and X follows. So the drive row is `solve_row` with
# that response, pushing by mix_r times its own push, and the rotor's impulse moves by
# (mix_r - 1) x_d. For a ball joint's blocks mix_r is the 3x3 (1 + I_r K')^-1. The velocity form
# of rows.spring_row_beside_rotor (the DBD solver's block).


def solve_drive_beside_rotor(pair: BodyPair, rows: Rows, drive: int, rotor: int, impulses: jnp.ndarray, push: Push,
                             rotor_share: jnp.ndarray) -> tuple[BodyPair, jnp.ndarray]:  # fmt: skip
    """One update of scalar row `drive` right after the rotor row `rotor` of its coordinate, the
    two as one block (the comment above): `solve_row` with the drive's mass and mix from the
    rotor-relaxed response and push (`Push`, fields (3,)) mix_r times its own, and the rotor's
    impulse moved by rotor_share x_d (rotor_share: (), mix_r - 1; 0 where the rotor is inactive,
    where this is `solve_row`). Returns (pair, impulses (R,))."""
    before = impulses[drive]
    pair, impulses = solve_row(pair, rows, drive, impulses, push)
    rotor_row = np.arange(impulses.shape[-1]) == rotor  # a mask, not .at[rotor]: one kernel fewer per sweep
    return pair, impulses + jnp.where(rotor_row, rotor_share * (impulses[drive] - before), 0.0)


def solve_drive_block_beside_rotor(pair: BodyPair, drive: Block, impulse: jnp.ndarray, push: Push,
                                   rotor_share: jnp.ndarray) -> tuple[BodyPair, jnp.ndarray, jnp.ndarray]:  # fmt: skip
    """A ball joint's drive block right after its rotor block, as `solve_drive_beside_rotor`: the
    drive's mass and mix from the rotor-relaxed response, its push (`Push`) mix_r^T times its own
    (mix_r (3, 3)), rotor_share: (3, 3) mix_r - 1. Returns (pair, drive impulse (3,), the rotor's
    impulse's change (3,))."""
    pair, value = solve_block(pair, drive, impulse, push)
    return pair, value, math.matvec(rotor_share, value - impulse)


def _warm(pair: BodyPair, pieces) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(dv (2, 3), dw (2, 3)) of the stored impulses: pieces are (rows with fields linear, turn_a,
    turn_b (..., 3), their impulses (K,))."""
    for rows, impulse in pieces:
        pair = _push(pair, rows.linear.reshape(-1, 3), rows.turn_a.reshape(-1, 3), rows.turn_b.reshape(-1, 3), impulse)
    return pair.displacements()


def point_hold(pair: BodyPair, point: Block, linear, angular_a, angular_b):
    """The point impulses that hold a joint's point while rows (R, 3) push, and what that takes
    off their K: (hold (R, 3), held (R, R)).

    A row's impulse d lambda changes the relative velocity of the joint points by s d lambda, with
    s = J_point M^-1 J_row^T (R, 3); the point block answers with the impulse hold d lambda, hold =
    -K_point^-1 s (its `mass`), given together with the row's. The row then moves J v by
    (K - s^T K_point^-1 s) d lambda: the Schur complement, the joint-space response with the
    point held, so that a rotor row on a body whose own inertia is small against m r^2 about the
    joint (a pendulum bob, a foot) converges in a few sweeps instead of spinning the body about
    its centre and leaving the point block to turn it back (the detour rows.PointHold describes
    for the DBD solver; here the sweeps converged too slowly: a ball pendulum with armature swung
    13 % slow at 8 iterations without the hold)."""
    turn_a = math.matvec(pair.inv_inertia_a, angular_a)
    turn_b = math.matvec(pair.inv_inertia_b, angular_b)
    coupling = (
        (pair.inv_mass_a + pair.inv_mass_b) * math.row_products(linear, point.linear)
        + math.row_products(turn_a, point.angular_a)
        + math.row_products(turn_b, point.angular_b)
    )  # (R, 3): s of each row
    hold = -math.matvec(point.mass, coupling)  # -K_point^-1 s
    return hold, -math.row_products(coupling, hold)


# ---------------------------------------------------------------------------------- joints

# Impulses of one joint: the ball drive block, the scalar rows, the angular lock, the point and the
# ball rotor block. Scalar rows: the hinge's and slider's motor, limits and cone (0-5), the
# universal lock (6), per hinge k of a universal or gimbal joint its lower and upper limit (7 + k,
# 10 + k), then the rows that push with the point held (`_PUSHED`): the hinge's drive (13), the
# drive of hinge k (14 + k) and the rotor of degree of freedom k (a hinge's, planar's or slider's:
# k = 0), 17 + k.
DRIVE_BLOCK = slice(0, 3)
MOTOR, ANGLE_LOWER, ANGLE_UPPER, CONE, TRAVEL_LOWER, TRAVEL_UPPER = range(6)
UNIVERSAL_LOCK, EULER_LOWER, EULER_UPPER, HINGE_DRIVE, EULER_DRIVE, ROTOR = 6, 7, 10, 13, 14, 17
NUM_SCALARS = 20
SCALARS = slice(3, 3 + NUM_SCALARS)
LOCK = slice(23, 26)
POINT = slice(26, 29)
ROTOR_BLOCK = slice(29, 32)
JOINT_IMPULSES = 32
# The scalar rows each kind of row in use (joints.rows_in_use) needs, in the order a sweep solves
# them: rotors, drives and motors first, then the hard rows (as the DBD solver's joints.project).
# Each drive right after the rotor of its coordinate (stepped as one: `solve_drive_beside_rotor`).
_SCALAR_ROWS = (
    ("rotor_hinge", ROTOR), ("rotor_slider", ROTOR), ("rotor_euler", ROTOR), ("hinge_drive", HINGE_DRIVE),
    *((kind, index + k) for k in range(3) for kind, index in (("rotor_euler", ROTOR), ("euler_drive", EULER_DRIVE))),
    ("angular_motor", MOTOR), ("linear_motor", MOTOR), ("has_angle_limits", ANGLE_LOWER),
    ("has_angle_limits", ANGLE_UPPER), ("has_cone", CONE), ("has_travel_limits", TRAVEL_LOWER),
    ("has_travel_limits", TRAVEL_UPPER), ("universal", UNIVERSAL_LOCK),
    *(("euler_limited", EULER_LOWER + k) for k in range(3)), *(("euler_limited", EULER_UPPER + k) for k in range(3)),
)  # fmt: skip
# (drive row, rotor row) on one coordinate: a hinge's drive and its rotor, a universal or gimbal
# joint's drive of hinge k and rotor k.
_BESIDE_ROTOR = ((HINGE_DRIVE, ROTOR), *((EULER_DRIVE + k, ROTOR + k) for k in range(3)))
_SOFT = np.isin(np.arange(NUM_SCALARS), [HINGE_DRIVE, *range(EULER_DRIVE, EULER_DRIVE + 3), *range(ROTOR, ROTOR + 3)])
# The rotor rows, whose K is taken with the joint point held (`point_hold`), and the rows that push
# with it held (the rotors and, beside an active rotor, the drives); slices, not index arrays: a
# NumPy int64 index array met int32 indices after a float64 test in the same process.
_HELD = slice(ROTOR, ROTOR + 3)
_PUSHED = slice(HINGE_DRIVE, NUM_SCALARS)


class JointRows(NamedTuple):
    """Every row of one joint: ball drive (Block), NUM_SCALARS scalar rows (Rows), angular lock,
    point, ball rotor (Block); for the scalar rows of `_PUSHED` (P of them), the ball rotor and
    the ball drive, the point impulse per unit impulse where they push with the point held
    (`point_hold`; *_hold (P, 3), (3, 3), (3, 3), zero where not) and how they move the bodies,
    point impulses and all (*_push: `Push`); and what a drive's step beside its rotor moves the
    rotor's impulse by, per unit (`solve_drive_beside_rotor`): scalar_rotor_share (P,),
    drive_rotor_share (3, 3)."""

    drive: Block
    scalars: Rows
    lock: Block
    point: Block
    rotor: Block
    scalar_hold: jnp.ndarray
    rotor_hold: jnp.ndarray
    drive_hold: jnp.ndarray
    scalar_push: Push
    rotor_push: Push
    drive_push: Push
    scalar_rotor_share: jnp.ndarray
    drive_rotor_share: jnp.ndarray


def _scalar_rows_in_use(rows: frozenset[str]) -> list[int]:
    """The scalar rows of the kinds in `rows`, each once, in solve order (`_SCALAR_ROWS`)."""
    return list(dict.fromkeys(index for name, index in _SCALAR_ROWS if name in rows))


_wrapped = math.wrap_angle


def prepare_joint(joint: Joints, flag: joints.JointFlags, target: joints.Targets, start: jnp.ndarray, pair: BodyPair,
                  impulses: jnp.ndarray, h: float, rows: frozenset[str]):  # fmt: skip
    """The velocity rows of one joint at the start of the substep, SI 2.2-2.5, and the warm start.

    pair: the two bodies at the start pose, dx = dtheta = 0, vel/ang_vel = V*. start: (4, 3) the
    bodies' velocities at the start of the substep (v_a, v_b, w_a, w_b; the rotor rows read the
    coordinate speeds from them). impulses: (JOINT_IMPULSES,) the joint's impulses of the previous
    substep. Returns (JointRows, impulses, dv (2, 3), dw (2, 3)).
    """
    dtype = pair.origin_a.dtype
    beta = joint.baumgarte
    zero3 = jnp.zeros(3, dtype)
    eye = jnp.eye(3, dtype=dtype)
    quat_a, quat_b = pair.current_quats()
    inf = jnp.asarray(jnp.inf, dtype)
    at_start = pair._replace(vel_a=start[0], vel_b=start[1], ang_vel_a=start[2], ang_vel_b=start[3])

    # Point: C = p_b - p_a (SI (45), (127)) as one block with the 3x3 K (48), its bias the Baumgarte
    # term and the arms' turn over the substep (`point_turn_bias`). A slider keeps the part across
    # its axis (SI (51)), a planar joint the part along its normal, both acting level with p_b.
    delta, arm_a, arm_b = joints.joint_points(joint, flag, pair, quat_a, quat_b)  # delta = p_a - p_b
    projector = None
    if "slider" in rows or "planar" in rows:
        axis = math.quat_rotate(quat_a, joint.local_axis_a)
        along_axis = axis[:, None] * axis[None, :]
        projector = jnp.where(flag.slider, eye - along_axis, jnp.where(flag.planar, along_axis, eye))
        arm_a = arm_a - math.matvec(eye - projector, delta)
        delta = math.matvec(projector, delta)
    rows_p = eye if projector is None else projector
    bias = baumgarte_bias(-delta, beta, h) + math.matvec(rows_p, point_turn_bias(pair, arm_a, arm_b, h))
    point = block(pair, rows_p, math.cross(arm_a[None], rows_p), math.cross(arm_b[None], rows_p), bias, True,
                  projector=projector)  # fmt: skip

    # Scalar rows, each (linear, angular_a, angular_b, bias, lower, upper, active, softness).
    scalar = [(zero3, zero3, zero3, 0.0, 0.0, 0.0, False, 0.0)] * NUM_SCALARS
    if rows & {"hinge_drive", "angular_motor", "has_angle_limits", "rotor_hinge"}:
        angle, axle = joints.hinge_angle(joint, pair)  # d angle / dt = axle . (w_b - w_a)
    if "hinge_drive" in rows:  # DBD 9 about the axle as a soft row; the error wrapped to (-pi, pi]
        softness, bias = spring_softness(joint.drive_stiffness, joint.drive_damping, _wrapped(angle - target.drive[0]),
                                         h)  # fmt: skip
        torque = joint.drive_max_torque * h
        scalar[HINGE_DRIVE] = (zero3, axle, axle, bias, -torque, torque, flag.hinge_drive, softness)
    if rows & {"linear_motor", "has_travel_limits", "rotor_slider"}:
        travel, slide, arm_a, arm_b = joints.slider_travel(joint, flag, pair)  # SI (65)-(78)
        torque_a, torque_b = math.cross(arm_a, slide), math.cross(arm_b, slide)
    if rows & {"angular_motor", "linear_motor"}:  # SI (124), (126): J v = target speed
        force = joint.motor_max_force * h
        motor = (zero3, zero3, zero3, 0.0, 0.0, 0.0, False, 0.0)
        if "angular_motor" in rows:
            motor = (zero3, axle, axle, -target.motor, -force, force, flag.angular_motor, 0.0)
        if "linear_motor" in rows:
            linear_motor = (slide, torque_a, torque_b, -target.motor, -force, force, flag.linear_motor, 0.0)
            motor = jax.tree.map(lambda x, y: jnp.where(flag.linear_motor, y, x), motor, linear_motor)
        scalar[MOTOR] = motor
    if "has_angle_limits" in rows:  # SI (108)-(121): C_min = angle - lower, C_max = upper - angle
        active = flag.has_angle_limits
        lower, upper = joints.limit_errors(angle, joint.lower, joint.upper, periodic=True)
        scalar[ANGLE_LOWER] = (zero3, axle, axle, baumgarte_bias(lower, beta, h, True), 0.0, inf, active, 0.0)
        scalar[ANGLE_UPPER] = (zero3, -axle, -axle, baumgarte_bias(upper, beta, h, True), 0.0, inf, active, 0.0)
    if "has_cone" in rows:  # C = cone limit - angle between the twist axes (DBD (81)), >= 0
        cone_angle, cone_axis = math.angle_between(
            math.quat_rotate(quat_a, joint.local_axis_a), math.quat_rotate(quat_b, joint.local_axis_b)
        )
        bias = baumgarte_bias(joint.cone_limit - cone_angle, beta, h, True)
        scalar[CONE] = (zero3, -cone_axis, -cone_axis, bias, 0.0, inf, flag.has_cone, 0.0)
    if "has_travel_limits" in rows:  # SI (65)-(78) on the travel along the slide axis
        active = flag.has_travel_limits
        lower, upper = travel - joint.lower, joint.upper - travel
        scalar[TRAVEL_LOWER] = (slide, torque_a, torque_b, baumgarte_bias(lower, beta, h, True), 0.0, inf, active, 0.0)
        scalar[TRAVEL_UPPER] = (-slide, -torque_a, -torque_b, baumgarte_bias(upper, beta, h, True), 0.0, inf, active,
                                0.0)  # fmt: skip

    # Universal lock: hinge axis 1 (fixed in a) and axis 2 (fixed in b) stay perpendicular, C = m1 . m2
    # (the DBD solver's universal row, joints.project). dC/dt = (w_a x m1) . m2 + m1 . (w_b x m2)
    # = (m2 x m1) . (w_b - w_a): J = (0, m2 x m1, 0, m2 x m1) in the form of SI (90), a unit
    # vector where the lock holds (never a normalised vanishing one); bias SI (17).
    if "universal" in rows:
        axis_1 = math.quat_rotate(quat_a, joint.local_axes_a[0])
        axis_2 = math.quat_rotate(quat_b, joint.local_axes_b[1])
        turn = math.cross(axis_2, axis_1)
        bias = baumgarte_bias(math.dot(axis_1, axis_2), beta, h)
        scalar[UNIVERSAL_LOCK] = (zero3, turn, turn, bias, -inf, inf, flag.universal, 0.0)

    # Hinges of universal and gimbal joints (`math.euler_angles`): angle t_k, dt_k/dt = g_k . (w_b - w_a)
    # (g_k the dual basis of the hinge axes; the universal's g_3 = 0). Per hinge: two one-sided
    # limit rows, C_min = t_k - lower_k, C_max = upper_k - t_k >= 0 (SI (108)-(121) with the axle a
    # replaced by g_k, speculative bias), and a drive row (DBD 9 on t_k as a soft row, MuJoCo's
    # per-dof stiffness and damping), |lambda| <= max torque h.
    if rows & {"euler_limited", "euler_drive", "rotor_euler"}:
        angles, directions = joints._euler_angles(joint, flag, pair, rows)
    if "euler_limited" in rows:
        for k in range(3):
            active = flag.euler_limited[k]
            lower, upper = joints.limit_errors(angles[k], joint.axis_lower[k], joint.axis_upper[k], periodic=True)
            g = directions[k]
            scalar[EULER_LOWER + k] = (zero3, g, g, baumgarte_bias(lower, beta, h, True), 0.0, inf, active, 0.0)
            scalar[EULER_UPPER + k] = (zero3, -g, -g, baumgarte_bias(upper, beta, h, True), 0.0, inf, active, 0.0)
    if "euler_drive" in rows:
        torque = joint.drive_max_torque * h
        for k in range(3):
            softness, bias = spring_softness(joint.axis_stiffness[k], joint.axis_damping[k],
                                             _wrapped(angles[k] - target.drive[k]), h)  # fmt: skip
            active = flag.euler_drive & (flag.gimbal | (k < 2))  # the universal has no third hinge
            scalar[EULER_DRIVE + k] = (zero3, directions[k], directions[k], bias, -torque, torque, active, softness)

    # Armature (MuJoCo's rotor inertia I_r on a joint coordinate q, kinetic energy 1/2 I_r qdot^2):
    # a flywheel of inertia I_r held to q by the velocity row J v - u = 0, J v = qdot (the DoF's
    # row: the axle, the slide, g_k). A torque actuator on q spins the flywheel up by h tau / I_r
    # (SI (12); integrator.actuator_wrenches leaves those torques to this row, as the DBD solver's
    # rotor row does), and an impulse lambda on the bodies takes lambda from it: u = u* - lambda / I_r.
    # So the row is J v + b + lambda / I_r = 0 with b = -u*, whose sequential-impulse update
    # (SI (20)-(23) with the flywheel's inverse mass 1 / I_r added to K) is the soft row's with
    # s = I_r: mass = 1 / (K + 1 / I_r), mix = 1 / (1 + I_r K). It is the velocity form of the
    # DBD solver's rotor row (a spring with k h^2 = I_r toward where the rotor carries q). A ball's
    # flywheel is isotropic: J = w_b - w_a in world axes, a soft block of three rows.
    # The flywheel keeps its own speed from one substep to the next: what the last solve left it,
    # J(X^(t-1)) V^t with the rows of the last substep's pose X^(t-1) = X^t - h V^t (exactly, in
    # `solvers.impulse.integrate`), not J(X^t) V^t. The difference, h dJ/dt v, is the flywheel's
    # share of the coordinate's acceleration when J turns (a gimbal's middle axis as hinge 1
    # turns): taking J(X^t) V^t would give it that speed for free, with no reaction on the bodies
    # (the middle hinge of a gimbal with armature drifted 0.38 rad from MuJoCo's in 1 s).
    def rotor_jacobians(at: BodyPair):  # the three rotor rows' (linear, angular_a, angular_b) at a pose
        result = []
        if "rotor_euler" in rows:
            _, gradients = joints._euler_angles(joint, flag, at, rows)
        if "rotor_hinge" in rows:
            _, axle_here = joints.hinge_angle(joint, at)
        if "rotor_slider" in rows:
            _, slide_here, arm_a_here, arm_b_here = joints.slider_travel(joint, flag, at)
            along = (slide_here, math.cross(arm_a_here, slide_here), math.cross(arm_b_here, slide_here))
        for k in range(3):
            jacobian = (zero3, gradients[k], gradients[k]) if "rotor_euler" in rows else (zero3, zero3, zero3)
            if k == 0 and "rotor_hinge" in rows:
                jacobian = jax.tree.map(lambda x, y: jnp.where(flag.rotor_hinge, y, x), jacobian, (zero3, axle_here,
                                        axle_here))  # fmt: skip
            if k == 0 and "rotor_slider" in rows:
                jacobian = jax.tree.map(lambda x, y: jnp.where(flag.rotor_slider, y, x), jacobian, along)
            result.append(jacobian)
        return result

    if rows & {"rotor_hinge", "rotor_slider", "rotor_euler"}:
        before = pair._replace(origin_a=pair.origin_a - h * start[0], origin_b=pair.origin_b - h * start[1],
                               quat_a=integrator.displaced_quat(pair.quat_a, -h * start[2]),
                               quat_b=integrator.displaced_quat(pair.quat_b, -h * start[3]))  # fmt: skip
        for k, (now, then) in enumerate(zip(rotor_jacobians(pair), rotor_jacobians(before), strict=True)):
            active = flag.rotor_euler[k] if "rotor_euler" in rows else jnp.asarray(False)
            if k == 0:
                active = active | flag.rotor_hinge | flag.rotor_slider
            armature = joint.armature[k]
            some = armature > 0.0
            spin_up = h * target.torque[k] / jnp.where(some, armature, 1.0)
            speed = _relative_speed(at_start, *then) + jnp.where(some, spin_up, 0.0)  # u*
            scalar[ROTOR + k] = (*now, -speed, -inf, inf, active & some, armature)
    # The rotor rows push with the joint point held (`point_hold`): their K is the joint-space one.
    rotor_hold = jnp.zeros((3, 3), dtype)
    if "rotor_ball" in rows:
        # MuJoCo's ball velocity is w_b - w_a in b's frame, so the flywheel keeps its speed in b's
        # frame: u* is the start's w_b - w_a turned with b over the last substep (by h w_b), as
        # above. Torques on a ball joint with armature are refused at finalize.
        spin = math.quat_rotate(math.quat_exp(h * start[3]), start[3] - start[2])
        rotor_hold, rotor_held = point_hold(pair, point, jnp.zeros((3, 3), dtype), eye, eye)
        ball_rotor_on = flag.rotor_ball & (joint.armature[0] > 0.0)
        rotor = block(pair, jnp.zeros((3, 3), dtype), eye, eye, -spin, ball_rotor_on, softness=joint.armature[0],
                      held=rotor_held)  # fmt: skip
    else:
        rotor = block(pair, jnp.zeros((3, 3), dtype), eye, eye, zero3, False)

    # Ball drive (DBD 9 as a soft block): the rotation vector of E = X T^-1 in world axes, pulled to
    # zero by a three-axis spring-damper, |lambda| <= max torque h. Beside a rotor it pushes with the
    # point held, with the rotor-relaxed response (`solve_drive_block_beside_rotor`).
    if "ball_drive" in rows:
        goal = math.quat_exp(target.drive)
        error_rotation = math.quat_multiply(joints.relative_rotation(joint, quat_a, quat_b), math.quat_conjugate(goal))
        error = math.quat_rotate(quat_a, math.quat_log(error_rotation))
        softness, bias = spring_softness(joint.drive_stiffness, joint.drive_damping, error, h)
        beside = {}
        if "rotor_ball" in rows:
            rotor_armature = jnp.where(ball_rotor_on, joint.armature[0], 0.0)
            beside = dict(held=jnp.where(ball_rotor_on, rotor_held, 0.0), relaxed=rotor_armature)
        drive = block(pair, jnp.zeros((3, 3), dtype), eye, eye, bias, flag.ball_drive, softness=softness,
                      bound=joint.drive_max_torque * h, **beside)  # fmt: skip
    else:
        drive = block(pair, jnp.zeros((3, 3), dtype), eye, eye, zero3, False)
    drive_hold, drive_rotor_share = jnp.zeros((3, 3), dtype), jnp.zeros((3, 3), dtype)
    drive_push = Push(drive.linear, drive.turn_a, drive.turn_b)
    if {"rotor_ball", "ball_drive"} <= rows:  # `solve_drive_block_beside_rotor`
        carry = jnp.where(ball_rotor_on, rotor.mix, eye)  # mix_r = (1 + I_r K')^-1
        drive_hold = jnp.where(ball_rotor_on, rotor_hold, 0.0)
        drive_push = Push(*(math.matmul(carry, field, transpose_a=True)
                            for field in held_push(drive, point, drive_hold)))  # fmt: skip
        drive_hold = math.matmul(carry, drive_hold, transpose_a=True)
        drive_rotor_share = carry - eye

    linear, angular_a, angular_b = (jnp.stack([entry[k] for entry in scalar]) for k in range(3))
    bias, lower, upper, softness = (jnp.stack([jnp.asarray(entry[k], dtype) for entry in scalar]) for k in (3, 4, 5, 7))
    active = jnp.stack([jnp.asarray(entry[6], bool) for entry in scalar])
    scalar_hold, held, relaxed = jnp.zeros((NUM_SCALARS, 3), dtype), 0.0, 0.0
    if rows & {"rotor_hinge", "rotor_slider", "rotor_euler"}:
        hold, held = point_hold(pair, point, linear[_HELD], angular_a[_HELD], angular_b[_HELD])
        scalar_hold = scalar_hold.at[_HELD].set(hold)
        held = jnp.zeros(NUM_SCALARS, dtype).at[_HELD].set(jnp.diagonal(held))
        relaxed = jnp.zeros(NUM_SCALARS, dtype)
        # A drive beside an active rotor pushes with the point held too, with the rotor-relaxed
        # response (`solve_drive_beside_rotor`).
        for drive_row, rotor_row in _BESIDE_ROTOR:
            rotor_on = active[rotor_row]  # the rotor row is active only with armature
            scalar_hold = scalar_hold.at[drive_row].set(jnp.where(rotor_on, scalar_hold[rotor_row], 0.0))
            held = held.at[drive_row].set(jnp.where(rotor_on, held[rotor_row], 0.0))
            relaxed = relaxed.at[drive_row].set(jnp.where(rotor_on, softness[rotor_row], 0.0))
    scalars = scalar_rows(pair, linear, angular_a, angular_b, bias, lower, upper, active, softness, _SOFT, held,
                          relaxed)  # fmt: skip
    # A drive beside an active rotor moves the bodies (and the point) by mix_r x_d and the rotor's
    # impulse by (mix_r - 1) x_d (`solve_drive_beside_rotor`).
    carry, scalar_rotor_share = jnp.ones(NUM_SCALARS, dtype), jnp.zeros(NUM_SCALARS, dtype)
    if rows & {"rotor_hinge", "rotor_slider", "rotor_euler"}:
        for drive_row, rotor_row in _BESIDE_ROTOR:
            share = jnp.where(active[rotor_row], scalars.mix[rotor_row], 1.0)  # mix_r = 1 / (1 + I_r K')
            carry = carry.at[drive_row].set(share)
            scalar_rotor_share = scalar_rotor_share.at[drive_row].set(share - 1.0)
        scalar_hold = carry[:, None] * scalar_hold

    # Angular lock, a block over the plane across the axle (hinge, planar: SI (86)-(90), the error
    # the angle between the axes about the axis turning a's toward b's) or over all three axes
    # (slider, fixed: SI (53), (129), the rotation vector of b away from its rest pose).
    if "rotation_lock" in rows:
        axis_a = math.quat_rotate(quat_a, joint.local_axis_a)
        axis_b = math.quat_rotate(quat_b, joint.local_axis_b)
        axle_angle, axle_axis = math.angle_between(axis_a, axis_b)
        bisector, _ = math.safe_normalize(axis_a + axis_b)
        relative = joints.relative_rotation(joint, quat_a, quat_b)
        axle_kind = flag.hinge | flag.planar
        error = jnp.where(axle_kind, axle_angle * axle_axis, math.quat_rotate(quat_a, math.quat_log(relative)))
        projector = jnp.where(axle_kind, eye - bisector[:, None] * bisector[None, :], eye)
        bias = math.matvec(projector, baumgarte_bias(error, beta, h))
        lock = block(pair, jnp.zeros((3, 3), dtype), projector, projector, bias, axle_kind | flag.rotation_locked,
                     projector=projector)  # fmt: skip
    else:
        lock = block(pair, jnp.zeros((3, 3), dtype), eye, eye, zero3, False)

    pushed = Push(scalars.linear[_PUSHED], scalars.turn_a[_PUSHED], scalars.turn_b[_PUSHED])
    scalar_push = held_push(pushed, point, scalar_hold[_PUSHED], carry[_PUSHED])
    result = JointRows(drive, scalars, lock, point, rotor, scalar_hold[_PUSHED], rotor_hold, drive_hold, scalar_push,
                       held_push(rotor, point, rotor_hold), drive_push, scalar_rotor_share[_PUSHED],
                       drive_rotor_share)  # fmt: skip
    dv, dw = _warm(pair, [(drive, impulses[DRIVE_BLOCK]), (scalars, impulses[SCALARS]), (lock, impulses[LOCK]),
                          (point, impulses[POINT]), (rotor, impulses[ROTOR_BLOCK])])  # fmt: skip
    return result, impulses, dv, dw


def solve_joint(joint_rows: JointRows, bodies: BodySet, impulses: jnp.ndarray, rows: frozenset[str]):
    """One pass over a joint's rows: rotors, drives and motors first, then limits, the angular lock
    and the point last (so that the joint gap has the last word, as in the DBD solver)."""
    pair = BodyPair.of(bodies)

    def held(point_impulse, step, hold):  # the point impulse that came with a held row's step (its Push)
        return point_impulse + math.sum_small(step[:, None] * hold, axis=0)

    point_impulse = impulses[POINT]
    if "rotor_ball" in rows:
        pair, value = solve_block(pair, joint_rows.rotor, impulses[ROTOR_BLOCK], joint_rows.rotor_push)
        point_impulse = held(point_impulse, value - impulses[ROTOR_BLOCK], joint_rows.rotor_hold)
        impulses = impulses.at[ROTOR_BLOCK].set(value)
    if {"rotor_ball", "ball_drive"} <= rows:
        pair, value, rotor_change = solve_drive_block_beside_rotor(
            pair, joint_rows.drive, impulses[DRIVE_BLOCK], joint_rows.drive_push, joint_rows.drive_rotor_share
        )
        point_impulse = held(point_impulse, value - impulses[DRIVE_BLOCK], joint_rows.drive_hold)
        impulses = impulses.at[DRIVE_BLOCK].set(value).at[ROTOR_BLOCK].add(rotor_change)
    elif "ball_drive" in rows:
        pair, value = solve_block(pair, joint_rows.drive, impulses[DRIVE_BLOCK])
        impulses = impulses.at[DRIVE_BLOCK].set(value)
    scalars = impulses[SCALARS]
    in_use = _scalar_rows_in_use(rows)
    beside_rotor = {drive: rotor for drive, rotor in _BESIDE_ROTOR if drive in in_use and rotor in in_use}
    for i in in_use:
        before = scalars[i]
        pushed = i - _PUSHED.start  # the row's place in the `_PUSHED` arrays
        with_point = i in beside_rotor or ROTOR <= i < ROTOR + 3  # (a drive only where a rotor is traced)
        push = Push(*(field[pushed] for field in joint_rows.scalar_push)) if with_point else None
        if i in beside_rotor:
            pair, scalars = solve_drive_beside_rotor(pair, joint_rows.scalars, i, beside_rotor[i], scalars, push,
                                                     joint_rows.scalar_rotor_share[pushed])  # fmt: skip
        else:
            pair, scalars = solve_row(pair, joint_rows.scalars, i, scalars, push)
        if with_point:
            point_impulse = held(point_impulse, (scalars[i] - before)[None], joint_rows.scalar_hold[pushed][None])
    impulses = impulses.at[SCALARS].set(scalars).at[POINT].set(point_impulse)
    if "rotation_lock" in rows:
        pair, value = solve_block(pair, joint_rows.lock, impulses[LOCK])
        impulses = impulses.at[LOCK].set(value)
    pair, value = solve_block(pair, joint_rows.point, impulses[POINT])
    impulses = impulses.at[POINT].set(value)
    return *pair.displacements(), impulses


def _solve_kind(joint_rows: JointRows, _, bodies: BodySet, impulses: jnp.ndarray, rows: frozenset[str]):
    """`solve_joint` in the shape of `VelocityFamily.solve`, tracing `rows` (every row in use, or
    one kind of joint's)."""
    return solve_joint(joint_rows, bodies, impulses, rows)


def rotor_excess(joint_rows: JointRows, armature: jnp.ndarray, bodies: BodySet, impulses: jnp.ndarray,
                 h: float) -> jnp.ndarray:  # fmt: skip
    """(3,) what the sweeps left of one joint's rotor rows, in the units of the DBD solver's
    `joints.rotor_excess` (rad or m; a ball's: a world rotation vector): h rho, with rho = J v + b +
    lambda / I_r the rotor row's residual (rad/s or m/s, 0 where converged: module docstring, the
    rotor row). rho is the rate the bodies carry past the flywheel's own, u = u* - lambda / I_r,
    with no impulse behind it; `solvers.dbd.rotor_momentum` takes it back (the same pass as the
    DBD solver's). 0 for the degrees of freedom without armature.

    armature: (3,) the joint's (`Joints.armature`). bodies: the joint's two bodies with the
    solve's velocity changes in dx, dtheta. impulses: (JOINT_IMPULSES,) at the end of the solve."""
    pair = BodyPair.of(bodies)
    scalars = joint_rows.scalars
    lam = impulses[SCALARS][_HELD]
    speed = _relative_speed(pair, scalars.linear[_HELD], scalars.angular_a[_HELD], scalars.angular_b[_HELD])
    has = scalars.mass[_HELD] > 0.0  # an active rotor row (inactive rows have mass 0)
    residual = jnp.where(has, speed + scalars.bias[_HELD] + lam / jnp.where(has, armature, 1.0), 0.0)
    ball = joint_rows.rotor
    ball_armature = armature[0]
    is_ball = jnp.any(ball.mass != 0.0) & (ball_armature > 0.0)
    ball_residual = (_relative_speed(pair, ball.linear, ball.angular_a, ball.angular_b) + ball.bias
                     + impulses[ROTOR_BLOCK] / jnp.where(is_ball, ball_armature, 1.0))  # fmt: skip
    return h * jnp.where(is_ball, ball_residual, residual)


# ---------------------------------------------------------------------------------- contacts

# Kept between substeps per point: lambda_n and the friction impulse as a world vector, so that a
# change of the tangent basis (any_perpendicular of a normal that turned) does not turn the warm
# start with it. Inside a solve: (lambda_n, lambda_t1, lambda_t2).
CONTACT_IMPULSES_PER_POINT = 4


class ContactRows(NamedTuple):
    """The rows of one shape pair's P points: normal and two tangents per point (SI 2.1).

    directions, angular_a, angular_b, turn_a, turn_b: (P, 3, 3), rows (n, t1, t2) on axis 1.
    tangent_coupling: (P, 2, 2) K of the two friction rows. normal_mass, normal_mix, normal_bias:
    (P,) the normal row's update (module docstring). friction: (P,) mu. active: (P,) bool.
    """

    directions: jnp.ndarray
    angular_a: jnp.ndarray
    angular_b: jnp.ndarray
    turn_a: jnp.ndarray
    turn_b: jnp.ndarray
    tangent_coupling: jnp.ndarray
    normal_mass: jnp.ndarray
    normal_mix: jnp.ndarray
    normal_bias: jnp.ndarray
    friction: jnp.ndarray
    active: jnp.ndarray


def _clamp_disc(vector, bound):
    """A 2-vector scaled back onto |vector| <= bound (the friction cone of SI (31))."""
    padded = jnp.concatenate([vector, jnp.zeros(1, vector.dtype)])
    return math.clamp_norm(padded, bound)[:2]


def prepare_contacts(slots: ContactSlots, world: np.ndarray, bodies: BodySet, impulses: jnp.ndarray, h: float,
                     beta: float, compliance: float, slow: float):  # fmt: skip
    """The contact and friction rows of one shape pair at the start of the substep, and the warm start.

    The points were found at the predicted pose X* (collision.detect, so that a fast body is caught
    before it passes through); the rows are taken where those body points are at the start pose:
    C = (p_b - p_a) . n (SI (25)), arms r_a, r_b, Jacobians (28)-(30), K (34)-(36). Normal bias:
    Baumgarte (37) on a penetration, C / h on a gap (speculative); with restitution (SI (39)-(41))
    the larger of that separation speed and e |v_n| for impacts faster than `slow` (m/s; v_n the
    normal speed before the solve). With contact compliance alpha > 0 the normal row is a spring
    of stiffness 1 / alpha. Friction: mu_d where the points were sliding at the start of the
    substep, mu_s where they stuck (DBD 7.1). impulses: (4 P,) of the previous substep (lambda_n,
    world friction impulse), kept where the slot is still active; returned as (3 P,) along the
    rows (n, t1, t2). Returns (ContactRows, impulses, dv (2, 3), dw (2, 3)).
    """
    pair = BodyPair.of(bodies)
    points = slots.active.shape[0]
    delta, arm_a, arm_b = row.anchor_points(pair, slots.local_a, slots.local_b, world[0], world[1], pair.quat_a,
                                            pair.quat_b)  # fmt: skip
    normal = slots.normal
    tangent = math.any_perpendicular(normal)
    directions = jnp.stack([normal, tangent, math.cross(normal, tangent)], axis=1)  # (P, 3, 3)
    angular_a = math.cross(arm_a[:, None, :], directions)
    angular_b = math.cross(arm_b[:, None, :], directions)
    inverse_mass, turn_a, turn_b = row.row_inverse_mass(pair, angular_a, angular_b, 1.0)  # (P, 3), SI (34)-(36)
    tangents = directions[:, 1:]
    tangent_coupling = (
        (pair.inv_mass_a + pair.inv_mass_b) * math.row_products(tangents, tangents)
        + math.row_products(angular_a[:, 1:], turn_a[:, 1:])
        + math.row_products(angular_b[:, 1:], turn_b[:, 1:])
    )
    separation = -math.dot(delta, normal)  # SI (25) at the start pose
    active = slots.active & (inverse_mass[:, 0] > 0.0)
    if compliance > 0.0:  # a spring of stiffness 1 / alpha, no damping
        softness, bias = spring_softness(1.0 / compliance, 0.0, separation, h)
        normal_rows = scalar_rows(pair, normal, angular_a[:, 0], angular_b[:, 0], bias, 0.0, jnp.inf, active, softness,
                                  True)  # fmt: skip
    else:
        bias = baumgarte_bias(separation, beta, h, True)
        normal_rows = scalar_rows(pair, normal, angular_a[:, 0], angular_b[:, 0], bias, 0.0, jnp.inf, active)
    bounce = slots.approach < -slow
    normal_bias = jnp.where(bounce, jnp.minimum(normal_rows.bias, slots.restitution * slots.approach), normal_rows.bias)
    friction = jnp.where(slots.sliding, slots.dynamic_friction, slots.friction)
    rows = ContactRows(directions, angular_a, angular_b, turn_a, turn_b, tangent_coupling, normal_rows.mass,
                       normal_rows.mix, normal_bias, friction, active)  # fmt: skip

    stored = jnp.where(active[:, None], impulses.reshape(points, CONTACT_IMPULSES_PER_POINT), 0.0)
    lam_n = jnp.maximum(stored[:, 0], 0.0)
    lam_t = jax.vmap(_clamp_disc)(math.sum_small(tangents * stored[:, None, 1:], axis=-1), friction * lam_n)
    lam = jnp.concatenate([lam_n[:, None], lam_t], axis=1)
    dv, dw = _warm(pair, [(Rows(directions, angular_a, angular_b, turn_a, turn_b, *(None,) * 5), lam.reshape(-1))])
    return rows, lam.reshape(-1), dv, dw


def store_contacts(rows: ContactRows, impulses: jnp.ndarray) -> jnp.ndarray:
    """(3 P,) impulses along (n, t1, t2) -> (4 P,) lambda_n and the world friction impulse."""
    lam = impulses.reshape(-1, 3)
    friction = math.sum_small(lam[:, 1:, None] * rows.directions[:, 1:], axis=1)
    return jnp.concatenate([lam[:, :1], friction], axis=1).reshape(-1)


def solve_contacts(rows: ContactRows, bodies: BodySet, impulses: jnp.ndarray):
    """One pass over a pair's points, each point's friction then its normal row (SI 2.1).

    Friction: the accumulated tangent impulse steps against the slip u with the effective mass
    along it, u.u / u.K u, and is held in the disc |lambda_t| <= mu lambda_n (SI (31)); a step
    along u rather than K^-1 u makes a sliding contact's friction oppose its slip exactly. Normal:
    the rigid (or soft) row update with lambda_n >= 0 (SI (42)).
    """
    pair = BodyPair.of(bodies)
    points = rows.active.shape[0]
    lam = impulses.reshape(points, 3)
    for i in range(points):  # P <= 8, static: each point sees the previous points' impulses
        slip = _relative_speed(pair, rows.directions[i, 1:], rows.angular_a[i, 1:], rows.angular_b[i, 1:])
        candidate = lam[i, 1:] - row.mass_along(slip, rows.tangent_coupling[i]) * slip
        candidate = _clamp_disc(candidate, rows.friction[i] * lam[i, 0])
        step = jnp.where(rows.active[i], candidate - lam[i, 1:], 0.0)
        pair = _push(pair, rows.directions[i, 1:], rows.turn_a[i, 1:], rows.turn_b[i, 1:], step)

        speed = _relative_speed(pair, rows.directions[i, 0], rows.angular_a[i, 0], rows.angular_b[i, 0])
        candidate = lam[i, 0] - rows.normal_mass[i] * (speed + rows.normal_bias[i]) - rows.normal_mix[i] * lam[i, 0]
        step_n = jnp.maximum(candidate, 0.0) - lam[i, 0]
        pair = _push(pair, rows.directions[i, :1], rows.turn_a[i, :1], rows.turn_b[i, :1], step_n[None])
        lam = lam.at[i].add(jnp.concatenate([step_n[None], step]))
    return *pair.displacements(), lam.reshape(-1)


# ------------------------------------------------------------------------------------ links


def prepare_link(link: Springs | Distances, world: np.ndarray, bodies: BodySet, impulses: jnp.ndarray, h: float,
                 beta: float, spring: bool):  # fmt: skip
    """One row along the line between the two anchor points, C = |p_b - p_a| - length: a spring-
    damper (DBD 8.1 as a soft row) or a rigid distance (Baumgarte, SI (17)). impulses: (1,)."""
    pair = BodyPair.of(bodies)
    direction, length, arm_a, arm_b = links.line(link.local_anchor_a, link.local_anchor_b, world, pair)
    along = -direction  # from p_a to p_b: C grows with (v_b - v_a) . along
    linear, angular_a, angular_b = along[None], math.cross(arm_a, along)[None], math.cross(arm_b, along)[None]
    if spring:
        softness, bias = spring_softness(link.stiffness, link.damping, length - link.rest_length, h)
        rows = scalar_rows(pair, linear, angular_a, angular_b, bias[None], -jnp.inf, jnp.inf, True, softness, True)
    else:
        bias = baumgarte_bias(length - link.length, beta, h)
        rows = scalar_rows(pair, linear, angular_a, angular_b, bias[None], -jnp.inf, jnp.inf, True)
    dv, dw = _warm(pair, [(rows, impulses)])
    return rows, impulses, dv, dw


def solve_link(rows: Rows, bodies: BodySet, impulses: jnp.ndarray):
    """One update of a link's row."""
    pair, impulses = solve_row(BodyPair.of(bodies), rows, 0, impulses)
    return *pair.displacements(), impulses


# ------------------------------------------------------------------------------ many bodies


class PointsRow(NamedTuple):
    """One row on the centres of mass of S bodies (a rope's length, a tetrahedron's volume):
    J v = sum_i gradient_i . v_i. gradient: (S, 3). mass: () 1 / K. bias: ()."""

    gradient: jnp.ndarray
    mass: jnp.ndarray
    bias: jnp.ndarray


def prepare_points(error_of: Callable, params, static, bodies: BodySet, impulses: jnp.ndarray, h: float, beta: float):
    """The rigid row of an S-body error (DBD 10, multibody.rope_error / volume_error) at the start
    pose: K = sum_i |g_i|^2 / m_i, Baumgarte bias (SI (17)), warm start. impulses: (1,)."""
    gradient, error = error_of(params, static, bodies)
    inverse_mass = jnp.sum(bodies.inv_mass * math.dot(gradient, gradient))
    solvable = inverse_mass > 0.0
    mass = jnp.where(solvable, 1.0 / jnp.where(solvable, inverse_mass, 1.0), 0.0)
    dv = (bodies.inv_mass * impulses[0])[:, None] * gradient
    return PointsRow(gradient, mass, baumgarte_bias(error, beta, h)), impulses, dv, jnp.zeros_like(dv)


def solve_points(rows: PointsRow, static, bodies: BodySet, impulses: jnp.ndarray):
    """One update of an S-body row: d lambda = -(J v + b) / K, dv_i = g_i d lambda / m_i."""
    speed = jnp.sum(math.dot(rows.gradient, bodies.vel + bodies.dx))
    step = -rows.mass * (speed + rows.bias)
    dv = bodies.dx + (bodies.inv_mass * step)[:, None] * rows.gradient
    return dv, bodies.dtheta, impulses + step


# ------------------------------------------------------------------------------------ families


class VelocityFamily(NamedTuple):
    """One constraint family for the impulse solver, in the order of `Structure.family_bodies`.

    bodies: (M, S) int. params, static: as `constraints.Family`. prepare(params, static, bodies,
    impulses) -> (rows, impulses, dv (S, 3), dw (S, 3)) for one node at the start of the substep.
    solve(rows, static, bodies, impulses) -> (dv (S, 3), dw (S, 3), impulses): one pass, in the
    shape of `constraints.Family.project` (the solver vmaps both). num_impulses: per node, as kept
    in State.impulses. store(rows, impulses) -> what is kept of a solve's impulses, None for all.
    variants: ((nodes, solve), ...) as `constraints.Family.variants` (the joints by kind: each
    kind's pass traces only its own rows; the rows it leaves out are inactive for its joints).
    """

    name: str
    bodies: np.ndarray
    params: Any
    static: Any
    prepare: Callable
    solve: Callable
    num_impulses: int
    store: Callable | None = None
    variants: tuple = ()


def _nothing_to_prepare(params, static, bodies: BodySet, impulses):
    zero = jnp.zeros_like(bodies.dx)
    return None, impulses, zero, zero


def _nothing_to_solve(rows, static, bodies: BodySet, impulses):
    return bodies.dx, bodies.dtheta, impulses


def families(model: Model, control: jnp.ndarray | None, contacts: tuple[ContactSlots, ...], h: float, dtype,
             start: State) -> list[VelocityFamily]:  # fmt: skip
    """Every constraint family of `model` as velocity rows, with this substep's control and contact
    slots; start: the state at the start of the substep (its velocities set the joints' rotor
    speeds). User forces have no rows here (the impulse solver applies them before the solve, SI
    (12)); their entries keep the family order."""
    structure, options = model.structure, model.options
    tables = structure.family_bodies()
    world = structure.num_bodies
    beta = options.baumgarte
    used = joints.rows_in_use(structure)
    gear = None if model.torques is None else model.torques.gear  # torques acting through rotor rows
    targets = joints.targets(structure, control, dtype, gear)
    vel, ang_vel = with_world_row(jnp.asarray(start.vel, dtype)), with_world_row(jnp.asarray(start.ang_vel, dtype))
    a, b = structure.joint_body_a.array, structure.joint_body_b.array
    start_speeds = jnp.stack([vel[a], vel[b], ang_vel[a], ang_vel[b]], axis=1)  # (J, 4, 3)

    def on_world(table: np.ndarray) -> np.ndarray:
        return table == world

    def link_family(name, table, params, spring):
        prepare = functools.partial(prepare_link, h=h, beta=beta, spring=spring)
        return VelocityFamily(name, table, params, on_world(table), prepare,
                              lambda r, _, bodies, lam: solve_link(r, bodies, lam), 1)  # fmt: skip

    def nothing(name, table):
        return VelocityFamily(name, table, None, None, _nothing_to_prepare, _nothing_to_solve, 0)

    result = [
        VelocityFamily(
            "joints", tables[0], (model.joints, targets, start_speeds), joints.flags(structure),
            lambda p, flag, bodies, lam: prepare_joint(p[0], flag, p[1], p[2], BodyPair.of(bodies), lam, h, used),
            functools.partial(_solve_kind, rows=used), JOINT_IMPULSES,
            variants=tuple((members, functools.partial(_solve_kind, rows=rows))
                           for members, rows in joints.variants(structure)),
        ),
        link_family("springs", tables[1], model.springs, spring=True),
        link_family("distances", tables[2], model.distances, spring=False),
        VelocityFamily("ropes", tables[3], model.ropes, ~on_world(tables[3]),
                       functools.partial(prepare_points, multibody.rope_error, h=h, beta=beta), solve_points, 1),
        VelocityFamily("volumes", tables[4], model.volumes, np.zeros(len(tables[4]), bool),
                       functools.partial(prepare_points, lambda p, _, bodies: multibody.volume_error(p, bodies), h=h,
                                         beta=beta), solve_points, 1),
    ]  # fmt: skip
    force_tables = tables[5 : 5 + len(structure.force_groups)]
    result += [nothing(group.name, table) for group, table in zip(structure.force_groups, force_tables, strict=True)]
    result.append(nothing("ik_targets", tables[5 + len(structure.force_groups)]))  # refused at finalize
    slow = 2.0 * math.safe_norm(model.gravity) * h  # as the DBD restitution pass: slower impacts do not bounce
    for group, slots in zip(structure.contact_groups, contacts, strict=True):
        prepare = functools.partial(prepare_contacts, h=h, beta=beta, compliance=options.contact_compliance, slow=slow)
        result.append(VelocityFamily(group.name, group.bodies.array, slots, on_world(group.bodies.array), prepare,
                                     lambda r, _, bodies, lam: solve_contacts(r, bodies, lam),
                                     CONTACT_IMPULSES_PER_POINT * group.num_points, store_contacts))  # fmt: skip
    return result
