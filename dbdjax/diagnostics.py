"""Quantities to check a simulation by: joint gaps, IK target errors, momentum, energy. Pure,
batch-friendly."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dbdjax import integrator, math
from dbdjax.constraints import joints, rows, targets
from dbdjax.constraints.rows import BodyPair
from dbdjax.model import PLANAR, SLIDER, Model, State


def joint_gaps(model: Model, state: State) -> jnp.ndarray:
    """Distance (m) between the two anchor points of every joint, (..., J).

    For a slider only the part across the axis counts (travel along it is free). The points are
    the solver's own (`rows.anchor_points`), from differences of like terms.
    """
    structure = model.structure
    if structure.num_joints == 0:
        return jnp.zeros(state.pos.shape[:-2] + (0,), state.pos.dtype)
    pad = [(0, 0)] * (state.pos.ndim - 2)
    pos = jnp.pad(state.pos, pad + [(0, 1), (0, 0)])  # the world: row N, at the origin
    quat = jnp.concatenate(
        [state.quat, jnp.broadcast_to(math.quat_identity(), state.quat.shape[:-2] + (1, 4))], axis=-2
    )
    a, b = structure.joint_body_a.array, structure.joint_body_b.array
    world = structure.num_bodies
    zero = jnp.zeros((), state.pos.dtype)
    pair = BodyPair(*([zero] * (len(BodyPair._fields) - 1)), jnp.zeros((4, 3), zero.dtype))._replace(
        origin_a=pos[..., a, :], origin_b=pos[..., b, :]
    )
    delta, _, _ = rows.anchor_points(
        pair, model.joints.local_anchor_a, model.joints.local_anchor_b, (a == world)[:, None], (b == world)[:, None],
        quat[..., a, :], quat[..., b, :],
    )  # fmt: skip
    axis = math.quat_rotate(quat[..., a, :], model.joints.local_axis_a)
    slider = jnp.asarray(structure.joint_kind.array == SLIDER)
    planar = jnp.asarray(structure.joint_kind.array == PLANAR)
    delta = delta - jnp.where(slider[:, None], math.dot(delta, axis)[..., None] * axis, 0.0)
    delta = jnp.where(planar[:, None], math.dot(delta, axis)[..., None] * axis, delta)
    return math.safe_norm(delta)


def ik_target_errors(model: Model, state: State, control: jnp.ndarray | None = None) -> jnp.ndarray:
    """Distance (m) from each IK target's point to where `control` puts the target, (..., T).

    control: (num_controls,) as passed to `step` (None: zero offsets, the targets at rest)."""
    ik = model.ik_targets
    if ik is None or not len(model.structure.ik_target_bodies.array):
        return jnp.zeros(state.pos.shape[:-2] + (0,), state.pos.dtype)
    body = model.structure.ik_target_bodies.array[:, 0]
    goal = targets.goals(model.structure, ik, control, state.pos.dtype)
    point = state.pos[..., body, :] + math.quat_rotate(state.quat[..., body, :], ik.local_point)
    return math.safe_norm(point - goal)


def centre_of_mass(model: Model, state: State) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Position (m) and velocity (m/s) of the whole model's centre of mass, each (..., 3)."""
    total = jnp.sum(model.bodies.mass)
    position = jnp.sum(model.bodies.mass[:, None] * state.pos, axis=-2) / total
    return position, linear_momentum(model, state) / total


def linear_momentum(model: Model, state: State) -> jnp.ndarray:
    """Total linear momentum (kg m/s), (..., 3)."""
    return jnp.sum(model.bodies.mass[:, None] * state.vel, axis=-2)


def angular_momentum(model: Model, state: State) -> jnp.ndarray:
    """Total angular momentum about the world origin (kg m^2/s), (..., 3)."""
    spin = math.matvec(integrator.world_inertia(model, state), state.ang_vel)
    orbital = math.cross(state.pos, model.bodies.mass[:, None] * state.vel)
    return jnp.sum(spin + orbital, axis=-2)


def energy(model: Model, state: State) -> jnp.ndarray:
    """Kinetic plus gravitational potential energy (J), (...): the bodies' and the joints' rotors'
    (armature, `rotor_energy`), as MuJoCo counts its joint-space inertia."""
    mass = model.bodies.mass
    kinetic = 0.5 * jnp.sum(mass * math.dot(state.vel, state.vel), axis=-1)
    spin = math.matvec(integrator.world_inertia(model, state), state.ang_vel)
    kinetic = kinetic + 0.5 * jnp.sum(math.dot(state.ang_vel, spin), axis=-1)
    potential = -jnp.sum(mass * math.dot(state.pos, model.gravity), axis=-1)
    return kinetic + potential + rotor_energy(model, state)


def rotor_energy(model: Model, state: State) -> jnp.ndarray:
    """The joints' rotors' kinetic energy (J), (...): 1/2 armature qdot^2 per degree of freedom with
    armature (`joints.rotor_energy`). It can be most of a model's energy: Brax's ant (armature 1
    kg m^2 on legs of 0.003 kg m^2) landing under random controls had 159 J in its rotors and 6.4 J
    in its bodies."""
    batch = state.pos.shape[:-2]
    flat = State(*(x.reshape((-1,) + x.shape[len(batch) :]) for x in (state.pos, state.quat, state.vel, state.ang_vel)))
    # (impulses dropped: energy reads poses and velocities only)
    return jax.vmap(lambda s: joints.rotor_energy(model, s))(flat).reshape(batch)
