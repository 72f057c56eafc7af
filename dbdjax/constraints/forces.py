"""User forces: any force/torque given as a JAX function of the bodies' state (DBD 8, (94)-(99)).

A force element acts on k bodies. With kappa_i the impulse times h it has applied to body i this
substep (so that its share of the displacement is M~_i^-1 kappa_i), the implicit force equation
kappa_i = h^2 F_i(X* + dX, V* + dX / h) (94) is solved by Gauss-Seidel over the element's bodies,
one Newton step each (98):

  (M~_i - h^2 dF_i/d dX_i) d dX_i = h^2 F_i - kappa_i,   kappa_i += M~_i d dX_i

dF_i/d dX_i is taken by forward-mode autodiff of the user's function, through the velocity
V* + dX / h too, so a damping force gets its 1/h term (the nu dt of (103)) for free. Linear and
angular parts are solved as separate 3x3 blocks (their coupling is left to the iterations).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from dbdjax import integrator, math
from dbdjax.constraints.rows import BodySet


def project_force(function: Callable, params, bodies: BodySet, multipliers: jnp.ndarray, h: float):
    """One Gauss-Seidel sweep over the bodies of one force element.

    multipliers: (k, 6) kappa (linear, angular) per body so far. Returns (dx, dtheta, multipliers).
    """
    k = bodies.origin.shape[0]
    dx, dtheta, kappa = bodies.dx, bodies.dtheta, multipliers

    def wrench_on(i, dx, dtheta):
        pos = bodies.origin + dx
        quat = integrator.displaced_quat(bodies.quat, dtheta)
        force, torque = function(pos, quat, bodies.vel + dx / h, bodies.ang_vel + dtheta / h, params)
        return jnp.concatenate([force[i], torque[i]])

    for i in range(k):  # k is static and small: each body in turn sees the others' latest move

        def wrench_of_own_move(move, i=i, dx=dx, dtheta=dtheta):
            return wrench_on(i, dx.at[i].add(move[:3]), dtheta.at[i].add(move[3:]))

        zero = jnp.zeros(6, dx.dtype)
        wrench, linearised = jax.linearize(wrench_of_own_move, zero)
        jacobian = jax.vmap(linearised, out_axes=-1)(jnp.eye(6, dtype=dx.dtype))  # (6, 6) dF/d move
        residual = h**2 * wrench - kappa[i]
        dynamic = bodies.inv_mass[i] > 0.0
        mass = jnp.where(dynamic, 1.0 / jnp.where(dynamic, bodies.inv_mass[i], 1.0), 0.0)
        inertia = math.inverse3(bodies.inv_inertia[i] + jnp.where(dynamic, 0.0, jnp.eye(3, dtype=dx.dtype)))
        linear_system = mass * jnp.eye(3, dtype=dx.dtype) - h**2 * jacobian[:3, :3]
        angular_system = inertia - h**2 * jacobian[3:, 3:]
        move_linear = math.matvec(math.inverse3(linear_system), residual[:3])
        move_angular = math.matvec(math.inverse3(angular_system), residual[3:])
        move_linear = jnp.where(dynamic, move_linear, 0.0)
        move_angular = jnp.where(dynamic, move_angular, 0.0)
        dx = dx.at[i].add(move_linear)
        dtheta = dtheta.at[i].add(move_angular)
        kappa = kappa.at[i].add(jnp.concatenate([mass * move_linear, math.matvec(inertia, move_angular)]))
    return dx, dtheta, kappa
