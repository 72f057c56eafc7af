"""Colouring of the constraint graph, done once at `finalize` on the host with numpy.

Two constraints that move a common dynamic body must not be projected at the same time (their
displacements would race). Constraints are the nodes here and share an edge when they share a
dynamic body; the world never conflicts. Greedy colouring gives colour groups in which every
body is touched at most once, so a whole group is projected at once with `jax.vmap` and its
displacements are written back with no conflicts: Gauss-Seidel at the parallelism of Jacobi.
The solver that uses these groups is `solvers/dbd.py`; it knows nothing of how they were made.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def greedy_colouring(constraint_bodies: Sequence[Sequence[int]], num_bodies: int) -> list[int]:
    """Colour of each constraint, given the bodies each one moves (world = any index < 0).

    Constraints are taken in order, each getting the smallest colour that none of its bodies
    already has. A chain gets 2 colours, a tree max-degree + 1 at most.
    """
    colours_of_body: list[set[int]] = [set() for _ in range(num_bodies)]
    result = []
    for bodies in constraint_bodies:
        dynamic = [b for b in bodies if b >= 0]
        taken = set().union(*(colours_of_body[b] for b in dynamic)) if dynamic else set()
        colour = 0
        while colour in taken:
            colour += 1
        for b in dynamic:
            colours_of_body[b].add(colour)
        result.append(colour)
    return result


def colour_tables(
    colours: Sequence[int], body_a: np.ndarray, body_b: np.ndarray, num_bodies: int
) -> tuple[np.ndarray, np.ndarray]:
    """The padded tables the solver scans over.

    Returns (colour_joint (C, K), colour_body_slot (C, N + 1)). Body index N is the world and
    joint index J an empty slot. After colour c is projected, body n's new displacement is row
    colour_body_slot[c, n] of [side a of slots 0..K-1, side b of slots 0..K-1, all N + 1 old
    rows]: a gather, never a scatter, because a colour moves each body at most once.
    """
    num_joints = len(colours)
    num_colours = max(colours) + 1 if num_joints else 1
    members = [[j for j in range(num_joints) if colours[j] == c] for c in range(num_colours)]
    slots = max(1, max(len(m) for m in members))
    colour_joint = np.full((num_colours, slots), num_joints, dtype=np.int32)
    untouched = 2 * slots + np.arange(num_bodies + 1, dtype=np.int32)
    colour_body_slot = np.tile(untouched, (num_colours, 1))
    for c, joints in enumerate(members):
        for k, j in enumerate(joints):
            colour_joint[c, k] = j
            a, b = body_a[j], body_b[j]
            if a < num_bodies:
                colour_body_slot[c, a] = k
            if b < num_bodies:
                colour_body_slot[c, b] = slots + k
    return colour_joint, colour_body_slot
