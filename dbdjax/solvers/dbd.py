"""DBD Algorithm 1: non-linear Gauss-Seidel over colour groups.

    prepare:  inverse masses and world inverse inertias at X* (once per substep)
    repeat `iterations` times:                                   (lax.scan)
        for each colour, in order:                               (lax.scan)
            project every joint of the colour at once            (jax.vmap, joints.project)
            write back the displacements of the bodies it moved  (a gather: no conflicts)

Only displacements dX from X* are accumulated; the caller applies them with (36)-(39).
With `jacobi`, all joints are projected at once from the same dX and each body moves by the
average of what its joints ask (for comparison; it converges more slowly).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import integrator
from dbdjax.constraints import joints as joint_family
from dbdjax.constraints.rows import BodyPair
from dbdjax.model import Model, State


def _with_world_row(array: jnp.ndarray, world_value: jnp.ndarray | float = 0.0) -> jnp.ndarray:
    """Append the world as body N (static: zero inverse mass and inertia, identity pose)."""
    row = jnp.broadcast_to(jnp.asarray(world_value, array.dtype), (1,) + array.shape[1:])
    return jnp.concatenate([array, row], axis=0)


def _joint_layout(model: Model, joint_of_slot: np.ndarray):
    """Joint parameters and flags rearranged into the slot layout (..., K) of the solver."""
    structure = model.structure
    padded = jax.tree.map(lambda x: jnp.concatenate([x, x[:1]], axis=0), model.joints)
    params = jax.tree.map(lambda x: x[joint_of_slot], padded)
    flags = joint_family.flags(structure)
    flags = joint_family.JointFlags(*(np.append(f, False)[joint_of_slot] for f in flags))
    world = structure.num_bodies
    body_a = np.append(structure.joint_body_a.array, world)[joint_of_slot]
    body_b = np.append(structure.joint_body_b.array, world)[joint_of_slot]
    return params, flags, body_a, body_b


def solve(model: Model, predicted: State, h: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Displacement (N, 3) and rotation (N, 3) that satisfy the joints from the prediction X*."""
    structure, options = model.structure, model.options
    n = structure.num_bodies
    zeros = jnp.zeros((n + 1, 3), predicted.pos.dtype)
    if structure.num_joints == 0:
        return zeros[:n], zeros[:n]

    identity = jnp.array([1.0, 0.0, 0.0, 0.0], predicted.quat.dtype)
    origin = _with_world_row(predicted.pos)
    quat = _with_world_row(predicted.quat, identity)
    inv_mass = _with_world_row(1.0 / model.bodies.mass)
    inv_inertia = _with_world_row(integrator.inverse_inertia(model, predicted, h))

    project = functools.partial(joint_family.project, rows=joint_family.rows_in_use(structure))

    def project_slots(params, flags, body_a, body_b, dx, dtheta, multipliers):
        pair = BodyPair(
            origin[body_a], origin[body_b], quat[body_a], quat[body_b],
            inv_mass[body_a], inv_mass[body_b], inv_inertia[body_a], inv_inertia[body_b],
            dx[body_a], dx[body_b], dtheta[body_a], dtheta[body_b],
        )  # fmt: skip
        moved, multipliers = jax.vmap(project)(params, flags, pair, multipliers)
        return pair, moved, multipliers

    if options.jacobi:
        joint_of_slot = np.arange(structure.num_joints)
        params, flags, body_a, body_b = _joint_layout(model, joint_of_slot)
        count = np.bincount(np.concatenate([body_a, body_b]), minlength=n + 1)
        share = jnp.asarray(1.0 / np.maximum(count, 1), predicted.pos.dtype)[:, None]

        def iteration(carry, _):
            dx, dtheta, multipliers = carry
            pair, moved, multipliers = project_slots(params, flags, body_a, body_b, dx, dtheta, multipliers)

            def averaged(side_a, side_b):
                total = jax.ops.segment_sum(side_a, body_a, n + 1) + jax.ops.segment_sum(side_b, body_b, n + 1)
                return total * share

            dx = dx + averaged(moved.dx_a - pair.dx_a, moved.dx_b - pair.dx_b)
            dtheta = dtheta + averaged(moved.dtheta_a - pair.dtheta_a, moved.dtheta_b - pair.dtheta_b)
            return (dx, dtheta, multipliers), None

        multipliers = jnp.zeros((structure.num_joints, joint_family.NUM_ROWS), predicted.pos.dtype)
    else:
        joint_of_slot = structure.colour_joint.array  # (C, K)
        params, flags, body_a, body_b = _joint_layout(model, joint_of_slot)
        body_slot = structure.colour_body_slot.array  # (C, N + 1)

        def colour_sweep(carry, colour):
            dx, dtheta = carry
            params_c, flags_c, body_a_c, body_b_c, body_slot_c, multipliers = colour
            _, moved, multipliers = project_slots(params_c, flags_c, body_a_c, body_b_c, dx, dtheta, multipliers)
            dx = jnp.concatenate([moved.dx_a, moved.dx_b, dx])[body_slot_c]
            dtheta = jnp.concatenate([moved.dtheta_a, moved.dtheta_b, dtheta])[body_slot_c]
            return (dx, dtheta), multipliers

        def iteration(carry, _):
            dx, dtheta, multipliers = carry
            colours = (params, flags, body_a, body_b, body_slot, multipliers)
            # Colours are unrolled (a model has few; a while loop per colour costs more on CPU
            # than the colour's work); iterations stay a loop so compile time does not grow.
            (dx, dtheta), multipliers = jax.lax.scan(colour_sweep, (dx, dtheta), colours, unroll=True)
            return (dx, dtheta, multipliers), None

        multipliers = jnp.zeros(joint_of_slot.shape + (joint_family.NUM_ROWS,), predicted.pos.dtype)

    (dx, dtheta, _), _ = jax.lax.scan(iteration, (zeros, zeros, multipliers), None, length=options.iterations)
    return dx[:n], dtheta[:n]
