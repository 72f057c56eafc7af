"""Host-side shape geometry for `finalize`: mass properties and which shape pairs may touch.

Numpy only, run once when a model is built. The narrow phase that runs inside the step is
`collision.py`; the contact constraint is `constraints/contacts.py`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dbdjax import host_math
from dbdjax.collision import BOX, CAPSULE, SPHERE


def volume_and_inertia(kind: int, size: np.ndarray) -> tuple[float, np.ndarray]:
    """Volume (m^3) and inertia per unit density about the shape's centre, in its own frame.

    size: (3,) as in `Shapes.size`. Returns (volume, (3,) principal moments / density, m^5).
    A capsule is a cylinder of length 2 half_length plus two hemispheres along its local z.
    """
    if kind == SPHERE:
        radius = size[0]
        volume = 4.0 / 3.0 * np.pi * radius**3
        return volume, np.full(3, 0.4 * volume * radius**2)
    if kind == BOX:
        volume = 8.0 * np.prod(size)
        squared = size**2
        return volume, volume / 3.0 * np.array(
            [squared[1] + squared[2], squared[0] + squared[2], squared[0] + squared[1]]
        )
    if kind == CAPSULE:
        radius, half = size[0], size[1]
        cylinder = np.pi * radius**2 * 2.0 * half
        ball = 4.0 / 3.0 * np.pi * radius**3
        axial = cylinder * radius**2 / 2.0 + ball * 0.4 * radius**2
        # each hemisphere: 2/5 m r^2 about its flat face's diameter, centroid 3r/8 from the face,
        # the face half_length from the centre: together m (2/5 r^2 + h^2 + 3/4 h r)
        transverse = cylinder * (radius**2 / 4.0 + (2.0 * half) ** 2 / 12.0) + ball * (
            0.4 * radius**2 + half**2 + 0.75 * half * radius
        )
        return cylinder + ball, np.array([transverse, transverse, axial])
    raise ValueError(f"shape kind {kind} has no volume (a plane is static)")


def mass_properties(
    kinds: Sequence[int], sizes: Sequence[np.ndarray], positions: Sequence[np.ndarray],
    quats: Sequence[np.ndarray], densities: Sequence[float],
) -> tuple[float, np.ndarray, np.ndarray]:  # fmt: skip
    """Mass (kg), centre of mass (3,) and inertia tensor (3, 3) about it of shapes in one frame.

    positions/quats: each shape's pose in that frame; densities kg/m^3.
    """
    mass, moment, tensor = 0.0, np.zeros(3), np.zeros((3, 3))
    parts = []
    for kind, size, pos, quat, density in zip(kinds, sizes, positions, quats, densities, strict=True):
        volume, inertia = volume_and_inertia(kind, size)
        rotation = host_math.to_matrix(quat)
        parts.append((density * volume, pos, rotation @ np.diag(density * inertia) @ rotation.T))
        mass += density * volume
        moment += density * volume * pos
    centre = moment / mass
    for part_mass, pos, part_tensor in parts:
        offset = pos - centre
        tensor += part_tensor + part_mass * host_math.parallel_axis(offset)
    return mass, centre, tensor


def principal_axes(tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(moments (3,), quat (4,)) such that tensor = R diag(moments) R^T with R = rotation(quat).

    A tensor that is already diagonal keeps the identity (no needless reordering of axes).
    """
    scale = max(np.max(np.abs(tensor)), 1e-300)
    if np.max(np.abs(tensor - np.diag(np.diag(tensor)))) <= 1e-12 * scale:
        return np.diag(tensor).copy(), np.array([1.0, 0.0, 0.0, 0.0])
    moments, axes = np.linalg.eigh(tensor)
    if np.linalg.det(axes) < 0.0:
        axes[:, 2] = -axes[:, 2]
    return moments, host_math.from_matrix(axes)


def may_collide(contype_a: int, conaffinity_a: int, contype_b: int, conaffinity_b: int) -> bool:
    """MuJoCo's rule: two shapes may touch when (contype_a & conaffinity_b) or (contype_b & conaffinity_a)."""
    return bool((contype_a & conaffinity_b) or (contype_b & conaffinity_a))
