"""Multi-body constraints (DBD 10): a rope's total length, a tetrahedron's volume."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd

NODES, SPACING, NODE_MASS = 30, 0.05, 0.02


def hanging_rope(total_length: bool, iterations: int = 8):
    """30 point-like nodes hanging straight down from a pin, joined by distance constraints."""
    b = dbd.ModelBuilder(gravity=(0, 0, -9.81))
    nodes = [b.add_body(pos=(0, 0, -i * SPACING), mass=NODE_MASS, inertia=(1e-6,) * 3) for i in range(NODES)]
    b.add_ball_joint(dbd.WORLD, nodes[0], anchor=(0, 0, 0))
    if total_length:
        b.add_rope(nodes)  # segments and the total length (DBD (118)-(121))
    else:
        for a, c in zip(nodes[:-1], nodes[1:], strict=True):
            b.add_distance(a, c, (0, 0, -a * SPACING), (0, 0, -c * SPACING))
    return b.finalize(dt=1 / 60, iterations=iterations)


def test_total_length_constraint_halves_the_stretch_of_a_hanging_rope():
    stretch, segment_error = {}, {}
    for total in (False, True):
        model = hanging_rope(total)
        _, trajectory = jax.jit(lambda s, m=model: dbd.rollout(m, s, steps=180))(dbd.init(model))
        pos = np.asarray(trajectory.pos)
        # How much longer than at rest the rope hangs (pin to last node), over the last second.
        stretch[total] = float(np.mean(np.linalg.norm(pos[-60:, -1], axis=-1))) - (NODES - 1) * SPACING
        lengths = np.linalg.norm(np.diff(pos[-60:], axis=1), axis=-1)
        segment_error[total] = float(np.mean(np.sum(np.abs(lengths - SPACING), axis=-1)))
    print(f"\nhanging 30-node rope, 8 iterations: stretch {stretch[False] * 1e3:.1f} mm with segments alone, "
          f"{stretch[True] * 1e3:.1f} mm with the total length; summed segment errors "
          f"{segment_error[False] * 1e3:.1f} mm -> {segment_error[True] * 1e3:.1f} mm")  # fmt: skip
    assert stretch[False] > 0.05  # the per-segment rope really does stretch at 8 iterations
    assert stretch[True] <= 0.5 * stretch[False]
    assert segment_error[True] < segment_error[False]


def squashed_tetrahedron(keep_volume: bool, load: float = 60.0):
    """Four 1 kg nodes on soft damped edge springs, squashed by a user force that pulls every node
    toward the weighted centre with weights (1, 1, 1, 6) times `load` N/m: the apex hardest. Each
    force points at the same centre and they sum to zero, so the load has no net force or torque
    in any pose (a dead load along z would make the squashed body buckle over)."""
    b = dbd.ModelBuilder(gravity=(0, 0, 0))
    corners = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.5, np.sqrt(3) / 2, 0.0), (0.5, np.sqrt(3) / 6, np.sqrt(2 / 3))]
    nodes = [b.add_body(pos=c, mass=1.0, inertia=(1e-3,) * 3) for c in corners]
    for i in range(4):
        for j in range(i + 1, 4):
            b.add_spring(nodes[i], nodes[j], corners[i], corners[j], stiffness=100.0, damping=5.0)

    def squash(pos, quat, vel, ang_vel, weights):
        centre = jnp.sum(weights[:, None] * pos, axis=0) / jnp.sum(weights)
        force = -weights[:, None] * (pos - centre)
        return force, jnp.zeros_like(force)

    b.add_force(nodes, squash, params=load * np.array([1.0, 1.0, 1.0, 6.0]))
    if keep_volume:
        b.add_volume(nodes)
    return b.finalize(dt=1 / 60, iterations=8)


def apex_height(pos):
    """Distance of node 3 from the plane of nodes 0, 1, 2."""
    normal = np.cross(pos[..., 1, :] - pos[..., 0, :], pos[..., 2, :] - pos[..., 0, :])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.einsum("...i,...i->...", pos[..., 3, :] - pos[..., 0, :], normal)


def tetrahedron_volume(pos):
    d = pos[..., 1:, :] - pos[..., :1, :]
    return np.einsum("...i,...i->...", d[..., 0, :], np.cross(d[..., 1, :], d[..., 2, :])) / 6.0


@pytest.mark.parametrize("keep_volume", [False, True])
def test_squashed_tetrahedron_keeps_its_volume(keep_volume):
    model = squashed_tetrahedron(keep_volume)
    rest = tetrahedron_volume(np.asarray(model.bodies.initial_pos))
    _, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=180))(dbd.init(model))
    pos = np.asarray(trajectory.pos)
    change = tetrahedron_volume(pos) / rest - 1.0
    apex_drop = 1.0 - apex_height(pos) / apex_height(np.asarray(model.bodies.initial_pos))
    print(
        f"\ntetrahedron (volume constraint {keep_volume}): apex height lost {apex_drop.max() * 100:.1f} %, "
        f"largest volume change {np.abs(change).max() * 100:.2f} %"
    )
    assert apex_drop.max() > 0.1  # it really was squashed (height down by more than 10 %)
    if keep_volume:
        assert np.abs(change).max() < 0.01
    else:
        assert np.abs(change).max() > 0.1  # without the constraint the load crushes it
