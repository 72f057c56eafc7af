"""Quaternions in float64 numpy, for build time (`ModelBuilder`, `shapes`, `ik` setup).

The step uses `dbdjax.math` (jax, the default float32); model construction stays in numpy
float64 on the host so local anchors and inertial frames are exact before they are cast.
Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import numpy as np


def rotate(quat: np.ndarray, vector: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Rotate `vector` (3,) by unit `quat` (or by its inverse)."""
    w, u = quat[0], quat[1:] * (-1.0 if inverse else 1.0)
    t = 2.0 * np.cross(u, vector)
    return vector + w * t + np.cross(u, t)


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p q."""
    pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def to_matrix(quat: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a unit quaternion."""
    return np.stack([rotate(quat, axis) for axis in np.eye(3)], axis=1)


def from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w >= 0) of a proper rotation matrix (Shepperd's method)."""
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


def z_to(normal: np.ndarray) -> np.ndarray:
    """The shortest-arc rotation taking +z to unit `normal` (half a turn about x for -z)."""
    raw = np.array([1.0 + normal[2], -normal[1], normal[0], 0.0])
    size = np.linalg.norm(raw)
    return raw / size if size > 1e-9 else np.array([0.0, 1.0, 0.0, 0.0])


def parallel_axis(offset: np.ndarray) -> np.ndarray:
    """|r|^2 1 - r r^T (= -[r]x [r]x): the inertia of a unit mass at `offset`, for the
    parallel-axis theorem."""
    return (offset @ offset) * np.eye(3) - np.outer(offset, offset)
