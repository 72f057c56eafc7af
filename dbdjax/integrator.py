"""Unconstrained prediction (DBD (21)-(24)) and the displacement update (DBD (36)-(39)).

The solver never sees velocities computed from differences of positions: it returns the
displacement dX from the prediction X*, and velocities are corrected by dX / h (36), (38).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dbdjax import math
from dbdjax.indexing import segment_sum, take
from dbdjax.model import UNIVERSAL, Model, State


def predict(model: Model, state: State, h: float, control: jnp.ndarray | None = None) -> State:
    """Free motion over one substep of h seconds under gravity, DBD (21)-(24), and the torque
    actuators' forces (`actuator_wrenches`) held over the substep: the f_ext of (21) and the
    torque of (20).

    The angular update is the implicit form (20), with the precession term at t + 1, solved in
    the body frame by one Newton step. The explicit form (23) gains energy (the paper's footnote
    1): a rod spinning at 50 rad/s with a 16:1 inertia ratio diverged in 150 steps at 60 Hz.
    """
    vel = state.vel + h * model.gravity  # (21)
    body_ang_vel = math.quat_rotate_inverse(state.quat, state.ang_vel)
    if control is not None and model.torques is not None and model.structure.torque_control.array.size:
        force, torque = actuator_wrenches(model, state, control)
        vel = vel + h * force / model.bodies.mass[:, None]
        # I (w' - w) = h tau in the body frame, before the implicit gyroscopic step below
        body_ang_vel = body_ang_vel + h * math.quat_rotate_inverse(state.quat, torque) / model.bodies.inertia
    pos = state.pos + h * vel  # (22)
    body_ang_vel = implicit_gyroscopic(model.bodies.inertia, body_ang_vel, h)
    ang_vel = math.quat_rotate(state.quat, body_ang_vel)  # (20)
    quat = displaced_quat(state.quat, h * ang_vel)  # (24)
    return State(pos=pos, quat=quat, vel=vel, ang_vel=ang_vel)


def actuator_wrenches(model: Model, state: State, control: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """World force (N, 3) N and torque (N, 3) N m at the centres of mass from the torque actuators.

    Angular: tau = gear u n on b and -tau on a, n the normalised sum of the axis carried by a and
    by b. Linear (slider): F = gear u n on b (n carried by a) and -F on a at b's centre of mass,
    so the pair exerts no net moment and does no work but on the slider's travel. On hinge k of a
    universal or gimbal joint: tau = gear u g_k, g_k the gradient of that hinge's angle
    (`math.euler_angles`), so that the torque pair is the generalised force gear u on hinge k alone.
    Torques on a degree of freedom with armature are left out: they act through the joint's rotor
    row (`constraints.joints`), which moves bodies and rotor together.
    """
    structure = model.structure
    n = structure.num_bodies
    a, b = structure.torque_bodies.array[:, 0], structure.torque_bodies.array[:, 1]
    pos = jnp.concatenate([state.pos, jnp.zeros((1, 3), state.pos.dtype)])
    quat = jnp.concatenate([state.quat, math.quat_identity((1,)).astype(state.quat.dtype)])
    u = take(jnp.asarray(control, state.pos.dtype), structure.torque_control.array) * model.torques.gear
    if structure.torque_in_joint.array.size:  # these act through their joint's rotor row (armature)
        u = jnp.where(jnp.asarray(structure.torque_in_joint.array), 0.0, u)
    quat_a, quat_b = take(quat, a), take(quat, b)
    axis_a = math.quat_rotate(quat_a, model.torques.local_axis_a)
    axis_b = math.quat_rotate(quat_b, model.torques.local_axis_b)
    linear = jnp.asarray(structure.torque_linear.array)[:, None]
    turning, _ = math.safe_normalize(axis_a + axis_b)
    direction = jnp.where(linear, axis_a, turning)
    dof = structure.torque_dof.array
    if dof.size and (dof >= 0).any():  # hinges of universal and gimbal joints
        joint = structure.torque_joint.array
        axes_a = math.quat_rotate(quat_a[:, None], model.joints.local_axes_a[joint])
        axes_b = math.quat_rotate(quat_b[:, None], model.joints.local_axes_b[joint])
        _, gradients = math.euler_angles(axes_a, axes_b, structure.joint_kind.array[joint] == UNIVERSAL)
        on_hinge = take(gradients.reshape(-1, 3), 3 * np.arange(len(dof)) + np.maximum(dof, 0))
        direction = jnp.where(jnp.asarray(dof >= 0)[:, None], on_hinge, direction)
    push = u[:, None] * direction
    force_b = jnp.where(linear, push, 0.0)
    torque_b = jnp.where(linear, 0.0, push)
    torque_a = jnp.where(linear, -math.cross(take(pos, b) - take(pos, a), push), -push)
    force = segment_sum(jnp.concatenate([force_b, -force_b]), np.concatenate([b, a]), n + 1)
    torque = segment_sum(jnp.concatenate([torque_b, torque_a]), np.concatenate([b, a]), n + 1)
    return force[:n], torque[:n]


def implicit_gyroscopic(inertia: jnp.ndarray, ang_vel: jnp.ndarray, h: float) -> jnp.ndarray:
    """One Newton step on I (w' - w) + h w' x (I w') = 0, DBD (20) with no torque, body frame.

    inertia: (N, 3) principal moments; ang_vel: (N, 3) body-frame angular velocity.
    The Jacobian of the residual at w is I + h ([w]x I - [I w]x).
    """
    moment = inertia * ang_vel
    residual = h * math.cross(ang_vel, moment)
    # diag(I) as jnp.diag builds it, a select (no gather): as the product I * eye, XLA rounded the
    # sum below differently in two programs holding the same step (session 68).
    jacobian = jnp.vectorize(jnp.diag, signature="(3)->(3,3)")(inertia) + h * (
        math.skew(ang_vel) * inertia[..., None, :] - math.skew(moment)
    )
    return ang_vel - math.matvec(math.inverse3(jacobian), residual)


def displaced_quat(quat: jnp.ndarray, rotation: jnp.ndarray, renormalise: bool = True) -> jnp.ndarray:
    """exp(i rotation / 2) q, renormalised: how an angular displacement turns a body (39).

    renormalise=False: the product as it is, a unit quaternion to rounding where q is one. The
    sweeps evaluate their constraints at such poses many times a substep (`BodyPair.current_quats`)
    and skip the renormalisation there (Brax's humanoid and ant on CPU at batch 1, 16 and 256: a
    step 1.04-1.10x faster, `benchmarks/profile_step.py --paired 16`); the poses the bodies are
    moved to are renormalised."""
    turned = math.quat_multiply(math.quat_exp(rotation), quat)
    return math.quat_normalize(turned) if renormalise else turned


def world_inertia(model: Model, state: State) -> jnp.ndarray:
    """World-frame inertia of every body at its pose, (..., N, 3, 3): R I R^T."""
    rotation = math.quat_to_matrix(state.quat)
    return jnp.einsum("...nij,nj,...nkj->...nik", rotation, model.bodies.inertia, rotation)


def inverse_inertia(model: Model, predicted: State, h: float) -> jnp.ndarray:
    """World-frame inverse inertia of every body at the predicted pose, (N, 3, 3).

    With `velocity_dependent_inertia` this is the inverse of DBD (58),
    I~ = I - [I w h]x + I [w h]x, which stiffens fast-spinning bodies with non-uniform inertia.
    """
    rotation = math.quat_to_matrix(predicted.quat)
    inv_moments = 1.0 / model.bodies.inertia
    inv_world = jnp.einsum("nij,nj,nkj->nik", rotation, inv_moments, rotation)
    if not model.options.velocity_dependent_inertia:
        return inv_world
    world = world_inertia(model, predicted)
    spin = h * predicted.ang_vel
    momentum = jnp.einsum("nij,nj->ni", world, spin)
    effective = world - math.skew(momentum) + world @ math.skew(spin)
    return math.inverse3(effective)


def apply(predicted: State, displacement: jnp.ndarray, rotation: jnp.ndarray, h: float) -> State:
    """Move the predicted state by the solver's displacement, DBD (36)-(39).

    displacement: (N, 3) m, rotation: (N, 3) rad (axis-angle), both relative to the prediction.

    The angular velocity takes the rotation the body actually made, `math.shortest_rotation`:
    the summed linearised corrections can exceed pi where a joint gap is larger than a lever arm
    (tens of radians on a chain stretched to twice its length), yet exp(i rotation / 2) turns
    the body by at most pi. Read literally, (38) turned that excess into spin of thousands of
    rad/s, and energy.
    """
    return State(
        pos=predicted.pos + displacement,  # (37)
        quat=displaced_quat(predicted.quat, rotation),  # (39)
        vel=predicted.vel + displacement / h,  # (36)
        ang_vel=predicted.ang_vel + math.shortest_rotation(rotation) / h,  # (38)
    )
