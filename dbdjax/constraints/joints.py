"""Joints: ball, hinge, slider, fixed, planar, universal and gimbal, each one node of the constraint graph.

All rows of one joint (drive, motor, angular lock, angle limits, cone, slider limits, then the
point constraint) are projected together, one after another, in `project` (Gauss-Seidel inside
the joint). One function serves every kind: the rows a kind does not have are inactive (their
multiplier step is zero), so a colour group of mixed kinds is a single `jax.vmap`.

Row by kind:
  ball   point (DBD 5, the vector form (64)-(66): one 3x3 block), cone (DBD (81)-(83)), twist limits,
         drive to a target relative orientation (DBD 9, (110)-(114), three-axis)
  hinge  point, axle alignment (DBD 6, (73)-(80); SI 2.4), angle limits (SI 2.4.5, clamped as
         DBD 6.1), drive to a target angle (DBD 9 about the axle), motor (SI 2.4.6)
  slider point off the axis (SI 2.3.1), rotation lock (SI (53)), travel limits (SI 2.3.5),
         motor (SI 2.3.6)
  fixed  point, rotation lock (SI 2.5)
  planar the point row along the normal only, axle alignment as a hinge's (MJCF slide-slide-hinge)
  universal  point, lock (the angle between hinge axis 1 on a and axis 2 on b held at 90 degrees: the
         axle row of DBD (73)-(80) with that offset), per-hinge angle limits, per-hinge drive
  gimbal point, per-hinge angle limits, per-hinge drive (three successive hinges, no lock)
  The hinge angles of universal and gimbal joints are MuJoCo's successive hinge angles
  (`math.euler_angles`); each limit is a one-sided row on one angle (SI (108), (115), clamped as
  DBD (83)) and each drive a spring row on one angle (DBD 9), along that angle's gradient g_k
  (the dual basis of the hinge axes), so its impulse is a generalised force on that hinge alone.
Every kind: armature (rotor inertia on the joint's coordinates, MuJoCo's armature), one implicit
  spring row per degree of freedom with k h^2 = armature toward the coordinate's inertial
  prediction, less what a torque actuator on it drives (`ModelBuilder.add_armature`). A drive on a
  coordinate with armature (MuJoCo's joint damping beside its armature) steps right after that
  rotor row, as one block with it (`rows.spring_row_beside_rotor`).
Rotors, drives and motors go first so that the hard rows, and the point block last of all, have the
last word.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import integrator, math
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.indexing import segment_sum, take
from dbdjax.model import (
    BALL,
    FIXED,
    GIMBAL,
    HINGE,
    PLANAR,
    SLIDER,
    UNIVERSAL,
    Joints,
    Model,
    State,
    Structure,
    with_world_row,
)

# Multipliers of one joint, in the order of `project`'s rows. The ball drive's torque, the
# rotation lock's and the point block's impulses are 3-vectors: they own slots [DRIVE, DRIVE + 3),
# [ROTATION_LOCK, ROTATION_LOCK + 3) and [POINT, POINT + 3). A universal joint's lock row owns
# ROTATION_LOCK (its three-row block is inactive there). A universal or gimbal joint's hinge k owns
# DRIVE + k, EULER_LOWER + k and EULER_UPPER + k; the rotor of degree of freedom k (a ball's: all
# three) owns ROTOR + k.
DRIVE, MOTOR, ROTATION_LOCK, ANGLE_LOWER, ANGLE_UPPER, CONE = 0, 3, 4, 7, 8, 9
TRAVEL_LOWER, TRAVEL_UPPER, POINT = 10, 11, 12
EULER_LOWER, EULER_UPPER, ROTOR = 15, 18, 21
NUM_MULTIPLIERS = ROTOR + 3


class JointFlags(NamedTuple):
    """Static per-joint switches, (J,) bool each."""

    world_a: np.ndarray
    world_b: np.ndarray
    hinge: np.ndarray
    slider: np.ndarray
    rotation_locked: np.ndarray  # slider and fixed
    has_angle_limits: np.ndarray  # hinge angle or ball twist
    has_cone: np.ndarray
    has_travel_limits: np.ndarray
    hinge_drive: np.ndarray
    ball_drive: np.ndarray
    angular_motor: np.ndarray  # hinge
    linear_motor: np.ndarray  # slider
    planar: np.ndarray  # planar joints (axle row as a hinge, point row along the normal)
    universal: np.ndarray  # universal joints (the lock row, two hinge angles)
    gimbal: np.ndarray  # gimbal joints (three hinge angles)
    euler_limited: np.ndarray  # (J, 3): limits on hinge k of a universal or gimbal joint
    euler_drive: np.ndarray  # a drive or spring on the hinges of a universal or gimbal joint
    rotor_hinge: np.ndarray  # armature on a hinge or on a planar joint's rotation
    rotor_slider: np.ndarray  # armature along a slider
    rotor_ball: np.ndarray  # armature on a ball joint (isotropic)
    rotor_euler: np.ndarray  # (J, 3): armature on hinge k of a universal or gimbal joint
    soft_limits: np.ndarray  # the limit rows are springs past their bounds (`Joints.limit_stiffness`)


class Targets(NamedTuple):
    """What the control vector asks of one joint this step (zero where it has no actuator)."""

    drive: jnp.ndarray  # (3,) hinge: [angle, 0, 0] rad; ball: rotation vector, rad, in a's frame
    motor: jnp.ndarray  # () rad/s (hinge) or m/s (slider)
    torque: jnp.ndarray  # (3,) N m (N) of torque actuators acting through the rotor row of each dof
    rotor: jnp.ndarray  # (3,) q(X*) - (2 q(X^t) - q(X^t-1)) of each dof with armature (`rotor_offsets`)
    # (hinge angle (), slider travel (), gimbal angles (3,)) at X*, the rotor rows' reference, fixed
    # through the sweeps: computed once per substep (`rotor_offsets`); None: in `project`.
    reference: tuple | None = None


def flags(structure: Structure) -> JointFlags:
    """numpy JointFlags for the joints of `structure` (host side, at trace time)."""
    kind = structure.joint_kind.array
    limits = structure.joint_has_limits.array
    drive = structure.joint_drive_control.array[:, 0] < structure.num_controls
    if structure.joint_passive_drive.array.size:  # spring-dampers toward the build pose, no control
        drive = drive | structure.joint_passive_drive.array
    motor = structure.joint_motor_control.array < structure.num_controls
    world = structure.num_bodies
    euler = (kind == UNIVERSAL) | (kind == GIMBAL)
    axis_limited = structure.joint_axis_limited.array
    if axis_limited.shape[0] != len(kind):  # a structure built without per-axis limits
        axis_limited = np.zeros((len(kind), 3), bool)
    rotor = structure.joint_rotor.array
    if rotor.shape[0] != len(kind):  # a structure built without armature
        rotor = np.zeros((len(kind), 3), bool)
    soft = structure.joint_soft_limits.array
    if soft.shape[0] != len(kind):  # a structure built without soft limits
        soft = np.zeros(len(kind), bool)
    return JointFlags(
        world_a=structure.joint_body_a.array == world,
        world_b=structure.joint_body_b.array == world,
        hinge=kind == HINGE,
        slider=kind == SLIDER,
        rotation_locked=(kind == SLIDER) | (kind == FIXED),
        has_angle_limits=limits & ((kind == HINGE) | (kind == BALL)),
        has_cone=structure.joint_has_cone.array & (kind == BALL),
        has_travel_limits=limits & (kind == SLIDER),
        hinge_drive=drive & (kind == HINGE),
        ball_drive=drive & (kind == BALL),
        angular_motor=motor & (kind == HINGE),
        linear_motor=motor & (kind == SLIDER),
        planar=kind == PLANAR,
        universal=kind == UNIVERSAL,
        gimbal=kind == GIMBAL,
        euler_limited=axis_limited & euler[:, None],
        euler_drive=drive & euler,
        rotor_hinge=rotor[:, 0] & ((kind == HINGE) | (kind == PLANAR)),
        rotor_slider=rotor[:, 0] & (kind == SLIDER),
        rotor_ball=rotor[:, 0] & (kind == BALL),
        rotor_euler=rotor & euler[:, None],
        soft_limits=soft,
    )


def targets(
    structure: Structure, control: jnp.ndarray | None, dtype, gear: jnp.ndarray | None = None,
    rotor: jnp.ndarray | None = None, reference: tuple | None = None,
) -> Targets:  # fmt: skip
    """Each joint's slice of the flat control vector, (J, 3) drive and (J,) motor targets, the
    (J, 3) torques gear * u of the torque actuators that act through a rotor row (gear: (T,), the
    torque actuators' `Torques.gear`), and the rotor rows' (J, 3) offsets (`rotor_offsets`; None:
    zero, the rotor then coasts with the bodies' prediction) and their references at X*
    (`rotor_offsets(..., with_reference=True)`; None: each joint's projection computes its own)."""
    padded = padded_control(structure, control, dtype)
    torque = jnp.zeros((structure.num_joints, 3), dtype)
    inside = np.flatnonzero(structure.torque_in_joint.array)
    if inside.size and gear is not None:
        push = take(padded, structure.torque_control.array[inside]) * gear[inside]
        hinge = np.maximum(structure.torque_dof.array[inside], 0)
        entry = 3 * structure.torque_joint.array[inside] + hinge  # in torque (J, 3) read flat
        torque = segment_sum(push, entry, 3 * structure.num_joints).reshape(-1, 3)
    return Targets(
        drive=take(padded, structure.joint_drive_control.array),
        motor=take(padded, structure.joint_motor_control.array),
        torque=torque,
        rotor=jnp.zeros((structure.num_joints, 3), dtype) if rotor is None else rotor,
        reference=reference,
    )


def _coordinates(joint: Joints, flag: JointFlags, pair: BodyPair, kinds: frozenset[str]):
    """The joint's coordinates at the pair's pose: (hinge or planar angle, slider travel, universal /
    gimbal angles (3,), relative rotation from rest (4,)), those of `kinds` only (else zeros)."""
    zero = jnp.zeros((), pair.origin_a.dtype)
    angle = hinge_angle(joint, pair)[0] if "rotor_hinge" in kinds else zero
    travel = slider_travel(joint, flag, pair)[0] if "rotor_slider" in kinds else zero
    euler = _euler_angles(joint, flag, pair, kinds)[0] if "rotor_euler" in kinds else jnp.zeros(3, zero.dtype)
    relative = relative_rotation(joint, *pair.current_quats()) if "rotor_ball" in kinds else jnp.zeros(4, zero.dtype)
    return angle, travel, euler, relative


def joint_coordinates(model: Model, pos: jnp.ndarray, quat: jnp.ndarray):
    """Every joint's coordinates at the bodies' poses pos (N, 3), quat (N, 4): (hinge or planar
    angles (J,), slider travels (J,), universal / gimbal angles (J, 3), relative rotations from
    rest (J, 4)); each joint's only where its kind of joint (`variants`) has that kind of rotor
    (else zeros): each kind is measured with its own rows, so a hinge never computes a gimbal's
    angles."""
    structure = model.structure
    if not structure.num_joints:
        return tuple(jnp.zeros((0, *shape), pos.dtype) for shape in ((), (), (3,), (4,)))
    pos, quat = with_world_row(pos), with_world_row(quat, math.quat_identity().astype(quat.dtype))
    every_flag = flags(structure)

    def measured(members, kinds):
        a, b = structure.joint_body_a.array[members], structure.joint_body_b.array[members]
        zero = jnp.zeros((len(a), 3), pos.dtype)
        scalar, matrix = jnp.zeros((len(a),), pos.dtype), jnp.zeros((len(a), 3, 3), pos.dtype)
        pair = BodyPair(take(pos, a), take(pos, b), take(quat, a), take(quat, b), scalar, scalar, matrix, matrix,
                        *([zero] * 4),
                        jnp.zeros((len(a), 4, 3), pos.dtype))  # fmt: skip
        joint, flag = jax.tree.map(lambda x: x[members], (model.joints, every_flag))
        return jax.vmap(lambda joint, flag, two: _coordinates(joint, flag, two, kinds))(joint, flag, pair)

    return by_kind(variants(structure), measured)


def by_kind(kinds: list[tuple[np.ndarray, frozenset[str]]], compute: Callable):
    """compute(members (K,) int, rows) -> a pytree of arrays with leading axis K, for each
    (members, rows) of `kinds` (`variants`, or any partition of some nodes into kinds); the
    results joined in the nodes' order, one pytree."""
    parts = [compute(members, rows) for members, rows in kinds]
    back = np.argsort(np.concatenate([members for members, _ in kinds]))
    return jax.tree.map(lambda *part: take(jnp.concatenate(part), back), *parts)


def rotor_offsets(model: Model, predicted: State, start: State, h: float, with_reference: bool = False):
    """(J, 3) q(X*) - q_rotor for each degree of freedom with armature: how far the bodies'
    prediction X* carries the joint coordinate q beyond where the rotor's own inertia carries it,
    q_rotor = q^t + (q^t - q^(t-1)) (its discrete velocity is the last substep's, as the bodies'
    is: X^(t-1) = X^t - h V^t exactly in DBD (36)-(39)). Gravity and the other actuators' torques
    move the bodies in X* but not the rotor, and q is curved in X (a hinge angle between two
    turning bodies, a gimbal angle), so taking q(X*) as the rotor's prediction would not do.
    Angles are differenced modulo 2 pi; a ball's entry is the world rotation vector.
    with_reference: also return the coordinates at X* ((J,) hinge angles, (J,) slider travels,
    (J, 3) gimbal angles; `Targets.reference`), which the rotor rows measure from: computed here
    once per substep instead of in every sweep over the joints."""
    structure = model.structure
    a = structure.joint_body_a.array
    before = integrator.displaced_quat(start.quat, -h * start.ang_vel)
    after, now, earlier = (joint_coordinates(model, pos, quat) for pos, quat in (
        (predicted.pos, predicted.quat), (start.pos, start.quat), (start.pos - h * start.vel, before)))  # fmt: skip
    quat_a = take(with_world_row(predicted.quat, math.quat_identity().astype(predicted.quat.dtype)), a)

    def one(flag, after, now, earlier, quat_a):
        (angle, travel, euler, relative) = zip(after, now, earlier, strict=True)
        wrapped = math.wrap_angle
        hinge = wrapped(angle[0] - angle[1]) - wrapped(angle[1] - angle[2])
        slide = (travel[0] - travel[1]) - (travel[1] - travel[2])
        gimbal = wrapped(euler[0] - euler[1]) - wrapped(euler[1] - euler[2])

        # A ball's rotor keeps its rate in b's frame, as MuJoCo's armature on a ball's local qvel
        # (the rate relative to a, in the child's frame): the change of X's right turns X^-1 X'
        # (in b's rest frame) over the two substeps, as a world vector in b's rest frame at the
        # step's start with a at X*. Kept in the world frame instead (left turns X' X^-1 rotated
        # by a), a free base's rotation changed the rotor's rate: a light leg on a ball (armature
        # 1, free base turning at 0.6 rad/s) ended 0.08 rad/s from MuJoCo's in 0.1 s at any dt.
        def right_turn(later, sooner):
            return math.quat_log(math.quat_multiply(math.quat_conjugate(sooner), later))

        frame = math.quat_multiply(quat_a, relative[1])
        ball = math.quat_rotate(frame, right_turn(relative[0], relative[1]) - right_turn(relative[1], relative[2]))
        first = jnp.where(flag.rotor_hinge, hinge, jnp.where(flag.rotor_slider, slide, 0.0))
        single = jnp.stack([first, jnp.zeros_like(first), jnp.zeros_like(first)])
        offset = jnp.where(flag.rotor_ball, ball, jnp.where(flag.rotor_euler, gimbal, single))
        return offset

    offsets = jax.vmap(one)(flags(structure), after, now, earlier, quat_a)
    return (offsets, after[:3]) if with_reference else offsets


def rotor_energy(model: Model, state: State) -> jnp.ndarray:
    """() J: the kinetic energy of the joints' rotors, 1/2 armature qdot^2 summed over every degree
    of freedom with armature (MuJoCo's joint-space term), qdot the rate of its coordinate that the
    bodies' velocities give (the derivative of `joint_coordinates` along them; a ball's rotor: its
    relative angular velocity). 0 for a model without armature."""
    structure = model.structure
    flag = flags(structure)
    if not (flag.rotor_hinge.any() or flag.rotor_slider.any() or flag.rotor_euler.any() or flag.rotor_ball.any()):
        return jnp.zeros((), state.pos.dtype)
    spin = jnp.concatenate([jnp.zeros_like(state.ang_vel[:, :1]), state.ang_vel], axis=-1)
    turning = 0.5 * math.quat_multiply(spin, state.quat)  # dq/dt of each body's orientation
    _, (angle, travel, euler, _) = jax.jvp(lambda pos, quat: joint_coordinates(model, pos, quat),
                                           (state.pos, state.quat), (state.vel, turning))  # fmt: skip
    ang_vel = with_world_row(state.ang_vel)
    relative = ang_vel[structure.joint_body_b.array] - ang_vel[structure.joint_body_a.array]
    armature = model.joints.armature
    energy = (jnp.where(flag.rotor_hinge, armature[:, 0] * angle**2, 0.0)
              + jnp.where(flag.rotor_slider, armature[:, 0] * travel**2, 0.0)
              + jnp.sum(jnp.where(flag.rotor_euler, armature * euler**2, 0.0), axis=-1)
              + jnp.where(flag.rotor_ball, armature[:, 0] * math.dot(relative, relative), 0.0))  # fmt: skip
    return 0.5 * jnp.sum(energy)


def rotor_inertia(model: Model, state: State, on_body_a: bool = True) -> jnp.ndarray:
    """(N, 3, 3) kg m^2, world frame: the joints' rotors' inertia as each body sees it with the
    other body of its joint held, armature d d^T per rotating degree of freedom (d = dq/dtheta: a
    hinge's axis, a universal / gimbal hinge's angle gradient, any direction for a ball) on both
    bodies (on_body_a False: on body b alone, the child of an MJCF joint). For the restitution
    pass, which moves the bodies of its contacts alone: without it a foot's spin about its knee is
    as cheap as its own inertia makes it, and the rotor, whose rate the bodies' velocities carry,
    takes that spin at no cost (`contacts.project_restitution`). Sliders' rotors are left out
    (their inertia is a mass along the axis)."""
    structure = model.structure
    flag = flags(structure)
    n = structure.num_bodies
    a, b = structure.joint_body_a.array, structure.joint_body_b.array
    quat = with_world_row(state.quat, math.quat_identity().astype(state.quat.dtype))
    quat_a, quat_b = take(quat, a), take(quat, b)
    armature = model.joints.armature
    axis = math.quat_rotate(quat_b, model.joints.local_axis_b)  # (J, 3)
    hinge = armature[:, 0, None, None] * axis[:, :, None] * axis[:, None, :]
    added = jnp.where(flag.rotor_hinge[:, None, None], hinge, 0.0)
    eye = jnp.eye(3, dtype=state.quat.dtype)
    added = added + jnp.where(flag.rotor_ball[:, None, None], armature[:, 0, None, None] * eye, 0.0)
    if flag.rotor_euler.any():
        axes_a = math.quat_rotate(quat_a[:, None], model.joints.local_axes_a)
        axes_b = math.quat_rotate(quat_b[:, None], model.joints.local_axes_b)
        _, gradients = math.euler_angles(axes_a, axes_b, flag.universal)  # (J, 3, 3): row k = dq_k/dtheta_b
        euler = jnp.where(flag.rotor_euler, armature, 0.0)
        added = added + jnp.einsum("jk,jki,jkl->jil", euler, gradients, gradients)
    if on_body_a:
        return segment_sum(jnp.concatenate([added, added]), np.concatenate([b, a]), n + 1)[:n]
    return segment_sum(added, b, n + 1)[:n]


def padded_control(structure: Structure, control: jnp.ndarray | None, dtype) -> jnp.ndarray:
    """(num_controls + 1,) the control vector (zeros for None) and a last entry 0: the index
    num_controls in the model's control tables reads as "no actuator"."""
    padded = jnp.zeros((structure.num_controls + 1,), dtype)
    return padded if control is None else jnp.concatenate([jnp.asarray(control, dtype), padded[-1:]])


def rows_in_use(structure: Structure) -> frozenset[str]:
    """The kinds of row some joint of the model has (the names of `JointFlags`, plus "point").
    The others are left out of the trace altogether: a chain of ball joints compiles to the point
    block alone."""
    f = flags(structure)
    return _rows_of(f, np.ones(len(f.hinge), bool))


def variants(structure: Structure) -> list[tuple[np.ndarray, frozenset[str]]]:
    """The joints grouped by kind (universal and gimbal together: the same hinge-angle rows), each
    group with the rows some member has (`Family.variants`). The solver projects each group with
    its own trace, so a knee does not evaluate a hip's three hinge angles nor a hip a knee's axle
    lock (Brax's humanoid, 4 iterations, CPU: a step at batch 16 took 6.0 ms instead of 11.2 ms,
    benchmarks/profile_step.py)."""
    f = flags(structure)
    kind = structure.joint_kind.array
    group = np.where(kind == GIMBAL, UNIVERSAL, kind)
    return [(np.flatnonzero(group == g), _rows_of(f, group == g)) for g in np.unique(group)]


def _rows_of(f: JointFlags, members: np.ndarray) -> frozenset[str]:
    """The row names some joint of `members` (bool (J,)) has, as `rows_in_use`."""
    used = {name for name, values in f._asdict().items() if np.any(values[members])}
    if np.any((f.hinge | f.rotation_locked | f.planar)[members]):
        used.add("rotation_lock")
    return frozenset(used | {"point"})


def joint_points(joint: Joints, flag: JointFlags, pair: BodyPair, quat_a, quat_b):
    """The joint point on each body: (delta = p_a - p_b, arm_a, arm_b) at X* + dX, for one joint
    (no J axis) whose bodies have the orientations quat_a, quat_b."""
    return row.anchor_points(pair, joint.local_anchor_a, joint.local_anchor_b, flag.world_a, flag.world_b,
                             quat_a, quat_b)  # fmt: skip


def relative_rotation(joint: Joints, quat_a, quat_b):
    """X with q_b = q_a X rest: the rotation of b away from its rest pose, in a's frame."""
    relative = math.quat_multiply(math.quat_conjugate(quat_a), quat_b)
    return math.quat_multiply(relative, math.quat_conjugate(joint.rest_rotation))


def hinge_angle(joint: Joints, pair: BodyPair):
    """(angle of b about the axle from its rest pose (rad), world axle = dangle/dtheta_b)."""
    quat_a, quat_b = pair.current_quats()
    angle = math.quat_twist_angle(relative_rotation(joint, quat_a, quat_b), joint.local_axis_a)
    # The bisector of the two bodies' axes (equal for a hinge, close for a ball's twist axis).
    axis_a, axis_b = row.rotate_pair(quat_a, quat_b, joint.local_axis_a, joint.local_axis_b)
    axis, _ = math.safe_normalize(axis_a + axis_b)
    return angle, axis


def _euler_angles(joint: Joints, flag: JointFlags, pair: BodyPair, rows: frozenset[str]):
    """(hinge angles (3,) rad, their gradients g_k (3, 3) w.r.t. a world rotation of b) of a
    universal or gimbal joint at X* + dX, `math.euler_angles` (one kind traced when the model
    has only one: `rows`)."""
    quat_a, quat_b = pair.current_quats()
    axes_a, axes_b = row.rotate_pair(quat_a[None], quat_b[None], joint.local_axes_a, joint.local_axes_b)
    universal = flag.universal if {"universal", "gimbal"} <= rows else "universal" in rows
    return math.euler_angles(axes_a, axes_b, universal)


def _carried(measured: jnp.ndarray, gradients: jnp.ndarray, pair: BodyPair) -> Callable[[BodyPair], jnp.ndarray]:
    """Angles (...,) rad measured at `pair`, with their gradients (..., 3) w.r.t. a world turn of b
    against a, as a function of the pair as later rows move it: carried to first order,
    t + g . (the turn since), g fixed for one projection of the joint (`project`)."""
    turn = pair.dtheta_b - pair.dtheta_a
    return lambda moved: measured + math.dot(gradients, (moved.dtheta_b - moved.dtheta_a) - turn)


def _unmoved(pair: BodyPair) -> BodyPair:
    """The pair at the prediction X* (nothing moved yet this substep): the rotor rows' reference."""
    return pair._replace(motion=jnp.zeros_like(pair.motion))


def rotor_error(joint: Joints, target: Targets, k: int, change, h: float):
    """The rotor row of degree of freedom k: q(X* + dX) - q_rotor - h^2 tau / armature, from
    change = q(X* + dX) - q(X*) (angles wrapped); `project`'s armature comment says why."""
    armature = jnp.where(joint.armature[k] > 0.0, joint.armature[k], 1.0)
    return change + target.rotor[k] - h**2 * target.torque[k] / armature


def _hinge_rotor_reference(joint: Joints, target: Targets, pair: BodyPair):
    """The hinge angle (rad) a hinge's rotor row measures its change from: at X*, or the
    substep's reference (`Targets.reference`) where the caller gave one."""
    return hinge_angle(joint, _unmoved(pair))[0] if target.reference is None else target.reference[0]


def rotor_rows(joint: Joints, flag: JointFlags, target: Targets, pair: BodyPair, kind: str, h: float,
               rows: frozenset[str] = frozenset({"universal", "gimbal"})):  # fmt: skip
    """All rotor rows of one joint at the pair's configuration: (errors (3,), directions (3, 3)),
    row k's error (`rotor_error`) and d_k = dq_k / dtheta_b, the row's Jacobian (-d_k on a's
    rotation, d_k on b's); zero rows where a kind has fewer degrees of freedom. kind: "rotor_hinge",
    "rotor_euler" (rows: which of universal / gimbal to trace, as `_euler_angles`) or "rotor_ball"."""
    still = _unmoved(pair)
    if kind == "rotor_hinge":
        reference = _hinge_rotor_reference(joint, target, pair)
        angle, axis = hinge_angle(joint, pair)
        error = rotor_error(joint, target, 0, math.wrap_angle(angle - reference), h)
        zero = jnp.zeros((2, 3), axis.dtype)
        return jnp.concatenate([error[None], zero[:, 0]]), jnp.concatenate([axis[None], zero])
    if kind == "rotor_euler":
        reference = _euler_angles(joint, flag, still, rows)[0] if target.reference is None else target.reference[2]
        angles, directions = _euler_angles(joint, flag, pair, rows)
        change = math.wrap_angle(angles - reference)
        return jnp.stack([rotor_error(joint, target, k, change[k], h) for k in range(3)]), directions
    quat_a, quat_b = pair.current_quats()
    predicted = relative_rotation(joint, still.quat_a, still.quat_b)
    change = math.quat_multiply(relative_rotation(joint, quat_a, quat_b), math.quat_conjugate(predicted))
    error = math.quat_rotate(quat_a, math.quat_log(change)) + target.rotor  # (ball torques are refused)
    return error, jnp.eye(3, dtype=error.dtype)


def slider_rotor_row(joint: Joints, flag: JointFlags, target: Targets, pair: BodyPair, h: float):
    """A slider's rotor row at the pair's configuration: (error (`rotor_error`), world axis, arm_a,
    arm_b), the travel measured from its value at X* (`slider_travel`)."""
    reference = slider_travel(joint, flag, _unmoved(pair))[0] if target.reference is None else target.reference[1]
    travel, axis, arm_a, arm_b = slider_travel(joint, flag, pair)
    return rotor_error(joint, target, 0, travel - reference, h), axis, arm_a, arm_b


def rotor_excess(joint: Joints, flag: JointFlags, target: Targets, bodies: BodySet, multipliers: jnp.ndarray,
                 h: float, rows: frozenset[str]) -> jnp.ndarray:  # fmt: skip
    """(3,) how far the sweeps left each rotor coordinate of one joint past where its rotor's own
    momentum carries it: r = c + lambda / armature at X* + dX (rad, m; a ball's: a world rotation
    vector), c the rotor row's error (`rotor_error`) and lambda its multiplier. The rotor row is a
    spring with k h^2 = armature (`project`), so r is its residual per unit armature: 0 where the
    sweeps converged. r / h is spin the bodies' motion gives the rotor with no impulse behind it
    (`project_rotor_momentum` takes it back). 0 for the degrees of freedom without armature.
    bodies: the joint's two bodies with the solve's displacements; multipliers: (NUM_MULTIPLIERS,)."""
    pair = BodyPair.of(bodies)
    armature = jnp.where(flag.rotor_ball, joint.armature[0], joint.armature)  # (3,) per degree of freedom
    per_armature = multipliers[ROTOR : ROTOR + 3] / jnp.where(armature > 0.0, armature, 1.0)
    first = jnp.arange(3) == 0
    excess = jnp.zeros(3, pair.dx_a.dtype)
    for kind, active in (("rotor_hinge", flag.rotor_hinge & first), ("rotor_euler", flag.rotor_euler),
                         ("rotor_ball", flag.rotor_ball)):  # fmt: skip
        if kind in rows:
            error, _ = rotor_rows(joint, flag, target, pair, kind, h, rows)
            excess = jnp.where(active, error + per_armature, excess)
    if "rotor_slider" in rows:
        error = slider_rotor_row(joint, flag, target, pair, h)[0]
        excess = jnp.where(flag.rotor_slider & first, error + per_armature, excess)
    return excess


def project_rotor_momentum(joint: Joints, flag: JointFlags, excess: jnp.ndarray, bodies: BodySet,
                           multipliers: jnp.ndarray, h: float, rows: frozenset[str]):  # fmt: skip
    """The rotor pass of one joint, after the position solve. The rotor has no state of its own:
    its rate is the rate qdot of its coordinate that the bodies' velocities give. Where the sweeps
    left its row unconverged (`rotor_excess` r), the rotor's momentum says qdot - r / h; rotor and
    bodies (effective inertia 1 / w along the coordinate, w the row's held response) meet at
    their momentum-weighted rate, qdot - s r / h with s = armature w / (1 + armature w) (an
    inelastic merge; s = 1 for a rotor far heavier than its bodies, about armature w for a light
    one, where the bodies' rate stands). That rate is taken only toward zero, into [0, qdot]: the
    pass takes spin back and never gives any (a ball's relative angular velocity w: to the point
    of the segment [0, w] nearest the merged one).

    Why: a rotor of armature far above its bodies' inertia (Brax's ant: 1 kg m^2, 40-120x its
    legs') is a stiff row between light bodies, and Gauss-Seidel sweeps leave what it shares with
    a contact or a limit unconverged; the light bodies then carry a rate the rotor's impulse does
    not account for, and the rotor's energy 1/2 armature qdot^2 takes it: the ant dropped with
    zero control had 106 J in its rotors at landing (from 6.7 J), the exact solve (tree_solve)
    0.66 J. Taken back whole (not only toward zero), the rotors kept spin a limit had stopped
    in positions, and under random controls they ran away. The joint's point is held (its
    relative velocity kept) as the rotor rows hold it.

    bodies: the velocity view (vel/ang_vel after the solve, dx/dtheta this pass's changes so far;
    poses at the end of the solve). excess: (3,) `rotor_excess`. Returns (dv (2, 3), dw (2, 3),
    multipliers (3,))."""
    pair = BodyPair.of(bodies)
    still = _unmoved(pair)  # the pose; dx/dtheta are velocity changes here
    quat_a, quat_b = still.current_quats()
    gap, arm_a, arm_b = joint_points(joint, flag, still, quat_a, quat_b)
    hold = row.point_hold(pair, arm_a, arm_b, jnp.zeros_like(gap), ~(flag.slider | flag.planar))
    armature = jnp.where(flag.rotor_ball, joint.armature[0], joint.armature)  # (3,) per degree of freedom
    lam = [multipliers[k] for k in range(3)]
    rigid = lambda active: row.rigid(1.0, 0.0, active)  # noqa: E731
    spin = pair.ang_vel_b - pair.ang_vel_a

    def merged(rate, k, response):  # the rotor's and the bodies' momentum-weighted rate
        share = armature[k] * response / (1.0 + armature[k] * response)
        return rate - share * excess[k] / h

    def toward_zero(rate, wanted):  # the change that takes rate to the point of [0, rate] nearest wanted
        return jnp.clip(wanted, jnp.minimum(rate, 0.0), jnp.maximum(rate, 0.0)) - rate

    def held_response(direction):
        return row.held_inverse_mass(*row.row_inverse_mass(pair, direction, direction), hold)[0]

    def angular(pair, hold, direction, change, k, active):
        now = math.dot(direction, pair.dtheta_b - pair.dtheta_a)
        pair, lam[k], hold = row.angular_row(pair, -direction, now - change, lam[k], rigid(active), 1.0, hold,
                                             held_step=True)  # fmt: skip
        return pair, hold

    if "rotor_hinge" in rows:
        axis = hinge_angle(joint, still)[1]
        rate = math.dot(axis, spin)
        change = toward_zero(rate, merged(rate, 0, held_response(axis)))
        pair, hold = angular(pair, hold, axis, change, 0, flag.rotor_hinge)
    if "rotor_euler" in rows:
        gradients = _euler_angles(joint, flag, still, rows)[1]
        for k in range(3):
            rate = math.dot(gradients[k], spin)
            change = toward_zero(rate, merged(rate, k, held_response(gradients[k])))
            pair, hold = angular(pair, hold, gradients[k], change, k, flag.rotor_euler[k])
    if "rotor_ball" in rows:
        axes = jnp.eye(3, dtype=spin.dtype)
        wanted = jnp.stack([merged(spin[k], k, held_response(axes[k])) for k in range(3)])
        share = jnp.clip(math.dot(wanted, spin) / jnp.maximum(math.dot(spin, spin), 1e-30), 0.0, 1.0)
        for k in range(3):
            pair, hold = angular(pair, hold, axes[k], (share - 1.0) * spin[k], k, flag.rotor_ball)
    if "rotor_slider" in rows:
        _, axis, arm_a, arm_b = slider_travel(joint, flag, still)
        rate = math.dot(axis, row.relative_point_motion(still, arm_a, arm_b, 1.0))  # the velocities alone
        now = math.dot(axis, row.relative_point_motion(pair, arm_a, arm_b, 0.0))  # this pass's changes
        response = row.row_inverse_mass(pair, math.cross(arm_a, axis), math.cross(arm_b, axis), 1.0)[0]
        change = toward_zero(rate, merged(rate, 0, response))
        pair, lam[0] = row.positional_row(pair, -axis, arm_a, arm_b, now - change, lam[0], rigid(flag.rotor_slider))
    return *pair.displacements(), jnp.stack(lam)


def axle_misalignment(joint: Joints, quat_a, quat_b):
    """(c = axis_b x axis_a (3,), the unit bisector of the two axes (3,)): a hinge's axle alignment
    error (DBD 6 (73)-(80), SI 2.4.1; |c| = sin of (73)'s angle), locked across the bisector."""
    axis_a, axis_b = row.rotate_pair(quat_a, quat_b, joint.local_axis_a, joint.local_axis_b)
    return math.cross(axis_b, axis_a), math.safe_normalize(axis_a + axis_b)[0]


def rotation_lock_error(joint: Joints, quat_a, quat_b):
    """(3,) minus the world rotation vector of X: a slider's or fixed joint's whole-rotation lock
    error (SI (53)), with dc/dtheta_a = 1."""
    return -math.quat_rotate(quat_a, math.quat_log(relative_rotation(joint, quat_a, quat_b)))


def universal_lock(joint: Joints, quat_a, quat_b):
    """(c = m1_a . m2_b, dc/dtheta_a = m1_a x m2_b): the universal joint's lock row (`project`)."""
    axis_1, axis_2 = row.rotate_pair(quat_a, quat_b, joint.local_axes_a[0], joint.local_axes_b[1])
    return math.dot(axis_1, axis_2), math.cross(axis_1, axis_2)


def lock_rows(joint: Joints, flag: JointFlags, pair: BodyPair, kind: str):
    """The rotation lock of one joint at the pair's configuration, as the tree's direct solve takes
    it: (errors (3,), directions (3, 3), basis (3, 3)). Row k has J = (0, d_k) on b and (0, -d_k) on
    a, error c_k, and multiplier mu_k = basis_k . L, L the lock's multipliers (ROTATION_LOCK, 3);
    a step d mu adds basis^T d mu to L. Rows of zeros where a kind has fewer. kind: "hinge" (the
    axle alignment across the bisector, two rows, as `project`'s block), "universal" (its one
    lock row on m1_a . m2_b) or "fixed" (the whole relative rotation, three rows)."""
    quat_a, quat_b = pair.current_quats()
    dtype = quat_a.dtype
    if kind == "universal":
        error, direction_a = universal_lock(joint, quat_a, quat_b)
        zero = jnp.zeros((2, 3), dtype)
        first = jnp.eye(3, dtype=dtype)[:1]
        errors = jnp.concatenate([error[None], zero[:, 0]])
        return errors, jnp.concatenate([-direction_a[None], zero]), jnp.concatenate([first, zero])
    if kind == "fixed":
        basis = jnp.eye(3, dtype=dtype)
        return rotation_lock_error(joint, quat_a, quat_b), -basis, basis
    misalignment, bisector = axle_misalignment(joint, quat_a, quat_b)
    first = math.any_perpendicular(bisector)
    basis = jnp.stack([first, math.cross(bisector, first), jnp.zeros(3, dtype)])
    return math.matvec(basis, misalignment), -basis, basis


class LimitRows(NamedTuple):
    """A joint's angle limit rows as the tree's direct solve takes them (`limit_rows`): per degree
    of freedom k, the nearer bound's row oriented along d_k = dq_k / dtheta_b (J = (0, d_k) on b,
    (0, -d_k) on a), in the compliance form of DBD (49): (J M~^-1 J^T + alpha) d mu = -(r + alpha mu)."""

    directions: jnp.ndarray  # (3, 3) d_k
    residual: jnp.ndarray  # (3,) r: the error q_k - bound (rigid), or the spring's (K c + D drift) / (K + D)
    compliance: jnp.ndarray  # (3,) alpha: the regularisation (rigid), or 1 / (K + D) (soft)
    upper: jnp.ndarray  # (3,) bool: the upper bound's row (its multiplier is -mu), else the lower's (+mu)
    active: jnp.ndarray  # (3,) bool: past its bound (the rows push only there)


def limit_rows(joint: Joints, flag: JointFlags, pair: BodyPair, kind: str, h: float,
               rows: frozenset[str] = frozenset({"universal", "gimbal"})) -> LimitRows:  # fmt: skip
    """The angle limits of one joint at the pair's configuration, all its degrees of freedom at
    once. kind: "has_angle_limits" (a hinge's angle: row 0) or "euler_limited" (a universal or
    gimbal joint's hinge angles; rows: which kind to trace, as `_euler_angles`).

    The same rows `project` steps one at a time: where the joint's limits are soft (the tree takes
    only those) a spring K = k h^2 (1 / w + armature) and damper D = nu h (1 / w + armature) per
    unit of the row's effective mass, w the row's response with the joint point held
    (`rows.soft_limit`); rigid, alpha the regularisation, where not (or where w = 0)."""
    if kind == "has_angle_limits":
        angle, axis = hinge_angle(joint, pair)
        zero = jnp.zeros((), angle.dtype)
        angles = jnp.stack([angle, zero, zero])
        directions = jnp.concatenate([axis[None], jnp.zeros((2, 3), axis.dtype)])
        lower, upper = jnp.stack([joint.lower, zero, zero]), jnp.stack([joint.upper, zero, zero])
        limited = jnp.stack([flag.has_angle_limits & flag.hinge, False, False])
    else:
        angles, directions = _euler_angles(joint, flag, pair, rows)
        lower, upper, limited = joint.axis_lower, joint.axis_upper, flag.euler_limited
    _, error, upper_row = _nearer_bound(angles, lower, upper, periodic=True)
    active = limited & (error < 0.0)
    error = jnp.where(upper_row, -error, error)  # q_k - bound: the row's error along d_k
    # The response along d_k with the joint's point held, as the sweep's soft limit rows step.
    inverse_mass, turn_a, turn_b = row.row_inverse_mass(pair, directions, directions)
    gap, arm_a, arm_b = joint_points(joint, flag, pair, *pair.current_quats())
    hold = row.point_hold(pair, arm_a, arm_b, gap, ~(flag.slider | flag.planar))
    impulse, opened = row.point_impulses(hold, turn_a, turn_b)
    held = jnp.maximum(inverse_mass + math.dot(opened, impulse), 0.0)
    # K = k' / w with k' the sweeps' spring per unit effective mass (`rows.soft_limit_scale`).
    per_mass = row.soft_limit_scale(joint.armature, held) / jnp.where(held > 0.0, held, 1.0)
    stiffness, damping = joint.limit_stiffness * h**2 * per_mass, joint.limit_damping * h * per_mass
    residual, compliance, _ = row.spring_compliance(
        stiffness, damping, error, math.matvec(directions, row.relative_turn(pair, h))
    )
    soft = flag.soft_limits & (held > 0.0)
    residual = jnp.where(soft, residual, error)
    compliance = jnp.where(soft, compliance, joint.regularization)
    return LimitRows(directions, residual, compliance, upper_row, active)


def ball_drive_error(joint: Joints, target: Targets, quat_a, quat_b):
    """(3,) rad: the world rotation vector of E = X T^-1 (X the relative rotation from rest, T =
    exp(target) in a's frame), a ball drive's error with dc/dtheta_b = 1 (DBD 9)."""
    goal = math.quat_exp(target.drive)
    error_rotation = math.quat_multiply(relative_rotation(joint, quat_a, quat_b), math.quat_conjugate(goal))
    return math.quat_rotate(quat_a, math.quat_log(error_rotation))


class DriveRows(NamedTuple):
    """A joint's drive rows as the tree's direct solve takes them (`drive_rows`): per degree of
    freedom k, a spring row along d_k (J = (0, d_k) on b, (0, -d_k) on a) in the compliance form of
    DBD (49): (J M~^-1 J^T + alpha) d kappa = -(r + alpha kappa), with K = k h^2, D = nu h,
    r = (K c + D drift) / (K + D) and alpha = 1 / (K + D) (the spring rule of DBD 9, (112))."""

    directions: jnp.ndarray  # (3, 3) d_k
    residual: jnp.ndarray  # (3,) r
    compliance: jnp.ndarray  # (3,) alpha
    active: jnp.ndarray  # (3,) bool: a spring on that row (K + D > 0)


def drive_rows(joint: Joints, flag: JointFlags, target: Targets, pair: BodyPair, kind: str, h: float,
               rows: frozenset[str] = frozenset({"universal", "gimbal"})) -> DriveRows:  # fmt: skip
    """The drive of one joint at the pair's configuration, all its degrees of freedom at once, as
    `project` steps them one at a time (its torque limit is not in these rows: the caller leaves a
    saturated drive out). kind: "hinge_drive" (row 0), "euler_drive" (a universal or gimbal joint's
    hinge angles; rows: which kind to trace, as `_euler_angles`) or "ball_drive" (three rows)."""
    dtype = pair.quat_a.dtype
    zero = jnp.zeros((), dtype)
    if kind == "hinge_drive":
        angle, axis = hinge_angle(joint, pair)
        errors = jnp.stack([math.wrap_angle(angle - target.drive[0]), zero, zero])
        directions = jnp.concatenate([axis[None], jnp.zeros((2, 3), dtype)])
        stiffness = jnp.stack([joint.drive_stiffness, zero, zero])
        damping = jnp.stack([joint.drive_damping, zero, zero])
    elif kind == "euler_drive":
        angles, directions = _euler_angles(joint, flag, pair, rows)
        errors = math.wrap_angle(angles - target.drive)
        stiffness, damping = joint.axis_stiffness, joint.axis_damping
    else:
        errors = ball_drive_error(joint, target, *pair.current_quats())
        directions = jnp.eye(3, dtype=dtype)
        stiffness = jnp.broadcast_to(joint.drive_stiffness, (3,))
        damping = jnp.broadcast_to(joint.drive_damping, (3,))
    drift = math.matvec(directions, row.relative_turn(pair, h))
    return DriveRows(directions, *row.spring_compliance(stiffness * h**2, damping * h, errors, drift))


def slider_travel(joint: Joints, flag: JointFlags, pair: BodyPair):
    """(travel d = (p_b - p_a) . axis, world axis, arm_a, arm_b) of a slider, SI (65)-(78).

    Body a's arm reaches the point of a level with p_b, so an impulse along the axis acts on the
    line through both points."""
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = joint_points(joint, flag, pair, quat_a, quat_b)
    axis = math.quat_rotate(quat_a, joint.local_axis_a)
    travel = -math.dot(delta, axis)
    across = delta + travel[..., None] * axis
    return travel, axis, arm_a - across, arm_b


def project(
    joint: Joints,
    flag: JointFlags,
    target: Targets,
    bodies: BodySet,
    multipliers: jnp.ndarray,
    h: float,
    rows: frozenset[str],
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Project every row of one joint once; `joint` holds one joint's parameters (no J axis).

    bodies: the two bodies (row 0 = a, row 1 = b). multipliers: (NUM_MULTIPLIERS,) lambda of each
    row so far this substep. h: the substep (s). rows: the rows to trace (static, `rows_in_use`).
    Returns (dx (2, 3), dtheta (2, 3), multipliers).
    """
    pair = BodyPair.of(bodies)
    xi, alpha = joint.relaxation, joint.regularization
    lam = [multipliers[k] for k in range(NUM_MULTIPLIERS)]
    untouched = list(lam)
    # The angular rows move the pair with the joint point held (rows.PointHold): where the point
    # block is a full 3-D one, at the points of the start of this sweep.
    hold_gap, hold_arm_a, hold_arm_b = joint_points(joint, flag, pair, *pair.current_quats())
    hold = row.point_hold(pair, hold_arm_a, hold_arm_b, hold_gap, ~(flag.slider | flag.planar))
    hard = lambda active, inequality=False: row.rigid(xi, alpha, active, inequality)  # noqa: E731
    # Limits: rigid rows, or where the joint's limits are soft (`Joints.limit_stiffness`) a spring and
    # damper per unit of the row's effective mass, stepped with the response with the point held
    # (the joint coordinate's own effective mass, not the turn of one body about its centre).
    if "soft_limits" in rows:
        soft = (flag.soft_limits, joint.limit_stiffness * h**2, joint.limit_damping * h)
        limit_rule = lambda active, armature: row.soft_limit(xi, alpha, active, *soft, armature)  # noqa: E731
        limit_held = flag.soft_limits
    else:
        limit_rule, limit_held = lambda active, armature: hard(active, inequality=True), False  # noqa: E731

    # Armature: MuJoCo's 1/2 armature qdot^2 on the joint coordinate q, in the step's variational
    # form 1/2 armature (q(X* + dX) - q_rotor)^2 / h^2, q_rotor where the rotor's own inertia
    # carries q (`rotor_offsets`): a spring row with k h^2 = armature (DBD 8.1) per degree of
    # freedom. A torque actuator on that coordinate acts here (targets.torque): h^2 tau / armature
    # shifts the rotor's target, so the torque moves bodies and rotor together. Angles are
    # differenced modulo 2 pi. The rotor rows step with the held response (the Schur complement,
    # `held_step`): how far a step goes sets how the correction is shared between the rotor and
    # the bodies, and with w about the body's centre a light pendulum's rotor took a step 80x too
    # short (armature 0.5 on a 1 kg bob 1 m out: period 2.04 s at 8 iterations, 2.21 s at 64,
    # against 2.46 s). The held step also counts the point's open gap (`rows.angular_row`): without
    # it Brax's ant (armature 40-120x its joints' inertia) gained energy at 4 substeps.
    # A universal or gimbal joint's hinge angles t_k are measured once per projection and carried
    # to first order through its rows: a row turns b against a by dtheta_b - dtheta_a, which moves
    # t_k by g_k . (that turn), and g_k stays the one measured here (the rows' Jacobians, fixed
    # for one projection of the joint). Measuring them again before each of the up to nine rows
    # that read them was a third of the humanoid's compiled joint sweep.
    # The rows along one g_k (its rotor, drive and limit) share its response (`rows.AngularResponse`),
    # computed for the three at once.
    if {"rotor_euler", "euler_drive", "euler_limited"} & rows:
        measured_angles, euler_directions = _euler_angles(joint, flag, pair, rows)
        euler_angles_now = _carried(measured_angles, euler_directions, pair)  # (3,) rad: t_k as rows move the pair
        euler_responses = row.angular_response(pair, euler_directions, hold)

        def euler_response(k, sign):  # the response along sign * g_k
            return jax.tree.map(lambda x: x[k], euler_responses).times(sign)

    # A hinge's angle about its axle (a ball's twist) likewise, for its rotor, drive, motor and
    # limit rows: measured once, carried to first order along the axle, which they share.
    if {"rotor_hinge", "hinge_drive", "angular_motor", "has_angle_limits"} & rows:
        measured_angle, hinge_axis = hinge_angle(joint, pair)
        hinge_angle_now = _carried(measured_angle, hinge_axis, pair)  # rad: the angle as rows move the pair
        hinge_response = row.angular_response(pair, hinge_axis, hold)

    def rotor_rule(k, active):  # a spring row with k h^2 = armature, undamped
        return row.spring(xi, active, joint.armature[k], 0.0)

    # Drive (DBD 9): an implicit angular spring/damper toward the control target with the torque
    # limit (114). Hinge: the angle about the axle, wrapped to (-pi, pi]. Ball: the rotation
    # vector of E = X T^-1 (X the relative rotation from rest, T = exp(target)) in world axes.
    # Universal and gimbal: one spring row per hinge angle t_k toward its target, along g_k (DBD 9
    # per hinge, as MuJoCo's per-dof stiffness and damping); the universal's third has g = 0.
    stiffness_h2, damping_h = joint.drive_stiffness * h**2, joint.drive_damping * h
    torque_bound = joint.drive_max_torque * h**2
    hinge_drive = row.spring(xi, flag.hinge_drive, stiffness_h2, damping_h, torque_bound)

    def euler_drive(k):
        stiffness, damping = joint.axis_stiffness[k] * h**2, joint.axis_damping[k] * h
        return row.spring(xi, flag.euler_drive, stiffness, damping, torque_bound)

    # A coordinate with both a rotor and a drive (MuJoCo's armature and joint damping) steps the
    # drive right after the rotor, the two as one block (`rows.spring_row_beside_rotor`; a ball's
    # three axes: `rows.angular_spring_beside_rotor`): one after the other, a light body's drive
    # and its heavy rotor undid each other's steps for tens of iterations.
    hinge_block, euler_block = {"rotor_hinge", "hinge_drive"} <= rows, {"rotor_euler", "euler_drive"} <= rows
    ball_block = {"rotor_ball", "ball_drive"} <= rows
    if "rotor_hinge" in rows:
        change = math.wrap_angle(hinge_angle_now(pair) - _hinge_rotor_reference(joint, target, pair))
        error = rotor_error(joint, target, 0, change, h)
        pair, lam[ROTOR], hold = row.angular_row(
            pair, -hinge_axis, error, lam[ROTOR], rotor_rule(0, flag.rotor_hinge), h, hold, held_step=True,
            response=hinge_response.times(-1.0),
        )  # fmt: skip
        if hinge_block:
            error = math.wrap_angle(hinge_angle_now(pair) - target.drive[0])
            pair, lam[ROTOR], lam[DRIVE], hold = row.spring_row_beside_rotor(
                pair, -hinge_axis, error, (lam[ROTOR], lam[DRIVE]), joint.armature[0], flag.rotor_hinge,
                hinge_drive, h, hold, hinge_response.times(-1.0),
            )  # fmt: skip
    if "rotor_slider" in rows:
        error, axis, arm_a, arm_b = slider_rotor_row(joint, flag, target, pair, h)
        pair, lam[ROTOR] = row.positional_row(
            pair, -axis, arm_a, arm_b, error, lam[ROTOR], rotor_rule(0, flag.rotor_slider), h
        )
    if "rotor_ball" in rows:
        error, _ = rotor_rows(joint, flag, target, pair, "rotor_ball", h)
        pair, kappa, hold = row.angular_spring(
            pair, error, jnp.stack(lam[ROTOR : ROTOR + 3]), xi, joint.armature[0], 0.0, jnp.inf, flag.rotor_ball, h,
            hold, held_step=True,
        )  # fmt: skip
        lam[ROTOR : ROTOR + 3] = list(kappa)
        if ball_block:
            error = ball_drive_error(joint, target, *pair.current_quats())
            pair, rotor, drive, hold = row.angular_spring_beside_rotor(
                pair, error, (jnp.stack(lam[ROTOR : ROTOR + 3]), jnp.stack(lam[DRIVE : DRIVE + 3])), xi, stiffness_h2,
                damping_h, torque_bound, flag.ball_drive, joint.armature[0], flag.rotor_ball, h, hold,
            )  # fmt: skip
            lam[ROTOR : ROTOR + 3], lam[DRIVE : DRIVE + 3] = list(rotor), list(drive)
    if "rotor_euler" in rows:
        reference = target.reference
        if reference is None:
            still = _unmoved(pair)
            reference = (None, None, _euler_angles(joint, flag, still, rows)[0])
        for k in range(3):
            angles, directions = euler_angles_now(pair), euler_directions
            error = rotor_error(joint, target, k, math.wrap_angle(angles[k] - reference[2][k]), h)
            pair, lam[ROTOR + k], hold = row.angular_row(
                pair, -directions[k], error, lam[ROTOR + k], rotor_rule(k, flag.rotor_euler[k]), h, hold,
                held_step=True, response=euler_response(k, -1.0),
            )  # fmt: skip
            if euler_block:
                error = math.wrap_angle(euler_angles_now(pair)[k] - target.drive[k])
                pair, lam[ROTOR + k], lam[DRIVE + k], hold = row.spring_row_beside_rotor(
                    pair, -directions[k], error, (lam[ROTOR + k], lam[DRIVE + k]), joint.armature[k],
                    flag.rotor_euler[k], euler_drive(k), h, hold, euler_response(k, -1.0),
                )  # fmt: skip

    if "hinge_drive" in rows and not hinge_block:
        error = math.wrap_angle(hinge_angle_now(pair) - target.drive[0])
        pair, lam[DRIVE], hold = row.angular_row(
            pair, -hinge_axis, error, lam[DRIVE], hinge_drive, h, hold, response=hinge_response.times(-1.0)
        )
    if "ball_drive" in rows and not ball_block:
        error = ball_drive_error(joint, target, *pair.current_quats())
        pair, kappa, hold = row.angular_spring(
            pair, error, jnp.stack(lam[DRIVE : DRIVE + 3]), xi, stiffness_h2, damping_h, torque_bound,
            flag.ball_drive, h, hold,
        )  # fmt: skip
        lam[DRIVE : DRIVE + 3] = list(kappa)
    if "euler_drive" in rows and not euler_block:
        for k in range(3):
            error = math.wrap_angle(euler_angles_now(pair)[k] - target.drive[k])
            pair, lam[DRIVE + k], hold = row.angular_row(
                pair, -euler_directions[k], error, lam[DRIVE + k], euler_drive(k), h, hold,
                response=euler_response(k, -1.0),
            )  # fmt: skip

    # Motor: the relative speed along the axle or slide axis, force-limited (SI 2.3.6, 2.4.6).
    force_bound = joint.motor_max_force * h**2
    if "angular_motor" in rows:
        pair, lam[MOTOR], hold = row.angular_row(
            pair, -hinge_axis, 0.0, lam[MOTOR], row.motor(xi, flag.angular_motor, target.motor * h, force_bound), h,
            hold, response=hinge_response.times(-1.0),
        )  # fmt: skip
    if "linear_motor" in rows:
        _, axis, arm_a, arm_b = slider_travel(joint, flag, pair)
        pair, lam[MOTOR] = row.positional_row(
            pair, -axis, arm_a, arm_b, 0.0, lam[MOTOR],
            row.motor(xi, flag.linear_motor, target.motor * h, force_bound), h,
        )  # fmt: skip

    # Angular lock, one block of rows (`row.angular_block`) so that where the lock holds no row
    # takes its direction from a normalised near-zero vector. Hinge and planar: the axle
    # alignment (DBD 6 (73)-(80), SI 2.4.1): c = axis_b x axis_a (|c| = sin of (73)'s angle),
    # locked across the bisector of the two axes; a rotation of a by dtheta changes c by
    # P dtheta, P the projector across the axle. Slider, fixed: the whole relative rotation
    # (SI (53)), c = minus the world rotation vector of X.
    if "rotation_lock" in rows:
        quat_a, quat_b = pair.current_quats()
        axle = flag.hinge | flag.planar
        misalignment, bisector = axle_misalignment(joint, quat_a, quat_b)
        eye = jnp.eye(3, dtype=quat_a.dtype)
        across = jnp.where(axle, eye - bisector[:, None] * bisector[None, :], eye)
        if "rotation_locked" in rows:  # else every lock is an axle's: no relative rotation to trace
            error = jnp.where(axle, misalignment, rotation_lock_error(joint, quat_a, quat_b))
        else:
            error = misalignment
        pair, locked = row.angular_block(
            pair, error, jnp.stack(lam[ROTATION_LOCK : ROTATION_LOCK + 3]), hard(axle | flag.rotation_locked),
            constrained=across,
        )  # fmt: skip
        lam[ROTATION_LOCK : ROTATION_LOCK + 3] = list(locked)

    # Universal lock: hinge axis 1 (on a) and axis 2 (on b) stay perpendicular (DBD 6, (73)-(80),
    # with the axle's 0 replaced by 90 degrees), c = m1_a . m2_b. A rotation of a by dtheta moves
    # m1_a by dtheta x m1_a, so dc/dtheta_a = m1_a x m2_b = -dc/dtheta_b: a unit vector where the
    # constraint holds (the axes are perpendicular there), so the row's direction never comes from
    # normalising a vanishing vector. Not the angle form acos(c) - pi/2 along the normalised cross
    # product: same row at the solution, but c is polynomial in the orientations.
    if "universal" in rows:
        error, direction_a = universal_lock(joint, *pair.current_quats())
        pair, lam[ROTATION_LOCK], hold = row.angular_row(
            pair, direction_a, error, lam[ROTATION_LOCK], hard(flag.universal), hold=hold
        )

    # Angle limits: the twist of X about a's axis (SI (101)-(106) via swing-twist), kept in
    # [lower, upper] by two one-sided rows (SI (108), (115)) clamped as in DBD (83), projected as
    # one (`_nearer_bound`).
    if "has_angle_limits" in rows:
        sign, error, upper_row = _nearer_bound(hinge_angle_now(pair), joint.lower, joint.upper, periodic=True)
        multiplier = jnp.where(upper_row, lam[ANGLE_UPPER], lam[ANGLE_LOWER])
        rule = limit_rule(flag.has_angle_limits, joint.armature[0])
        pair, multiplier, hold = row.angular_row(
            pair, sign * hinge_axis, error, multiplier, rule, h, hold, limit_held, hinge_response.times(sign)
        )
        lam[ANGLE_LOWER] = jnp.where(upper_row, lam[ANGLE_LOWER], multiplier)
        lam[ANGLE_UPPER] = jnp.where(upper_row, multiplier, lam[ANGLE_UPPER])

    # Cone: the angle between the twist axes stays below the limit, DBD (81)-(83).
    if "has_cone" in rows:
        quat_a, quat_b = pair.current_quats()
        cone_angle, cone_axis = math.angle_between(
            *row.rotate_pair(quat_a, quat_b, joint.local_axis_a, joint.local_axis_b)
        )
        rule = limit_rule(flag.has_cone, joint.armature[0])
        pair, lam[CONE], hold = row.angular_row(
            pair, cone_axis, joint.cone_limit - cone_angle, lam[CONE], rule, h, hold, limit_held
        )

    # Universal / gimbal hinge limits: t_k in [lower_k, upper_k] by two one-sided rows per hinge
    # (SI (108), (115)), clamped as DBD (83), projected as one (`_nearer_bound`); dc/dtheta_b =
    # +-g_k: its impulse is the generalised force on hinge k alone.
    if "euler_limited" in rows:
        for k in range(3):
            angles, directions = euler_angles_now(pair), euler_directions
            sign, error, upper_row = _nearer_bound(angles[k], joint.axis_lower[k], joint.axis_upper[k], periodic=True)
            multiplier = jnp.where(upper_row, lam[EULER_UPPER + k], lam[EULER_LOWER + k])
            rule = limit_rule(flag.euler_limited[k], joint.armature[k])
            pair, multiplier, hold = row.angular_row(
                pair, sign * directions[k], error, multiplier, rule, h, hold, limit_held, euler_response(k, sign)
            )
            lam[EULER_LOWER + k] = jnp.where(upper_row, lam[EULER_LOWER + k], multiplier)
            lam[EULER_UPPER + k] = jnp.where(upper_row, multiplier, lam[EULER_UPPER + k])

    # Slider travel limits, SI (65)-(78), on the travel d = (p_b - p_a) . axis, the two one-sided
    # rows projected as one (`_nearer_bound`).
    if "has_travel_limits" in rows:
        travel, axis, arm_a, arm_b = slider_travel(joint, flag, pair)
        sign, error, upper_row = _nearer_bound(travel, joint.lower, joint.upper)
        multiplier = jnp.where(upper_row, lam[TRAVEL_UPPER], lam[TRAVEL_LOWER])
        rule = limit_rule(flag.has_travel_limits, joint.armature[0])
        pair, multiplier = row.positional_row(pair, sign * axis, arm_a, arm_b, error, multiplier, rule, h)
        lam[TRAVEL_LOWER] = jnp.where(upper_row, lam[TRAVEL_LOWER], multiplier)
        lam[TRAVEL_UPPER] = jnp.where(upper_row, multiplier, lam[TRAVEL_UPPER])

    # Point constraint last, so the joint gap is what this sweep leaves smallest: c = p_a - p_b as
    # one block of three rows with the full 3x3 effective mass, DBD (64)-(66). Not the magnitude
    # form |p_a - p_b| (54): that is a cone at zero gap, so the step map has a kink exactly where
    # the joint holds (derivatives there disagree with finite differences), and its one row along
    # the gap leaves what lies across it. The block conserves linear momentum exactly and angular
    # momentum up to gap x impulse (63), which vanishes as the gap closes.
    pair, point = _point_step(joint, flag, pair, jnp.stack(lam[POINT : POINT + 3]) + hold.impulse, rows)
    lam[POINT : POINT + 3] = list(point)
    dx, dtheta = pair.displacements()
    return dx, dtheta, _restacked(multipliers, lam, untouched)


def _point_step(joint: Joints, flag: JointFlags, pair: BodyPair, multiplier: jnp.ndarray, rows: frozenset[str]):
    """The joint's point block, DBD (64)-(66), projected once from `pair`: (moved pair, multiplier (3,)).
    A slider only removes the part across its axis (SI (51)), a planar joint only the part along
    its normal; both act level with p_b on a."""
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = joint_points(joint, flag, pair, quat_a, quat_b)
    constrained = None
    if "slider" in rows or "planar" in rows:
        axis = math.quat_rotate(quat_a, joint.local_axis_a)
        along_axis = axis[:, None] * axis[None, :]
        eye = jnp.eye(3, dtype=delta.dtype)
        constrained = jnp.where(flag.slider, eye - along_axis, jnp.where(flag.planar, along_axis, eye))
        arm_a = arm_a - math.matvec(eye - constrained, delta)
    rule = row.rigid(joint.relaxation, joint.regularization, True)
    return row.point_block(pair, arm_a, arm_b, delta, multiplier, rule, constrained=constrained)


def project_point(joint: Joints, flag: JointFlags, bodies: BodySet, multipliers: jnp.ndarray, rows: frozenset[str]):
    """The joint's point block alone (`project`'s last row), for the point sweeps after the DBD
    sweeps (`solvers.dbd.sweep_joint_points`). multipliers: (NUM_MULTIPLIERS,), the point's
    continued. Returns (dx (2, 3), dtheta (2, 3), multipliers)."""
    pair, point = _point_step(joint, flag, BodyPair.of(bodies), multipliers[POINT : POINT + 3], rows)
    dx, dtheta = pair.displacements()
    return dx, dtheta, multipliers.at[POINT : POINT + 3].set(point)


def limit_errors(value, lower, upper, periodic=False):
    """(value - lower, upper - value): how far inside each bound `value` is (negative: past it).
    periodic: `value` is an angle, measured from the middle of the range and wrapped there, so that
    an angle pushed past a bound keeps that bound's error until it is half the excluded arc beyond
    it (measured from zero and wrapped at +-pi, a knee bent 20 degrees past a -160 degree limit
    read +160, past its upper limit, and was driven back the long way, through the excluded arc)."""
    if not periodic:
        return value - lower, upper - value
    middle, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
    offset = math.wrap_angle(value - middle)
    return offset + half, half - offset


def _nearer_bound(value, lower, upper, periodic=False):
    """The one of the two limit rows lower <= value <= upper that can act: (sign of its direction,
    -1 for the lower row and +1 for the upper, its error (value - lower or upper - value), True
    where it is the upper row). periodic: an angle (`limit_errors`).

    Both rows only push (DBD (83)) and their multipliers start the substep at zero, so a row
    whose error is positive never steps. With lower <= upper at most one error is negative, the
    one of the nearer bound: projecting that row alone moves the bodies exactly as projecting
    both in turn, with half the rows in the compiled sweep (each of which the reverse pass keeps
    residuals for)."""
    below, above = limit_errors(value, lower, upper, periodic)
    upper_row = above < below
    return jnp.where(upper_row, 1.0, -1.0), jnp.where(upper_row, above, below), upper_row


def _restacked(multipliers: jnp.ndarray, lam: list, untouched: list) -> jnp.ndarray:
    """The (NUM_MULTIPLIERS,) multipliers with the entries the traced rows wrote: runs of entries no
    row touched are copied as one slice each (stacking all 24 entries one by one costs the
    compiled sweep a kernel per entry, for every joint colour and iteration)."""
    pieces, k = [], 0
    while k < len(lam):
        stop = k + 1
        same = lam[k] is untouched[k]
        while stop < len(lam) and (lam[stop] is untouched[stop]) == same:
            stop += 1
        pieces.append(multipliers[k:stop] if same else jnp.stack(lam[k:stop]))
        k = stop
    return pieces[0] if len(pieces) == 1 else jnp.concatenate(pieces)
