"""Two-point links: springs/dampers (DBD 8.1) and rigid distance constraints.

Both act along the line between a point on each body, c = |p_a - p_b| - length, as one
positional row (rows.py). A spring is the implicit spring/damper rule of DBD (105)-(109): the
force -k c - nu c_dot is applied exactly at the end of the substep, so its stiffness does not
depend on the iteration count (unlike a compliance made of relaxation or regularisation, DBD 8.1).
Its damping acts along the line, like a damper strut. A distance constraint is the rigid rule.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.model import Distances, Springs


def line(local_anchor_a, local_anchor_b, world: np.ndarray, pair: BodyPair):
    """(unit direction, length, arm_a, arm_b) of the line from p_b to p_a at X* + dX.

    world: (2,) bool, which side is the world (its anchor is a world point, its arm zero)."""
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = row.anchor_points(pair, local_anchor_a, local_anchor_b, world[0], world[1], quat_a, quat_b)
    direction, length = math.safe_normalize(delta)
    return direction, length, arm_a, arm_b


def project_spring(spring: Springs, world: np.ndarray, bodies: BodySet, multiplier: jnp.ndarray, h: float):
    """One implicit spring/damper row (DBD (105), (108)-(109)). multiplier: (1,). Returns
    (dx (2, 3), dtheta (2, 3), multiplier)."""
    pair = BodyPair.of(bodies)
    direction, length, arm_a, arm_b = line(spring.local_anchor_a, spring.local_anchor_b, world, pair)
    rule = row.spring(spring.relaxation, True, spring.stiffness * h**2, spring.damping * h)
    pair, lam = row.positional_row(pair, direction, arm_a, arm_b, length - spring.rest_length, multiplier[0], rule, h)
    return *pair.displacements(), lam[None]


def project_distance(distance: Distances, world: np.ndarray, bodies: BodySet, multiplier: jnp.ndarray):
    """One rigid distance row, DBD (45)-(52) on c = |p_a - p_b| - length. multiplier: (1,)."""
    pair = BodyPair.of(bodies)
    direction, length, arm_a, arm_b = line(distance.local_anchor_a, distance.local_anchor_b, world, pair)
    rule = row.rigid(distance.relaxation, 0.0, True)
    pair, lam = row.positional_row(pair, direction, arm_a, arm_b, length - distance.length, multiplier[0], rule)
    return *pair.displacements(), lam[None]
