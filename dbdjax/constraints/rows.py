"""The scalar constraint row updates every constraint family is built from.

A row is one scalar position error c(X* + dX) with a Jacobian of one of two shapes:
  positional: J = (n, arm_a x n, -n, -arm_b x n)   (DBD (55), (85); SI (69))
  angular:    J = (0, d, 0, -d)                     (DBD (74); SI (109))
Its update is the non-linear Gauss-Seidel step of DBD (45)-(52) with relaxation xi and
regularisation alpha, solved for the row's multiplier lambda (the integrated impulse times h, as
in DBD's lambda dt^2: kg m for positional rows, kg m^2 for angular ones):

  w           = J M~^-1 J^T                         effective inverse mass (51), (57), (76)
  d lambda    = -xi (c + alpha lambda) / (w + alpha)
  dX_body    += M~^-1 J_body^T d lambda             (52)

which converges to c + alpha lambda = 0, the regularised solution (49). Inequality rows (limits,
DBD 6.1) only ever push: the increment is clamped to d lambda >= 0 as in (83).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from dbdjax import integrator, math


class BodyPair(NamedTuple):
    """The two bodies one constraint moves, as the solver sees them (one slot, no batch axis).

    origin_*: (3,) predicted centre of mass X*. quat_*: (4,) predicted orientation.
    inv_mass_*: () 1/kg (0 for the world). inv_inertia_*: (3, 3) world frame (0 for the world).
    dx_*, dtheta_*: (3,) displacement and rotation accumulated so far this substep.
    """

    origin_a: jnp.ndarray
    origin_b: jnp.ndarray
    quat_a: jnp.ndarray
    quat_b: jnp.ndarray
    inv_mass_a: jnp.ndarray
    inv_mass_b: jnp.ndarray
    inv_inertia_a: jnp.ndarray
    inv_inertia_b: jnp.ndarray
    dx_a: jnp.ndarray
    dx_b: jnp.ndarray
    dtheta_a: jnp.ndarray
    dtheta_b: jnp.ndarray

    def current_quats(self) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Orientations at X* + dX (what the non-linear update of DBD 4.1 evaluates at)."""
        return (
            integrator.displaced_quat(self.quat_a, self.dtheta_a),
            integrator.displaced_quat(self.quat_b, self.dtheta_b),
        )


def _multiplier_step(error, inverse_mass, multiplier, relaxation, regularization, inequality, active):
    """d lambda of DBD (46)/(52) with the regularised denominator; 0 where w + alpha is 0."""
    denominator = inverse_mass + regularization
    solvable = active & (denominator > 0.0)
    safe_denominator = jnp.where(solvable, denominator, 1.0)
    step = -relaxation * (error + regularization * multiplier) / safe_denominator
    step = jnp.where(inequality, jnp.maximum(step, 0.0), step)
    return jnp.where(solvable, step, 0.0)


def positional_row(
    pair: BodyPair,
    direction: jnp.ndarray,
    arm_a: jnp.ndarray,
    arm_b: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    relaxation: jnp.ndarray,
    regularization: jnp.ndarray,
    inequality: bool | jnp.ndarray,
    active: jnp.ndarray,
) -> tuple[BodyPair, jnp.ndarray]:
    """Project one positional row: error c along unit `direction` (dc/dx_a), applied at arm_a
    from a's centre and arm_b from b's. Returns the moved pair and the new multiplier."""
    torque_a = math.cross(arm_a, direction)
    torque_b = math.cross(arm_b, direction)
    turn_a = math.matvec(pair.inv_inertia_a, torque_a)
    turn_b = math.matvec(pair.inv_inertia_b, torque_b)
    inverse_mass = (
        pair.inv_mass_a + pair.inv_mass_b + math.dot(torque_a, turn_a) + math.dot(torque_b, turn_b)
    )  # (57) projected on the direction, (56)
    step = _multiplier_step(error, inverse_mass, multiplier, relaxation, regularization, inequality, active)
    moved = pair._replace(
        dx_a=pair.dx_a + (pair.inv_mass_a * step) * direction,
        dx_b=pair.dx_b - (pair.inv_mass_b * step) * direction,
        dtheta_a=pair.dtheta_a + step * turn_a,
        dtheta_b=pair.dtheta_b - step * turn_b,
    )
    return moved, multiplier + step


def angular_row(
    pair: BodyPair,
    direction: jnp.ndarray,
    error: jnp.ndarray,
    multiplier: jnp.ndarray,
    relaxation: jnp.ndarray,
    regularization: jnp.ndarray,
    inequality: bool | jnp.ndarray,
    active: jnp.ndarray,
) -> tuple[BodyPair, jnp.ndarray]:
    """Project one angular row: error c (rad) with dc/dtheta_a = `direction` = -dc/dtheta_b."""
    turn_a = math.matvec(pair.inv_inertia_a, direction)
    turn_b = math.matvec(pair.inv_inertia_b, direction)
    inverse_mass = math.dot(direction, turn_a) + math.dot(direction, turn_b)  # (76)
    step = _multiplier_step(error, inverse_mass, multiplier, relaxation, regularization, inequality, active)
    moved = pair._replace(
        dtheta_a=pair.dtheta_a + step * turn_a,
        dtheta_b=pair.dtheta_b - step * turn_b,
    )
    return moved, multiplier + step
