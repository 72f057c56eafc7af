"""DBD Algorithm 1: non-linear Gauss-Seidel over colour groups.

    prepare:  inverse masses and world inverse inertias at X* (once per substep), and each
              colour's constraint parameters gathered into its own arrays
    repeat `iterations` times:                                   (lax.scan)
        for each colour, in order:                               (unrolled: a model has few)
            for each constraint family present in the colour:
                project all its nodes at once                    (jax.vmap, constraints/*.py)
            write back the displacements of the bodies moved     (one gather: no conflicts)

Only displacements dX from X* are accumulated; the caller applies them with (36)-(39).
With `jacobi`, every node is projected at once from the same dX and each body moves by the
average of what its nodes ask (for comparison; it converges more slowly).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import constraints, integrator
from dbdjax.constraints import Family
from dbdjax.constraints.rows import BodySet
from dbdjax.model import Model, State


def _with_world_row(array: jnp.ndarray, world_value: jnp.ndarray | float = 0.0) -> jnp.ndarray:
    """Append the world as body N (static: zero inverse mass and inertia, identity pose)."""
    row = jnp.broadcast_to(jnp.asarray(world_value, array.dtype), (1,) + array.shape[1:])
    return jnp.concatenate([array, row], axis=0)


def solve(model: Model, predicted: State, control: jnp.ndarray | None, h: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Displacement (N, 3) and rotation (N, 3) that satisfy the constraints from the prediction X*.

    control: (num_controls,) or None, the drive and motor targets of this step. h: substep (s).
    """
    structure, options = model.structure, model.options
    n = structure.num_bodies
    dtype = predicted.pos.dtype
    zeros = jnp.zeros((n + 1, 3), dtype)
    all_families = constraints.families(model, control, h, dtype)
    if not any(len(f.bodies) for f in all_families):
        return zeros[:n], zeros[:n]

    identity = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    table = BodySet(
        origin=_with_world_row(predicted.pos),
        quat=_with_world_row(predicted.quat, identity),
        inv_mass=_with_world_row(1.0 / model.bodies.mass),
        inv_inertia=_with_world_row(integrator.inverse_inertia(model, predicted, h)),
        vel=_with_world_row(predicted.vel),
        ang_vel=_with_world_row(predicted.ang_vel),
        dx=zeros,
        dtheta=zeros,
    )

    def project(family: Family, dx, dtheta, multipliers):
        """Every node of `family` at once: moved rows (M * S, 3) twice, and new multipliers."""
        bodies = table._replace(dx=dx, dtheta=dtheta)
        bodies = jax.tree.map(lambda column: column[family.bodies], bodies)  # (M, S, ...)
        moved_dx, moved_dtheta, multipliers = jax.vmap(family.project)(
            family.params, family.static, bodies, multipliers
        )
        return moved_dx.reshape(-1, 3), moved_dtheta.reshape(-1, 3), multipliers

    def zero_multipliers(groups):
        return [jnp.zeros((len(f.bodies), f.num_multipliers), dtype) for f in groups]

    if options.jacobi:
        groups = [f for f in all_families if len(f.bodies)]
        touched = np.concatenate([f.bodies.reshape(-1) for f in groups])
        share = jnp.asarray(1.0 / np.maximum(np.bincount(touched, minlength=n + 1), 1), dtype)[:, None]

        def iteration(carry, _):
            dx, dtheta, multipliers = carry
            moved = [project(f, dx, dtheta, lam) for f, lam in zip(groups, multipliers, strict=True)]
            before = jax.tree.map(lambda column: column[touched], (dx, dtheta))
            dx_rows = jnp.concatenate([m[0] for m in moved]) - before[0]
            dtheta_rows = jnp.concatenate([m[1] for m in moved]) - before[1]
            dx = dx + jax.ops.segment_sum(dx_rows, touched, n + 1) * share
            dtheta = dtheta + jax.ops.segment_sum(dtheta_rows, touched, n + 1) * share
            return (dx, dtheta, [m[2] for m in moved]), None

        multipliers = zero_multipliers(groups)
    else:
        colours = [
            [constraints.gather(f, nodes.array)
             for f, nodes in zip(all_families, colour.nodes[: len(all_families)], strict=True) if len(nodes.array)]
            for colour in structure.colours
        ]  # fmt: skip
        # Families the colouring knows but no projection exists for yet (the contact groups until
        # the contact solver lands): their rows in the body_slot gather keep the bodies' current moves.
        tables = structure.family_bodies()
        pending = [
            np.concatenate([tables[k][nodes.array].reshape(-1) for k, nodes in enumerate(colour.nodes)
                            if k >= len(all_families)] + [np.zeros(0, np.int64)])
            for colour in structure.colours
        ]  # fmt: skip

        def iteration(carry, _):
            dx, dtheta, multipliers = carry
            updated = []
            for groups, colour, lams, kept in zip(colours, structure.colours, multipliers, pending, strict=True):
                moved = [project(f, dx, dtheta, lam) for f, lam in zip(groups, lams, strict=True)]
                slot = colour.body_slot.array
                dx = jnp.concatenate([m[0] for m in moved] + [dx[kept], dx])[slot]
                dtheta = jnp.concatenate([m[1] for m in moved] + [dtheta[kept], dtheta])[slot]
                updated.append([m[2] for m in moved])
            return (dx, dtheta, updated), None

        multipliers = [zero_multipliers(groups) for groups in colours]

    (dx, dtheta, _), _ = jax.lax.scan(iteration, (zeros, zeros, multipliers), None, length=options.iterations)
    return dx[:n], dtheta[:n]
