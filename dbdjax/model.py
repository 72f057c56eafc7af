"""The data the engine runs on: `Model` (structure + differentiable parameters) and `State`.

Everything is a plain frozen dataclass registered as a JAX pytree. Float arrays are pytree
leaves, so `jax.grad` reaches masses, inertias, joint anchors, limits and the rest. Structure
(counts, joint kinds, body indices, colour groups) lives in `Structure`, a static (hashable)
field: changing it means a new model and a new compilation, changing a float does not.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

WORLD = -1
"""Body index of the static world, accepted wherever a body index is."""

# Joint kinds (`Structure.joint_kind`).
BALL, HINGE, SLIDER, FIXED = 0, 1, 2, 3
JOINT_KIND_NAMES = ("ball", "hinge", "slider", "fixed")


def _pytree(cls, meta: tuple[str, ...] = ()):
    """Register a frozen dataclass as a pytree whose `meta` fields are static."""
    fields = [f.name for f in dataclasses.fields(cls)]
    data = [name for name in fields if name not in meta]
    return jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=list(meta))


@dataclasses.dataclass(frozen=True, eq=False)
class StaticArray:
    """A numpy array that can sit in a static pytree field: hashed and compared by value.

    Index arrays are compile-time constants of the step; keeping them out of the leaves means
    `jax.grad(loss)(model)` sees only float parameters.
    """

    array: np.ndarray

    def __post_init__(self):
        self.array.setflags(write=False)
        object.__setattr__(self, "_hash", hash((self.array.shape, self.array.dtype.str, self.array.tobytes())))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: Any) -> bool:
        return (
            isinstance(other, StaticArray)
            and self.array.shape == other.array.shape
            and self.array.dtype == other.array.dtype
            and bool(np.array_equal(self.array, other.array))
        )

    def __repr__(self) -> str:
        return f"StaticArray(shape={self.array.shape}, dtype={self.array.dtype})"


@dataclasses.dataclass(frozen=True)
class State:
    """Dynamic state of N bodies, at their centres of mass, in world coordinates (SI units).

    pos: (..., N, 3) m. quat: (..., N, 4) body-to-world rotation (w, x, y, z).
    vel: (..., N, 3) m/s. ang_vel: (..., N, 3) rad/s, world frame.
    Leading axes are batch axes (the step is written for none and vmapped over them).
    """

    pos: jnp.ndarray
    quat: jnp.ndarray
    vel: jnp.ndarray
    ang_vel: jnp.ndarray


State = _pytree(State)


@dataclasses.dataclass(frozen=True)
class Bodies:
    """Per-body parameters, N rows. Inertia is diagonal in the body frame (kg m^2)."""

    mass: jnp.ndarray  # (N,) kg
    inertia: jnp.ndarray  # (N, 3) principal moments, body frame
    initial_pos: jnp.ndarray  # (N, 3)
    initial_quat: jnp.ndarray  # (N, 4)
    initial_vel: jnp.ndarray  # (N, 3)
    initial_ang_vel: jnp.ndarray  # (N, 3)


Bodies = _pytree(Bodies)


@dataclasses.dataclass(frozen=True)
class Joints:
    """Per-joint parameters, J rows, in the local frames of the two bodies.

    Body a is the first body given to `add_*_joint` (the parent), body b the second. For a side
    that is the world, "local" means world coordinates.
    local_anchor_a/b: (J, 3) the joint point in each body frame, m.
    local_axis_a/b: (J, 3) unit hinge axis / slider axis / ball twist axis in each body frame.
    rest_rotation: (J, 4) q_a^-1 q_b at build time: the relative rotation that counts as zero.
    lower/upper: (J,) hinge angle or ball twist limits (rad), slider limits (m).
    cone_limit: (J,) largest angle between the twist axes of a ball joint, rad.
    relaxation: (J,) xi of DBD (46). regularization: (J,) alpha of DBD (47)-(52).
    """

    local_anchor_a: jnp.ndarray
    local_anchor_b: jnp.ndarray
    local_axis_a: jnp.ndarray
    local_axis_b: jnp.ndarray
    rest_rotation: jnp.ndarray
    lower: jnp.ndarray
    upper: jnp.ndarray
    cone_limit: jnp.ndarray
    relaxation: jnp.ndarray
    regularization: jnp.ndarray


Joints = _pytree(Joints)


@dataclasses.dataclass(frozen=True)
class Structure:
    """Static structure of a model: counts, indices and the colouring of the constraint graph.

    Body index N (one past the last body) is the world in the index arrays below.
    joint_body_a/b: (J,) int. joint_kind: (J,) int (BALL, HINGE, SLIDER, FIXED).
    joint_has_limits / joint_has_cone: (J,) bool.
    colour_joint: (C, K) int, the joint in each slot of each colour; J marks an empty slot.
    colour_body_slot: (C, N + 1) int, where each body's displacement is found after colour c:
      an index into [side a of slots 0..K-1, side b of slots 0..K-1, the N + 1 previous rows].
    """

    num_bodies: int
    num_joints: int
    num_controls: int
    joint_body_a: StaticArray
    joint_body_b: StaticArray
    joint_kind: StaticArray
    joint_has_limits: StaticArray
    joint_has_cone: StaticArray
    colour_joint: StaticArray
    colour_body_slot: StaticArray
    body_names: tuple[str, ...]
    joint_names: tuple[str, ...]

    @property
    def num_colours(self) -> int:
        return self.colour_joint.array.shape[0]


@dataclasses.dataclass(frozen=True)
class Options:
    """Static simulation settings chosen at `finalize`."""

    dt: float
    substeps: int
    iterations: int
    solver: str  # "dbd"
    jacobi: bool  # all joints at once, averaged per body, instead of coloured Gauss-Seidel
    velocity_dependent_inertia: bool  # DBD (58)
    checkpoint: bool  # jax.checkpoint each substep to keep reverse-mode memory flat


@dataclasses.dataclass(frozen=True)
class Model:
    """A simulatable model: `bodies`, `joints` and `gravity` are differentiable leaves."""

    bodies: Bodies
    joints: Joints
    gravity: jnp.ndarray  # (3,) m/s^2
    structure: Structure
    options: Options

    @property
    def num_bodies(self) -> int:
        return self.structure.num_bodies

    @property
    def num_joints(self) -> int:
        return self.structure.num_joints

    @property
    def num_controls(self) -> int:
        return self.structure.num_controls

    @property
    def dt(self) -> float:
        return self.options.dt


Model = _pytree(Model, meta=("structure", "options"))
