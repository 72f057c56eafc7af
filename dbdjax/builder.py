"""`ModelBuilder`: describe bodies and joints in world coordinates, then `finalize()` a `Model`.

All checks happen here, on the host, so that a model that cannot be simulated is refused with a
`ValueError` naming the body or joint and the reason, before anything is traced.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import colouring, host_math, shapes
from dbdjax.collision import BOX, CAPSULE, PLANE, SPHERE, num_points
from dbdjax.constraints import joints
from dbdjax.model import (
    BALL,
    FIXED,
    GIMBAL,
    HINGE,
    JOINT_KIND_NAMES,
    PLANAR,
    SLIDER,
    UNIVERSAL,
    WORLD,
    Bodies,
    ContactGroup,
    Distances,
    ForceGroup,
    IKTargets,
    Joints,
    Model,
    Options,
    Ropes,
    Shapes,
    Springs,
    StaticArray,
    Structure,
    Torques,
    Volumes,
)

SOLVERS = ("dbd", "impulse")
INITIAL_GUESSES = ("tree", "zero")


def colour_classes(structure: Structure) -> list[int | np.ndarray]:
    """The colouring's class of every family's nodes (`colouring.colour_groups`), in solver order:
    each kind of joint (`joints.variants`) and each other family a class of its own, then the
    contact groups one class together. So every joint colour projects one kind of joint: a colour
    runs the kernels of each kind it holds once, however few of its joints are of that kind (Brax's
    humanoid, 1 x 4, CPU: its hinges and its universal / gimbal joints mixed in 3 colours ran both
    kinds' kernels 3 times a sweep; kind by kind, 1 colour of hinges and 3 of the others, a step
    took 0.54 instead of 0.77 ms of CPU at batch 1 and 3.77 instead of 4.66 ms at batch 16)."""
    tables = structure.family_bodies()
    kinds = joints.variants(structure) if structure.num_joints else []
    joint_class = colouring.kind_classes([members for members, _ in kinds], structure.num_joints)
    first = max(len(kinds), 1)  # the classes after the joints'
    others = len(tables) - 1 - len(structure.contact_groups)  # springs, distances, ..., the IK targets
    return [joint_class, *range(first, first + others), *[first + others] * len(structure.contact_groups)]


def _vector(value, size: int, what: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (size,):
        raise ValueError(f"{what} must have {size} numbers, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} contains NaN or infinity: {array.tolist()}")
    return array


def _scalar(value, what: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{what} is NaN or infinite")
    return number


def _unit(value, what: str) -> np.ndarray:
    vector = _vector(value, 3, what)
    norm = np.linalg.norm(vector)
    if norm < 1e-9:
        raise ValueError(f"{what} is the zero vector; it needs a direction")
    return vector / norm


def _quat(value, what: str) -> np.ndarray:
    quat = _vector(value, 4, what)
    norm = np.linalg.norm(quat)
    if norm < 1e-9:
        raise ValueError(f"{what} is the zero quaternion; give (w, x, y, z) of a rotation")
    return quat / norm


def _check_inertia(label: str, inertia: np.ndarray) -> None:
    if np.any(inertia <= 0.0):
        raise ValueError(f"{label}: inertia must be positive definite, got {inertia.tolist()}")
    for i in range(3):
        others = inertia[(i + 1) % 3] + inertia[(i + 2) % 3]
        if inertia[i] > others * (1.0 + 1e-6):
            raise ValueError(
                f"{label}: inertia {inertia.tolist()} violates the triangle inequality "
                "(no rigid body has one principal moment larger than the other two together)"
            )


@dataclasses.dataclass
class _Body:
    name: str
    mass: float | None  # None: from the shapes and their density
    inertia: np.ndarray | None  # None: from the shapes
    pos: np.ndarray
    quat: np.ndarray
    vel: np.ndarray
    ang_vel: np.ndarray


@dataclasses.dataclass
class _Joint:
    name: str
    kind: int
    body_a: int
    body_b: int
    anchor: np.ndarray  # world, at build time
    axis: np.ndarray  # world unit vector (hinge/slider axis, ball twist axis)
    lower: float
    upper: float
    has_limits: bool
    cone_limit: float
    has_cone: bool
    relaxation: float
    regularization: float
    drive_stiffness: float = 0.0
    drive_damping: float = 0.0
    drive_max_torque: float = math.inf
    drive_control: tuple[int, ...] = ()  # control entries of the drive target
    motor_max_force: float = 0.0
    motor_control: int | None = None
    passive_drive: bool = False  # add_joint_spring: a drive toward the build pose, no control
    axis_b: np.ndarray | None = None  # world axis whose b-frame copy is local_axis_b (default: axis)
    axes: np.ndarray | None = None  # universal, gimbal: (3, 3) world rows m1, m2, m3 at build time
    axis_lower: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, -math.pi))
    axis_upper: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, math.pi))
    axis_limited: tuple[bool, bool, bool] = (False, False, False)
    axis_stiffness: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    axis_damping: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    armature: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))  # per degree of freedom
    baumgarte: float | None = None  # beta of SI (17) for the impulse solver; None: finalize's
    limit_stiffness: float = 0.0  # soft limits (set_limit_softness): 1/s^2 per unit effective mass
    limit_damping: float = 0.0  # 1/s

    @property
    def num_axes(self) -> int:
        """Hinges of a universal (2) or gimbal (3) joint; 0 for the other kinds."""
        return {UNIVERSAL: 2, GIMBAL: 3}.get(self.kind, 0)


@dataclasses.dataclass
class _Torque:
    """A torque (force) actuator on a joint: gear * control about (along) a world axis at build time."""

    joint: int
    gear: float
    axis: np.ndarray
    linear: bool
    control: int
    dof: int = -1  # the hinge of a universal or gimbal joint (-1: the joint's own axis)


@dataclasses.dataclass
class _Link:
    """A spring or a distance constraint between world points on two bodies at build time."""

    body_a: int
    body_b: int
    anchor_a: np.ndarray
    anchor_b: np.ndarray
    length: float
    stiffness: float
    damping: float
    relaxation: float


@dataclasses.dataclass
class _IKTarget:
    """A point of a body pulled to a target the control moves (DBD 11 as a constraint)."""

    body: int
    point: np.ndarray  # world, at build time
    stiffness: float  # inf: rigid
    damping: float
    max_force: float  # inf: unlimited
    control: int  # the first of three entries


@dataclasses.dataclass
class _Shape:
    name: str
    kind: int
    body: int
    size: np.ndarray
    pos: np.ndarray  # in the body frame at build time (world for the world)
    quat: np.ndarray
    friction: float
    dynamic_friction: float
    restitution: float
    density: float
    contype: int
    conaffinity: int


@dataclasses.dataclass
class _Force:
    bodies: tuple[int, ...]
    function: Callable
    params: Any
    name: str


class ModelBuilder:
    """Collects bodies and joints in world coordinates (z up, SI units, quats (w, x, y, z)).

    >>> b = ModelBuilder(gravity=(0, 0, -9.81))
    >>> link = b.add_body(pos=(0, 0, 1), mass=1.0, inertia=(0.1, 0.1, 0.1))
    >>> joint = b.add_ball_joint(WORLD, link, anchor=(0, 0, 2))
    >>> model = b.finalize(dt=1 / 60)
    """

    def __init__(self, gravity: Sequence[float] = (0.0, 0.0, -9.81)):
        self.gravity = _vector(gravity, 3, "gravity")
        self._bodies: list[_Body] = []
        self._joints: list[_Joint] = []
        self._springs: list[_Link] = []
        self._distances: list[_Link] = []
        self._ropes: list[tuple[tuple[int, ...], float, float]] = []  # (bodies, length, relaxation)
        self._volumes: list[tuple[tuple[int, ...], float, float]] = []  # (bodies, volume, relaxation)
        self._forces: list[_Force] = []
        self._shapes: list[_Shape] = []
        self._excluded: set[frozenset[int]] = set()  # body pairs that never touch
        self._allowed: set[frozenset[int]] = set()  # jointed body pairs that may touch anyway
        self._control_names: list[str] = []
        self._control_ranges: list[tuple[float, float]] = []
        self._torques: list[_Torque] = []
        self._ik_targets: list[_IKTarget] = []

    # ----------------------------------------------------------------------------- bodies
    def add_body(
        self,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
        mass: float | None = None,
        inertia: Sequence[float] | None = None,
        vel: Sequence[float] = (0.0, 0.0, 0.0),
        ang_vel: Sequence[float] = (0.0, 0.0, 0.0),
        name: str | None = None,
    ) -> int:
        """Add a rigid body and return its index.

        pos: centre of mass (m). quat: orientation of the body frame, in which `inertia` (the
        three principal moments, kg m^2) is given. vel, ang_vel: initial velocities (world).
        mass/inertia left out are derived at `finalize` from the body's shapes and their density
        (the body frame then moves to the shapes' centre of mass and principal axes, as MuJoCo's
        inertial frame does; shapes and joint anchors keep their world placement). A body with no
        shapes and no mass gets mass 1 kg and inertia (0.1, 0.1, 0.1).
        """
        index = len(self._bodies)
        label = f"body {index}" + (f" ({name!r})" if name else "")
        if mass is not None:
            mass = _scalar(mass, f"{label}: mass")
            if mass <= 0.0:
                raise ValueError(f"{label}: mass must be positive, got {mass}")
        if inertia is not None:
            inertia = _vector(inertia, 3, f"{label}: inertia")
            _check_inertia(label, inertia)
        self._bodies.append(
            _Body(
                name=name or f"body {index}",
                mass=mass,
                inertia=inertia,
                pos=_vector(pos, 3, f"{label}: pos"),
                quat=_quat(quat, f"{label}: quat"),
                vel=_vector(vel, 3, f"{label}: vel"),
                ang_vel=_vector(ang_vel, 3, f"{label}: ang_vel"),
            )
        )
        return index

    # ----------------------------------------------------------------------------- shapes
    def add_sphere(self, body: int, radius: float, pos: Sequence[float] = (0.0, 0.0, 0.0), **material) -> int:
        """A sphere on `body` (or the world) centred at `pos` in the body frame; returns its index.

        material (every shape): friction (static mu_s, default 0.5), dynamic_friction (mu_d,
        default = friction), restitution (default 0), density (kg/m^3, default 1000, for bodies
        without a mass), contype / conaffinity (MuJoCo's collision bits, default 1 / 1), name.
        """
        label = self._shape_label("sphere", material.get("name"))
        size = np.array([self._positive(radius, f"{label}: radius"), 0.0, 0.0])
        return self._add_shape(label, SPHERE, body, size, pos, (1.0, 0.0, 0.0, 0.0), **material)

    def add_capsule(
        self, body: int, radius: float, half_length: float, pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0), **material,
    ) -> int:  # fmt: skip
        """A capsule on `body`: a segment of 2 half_length along its local z axis, swept by a
        sphere of `radius`; pose (pos, quat) in the body frame. material: see `add_sphere`."""
        label = self._shape_label("capsule", material.get("name"))
        size = np.array([self._positive(radius, f"{label}: radius"),
                         self._non_negative(half_length, f"{label}: half_length"), 0.0])  # fmt: skip
        return self._add_shape(label, CAPSULE, body, size, pos, quat, **material)

    def add_box(
        self, body: int, half_extents: Sequence[float], pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0), **material,
    ) -> int:  # fmt: skip
        """A box of `half_extents` (m) on `body`, pose (pos, quat) in the body frame.
        material: see `add_sphere`."""
        label = self._shape_label("box", material.get("name"))
        size = _vector(half_extents, 3, f"{label}: half_extents")
        if np.any(size <= 0.0):
            raise ValueError(f"{label}: half_extents must be positive, got {size.tolist()}")
        return self._add_shape(label, BOX, body, size, pos, quat, **material)

    def add_plane(self, normal: Sequence[float] = (0.0, 0.0, 1.0), offset: float = 0.0, **material) -> int:
        """The static half-space {x : normal . x <= offset} (solid below the plane); returns its
        index. normal: world direction (normalised here). material: see `add_sphere`."""
        label = self._shape_label("plane", material.get("name"))
        normal = _unit(normal, f"{label}: normal")
        offset = _scalar(offset, f"{label}: offset")
        quat = host_math.z_to(normal)  # the plane pose: local z is the normal
        return self._add_shape(label, PLANE, WORLD, np.zeros(3), offset * normal, quat, **material)

    def exclude_collision(self, body_a: int, body_b: int) -> None:
        """Never let the shapes of these two bodies touch (MJCF's <exclude>)."""
        self._check_bodies("exclude_collision", body_a, body_b)
        self._excluded.add(frozenset((int(body_a), int(body_b))))

    def allow_collision(self, body_a: int, body_b: int) -> None:
        """Let two bodies joined by a joint touch (by default jointed neighbours do not)."""
        self._check_bodies("allow_collision", body_a, body_b)
        self._allowed.add(frozenset((int(body_a), int(body_b))))

    def _shape_label(self, kind: str, name: str | None) -> str:
        return f"{kind} shape {len(self._shapes)}" + (f" ({name!r})" if name else "")

    def _add_shape(
        self, label: str, kind: int, body: int, size: np.ndarray, pos, quat, friction: float = 0.5,
        dynamic_friction: float | None = None, restitution: float = 0.0, density: float = 1000.0,
        contype: int = 1, conaffinity: int = 1, name: str | None = None,
    ) -> int:  # fmt: skip
        if not isinstance(body, (int, np.integer)) or isinstance(body, bool):
            raise ValueError(f"{label}: body must be a body index (int), got {body!r}")
        if body != WORLD and not 0 <= body < len(self._bodies):
            raise ValueError(f"{label}: body = {body} is not a body index "
                             f"(there are {len(self._bodies)} bodies; the world is {WORLD})")  # fmt: skip
        friction = self._non_negative(friction, f"{label}: friction")
        dynamic = (
            friction if dynamic_friction is None else self._non_negative(dynamic_friction, f"{label}: dynamic_friction")
        )
        if dynamic > friction:
            raise ValueError(f"{label}: dynamic_friction {dynamic} exceeds the static friction {friction} "
                             "(the dry friction model of DBD 7.1 needs mu_d <= mu_s)")  # fmt: skip
        restitution = _scalar(restitution, f"{label}: restitution")
        if not 0.0 <= restitution <= 1.0:
            raise ValueError(f"{label}: restitution must be in [0, 1], got {restitution}")
        for what, bits in (("contype", contype), ("conaffinity", conaffinity)):
            if not isinstance(bits, (int, np.integer)) or isinstance(bits, bool) or bits < 0:
                raise ValueError(f"{label}: {what} must be a non-negative int (bit mask), got {bits!r}")
        self._shapes.append(
            _Shape(
                name or label,
                kind,
                int(body),
                size,
                _vector(pos, 3, f"{label}: pos"),
                _quat(quat, f"{label}: quat"),
                friction,
                dynamic,
                restitution,
                self._positive(density, f"{label}: density"),
                int(contype),
                int(conaffinity),
            )  # fmt: skip
        )
        return len(self._shapes) - 1

    @staticmethod
    def _positive(value, what: str) -> float:
        number = _scalar(value, what)
        if number <= 0.0:
            raise ValueError(f"{what} must be positive, got {number}")
        return number

    # ----------------------------------------------------------------------------- joints
    def add_ball_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        cone_limit: float | None = None,
        twist_limits: tuple[float, float] | None = None,
        twist_axis: Sequence[float] | None = None,
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
        baumgarte: float | None = None,
    ) -> int:
        """Ball-and-socket joint at world point `anchor` (DBD section 5); returns its index.

        cone_limit: largest angle (rad, in (0, pi]) between the twist axis fixed in body a and
        the one fixed in body b (DBD (81)-(83)). twist_limits: (lower, upper) rad in [-pi, pi]
        of the rotation of b about the twist axis. twist_axis: world direction at build time;
        by default the direction from the anchor to body b's centre of mass (the bone).
        relaxation, regularization: xi and alpha of the DBD solver (DBD (46)-(47)). baumgarte:
        beta of SI (17) for the impulse solver (None: finalize's `baumgarte`); every joint takes
        these three.
        """
        label = self._joint_label("ball", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        self._check_bodies(label, body_a, body_b)
        if twist_axis is None:
            bone = self._bodies[body_b].pos - anchor if body_b >= 0 else anchor * 0.0
            twist_axis = bone if np.linalg.norm(bone) > 1e-9 else np.array([0.0, 0.0, 1.0])
        axis = _unit(twist_axis, f"{label}: twist_axis")
        cone = math.pi
        if cone_limit is not None:
            cone = _scalar(cone_limit, f"{label}: cone_limit")
            if not 0.0 < cone <= math.pi:
                raise ValueError(f"{label}: cone_limit must be in (0, pi], got {cone}")
        lower, upper = self._limits(label, twist_limits, angular=True)
        return self._add_joint(
            label, name, BALL, body_a, body_b, anchor, axis, lower, upper,
            twist_limits is not None, cone, cone_limit is not None, relaxation, regularization, baumgarte,
        )  # fmt: skip

    def add_hinge_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        axis: Sequence[float],
        limits: tuple[float, float] | None = None,
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
        baumgarte: float | None = None,
    ) -> int:
        """Hinge about world `axis` through `anchor` (DBD 6, SI 2.4); limits (rad) in [-pi, pi]."""
        return self._add_axis_joint(HINGE, body_a, body_b, anchor, axis, limits, relaxation, regularization, name,
                                    baumgarte)  # fmt: skip

    def add_slider_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        axis: Sequence[float],
        limits: tuple[float, float] | None = None,
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
        baumgarte: float | None = None,
    ) -> int:
        """Slider (prismatic) along world `axis` (SI 2.3); limits (m) on the travel of b from a."""
        return self._add_axis_joint(SLIDER, body_a, body_b, anchor, axis, limits, relaxation, regularization, name,
                                    baumgarte)  # fmt: skip

    def _add_axis_joint(self, kind, body_a, body_b, anchor, axis, limits, relaxation, regularization, name,
                        baumgarte=None) -> int:  # fmt: skip
        """Hinge or slider: a joint defined by an anchor and one axis, with optional limits."""
        label = self._joint_label("hinge" if kind == HINGE else "slider", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        axis = _unit(axis, f"{label}: axis")
        self._check_bodies(label, body_a, body_b)
        lower, upper = self._limits(label, limits, angular=kind == HINGE)
        return self._add_joint(
            label, name, kind, body_a, body_b, anchor, axis, lower, upper,
            limits is not None, math.pi, False, relaxation, regularization, baumgarte,
        )  # fmt: skip

    def add_fixed_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
        baumgarte: float | None = None,
    ) -> int:
        """Weld b to a at world `anchor` (SI 2.5): no relative motion at all."""
        label = self._joint_label("fixed", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        self._check_bodies(label, body_a, body_b)
        return self._add_joint(
            label, name, FIXED, body_a, body_b, anchor, np.array([0.0, 0.0, 1.0]), 0.0, 0.0,
            False, math.pi, False, relaxation, regularization, baumgarte,
        )  # fmt: skip

    def add_planar_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        normal: Sequence[float],
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
        baumgarte: float | None = None,
    ) -> int:
        """Planar joint: b translates in the plane through world `anchor` normal to `normal` and
        rotates about `normal` only (3 degrees of freedom; MJCF's slide-slide-hinge root of a 2-D
        walker). The point row keeps the anchor's offset along the normal zero, the axle row (as a
        hinge's) keeps the normal of both bodies aligned."""
        label = self._joint_label("planar", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        normal = _unit(normal, f"{label}: normal")
        self._check_bodies(label, body_a, body_b)
        return self._add_joint(
            label, name, PLANAR, body_a, body_b, anchor, normal, 0.0, 0.0,
            False, math.pi, False, relaxation, regularization, baumgarte,
        )  # fmt: skip

    def add_universal_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        axes: Sequence[Sequence[float]],
        limits: Sequence[tuple[float, float] | None] | None = None,
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
    ) -> int:
        """Universal joint (2 degrees of freedom): b turns about axes[0], fixed in a, then about
        axes[1], fixed in b: the relative rotation R(axis1, t1) R(axis2, t2), MuJoCo's two hinges
        on one body. axes: two perpendicular world directions at build time. limits: None, or one
        (lower, upper) in [-pi, pi] rad (or None) per hinge, of the angles `math.euler_angles`
        measures from the build pose. Rows: the point block, one lock row keeping the angle
        between axis 1 (on a) and axis 2 (on b) at 90 degrees (DBD 6, (73)-(80), with that
        offset), and one-sided angle rows for the limits (SI 2.4.5, clamped as DBD 6.1)."""
        return self._add_euler_joint(UNIVERSAL, body_a, body_b, anchor, axes, limits, relaxation, regularization,
                                     name)  # fmt: skip

    def add_gimbal_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        axes: Sequence[Sequence[float]],
        limits: Sequence[tuple[float, float] | None] | None = None,
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
    ) -> int:
        """Three successive hinges through `anchor` (3 rotational degrees of freedom, MuJoCo's three
        hinges on one body): the relative rotation R(axis1, t1) R(axis2, t2) R(axis3, t3), axis 1
        fixed in a, axis 3 in b. axes: three mutually perpendicular world directions at build time
        (either handedness). limits: None, or per hinge (lower, upper) rad or None; the outer
        hinges' in [-pi, pi], the middle one's in [-pi/2, pi/2] (the decomposition is singular at
        t2 = +-pi/2, where axes 1 and 3 align). Rows: the point block and the limit rows."""
        return self._add_euler_joint(GIMBAL, body_a, body_b, anchor, axes, limits, relaxation, regularization, name)

    def _add_euler_joint(self, kind, body_a, body_b, anchor, axes, limits, relaxation, regularization, name) -> int:
        count = 2 if kind == UNIVERSAL else 3
        label = self._joint_label(JOINT_KIND_NAMES[kind], name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        self._check_bodies(label, body_a, body_b)
        if len(axes) != count:
            raise ValueError(f"{label}: needs {count} axes, got {len(axes)}")
        units = [_unit(axis, f"{label}: axis {k + 1}") for k, axis in enumerate(axes)]
        for i in range(count):
            for k in range(i + 1, count):
                if abs(units[i] @ units[k]) > 1e-6:
                    raise ValueError(f"{label}: axes {i + 1} and {k + 1} must be perpendicular, their cosine is "
                                     f"{units[i] @ units[k]:.3g}")  # fmt: skip
        # Gram-Schmidt: exactly orthonormal, so the decomposition's handedness is exactly +-1
        units[1] = units[1] - (units[1] @ units[0]) * units[0]
        units[1] /= np.linalg.norm(units[1])
        if count == 2:
            units.append(np.cross(units[0], units[1]))
        else:
            units[2] = np.sign(units[2] @ np.cross(units[0], units[1])) * np.cross(units[0], units[1])
        if limits is not None and len(limits) != count:
            raise ValueError(f"{label}: limits must give one (lower, upper) or None per axis, got {limits!r}")
        lower, upper, limited = np.full(3, -math.pi), np.full(3, math.pi), [False, False, False]
        for k, pair in enumerate(limits or [None] * count):
            if pair is None:
                continue
            lower[k], upper[k] = self._limits(f"{label} axis {k + 1}", pair, angular=True)
            if kind == GIMBAL and k == 1 and (lower[k] < -math.pi / 2 or upper[k] > math.pi / 2):
                raise ValueError(f"{label}: the middle axis' limits must lie in [-pi/2, pi/2], got "
                                 f"({lower[k]}, {upper[k]})")  # fmt: skip
            limited[k] = True
        index = self._add_joint(
            label, name, kind, body_a, body_b, anchor, units[0], 0.0, 0.0, False, math.pi, False,
            relaxation, regularization,
        )  # fmt: skip
        record = self._joints[index]
        record.axes = np.stack(units)
        record.axis_b = units[1] if kind == UNIVERSAL else units[2]
        record.axis_lower, record.axis_upper, record.axis_limited = lower, upper, tuple(limited)
        return index

    def _joint_label(self, kind: str, name: str | None) -> str:
        index = len(self._joints)
        return f"{kind} joint {index}" + (f" ({name!r})" if name else "")

    def _check_bodies(self, label: str, body_a: int, body_b: int) -> None:
        for role, body in (("body_a", body_a), ("body_b", body_b)):
            if not isinstance(body, (int, np.integer)) or isinstance(body, bool):
                raise ValueError(f"{label}: {role} must be a body index (int), got {body!r}")
            if body != WORLD and not 0 <= body < len(self._bodies):
                raise ValueError(
                    f"{label}: {role} = {body} is not a body index "
                    f"(there are {len(self._bodies)} bodies; the world is {WORLD})"
                )
        if body_a == body_b:
            what = "the world to itself" if body_a == WORLD else f"body {body_a} to itself"
            raise ValueError(f"{label}: a joint cannot connect {what}")

    def _limits(self, label: str, limits, angular: bool) -> tuple[float, float]:
        if limits is None:  # unused values, kept finite so masked rows stay finite too
            return (-math.pi, math.pi) if angular else (0.0, 0.0)
        if len(limits) != 2:
            raise ValueError(f"{label}: limits must be (lower, upper), got {limits!r}")
        lower = _scalar(limits[0], f"{label}: lower limit")
        upper = _scalar(limits[1], f"{label}: upper limit")
        if lower > upper:
            raise ValueError(f"{label}: lower limit {lower} is above upper limit {upper}")
        if angular and (lower < -math.pi or upper > math.pi):
            raise ValueError(f"{label}: angle limits must lie in [-pi, pi], got ({lower}, {upper})")
        return lower, upper

    def _add_joint(self, label, name, kind, body_a, body_b, anchor, axis, lower, upper,
                   has_limits, cone, has_cone, relaxation, regularization, baumgarte=None) -> int:  # fmt: skip
        relaxation = self._relaxation(label, relaxation)
        if baumgarte is not None:
            baumgarte = self._baumgarte(f"{label}: baumgarte", baumgarte)
        regularization = _scalar(regularization, f"{label}: regularization")
        if regularization < 0.0:
            raise ValueError(f"{label}: regularization must be >= 0, got {regularization}")
        self._joints.append(
            _Joint(
                name or label,
                kind,
                int(body_a),
                int(body_b),
                anchor,
                axis,
                lower,
                upper,
                has_limits,
                cone,
                has_cone,
                relaxation,
                regularization,
                baumgarte=baumgarte,
            )  # fmt: skip
        )
        return len(self._joints) - 1

    # ----------------------------------------------------------------------------- actuators
    def add_drive(
        self,
        joint: int,
        stiffness: float,
        damping: float = 0.0,
        max_torque: float | None = None,
        name: str | None = None,
    ) -> slice:
        """A torque-limited angular spring/damper pulling a joint toward a control target (DBD 9).

        Hinge joints: the target is 1 control entry, the angle (rad) of b about the axle from the
        build pose. Ball joints: 3 entries, the target rotation of b relative to a from the build
        pose as a rotation vector (rad) in a's frame. Universal / gimbal joints: 2 / 3 entries,
        the target angle of each hinge (`math.euler_angles`), one spring row per hinge acting on
        that angle alone; stiffness and damping may then be given per hinge. stiffness: N m/rad.
        damping: N m s/rad. max_torque: N m, None for unlimited (the clamp of (114); per hinge).
        Returns the drive's slice of the control vector (controls are numbered in the order
        drives and motors are added).
        """
        label, record = self._actuated_joint("add_drive", joint)
        if record.kind not in (HINGE, BALL, UNIVERSAL, GIMBAL):
            raise ValueError(f"add_drive: {label} is a {JOINT_KIND_NAMES[record.kind]} joint; drives act on hinge, "
                             "ball, universal and gimbal joints (use add_motor for a slider)")  # fmt: skip
        if record.drive_control or record.passive_drive:
            raise ValueError(f"add_drive: {label} already has a drive")
        self._set_drive(record, f"add_drive on {label}", stiffness, damping)
        if max_torque is not None:
            record.drive_max_torque = _scalar(max_torque, f"add_drive on {label}: max_torque")
            if record.drive_max_torque <= 0.0:
                raise ValueError(f"add_drive on {label}: max_torque must be positive, got {max_torque}")
        size = {HINGE: 1, BALL: 3}.get(record.kind, record.num_axes)
        controls = self._new_controls(f"drive on {name or record.name}", size)
        record.drive_control = tuple(range(controls.start, controls.stop))
        return controls

    def add_joint_spring(
        self, joint: int, stiffness: float | Sequence[float], damping: float | Sequence[float] = 0.0
    ) -> None:
        """A passive spring-damper on a hinge, ball, universal or gimbal joint toward its build pose
        (MJCF joint stiffness and damping): the drive of DBD 9 with a fixed zero target and no
        control entry. stiffness: N m/rad, damping: N m s/rad (ball: the same about every axis;
        universal, gimbal: a number for every hinge or one per hinge, each acting on its own
        hinge angle as MuJoCo's per-dof stiffness and damping do)."""
        label, record = self._actuated_joint("add_joint_spring", joint)
        if record.kind not in (HINGE, BALL, UNIVERSAL, GIMBAL):
            raise ValueError(f"add_joint_spring: {label} is a {JOINT_KIND_NAMES[record.kind]} joint; joint springs "
                             "act on hinge, ball, universal and gimbal joints")  # fmt: skip
        if record.drive_control or record.passive_drive:
            raise ValueError(f"add_joint_spring: {label} already has a drive")
        self._set_drive(record, f"add_joint_spring on {label}", stiffness, damping)
        record.passive_drive = True

    def _set_drive(self, record: _Joint, what: str, stiffness, damping) -> None:
        """Stiffness and damping of a drive: scalars, or per hinge for universal and gimbal joints."""
        if not record.num_axes:
            record.drive_stiffness = self._non_negative(stiffness, f"{what}: stiffness")
            record.drive_damping = self._non_negative(damping, f"{what}: damping")
            return
        for field, value in (("stiffness", stiffness), ("damping", damping)):
            values = np.broadcast_to(np.asarray(value, dtype=np.float64), (record.num_axes,)) if np.ndim(value) == 0 \
                else np.asarray(value, dtype=np.float64)  # fmt: skip
            if values.shape != (record.num_axes,):
                raise ValueError(
                    f"{what}: {field} must be a number or one per hinge ({record.num_axes}), got {value!r}"
                )
            per_axis = np.zeros(3)
            per_axis[: record.num_axes] = [self._non_negative(v, f"{what}: {field}") for v in values]
            setattr(record, f"axis_{field}", per_axis)

    def joint_limited(self, joint: int) -> bool:
        """Whether a joint has any limit: a hinge's or slider's range, a ball's cone or twist, a
        universal or gimbal joint's limit on one of its hinges."""
        _, record = self._actuated_joint("joint_limited", joint)
        return bool(record.has_limits or record.has_cone or any(record.axis_limited))

    def set_limit_softness(self, joint: int, time_constant: float, damping_ratio: float = 1.0) -> None:
        """Make a joint's limits soft, as MuJoCo's are (MJCF solreflimit = (time_constant,
        damping_ratio)): past a bound, the limit row is an implicit spring and damper per unit of
        its effective mass (the joint's armature included, `add_armature`, as MuJoCo's joint-space
        mass includes it), so that the overshoot decays like a damped oscillator of natural
        frequency 1 / (time_constant damping_ratio) and that damping ratio, whatever the masses.
        A joint built past a bound eases back over about `time_constant` instead of being snapped
        back within one step; a limit hit at speed is overrun by about speed x time_constant.
        time_constant: s, > 0. damping_ratio: > 0 (1: critically damped). Limits stay rigid by
        default. The DBD solver only (`rows.soft_limit`): the impulse solver keeps its limits rigid,
        eased by its Baumgarte bias (soft velocity rows made Brax's ant, whose armature that solver
        already fails on, gain 94 J instead of 16 J, and its humanoid follow MuJoCo less closely).
        """
        label, record = self._actuated_joint("set_limit_softness", joint)
        if not self.joint_limited(joint):
            raise ValueError(f"set_limit_softness: {label} has no limits")
        time_constant = _scalar(time_constant, f"set_limit_softness on {label}: time_constant")
        damping_ratio = _scalar(damping_ratio, f"set_limit_softness on {label}: damping_ratio")
        if not (time_constant > 0.0 and damping_ratio > 0.0):
            raise ValueError(f"set_limit_softness on {label}: time_constant and damping_ratio must be positive, got "
                             f"{time_constant} and {damping_ratio}")  # fmt: skip
        frequency = 1.0 / (time_constant * damping_ratio)  # rad/s
        record.limit_stiffness = frequency**2
        record.limit_damping = 2.0 / time_constant  # = 2 damping_ratio frequency

    def add_armature(self, joint: int, armature: float | Sequence[float]) -> None:
        """Rotor inertia on a joint's degrees of freedom (MJCF's armature): kg m^2 on a hinge, planar
        (its rotation), ball (about every axis), universal or gimbal joint (one number, or one per
        hinge); kg along a slider.

        MuJoCo adds armature to the diagonal of the joint-space mass matrix: kinetic energy
        1/2 armature qdot^2 in the joint's own coordinate q (an angle of b relative to a, or the
        slider's travel). Here it is that same energy in the step's variational form (DBD 3-4):
        1/2 armature (q(X) - q(X*))^2 / h^2, X* the bodies' inertial prediction, is one implicit
        spring row of the joint (the spring rule of DBD 8.1 with k h^2 = armature) per degree of
        freedom, toward where the rotor's own inertia carries it. It holds whatever the bodies
        do (a rotor on a joint between two free bodies spins up both bodies' relative motion,
        not one body's), unlike adding armature a a^T to the child's inertia, which is right only
        while the parent does not turn. A torque actuator (`add_torque`) on a degree of freedom
        with armature acts through that row (it accelerates bodies and rotor together, as in
        MuJoCo); on a ball joint with armature, torque actuators are refused at finalize. The impulse
        solver (finalize(solver="impulse")) holds a flywheel of inertia armature to the coordinate's
        velocity instead, one velocity row per degree of freedom (constraints/velocity_rows.py).
        """
        label, record = self._actuated_joint("add_armature", joint)
        if record.kind == FIXED:
            raise ValueError(f"add_armature: {label} is a fixed joint; it has no degree of freedom")
        count = record.num_axes or 1
        values = np.atleast_1d(np.asarray(armature, dtype=np.float64))
        if values.size == 1:
            values = np.repeat(values, count)
        if values.shape != (count,):
            raise ValueError(f"add_armature: {label}: armature must be a number or one per hinge ({count}), "
                             f"got {armature!r}")  # fmt: skip
        record.armature = np.zeros(3)
        record.armature[:count] = [self._non_negative(v, f"add_armature on {label}: armature") for v in values]

    def add_motor(self, joint: int, max_force: float, name: str | None = None) -> slice:
        """A motor driving a joint at a control target speed with a force limit (SI 2.3.6, 2.4.6).

        Hinge joints: speed in rad/s, max_force a torque (N m). Slider joints: speed in m/s of b
        along the axis, max_force in N. Returns the motor's slice (1 entry) of the control vector.
        """
        label, record = self._actuated_joint("add_motor", joint)
        if record.kind not in (HINGE, SLIDER):
            raise ValueError(f"add_motor: {label} is a {JOINT_KIND_NAMES[record.kind]} joint; motors act on hinge "
                             "and slider joints")  # fmt: skip
        if record.motor_control is not None:
            raise ValueError(f"add_motor: {label} already has a motor")
        record.motor_max_force = _scalar(max_force, f"add_motor on {label}: max_force")
        if record.motor_max_force <= 0.0:
            raise ValueError(f"add_motor on {label}: max_force must be positive, got {max_force}")
        controls = self._new_controls(f"motor on {name or record.name}", 1)
        record.motor_control = controls.start
        return controls

    def add_torque(
        self, joint: int, gear: float = 1.0, axis: Sequence[float] | None = None, name: str | None = None,
        dof: int | None = None,
    ) -> slice:  # fmt: skip
        """A torque actuator (MJCF <motor>): gear * control as an external torque on the joint.

        Hinge: torque gear * u (N m) about the axle on b and the opposite on a. Slider: force
        gear * u (N) along the axis on b, and the opposite on a at the same point. Ball: torque
        about `axis` (world, at build time; required), which turns with both bodies (the
        normalised sum of the axis carried by a and by b). Universal, gimbal: `dof` (0, 1 or 2)
        names the hinge, and gear * u is the generalised force on that hinge's angle alone, as
        MuJoCo's motor on that hinge: the torque along the dual direction g_dof of
        `math.euler_angles` (the hinge's own axis while the other axes stay perpendicular to it).
        The torque is held constant over each substep and applied in the prediction (as MuJoCo's
        actuator force, semi-implicit Euler). Returns the actuator's slice (1 entry) of the
        control vector.
        """
        label, record = self._actuated_joint("add_torque", joint)
        if record.kind not in (HINGE, SLIDER, BALL, UNIVERSAL, GIMBAL):
            raise ValueError(f"add_torque: {label} is a {JOINT_KIND_NAMES[record.kind]} joint; torque actuators act "
                             "on hinge, slider, ball, universal and gimbal joints")  # fmt: skip
        gear = _scalar(gear, f"add_torque on {label}: gear")
        if record.num_axes:
            if axis is not None or not isinstance(dof, (int, np.integer)) or not 0 <= dof < record.num_axes:
                raise ValueError(f"add_torque: {label} has {record.num_axes} hinges; give dof = 0 .. "
                                 f"{record.num_axes - 1} (and no axis), got dof={dof!r}")  # fmt: skip
            controls = self._new_controls(f"torque on {name or record.name}", 1)
            self._torques.append(_Torque(int(joint), gear, record.axes[dof], False, controls.start, int(dof)))
            return controls
        if dof is not None:
            raise ValueError(f"add_torque: {label} has no hinges to pick with dof; leave it out")
        if record.kind == BALL:
            if axis is None:
                raise ValueError(f"add_torque: {label} is a ball joint; give the torque axis")
            direction = _unit(axis, f"add_torque on {label}: axis")
        else:
            if axis is not None:
                raise ValueError(f"add_torque: {label} acts along its own axis; leave axis out")
            direction = record.axis
        controls = self._new_controls(f"torque on {name or record.name}", 1)
        self._torques.append(_Torque(int(joint), gear, direction, record.kind == SLIDER, controls.start))
        return controls

    def add_ik_target(
        self,
        body: int,
        point: Sequence[float],
        stiffness: float | None = None,
        damping: float = 0.0,
        max_force: float | None = None,
        name: str | None = None,
    ) -> slice:
        """Inverse kinematics as a constraint (DBD 11, last paragraph): pull `point` (world, at
        build time) of `body` to a target that the control vector moves, solved in the same sweeps
        as the joints, contacts and forces (constraints/targets.py).

        Three control entries: the target's offset (m, world) from `point`, so zero control holds
        the point where it was built (as a drive's zero is its build pose). stiffness (N/m): None
        for a rigid target (the point constraint of DBD (64)-(66) to a moving world point), else
        an implicit spring of zero rest length (DBD 8.1) with damping (N s/m). max_force (N): the
        largest pull, None for none; with a limit an unreachable target stretches the chain
        toward it and no further, instead of pulling its joints apart (a soft target pulls along
        the line to its goal; a rigid one spends its limit where the chain resists most, along a
        straight chain, and turns toward the goal slowly). Not available with solver="impulse".
        Returns the target's slice of the control vector.
        """
        label = f"IK target {len(self._ik_targets)}" + (f" ({name!r})" if name else "")
        if not isinstance(body, (int, np.integer)) or isinstance(body, bool) or not 0 <= body < len(self._bodies):
            raise ValueError(f"add_ik_target: {label}: body = {body!r} is not a body index (there are "
                             f"{len(self._bodies)} bodies; a target pulls a body, not the world)")  # fmt: skip
        point = _vector(point, 3, f"{label}: point")
        if stiffness is None:
            stiffness = math.inf
        else:
            stiffness = _scalar(stiffness, f"{label}: stiffness")
            if not 0.0 < stiffness < math.inf:
                raise ValueError(f"{label}: stiffness must be positive and finite (None for a rigid target), "
                                 f"got {stiffness}")  # fmt: skip
        damping = self._non_negative(damping, f"{label}: damping")
        if max_force is None:
            max_force = math.inf
        else:
            max_force = _scalar(max_force, f"{label}: max_force")
            if not 0.0 < max_force < math.inf:
                raise ValueError(f"{label}: max_force must be positive and finite (None for no limit), got {max_force}")
        controls = self._new_controls(f"{name or label} target", 3)
        self._ik_targets.append(_IKTarget(int(body), point, stiffness, damping, max_force, controls.start))
        return controls

    def set_control_range(self, controls: slice | int, lower: float, upper: float) -> None:
        """Record the range [lower, upper] the control entries `controls` are meant for (MJCF's
        ctrlrange; `Model.control_range`). Informational: `step` does not clip."""
        entries = range(len(self._control_names))[
            controls if isinstance(controls, slice) else slice(controls, controls + 1)
        ]
        if not len(entries):
            raise ValueError(f"set_control_range: {controls!r} names no control entry "
                             f"(there are {len(self._control_names)})")  # fmt: skip
        lower, upper = float(lower), float(upper)
        if math.isnan(lower) or math.isnan(upper) or lower > upper:
            raise ValueError(f"set_control_range: need lower <= upper, got ({lower}, {upper})")
        for entry in entries:
            self._control_ranges[entry] = (lower, upper)

    def _actuated_joint(self, what: str, joint) -> tuple[str, _Joint]:
        if not isinstance(joint, (int, np.integer)) or isinstance(joint, bool) or not 0 <= joint < len(self._joints):
            raise ValueError(f"{what}: joint = {joint!r} is not a joint index (there are {len(self._joints)} joints)")
        record = self._joints[joint]
        return f"{JOINT_KIND_NAMES[record.kind]} joint {joint} ({record.name!r})", record

    def _new_controls(self, name: str, size: int) -> slice:
        start = len(self._control_names)
        self._control_names.extend([name] if size == 1 else [f"{name} [{axis}]" for axis in "xyz"[:size]])
        self._control_ranges.extend([(-math.inf, math.inf)] * size)
        return slice(start, start + size)

    @staticmethod
    def _non_negative(value, what: str) -> float:
        number = _scalar(value, what)
        if number < 0.0:
            raise ValueError(f"{what} must be >= 0, got {number}")
        return number

    # ----------------------------------------------------------------------------- links
    def add_spring(
        self,
        body_a: int,
        body_b: int,
        anchor_a: Sequence[float],
        anchor_b: Sequence[float],
        stiffness: float,
        damping: float = 0.0,
        rest_length: float | None = None,
        relaxation: float = 1.0,
    ) -> int:
        """A linear spring/damper between world points `anchor_a` on body a and `anchor_b` on b
        (at build time), DBD 8.1. stiffness N/m, damping N s/m (along the line), rest_length m
        (default: the distance at build time). Returns the spring's index."""
        label = f"spring {len(self._springs)}"
        link = self._link(label, body_a, body_b, anchor_a, anchor_b, rest_length, relaxation)
        link.stiffness = self._non_negative(stiffness, f"{label}: stiffness")
        link.damping = self._non_negative(damping, f"{label}: damping")
        self._springs.append(link)
        return len(self._springs) - 1

    def add_distance(
        self,
        body_a: int,
        body_b: int,
        anchor_a: Sequence[float],
        anchor_b: Sequence[float],
        length: float | None = None,
        relaxation: float = 1.0,
    ) -> int:
        """A rigid distance constraint between world points on two bodies (default length: the
        distance at build time). Returns its index."""
        label = f"distance {len(self._distances)}"
        self._distances.append(self._link(label, body_a, body_b, anchor_a, anchor_b, length, relaxation))
        return len(self._distances) - 1

    def _link(self, label, body_a, body_b, anchor_a, anchor_b, length, relaxation) -> _Link:
        self._check_bodies(label, body_a, body_b)
        anchor_a = _vector(anchor_a, 3, f"{label}: anchor_a")
        anchor_b = _vector(anchor_b, 3, f"{label}: anchor_b")
        if length is None:
            length = float(np.linalg.norm(anchor_a - anchor_b))
        length = self._non_negative(length, f"{label}: length")
        return _Link(int(body_a), int(body_b), anchor_a, anchor_b, length, 0.0, 0.0,
                     self._relaxation(label, relaxation))  # fmt: skip

    @staticmethod
    def _baumgarte(what: str, value) -> float:
        beta = _scalar(value, what)
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"{what} must be in [0, 1] (SI (17): the fraction of the error removed per step), "
                             f"got {beta}")  # fmt: skip
        return beta

    @staticmethod
    def _relaxation(label: str, relaxation) -> float:
        relaxation = _scalar(relaxation, f"{label}: relaxation")
        if not 0.0 < relaxation < 2.0:
            raise ValueError(f"{label}: relaxation must be in (0, 2) (DBD 4.2), got {relaxation}")
        return relaxation

    # ----------------------------------------------------------------------------- multi-body
    def add_rope(
        self,
        bodies: Sequence[int],
        length: float | None = None,
        segments: bool = True,
        relaxation: float = 1.0,
    ) -> int:
        """A rope through the centres of mass of `bodies`, in order (DBD 10.1).

        Adds the total-length constraint (118)-(121), sum of the segment lengths = `length`
        (default: the length at build time), and with `segments` a rigid distance constraint
        along each segment (115) at its build-time length. Pin an end with a joint or
        `add_distance` to the world. Returns the rope's index.
        """
        label = f"rope {len(self._ropes)}"
        nodes = self._distinct_bodies(label, bodies, minimum=2)
        centres = np.stack([self._bodies[b].pos for b in nodes])
        built = float(np.sum(np.linalg.norm(np.diff(centres, axis=0), axis=1)))
        length = built if length is None else self._non_negative(length, f"{label}: length")
        relaxation = self._relaxation(label, relaxation)
        self._ropes.append((nodes, length, relaxation))
        if segments:
            for a, b in zip(nodes[:-1], nodes[1:], strict=True):
                self.add_distance(a, b, self._bodies[a].pos, self._bodies[b].pos, relaxation=relaxation)
        return len(self._ropes) - 1

    def add_volume(self, bodies: Sequence[int], rest_volume: float | None = None, relaxation: float = 1.0) -> int:
        """Keep the signed volume of the tetrahedron of four centres of mass (DBD 10.2).

        rest_volume: m^3, signed (positive when x1 - x0, x2 - x0, x3 - x0 are right-handed);
        default: the volume at build time. Returns the constraint's index.
        """
        label = f"volume {len(self._volumes)}"
        nodes = self._distinct_bodies(label, bodies, minimum=4)
        if len(nodes) != 4:
            raise ValueError(f"{label}: a tetrahedron has 4 bodies, got {len(nodes)}")
        x = np.stack([self._bodies[b].pos for b in nodes])
        built = float(np.dot(x[1] - x[0], np.cross(x[2] - x[0], x[3] - x[0])) / 6.0)
        if rest_volume is None:
            if abs(built) < 1e-12:
                raise ValueError(f"{label}: the four centres of mass are coplanar; give rest_volume")
            rest_volume = built
        rest_volume = _scalar(rest_volume, f"{label}: rest_volume")
        self._volumes.append((nodes, rest_volume, self._relaxation(label, relaxation)))
        return len(self._volumes) - 1

    def _distinct_bodies(self, label: str, bodies, minimum: int) -> tuple[int, ...]:
        nodes = tuple(bodies)
        if len(nodes) < minimum:
            raise ValueError(f"{label}: needs at least {minimum} bodies, got {len(nodes)}")
        for body in nodes:
            if not isinstance(body, (int, np.integer)) or isinstance(body, bool) or not 0 <= body < len(self._bodies):
                raise ValueError(f"{label}: {body!r} is not a body index (there are {len(self._bodies)} bodies; "
                                 "the world cannot be a node)")  # fmt: skip
        if len(set(nodes)) != len(nodes):
            raise ValueError(f"{label}: a body appears twice in {list(nodes)}")
        return tuple(int(b) for b in nodes)

    # ----------------------------------------------------------------------------- forces
    def add_force(self, bodies: Sequence[int], function: Callable, params: Any = None, name: str | None = None) -> int:
        """A force/torque given as a JAX function of the state of `bodies` (DBD 8, (94)-(99)).

        function(pos (k, 3), quat (k, 4), vel (k, 3), ang_vel (k, 3), params) -> (force (k, 3),
        torque (k, 3)): world frame, forces at the centres of mass, k = len(bodies). It is
        applied implicitly (its derivative w.r.t. the bodies' motion is taken by autodiff), so
        stiff springs and dampers stay stable. params: a pytree of arrays, differentiable
        (`model.forces`). Elements sharing one function are vmapped together; their params must
        have the same structure. Returns the force's index.
        """
        label = f"force {len(self._forces)}" + (f" ({name!r})" if name else "")
        if not callable(function):
            raise ValueError(f"{label}: function must be callable, got {function!r}")
        nodes = self._distinct_bodies(label, bodies, minimum=1)
        params = jax.tree.map(lambda x: np.asarray(x, dtype=np.float64), params)
        for leaf in jax.tree.leaves(params):
            if not np.all(np.isfinite(leaf)):
                raise ValueError(f"{label}: params contain NaN or infinity")
        self._forces.append(_Force(nodes, function, params, name or label))
        return len(self._forces) - 1

    # ----------------------------------------------------------------------------- finalize
    def finalize(
        self,
        dt: float = 1.0 / 60.0,
        substeps: int = 1,
        iterations: int = 8,
        solver: str = "dbd",
        jacobi: bool = False,
        velocity_dependent_inertia: bool = False,
        checkpoint: bool = False,
        contact_margin: float = 0.01,
        contact_compliance: float = 0.0,
        depenetration_speed: float = 1.0,
        restitution_iterations: int = 2,
        initial_guess: str = "zero",
        baumgarte: float = 0.05,
        tree_solve: bool = False,
        point_sweeps: int = 0,
    ) -> Model:
        """Freeze the description into a `Model` for `init`, `step` and `rollout`.

        dt: seconds per `step`; each step runs `substeps` substeps of dt / substeps, and each
        substep `iterations` Gauss-Seidel sweeps over the colour groups (DBD Algorithm 1).
        jacobi: project every joint at once and average per body instead (for comparison).
        velocity_dependent_inertia: use the effective inertia of DBD (58) in the solver.
        checkpoint: rematerialise each substep in reverse mode (memory flat in substeps).
        contact_margin: m, shapes closer than this at the predicted pose, or at the start of the
        substep, get contact slots (speculative contacts; they only push once they touch).
        contact_compliance: m/N, 0 for rigid contacts; a small value (1e-6 .. 1e-4) makes contact a
        stiff spring, whose gradients are smoother for trajectory optimisation.
        depenetration_speed: m/s, the fastest the DBD solver pushes a point out of a penetration
        it began a substep in (the rest waits for the next substeps; inf: all at once,
        which gives a deep point depth / h, a kick at small h). restitution_iterations: sweeps of
        the velocity pass (restitution).
        solver: "dbd" (DBD Algorithm 1, positions) or "impulse" (SI: sequential impulses on the
        velocities with Baumgarte bias, semi-implicit Euler; solvers/impulse.py). The impulse
        solver has velocity rows for every joint kind (universal and gimbal joints: the point,
        the universal's lock, per-hinge limits and drives), motors, drives, torques and armature
        (a flywheel row per degree of freedom, constraints/velocity_rows.py); it refuses IK
        targets (ValueError). baumgarte: beta of SI (17) for the impulse solver, the share of a
        position error its bias removes per substep (contacts, links, and joints that were not
        given their own). 0.05, not Catto's 0.2: the bias is a velocity beta C / h that the
        rotors (armature) and the next substeps keep, and at 0.2 Brax's humanoid at 4 substeps
        and its ant under random control ran away (README, "The Baumgarte bias's default").
        initial_guess: where each substep's sweeps start. "zero" (default): dX = 0 as in DBD Algorithm 1;
          "tree": the exact solution of the linearised point constraints of the joint tree
          (solvers/tree.py), which long chains need to hold their tension.
        tree_solve: end every iteration but the last (where the whole-joint solve below follows)
          with that exact solve, linearised where the sweep left the bodies (block Gauss-Seidel:
          the joint tree's points as one block, solved directly). The
          joint points then hold to second order at every step and the other rows carry what the
          sweeps leave: a 20-link chain at dt = 1/30 and 10 iterations keeps its joints to
          0.0001 mm (170 mm without). A tree body's contacts with the world are rows of every
          direct solve, unilateral and within the friction cone by one active-set step
          (solvers/tree_contacts.py): they carry the load (a standing ragdoll's 687 N on its feet)
          and a leaning ragdoll stands at 1 substep x 1 iteration (under the env's pushes it
          needs 2 substeps: docs/brax_comparison.md, session 27). After the last sweep one more direct solve takes each
          tree joint whole: point, rotation lock, rotors (armature), the soft angle limits past their
          bounds and its drive within its torque limit, so a joint with a heavy rotor, pressed on a
          limit or driven is solved with its point (Brax's dropped ant lands at 1 iteration as at 32
          sweeps alone; a driven arm settles at its static sag within 1.1e-6 rad). DBD solver only; off by
          default.
        point_sweeps: sweeps of the joints' points alone after the `iterations` whole-joint sweeps
          (`solvers.dbd.sweep_joint_points`), which close what the other rows of a joint left open
          at its neighbours' points. Brax's ant at 1 substep x 4 iterations, dropped: largest joint
          gap 19.6 -> 3.8 mm with 2 point sweeps (docs/brax_comparison.md, "Point sweeps"). Contacts, limits and
          drives are not in the point sweeps, which can undo them: with 2, the driven ragdoll of
          `examples/ragdoll_demo.py` fell (pelvis 0.13 m) and its 10,000 random-action steps went
          64 mm into the floor (its test allows 20 mm, and passes without). DBD solver only; 0 (none) by
          default.
        """
        dt = _scalar(dt, "finalize: dt")
        if dt <= 0.0:
            raise ValueError(f"finalize: dt must be positive, got {dt}")
        for what, count in (("substeps", substeps), ("iterations", iterations),
                            ("restitution_iterations", restitution_iterations)):  # fmt: skip
            if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
                raise ValueError(f"finalize: {what} must be a positive integer, got {count!r}")
        if not isinstance(point_sweeps, (int, np.integer)) or isinstance(point_sweeps, bool) or point_sweeps < 0:
            raise ValueError(f"finalize: point_sweeps must be a non-negative integer, got {point_sweeps!r}")
        if solver not in SOLVERS:
            raise ValueError(f"finalize: unknown solver {solver!r}; choose one of {SOLVERS}")
        if initial_guess not in INITIAL_GUESSES:
            raise ValueError(f"finalize: unknown initial_guess {initial_guess!r}; choose one of {INITIAL_GUESSES}")
        if solver == "impulse":
            self._check_impulse_support()
            if tree_solve:
                raise ValueError(
                    "finalize: tree_solve is a step of the DBD solver's iterations; solver='impulse' has none"
                )
            if point_sweeps:
                raise ValueError("finalize: point_sweeps are the DBD solver's; solver='impulse' sweeps its joints' "
                                 "points after its rotor pass already")  # fmt: skip
        baumgarte = self._baumgarte("finalize: baumgarte", baumgarte)
        if not self._bodies:
            raise ValueError("finalize: the model has no bodies")
        contact_margin = self._non_negative(contact_margin, "finalize: contact_margin")
        contact_compliance = self._non_negative(contact_compliance, "finalize: contact_compliance")
        depenetration_speed = float(depenetration_speed)
        if not depenetration_speed > 0.0:  # NaN fails this too
            raise ValueError(
                f"finalize: depenetration_speed must be positive (m/s; inf for none), got {depenetration_speed}"
            )

        options = Options(
            dt=dt, substeps=int(substeps), iterations=int(iterations), solver=solver,
            jacobi=bool(jacobi), velocity_dependent_inertia=bool(velocity_dependent_inertia),
            checkpoint=bool(checkpoint), contact_margin=contact_margin, contact_compliance=contact_compliance,
            depenetration_speed=depenetration_speed,
            restitution_iterations=int(restitution_iterations), initial_guess=initial_guess, baumgarte=baumgarte,
            tree_solve=bool(tree_solve), point_sweeps=int(point_sweeps),
        )  # fmt: skip
        return self._model(options)

    def _check_impulse_support(self) -> None:
        """Refuse, naming the element, what the impulse solver has no velocity rows for: IK targets.
        (Every joint kind, limit, drive, motor, torque and armature has its rows in
        constraints/velocity_rows.py.)"""
        if self._ik_targets:
            raise ValueError(f"finalize: IK target 0 (on body {self._ik_targets[0].body}): the impulse solver has no "
                             "IK target constraint; use solver='dbd'")  # fmt: skip

    def _resolve_bodies(self) -> tuple[list[_Body], list[tuple[np.ndarray, np.ndarray]]]:
        """Bodies with every mass and inertia filled in, and each shape's pose in its body's frame.

        Mass and inertia that were not given come from the body's shapes (density x volume, the
        inertia tensor about the centre of mass). When the shapes' centre of mass or principal
        axes differ from the body frame, the frame moves there (velocities follow: the centre's
        velocity is v + w x offset) and the shapes' local poses are re-expressed in it.
        """
        resolved = [dataclasses.replace(b) for b in self._bodies]
        poses = [(s.pos, s.quat) for s in self._shapes]
        for index, body in enumerate(resolved):
            if body.mass is not None and body.inertia is not None:
                continue
            own = [i for i, s in enumerate(self._shapes) if s.body == index]
            if not own:
                body.mass = 1.0 if body.mass is None else body.mass
                body.inertia = np.full(3, 0.1) if body.inertia is None else body.inertia
                continue
            records = [self._shapes[i] for i in own]
            mass, centre, tensor = shapes.mass_properties(
                [s.kind for s in records], [s.size for s in records], [s.pos for s in records],
                [s.quat for s in records], [s.density for s in records],
            )  # fmt: skip
            if body.mass is not None:  # the given mass, the shapes' mass distribution
                tensor, mass = tensor * body.mass / mass, body.mass
            if body.inertia is not None:  # the given inertia keeps the given frame
                centre, moments, turn = np.zeros(3), body.inertia, np.array([1.0, 0.0, 0.0, 0.0])
            else:
                moments, turn = shapes.principal_axes(tensor)
            _check_inertia(f"body {index} ({body.name!r}), inertia from its shapes,", moments)
            body.vel = body.vel + np.cross(body.ang_vel, host_math.rotate(body.quat, centre))
            body.pos = body.pos + host_math.rotate(body.quat, centre)
            body.quat = host_math.multiply(body.quat, turn)
            body.mass, body.inertia = mass, moments
            for i in own:  # shape pose in the new frame: turn^-1 (pos - centre), turn^-1 q
                pos, quat = poses[i]
                poses[i] = (
                    host_math.rotate(turn, pos - centre, inverse=True),
                    host_math.multiply(host_math.conjugate(turn), quat),
                )
        return resolved, poses

    @staticmethod
    def _frame(bodies: list[_Body], index: int) -> tuple[np.ndarray, np.ndarray]:
        """(position, orientation) of a body at build time; the world is the identity at the origin."""
        if index == WORLD:
            return np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        return bodies[index].pos, bodies[index].quat

    def _local_point(self, bodies: list[_Body], index: int, point: np.ndarray) -> np.ndarray:
        """A world point at build time in the frame of body `index` (world coordinates for the world)."""
        pos, quat = self._frame(bodies, index)
        return host_math.rotate(quat, point - pos, inverse=True)

    def _contact_groups(self, num_bodies: int) -> tuple[ContactGroup, ...]:
        """The shape pairs that may touch, grouped by kind pair (kind_a <= kind_b).

        Left out: shapes of one body, two static shapes, bodies excluded by `exclude_collision`,
        bodies joined by a joint (unless `allow_collision`), and pairs MuJoCo's contype /
        conaffinity rule rejects.
        """
        jointed = {frozenset((j.body_a, j.body_b)) for j in self._joints} - self._allowed
        groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for i, first in enumerate(self._shapes):
            for j in range(i + 1, len(self._shapes)):
                second = self._shapes[j]
                bodies = frozenset((first.body, second.body))
                if (first.body == second.body or (first.body == WORLD and second.body == WORLD)
                        or bodies in self._excluded or bodies in jointed
                        or not shapes.may_collide(first.contype, first.conaffinity, second.contype,
                                                  second.conaffinity)):  # fmt: skip
                    continue
                pair = (i, j) if first.kind <= second.kind else (j, i)
                groups.setdefault((self._shapes[pair[0]].kind, self._shapes[pair[1]].kind), []).append(pair)
        body_of = np.asarray([num_bodies if s.body == WORLD else s.body for s in self._shapes], dtype=np.int32)
        result = []
        for (kind_a, kind_b), pairs in sorted(groups.items()):
            table = np.asarray(pairs, dtype=np.int32).reshape(-1, 2)
            result.append(ContactGroup(kind_a, kind_b, StaticArray(table), StaticArray(body_of[table]),
                                       num_points(kind_a, kind_b)))  # fmt: skip
        return tuple(result)

    def _model(self, options: Options) -> Model:
        n = len(self._bodies)
        body, shape_poses = self._resolve_bodies()
        frame = functools.partial(self._frame, body)
        local_point = functools.partial(self._local_point, body)
        bodies = Bodies(
            mass=jnp.asarray([b.mass for b in body]),
            inertia=jnp.asarray(np.stack([b.inertia for b in body])),
            initial_pos=jnp.asarray(np.stack([b.pos for b in body])),
            initial_quat=jnp.asarray(np.stack([b.quat for b in body])),
            initial_vel=jnp.asarray(np.stack([b.vel for b in body])),
            initial_ang_vel=jnp.asarray(np.stack([b.ang_vel for b in body])),
        )

        def table(rows, width: int) -> jnp.ndarray:
            return jnp.asarray(np.reshape(np.asarray(rows, dtype=np.float64), (-1, width)))

        def column(records, field: str) -> jnp.ndarray:
            return jnp.asarray(np.asarray([getattr(r, field) for r in records], dtype=np.float64))

        # Body index n (one past the last) stands for the world in the solver's tables.
        def solver_index(index: int) -> int:
            return n if index == WORLD else index

        def body_table(rows, width: int) -> StaticArray:
            return StaticArray(np.reshape(np.asarray(rows, dtype=np.int32), (-1, width)))

        js = self._joints

        def local_axes(side: str) -> jnp.ndarray:
            """(J, 3, 3) the hinge axes of universal and gimbal joints in one side's body frame."""
            rows = [np.eye(3) if j.axes is None else
                    np.stack([host_math.rotate(frame(getattr(j, side))[1], axis, inverse=True) for axis in j.axes])
                    for j in js]  # fmt: skip
            return jnp.asarray(np.reshape(np.asarray(rows, dtype=np.float64), (-1, 3, 3)))

        joints = Joints(
            local_anchor_a=table([local_point(j.body_a, j.anchor) for j in js], 3),
            local_anchor_b=table([local_point(j.body_b, j.anchor) for j in js], 3),
            local_axis_a=table([host_math.rotate(frame(j.body_a)[1], j.axis, inverse=True) for j in js], 3),
            local_axis_b=table([host_math.rotate(frame(j.body_b)[1], j.axis if j.axis_b is None else j.axis_b,
                                                 inverse=True) for j in js], 3),  # fmt: skip
            rest_rotation=table([host_math.multiply(host_math.conjugate(frame(j.body_a)[1]), frame(j.body_b)[1])
                                 for j in js], 4),  # fmt: skip
            **{f: column(js, f) for f in ("lower", "upper", "cone_limit", "relaxation", "regularization",
                                          "drive_stiffness", "drive_damping", "drive_max_torque", "motor_max_force",
                                          "limit_stiffness", "limit_damping")},
            local_axes_a=local_axes("body_a"),
            local_axes_b=local_axes("body_b"),
            **{f: table([getattr(j, f) for j in js], 3) for f in ("axis_lower", "axis_upper", "axis_stiffness",
                                                                  "axis_damping", "armature")},
            baumgarte=jnp.asarray(np.asarray([options.baumgarte if j.baumgarte is None else j.baumgarte for j in js],
                                             dtype=np.float64)),
        )  # fmt: skip
        # a torque on a degree of freedom with armature acts through the joint's rotor row
        in_joint = [js[t.joint].armature[max(t.dof, 0)] > 0.0 for t in self._torques]
        for t, inside in zip(self._torques, in_joint, strict=True):
            if inside and js[t.joint].kind == BALL:
                raise ValueError(f"finalize: ball joint {t.joint} ({js[t.joint].name!r}) has armature and a torque "
                                 "actuator; that combination is not supported")  # fmt: skip

        def links(records) -> tuple[dict, StaticArray]:
            arrays = dict(
                local_anchor_a=table([local_point(r.body_a, r.anchor_a) for r in records], 3),
                local_anchor_b=table([local_point(r.body_b, r.anchor_b) for r in records], 3),
                relaxation=column(records, "relaxation"),
            )
            return arrays, body_table([(solver_index(r.body_a), solver_index(r.body_b)) for r in records], 2)

        spring_arrays, spring_bodies = links(self._springs)
        springs = Springs(rest_length=column(self._springs, "length"), stiffness=column(self._springs, "stiffness"),
                          damping=column(self._springs, "damping"), **spring_arrays)  # fmt: skip
        distance_arrays, distance_bodies = links(self._distances)
        distances = Distances(length=column(self._distances, "length"), **distance_arrays)

        longest = max((len(nodes) for nodes, _, _ in self._ropes), default=2)
        ropes = Ropes(length=table([r[1] for r in self._ropes], 1)[:, 0],
                      relaxation=table([r[2] for r in self._ropes], 1)[:, 0])  # fmt: skip
        rope_bodies = body_table([list(nodes) + [n] * (longest - len(nodes)) for nodes, _, _ in self._ropes], longest)
        volumes = Volumes(rest_volume=table([v[1] for v in self._volumes], 1)[:, 0],
                          relaxation=table([v[2] for v in self._volumes], 1)[:, 0])  # fmt: skip
        volume_bodies = body_table([nodes for nodes, _, _ in self._volumes], 4)

        groups: dict[tuple, list[_Force]] = {}
        for force in self._forces:  # one group per function, body count and params structure
            key = (force.function, len(force.bodies), jax.tree.structure(force.params))
            groups.setdefault(key, []).append(force)
        force_groups = tuple(
            ForceGroup(function=key[0], bodies=body_table([f.bodies for f in members], key[1]),
                       name=f"forces {getattr(key[0], '__name__', 'function')} {g}")
            for g, (key, members) in enumerate(groups.items())
        )  # fmt: skip
        force_params = tuple(
            jax.tree.map(lambda *leaves: jnp.asarray(np.stack(leaves)), *[f.params for f in members])
            for members in groups.values()
        )

        num_controls = len(self._control_names)

        def controls(entries, width: int) -> StaticArray:
            return body_table([list(e) + [num_controls] * (width - len(e)) for e in entries], width)

        structure = Structure(
            num_bodies=n,
            num_joints=len(js),
            num_controls=num_controls,
            joint_body_a=StaticArray(np.asarray([solver_index(j.body_a) for j in js], dtype=np.int32)),
            joint_body_b=StaticArray(np.asarray([solver_index(j.body_b) for j in js], dtype=np.int32)),
            joint_kind=StaticArray(np.asarray([j.kind for j in js], dtype=np.int32)),
            joint_has_limits=StaticArray(np.asarray([j.has_limits for j in js], dtype=bool)),
            joint_has_cone=StaticArray(np.asarray([j.has_cone for j in js], dtype=bool)),
            joint_drive_control=controls([j.drive_control for j in js], 3),
            joint_motor_control=StaticArray(
                np.asarray([num_controls if j.motor_control is None else j.motor_control for j in js], dtype=np.int32)
            ),
            spring_bodies=spring_bodies,
            distance_bodies=distance_bodies,
            rope_bodies=rope_bodies,
            volume_bodies=volume_bodies,
            force_groups=force_groups,
            shape_kind=StaticArray(np.asarray([sh.kind for sh in self._shapes], dtype=np.int32)),
            shape_body=StaticArray(np.asarray([solver_index(sh.body) for sh in self._shapes], dtype=np.int32)),
            contact_groups=self._contact_groups(n),
            colours=(),
            contact_colours=(),
            body_names=tuple(b.name for b in body),
            joint_names=tuple(j.name for j in js),
            control_names=tuple(self._control_names),
            torque_bodies=body_table(
                [(solver_index(js[t.joint].body_a), solver_index(js[t.joint].body_b)) for t in self._torques], 2
            ),
            torque_control=StaticArray(np.asarray([t.control for t in self._torques], dtype=np.int32)),
            torque_linear=StaticArray(np.asarray([t.linear for t in self._torques], dtype=bool)),
            control_range=StaticArray(np.reshape(np.asarray(self._control_ranges, dtype=np.float64), (-1, 2))),
            joint_passive_drive=StaticArray(np.asarray([j.passive_drive for j in js], dtype=bool)),
            ik_target_bodies=body_table([(t.body, n) for t in self._ik_targets], 2),
            ik_target_control=body_table([[t.control + k for k in range(3)] for t in self._ik_targets], 3),
            joint_axis_limited=StaticArray(np.reshape(np.asarray([j.axis_limited for j in js], dtype=bool), (-1, 3))),
            torque_joint=StaticArray(np.asarray([t.joint for t in self._torques], dtype=np.int32)),
            torque_dof=StaticArray(np.asarray([t.dof for t in self._torques], dtype=np.int32)),
            torque_in_joint=StaticArray(np.asarray(in_joint, dtype=bool)),
            joint_rotor=StaticArray(np.reshape(np.asarray([j.armature > 0.0 for j in js], dtype=bool), (-1, 3))),
            joint_soft_limits=StaticArray(np.asarray([j.limit_stiffness > 0.0 for j in js], dtype=bool)),
            joint_drive_limited=StaticArray(np.asarray([np.isfinite(j.drive_max_torque) for j in js], dtype=bool)),
        )
        structure = dataclasses.replace(
            structure,
            colours=colouring.colour_groups(structure.family_bodies(), n, classes=colour_classes(structure)),
            contact_colours=colouring.colour_groups([g.bodies.array for g in structure.contact_groups], n),
        )
        sh = self._shapes
        shape_table = Shapes(
            size=table([r.size for r in sh], 3),
            local_pos=table([pos for pos, _ in shape_poses], 3),
            local_quat=table([quat for _, quat in shape_poses], 4),
            **{f: column(sh, f) for f in ("friction", "dynamic_friction", "restitution")},
        )
        ts = self._torques
        torques = Torques(
            gear=column(ts, "gear"),
            local_axis_a=table([host_math.rotate(frame(js[t.joint].body_a)[1], t.axis, inverse=True) for t in ts], 3),
            local_axis_b=table([host_math.rotate(frame(js[t.joint].body_b)[1], t.axis, inverse=True) for t in ts], 3),
        )
        ik = self._ik_targets
        ik_targets = IKTargets(
            local_point=table([local_point(t.body, t.point) for t in ik], 3),
            rest_target=table([t.point for t in ik], 3),
            **{f: column(ik, f) for f in ("stiffness", "damping", "max_force")},
        )
        return Model(bodies=bodies, joints=joints, springs=springs, distances=distances, ropes=ropes,
                     volumes=volumes, forces=force_params, shapes=shape_table, gravity=jnp.asarray(self.gravity),
                     structure=structure, options=options, torques=torques, ik_targets=ik_targets)  # fmt: skip
