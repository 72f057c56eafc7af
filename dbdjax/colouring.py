"""Colouring of the constraint graph, done once at `finalize` on the host with numpy.

Two constraints that move a common dynamic body must not be projected at the same time (their
displacements would race). Constraint nodes (a joint with all its rows, a spring, a rope over
many bodies, ...) are the vertices here and share an edge when they share a dynamic body; the
world never conflicts. Greedy colouring gives colour groups in which every body is touched at
most once, so a whole group is projected at once with `jax.vmap` and its displacements are
written back with no conflicts: Gauss-Seidel at the parallelism of Jacobi. The colours' sizes
are then evened out without changing any body's order of projections (`even_colouring`). The
solver that uses these groups is `solvers/dbd.py`; it knows nothing of how they were made.
"""

from __future__ import annotations

import itertools
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


def even_colouring(constraint_bodies: Sequence[Sequence[int]], num_bodies: int, colours: Sequence[int]) -> list[int]:
    """The sweep of `colours` (a valid colouring of the constraints, given the bodies each one
    moves) with its colours' sizes evened out: the same number of colours, and on every body its
    constraints projected in the same order, so a Gauss-Seidel sweep computes the same thing.

    The solver pads every colour of a run to the run's largest (`solvers.dbd._Run`), so the cost of
    a sweep is the number of colours times the largest. Greedy colouring fills the first colours
    and leaves the last nearly empty: Brax's ant's 4 hips (all on the torso) and 4 ankles came as
    4, 2, 1, 1, a sweep of 16 projections for 8 joints; evened, 2, 2, 2, 2.

    List scheduling with deadlines: a constraint waits for those before it on each of its bodies,
    and must be placed by the colour that leaves room for the longest chain after it; each colour
    takes those due, then the ready ones that are due soonest, up to an even share. Returns
    `colours` as they are where evening does not make the largest colour smaller.
    """
    count = max(colours, default=-1) + 1
    if count < 2:
        return list(colours)
    on_body: list[list[tuple[int, int]]] = [[] for _ in range(num_bodies)]
    for k, (colour, bodies) in enumerate(zip(colours, constraint_bodies, strict=True)):
        for body in bodies:
            if 0 <= body < num_bodies:
                on_body[body].append((colour, k))
    after: list[list[int]] = [[] for _ in colours]  # the constraints that wait for each one
    waits_for = [0] * len(colours)
    for sequence in on_body:
        sequence.sort()
        for (_, first), (_, second) in itertools.pairwise(sequence):
            after[first].append(second)
            waits_for[second] += 1
    chain = [0] * len(colours)  # the longest chain of constraints after each one
    for k in sorted(range(len(colours)), key=lambda k: -colours[k]):
        chain[k] = max((chain[j] + 1 for j in after[k]), default=0)
    due = [count - 1 - c for c in chain]
    share = -(-len(colours) // count)
    result = [-1] * len(colours)
    ready = [k for k, w in enumerate(waits_for) if w == 0]
    for colour in range(count):
        ready.sort(key=lambda k: (due[k], colours[k], k))
        due_now = [k for k in ready if due[k] == colour]  # every one due is ready: those before are due sooner
        later = [k for k in ready if due[k] > colour]
        room = max(share - len(due_now), 0)
        taken, ready = due_now + later[:room], later[room:]
        for k in taken:
            result[k] = colour
            for j in after[k]:
                waits_for[j] -= 1
                if waits_for[j] == 0:
                    ready.append(j)
    widths = np.bincount(result, minlength=count)
    return result if widths.max() < np.bincount(colours).max() else list(colours)


def colour_groups(
    family_bodies: Sequence[np.ndarray], num_bodies: int, classes: Sequence[int | np.ndarray] | None = None
) -> tuple[Colour, ...]:
    """Colour the nodes of every constraint family together.

    family_bodies: one (M_f, S_f) int table per family, the bodies each node moves (index
    num_bodies = the world). classes: per family, one class for all its nodes or an (M_f,) int
    array of one class per node (default: all 0); nodes of different classes never share a colour,
    and lower classes get the lower colours. Each class is coloured greedily, then, where all its
    nodes are of one family, evened out (`even_colouring`). Returns the colour groups, each with
    its nodes per family and the gather table that writes the moved bodies back (see `Colour`).

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
        bodies = [family_bodies[nodes[k][0]][nodes[k][1]] for k in members]
        local = greedy_colouring(bodies, num_bodies)
        if len({nodes[k][0] for k in members}) == 1:
            # Evened within one family only: across families (the contact groups' class) it would
            # change which families each colour holds, and with them the solver's runs.
            local = even_colouring(bodies, num_bodies, local)
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
