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

`restitution` is the velocity pass after the position solve: the same coloured sweep over the
contact groups alone, moving velocities instead of displacements.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import constraints, integrator
from dbdjax.collision import ContactSlots
from dbdjax.constraints import Family
from dbdjax.constraints.rows import BodySet
from dbdjax.model import Colour, Model, State, with_world_row


def body_table(model: Model, state: State, h: float) -> BodySet:
    """The N + 1 rows every constraint reads (row N is the world), with nothing moved yet."""
    dtype = state.pos.dtype
    zeros = jnp.zeros((model.num_bodies + 1, 3), dtype)
    return BodySet(
        origin=with_world_row(state.pos),
        quat=with_world_row(state.quat, jnp.array([1.0, 0.0, 0.0, 0.0], dtype)),
        inv_mass=with_world_row(1.0 / model.bodies.mass),
        inv_inertia=with_world_row(integrator.inverse_inertia(model, state, h)),
        vel=with_world_row(state.vel),
        ang_vel=with_world_row(state.ang_vel),
        dx=zeros,
        dtheta=zeros,
    )


def _project(family: Family, table: BodySet, dx, dtheta, multipliers):
    """Every node of `family` at once: moved rows (M * S, 3) twice, and new multipliers."""
    bodies = table._replace(dx=dx, dtheta=dtheta)
    bodies = jax.tree.map(lambda column: column[family.bodies], bodies)  # (M, S, ...)
    moved_dx, moved_dtheta, multipliers = jax.vmap(family.project)(family.params, family.static, bodies, multipliers)
    return moved_dx.reshape(-1, 3), moved_dtheta.reshape(-1, 3), multipliers


def _gauss_seidel(
    colours: tuple[Colour, ...], families: list[Family], table: BodySet, iterations: int, multipliers: list
) -> tuple[jnp.ndarray, jnp.ndarray, list]:
    """`iterations` sweeps over the colours; multipliers: one (M_f, m_f) array per family, in
    node order, in and out. Returns (dx, dtheta) (N + 1, 3) and the final multipliers."""
    present = [[f for f, nodes in enumerate(colour.nodes) if len(nodes.array)] for colour in colours]
    groups = [[constraints.gather(families[f], colours[c].nodes[f].array) for f in fs] for c, fs in enumerate(present)]
    start = [[multipliers[f][colours[c].nodes[f].array] for f in fs] for c, fs in enumerate(present)]

    def iteration(carry, _):
        dx, dtheta, lams = carry
        updated = []
        for colour_groups, colour, colour_lams in zip(groups, colours, lams, strict=True):
            moved = [_project(f, table, dx, dtheta, lam) for f, lam in zip(colour_groups, colour_lams, strict=True)]
            slot = colour.body_slot.array
            dx = jnp.concatenate([m[0] for m in moved] + [dx])[slot]
            dtheta = jnp.concatenate([m[1] for m in moved] + [dtheta])[slot]
            updated.append([m[2] for m in moved])
        return (dx, dtheta, updated), None

    (dx, dtheta, lams), _ = jax.lax.scan(iteration, (table.dx, table.dtheta, start), None, length=iterations)
    result = list(multipliers)
    for f in range(len(families)):  # back to node order
        colours_with = [c for c, fs in enumerate(present) if f in fs]
        if not colours_with:
            continue
        order = np.concatenate([colours[c].nodes[f].array for c in colours_with])
        values = jnp.concatenate([lams[c][present[c].index(f)] for c in colours_with])
        result[f] = values[np.argsort(order)]
    return dx, dtheta, result


def _jacobi(families: list[Family], table: BodySet, iterations: int, multipliers: list):
    """Every node at once from the same dX; each body moves by the mean of its nodes' requests."""
    n = table.dx.shape[0] - 1
    used = [f for f, family in enumerate(families) if len(family.bodies)]
    touched = np.concatenate([families[f].bodies.reshape(-1) for f in used])
    share = jnp.asarray(1.0 / np.maximum(np.bincount(touched, minlength=n + 1), 1), table.dx.dtype)[:, None]

    def iteration(carry, _):
        dx, dtheta, lams = carry
        moved = [_project(families[f], table, dx, dtheta, lam) for f, lam in zip(used, lams, strict=True)]
        dx_rows = jnp.concatenate([m[0] for m in moved]) - dx[touched]
        dtheta_rows = jnp.concatenate([m[1] for m in moved]) - dtheta[touched]
        dx = dx + jax.ops.segment_sum(dx_rows, touched, n + 1) * share
        dtheta = dtheta + jax.ops.segment_sum(dtheta_rows, touched, n + 1) * share
        return (dx, dtheta, [m[2] for m in moved]), None

    start = [multipliers[f] for f in used]
    (dx, dtheta, lams), _ = jax.lax.scan(iteration, (table.dx, table.dtheta, start), None, length=iterations)
    result = list(multipliers)
    for f, lam in zip(used, lams, strict=True):
        result[f] = lam
    return dx, dtheta, result


def solve(
    model: Model, predicted: State, control: jnp.ndarray | None, contacts: tuple[ContactSlots, ...], h: float,
    start: State | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, tuple[jnp.ndarray, ...]]:  # fmt: skip
    """Displacement (N, 3) and rotation (N, 3) that satisfy the constraints from the prediction X*.

    control: (num_controls,) or None, the drive and motor targets of this step. contacts: this
    substep's slots (collision.detect). h: substep (s). start: the state the substep began from
    (the joints' armature rows read the rotor's own motion from it; None: from the prediction).
    Also returns each contact group's normal multipliers lambda_n (C, P) (the restitution pass
    reads which points pushed).
    """
    structure, options = model.structure, model.options
    n = structure.num_bodies
    dtype = predicted.pos.dtype
    all_families = constraints.families(model, control, contacts, h, dtype, predicted=predicted, start=start)
    multipliers = [jnp.zeros((len(f.bodies), f.num_multipliers), dtype) for f in all_families]
    if any(len(f.bodies) for f in all_families):
        table = body_table(model, predicted, h)
        if options.jacobi:
            dx, dtheta, multipliers = _jacobi(all_families, table, options.iterations, multipliers)
        else:
            dx, dtheta, multipliers = _gauss_seidel(structure.colours, all_families, table, options.iterations,
                                                    multipliers)  # fmt: skip
    else:
        dx = dtheta = jnp.zeros((n + 1, 3), dtype)
    contact_lams = multipliers[len(all_families) - len(contacts) :]
    normal = tuple(lam.reshape(len(lam), -1, 4)[..., 0] for lam in contact_lams)
    return dx[:n], dtheta[:n], normal


def restitution(
    model: Model, state: State, contacts: tuple[ContactSlots, ...], normal: tuple[jnp.ndarray, ...], h: float
) -> State:
    """The velocity pass after the position solve (contacts.project_restitution), on `state`
    (the state after the substep's displacements were applied)."""
    if not contacts:
        return state
    families = constraints.restitution_families(model, contacts, h)
    table = body_table(model, state, h)
    dv, dw, _ = _gauss_seidel(model.structure.contact_colours, families, table, model.options.restitution_iterations,
                              list(normal))  # fmt: skip
    n = model.num_bodies
    return State(pos=state.pos, quat=state.quat, vel=state.vel + dv[:n], ang_vel=state.ang_vel + dw[:n])
