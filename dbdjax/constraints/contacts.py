"""Contact and friction between shapes (DBD section 7), and the restitution velocity pass.

One node is one shape pair with its P contact slots (collision.ContactSlots). Per point three
rows, evaluated at X* + dX (the non-linear update of DBD 4.1):

  normal    c = (p_b - p_a) . n >= 0                                   DBD (84)-(88)
            the accumulated lambda_n >= 0 is projected (projected Gauss-Seidel: an over-push is
            taken back, never a pull). With contact_compliance alpha, c + alpha / h^2 lambda_n
            = 0: a stiff spring (smoother gradients).
  friction  the body points may not slide in the contact plane over the substep: the slip
            (p_b - p_a) - offset, projected on the plane, is driven to zero along s (89)-(91);
            the accumulated friction vector kappa is held inside the cone |kappa| <= mu lambda_n
            (92)-(93), with mu = mu_d where the points were already sliding at the start of the
            substep and mu_s where they were sticking: static friction at position level,
            dynamic friction bounded by mu_d times the normal impulse. (93) switches to mu_d as
            soon as the static cone is left inside the iterations; deciding by the motion at the
            start of the substep instead keeps a box held by mu_s > tan(slope) > mu_d at rest,
            where the iterates, whose normal impulses are still growing, would leave the cone.

The rows of one pair share two bodies and are strongly coupled through rotation (a box's four
corners), so a node solves them together: their coupling K = J M~^-1 J^T is linearised at the
current pose and SWEEPS projected Gauss-Seidel sweeps run on that small system before the total
is applied (point-by-point projection left a rotation every substep that made stacks rock).

After the position solve, `project_restitution` brings the normal speed of every point that pushed
(lambda_n > 0) up to -e times its speed before the solve (0 for slow impacts, below 2 |g| h, so
resting contacts do not jitter), and takes back what pushing it out of a penetration it began the
substep in gave it, as impulses on the velocities (SI 2.1.4, (37)-(42)). A point that the rest of
the solve lifts away (a foot its leg's rotor swings up) keeps its speed.
Multipliers per point: (lambda_n, kappa_t1, kappa_t2, unused), kg m (impulse times h, like
every DBD row).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import math, sharding
from dbdjax.collision import ContactSlots
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet

MULTIPLIERS_PER_POINT = 4  # lambda_n, kappa along t1 and t2, one unused (a 4-aligned row)
SWEEPS = 16  # Gauss-Seidel sweeps over a pair's points on its linearised coupling (P >= 4)
# Fewer sweeps where a pair has few points: one or two points converge on their small system in a
# few sweeps, and the solver's outer iterations re-linearise and go on from the multipliers so far.
# A box's 4-8 corners, strongly coupled through its rotation, keep 16 (stacks need them).
FEW_POINT_SWEEPS = {1: 2, 2: 4}


def sweeps(points: int) -> int:
    """Gauss-Seidel sweeps for a pair of P contact points (sphere-plane P = 1, capsule-plane 2, box-plane 8)."""
    return FEW_POINT_SWEEPS.get(points, SWEEPS)


def row_directions(normal: jnp.ndarray) -> jnp.ndarray:
    """(..., 3, 3) the directions of a point's rows (n, t1, t2) from its unit normal (..., 3)."""
    tangent = math.any_perpendicular(normal)
    return jnp.stack([normal, tangent, math.cross(normal, tangent)], axis=-2)


def _manifold(pair: BodyPair, normal: jnp.ndarray, arm_a: jnp.ndarray, arm_b: jnp.ndarray):
    """The P points' rows along (n, t1, t2) and their coupling, linearised at the current pose.

    normal, arm_a, arm_b: (P, 3). Returns (directions (P, 3, 3), turn_a, turn_b (P, 3, 3): the
    rotation of a and b per unit multiplier, coupling K (3P, 3P) = J M~^-1 J^T, DBD (86)-(87) for
    every pair of rows). A unit multiplier on row (i, k) pushes b along d_ik and a against it.
    """
    directions = row_directions(normal)
    torque_a = math.cross(arm_a[:, None, :], directions)
    torque_b = math.cross(arm_b[:, None, :], directions)
    turn_a = math.matvec(pair.inv_inertia_a, torque_a)
    turn_b = math.matvec(pair.inv_inertia_b, torque_b)

    def rows(x):  # (3 P, 3): every point's three rows in turn
        return x.reshape(-1, 3)

    coupling = (
        (pair.inv_mass_a + pair.inv_mass_b) * math.row_products(rows(directions), rows(directions))
        + math.row_products(rows(torque_a), rows(turn_a))
        + math.row_products(rows(torque_b), rows(turn_b))
    )
    return directions, turn_a, turn_b, coupling


def _move(pair: BodyPair, impulse: jnp.ndarray, directions, turn_a, turn_b) -> BodyPair:
    """Apply multiplier increments (P, 3) along the rows: b along d, a against it."""

    def total(rows):  # (3,): the rows (P, 3, 3) times their increments, summed
        return math.sum_small((impulse[..., None] * rows).reshape(-1, 3), axis=0)

    push = total(directions)
    return pair.moved_by(
        dx_a=-pair.inv_mass_a * push, dx_b=pair.inv_mass_b * push, dtheta_a=-total(turn_a), dtheta_b=total(turn_b)
    )


def project_contacts(slots: ContactSlots, world: np.ndarray, bodies: BodySet, multipliers: jnp.ndarray,
                     compliance_h2: float, sweeps: int):  # fmt: skip
    """Normal and friction rows of one shape pair's P points (DBD (84)-(93)).

    The rows of one pair share two bodies and are strongly coupled through the rotations (a
    box's four corners). They are solved together: errors evaluated at X* + dX (DBD 4.1), the
    coupling K linearised there, then `sweeps` projected Gauss-Seidel sweeps over the points on
    that small system (normal: lambda_n >= 0; friction: (92)-(93) on the tangent impulse), and
    the total increment applied once.

    slots: one pair's `ContactSlots` (arrays with leading axis P, materials ()). world: (2,) bool.
    multipliers: (4 P,) per point (lambda_n, kappa_t1, kappa_t2, unused). compliance_h2: contact
    compliance / h^2. Returns (dx (2, 3), dtheta (2, 3), multipliers).
    """
    pair = BodyPair.of(bodies)
    points = slots.active.shape[0]
    lam = multipliers.reshape(points, MULTIPLIERS_PER_POINT)[:, :3]
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = row.anchor_points(pair, slots.local_a, slots.local_b, world[0], world[1], quat_a, quat_b)
    directions, turn_a, turn_b, coupling = _manifold(pair, slots.normal, arm_a, arm_b)
    # errors of the rows: the gap (p_b - p_a) . n (84), less the depth the point may keep this
    # substep (`ContactSlots.allowed_depth`), and the slip in the plane (89)
    error = math.dot(directions, (-delta - slots.offset)[:, None, :])
    gap = -math.dot(delta, slots.normal) + slots.allowed_depth
    error = jnp.concatenate([gap[:, None], error[:, 1:]], axis=1)  # (not .at[:, 0].set: no scatter)
    diagonal = math.diagonal(coupling).reshape(points, 3)
    blocks = coupling.reshape(points, 3, points, 3)
    solvable = slots.active & (diagonal[:, 0] > 0.0)

    def point(i: int, increment):
        # row errors after the increment: the pair's coupling times every point's increment
        residual = error[i] + math.sum_small((blocks[i] * increment[None]).reshape(3, -1))
        total = lam[i] + increment[i]
        normal = jnp.maximum(total[0] - (residual[0] + compliance_h2 * total[0]) / jnp.where(
            solvable[i], diagonal[i, 0] + compliance_h2, 1.0), 0.0)  # fmt: skip
        slip = residual[1:] + blocks[i, 1:, i, 0] * (normal - total[0])
        # (90)-(92): a step along the slip direction s with the effective mass along s. (A full
        # 2 x 2 solve would converge to friction along B^-1 slip, not against the slip: a box
        # sliding on its corners would feel ~6% less friction than mu N.)
        kappa = total[1:] - row.mass_along(slip, blocks[i, 1:, i, 1:]) * slip
        kappa_direction, kappa_size = math.safe_normalize(jnp.concatenate([kappa, jnp.zeros(1, kappa.dtype)]))
        bound = jnp.where(slots.sliding[i], slots.dynamic_friction, slots.friction) * normal
        kappa = jnp.where(kappa_size > bound, bound * kappa_direction[:2], kappa)  # (93)
        new = jnp.where(solvable[i], jnp.concatenate([normal[None], kappa]), total)
        return jnp.where((np.arange(points) == i)[:, None], new - lam[i], increment)  # row i (a mask: no scatter)

    def sweep(increment, _):
        for i in range(points):  # unrolled: P is static and small, XLA fuses the points' arithmetic
            increment = point(i, increment)
        return increment, None

    start = sharding.varying_like(jnp.zeros_like(lam), lam, error, blocks, slots)  # (shard_map)
    increment, _ = jax.lax.scan(sweep, start, None, length=sweeps)
    pair = _move(pair, increment, directions, turn_a, turn_b)
    lam = jnp.concatenate([lam + increment, jnp.zeros((points, 1), lam.dtype)], axis=1)
    return *pair.displacements(), lam.reshape(-1)


def project_restitution(slots: ContactSlots, world: np.ndarray, bodies: BodySet, normal_multipliers: jnp.ndarray,
                        slow: float, sweeps: int):  # fmt: skip
    """The velocity pass of one shape pair: restitution on the points that pushed.

    bodies: the velocity view (vel/ang_vel the velocities after the position solve, dx/dtheta
    the velocity changes of this pass so far). normal_multipliers: (P,) lambda_n of the solve.
    slow: m/s, impacts slower than this do not bounce (2 |g| h). The normal speed v of a pushed
    point is brought into [target, max(target, v - pushout_speed)], v its speed after the position
    solve: up to its target (-e times its approach speed, or 0), and down by what its depenetration
    gave it (`ContactSlots.pushout_speed`), not below the target, all together (projected
    Gauss-Seidel sweeps on the pair's coupling, as in `project_contacts`). Returns (dv (2, 3),
    dw (2, 3), normal_multipliers).

    Why not down to the target whatever the speed: it pulled back points that the rest of the solve
    lifted. Brax's ant landing at 4 substeps: the pass held a foot its leg's rotor (armature 1 kg m^2)
    swung up, through that foot's own body alone, and spun its knee from -3.6 to 43 rad/s; the
    rotors' kinetic energy went from 29 J to 968 J in one substep.
    """
    pair = BodyPair.of(bodies)
    points = slots.active.shape[0]
    _, arm_a, arm_b = row.anchor_points(pair, slots.local_a, slots.local_b, world[0], world[1], pair.quat_a,
                                        pair.quat_b)  # fmt: skip
    directions, turn_a, turn_b, coupling = _manifold(pair, slots.normal, arm_a, arm_b)
    speed = row.relative_point_motion(pair, arm_a, arm_b, 1.0)  # (P, 3) b's points against a's
    bounce = jnp.where(slots.approach < -slow, slots.restitution, 0.0)
    target = jnp.maximum(-bounce * slots.approach, 0.0)
    error = math.dot(speed, slots.normal) - target
    normal_coupling = coupling.reshape(points, 3, points, 3)[:, 0, :, 0]
    pushed = slots.active & (normal_multipliers > 0.0) & (math.diagonal(normal_coupling) > 0.0)

    ceiling = jnp.maximum(error - slots.pushout_speed, 0.0)  # the speed less its depenetration's, over the target

    def sweep(increment, _):
        for i in range(points):  # unrolled, as in project_contacts
            above = error[i] + normal_coupling[i] @ increment  # the speed now, less the target
            wanted = jnp.clip(above, 0.0, ceiling[i])
            step = (wanted - above) / jnp.where(pushed[i], normal_coupling[i, i], 1.0)
            increment = increment + jnp.where((np.arange(points) == i) & pushed[i], step, 0.0)
        return increment, None

    start = sharding.varying_like(jnp.zeros(points, error.dtype), error, normal_coupling, ceiling, pushed)
    increment, _ = jax.lax.scan(sweep, start, None, length=sweeps)
    impulse = jnp.stack([increment, jnp.zeros_like(increment), jnp.zeros_like(increment)], axis=1)
    pair = _move(pair, impulse, directions, turn_a, turn_b)
    return *pair.displacements(), normal_multipliers
