"""Scenes shared by the tests (and mirrored by the benchmarks): plain builders, no magic."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import dbdjax as dbd
from dbdjax.constraints import joints
from dbdjax.model import GIMBAL, HINGE, UNIVERSAL

LINK_LENGTH = 0.1
LINK_MASS = 0.1
# A slender rod: m l^2 / 12 across, m r^2 / 2 along (r = 1 cm).
LINK_INERTIA = (LINK_MASS * 0.01**2 / 2, LINK_MASS * LINK_LENGTH**2 / 12, LINK_MASS * LINK_LENGTH**2 / 12)


def chain(
    links: int = 20,
    origin=(0.0, 0.0, 2.0),
    pinned: bool = True,
    gravity=(0.0, 0.0, -9.81),
    velocities=None,
    **finalize,
):
    """A horizontal chain of rods along +x joined by ball joints, pinned to the world at `origin`."""
    b = dbd.ModelBuilder(gravity=gravity)
    origin = np.asarray(origin, dtype=np.float64)
    previous = dbd.WORLD
    for i in range(links):
        centre = origin + np.array([(i + 0.5) * LINK_LENGTH, 0.0, 0.0])
        vel = (0.0, 0.0, 0.0) if velocities is None else velocities[i]
        body = b.add_body(pos=centre, mass=LINK_MASS, inertia=LINK_INERTIA, vel=vel)
        if previous != dbd.WORLD or pinned:
            b.add_ball_joint(previous, body, anchor=origin + np.array([i * LINK_LENGTH, 0.0, 0.0]))
        previous = body
    return b.finalize(**finalize)


def pendulum(joint: str = "hinge", length: float = 1.0, angle: float = 0.05, radius: float = 0.1, **finalize):
    """A solid sphere (radius `radius`, 1 kg) hanging `length` below a pivot at the origin."""
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    moment = 0.4 * radius**2
    bob = b.add_body(pos=(length * np.sin(angle), 0.0, -length * np.cos(angle)), mass=1.0, inertia=(moment,) * 3)
    if joint == "hinge":
        b.add_hinge_joint(dbd.WORLD, bob, anchor=(0, 0, 0), axis=(0, 1, 0))
    else:
        b.add_ball_joint(dbd.WORLD, bob, anchor=(0, 0, 0))
    return b.finalize(**finalize)


def box_on_incline(angle_degrees: float, friction: float, dynamic_friction=None, **finalize):
    """A 0.2 m cube resting face down on a plane tilted by `angle_degrees` about y. Returns
    (model, start position of the cube's centre)."""
    angle = np.radians(angle_degrees)
    normal = np.array([-np.sin(angle), 0.0, np.cos(angle)])
    b = dbd.ModelBuilder()
    start = 0.1 * normal
    box = b.add_body(pos=start, quat=(np.cos(-angle / 2), 0, np.sin(-angle / 2), 0))  # bottom face on the plane
    material = dict(friction=friction, dynamic_friction=dynamic_friction)
    b.add_box(box, (0.1, 0.1, 0.1), **material)
    b.add_plane(normal=normal, **material)
    return b.finalize(**finalize), start


def ragdoll(height: float = 1.2, spin=(1.0, 2.0, 0.5), drives: bool = False, **finalize):
    """A ragdoll of 10 bodies and 9 joints falling onto the ground plane: a box torso, a sphere
    head (ball joint with a cone), arms and legs of two capsules each (shoulders and hips: ball
    joints with cone and twist limits; elbows and knees: hinges with limits). Masses come from the
    shapes (density 1000). Limbs do not collide with each other, only with the plane. The torso
    starts `height` m up, turning at `spin` rad/s. drives: a drive (DBD 9) on every joint holding
    the build pose (targets 0). Returns the model; joint names say which is which."""
    b = dbd.ModelBuilder()
    limb = dict(contype=2, conaffinity=1)  # limbs touch the plane only (MuJoCo's bit rule)
    up = np.array([0.0, 0.0, height])
    torso = b.add_body(pos=up, ang_vel=spin, name="torso")
    b.add_box(torso, (0.12, 0.08, 0.2), **limb)
    head = b.add_body(pos=up + (0, 0, 0.32), name="head")
    b.add_sphere(head, 0.1, **limb)
    joints = [b.add_ball_joint(torso, head, anchor=up + (0, 0, 0.22), cone_limit=0.6, name="neck")]
    along_x = (np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0)  # a capsule's local z turned onto x
    for side in (-1.0, 1.0):
        shoulder = up + (side * 0.14, 0, 0.16)
        upper = b.add_body(pos=shoulder + (side * 0.15, 0, 0), quat=along_x, name="upper arm")
        b.add_capsule(upper, 0.04, 0.11, **limb)
        fore = b.add_body(pos=shoulder + (side * 0.45, 0, 0), quat=along_x, name="forearm")
        b.add_capsule(fore, 0.035, 0.11, **limb)
        joints.append(b.add_ball_joint(torso, upper, anchor=shoulder, cone_limit=1.2, twist_limits=(-0.6, 0.6),
                                       name="shoulder"))  # fmt: skip
        joints.append(b.add_hinge_joint(upper, fore, anchor=shoulder + (side * 0.3, 0, 0), axis=(0, 0, side),
                                        limits=(0.0, 2.2), name="elbow"))  # fmt: skip
        hip = up + (side * 0.08, 0, -0.22)
        thigh = b.add_body(pos=hip + (0, 0, -0.2), name="thigh")
        b.add_capsule(thigh, 0.055, 0.14, **limb)
        shin = b.add_body(pos=hip + (0, 0, -0.6), name="shin")
        b.add_capsule(shin, 0.045, 0.15, **limb)
        joints.append(b.add_ball_joint(torso, thigh, anchor=hip, cone_limit=1.0, twist_limits=(-0.4, 0.4),
                                       name="hip"))  # fmt: skip
        joints.append(b.add_hinge_joint(thigh, shin, anchor=hip + (0, 0, -0.4), axis=(1, 0, 0), limits=(0.0, 2.4),
                                        name="knee"))  # fmt: skip
    if drives:
        for joint in joints:
            b.add_drive(joint, stiffness=40.0, damping=4.0, max_torque=60.0)
    b.add_plane(friction=0.8)
    return b.finalize(**finalize)


# The model an argument of the program, not its constant: models of one structure (other angles,
# frictions, masses) share one compile (session 69: four box-on-incline cases 17.9 s instead of
# 54.3 s, the same results to the bit).
_ROLLOUT = jax.jit(dbd.rollout, static_argnames="steps")


def rollout(model, steps: int, state=None, controls=None):
    """`dbd.rollout` from `state` (default: the build pose) for `steps` steps, with `controls`
    (broadcast to (steps, num_controls)) or none: (final state, trajectory)."""
    state = dbd.init(model) if state is None else state
    if controls is None:
        return _ROLLOUT(model, state, steps=steps)
    return _ROLLOUT(model, state, jnp.broadcast_to(jnp.asarray(controls), (steps, model.num_controls)))


def hinge_angles(model, quat):
    """(T, J, 3) joint coordinates along a trajectory's orientations (T, N, 4): a hinge's angle
    (`joints.hinge_angle`'s twist) in column 0, a universal or gimbal joint's hinge angles
    (`math.euler_angles`, the universal's third 0); other kinds 0."""
    structure = model.structure
    kind = structure.joint_kind.array
    identity = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0], quat.dtype), quat.shape[:-2] + (1, 4))
    padded = jnp.concatenate([quat, identity], axis=-2)
    quat_a, quat_b = padded[..., structure.joint_body_a.array, :], padded[..., structure.joint_body_b.array, :]

    def one(joint, a, b, universal):
        hinge = dbd.math.quat_twist_angle(joints.relative_rotation(joint, a, b), joint.local_axis_a)
        axes_a = dbd.math.quat_rotate(a[None], joint.local_axes_a)
        axes_b = dbd.math.quat_rotate(b[None], joint.local_axes_b)
        euler, _ = dbd.math.euler_angles(axes_a, axes_b, universal)
        return hinge, euler

    per_joint = jax.vmap(one, in_axes=(0, 0, 0, 0))
    hinge, euler = jax.vmap(per_joint, in_axes=(None, 0, 0, None))(model.joints, quat_a, quat_b,
                                                                  jnp.asarray(kind == UNIVERSAL))  # fmt: skip
    zero = jnp.zeros_like(hinge)
    is_hinge = jnp.asarray(kind == HINGE)[:, None]
    angles = jnp.where(is_hinge, jnp.stack([hinge, zero, zero], -1), euler)
    return np.asarray(jnp.where(jnp.asarray((kind == HINGE) | (kind == UNIVERSAL) | (kind == GIMBAL))[:, None],
                                angles, 0.0))  # fmt: skip


def mixed_tree(**options) -> dbd.Model:
    """Six bodies on six kinds of joint (ball, hinge, universal, slider, gimbal, fixed), thrown;
    the colouring gives each kind colours of its own (builder.colour_classes)."""
    rng = np.random.default_rng(5)
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    bodies = [b.add_body(pos=(0.1 * k, 0.05 * k, -0.3 * (k + 1)), mass=1.0 + 0.2 * k, inertia=(0.02, 0.03, 0.015),
                         vel=rng.normal(size=3), ang_vel=2.0 * rng.normal(size=3)) for k in range(6)]  # fmt: skip
    b.add_ball_joint(dbd.WORLD, bodies[0], anchor=(0, 0, 0), cone_limit=0.8)
    b.add_hinge_joint(bodies[0], bodies[1], anchor=(0.05, 0.02, -0.45), axis=(0, 1, 0), limits=(-1.0, 1.2))
    b.add_universal_joint(bodies[1], bodies[2], anchor=(0.15, 0.07, -0.75), axes=[(1, 0, 0), (0, 1, 0)],
                          limits=[(-0.5, 0.5), (-0.7, 0.3)])  # fmt: skip
    b.add_slider_joint(bodies[2], bodies[3], anchor=(0.25, 0.12, -1.05), axis=(0, 0, 1), limits=(-0.1, 0.1))
    b.add_gimbal_joint(bodies[0], bodies[4], anchor=(0.2, 0.1, -0.6), axes=[(0, 0, 1), (0, 1, 0), (1, 0, 0)])
    b.add_fixed_joint(bodies[1], bodies[5], anchor=(0.3, 0.15, -1.2))
    return b.finalize(dt=1 / 60, iterations=4, **options)
