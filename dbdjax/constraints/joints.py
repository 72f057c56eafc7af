"""Joints: ball, hinge, slider and fixed, each one node of the constraint graph.

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
Drives and motors go first so that the hard rows, and the point block last of all, have the last word.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.model import BALL, FIXED, HINGE, PLANAR, SLIDER, Joints, Structure

# Multipliers of one joint, in the order of `project`'s rows. The ball drive's torque, the
# rotation lock's and the point block's impulses are 3-vectors: they own slots [DRIVE, DRIVE + 3),
# [ROTATION_LOCK, ROTATION_LOCK + 3) and [POINT, POINT + 3).
DRIVE, MOTOR, ROTATION_LOCK, ANGLE_LOWER, ANGLE_UPPER, CONE = 0, 3, 4, 7, 8, 9
TRAVEL_LOWER, TRAVEL_UPPER, POINT = 10, 11, 12
NUM_MULTIPLIERS = POINT + 3


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


class Targets(NamedTuple):
    """What the control vector asks of one joint this step (zero where it has no actuator)."""

    drive: jnp.ndarray  # (3,) hinge: [angle, 0, 0] rad; ball: rotation vector, rad, in a's frame
    motor: jnp.ndarray  # () rad/s (hinge) or m/s (slider)


def flags(structure: Structure) -> JointFlags:
    """numpy JointFlags for the joints of `structure` (host side, at trace time)."""
    kind = structure.joint_kind.array
    limits = structure.joint_has_limits.array
    drive = structure.joint_drive_control.array[:, 0] < structure.num_controls
    if structure.joint_passive_drive.array.size:  # spring-dampers toward the build pose, no control
        drive = drive | structure.joint_passive_drive.array
    motor = structure.joint_motor_control.array < structure.num_controls
    world = structure.num_bodies
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
    )


def targets(structure: Structure, control: jnp.ndarray | None, dtype) -> Targets:
    """Each joint's slice of the flat control vector, (J, 3) drive and (J,) motor targets."""
    padded = jnp.zeros((structure.num_controls + 1,), dtype)  # the last entry reads as "no actuator"
    if control is not None:
        padded = padded.at[:-1].set(control)
    return Targets(
        drive=padded[structure.joint_drive_control.array],
        motor=padded[structure.joint_motor_control.array],
    )


def rows_in_use(structure: Structure) -> frozenset[str]:
    """The kinds of row some joint of the model has (the names of `JointFlags`, plus "point").
    The others are left out of the trace altogether: a chain of ball joints compiles to the point
    block alone."""
    f = flags(structure)
    used = {name for name, values in f._asdict().items() if values.any()}
    if (f.hinge | f.rotation_locked | f.planar).any():
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
    axis, _ = math.safe_normalize(
        math.quat_rotate(quat_a, joint.local_axis_a) + math.quat_rotate(quat_b, joint.local_axis_b)
    )
    return angle, axis


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
    lam = list(multipliers)
    hard = lambda active, inequality=False: row.rigid(xi, alpha, active, inequality)  # noqa: E731

    # Drive (DBD 9): an implicit angular spring/damper toward the control target with the torque
    # limit (114). Hinge: the angle about the axle, wrapped to (-pi, pi]. Ball: the rotation
    # vector of E = X T^-1 (X the relative rotation from rest, T = exp(target)) in world axes.
    stiffness_h2, damping_h = joint.drive_stiffness * h**2, joint.drive_damping * h
    torque_bound = joint.drive_max_torque * h**2
    if "hinge_drive" in rows:
        angle, axis = hinge_angle(joint, pair)
        offset = angle - target.drive[0]
        error = math.safe_atan2(jnp.sin(offset), jnp.cos(offset))
        pair, lam[DRIVE] = row.angular_row(
            pair, -axis, error, lam[DRIVE],
            row.spring(xi, flag.hinge_drive, stiffness_h2, damping_h, torque_bound), h,
        )  # fmt: skip
    if "ball_drive" in rows:
        quat_a, quat_b = pair.current_quats()
        goal = math.quat_exp(target.drive)  # the target relative rotation, in a's frame
        error_rotation = math.quat_multiply(relative_rotation(joint, quat_a, quat_b), math.quat_conjugate(goal))
        error = math.quat_rotate(quat_a, math.quat_log(error_rotation))
        pair, kappa = row.angular_spring(
            pair, error, jnp.stack(lam[DRIVE : DRIVE + 3]), xi, stiffness_h2, damping_h, torque_bound,
            flag.ball_drive, h,
        )  # fmt: skip
        lam[DRIVE : DRIVE + 3] = list(kappa)

    # Motor: the relative speed along the axle or slide axis, force-limited (SI 2.3.6, 2.4.6).
    force_bound = joint.motor_max_force * h**2
    if "angular_motor" in rows:
        _, axis = hinge_angle(joint, pair)
        pair, lam[MOTOR] = row.angular_row(
            pair, -axis, 0.0, lam[MOTOR], row.motor(xi, flag.angular_motor, target.motor * h, force_bound), h
        )
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
        axis_a = math.quat_rotate(quat_a, joint.local_axis_a)
        axis_b = math.quat_rotate(quat_b, joint.local_axis_b)
        axle = flag.hinge | flag.planar
        bisector, _ = math.safe_normalize(axis_a + axis_b)
        eye = jnp.eye(3, dtype=axis_a.dtype)
        across = jnp.where(axle, eye - bisector[:, None] * bisector[None, :], eye)
        misalignment = math.cross(axis_b, axis_a)
        lock = -math.quat_rotate(quat_a, math.quat_log(relative_rotation(joint, quat_a, quat_b)))
        error = jnp.where(axle, misalignment, lock)
        pair, locked = row.angular_block(
            pair, error, jnp.stack(lam[ROTATION_LOCK : ROTATION_LOCK + 3]), hard(axle | flag.rotation_locked),
            constrained=across,
        )  # fmt: skip
        lam[ROTATION_LOCK : ROTATION_LOCK + 3] = list(locked)

    # Angle limits: the twist of X about a's axis (SI (101)-(106) via swing-twist), kept in
    # [lower, upper] by two one-sided rows (SI (108), (115)) clamped as in DBD (83).
    if "has_angle_limits" in rows:
        for index, sign in ((ANGLE_LOWER, -1.0), (ANGLE_UPPER, 1.0)):
            angle, axis = hinge_angle(joint, pair)
            error = (angle - joint.lower) if sign < 0 else (joint.upper - angle)
            pair, lam[index] = row.angular_row(
                pair, sign * axis, error, lam[index], hard(flag.has_angle_limits, inequality=True)
            )

    # Cone: the angle between the twist axes stays below the limit, DBD (81)-(83).
    if "has_cone" in rows:
        quat_a, quat_b = pair.current_quats()
        cone_angle, cone_axis = math.angle_between(
            math.quat_rotate(quat_a, joint.local_axis_a), math.quat_rotate(quat_b, joint.local_axis_b)
        )
        pair, lam[CONE] = row.angular_row(
            pair, cone_axis, joint.cone_limit - cone_angle, lam[CONE], hard(flag.has_cone, inequality=True)
        )

    # Slider travel limits, SI (65)-(78), on the travel d = (p_b - p_a) . axis.
    if "has_travel_limits" in rows:
        for index, sign, bound in ((TRAVEL_LOWER, -1.0, joint.lower), (TRAVEL_UPPER, 1.0, joint.upper)):
            travel, axis, arm_a, arm_b = slider_travel(joint, flag, pair)
            error = (travel - bound) if sign < 0 else (bound - travel)
            pair, lam[index] = row.positional_row(
                pair, sign * axis, arm_a, arm_b, error, lam[index], hard(flag.has_travel_limits, inequality=True)
            )

    # Point constraint last, so the joint gap is what this sweep leaves smallest: c = p_a - p_b as
    # one block of three rows with the full 3x3 effective mass, DBD (64)-(66). Not the magnitude
    # form |p_a - p_b| (54): that is a cone at zero gap, so the step map has a kink exactly where
    # the joint holds (derivatives there disagree with finite differences), and its one row along
    # the gap leaves what lies across it. The block conserves linear momentum exactly and angular
    # momentum up to gap x impulse (63), which vanishes as the gap closes.
    # A slider only removes the part across its axis (SI (51)), a planar joint only the part along
    # its normal; both act level with p_b on a.
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = joint_points(joint, flag, pair, quat_a, quat_b)
    constrained = None
    if "slider" in rows or "planar" in rows:
        axis = math.quat_rotate(quat_a, joint.local_axis_a)
        along_axis = axis[:, None] * axis[None, :]
        eye = jnp.eye(3, dtype=delta.dtype)
        constrained = jnp.where(flag.slider, eye - along_axis, jnp.where(flag.planar, along_axis, eye))
        arm_a = arm_a - math.matvec(eye - constrained, delta)
    pair, point = row.point_block(
        pair, arm_a, arm_b, delta, jnp.stack(lam[POINT : POINT + 3]), hard(True), constrained=constrained
    )
    lam[POINT : POINT + 3] = list(point)
    dx, dtheta = pair.displacements()
    return dx, dtheta, jnp.stack(lam)
