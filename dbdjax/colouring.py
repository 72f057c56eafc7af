"""Colouring of the constraint graph, done once at `finalize` on the host with numpy.

Two constraints that move a common dynamic body must not be projected at the same time (their
displacements would race). Constraint nodes (a joint with all its rows, a spring, a rope over
many bodies, ...) are the vertices here and share an edge when they share a dynamic body; the
world never conflicts. Greedy colouring gives colour groups in which every body is touched at
most once, so a whole group is projected at once with `jax.vmap` and its displacements are
written back with no conflicts: Gauss-Seidel at the parallelism of Jacobi. The solver that uses
these groups is `solvers/dbd.py`; it knows nothing of how they were made.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dbdjax.model import Colour, StaticArray


def greedy_colouring(constraint_bodies: Sequence[Sequence[int]], num_bodies: int) -> list[int]:
    """Colour of each constraint, given the bodies each one moves (indices outside
    [0, num_bodies) are the world).

    Constraints are taken in order, each getting the smallest colour that none of its bodies
    already has. A chain gets 2 colours, a tree max-degree + 1 at most.
    """
    colours_of_body: list[set[int]] = [set() for _ in range(num_bodies)]
    result = []
    for bodies in constraint_bodies:
        dynamic = [b for b in bodies if 0 <= b < num_bodies]
        taken = set().union(*(colours_of_body[b] for b in dynamic)) if dynamic else set()
        colour = 0
        while colour in taken:
            colour += 1
        for b in dynamic:
            colours_of_body[b].add(colour)
        result.append(colour)
    return result


def colour_groups(
    family_bodies: Sequence[np.ndarray], num_bodies: int, classes: Sequence[int | np.ndarray] | None = None
) -> tuple[Colour, ...]:
    """Colour the nodes of every constraint family together.

    family_bodies: one (M_f, S_f) int table per family, the bodies each node moves (index
    num_bodies = the world). classes: per family, one class for all its nodes or an (M_f,) int
    array of one class per node (default: all 0); nodes of different classes never share a colour,
    and lower classes get the lower colours. Returns the colour groups, each with its nodes per
    family and the gather table that writes the moved bodies back (see `Colour`).

    The solver projects every family (every variant of a family: the joints by kind) present in a
    colour as one vmapped call, so the cost of an iteration (and the size of the compiled program)
    grows with the number of (colour, variant) pairs, not only with the number of colours. The
    builder gives each family and each kind of joint a class of its own (`builder.colour_classes`),
    and the contact groups one class together: a ragdoll's 15 floor contacts, each on its own body,
    then fill one colour (two families) instead of being spread over the joints' colours.
    """
    classes = [0] * len(family_bodies) if classes is None else list(classes)
    if len(classes) != len(family_bodies):
        raise ValueError(f"colour_groups: {len(classes)} classes for {len(family_bodies)} families")
    per_family = [np.asarray(c, np.int64) for c in classes]
    for f, (c, table) in enumerate(zip(per_family, family_bodies, strict=True)):
        if c.ndim and c.shape != (len(table),):
            raise ValueError(f"colour_groups: family {f} has {len(table)} nodes, its classes shape {c.shape}")
    nodes = [(f, m) for f, table in enumerate(family_bodies) for m in range(len(table))]
    node_class = [int(c) for c, table in zip(per_family, family_bodies, strict=True)
                  for c in np.broadcast_to(c, (len(table),))]  # fmt: skip
    colours = [0] * len(nodes)
    first = 0
    for kind in sorted(set(node_class)):
        members = [k for k, c in enumerate(node_class) if c == kind]
        local = greedy_colouring([family_bodies[nodes[k][0]][nodes[k][1]] for k in members], num_bodies)
        for k, colour in zip(members, local, strict=True):
            colours[k] = first + colour
        first += max(local, default=-1) + 1
    groups = []
    for colour in range(max(colours, default=-1) + 1):
        members = [[m for (f, m), c in zip(nodes, colours, strict=True) if f == family and c == colour]
                   for family in range(len(family_bodies))]  # fmt: skip
        body_slot = write_back_slots(
            [table[indices] for table, indices in zip(family_bodies, members, strict=True)], num_bodies
        )
        groups.append(
            Colour(
                nodes=tuple(StaticArray(np.asarray(indices, dtype=np.int32)) for indices in members),
                body_slot=StaticArray(body_slot),
            )
        )
    return tuple(groups)


def kind_classes(kinds: Sequence[np.ndarray], count: int) -> np.ndarray:
    """The colouring class (`colour_groups`) of each of `count` nodes, given the members (K,) int
    of each kind of node (the joints by kind, `joints.variants`): one class per kind, so that a
    colour projects one kind. The kinds take their classes in the reverse of the order their first
    node came (the hinges first on Brax's humanoid and on the ragdoll): chosen by measurement, as
    the Gauss-Seidel order moves results. The other way round the ragdoll's demo keyframes toppled
    it (tests/test_ragdoll.py, slow); this way the dropped humanoid's largest gap at 1 x 4 is
    3.64 mm instead of 2.96."""
    classes = np.zeros(count, np.int64)
    for k, members in enumerate(sorted(kinds, key=lambda members: -members[0])):
        classes[members] = k
    return classes


def write_back_slots(tables: Sequence[np.ndarray], num_bodies: int, real: Sequence[int] | None = None) -> np.ndarray:
    """Where each body's displacement is found after a colour (`Colour.body_slot`), (N + 1,) int.

    tables: per family, the (M_f, S_f) bodies of the nodes projected in the colour, laid out as
    the solver concatenates their rows: every family's node rows in order (each node's S_f bodies
    in turn), then the N + 1 previous rows (a body no node moves keeps its previous row). real: the
    number of leading nodes of each table whose rows are read back (the rest pad the table; all by
    default). The world (num_bodies) is never read back."""
    real = [len(table) for table in tables] if real is None else real
    rows = sum(table.shape[0] * table.shape[1] for table in tables)
    body_slot = rows + np.arange(num_bodies + 1, dtype=np.int32)
    offset = 0
    for table, count in zip(tables, real, strict=True):
        for m, node in enumerate(table):
            for s, body in enumerate(node):
                if m < count and body < num_bodies:
                    body_slot[body] = offset + m * table.shape[1] + s
        offset += table.shape[0] * table.shape[1]
    return body_slot
