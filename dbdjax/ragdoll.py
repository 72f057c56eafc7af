"""A driven ragdoll: a humanoid of capsules with limited ball and hinge joints and torque-limited drives.

    from dbdjax import ragdoll
    builder, doll = ragdoll.build()                       # a new builder with gravity -z and a floor
    model = builder.finalize(dt=1 / 60, substeps=ragdoll.SUBSTEPS, iterations=ragdoll.ITERATIONS)
    control = ragdoll.pose_control(doll, {"knee_l": 0.5, "hip_l": (0.0, -0.4, 0.0)})
    state = dbd.step(model, dbd.init(model), control)

The doll stands at build time (arms hanging at its sides), faces +x, its left is +y, z is up. 15
bodies (pelvis, torso, head, upper_arm/lower_arm/hand and thigh/shin/foot on each side), one
capsule each (the feet lie along x, heel to toe; the pelvis along y). 14 joints: ball joints with cone and
twist limits at the waist, neck, shoulders and hips (the twist axis is the world z axis at build
time, along the bone); hinges at the elbows and knees (flexion), the ankles (about y) and the
wrists (about x). Every joint has a drive (DBD 9, `ModelBuilder.add_drive`) whose target is the
joint's rotation from the build pose: a rotation vector in the parent's frame (3 controls) for a
ball joint, an angle (1 control) for a hinge. Body frames are the world axes at build time, so
a ball joint's target is a rotation vector in world axes of the standing doll.

Stabilisation, as game engines build ragdolls (PhysX / Havok guidance):

- mass ratios: the segment masses are fixed fractions of `mass` (roughly anatomical, after de
  Leva's table, with the trunk split so that no jointed pair is further apart than
  MAX_MASS_RATIO = 10: the torso is 8.3 times an upper arm, the largest ratio).
- inertia: each body's inertia is that of its capsule at its mass, then (`_stabilised_inertia`)
  each foot's moments are raised to its shin's largest (the standing doll's load path roots at
  the feet: a foot at its own inertia is turned far more than the shin by the ankle drive, the
  floor turns it back, the two fight and the feet creep until the doll falls), and then, from
  the hands and feet up to the pelvis, every principal moment of a parent to at least the sum
  of its children's largest (a light parent between heavy children, the pelvis between the
  torso and the thighs, is otherwise spun by its children's drives and joint corrections faster
  than the Gauss-Seidel sweeps converge). Only moments below those bounds are raised, which
  keeps the triangle inequality. The pelvis gains 6-11x, the feet 10-45x, the shins' and
  thighs' moments about their long axes 11x and 2.5x; the other bodies keep theirs.
- collision: jointed neighbours never touch (`ModelBuilder` excludes jointed pairs), and by
  default the doll does not collide with itself at all: its shapes have contype 2 and
  conaffinity 1, so they touch anything with contype bit 1 (the floor and the builder's default
  shapes) but not each other (MuJoCo's rule (ct_a & ca_b) | (ct_b & ca_a)). Every shape pair
  that may touch is a contact node solved each iteration; without self-contacts the 15 floor
  contacts fill one colour of the solver. The price: limbs may pass through each other (legs
  crossing, an arm through the torso), as in many game ragdolls. `self_collision=True` gives
  conaffinity 3 instead: every pair of non-jointed bodies (91 more nodes) may touch; in the
  build pose none overlap (the hands hang 5 mm beside the thighs).
- drives: implicit (DBD 9), so stiff drives stay stable; their torque is limited per joint.

`pose_control` turns a pose (joint name -> angle or rotation vector) into the control vector.
`load_mjcf_ragdoll` loads the same doll from the MJCF file `dbdjax/assets/ragdoll.xml`, which
`mjcf_xml()` writes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from dbdjax import host_math, shapes
from dbdjax import math as dmath
from dbdjax.builder import ModelBuilder
from dbdjax.collision import BOX, CAPSULE, SPHERE
from dbdjax.model import Model, State

REFERENCE_HEIGHT = 1.8  # m: the table below is for a doll of this height; `height` scales it
REFERENCE_MASS = 70.0  # kg
MAX_MASS_RATIO = 10.0  # the largest mass ratio of two jointed bodies (game-engine guidance)
DOLL_CONTYPE = 2  # the doll's collision bits: touches contype-1 shapes (the floor), not itself
DOLL_CONAFFINITY = 1
SELF_CONAFFINITY = 3
FRICTION = 0.9  # doll shapes and the floor
# Defaults of `finalize` that the standing tests and benchmarks/ragdoll_step.py use.
DT = 1.0 / 60.0
SUBSTEPS = 2
ITERATIONS = 8
# Default drives of a 70 kg, 1.8 m doll at share 1 (waist, hips, knees), scaled by mass x height.
STIFFNESS = 10000.0  # N m/rad
DAMPING = 500.0  # N m s/rad
MAX_TORQUE = 400.0  # N m
ASSET = Path(__file__).parent / "assets" / "ragdoll.xml"


@dataclasses.dataclass(frozen=True)
class _Part:
    """One body at the reference height, feet at the origin, standing, facing +x: a capsule
    covering the segment start..end with its caps (start and end are its extreme points) of
    `radius` (m). mass: its fraction of the total."""

    name: str
    parent: str | None
    mass: float
    radius: float
    start: tuple[float, float, float]
    end: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class _JointSpec:
    """One joint: kind 'ball' (limits: cone, twist) or 'hinge' (axis, limits (lower, upper)).
    strength: the drive's share of `drive_stiffness` and `drive_damping`; torque: its share of
    `max_torque` (roughly a person's strength: the arms are far weaker than the legs)."""

    name: str
    parent: str
    child: str
    kind: str
    anchor: tuple[float, float, float]
    limits: tuple[float, float]
    strength: float
    torque: float
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)


def _sided(side: str, point: tuple[float, float, float]) -> tuple[float, float, float]:
    sign = 1.0 if side == "l" else -1.0
    return (point[0], sign * point[1], point[2])


def _parts() -> tuple[_Part, ...]:
    """The bodies in depth-first order (the order of the MJCF tree, hence of `load_mjcf`)."""
    parts = [
        _Part("pelvis", None, 0.19, 0.09, (0.0, -0.15, 0.98), (0.0, 0.15, 0.98)),
        _Part("torso", "pelvis", 0.29, 0.13, (0.0, 0.0, 1.05), (0.0, 0.0, 1.52)),
        _Part("head", "torso", 0.07, 0.10, (0.0, 0.0, 1.54), (0.0, 0.0, 1.80)),
    ]
    for s in "lr":
        parts += [
            _Part(f"upper_arm_{s}", "torso", 0.035, 0.045, _sided(s, (0, 0.2, 1.45)),
                  _sided(s, (0, 0.2, 1.16))),
            _Part(f"lower_arm_{s}", f"upper_arm_{s}", 0.02, 0.04, _sided(s, (0, 0.2, 1.16)),
                  _sided(s, (0, 0.2, 0.90))),
            _Part(f"hand_{s}", f"lower_arm_{s}", 0.008, 0.035, _sided(s, (0, 0.2, 0.90)),
                  _sided(s, (0, 0.2, 0.72))),
        ]  # fmt: skip
    for s in "lr":
        parts += [
            _Part(f"thigh_{s}", "pelvis", 0.10, 0.07, _sided(s, (0, 0.09, 0.92)), _sided(s, (0, 0.09, 0.50))),
            _Part(f"shin_{s}", f"thigh_{s}", 0.045, 0.05, _sided(s, (0, 0.09, 0.50)),
                  _sided(s, (0, 0.09, 0.085))),
            _Part(f"foot_{s}", f"shin_{s}", 0.017, 0.04, _sided(s, (-0.06, 0.09, 0.04)),
                  _sided(s, (0.16, 0.09, 0.04))),
        ]  # fmt: skip
    return tuple(parts)


def _joint_specs() -> tuple[_JointSpec, ...]:
    """The joints, one per non-root body, in the order of `_parts` (so controls line up with MJCF).

    Ball limits are (cone, twist): the largest angle (rad) between the bone at build time and the
    bone now, and the symmetric twist about it. Hinge axes: knees about +y and elbows about -y
    (positive = flexion), ankles about +y (positive = toes down), wrists about +x."""
    specs = [
        _JointSpec("waist", "pelvis", "torso", "ball", (0.0, 0.0, 1.05), (0.6, 0.6), 1.0, 1.0),
        _JointSpec("neck", "torso", "head", "ball", (0.0, 0.0, 1.53), (0.7, 1.0), 0.15, 0.125),
    ]
    for s in "lr":
        specs += [
            _JointSpec(f"shoulder_{s}", "torso", f"upper_arm_{s}", "ball", _sided(s, (0, 0.2, 1.43)), (2.4, 1.2), 0.3,
                       0.2),
            _JointSpec(f"elbow_{s}", f"upper_arm_{s}", f"lower_arm_{s}", "hinge", _sided(s, (0, 0.2, 1.16)),
                       (0.0, 2.4), 0.15, 0.15, (0.0, -1.0, 0.0)),
            _JointSpec(f"wrist_{s}", f"lower_arm_{s}", f"hand_{s}", "hinge", _sided(s, (0, 0.2, 0.90)),
                       (-1.0, 1.0), 0.03, 0.04, (1.0, 0.0, 0.0)),
        ]  # fmt: skip
    for s in "lr":
        specs += [
            _JointSpec(f"hip_{s}", "pelvis", f"thigh_{s}", "ball", _sided(s, (0, 0.09, 0.92)), (1.6, 0.6), 1.0, 1.0),
            _JointSpec(f"knee_{s}", f"thigh_{s}", f"shin_{s}", "hinge", _sided(s, (0, 0.09, 0.50)), (0.0, 2.4),
                       1.0, 1.0, (0.0, 1.0, 0.0)),
            _JointSpec(f"ankle_{s}", f"shin_{s}", f"foot_{s}", "hinge", _sided(s, (0, 0.09, 0.085)), (-0.5, 0.8),
                       0.8, 0.75, (0.0, 1.0, 0.0)),
        ]  # fmt: skip
    return tuple(specs)


PARTS = _parts()
JOINTS = _joint_specs()
BODY_NAMES = tuple(p.name for p in PARTS)
JOINT_NAMES = tuple(j.name for j in JOINTS)


@dataclasses.dataclass(frozen=True)
class Ragdoll:
    """What `build` added to the builder, by name.

    bodies: body name -> body index in the model. joints: joint name -> joint index.
    joint_kinds: joint name -> "ball" or "hinge". shapes: body name -> shape index.
    controls: joint name -> its slice of the doll's control block (3 entries for a ball joint: a
      rotation vector, rad, in the parent's frame; 1 for a hinge: an angle, rad; both from the
      build pose). control_slice: where that block lies in the model's control vector (slice(0,
      num_controls) when the doll is the first thing with controls in its builder).
    num_controls: 26. control_low, control_high: (num_controls,) the range of each drive target
      from the joint limits (ball: +-cone on the swing axes, the twist limits on z; hinge: its
      limits). rest_height: m, the pelvis centre's height standing in the build pose. height,
      mass: m, kg, as built. floor: the floor's shape index, or None.
    """

    bodies: dict[str, int]
    joints: dict[str, int]
    joint_kinds: dict[str, str]
    shapes: dict[str, int]
    controls: dict[str, slice]
    control_slice: slice
    num_controls: int
    control_low: np.ndarray
    control_high: np.ndarray
    rest_height: float
    height: float
    mass: float
    floor: int | None


def _capsule_axis(part: _Part) -> tuple[np.ndarray, float, np.ndarray]:
    """(centre (3,), half_length, unit axis (3,), pointing up or +y) of a capsule part, reference size."""
    start, end = np.asarray(part.start, dtype=np.float64), np.asarray(part.end, dtype=np.float64)
    length = float(np.linalg.norm(end - start))
    axis = (end - start) / length
    if axis[2] < 0.0:
        axis = -axis
    return (start + end) / 2.0, length / 2.0 - part.radius, axis


def _shape_inertia(part: _Part, scale: float, mass: float) -> np.ndarray:
    """Principal moments (kg m^2) in world axes of a part's capsule at `mass`, `scale` x reference size."""
    _, half, axis = _capsule_axis(part)
    volume, per_density = shapes.volume_and_inertia(CAPSULE, np.array([part.radius, half, 0.0]) * scale)
    rotation = host_math.to_matrix(host_math.z_to(axis))
    tensor = rotation @ np.diag(per_density * mass / volume) @ rotation.T
    return np.diag(tensor).copy()  # the capsules lie along the world axes: the tensor is diagonal


def _stabilised_inertia(moments: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Raise small principal moments so that the Gauss-Seidel sweeps converge (module docstring).

    moments: body name -> (3,) principal moments (kg m^2). Two rules, from the ends of the tree in:
    1. the feet carry the standing doll: in that load path a foot is the parent of its shin, so
       its moments are raised to the shin's largest (a foot at its own inertia is turned by the
       ankle drive and joint far more than the shin, and the contact under it turns it back:
       the two fight, the sweeps do not converge and the feet creep over the floor);
    2. every principal moment of a parent is at least the sum of its children's largest, from
       the hands and feet up to the pelvis, so a raised child raises its parent in turn.
    Raising the smallest moments keeps the triangle inequality (the largest is untouched or all
    become equal)."""
    result = {name: np.array(value, dtype=np.float64) for name, value in moments.items()}
    for part in PARTS:
        if part.name.startswith("foot"):
            result[part.name] = np.maximum(result[part.name], float(np.max(result[part.parent])))
    for part in reversed(PARTS):  # depth-first order reversed: every child before its parent
        children = [p.name for p in PARTS if p.parent == part.name]
        if children:
            floor = sum(float(np.max(result[c])) for c in children)
            result[part.name] = np.maximum(result[part.name], floor)
    return result


def mass_properties(height: float = REFERENCE_HEIGHT, mass: float = REFERENCE_MASS, stabilise: bool = True):
    """Mass (kg) and principal moments (3,) (kg m^2, world axes) of each body, by name.

    stabilise: apply the inertia rule of `_stabilised_inertia` (what `build` uses); False gives
    the shapes' own moments."""
    scale = height / REFERENCE_HEIGHT
    masses = {p.name: p.mass * mass for p in PARTS}
    moments = {p.name: _shape_inertia(p, scale, masses[p.name]) for p in PARTS}
    return masses, (_stabilised_inertia(moments) if stabilise else moments)


def _drive_parameter(value, default: float, joint: _JointSpec, share: float, what: str) -> float:
    """A drive parameter of one joint: value (float: the value at share 1, times the joint's
    share; Mapping: per joint name, missing joints from the default) or the default (at share 1)."""
    if isinstance(value, Mapping):
        unknown = set(value) - set(JOINT_NAMES)
        if unknown:
            raise ValueError(f"ragdoll.build: {what} names unknown joints {sorted(unknown)}; joints: {JOINT_NAMES}")
        return float(value[joint.name]) if joint.name in value else default * share
    base = default if value is None else float(value)
    return base * share


def _drives(height: float, mass: float, drive_stiffness, drive_damping, max_torque) -> dict[str, tuple]:
    """(stiffness, damping, max_torque) of every joint's drive, by name (see `build`)."""
    strength = (mass / REFERENCE_MASS) * (height / REFERENCE_HEIGHT)
    return {
        spec.name: (
            _drive_parameter(drive_stiffness, STIFFNESS * strength, spec, spec.strength, "drive_stiffness"),
            _drive_parameter(drive_damping, DAMPING * strength, spec, spec.strength, "drive_damping"),
            _drive_parameter(max_torque, MAX_TORQUE * strength, spec, spec.torque, "max_torque"),
        )
        for spec in JOINTS
    }


def _check_size(height: float, mass: float, what: str) -> None:
    if not (math.isfinite(height) and height > 0.0):
        raise ValueError(f"{what}: height must be positive, got {height}")
    if not (math.isfinite(mass) and mass > 0.0):
        raise ValueError(f"{what}: mass must be positive, got {mass}")


def _ranges(spec: _JointSpec) -> list[tuple[float, float]]:
    """The control range of each of a joint's drive entries (from its limits)."""
    if spec.kind == "ball":
        cone, twist = spec.limits
        return [(-cone, cone), (-cone, cone), (-twist, twist)]
    return [spec.limits]


def build(
    builder: ModelBuilder | None = None,
    *,
    height: float = REFERENCE_HEIGHT,
    mass: float = REFERENCE_MASS,
    drive_stiffness: float | Mapping[str, float] | None = None,
    drive_damping: float | Mapping[str, float] | None = None,
    max_torque: float | Mapping[str, float] | None = None,
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0),
    floor: bool = True,
    self_collision: bool = False,
    friction: float = FRICTION,
    contype: int = DOLL_CONTYPE,
    conaffinity: int | None = None,
    relaxation: float = 1.0,
) -> tuple[ModelBuilder, Ragdoll]:
    """Add a driven ragdoll, standing, to `builder` (a new one with gravity (0, 0, -9.81) if None).

    height: m, top of the head above the soles (every length scales with it). mass: kg in all.
    drive_stiffness (N m/rad), drive_damping (N m s/rad), max_torque (N m): a number is the value
      for the strongest joints (waist, hips, knees); the others get a share (stiffness and
      damping: ankles 0.8, shoulders 0.3, neck and elbows 0.15, wrists 0.03; torque: ankles 0.75,
      shoulders 0.2, elbows 0.15, neck 0.125, wrists 0.04). A Mapping gives values per joint name
      (joints left out keep their default). None: STIFFNESS, DAMPING and MAX_TORQUE (10000,
      500, 400) scaled by (mass / 70) (height / 1.8): stiff enough to hold the build pose
      standing at dt = 1/60 with SUBSTEPS and ITERATIONS (weaker drives sag and the doll tips
      over slowly: the sweeps have not converged), torques of a strong person (the hips 400,
      the shoulders 80, the wrists 16 N m).
    pos: (x, y) where the feet stand and z the ground height. floor: add a static plane at z =
      pos[2] (contype 1, friction `friction`). self_collision: let the doll's own non-jointed
      bodies touch (91 more contact pairs; see the module docstring).
    contype, conaffinity: the doll's collision bits (MuJoCo's rule); conaffinity None:
      SELF_CONAFFINITY if self_collision else DOLL_CONAFFINITY. Several dolls in one builder that
      touch each other but not themselves: give doll k contype 2 << k and conaffinity 1 | (the
      other dolls' contype bits).
    relaxation: xi of every joint's rows (DBD (46), 0 < xi < 2; `add_ball_joint`). Above 1 the
      sweeps over-relax (SOR, DBD 4.2) and pass the body's weight down to the feet in fewer of
      them: at 4 substeps x 4 iterations with 1.3 the leaning doll holds its ankles as 4 x 8 sweeps
      at 1.0 do, where at 1.0 they sag twice as far and the kicked doll falls
      (`benchmarks/ragdoll_relaxation.py`; README, session 45).
    Returns (builder, Ragdoll). Finalize the builder yourself, e.g. with DT, SUBSTEPS, ITERATIONS.
    """
    builder = ModelBuilder() if builder is None else builder
    _check_size(height, mass, "ragdoll.build")
    origin = np.asarray(pos, dtype=np.float64)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"ragdoll.build: pos must be 3 finite numbers, got {pos!r}")
    scale = height / REFERENCE_HEIGHT
    masses, moments = mass_properties(height, mass)
    drives = _drives(height, mass, drive_stiffness, drive_damping, max_torque)
    if conaffinity is None:
        conaffinity = SELF_CONAFFINITY if self_collision else DOLL_CONAFFINITY
    material = dict(friction=friction, contype=contype, conaffinity=conaffinity)

    def place(point) -> np.ndarray:
        return origin + scale * np.asarray(point, dtype=np.float64)

    bodies, shape_of = {}, {}
    for part in PARTS:
        centre, half, axis = _capsule_axis(part)
        body = builder.add_body(pos=place(centre), mass=masses[part.name], inertia=moments[part.name], name=part.name)
        shape_of[part.name] = builder.add_capsule(body, radius=scale * part.radius, half_length=scale * half,
                                                  quat=host_math.z_to(axis), name=part.name, **material)  # fmt: skip
        bodies[part.name] = body

    joints, kinds, controls, ranges = {}, {}, {}, []
    first = None
    for spec in JOINTS:
        a, b, anchor = bodies[spec.parent], bodies[spec.child], place(spec.anchor)
        if spec.kind == "ball":
            cone, twist = spec.limits
            index = builder.add_ball_joint(a, b, anchor, cone_limit=cone, twist_limits=(-twist, twist),
                                           twist_axis=spec.axis, name=spec.name, relaxation=relaxation)  # fmt: skip
        else:
            index = builder.add_hinge_joint(a, b, anchor, axis=spec.axis, limits=spec.limits, name=spec.name,
                                            relaxation=relaxation)  # fmt: skip
        stiffness, damping, torque = drives[spec.name]
        entries = builder.add_drive(index, stiffness=stiffness, damping=damping, max_torque=torque, name=spec.name)
        first = entries.start if first is None else first
        controls[spec.name] = slice(entries.start - first, entries.stop - first)
        joints[spec.name], kinds[spec.name] = index, spec.kind
        for entry, (low, high) in zip(range(entries.start, entries.stop), _ranges(spec), strict=True):
            builder.set_control_range(entry, low, high)
        ranges += _ranges(spec)
    num_controls = len(ranges)

    floor_shape = None
    if floor:
        floor_shape = builder.add_plane(normal=(0.0, 0.0, 1.0), offset=float(origin[2]), friction=friction,
                                        name="floor")  # fmt: skip
    pelvis = PARTS[0]
    doll = Ragdoll(
        bodies=bodies,
        joints=joints,
        joint_kinds=kinds,
        shapes=shape_of,
        controls=controls,
        control_slice=slice(first, first + num_controls),
        num_controls=num_controls,
        control_low=np.asarray([low for low, _ in ranges]),
        control_high=np.asarray([high for _, high in ranges]),
        rest_height=float(scale * _capsule_axis(pelvis)[0][2]),
        height=float(height),
        mass=float(mass),
        floor=floor_shape,
    )
    return builder, doll


def pose_control(doll: Ragdoll, pose: Mapping[str, Any]) -> np.ndarray:
    """The doll's control block (num_controls,) that drives it to `pose`, clipped to the ranges.

    pose: joint name -> angle (rad, hinge) or rotation vector (3,) (rad, ball joint, in the
    parent's frame at build time = world axes of the standing doll), both from the build pose;
    joints left out hold the build pose (0). Each entry is clipped to [control_low, control_high]
    (a ball joint's swing per axis: the cone limit then bounds what the box leaves over).
    """
    control = np.zeros(doll.num_controls)
    for name, value in pose.items():
        if name not in doll.controls:
            raise ValueError(f"pose_control: unknown joint {name!r}; joints: {tuple(doll.controls)}")
        entries = doll.controls[name]
        array = np.asarray(value, dtype=np.float64).reshape(-1)
        width = entries.stop - entries.start
        if array.shape != (width,):
            what = "a rotation vector (3,)" if width == 3 else "one angle"
            raise ValueError(f"pose_control: {name!r} is a {doll.joint_kinds[name]} joint and takes {what}, "
                             f"got shape {np.shape(value)}")  # fmt: skip
        if not np.all(np.isfinite(array)):
            raise ValueError(f"pose_control: {name!r} has NaN or infinite angles: {array.tolist()}")
        control[entries] = array
    return np.clip(control, doll.control_low, doll.control_high)


def lowest_point(model: Model, state: State) -> jnp.ndarray:
    """Height (m) of the lowest point of every capsule, sphere and box of the model's bodies, (..., S).

    Planes and shapes on the world give +inf. Works on batched states (leading axes)."""
    structure, table = model.structure, model.shapes
    kind = structure.shape_kind.array
    body = structure.shape_body.array
    dynamic = body < structure.num_bodies
    rows = np.where(dynamic, body, 0)
    centre = state.pos[..., rows, :] + dmath.quat_rotate(state.quat[..., rows, :], table.local_pos)
    quat = dmath.quat_multiply(state.quat[..., rows, :], table.local_quat)
    # the world z component of each local axis: row 2 of the rotation matrix
    axes = jnp.stack([dmath.quat_rotate(quat, jnp.broadcast_to(e, quat.shape[:-1] + (3,)))[..., 2]
                      for e in jnp.eye(3, dtype=quat.dtype)], axis=-1)  # fmt: skip
    size = table.size
    capsule = size[:, 0] + size[:, 1] * jnp.abs(axes[..., 2])
    box = jnp.sum(size * jnp.abs(axes), axis=-1)
    sphere = size[:, 0]
    reach = jnp.where(kind == CAPSULE, capsule, jnp.where(kind == BOX, box, sphere))
    dynamic = dynamic & np.isin(kind, (SPHERE, CAPSULE, BOX))
    return jnp.where(dynamic, centre[..., 2] - reach, jnp.inf)


def _numbers(values) -> str:
    return " ".join(repr(round(float(v), 12) + 0.0) for v in np.ravel(values))


def mjcf_xml(
    height: float = REFERENCE_HEIGHT,
    mass: float = REFERENCE_MASS,
    drive_stiffness: float | Mapping[str, float] | None = None,
    drive_damping: float | Mapping[str, float] | None = None,
    max_torque: float | Mapping[str, float] | None = None,
    friction: float = FRICTION,
) -> str:
    """The doll of `build` (with its floor, at the origin) as an MJCF document.

    Bodies keep the world axes as their frames with explicit inertials (so `load_mjcf` finds the
    same centres, masses and principal moments); the pelvis has a free joint. A ball joint is
    written as three hinges through its anchor about x, y, z (MuJoCo has no cone-and-twist ball
    limits): x and y limited to +-cone, z to the twist, which `load_mjcf` merges back into one
    ball joint with that cone and twist. Drives are position actuators (kp, kv, forcerange,
    ctrlrange) on each hinge; the three on a ball joint's hinges become its ball drive.
    `dbdjax/assets/ragdoll.xml` is `mjcf_xml()`.
    """
    _check_size(height, mass, "ragdoll.mjcf_xml")
    scale = height / REFERENCE_HEIGHT
    masses, moments = mass_properties(height, mass)
    drives = _drives(height, mass, drive_stiffness, drive_damping, max_torque)
    centres = {p.name: scale * _capsule_axis(p)[0] for p in PARTS}
    joint_of = {spec.child: spec for spec in JOINTS}
    lines = [
        '<mujoco model="dbdjax ragdoll">',
        "  <!-- written by dbdjax.ragdoll.mjcf_xml(); the doll of dbdjax.ragdoll.build() -->",
        '  <compiler angle="radian" inertiafromgeom="false"/>',
        f'  <option timestep="{_numbers([DT])}" gravity="0 0 -9.81"/>',
        "  <worldbody>",
        f'    <geom name="floor" type="plane" size="0 0 1" friction="{_numbers([friction])} 0.005 0.0001" '
        'contype="1" conaffinity="1"/>',
    ]
    hinges = []  # (joint name, axis name, range, drive) in tree order: the actuators

    def body(part: _Part, depth: int) -> None:
        pad = "  " * depth
        parent = np.zeros(3) if part.parent is None else centres[part.parent]
        centre, half, axis = _capsule_axis(part)
        lines.append(f'{pad}<body name="{part.name}" pos="{_numbers(centres[part.name] - parent)}">')
        if part.parent is None:
            lines.append(f'{pad}  <freejoint name="root"/>')
        else:
            spec = joint_of[part.name]
            at = _numbers(scale * np.asarray(spec.anchor) - centres[part.name])
            axes = (("x", (1, 0, 0)), ("y", (0, 1, 0)), ("z", spec.axis)) if spec.kind == "ball" else (("", spec.axis),)
            for (suffix, direction), (low, high) in zip(axes, _ranges(spec), strict=True):
                name = f"{spec.name}_{suffix}" if suffix else spec.name
                lines.append(f'{pad}  <joint name="{name}" type="hinge" pos="{at}" axis="{_numbers(direction)}" '
                             f'limited="true" range="{_numbers([low, high])}"/>')  # fmt: skip
                hinges.append((name, (low, high), drives[spec.name]))
        lines.append(f'{pad}  <inertial pos="0 0 0" mass="{_numbers([masses[part.name]])}" '
                     f'diaginertia="{_numbers(moments[part.name])}"/>')  # fmt: skip
        # MuJoCo points a fromto capsule's local z from the second end to the first (z = from - to): the
        # first end on +axis gives the frame of `build` (z along +axis), so the two contact slots of a
        # capsule come in the same order and the loaded doll steps as the built one.
        ends = np.concatenate([half * scale * axis, -half * scale * axis])
        lines.append(f'{pad}  <geom name="{part.name}" type="capsule" fromto="{_numbers(ends)}" '
                     f'size="{_numbers([scale * part.radius])}" friction="{_numbers([friction])} 0.005 0.0001" '
                     f'contype="{DOLL_CONTYPE}" conaffinity="{DOLL_CONAFFINITY}"/>')  # fmt: skip
        for child in PARTS:
            if child.parent == part.name:
                body(child, depth + 1)
        lines.append(f"{pad}</body>")

    body(PARTS[0], 2)
    lines += ["  </worldbody>", "  <actuator>"]
    for name, (low, high), (stiffness, damping, torque) in hinges:
        lines.append(f'    <position name="{name}" joint="{name}" kp="{_numbers([stiffness])}" '
                     f'kv="{_numbers([damping])}" forcelimited="true" forcerange="{_numbers([-torque, torque])}" '
                     f'ctrllimited="true" ctrlrange="{_numbers([low, high])}"/>')  # fmt: skip
    lines += ["  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)


def load_mjcf_ragdoll(path: str | Path | None = None, **finalize_kwargs: Any) -> Model:
    """The doll of `build()` (default size, mass and drives, standing at the origin, with its
    floor) from the MJCF file dbdjax/assets/ragdoll.xml (or `path`), loaded with `dbd.load_mjcf`
    (needs `mujoco`). finalize_kwargs go to `finalize` (dt defaults to the file's timestep, 1/60
    s). Joints of the loaded model are named as in the file: a ball joint "waist_x+waist_y+waist_z".
    Its limits are rigid, as `build()`'s (`load_mjcf(..., soft_limits=False)`; pass
    soft_limits=True for MuJoCo's soft ones).
    """
    from dbdjax.mjcf import load_mjcf

    return load_mjcf(ASSET if path is None else path, **{"soft_limits": False, **finalize_kwargs})
