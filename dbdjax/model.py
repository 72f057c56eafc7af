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


def with_world_row(array: jnp.ndarray, world_value: jnp.ndarray | float = 0.0) -> jnp.ndarray:
    """Append the world as row N of a per-body array (N, ...) -> (N + 1, ...): the index the
    solver's tables give the world (static: zero velocity, identity pose, zero inverse mass)."""
    row = jnp.broadcast_to(jnp.asarray(world_value, array.dtype), (1,) + array.shape[1:])
    return jnp.concatenate([array, row], axis=0)


# Joint kinds (`Structure.joint_kind`). PLANAR: motion in the plane normal to the axis plus rotation
# about it (MJCF's slide-slide-hinge roots of hopper, walker2d, half_cheetah). UNIVERSAL, GIMBAL: two or
# three successive perpendicular hinges through one point (MJCF's multi-hinge bodies: the humanoid's
# abdomen, hips and shoulders), with per-axis limits, springs and torques.
BALL, HINGE, SLIDER, FIXED, PLANAR, UNIVERSAL, GIMBAL = 0, 1, 2, 3, 4, 5, 6
JOINT_KIND_NAMES = ("ball", "hinge", "slider", "fixed", "planar", "universal", "gimbal")


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
    impulses: the impulse solver's accumulated impulses of the last substep, one (..., M_f, m_f)
      array per constraint family (solvers/impulse.py), read back to warm-start the next one; None
      for the DBD solver, and for a state built by hand (the impulse solver then starts cold).
    Leading axes are batch axes (the step is written for none and vmapped over them).
    """

    pos: jnp.ndarray
    quat: jnp.ndarray
    vel: jnp.ndarray
    ang_vel: jnp.ndarray
    impulses: tuple[jnp.ndarray, ...] | None = None


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
    baumgarte: (J,) beta of SI (17), the fraction of the position error the impulse solver's bias
      removes per substep (the DBD solver does not read it).
    drive_stiffness (N m/rad), drive_damping (N m s/rad), drive_max_torque (N m): (J,) the drive
      of DBD 9 (zero where a joint has none). motor_max_force: (J,) N (slider) or N m (hinge).
    local_axes_a/b: (J, 3, 3) universal and gimbal joints: rows m1, m2, m3, the successive hinge
      axes in each body frame (universal: m3 = m1 x m2); identity rows for the other kinds.
    axis_lower/axis_upper: (J, 3) rad, per-hinge limits of universal and gimbal joints.
    axis_stiffness (N m/rad), axis_damping (N m s/rad): (J, 3) per-hinge drive or spring of
      universal and gimbal joints (their drive_max_torque bounds each hinge's torque).
    armature: (J, 3) rotor inertia of each degree of freedom (MJCF armature): kg m^2 on hinge k of a
      universal or gimbal joint, entry 0 for a hinge, planar or ball joint (kg for a slider).
    limit_stiffness (1/s^2), limit_damping (1/s): (J,) soft limits (`ModelBuilder.set_limit_softness`,
      MJCF solreflimit): a limit row past its bound is a spring and damper per unit of the row's
      effective mass, omega^2 and 2 zeta omega; both 0 where the limits are rigid.
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
    baumgarte: jnp.ndarray
    drive_stiffness: jnp.ndarray
    drive_damping: jnp.ndarray
    drive_max_torque: jnp.ndarray
    motor_max_force: jnp.ndarray
    local_axes_a: jnp.ndarray
    local_axes_b: jnp.ndarray
    axis_lower: jnp.ndarray
    axis_upper: jnp.ndarray
    axis_stiffness: jnp.ndarray
    axis_damping: jnp.ndarray
    armature: jnp.ndarray
    limit_stiffness: jnp.ndarray
    limit_damping: jnp.ndarray


Joints = _pytree(Joints)


@dataclasses.dataclass(frozen=True)
class Torques:
    """Torque (force) actuators on joints, T rows: MJCF's <motor>, `ModelBuilder.add_torque`.

    Each applies gear * control as an external torque about its axis (hinge, ball: +tau on b,
    -tau on a) or force along it (slider: +F on b at its centre of mass, -F on a at that same
    point), held over the substep in `integrator.predict`. On one hinge of a universal or gimbal
    joint (`Structure.torque_dof`) it is the generalised force on that hinge's angle: the torque
    about the dual direction of `math.euler_angles`, from the joint's own axes.
    gear: (T,) N m (or N) per unit of control. local_axis_a/b: (T, 3) the unit axis in the frames
    of the joint's two bodies (world coordinates for the world); angular actuators act about the
    normalised sum of the two (equal for a hinge), linear ones along a's.
    """

    gear: jnp.ndarray
    local_axis_a: jnp.ndarray
    local_axis_b: jnp.ndarray


Torques = _pytree(Torques)


@dataclasses.dataclass(frozen=True)
class IKTargets:
    """Inverse kinematics as a constraint (DBD 11, last paragraph), T rows: a point fixed on a
    body is pulled to a target position that the control vector moves, inside the same solve
    as the joints, contacts and forces (`ModelBuilder.add_ik_target`).

    local_point: (T, 3) the point in its body's frame. rest_target: (T, 3) m, world, where the
    target is at zero control (the point at build time); the control adds a world offset (m).
    stiffness: (T,) N/m, inf for a rigid target. damping: (T,) N s/m. max_force: (T,) N, the
    largest pull (inf for none).
    """

    local_point: jnp.ndarray
    rest_target: jnp.ndarray
    stiffness: jnp.ndarray
    damping: jnp.ndarray
    max_force: jnp.ndarray


IKTargets = _pytree(IKTargets)


@dataclasses.dataclass(frozen=True)
class Springs:
    """Linear springs/dampers between two body points (DBD 8.1), L rows.

    local_anchor_a/b: (L, 3) the end points in the body frames (world coordinates for the world).
    rest_length: (L,) m. stiffness: (L,) N/m. damping: (L,) N s/m, along the spring's line.
    relaxation: (L,) xi of DBD (105).
    """

    local_anchor_a: jnp.ndarray
    local_anchor_b: jnp.ndarray
    rest_length: jnp.ndarray
    stiffness: jnp.ndarray
    damping: jnp.ndarray
    relaxation: jnp.ndarray


Springs = _pytree(Springs)


@dataclasses.dataclass(frozen=True)
class Distances:
    """Rigid distance constraints |p_a - p_b| = length between two body points, D rows.

    local_anchor_a/b: (D, 3) body frames. length: (D,) m. relaxation: (D,) xi.
    """

    local_anchor_a: jnp.ndarray
    local_anchor_b: jnp.ndarray
    length: jnp.ndarray
    relaxation: jnp.ndarray


Distances = _pytree(Distances)


@dataclasses.dataclass(frozen=True)
class Ropes:
    """Total-length constraints over the centres of mass of a row of bodies (DBD 10.1), R rows.

    length: (R,) m, the sum of the segment lengths. relaxation: (R,) xi.
    """

    length: jnp.ndarray
    relaxation: jnp.ndarray


Ropes = _pytree(Ropes)


@dataclasses.dataclass(frozen=True)
class Volumes:
    """Volume constraints on tetrahedra of four centres of mass (DBD 10.2), V rows.

    rest_volume: (V,) m^3, signed: positive when x1 - x0, x2 - x0, x3 - x0 are right-handed.
    relaxation: (V,) xi.
    """

    rest_volume: jnp.ndarray
    relaxation: jnp.ndarray


Volumes = _pytree(Volumes)


@dataclasses.dataclass(frozen=True)
class Shapes:
    """Collision shapes, K rows, each attached to a body (or to the world) with a local pose.

    size: (K, 3) m: sphere (radius, 0, 0), capsule (radius, half_length, 0) along its local z,
      box half extents, plane (0, 0, 0) (its normal is the local z axis).
    local_pos: (K, 3), local_quat: (K, 4): the pose in the body frame (world frame for the world).
    friction: (K,) static coefficient mu_s. dynamic_friction: (K,) mu_d <= mu_s.
    restitution: (K,) in [0, 1]. A pair combines them as sqrt(mu_1 mu_2) and max(e_1, e_2).
    """

    size: jnp.ndarray
    local_pos: jnp.ndarray
    local_quat: jnp.ndarray
    friction: jnp.ndarray
    dynamic_friction: jnp.ndarray
    restitution: jnp.ndarray


Shapes = _pytree(Shapes)


@dataclasses.dataclass(frozen=True)
class ContactGroup:
    """The shape pairs of one kind pair (static: which pairs may touch is decided at finalize).

    kind_a <= kind_b (collision.PLANE, SPHERE, CAPSULE, BOX). shapes: (C, 2) shape indices of each
    pair, side a first. bodies: (C, 2) their bodies (index N for the world). num_points: P, the
    contact slots of one pair (collision.num_points).
    """

    kind_a: int
    kind_b: int
    shapes: StaticArray
    bodies: StaticArray
    num_points: int

    @property
    def name(self) -> str:
        return f"contacts {self.kind_a}-{self.kind_b}"


@dataclasses.dataclass(frozen=True)
class ForceGroup:
    """Static part of the user forces sharing one function (DBD 8, (94)-(99)).

    function(pos (k, 3), quat (k, 4), vel (k, 3), ang_vel (k, 3), params) -> (force (k, 3) N,
    torque (k, 3) N m), world frame, forces at the centres of mass. bodies: (M, k) the bodies
    of each of the group's M elements (index N for the world).
    """

    function: Any
    bodies: StaticArray
    name: str


@dataclasses.dataclass(frozen=True)
class Colour:
    """One colour group: constraint nodes that share no dynamic body (colouring.py).

    nodes: per constraint family (in the order of `Structure.family_bodies`), the indices of
    the family's nodes in this colour. body_slot: (N + 1,) where each body's displacement is
    found afterwards: an index into [the node rows of every family in order, each node's S
    bodies in turn, then the N + 1 previous rows]. A gather, never a scatter.
    """

    nodes: tuple[StaticArray, ...]
    body_slot: StaticArray


@dataclasses.dataclass(frozen=True)
class Structure:
    """Static structure of a model: counts, indices and the colouring of the constraint graph.

    Body index N (one past the last body) is the world in the index arrays below, and control
    index num_controls means "no control".
    joint_body_a/b: (J,) int. joint_kind: (J,) int (BALL, HINGE, SLIDER, FIXED, PLANAR, UNIVERSAL,
    GIMBAL). joint_has_limits / joint_has_cone: (J,) bool.
    joint_drive_control: (J, 3) int, the control entries of each joint's drive target.
    joint_motor_control: (J,) int, the control entry of each joint's motor speed.
    spring_bodies (L, 2), distance_bodies (D, 2), volume_bodies (V, 4): int.
    rope_bodies: (R, S) int, each rope's nodes in order, padded with N to the longest rope.
    force_groups: the user forces, one group per function.
    shape_kind: (K,) int, shape_body: (K,) int (N for the world).
    contact_groups: the shape pairs that may touch, one group per kind pair.
    colours: the colour groups of the solver (Gauss-Seidel order), over every family.
    contact_colours: the colouring of the contact groups alone (the restitution pass).
    """

    num_bodies: int
    num_joints: int
    num_controls: int
    joint_body_a: StaticArray
    joint_body_b: StaticArray
    joint_kind: StaticArray
    joint_has_limits: StaticArray
    joint_has_cone: StaticArray
    joint_drive_control: StaticArray
    joint_motor_control: StaticArray
    spring_bodies: StaticArray
    distance_bodies: StaticArray
    rope_bodies: StaticArray
    volume_bodies: StaticArray
    force_groups: tuple[ForceGroup, ...]
    shape_kind: StaticArray
    shape_body: StaticArray
    contact_groups: tuple[ContactGroup, ...]
    colours: tuple[Colour, ...]
    contact_colours: tuple[Colour, ...]
    body_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    control_names: tuple[str, ...]
    # Torque actuators (`Torques`), T rows: their two bodies (T, 2) int (N = world), the control
    # entry of each (T,) int, and (T,) bool True for a force along a slider.
    torque_bodies: StaticArray = StaticArray(np.zeros((0, 2), np.int32))
    torque_control: StaticArray = StaticArray(np.zeros((0,), np.int32))
    torque_linear: StaticArray = StaticArray(np.zeros((0,), bool))
    # (num_controls, 2) the range each control entry is meant to stay in (MJCF ctrlrange; -inf, inf
    # for drives and motors added directly). Informational: `step` does not clip.
    control_range: StaticArray = StaticArray(np.zeros((0, 2)))
    # (J,) bool: the joint's drive is a passive spring-damper toward the build pose with no control
    # entry (`ModelBuilder.add_joint_spring`, MJCF joint stiffness/damping). Empty: none.
    joint_passive_drive: StaticArray = StaticArray(np.zeros((0,), bool))
    # IK targets (`IKTargets`): (T, 2) int, the body and the world (N); (T, 3) int, the control
    # entries of each target's offset.
    ik_target_bodies: StaticArray = StaticArray(np.zeros((0, 2), np.int32))
    ik_target_control: StaticArray = StaticArray(np.zeros((0, 3), np.int32))
    # (J, 3) bool: which hinges of a universal or gimbal joint have limits. Empty: none.
    joint_axis_limited: StaticArray = StaticArray(np.zeros((0, 3), bool))
    # (T,) int: the joint of each torque actuator, and the hinge (0, 1, 2) of a universal or gimbal
    # joint it acts on (-1: the joint's own axis). Empty: no torque acts on such a hinge.
    torque_joint: StaticArray = StaticArray(np.zeros((0,), np.int32))
    torque_dof: StaticArray = StaticArray(np.zeros((0,), np.int32))
    # (T,) bool: the torque acts through its joint's rotor row (its degree of freedom has armature)
    # instead of in the prediction. (J, 3) bool: which degrees of freedom of each joint have armature.
    torque_in_joint: StaticArray = StaticArray(np.zeros((0,), bool))
    joint_rotor: StaticArray = StaticArray(np.zeros((0, 3), bool))
    # (J,) bool: which joints' limits are soft (`Joints.limit_stiffness`). Empty: none.
    joint_soft_limits: StaticArray = StaticArray(np.zeros((0,), bool))
    # (J,) bool: the joint's drive has a finite torque limit (DBD (114)) at build time, which the
    # tree's whole-joint solve must respect (`solvers.tree.direct_step`). Empty: none.
    joint_drive_limited: StaticArray = StaticArray(np.zeros((0,), bool))

    @property
    def num_colours(self) -> int:
        return len(self.colours)

    def family_bodies(self) -> tuple[np.ndarray, ...]:
        """The bodies of every constraint node, one (M, S) table per family, in solver order:
        joints, springs, distances, ropes, volumes, each force group, the IK targets, then each
        contact group."""
        joints = np.stack([self.joint_body_a.array, self.joint_body_b.array], axis=-1).reshape(-1, 2)
        fixed = (joints, self.spring_bodies.array, self.distance_bodies.array, self.rope_bodies.array,
                 self.volume_bodies.array)  # fmt: skip
        forces = tuple(group.bodies.array for group in self.force_groups)
        contacts = tuple(group.bodies.array for group in self.contact_groups)
        return fixed + forces + (self.ik_target_bodies.array,) + contacts


@dataclasses.dataclass(frozen=True)
class Options:
    """Static simulation settings chosen at `finalize`."""

    dt: float
    substeps: int
    iterations: int
    solver: str  # "dbd" or "impulse"
    jacobi: bool  # all joints at once, averaged per body, instead of coloured Gauss-Seidel
    velocity_dependent_inertia: bool  # DBD (58)
    checkpoint: bool  # jax.checkpoint each substep to keep reverse-mode memory flat
    contact_margin: float = 0.01  # m: shapes closer than this get contact slots (speculative)
    contact_compliance: float = 0.0  # m/N: 0 is rigid; > 0 softens contacts (smoother gradients)
    # m/s: the fastest the DBD solver pushes a point out of a penetration it began a substep in
    depenetration_speed: float = 1.0
    restitution_iterations: int = 2  # Gauss-Seidel sweeps of the velocity pass
    initial_guess: str = "zero"  # "zero": dX = 0 (Algorithm 1); "tree": exact solve of the tree's linearised points
    tree_solve: bool = False  # direct solves of the joint tree: points after the sweeps, whole joints after the last
    point_sweeps: int = 0  # DBD solver: sweeps of the joints' points alone after the whole-joint sweeps
    baumgarte: float = 0.05  # impulse solver: beta of SI (17) for contacts, springs' links, distances


@dataclasses.dataclass(frozen=True)
class Model:
    """A simulatable model: every float array (bodies, joints, springs, ..., gravity) is a
    differentiable leaf; `structure` and `options` are static."""

    bodies: Bodies
    joints: Joints
    springs: Springs
    distances: Distances
    ropes: Ropes
    volumes: Volumes
    forces: tuple[Any, ...]  # the parameters of each force group, leading axis M
    shapes: Shapes
    gravity: jnp.ndarray  # (3,) m/s^2
    structure: Structure
    options: Options
    torques: Torques | None = None  # torque actuators (None: none)
    ik_targets: IKTargets | None = None  # IK targets (None: none)

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

    @property
    def control_range(self) -> np.ndarray:
        """(num_controls, 2) lower and upper bound of each control entry (informational: not clipped)."""
        return self.structure.control_range.array


Model = _pytree(Model, meta=("structure", "options"))
