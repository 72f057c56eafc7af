"""IK targets: inverse kinematics as a constraint inside the simulation step (DBD 11).

DBD 11 ends: the IK update "can be used as a constraint in a simulation", so that the reach is
solved together with the joints, contacts and forces rather than before them. Here a target is
one constraint node between a body and the world: c = p - target (3,), p the target's point on
the body at X* + dX, target = rest_target + the control's offset. It is projected with the other
constraints in the same Gauss-Seidel sweeps (one colour group among the joints'), as the block
`rows.point_spring`: rigid (stiffness inf) it is the point constraint of DBD (64)-(66) to a moving
world point; soft, the implicit spring of DBD 8.1 with zero rest length; either way its pull is
capped at max_force, so an unreachable target stretches the chain toward it and no further
instead of tearing the joints apart. The mass weighting of DBD (133) comes for free: the
displacement each sweep distributes over the chain is the least-kinetic-energy one of (49),
so the chain bends where it is light, as `dbdjax.ik.solve(method="dbd")` does by itself.
"""

from __future__ import annotations

import jax.numpy as jnp

from dbdjax import math
from dbdjax.constraints import joints
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.model import IKTargets, Structure


def goals(structure: Structure, targets: IKTargets, control: jnp.ndarray | None, dtype) -> jnp.ndarray:
    """(T, 3) m: each target's world position this step, rest_target plus its control offset."""
    return targets.rest_target + joints.padded_control(structure, control, dtype)[structure.ik_target_control.array]


def project(target: IKTargets, goal: jnp.ndarray, bodies: BodySet, multiplier: jnp.ndarray, h: float):
    """Project one IK target (no T axis): bodies row 0 is the body, row 1 the world. goal: (3,) m,
    world. multiplier: (3,) kg m, the pull times h so far this substep.
    Returns (dx (2, 3), dtheta (2, 3), multiplier)."""
    pair = BodyPair.of(bodies)
    quat_a, _ = pair.current_quats()
    arm = math.quat_rotate(quat_a, target.local_point)
    # p - goal from differences of like terms (precise far from the origin, as anchor_points)
    error = (pair.origin_a - goal) + pair.dx_a + arm
    rule = row.spring(1.0, True, target.stiffness * h**2, target.damping * h, target.max_force * h**2)
    pair, multiplier = row.point_spring(pair, arm, jnp.zeros_like(arm), error, multiplier, rule, h)
    return *pair.displacements(), multiplier
