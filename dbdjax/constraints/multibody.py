"""Constraints over many bodies at once (DBD 10): a rope's total length and a tetrahedron's volume.

Both are one scalar error c(x_0, ..., x_{S-1}) of the bodies' centres of mass with gradient
g_i = dc/dx_i, solved by the rigid rule of rows.py generalised to S bodies:
  w = sum_i g_i . g_i / m_i,  d lambda = -xi c / w,  dx_i += g_i d lambda / m_i   (DBD (45)-(52))
One node of the constraint graph touches all S bodies, so it is coloured apart from everything
that shares one of them (colouring.py); one update moves every body (DBD Fig. 6).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.constraints.rows import BodySet
from dbdjax.model import Ropes, Volumes


def _points_row(bodies: BodySet, gradient, error, multiplier, relaxation):
    """The rigid update on an S-point error; gradient: (S, 3). Returns (dx, dtheta, multiplier)."""
    inverse_mass = jnp.sum(bodies.inv_mass * math.dot(gradient, gradient))
    solvable = inverse_mass > 0.0
    step = jnp.where(solvable, -relaxation * error / jnp.where(solvable, inverse_mass, 1.0), 0.0)
    dx = bodies.dx + (bodies.inv_mass * step)[:, None] * gradient
    return dx, bodies.dtheta, multiplier + step


def _relative_positions(bodies: BodySet) -> jnp.ndarray:
    """x_i - x_0 at X* + dX, (S, 3), from differences of like terms (precise far from the origin)."""
    return (bodies.origin - bodies.origin[0]) + (bodies.dx - bodies.dx[0])


def rope_error(rope: Ropes, present: np.ndarray, bodies: BodySet):
    """(gradient (S, 3), error) of the total length c = sum_i |x_i - x_{i+1}| - L, DBD (118)-(121).

    present: (S,) bool, which node slots hold a body (ropes are padded to the longest). The
    gradient on node i is d_{i,i+1} - d_{i-1,i} (119), the unit segment directions, so a node
    moves most where the rope bends most.
    """
    x = _relative_positions(bodies)
    segment_present = present[:-1] & present[1:]
    unit, length = math.safe_normalize(x[:-1] - x[1:])  # (S - 1, 3): d_{i,i+1} from x_{i+1} to x_i
    unit = jnp.where(segment_present[:, None], unit, 0.0)
    error = jnp.sum(jnp.where(segment_present, length, 0.0)) - rope.length
    zero = jnp.zeros((1, 3), unit.dtype)
    gradient = jnp.concatenate([unit, zero]) - jnp.concatenate([zero, unit])  # (119)
    return gradient, error


def project_rope(rope: Ropes, present: np.ndarray, bodies: BodySet, multiplier: jnp.ndarray):
    """The rigid update of the rope's total length (`rope_error`). multiplier: (1,)."""
    gradient, error = rope_error(rope, present, bodies)
    dx, dtheta, lam = _points_row(bodies, gradient, error, multiplier[0], rope.relaxation)
    return dx, dtheta, lam[None]


def volume_error(volume: Volumes, bodies: BodySet):
    """(gradient (4, 3), error) of the signed volume c = d1 . (d2 x d3) - 6 V0, d_i = x_i - x_0,
    DBD (122)-(124). The gradient on x_i (i = 1, 2, 3) is twice the directed area of the opposite
    face (123), and on x_0 minus their sum, so an update along it conserves linear momentum.
    """
    d = _relative_positions(bodies)
    d1, d2, d3 = d[1], d[2], d[3]
    areas = jnp.stack([math.cross(d2, d3), math.cross(d3, d1), math.cross(d1, d2)])
    gradient = jnp.concatenate([-jnp.sum(areas, axis=0, keepdims=True), areas])  # (123)
    error = math.dot(d1, areas[0]) - 6.0 * volume.rest_volume
    return gradient, error


def project_volume(volume: Volumes, bodies: BodySet, multiplier: jnp.ndarray):
    """The rigid update of the tetrahedron's volume (`volume_error`). multiplier: (1,)."""
    gradient, error = volume_error(volume, bodies)
    dx, dtheta, lam = _points_row(bodies, gradient, error, multiplier[0], volume.relaxation)
    return dx, dtheta, lam[None]
