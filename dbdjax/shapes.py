"""Host-side shape geometry for `finalize`: mass properties and which shape pairs may touch.

Numpy only, run once when a model is built. The narrow phase that runs inside the step is
`collision.py`; the contact constraint is `constraints/contacts.py`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

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


def rotation_matrix(quat: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quat
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation matrix (Shepperd's method)."""
    trace = np.trace(rotation)
    if trace > 0.0:
        s = 2.0 * np.sqrt(1.0 + trace)
        quat = [0.25 * s, (rotation[2, 1] - rotation[1, 2]) / s, (rotation[0, 2] - rotation[2, 0]) / s,
                (rotation[1, 0] - rotation[0, 1]) / s]  # fmt: skip
    else:
        i = int(np.argmax(np.diag(rotation)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + rotation[i, i] - rotation[j, j] - rotation[k, k])
        quat = [0.0, 0.0, 0.0, 0.0]
        quat[0] = (rotation[k, j] - rotation[j, k]) / s
        quat[1 + i] = 0.25 * s
        quat[1 + j] = (rotation[j, i] + rotation[i, j]) / s
        quat[1 + k] = (rotation[k, i] + rotation[i, k]) / s
    quat = np.asarray(quat)
    return quat / np.linalg.norm(quat) * (1.0 if quat[0] >= 0.0 else -1.0)


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
        rotation = rotation_matrix(quat)
        parts.append((density * volume, pos, rotation @ np.diag(density * inertia) @ rotation.T))
        mass += density * volume
        moment += density * volume * pos
    centre = moment / mass
    for part_mass, pos, part_tensor in parts:
        offset = pos - centre
        tensor += part_tensor + part_mass * (offset @ offset * np.eye(3) - np.outer(offset, offset))
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
    return moments, matrix_to_quat(axes)


def may_collide(contype_a: int, conaffinity_a: int, contype_b: int, conaffinity_b: int) -> bool:
    """MuJoCo's rule: two shapes may touch when (contype_a & conaffinity_b) or (contype_b & conaffinity_a)."""
    return bool((contype_a & conaffinity_b) or (contype_b & conaffinity_a))
