"""`ModelBuilder`: describe bodies and joints in world coordinates, then `finalize()` a `Model`.

All checks happen here, on the host, so that a model that cannot be simulated is refused with a
`ValueError` naming the body or joint and the reason, before anything is traced.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from dbdjax import colouring
from dbdjax.model import (
    BALL,
    FIXED,
    HINGE,
    SLIDER,
    WORLD,
    Bodies,
    Joints,
    Model,
    Options,
    StaticArray,
    Structure,
)

SOLVERS = ("dbd",)
PLANNED_SOLVERS = ("impulse",)


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


def _rotate(quat: np.ndarray, vector: np.ndarray, inverse: bool = False) -> np.ndarray:
    w, u = quat[0], quat[1:] * (-1.0 if inverse else 1.0)
    t = 2.0 * np.cross(u, vector)
    return vector + w * t + np.cross(u, t)


def _multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def _conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


@dataclasses.dataclass
class _Body:
    name: str
    mass: float
    inertia: np.ndarray
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

    # ----------------------------------------------------------------------------- bodies
    def add_body(
        self,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
        mass: float = 1.0,
        inertia: Sequence[float] = (0.1, 0.1, 0.1),
        vel: Sequence[float] = (0.0, 0.0, 0.0),
        ang_vel: Sequence[float] = (0.0, 0.0, 0.0),
        name: str | None = None,
    ) -> int:
        """Add a rigid body and return its index.

        pos: centre of mass (m). quat: orientation of the body frame, in which `inertia` (the
        three principal moments, kg m^2) is given. vel, ang_vel: initial velocities (world).
        """
        index = len(self._bodies)
        label = f"body {index}" + (f" ({name!r})" if name else "")
        mass = _scalar(mass, f"{label}: mass")
        if mass <= 0.0:
            raise ValueError(f"{label}: mass must be positive, got {mass}")
        inertia = _vector(inertia, 3, f"{label}: inertia")
        if np.any(inertia <= 0.0):
            raise ValueError(f"{label}: inertia must be positive definite, got {inertia.tolist()}")
        for i in range(3):
            others = inertia[(i + 1) % 3] + inertia[(i + 2) % 3]
            if inertia[i] > others * (1.0 + 1e-6):
                raise ValueError(
                    f"{label}: inertia {inertia.tolist()} violates the triangle inequality "
                    "(no rigid body has one principal moment larger than the other two together)"
                )
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
    ) -> int:
        """Ball-and-socket joint at world point `anchor` (DBD section 5); returns its index.

        cone_limit: largest angle (rad, in (0, pi]) between the twist axis fixed in body a and
        the one fixed in body b (DBD (81)-(83)). twist_limits: (lower, upper) rad in [-pi, pi]
        of the rotation of b about the twist axis. twist_axis: world direction at build time;
        by default the direction from the anchor to body b's centre of mass (the bone).
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
            twist_limits is not None, cone, cone_limit is not None, relaxation, regularization,
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
    ) -> int:
        """Hinge about world `axis` through `anchor` (DBD 6, SI 2.4); limits (rad) in [-pi, pi]."""
        return self._add_axis_joint(HINGE, body_a, body_b, anchor, axis, limits, relaxation, regularization, name)

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
    ) -> int:
        """Slider (prismatic) along world `axis` (SI 2.3); limits (m) on the travel of b from a."""
        return self._add_axis_joint(SLIDER, body_a, body_b, anchor, axis, limits, relaxation, regularization, name)

    def _add_axis_joint(self, kind, body_a, body_b, anchor, axis, limits, relaxation, regularization, name) -> int:
        """Hinge or slider: a joint defined by an anchor and one axis, with optional limits."""
        label = self._joint_label("hinge" if kind == HINGE else "slider", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        axis = _unit(axis, f"{label}: axis")
        self._check_bodies(label, body_a, body_b)
        lower, upper = self._limits(label, limits, angular=kind == HINGE)
        return self._add_joint(
            label, name, kind, body_a, body_b, anchor, axis, lower, upper,
            limits is not None, math.pi, False, relaxation, regularization,
        )  # fmt: skip

    def add_fixed_joint(
        self,
        body_a: int,
        body_b: int,
        anchor: Sequence[float],
        relaxation: float = 1.0,
        regularization: float = 0.0,
        name: str | None = None,
    ) -> int:
        """Weld b to a at world `anchor` (SI 2.5): no relative motion at all."""
        label = self._joint_label("fixed", name)
        anchor = _vector(anchor, 3, f"{label}: anchor")
        self._check_bodies(label, body_a, body_b)
        return self._add_joint(
            label, name, FIXED, body_a, body_b, anchor, np.array([0.0, 0.0, 1.0]), 0.0, 0.0,
            False, math.pi, False, relaxation, regularization,
        )  # fmt: skip

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
                   has_limits, cone, has_cone, relaxation, regularization) -> int:  # fmt: skip
        relaxation = _scalar(relaxation, f"{label}: relaxation")
        if not 0.0 < relaxation < 2.0:
            raise ValueError(f"{label}: relaxation must be in (0, 2) (DBD 4.2), got {relaxation}")
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
            )  # fmt: skip
        )
        return len(self._joints) - 1

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
    ) -> Model:
        """Freeze the description into a `Model` for `init`, `step` and `rollout`.

        dt: seconds per `step`; each step runs `substeps` substeps of dt / substeps, and each
        substep `iterations` Gauss-Seidel sweeps over the colour groups (DBD Algorithm 1).
        jacobi: project every joint at once and average per body instead (for comparison).
        velocity_dependent_inertia: use the effective inertia of DBD (58) in the solver.
        checkpoint: rematerialise each substep in reverse mode (memory flat in substeps).
        """
        dt = _scalar(dt, "finalize: dt")
        if dt <= 0.0:
            raise ValueError(f"finalize: dt must be positive, got {dt}")
        for what, count in (("substeps", substeps), ("iterations", iterations)):
            if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
                raise ValueError(f"finalize: {what} must be a positive integer, got {count!r}")
        if solver not in SOLVERS:
            if solver in PLANNED_SOLVERS:
                raise ValueError(f"finalize: solver {solver!r} is not available yet; use 'dbd'")
            raise ValueError(f"finalize: unknown solver {solver!r}; choose one of {SOLVERS}")
        if not self._bodies:
            raise ValueError("finalize: the model has no bodies")

        bodies, joints, structure = self._arrays()
        options = Options(
            dt=dt, substeps=int(substeps), iterations=int(iterations), solver=solver,
            jacobi=bool(jacobi), velocity_dependent_inertia=bool(velocity_dependent_inertia),
            checkpoint=bool(checkpoint),
        )  # fmt: skip
        return Model(bodies=bodies, joints=joints, gravity=jnp.asarray(self.gravity),
                     structure=structure, options=options)  # fmt: skip

    def _arrays(self) -> tuple[Bodies, Joints, Structure]:
        n = len(self._bodies)
        body = self._bodies
        bodies = Bodies(
            mass=jnp.asarray([b.mass for b in body]),
            inertia=jnp.asarray(np.stack([b.inertia for b in body])),
            initial_pos=jnp.asarray(np.stack([b.pos for b in body])),
            initial_quat=jnp.asarray(np.stack([b.quat for b in body])),
            initial_vel=jnp.asarray(np.stack([b.vel for b in body])),
            initial_ang_vel=jnp.asarray(np.stack([b.ang_vel for b in body])),
        )

        identity = np.array([1.0, 0.0, 0.0, 0.0])
        rows = {k: [] for k in ("anchor_a", "anchor_b", "axis_a", "axis_b", "rest")}
        for joint in self._joints:
            frames = []
            for index in (joint.body_a, joint.body_b):
                if index == WORLD:  # the world frame is the identity at the origin
                    frames.append((np.zeros(3), identity))
                else:
                    frames.append((body[index].pos, body[index].quat))
            (pos_a, quat_a), (pos_b, quat_b) = frames
            rows["anchor_a"].append(_rotate(quat_a, joint.anchor - pos_a, inverse=True))
            rows["anchor_b"].append(_rotate(quat_b, joint.anchor - pos_b, inverse=True))
            rows["axis_a"].append(_rotate(quat_a, joint.axis, inverse=True))
            rows["axis_b"].append(_rotate(quat_b, joint.axis, inverse=True))
            rows["rest"].append(_multiply(_conjugate(quat_a), quat_b))

        def stacked(name: str, width: int) -> jnp.ndarray:
            return jnp.asarray(np.reshape(np.asarray(rows[name]), (-1, width)))

        def column(field: str) -> jnp.ndarray:
            return jnp.asarray(np.asarray([getattr(j, field) for j in self._joints], dtype=np.float64))

        joints = Joints(
            local_anchor_a=stacked("anchor_a", 3),
            local_anchor_b=stacked("anchor_b", 3),
            local_axis_a=stacked("axis_a", 3),
            local_axis_b=stacked("axis_b", 3),
            rest_rotation=stacked("rest", 4),
            lower=column("lower"),
            upper=column("upper"),
            cone_limit=column("cone_limit"),
            relaxation=column("relaxation"),
            regularization=column("regularization"),
        )

        # Body index n (one past the last) stands for the world in the solver's tables.
        def solver_index(index: int) -> int:
            return n if index == WORLD else index

        body_a = np.asarray([solver_index(j.body_a) for j in self._joints], dtype=np.int32)
        body_b = np.asarray([solver_index(j.body_b) for j in self._joints], dtype=np.int32)
        colours = colouring.greedy_colouring([(j.body_a, j.body_b) for j in self._joints], num_bodies=n)
        colour_joint, colour_body_slot = colouring.colour_tables(colours, body_a, body_b, n)
        structure = Structure(
            num_bodies=n,
            num_joints=len(self._joints),
            num_controls=0,
            joint_body_a=StaticArray(body_a),
            joint_body_b=StaticArray(body_b),
            joint_kind=StaticArray(np.asarray([j.kind for j in self._joints], dtype=np.int32)),
            joint_has_limits=StaticArray(np.asarray([j.has_limits for j in self._joints], dtype=bool)),
            joint_has_cone=StaticArray(np.asarray([j.has_cone for j in self._joints], dtype=bool)),
            colour_joint=StaticArray(colour_joint),
            colour_body_slot=StaticArray(colour_body_slot),
            body_names=tuple(b.name for b in body),
            joint_names=tuple(j.name for j in self._joints),
        )
        return bodies, joints, structure
