"""The scalar constraint row updates every constraint family is built from.

A row is one scalar position error c(X* + dX) with a Jacobian of one of two shapes:
  positional: J = (n, arm_a x n, -n, -arm_b x n)   (DBD (55), (85); SI (69))
  angular:    J = (0, d, 0, -d)                     (DBD (74); SI (109))
and w = J M~^-1 J^T its effective inverse mass ((51), (57), (76)). A row is solved for its
multiplier lambda (the integrated impulse times h, DBD's lambda dt^2: kg m for positional rows,
kg m^2 for angular ones) and moves the bodies by dX += M~^-1 J^T d lambda (52). Three rules:

  rigid   d lambda = -xi (c + alpha lambda) / (w + alpha)            DBD (45)-(52)
          converges to the regularised c + alpha lambda = 0 (49); inequality rows (limits,
          DBD 6.1) only push: d lambda >= 0 as in (83).
  spring  lambda = h^2 f with f = -k c - nu c_dot, implicit (DBD 8, (94)-(99), 8.1):
          d lambda = -xi (lambda + k h^2 c + nu h drift) / (1 + (k h^2 + nu h) w)
          where drift = J (h V* + dX) = h c_dot is how far the row moved this substep.
          Written at X* + dX this is (105); written at the start of the substep, where
          c(X*) = c(X^t) + J h V*, the velocity term gains the "1 +" of (108)-(109) that XPBD's
          gamma lacks. The clamp |lambda| <= bound h^2 is the torque limit (114).
  speed   a motor: drift = target speed h, with |lambda| <= max force h^2 (SI 2.3.6, 2.4.6).
  soft limit  a one-sided limit row that is rigid, or (where the joint's limits are soft) the
          spring rule with k = omega^2 / w and nu = 2 zeta omega / w: a spring and damper per unit
          of the row's effective mass, MuJoCo's solref (timeconst, dampratio) with omega =
          1 / (timeconst dampratio); it pushes only while c < 0 (`soft_limit`).

A joint's point constraint is not a row but a block of three: the vector error c = p_a - p_b
(DBD (64)) with J = (1, -[arm_a]x, -1, [arm_b]x) (65), solved at once with the 3x3 effective
inverse mass K = (1/m_a + 1/m_b) 1 - [arm_a]x I_a^-1 [arm_a]x - [arm_b]x I_b^-1 [arm_b]x ((57),
(66)) by the rigid rule in matrix form, d lambda = -xi (K + alpha 1)^-1 (c + alpha lambda), with
a 3-vector lambda (`point_block`). Unlike the magnitude form |c| (54) it is linear in c, so the
update is smooth where the joint is closed, and one projection closes a small gap in every
direction, not only along it.

The angular rows of a joint (drive, motor, limits, cone, rotor) move the pair with the joint's
point held (`PointHold`): each step of such a row comes with the point impulse -K^-1 s that
closes the gap s it would open between the two joint points (to first order), so the row turns
the bodies about the joint instead of about their centres. Without it a row on a body whose
own inertia is small against its mass times the lever arm squared (a hand, a foot, a thin arm
on its pivot) turns that body about its centre by far more than the joint turns, the point
block turns it back, and the fixed point the sweeps reach depends on that detour: a drive on a
0.5 m arm with I = 1e-3 kg m^2 applied 1.5 times its torque per step at dt = 1/240, and the
answer depended on the initial guess. The step length stays the row's own, from w: the exact
response with the point held, the Schur complement w - s^T K^-1 s, takes longer steps that made
the sweeps of the 2 x 8 standing ragdoll oscillate until it fell (after 5 s).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from dbdjax import integrator, math


class BodyPair(NamedTuple):
    """The two bodies one constraint moves, as the solver sees them (one slot, no batch axis).

    origin_*: (3,) predicted centre of mass X*. quat_*: (4,) predicted orientation.
    inv_mass_*: () 1/kg (0 for the world). inv_inertia_*: (3, 3) world frame (0 for the world).
    vel_*, ang_vel_*: (3,) predicted velocities V* (so that X* - X^t = h V*).
    motion: (4, 3) what the pair moved so far this substep, rows dx_a, dx_b, dtheta_a, dtheta_b
    (displacements and rotations; read them by name). One array, not four: on XLA:CPU every
    array a row writes is a kernel of its own, so a row that moves the pair writes one.
    """

    origin_a: jnp.ndarray
    origin_b: jnp.ndarray
    quat_a: jnp.ndarray
    quat_b: jnp.ndarray
    inv_mass_a: jnp.ndarray
    inv_mass_b: jnp.ndarray
    inv_inertia_a: jnp.ndarray
    inv_inertia_b: jnp.ndarray
    vel_a: jnp.ndarray
    vel_b: jnp.ndarray
    ang_vel_a: jnp.ndarray
    ang_vel_b: jnp.ndarray
    motion: jnp.ndarray

    dx_a = property(lambda self: self.motion[..., 0, :])
    dx_b = property(lambda self: self.motion[..., 1, :])
    dtheta_a = property(lambda self: self.motion[..., 2, :])
    dtheta_b = property(lambda self: self.motion[..., 3, :])

    @classmethod
    def of(cls, bodies: BodySet) -> BodyPair:
        """The pair view of a two-body `BodySet` (side a is row 0, side b row 1)."""
        fixed = [name for name in BodySet._fields if name not in ("dx", "dtheta")]
        fields = [getattr(bodies, name)[i] for name in fixed for i in (0, 1)]
        return cls(*fields, jnp.concatenate([bodies.dx, bodies.dtheta]))

    def moved_by(self, dx_a=0.0, dx_b=0.0, dtheta_a=0.0, dtheta_b=0.0) -> BodyPair:
        """The pair moved further by dx_a, dx_b (m) and dtheta_a, dtheta_b (rad), each (3,) or 0."""
        shape, dtype = self.motion.shape[:-2] + (3,), self.motion.dtype
        change = [jnp.broadcast_to(jnp.asarray(v, dtype), shape) for v in (dx_a, dx_b, dtheta_a, dtheta_b)]
        return self._replace(motion=self.motion + jnp.stack(change, axis=-2))

    def displacements(self) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(dx (2, 3), dtheta (2, 3)): the pair's displacements in `BodySet` row order."""
        return self.motion[..., :2, :], self.motion[..., 2:, :]

    def current_quats(self) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Orientations at X* + dX (what the non-linear update of DBD 4.1 evaluates at)."""
        # Both sides as one (2, 4) computation, as `rotate_pair`.
        quats = jnp.stack([self.quat_a, self.quat_b])
        both = integrator.displaced_quat(quats, self.motion[..., 2:, :], renormalise=False)
        return both[0], both[1]


def rotate_pair(quat_a, quat_b, vector_a, vector_b) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(quat_rotate(quat_a, vector_a), quat_rotate(quat_b, vector_b)) as one stacked computation.

    The same arithmetic per element in fewer compiled kernels: the solver's sweeps are a long
    chain of tiny operations, and on CPU each kernel costs more than its arithmetic. (Measured on
    the humanoid's joint projection: stacking the two sides' orientations and rotations cut its
    kernels by a quarter; stacking the inertia products or point responses did not help.)"""
    lead = jnp.broadcast_shapes(*(jnp.shape(x)[:-1] for x in (quat_a, quat_b, vector_a, vector_b)))
    quats = jnp.stack([jnp.broadcast_to(q, lead + (4,)) for q in (quat_a, quat_b)])
    vectors = jnp.stack([jnp.broadcast_to(v, lead + (3,)) for v in (vector_a, vector_b)])
    both = math.quat_rotate(quats, vectors)
    return both[0], both[1]


def anchor_points(pair: BodyPair, local_anchor_a, local_anchor_b, world_a, world_b, quat_a, quat_b):
    """A point fixed on each body at X* + dX: (delta = p_a - p_b, arm_a, arm_b).

    local_anchor_*: (3,) in the body frames (world coordinates for the world side, flagged by the
    bool world_*). quat_*: the bodies' current orientations. delta is summed from differences of
    like terms, never from large absolute positions, so a constraint 10 km from the origin is
    solved as precisely as one at the origin. For the world side the anchor itself is the origin
    and the arm is zero.
    """
    arm_a, arm_b = rotate_pair(quat_a, quat_b, local_anchor_a, local_anchor_b)
    origin_a = pair.origin_a + jnp.where(world_a, arm_a, 0.0)
    origin_b = pair.origin_b + jnp.where(world_b, arm_b, 0.0)
    arm_a = jnp.where(world_a, 0.0, arm_a)
    arm_b = jnp.where(world_b, 0.0, arm_b)
    delta = (origin_a - origin_b) + (pair.dx_a - pair.dx_b) + (arm_a - arm_b)
    return delta, arm_a, arm_b


class BodySet(NamedTuple):
    """The S bodies one constraint node moves (S = 2 for joints, 4 for a tetrahedron, ...).

    Fields as in `BodyPair`, stacked on a leading axis of S rows.
    """

    origin: jnp.ndarray  # (S, 3)
    quat: jnp.ndarray  # (S, 4)
    inv_mass: jnp.ndarray  # (S,)
    inv_inertia: jnp.ndarray  # (S, 3, 3)
    vel: jnp.ndarray  # (S, 3)
    ang_vel: jnp.ndarray  # (S, 3)
    dx: jnp.ndarray  # (S, 3)
    dtheta: jnp.ndarray  # (S, 3)


class Rule(NamedTuple):
    """How a row's multiplier is updated (see the module docstring); all fields are () arrays.

    relaxation xi, regularization alpha, active (bool). inequality (bool): rigid rows only push.
    stiffness_h2 = k h^2 and damping_h = nu h for springs (both 0 for a rigid row; `spring`
    switches to the spring rule). bound: |lambda| <= bound (inf for none). speed_h: a motor's
    target drift (target speed times h); `speed` switches to the motor rule. `soft` switches to
    the limit rule of `soft_limit`, a spring per unit effective mass where `softened`; `armature`
    is the rotor inertia on its coordinate, part of that mass.
    """

    relaxation: jnp.ndarray
    regularization: jnp.ndarray
    active: jnp.ndarray
    inequality: bool | jnp.ndarray = False
    spring: bool = False
    stiffness_h2: jnp.ndarray | float = 0.0
    damping_h: jnp.ndarray | float = 0.0
    speed: bool = False
    speed_h: jnp.ndarray | float = 0.0
    bound: jnp.ndarray | float = jnp.inf
    soft: bool = False
    softened: jnp.ndarray | bool = False
    armature: jnp.ndarray | float = 0.0


def rigid(relaxation, regularization, active, inequality=False) -> Rule:
    """A hard row: joints, limits, distance constraints."""
    return Rule(relaxation, regularization, active, inequality)


def spring(relaxation, active, stiffness_h2, damping_h, bound=jnp.inf) -> Rule:
    """An implicit spring/damper row (DBD 8.1, 9): stiffness k h^2, damping nu h, |lambda| <= bound."""
    return Rule(relaxation, 0.0, active, spring=True, stiffness_h2=stiffness_h2, damping_h=damping_h, bound=bound)


def soft_limit(relaxation, regularization, active, softened, stiffness_h2, damping_h, armature=0.0) -> Rule:
    """A one-sided limit row: where `softened` ((), bool) is False the rigid inequality rule, else
    an implicit spring and damper per unit of the row's effective mass, stiffness_h2 = omega^2 h^2
    and damping_h = 2 zeta omega h (`Joints.limit_stiffness` and `limit_damping` times h^2 and h).
    armature: the rotor inertia on the row's coordinate (`Joints.armature`), which that mass
    includes, as MuJoCo's joint-space mass does (the rotor row carries its inertia separately)."""
    return Rule(relaxation, regularization, active, True, False, stiffness_h2, damping_h, soft=True, softened=softened,
                armature=armature)  # fmt: skip


def motor(relaxation, active, speed_h, bound) -> Rule:
    """A velocity row: drift -> speed_h with |lambda| <= bound (SI 2.3.6, 2.4.6)."""
    return Rule(relaxation, 0.0, active, speed=True, speed_h=speed_h, bound=bound)


def spring_compliance(stiffness_h2, damping_h, error, drift):
    """An implicit spring and damper row (DBD 8.1, 9) in the compliance form of DBD (49), as a
    direct solve takes it: (J M~^-1 J^T + alpha) d lambda = -(r + alpha lambda) with
    alpha = 1 / (k h^2 + nu h) and r = (k h^2 c + nu h drift) alpha, the same step as the `spring`
    rule's. Returns (r, alpha, on), on where k h^2 + nu h > 0 (elsewhere r = c, alpha = 1)."""
    total = stiffness_h2 + damping_h
    on = total > 0.0
    alpha = 1.0 / jnp.where(on, total, 1.0)
    return jnp.where(on, (stiffness_h2 * error + damping_h * drift) * alpha, error), alpha, on


def relative_turn(pair: BodyPair, h: float) -> jnp.ndarray:
    """(3,) h (w_b - w_a) + (dtheta_b - dtheta_a): the turn of b against a that an angular row's
    drift J (h V* + dX) reads (J = (0, d) on b, (0, -d) on a: drift = d . this)."""
    return h * (pair.ang_vel_b - pair.ang_vel_a) + (pair.dtheta_b - pair.dtheta_a)


def relative_point_motion(pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray, h: float) -> jnp.ndarray:
    """(..., 3) h (v_b + w_b x r_b - v_a - w_a x r_a) + (dx_b + dtheta_b x r_b - dx_a - dtheta_a x r_a):
    how far the points at arm_a on a and arm_b on b move apart over h at V* and by dX, as
    `relative_turn` for their turn (h = 1 in a velocity pass: their relative velocity; h = 0: the
    part of dX alone). arm_a, arm_b: (..., 3) m, one pair of points or P of them."""
    moved_a = pair.dx_a + math.cross(pair.dtheta_a, arm_a) + h * (pair.vel_a + math.cross(pair.ang_vel_a, arm_a))
    moved_b = pair.dx_b + math.cross(pair.dtheta_b, arm_b) + h * (pair.vel_b + math.cross(pair.ang_vel_b, arm_b))
    return moved_b - moved_a


def soft_limit_scale(armature, inverse_mass):
    """m w = 1 + armature w: the soft limit's effective mass m = 1 / w + armature (the rotor's
    inertia on the row's coordinate included, as MuJoCo's joint-space mass) in units of 1 / w, the
    factor on its spring and damper per unit of the bodies' response w (`soft_limit`)."""
    return 1.0 + armature * inverse_mass


def multiplier_step(rule: Rule, error, drift, inverse_mass, multiplier):
    """d lambda of one row under `rule`; 0 where the row is inactive or cannot move anything.

    error: c at X* + dX. drift: J (h V* + dX) (only the spring and motor rules read it).
    inverse_mass: w = J M~^-1 J^T. multiplier: lambda so far this substep.
    """
    if rule.soft:  # a limit: rigid, or where softened the spring rule with k = omega^2 m, nu = 2 zeta omega m
        # per unit of the effective mass m = 1 / w + armature: omega^2 h^2 and 2 zeta omega h times m w.
        per_mass = soft_limit_scale(rule.armature, inverse_mass)
        stiffness_h2, damping_h = rule.stiffness_h2 * per_mass, rule.damping_h * per_mass
        share = 1.0 / (1.0 + stiffness_h2 + damping_h)
        error_weight = jnp.where(rule.softened, stiffness_h2 * share, 1.0)
        drift_weight = jnp.where(rule.softened, damping_h * share, 0.0)
        multiplier_weight = jnp.where(rule.softened, share * inverse_mass, 0.0)
        denominator = inverse_mass + error_weight * rule.regularization
        residual = (multiplier_weight * multiplier + error_weight * (error + rule.regularization * multiplier)
                    + drift_weight * drift)  # fmt: skip
        solvable = rule.active & (denominator > 0.0)
        step = -rule.relaxation * residual / jnp.where(solvable, denominator, 1.0)
        # Rigid: the increments only push, DBD (83). Soft: the spring only pushes, and lets go
        # where the row is not past its bound (MuJoCo's limit is active only there).
        pushed = jnp.where(error < 0.0, jnp.maximum(multiplier + step, 0.0), 0.0)
        step = jnp.where(rule.softened, pushed - multiplier, jnp.maximum(step, 0.0))
        return jnp.where(solvable, step, 0.0)
    if rule.spring:
        compliance = rule.stiffness_h2 + rule.damping_h
        denominator = 1.0 + compliance * inverse_mass
        residual = multiplier + rule.stiffness_h2 * error + rule.damping_h * drift
        solvable = rule.active & (inverse_mass > 0.0)
    elif rule.speed:
        denominator = inverse_mass
        residual = drift - rule.speed_h
        solvable = rule.active & (inverse_mass > 0.0)
    else:
        denominator = inverse_mass + rule.regularization
        residual = error + rule.regularization * multiplier
        solvable = rule.active & (denominator > 0.0)
    step = -rule.relaxation * residual / jnp.where(solvable, denominator, 1.0)
    step = jnp.where(rule.inequality, jnp.maximum(step, 0.0), step)
    step = jnp.clip(multiplier + step, -rule.bound, rule.bound) - multiplier
    return jnp.where(solvable, step, 0.0)


def mass_along(vector: jnp.ndarray, inverse_mass: jnp.ndarray) -> jnp.ndarray:
    """1 / (u . W u), u the unit direction of `vector` (2,) and W (2, 2) an inverse mass: the
    effective mass a friction step along the slip uses (DBD (90)-(92), SI (31)); 0 where the
    vector or W u vanishes. Written with the unit direction because |s|^2 / (s . W s), equal in
    value, has a gradient that divides by (s . W s)^2, which underflows in float32 as s -> 0
    (a capsule lying still on the floor gave NaN gradients)."""
    unit, _ = math.safe_normalize(jnp.concatenate([vector, jnp.zeros(1, vector.dtype)]))
    along = unit[:2] @ (inverse_mass @ unit[:2])
    ok = along > 0.0
    return jnp.where(ok, 1.0 / jnp.where(ok, along, 1.0), 0.0)


def row_inverse_mass(pair: BodyPair, angular_a, angular_b, linear_squared=None):
    """w = J M~^-1 J^T of one row (DBD (51), (57); SI (34), (113)): (w, I_a^-1 angular_a, I_b^-1 angular_b).

    angular_a, angular_b: (..., 3) the row's angular parts on a and b (arm x direction for a
    positional row, the direction itself for an angular one). linear_squared: |linear part|^2 (1
    for a unit direction), None for an angular row (no linear part). Broadcasts over leading axes.
    """
    turn_a = math.matvec(pair.inv_inertia_a, angular_a)
    turn_b = math.matvec(pair.inv_inertia_b, angular_b)
    if linear_squared is None:
        return math.dot(angular_a, turn_a) + math.dot(angular_b, turn_b), turn_a, turn_b
    inverse_mass = linear_squared * (pair.inv_mass_a + pair.inv_mass_b) + math.dot(angular_a, turn_a)
    return inverse_mass + math.dot(angular_b, turn_b), turn_a, turn_b


def positional_row(
    pair: BodyPair,
    direction: jnp.ndarray,
    arm_a: jnp.ndarray,
    arm_b: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    rule: Rule,
    h: float = 1.0,
) -> tuple[BodyPair, jnp.ndarray]:
    """Project one positional row: error c along unit `direction` (dc/dx_a), applied at arm_a
    from a's centre and arm_b from b's. h: the substep (read by the spring and motor rules).
    Returns the moved pair and the new multiplier."""
    torque_a = math.cross(arm_a, direction)
    torque_b = math.cross(arm_b, direction)
    inverse_mass, turn_a, turn_b = row_inverse_mass(pair, torque_a, torque_b, 1.0)  # (57) along the direction, (56)
    drift = 0.0
    if rule.spring or rule.speed or rule.soft:
        drift = (
            math.dot(direction, h * (pair.vel_a - pair.vel_b) + (pair.dx_a - pair.dx_b))
            + math.dot(torque_a, h * pair.ang_vel_a + pair.dtheta_a)
            - math.dot(torque_b, h * pair.ang_vel_b + pair.dtheta_b)
        )
    step = multiplier_step(rule, error, drift, inverse_mass, multiplier)
    moved = pair.moved_by(
        dx_a=(pair.inv_mass_a * step) * direction,
        dx_b=-(pair.inv_mass_b * step) * direction,
        dtheta_a=step * turn_a,
        dtheta_b=-step * turn_b,
    )
    return moved, multiplier + step


class PointHold(NamedTuple):
    """A joint's point constraint, held while its angular rows move the pair (module docstring).

    arm_a, arm_b: (3,) the joint point from each centre (m). solve: (3, 3) K^-1, the inverse of
    the point block's effective inverse mass (zero where nothing is held: a slider, a planar
    joint, two static bodies). impulse: (3,) kg m, the point impulse the held rows have applied
    so far this substep (it joins the point block's multiplier). gap: (3,) m, p_a - p_b where the
    hold was taken; held rows leave it unchanged to first order, so it stands for the gap while
    they act (the held step's slope, `angular_row`).
    """

    arm_a: jnp.ndarray
    arm_b: jnp.ndarray
    solve: jnp.ndarray
    impulse: jnp.ndarray
    gap: jnp.ndarray


def point_hold(
    pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray, gap: jnp.ndarray, active: jnp.ndarray
) -> PointHold:
    """Hold the point at arm_a on a and arm_b on b together while angular rows act (`active`:
    () bool, False for joints whose point block is not a full 3-D one). gap: (3,) m, p_a - p_b
    where the hold starts (held rows keep it, to first order)."""
    solve, _ = definite_inverse(point_inverse_mass(pair, arm_a, arm_b), active)
    return PointHold(arm_a, arm_b, solve, jnp.zeros_like(arm_a), gap)


def point_impulses(hold: PointHold, turn_a: jnp.ndarray, turn_b: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(the point impulse (3,) kg m, the gap s (3,) m) for a turn of a by turn_a and of b by
    -turn_b: s = turn_a x arm_a + turn_b x arm_b opens between the joint points, -K^-1 s closes it."""
    gap = math.cross(turn_a, hold.arm_a) + math.cross(turn_b, hold.arm_b)
    return -math.matvec(hold.solve, gap), gap


def held_inverse_mass(inverse_mass, turn_a, turn_b, hold: PointHold) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(the held response w - s^T K^-1 s, the point impulse mu = -K^-1 s per unit step) of an
    angular row whose response is w = `row_inverse_mass` (turn_a, turn_b its turns) with the joint's
    point held: the Schur complement, >= 0 up to rounding (K^-1 is of a positive definite K)."""
    point_impulse, gap = point_impulses(hold, turn_a, turn_b)
    return jnp.maximum(inverse_mass + math.dot(gap, point_impulse), 0.0), point_impulse


class AngularResponse(NamedTuple):
    """What a unit step of an angular row along `direction` d does, with the joint's point held or
    not (`angular_response`): its response w = d . (I_a^-1 + I_b^-1) d (`row_inverse_mass`), the
    held response w - s^T K^-1 s and its point impulse mu = -K^-1 s (`held_inverse_mass`; w and 0
    with no hold), and how it moves the pair (`BodyPair.motion` (..., 4, 3): the turns +-I^-1 d
    and, held, mu's push at the point). They read only the inertias at X* and the hold's arms,
    both fixed through a joint's projection: rows along one direction (a hinge angle's rotor,
    drive and limit) share them, and a row along -d takes them with its sign (`times`)."""

    inverse_mass: jnp.ndarray
    held_mass: jnp.ndarray
    point_impulse: jnp.ndarray
    motion: jnp.ndarray

    def times(self, sign) -> AngularResponse:
        """The response along sign * d (sign: +-1)."""
        return self._replace(point_impulse=sign * self.point_impulse, motion=sign * self.motion)


def angular_response(pair: BodyPair, direction: jnp.ndarray, hold: PointHold | None) -> AngularResponse:
    """The `AngularResponse` of rows along `direction` (..., 3) (leading axes: several directions
    at once) with the point of `hold` held (None: nothing held)."""
    inverse_mass, turn_a, turn_b = row_inverse_mass(pair, direction, direction)  # (76)
    zero = jnp.zeros_like(turn_a)
    turned = jnp.stack([zero, zero, turn_a, -turn_b], axis=-2)  # as `BodyPair.motion`
    if hold is None:
        return AngularResponse(inverse_mass, inverse_mass, zero, turned)
    held_mass, point_impulse = held_inverse_mass(inverse_mass, turn_a, turn_b, hold)
    pushed = point_impulse_motion(pair, hold.arm_a, hold.arm_b, point_impulse)
    return AngularResponse(inverse_mass, held_mass, point_impulse, pushed + turned)


def angular_row(
    pair: BodyPair,
    direction: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    rule: Rule,
    h: float = 1.0,
    hold: PointHold | None = None,
    held_step: bool = False,
    response: AngularResponse | None = None,
) -> tuple[BodyPair, jnp.ndarray, PointHold | None]:
    """Project one angular row: error c (rad) with dc/dtheta_a = `direction` = -dc/dtheta_b.

    hold: the joint's point, held while the row acts (module docstring), or None. held_step: the
    step length from the held response w - s^T K^-1 s instead of w (a rotor row: see
    `joints.project`), and the step is then the exact minimiser along the held direction: the
    row together with its point impulse mu = -K^-1 s per unit step is one direction in the
    multipliers of (row, point), and the slope there is c + mu . g, g the point's own gap. Without
    mu . g a row that acts while the point is still open (the first sweep of a substep, the point
    projected last) steps as if it were closed, and the point block then undoes part of the turn:
    a rotor of armature 40-120x its joint's inertia (Brax's ant) fed energy in that way, 6.7 J ->
    2,352 J in 20 steps at 4 substeps x 4 iterations. held_step may also be a () bool array, per
    joint (soft limits: `joints.project`). response: `angular_response(pair, direction, hold)`
    computed beforehand (rows along one direction share it), or None to compute it here. Returns
    the moved pair, the new multiplier and the hold with the point impulse it added.
    """
    if response is None:
        response = angular_response(pair, direction, hold)
    inverse_mass = response.inverse_mass
    if hold is not None and held_step is not False:  # True, or per joint (soft limits)
        inverse_mass = jnp.where(held_step, response.held_mass, inverse_mass)
        error = jnp.where(held_step, error + math.dot(response.point_impulse, hold.gap), error)  # the held slope
    drift = 0.0
    if rule.spring or rule.speed or rule.soft:
        drift = -math.dot(direction, relative_turn(pair, h))  # direction is dc/dtheta_a = -d
    step = multiplier_step(rule, error, drift, inverse_mass, multiplier)
    moved = pair._replace(motion=pair.motion + step * response.motion)
    if hold is not None:
        hold = hold._replace(impulse=hold.impulse + step * response.point_impulse)
    return moved, multiplier + step, hold


def spring_row_beside_rotor(
    pair: BodyPair,
    direction: jnp.ndarray,
    error: jnp.ndarray,
    multipliers: tuple[jnp.ndarray, jnp.ndarray],
    armature: jnp.ndarray,
    rotor_active: jnp.ndarray,
    rule: Rule,
    h: float,
    hold: PointHold,
    response: AngularResponse,
) -> tuple[BodyPair, jnp.ndarray, jnp.ndarray, PointHold]:
    """Project a spring row (`rule`: a `spring`, its bound included; error c, dc/dtheta_a =
    `direction`) on a coordinate whose rotor row (k h^2 = armature, `angular_row`'s held step)
    has just been projected: the two as one block, the rotor's residual left at zero.

    The rotor row, undamped, has residual lambda_r + armature (c_r + slope); per unit of a step S
    of the bodies along the row it moves by K_r w (K_r = armature, w the held response), and the
    spring's r_s = lambda_s + k h^2 (c + slope) + nu h drift by K_s w (K_s = k h^2 + nu h). From
    r_r = 0 the block of both moves the bodies by S = -r_s / (1 + (K_r + K_s) w), of which the
    spring's multiplier takes step_s = (1 + K_r w) S and the rotor's the rest, -K_r w S. That is
    the spring row of `angular_row` (DBD 8.1) with the rotor relaxed along: response
    w / (1 + K_r w) (the Schur complement of the rotor row) and the bodies moved by
    step_s / (1 + K_r w); its bound clamps step_s and S follows. Without a rotor (rotor_active
    False) this is the spring row of `angular_row` (plain response, no slope).

    Why: stepped as two rows, a spring (a hinge's joint damping) on a light body with a heavy
    rotor converged in tens of iterations: the damping stopped the light body, the rotor row
    pushed it back, a little less each time. Brax's ant (damping 1, armature 1 kg m^2, legs of
    about 1/300 of that) in the air drifted 0.11 rad from MuJoCo in 0.1 s at 4 iterations.

    multipliers: (lambda_rotor, lambda_spring) so far. response: `angular_response` along
    `direction` with `hold`. Returns (moved pair, lambda_rotor, lambda_spring, hold).
    """
    inverse_mass = jnp.where(rotor_active, response.held_mass, response.inverse_mass)
    slope = jnp.where(rotor_active, math.dot(response.point_impulse, hold.gap), 0.0)  # `angular_row`'s held slope
    rotor_share = 1.0 + jnp.where(rotor_active, armature, 0.0) * inverse_mass  # 1 + K_r w
    drift = -math.dot(direction, relative_turn(pair, h))  # direction is dc/dtheta_a = -d
    spring_step = multiplier_step(rule, error + slope, drift, inverse_mass / rotor_share, multipliers[1])
    step = spring_step / rotor_share  # the bodies' step S
    moved = pair._replace(motion=pair.motion + step * response.motion)
    hold = hold._replace(impulse=hold.impulse + step * response.point_impulse)
    return moved, multipliers[0] + step - spring_step, multipliers[1] + spring_step, hold


def angular_spring(
    pair: BodyPair,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    relaxation: jnp.ndarray,
    stiffness_h2: jnp.ndarray,
    damping_h: jnp.ndarray,
    bound: jnp.ndarray,
    active: jnp.ndarray,
    h: float,
    hold: PointHold | None = None,
    held_step: bool = False,
) -> tuple[BodyPair, jnp.ndarray, PointHold | None]:
    """A three-axis angular spring/damper with a torque limit, DBD (110)-(114).

    error: (3,) world rotation vector of b away from its target relative to a (dc/dtheta_b = 1,
    dc/dtheta_a = -1). multiplier: (3,) kappa so far (the torque on b times h^2). The update is
    the matrix form of the spring rule with the effective inverse inertia W = I_a^-1 + I_b^-1
    (113): d kappa = -xi (1 + (k h^2 + nu h) W)^-1 (kappa + k h^2 c + nu h drift) (112); then
    |kappa| <= bound = tau_max h^2 (114). hold: the joint's point, held as in `angular_row`;
    held_step: W - G^T K^-1 G in (112), the response with the point held (G kappa: the gap a
    step kappa opens at the joint point, G = [arm_a]x I_a^-1 + [arm_b]x I_b^-1), and the error
    c - G^T K^-1 g with the point's open gap g, as in `angular_row`.
    Returns the moved pair, the new kappa and the hold.
    """
    inverse_inertia, slope = angular_spring_response(pair, hold if held_step else None)
    step = _spring_torque_step(
        multiplier, error + slope, relative_turn(pair, h), inverse_inertia, relaxation, stiffness_h2, damping_h,
        bound, active,
    )  # fmt: skip
    moved, hold = _turned_by_torque(pair, hold, step)
    return moved, multiplier + step, hold


def _spring_torque_step(multiplier, error, drift, inverse_inertia, relaxation, stiffness_h2, damping_h, bound, active):
    """(3,) d kappa of a three-axis spring/damper with response W = `inverse_inertia` (3, 3):
    -xi (1 + (k h^2 + nu h) W)^-1 (kappa + k h^2 c + nu h drift) (112), then |kappa| <= bound
    (114); 0 where not active."""
    residual = multiplier + stiffness_h2 * error + damping_h * drift
    system = jnp.eye(3, dtype=error.dtype) + (stiffness_h2 + damping_h) * inverse_inertia
    candidate = multiplier - relaxation * math.matvec(math.inverse3(system), residual)
    candidate = math.clamp_norm(candidate, bound)  # (114)
    return jnp.where(active, candidate - multiplier, 0.0)


def angular_spring_response(pair: BodyPair, hold: PointHold | None) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(W (3, 3), slope (3,)): the response of an `angular_spring` and the shift of its error.
    hold None: W = I_a^-1 + I_b^-1 (113), no shift. With the point of `hold` held (its held step):
    W - G^T K^-1 G and -G^T K^-1 g, g the point's open gap."""
    inverse_inertia = pair.inv_inertia_a + pair.inv_inertia_b  # (113)
    if hold is None:
        return inverse_inertia, jnp.zeros(3, inverse_inertia.dtype)
    opens = math.skew(hold.arm_a) @ pair.inv_inertia_a + math.skew(hold.arm_b) @ pair.inv_inertia_b
    held = inverse_inertia - opens.T @ hold.solve @ opens
    return held, -math.matvec(opens.T, math.matvec(hold.solve, hold.gap))


def _turned_by_torque(pair: BodyPair, hold: PointHold | None, step: jnp.ndarray):
    """The pair moved by a torque step kappa (3,) (a by -I_a^-1 kappa, b by +I_b^-1 kappa), with
    the point of `hold` held: (moved pair, hold with the point impulse added)."""
    moved = pair.moved_by(
        dtheta_a=-math.matvec(pair.inv_inertia_a, step), dtheta_b=math.matvec(pair.inv_inertia_b, step)
    )
    if hold is not None:
        point_impulse, _ = point_impulses(
            hold, -math.matvec(pair.inv_inertia_a, step), -math.matvec(pair.inv_inertia_b, step)
        )
        moved = apply_point_impulse(moved, hold.arm_a, hold.arm_b, point_impulse)
        hold = hold._replace(impulse=hold.impulse + point_impulse)
    return moved, hold


def angular_spring_beside_rotor(
    pair: BodyPair,
    error: jnp.ndarray,
    multipliers: tuple[jnp.ndarray, jnp.ndarray],
    relaxation: jnp.ndarray,
    stiffness_h2: jnp.ndarray,
    damping_h: jnp.ndarray,
    bound: jnp.ndarray,
    active: jnp.ndarray,
    armature: jnp.ndarray,
    rotor_active: jnp.ndarray,
    h: float,
    hold: PointHold,
) -> tuple[BodyPair, jnp.ndarray, jnp.ndarray, PointHold]:
    """`spring_row_beside_rotor` for a ball joint: its three-axis drive (`angular_spring`)
    projected right after its rotor rows (`angular_spring(..., held_step=True)` with k h^2 =
    armature), the two as one block from the rotor's solved residual: the drive's step (112),
    (114) with the rotor relaxed along, response W (1 + K_r W)^-1 (W the held response, K_r =
    armature), and the bodies moved by (1 + K_r W)^-1 times that step; the rotor's kappa takes the
    difference. Without a rotor (rotor_active False) this is `angular_spring`'s step.
    multipliers: (kappa_rotor (3,), kappa_drive (3,)). Returns (moved pair, kappa_rotor,
    kappa_drive, hold)."""
    plain, _ = angular_spring_response(pair, None)
    held, held_slope = angular_spring_response(pair, hold)
    inverse_inertia = jnp.where(rotor_active, held, plain)
    slope = jnp.where(rotor_active, held_slope, 0.0)
    eye = jnp.eye(3, dtype=error.dtype)
    rotor_inverse = math.inverse3(eye + jnp.where(rotor_active, armature, 0.0) * inverse_inertia)  # (1 + K_r W)^-1
    drive_step = _spring_torque_step(
        multipliers[1], error + slope, relative_turn(pair, h), inverse_inertia @ rotor_inverse, relaxation,
        stiffness_h2, damping_h, bound, active,
    )  # fmt: skip
    moved_by = math.matvec(rotor_inverse, drive_step)
    moved, hold = _turned_by_torque(pair, hold, moved_by)
    return moved, multipliers[0] + moved_by - drive_step, multipliers[1] + drive_step, hold


def angular_block(
    pair: BodyPair,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    rule: Rule,
    constrained: jnp.ndarray | None = None,
) -> tuple[BodyPair, jnp.ndarray]:
    """Project a rotation lock c = `error` (3,) rad, with dc/dtheta_a = 1 = -dc/dtheta_b, as one
    block of three angular rows (SI (53), (85)-(88)) by the rigid rule in matrix form, with the
    effective inverse inertia W = I_a^-1 + I_b^-1 (113) regularised by alpha.

    The angular twin of `point_block`, and for the same reason: the one-row magnitude form (a row
    along the normalised error) takes its direction from rounding noise where the lock holds, so
    the sweeps would amplify that noise instead of damping it. multiplier: (3,) so far this
    substep (kg m^2). constrained: (3, 3) orthogonal projector onto the locked directions (the
    plane across a hinge's axle, SI 2.4.1), None for all three. Returns the moved pair and the new
    multiplier.
    """
    if rule.spring or rule.speed:
        raise ValueError("angular_block takes the rigid rule only")
    eye = jnp.eye(3, dtype=error.dtype)
    inverse_inertia = pair.inv_inertia_a + pair.inv_inertia_b + rule.regularization * eye  # (113), (47)
    residual = error + rule.regularization * multiplier
    if constrained is not None:  # restricted to range(P), as in point_block
        inverse_inertia = constrained @ inverse_inertia @ constrained + (eye - constrained)
        residual = math.matvec(constrained, residual)
    solve, solvable = definite_inverse(inverse_inertia, rule.active)
    step = jnp.where(solvable, -rule.relaxation * math.matvec(solve, residual), 0.0)
    moved = pair.moved_by(
        dtheta_a=math.matvec(pair.inv_inertia_a, step), dtheta_b=-math.matvec(pair.inv_inertia_b, step)
    )
    return moved, multiplier + step


def point_response(arm: jnp.ndarray, inv_mass: jnp.ndarray, inv_inertia: jnp.ndarray) -> jnp.ndarray:
    """How the point at `arm` from a body's centre moves per unit impulse there, (3, 3):
    1/m 1 - [arm]x I^-1 [arm]x, one body's term of DBD (57). Written column by column (no matmul):
    the response to e_j is e_j / m + (I^-1 (arm x e_j)) x arm."""
    eye = jnp.eye(3, dtype=arm.dtype)
    turn = math.matvec(inv_inertia[None], math.cross(arm[None], eye))  # row j: I^-1 (arm x e_j)
    columns = inv_mass * eye + math.cross(turn, arm[None])  # row j: the response to e_j
    return jnp.swapaxes(columns, -1, -2)


def point_inverse_mass(pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray) -> jnp.ndarray:
    """K (3, 3) m/kg, how the gap p_a - p_b between the points at arm_a on a and arm_b on b opens
    per unit impulse at them: the point block's effective inverse mass, DBD (57), (66)."""
    return point_response(arm_a, pair.inv_mass_a, pair.inv_inertia_a) + point_response(
        arm_b, pair.inv_mass_b, pair.inv_inertia_b
    )


def definite_inverse(matrix: jnp.ndarray, active: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(matrix^-1, invertible) of a (3, 3) effective inverse mass, positive definite unless neither
    side can move: 0 and False there (or where `active` is False). The adjugate and determinant
    are computed once (`math.adjugate3`, the same arithmetic as `math.inverse3`); the adjugate is a
    polynomial, and only the division is kept from a zero determinant, so gradients stay finite."""
    adjugate, determinant = math.adjugate3(matrix)
    invertible = active & (determinant > 0.0)
    inverse = adjugate / jnp.where(invertible, determinant, 1.0)[..., None, None]
    return jnp.where(invertible[..., None, None], inverse, 0.0), invertible


def point_impulse_motion(pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray, impulse: jnp.ndarray):
    """How an impulse (..., 3) (kg m: the multiplier step) at arm_a from a's centre and its
    opposite at arm_b from b's move the pair, (..., 4, 3) as `BodyPair.motion`:
    dX = M~^-1 J^T d lambda with J of (65), DBD (52)."""
    return jnp.stack(
        [
            pair.inv_mass_a * impulse,
            -pair.inv_mass_b * impulse,
            math.matvec(pair.inv_inertia_a, math.cross(arm_a, impulse)),
            -math.matvec(pair.inv_inertia_b, math.cross(arm_b, impulse)),
        ],
        axis=-2,
    )


def apply_point_impulse(pair: BodyPair, arm_a: jnp.ndarray, arm_b: jnp.ndarray, impulse: jnp.ndarray) -> BodyPair:
    """Move the pair by an impulse (3,) acting at arm_a from a's centre and its opposite at arm_b
    from b's (`point_impulse_motion`)."""
    return pair._replace(motion=pair.motion + point_impulse_motion(pair, arm_a, arm_b, impulse))


def point_spring(
    pair: BodyPair,
    arm_a: jnp.ndarray,
    arm_b: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    rule: Rule,
    h: float,
) -> tuple[BodyPair, jnp.ndarray]:
    """A zero-length spring/damper between two points as one block of three rows: c = `error`
    (3,) m = p_a - p_b, the spring rule of the module docstring in matrix form with the 3x3
    effective inverse mass K of `point_block` ((57), (66)), and |lambda| <= bound (the force limit
    times h^2, as the drive's (114)). A spring of infinite stiffness is the rigid `point_block`.

    Written in compliance form, so that stiffness inf is exact: with s = k h^2, a = 1 / s (0 when
    rigid) and r = nu h / s, d lambda = -xi (a 1 + (1 + r) K)^-1 (a lambda + c + r drift), which
    is the rule's -xi (1 + (s + nu h) K)^-1 (lambda + s c + nu h drift) divided through by s.
    Unlike a row along the normalised gap, nothing here is undefined where the points meet.
    rule: a `spring` rule (relaxation, active, stiffness_h2, damping_h, bound). Returns the moved
    pair and the new multiplier (3,) kg m.
    """
    eye = jnp.eye(3, dtype=error.dtype)
    rigid = jnp.isinf(rule.stiffness_h2)
    stiffness_h2 = jnp.where(rigid, 1.0, rule.stiffness_h2)
    compliance = jnp.where(rigid, 0.0, 1.0 / stiffness_h2)
    damping_ratio = jnp.where(rigid, 0.0, rule.damping_h / stiffness_h2)
    inverse_mass = point_inverse_mass(pair, arm_a, arm_b)
    drift = -relative_point_motion(pair, arm_a, arm_b, h)  # J (h V* + dX): how far the points moved apart
    system = compliance * eye + (1.0 + damping_ratio) * inverse_mass
    residual = compliance * multiplier + error + damping_ratio * drift
    solve, solvable = definite_inverse(system, rule.active)
    candidate = multiplier - rule.relaxation * math.matvec(solve, residual)
    direction, size = math.safe_normalize(candidate)
    limited = jnp.isfinite(rule.bound)
    bound = jnp.where(limited, rule.bound, 0.0)
    candidate = jnp.where(limited & (size > bound), bound * direction, candidate)  # as (114)
    step = jnp.where(solvable, candidate - multiplier, 0.0)
    return apply_point_impulse(pair, arm_a, arm_b, step), multiplier + step


def point_block(
    pair: BodyPair,
    arm_a: jnp.ndarray,
    arm_b: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    rule: Rule,
    constrained: jnp.ndarray | None = None,
) -> tuple[BodyPair, jnp.ndarray]:
    """Project the point constraint c = `error` (3,) m = p_a - p_b as one block of three rows,
    DBD (64)-(66), by the rigid rule in matrix form (see the module docstring).

    The impulse lambda (3,) kg m acts at arm_a from a's centre and -lambda at arm_b from b's.
    multiplier: (3,) lambda so far this substep. rule: a `rigid` rule (relaxation xi,
    regularisation alpha, active). constrained: (3, 3) orthogonal projector P onto the directions
    the block removes, or None for all three: the plane across a slider's axis (SI (51)), the normal
    line of a planar joint. The error is taken in range(P) and so is the step. Returns the moved
    pair and the new multiplier.
    """
    if rule.spring or rule.speed:
        raise ValueError("point_block takes the rigid rule only")
    eye = jnp.eye(3, dtype=error.dtype)
    inverse_mass = point_inverse_mass(pair, arm_a, arm_b) + rule.regularization * eye  # (57), (66), (47)
    residual = error + rule.regularization * multiplier
    if constrained is not None:
        # Restricted to range(P): P K P + (1 - P) maps range(P) to itself and its complement to
        # itself, so with a residual in range(P) the step stays there too.
        projector = constrained
        inverse_mass = projector @ inverse_mass @ projector + (eye - projector)
        residual = math.matvec(projector, residual)
    solve, solvable = definite_inverse(inverse_mass, rule.active)
    step = jnp.where(solvable, -rule.relaxation * math.matvec(solve, residual), 0.0)
    return apply_point_impulse(pair, arm_a, arm_b, step), multiplier + step
