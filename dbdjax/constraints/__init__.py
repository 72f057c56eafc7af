"""Constraint families. Each is data (struct of arrays, one row per constraint) plus a pure
projection that moves the displacements of the bodies it touches (DBD Algorithm 1, inner loop).
`rows.py` holds the scalar row updates every family is built from; `families` lists a model's
families in the order of `Structure.family_bodies`, which is the order the colouring uses.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.collision import ContactSlots
from dbdjax.constraints import contacts as contact
from dbdjax.constraints import forces, joints, links, multibody, targets
from dbdjax.indexing import take
from dbdjax.model import Model, State


class Family(NamedTuple):
    """One constraint family of a model, ready for the solver.

    bodies: (M, S) int, the bodies of each node (index N = the world).
    params: pytree of arrays with leading axis M (differentiable model leaves, controls).
    static: pytree of numpy arrays with leading axis M (flags fixed at finalize).
    project(params, static, bodies: BodySet, multipliers) -> (dx (S, 3), dtheta (S, 3), multipliers),
      for one node (the solver vmaps it). num_multipliers: the size of one node's multipliers.
    variants: ((nodes (K,) int, project), ...) partitioning the nodes, each part with a projection
      that traces only the rows its nodes have (the joints, by kind); () for one projection of all.
    """

    name: str
    bodies: np.ndarray
    params: Any
    static: Any
    project: Callable
    num_multipliers: int
    variants: tuple = ()


def families(model: Model, control: jnp.ndarray | None, contacts: tuple[ContactSlots, ...], h: float,
             dtype, predicted: State | None = None, start: State | None = None) -> list[Family]:  # fmt: skip
    """Every constraint family of `model`, with this step's control and contact slots, for
    substeps of h seconds (contact groups last). predicted, start: the substep's prediction X*
    and the state it began from (for the joints' armature rows, `joints.rotor_offsets`)."""
    structure = model.structure
    tables = structure.family_bodies()
    world = structure.num_bodies

    def on_world(table: np.ndarray) -> np.ndarray:
        return table == world

    gear = None if model.torques is None else model.torques.gear
    offsets = reference = None
    if start is not None and predicted is not None and structure.joint_rotor.array.any():
        offsets, reference = joints.rotor_offsets(model, predicted, start, h, with_reference=True)
    joint_targets = joints.targets(structure, control, dtype, gear, offsets, reference)

    def project_joints(rows):
        return lambda p, flag, bodies, lam: joints.project(p[0], flag, p[1], bodies, lam, h, rows)

    result = [
        Family(
            "joints", tables[0], (model.joints, joint_targets), joints.flags(structure),
            project_joints(joints.rows_in_use(structure)), joints.NUM_MULTIPLIERS,
            tuple((members, project_joints(rows)) for members, rows in joints.variants(structure)),
        ),
        Family("springs", tables[1], model.springs, on_world(tables[1]),
               functools.partial(links.project_spring, h=h), 1),
        Family("distances", tables[2], model.distances, on_world(tables[2]), links.project_distance, 1),
        Family("ropes", tables[3], model.ropes, ~on_world(tables[3]), multibody.project_rope, 1),
        Family("volumes", tables[4], model.volumes, np.zeros(len(tables[4]), bool),
               lambda p, _, bodies, lam: multibody.project_volume(p, bodies, lam), 1),
    ]  # fmt: skip
    force_tables = tables[5 : 5 + len(structure.force_groups)]
    for group, params, table in zip(structure.force_groups, model.forces, force_tables, strict=True):
        k = table.shape[1]
        project = functools.partial(_project_force_flat, group.function, h=h, k=k)
        result.append(Family(group.name, table, params, np.zeros(len(table), bool), project, 6 * k))
    ik_table = tables[5 + len(structure.force_groups)]
    if len(ik_table):
        ik_params = (model.ik_targets, targets.goals(structure, model.ik_targets, control, dtype))
    else:  # no targets: nothing to gather (model.ik_targets may be None)
        ik_params = (None, jnp.zeros((0, 3), dtype))
    result.append(Family("ik_targets", ik_table, ik_params, np.zeros(len(ik_table), bool),
                         lambda p, _, bodies, lam: targets.project(p[0], p[1], bodies, lam, h), 3))  # fmt: skip
    compliance_h2 = model.options.contact_compliance / h**2
    for group, slots in zip(structure.contact_groups, contacts, strict=True):
        project = functools.partial(
            contact.project_contacts, compliance_h2=compliance_h2, sweeps=contact.sweeps(group.num_points)
        )
        result.append(Family(group.name, group.bodies.array, slots, on_world(group.bodies.array), project,
                             contact.MULTIPLIERS_PER_POINT * group.num_points))  # fmt: skip
    return result


def restitution_families(model: Model, contacts: tuple[ContactSlots, ...], h: float) -> list[Family]:
    """The contact groups as velocity-pass families (multipliers: the solve's lambda_n (P,)).
    Impacts slower than 2 |g| h do not bounce: that is the speed gravity alone builds up in a
    substep or two, and bouncing it would keep resting bodies jittering."""
    slow = 2.0 * math.safe_norm(model.gravity) * h
    return [
        Family(group.name, group.bodies.array, slots, group.bodies.array == model.num_bodies,
               functools.partial(contact.project_restitution, slow=slow, sweeps=contact.sweeps(group.num_points)),
               group.num_points)
        for group, slots in zip(model.structure.contact_groups, contacts, strict=True)
    ]  # fmt: skip


def _project_force_flat(function, params, _, bodies, multipliers, h, k):
    dx, dtheta, kappa = forces.project_force(function, params, bodies, jnp.reshape(multipliers, (k, 6)), h)
    return dx, dtheta, jnp.reshape(kappa, (-1,))


def gather(family: Family, nodes: np.ndarray) -> Family:
    """The family restricted to `nodes` (static indices), parameters gathered once."""
    return family._replace(
        bodies=family.bodies[nodes],
        params=jax.tree.map(lambda x: take(x, nodes), family.params),
        static=jax.tree.map(lambda x: take(x, nodes), family.static),
    )
