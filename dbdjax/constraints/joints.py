"""Joints: ball, hinge, slider and fixed, each one node of the constraint graph.

All rows of one joint (angular lock, angle limits, cone, slider limits, then the point
constraint) are projected together, one after another, in `project` (Gauss-Seidel inside the
joint). One function serves every kind: the rows a kind does not have are inactive (their
multiplier step is zero), so a colour group of mixed kinds is a single `jax.vmap`.

Row by kind:
  ball   point (DBD 5, magnitude form (54)), cone (DBD (81)-(83)), twist limits
  hinge  point, axle alignment (DBD 6, (73)-(80); SI 2.4), angle limits (SI 2.4.5, clamped as DBD 6.1)
  slider point off the axis (SI 2.3.1), rotation lock (SI (53)), travel limits (SI 2.3.5)
  fixed  point, rotation lock (SI 2.5)
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.constraints.rows import BodyPair, angular_row, positional_row
from dbdjax.model import BALL, FIXED, HINGE, SLIDER, Joints, Structure

# Multiplier rows per joint, in projection order.
ROTATION_LOCK, ANGLE_LOWER, ANGLE_UPPER, CONE, TRAVEL_LOWER, TRAVEL_UPPER, POINT = range(7)
NUM_ROWS = 7


class JointFlags(NamedTuple):
    """Static per-joint switches, (J,) bool each (padded slots have all False)."""

    active: jnp.ndarray
    world_a: jnp.ndarray
    world_b: jnp.ndarray
    hinge: jnp.ndarray
    slider: jnp.ndarray
    rotation_locked: jnp.ndarray  # slider and fixed
    has_angle_limits: jnp.ndarray  # hinge angle or ball twist
    has_cone: jnp.ndarray
    has_travel_limits: jnp.ndarray


def flags(structure: Structure):
    """numpy JointFlags for the joints of `structure` (host side, at trace time)."""
    kind = structure.joint_kind.array
    limits = structure.joint_has_limits.array
    world = structure.num_bodies
    return JointFlags(
        active=np.ones_like(limits),
        world_a=structure.joint_body_a.array == world,
        world_b=structure.joint_body_b.array == world,
        hinge=kind == HINGE,
        slider=kind == SLIDER,
        rotation_locked=(kind == SLIDER) | (kind == FIXED),
        has_angle_limits=limits & ((kind == HINGE) | (kind == BALL)),
        has_cone=structure.joint_has_cone.array & (kind == BALL),
        has_travel_limits=limits & (kind == SLIDER),
    )


def rows_in_use(structure: Structure) -> frozenset[int]:
    """The rows some joint of the model has. The others are left out of the trace altogether:
    a chain of ball joints compiles to the point row alone."""
    f = flags(structure)
    used = {POINT}
    if (f.hinge | f.rotation_locked).any():
        used.add(ROTATION_LOCK)
    if f.has_angle_limits.any():
        used.update((ANGLE_LOWER, ANGLE_UPPER))
    if f.has_cone.any():
        used.add(CONE)
    if f.has_travel_limits.any():
        used.update((TRAVEL_LOWER, TRAVEL_UPPER))
    return frozenset(used)


def _anchor_points(joint: Joints, flag: JointFlags, pair: BodyPair, quat_a, quat_b):
    """The joint point on each body: (delta = p_a - p_b, arm_a, arm_b) at X* + dX.

    delta is summed from differences of like terms, never from large absolute positions, so a
    joint 10 km from the origin is solved as precisely as one at the origin. For the world side
    the anchor itself is the origin and the arm is zero.
    """
    arm_a = math.quat_rotate(quat_a, joint.local_anchor_a)
    arm_b = math.quat_rotate(quat_b, joint.local_anchor_b)
    origin_a = pair.origin_a + jnp.where(flag.world_a, arm_a, 0.0)
    origin_b = pair.origin_b + jnp.where(flag.world_b, arm_b, 0.0)
    arm_a = jnp.where(flag.world_a, 0.0, arm_a)
    arm_b = jnp.where(flag.world_b, 0.0, arm_b)
    delta = (origin_a - origin_b) + (pair.dx_a - pair.dx_b) + (arm_a - arm_b)
    return delta, arm_a, arm_b


def _relative_rotation(joint: Joints, quat_a, quat_b):
    """X with q_b = q_a X rest: the rotation of b away from its rest pose, in a's frame."""
    relative = math.quat_multiply(math.quat_conjugate(quat_a), quat_b)
    return math.quat_multiply(relative, math.quat_conjugate(joint.rest_rotation))


def project(
    joint: Joints,
    flag: JointFlags,
    pair: BodyPair,
    multipliers: jnp.ndarray,
    rows: frozenset[int] = frozenset(range(NUM_ROWS)),
) -> tuple[BodyPair, jnp.ndarray]:
    """Project every row of one joint once; `joint` holds one joint's parameters (no J axis).

    multipliers: (NUM_ROWS,) accumulated lambda of each row this substep. rows: the rows to
    trace (static, `rows_in_use`). Returns the moved pair and the updated multipliers.
    """
    xi, alpha = joint.relaxation, joint.regularization
    lam = [multipliers[i] for i in range(NUM_ROWS)]

    # Angular lock. Hinge: the axle constraint, angle between the axes (73) along w (75); the
    # update rotates a toward b (78). Slider, fixed: the whole relative rotation (SI (53)),
    # in its rotation-invariant magnitude form so that it conserves angular momentum (DBD 5.1).
    if ROTATION_LOCK in rows:
        quat_a, quat_b = pair.current_quats()
        axis_a = math.quat_rotate(quat_a, joint.local_axis_a)
        axis_b = math.quat_rotate(quat_b, joint.local_axis_b)
        axle_angle, axle_axis = math.angle_between(axis_a, axis_b)
        relative = _relative_rotation(joint, quat_a, quat_b)
        lock_axis, lock_angle = math.safe_normalize(math.quat_rotate(quat_a, math.quat_log(relative)))
        error = jnp.where(flag.hinge, axle_angle, lock_angle)
        direction = jnp.where(flag.hinge[..., None], -axle_axis, -lock_axis)  # dc/dtheta_a
        pair, lam[ROTATION_LOCK] = angular_row(
            pair, direction, error, lam[ROTATION_LOCK], xi, alpha, False,
            flag.hinge | flag.rotation_locked,
        )  # fmt: skip

    # Angle limits: the twist of X about a's axis (SI (101)-(106) via swing-twist), kept in
    # [lower, upper] by two one-sided rows (SI (108), (115)) clamped as in DBD (83).
    # The row direction is the bisector of the two bodies' axes (equal for a hinge).
    for row, sign in ((ANGLE_LOWER, -1.0), (ANGLE_UPPER, 1.0)):
        if row not in rows:
            continue
        quat_a, quat_b = pair.current_quats()
        angle = math.quat_twist_angle(_relative_rotation(joint, quat_a, quat_b), joint.local_axis_a)
        axis, _ = math.safe_normalize(
            math.quat_rotate(quat_a, joint.local_axis_a) + math.quat_rotate(quat_b, joint.local_axis_b)
        )
        error = (angle - joint.lower) if sign < 0 else (joint.upper - angle)
        pair, lam[row] = angular_row(pair, sign * axis, error, lam[row], xi, alpha, True, flag.has_angle_limits)

    # Cone: the angle between the twist axes stays below the limit, DBD (81)-(83).
    if CONE in rows:
        quat_a, quat_b = pair.current_quats()
        cone_angle, cone_axis = math.angle_between(
            math.quat_rotate(quat_a, joint.local_axis_a), math.quat_rotate(quat_b, joint.local_axis_b)
        )
        pair, lam[CONE] = angular_row(
            pair, cone_axis, joint.cone_limit - cone_angle, lam[CONE], xi, alpha, True, flag.has_cone
        )

    # Slider travel limits, SI (65)-(78): travel d = (p_b - p_a) . axis. Each side acts at the
    # point of body a level with p_b, so the impulse is parallel to the points' separation.
    for row, sign, bound in ((TRAVEL_LOWER, -1.0, joint.lower), (TRAVEL_UPPER, 1.0, joint.upper)):
        if row not in rows:
            continue
        quat_a, quat_b = pair.current_quats()
        delta, arm_a, arm_b = _anchor_points(joint, flag, pair, quat_a, quat_b)
        slide_axis = math.quat_rotate(quat_a, joint.local_axis_a)
        travel = -math.dot(delta, slide_axis)
        across = delta + travel[..., None] * slide_axis
        error = (travel - bound) if sign < 0 else (bound - travel)
        pair, lam[row] = positional_row(
            pair, sign * slide_axis, arm_a - across, arm_b, error, lam[row], xi, alpha, True,
            flag.has_travel_limits,
        )  # fmt: skip

    # Point constraint last, so the joint gap is what this sweep leaves smallest: the distance
    # between the joint points in the magnitude form (54)-(61) that conserves momentum (62)-(63).
    # A slider only removes the part across its axis (SI (51)), acting level with p_b on a.
    quat_a, quat_b = pair.current_quats()
    delta, arm_a, arm_b = _anchor_points(joint, flag, pair, quat_a, quat_b)
    slide_axis = math.quat_rotate(quat_a, joint.local_axis_a)
    along = jnp.where(flag.slider, math.dot(delta, slide_axis), 0.0)[..., None] * slide_axis
    direction, gap = math.safe_normalize(delta - along)
    pair, lam[POINT] = positional_row(
        pair, direction, arm_a - along, arm_b, gap, lam[POINT], xi, alpha, False, flag.active
    )
    return pair, jnp.stack(lam)
