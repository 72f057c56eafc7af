"""States carried between dbdjax and MuJoCo, for a model loaded from MJCF (`load_mjcf`).

`load_mjcf` builds one dbdjax body per body of MuJoCo's compiled model with its jointless bodies
fused into their parents (`mujoco_model`: MuJoCo body i + 1 is dbdjax body i), at its centre
of mass in its inertial frame. So a MuJoCo state gives a dbdjax state body by body
(`state_from_mujoco`: to start from a keyframe or any qpos), and MuJoCo can step from a state
dbdjax reached (`state_to_mujoco`: to compare the two engines from one state).

dbdjax -> MuJoCo is a fit. dbdjax's joints may be open by a little, and its bodies' velocities may
carry what the joints would not let through, so then no qpos, qvel reproduces them exactly. qpos
is the least-squares fit of the bodies' poses (Gauss-Newton from qpos0) and qvel of their
velocities, both weighted by the bodies' masses and inertias, qvel by the joints' rotors too: the
kinetic energy of the part the joints cannot carry, made least. On a state the joints carry (from
`state_from_mujoco`, or with closed joints) the fit is exact to rounding.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np

from dbdjax import host_math, pipeline
from dbdjax.mjcf import _import_mujoco, _quat_of
from dbdjax.model import Model, State

# The pose fit stops once a Gauss-Newton step moves no coordinate by more than this (m or rad).
_CONVERGED = 1e-10
_MAX_ITERATIONS = 50


def state_from_mujoco(model: Model, m, d) -> State:
    """The dbdjax state of MuJoCo's `d` (its qpos, qvel) on `m = mujoco_model(xml)`, for
    `model = load_mjcf(xml)`: each body's centre of mass (N, 3) m, inertial frame (N, 4), velocity
    (N, 3) m/s and angular velocity (N, 3) rad/s, world frame. Runs `mj_forward` on `d`."""
    mujoco = _import_mujoco()
    _check_bodies(model, m, "state_from_mujoco")
    mujoco.mj_forward(m, d)
    velocity = np.zeros((m.nbody - 1, 6))  # (angular, linear) at each centre of mass, world frame
    for body in range(1, m.nbody):
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, body, velocity[body - 1], 0)
    quat = np.stack([_quat_of(mujoco, d.ximat[body]) for body in range(1, m.nbody)])
    # (from `init`, so that the impulse solver's impulses start cold as they do there)
    return dataclasses.replace(pipeline.init(model), pos=jnp.asarray(d.xipos[1:]), quat=jnp.asarray(quat),
                               vel=jnp.asarray(velocity[:, 3:]), ang_vel=jnp.asarray(velocity[:, :3]))  # fmt: skip


def state_to_mujoco(model: Model, state: State, m, d=None):
    """MuJoCo's `MjData` on `m = mujoco_model(xml)` at the pose and velocities of one (unbatched)
    dbdjax state of `model = load_mjcf(xml)`: a new MjData unless `d` is given, `mj_forward` run on
    it. qpos and qvel are least-squares fits (module docstring); hinge angles come out within half
    a turn of qpos0, where the fit starts. Raises ValueError for a batched state or an MjModel with
    other bodies."""
    mujoco = _import_mujoco()
    _check_bodies(model, m, "state_to_mujoco")
    pos, quat, vel, ang_vel = (np.asarray(x, np.float64) for x in (state.pos, state.quat, state.vel, state.ang_vel))
    if pos.shape != (model.num_bodies, 3):
        raise ValueError(f"state_to_mujoco: one state at a time: pos has shape {pos.shape}, not "
                         f"({model.num_bodies}, 3); index the batch first")  # fmt: skip
    d = mujoco.MjData(m) if d is None else d
    mass = np.sqrt(np.maximum(np.asarray(model.bodies.mass, np.float64), 0.0))[:, None]  # (N, 1)
    # |root w|^2 = w . I w with I a body's world inertia R diag(I_0) R^T: root = diag(sqrt I_0) R^T
    principal = np.sqrt(np.maximum(np.asarray(model.bodies.inertia, np.float64), 0.0))
    inertia_root = principal[:, :, None] * np.stack([host_math.to_matrix(q).T for q in quat])  # (N, 3, 3)

    def weighted(linear, angular):
        """The fit's rows (6 N, ...) of per-body linear and angular parts (N, 3, ...): Jacobians
        (..., = nv) or errors and velocities (no trailing axis)."""
        scale = mass.reshape((-1, 1) + (1,) * (linear.ndim - 2))
        rows = np.concatenate([scale * linear, np.einsum("nij,nj...->ni...", inertia_root, angular)], axis=1)
        return rows.reshape((-1,) + rows.shape[2:])

    d.qpos[:] = _free_bodies_placed(mujoco, m, m.qpos0.copy(), pos, quat)
    for _ in range(_MAX_ITERATIONS):  # Gauss-Newton on the weighted pose errors
        linear, angular = _jacobians(mujoco, m, d)
        turn = np.stack([_rotation_vector(mujoco, quat[i], _quat_of(mujoco, d.ximat[i + 1])) for i in range(len(quat))])
        step = np.linalg.lstsq(weighted(linear, angular), weighted(pos - d.xipos[1:], turn), rcond=None)[0]
        mujoco.mj_integratePos(m, d.qpos, step, 1.0)
        if np.max(np.abs(step)) < _CONVERGED:
            break
    else:
        last = float(np.max(np.abs(step)))
        warnings.warn(f"state_to_mujoco: the pose fit did not converge in {_MAX_ITERATIONS} Gauss-Newton steps (the "
                      f"last moved a coordinate by {last:.1e}): qpos is where it stopped", stacklevel=2)  # fmt: skip
    linear, angular = _jacobians(mujoco, m, d)
    rotor_rows, rotor_rates = _rotors(mujoco, m, linear, angular, pos, vel, ang_vel)
    rows = np.concatenate([weighted(linear, angular), rotor_rows])
    d.qvel[:] = np.linalg.lstsq(rows, np.concatenate([weighted(vel, ang_vel), rotor_rates]), rcond=None)[0]
    mujoco.mj_forward(m, d)
    return d


def _check_bodies(model: Model, m, caller: str) -> None:
    if m.nbody - 1 != model.num_bodies:
        raise ValueError(f"{caller}: the MjModel has {m.nbody - 1} bodies besides the world, the dbdjax model "
                         f"{model.num_bodies}: give `dbdjax.mujoco_model` of the file `load_mjcf` read")  # fmt: skip


def _free_bodies_placed(mujoco, m, qpos: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """qpos with each free joint's body put where the state has it (its frame from its inertial
    frame: MuJoCo's body_ipos, body_iquat), so that the fit starts there."""
    for joint in np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        body, address = m.jnt_bodyid[joint], m.jnt_qposadr[joint]
        frame = host_math.multiply(quat[body - 1], host_math.conjugate(m.body_iquat[body]))
        qpos[address : address + 3] = pos[body - 1] - host_math.rotate(frame, m.body_ipos[body])
        qpos[address + 3 : address + 7] = frame if frame[0] >= 0.0 else -frame  # the same turn, w >= 0
    return qpos


def _jacobians(mujoco, m, d) -> tuple[np.ndarray, np.ndarray]:
    """At d.qpos: (nbody - 1, 3, nv) each body's centre-of-mass translational and rotational
    Jacobians (poses computed first)."""
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    linear, angular = np.zeros((m.nbody - 1, 3, m.nv)), np.zeros((m.nbody - 1, 3, m.nv))
    for body in range(1, m.nbody):
        mujoco.mj_jacBodyCom(m, d, linear[body - 1], angular[body - 1], body)
    return linear, angular


def _rotation_vector(mujoco, target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The world-frame rotation vector that turns orientation `current` into `target`."""
    vector = np.zeros(3)
    mujoco.mju_quat2Vel(vector, host_math.multiply(target, host_math.conjugate(current)), 1.0)
    return vector


def _rotors(mujoco, m, linear, angular, pos, vel, ang_vel) -> tuple[np.ndarray, np.ndarray]:
    """The rotors' rows of the velocity fit, (K, nv) and (K,): sqrt(armature) qdot_k = sqrt(armature)
    r_k for each of the K degrees of freedom with armature, r_k its rate as the state's bodies give
    it (the rates `diagnostics.rotor_energy` counts): a body's rotational dofs from its angular
    velocity relative to its parent, its slides from its linear velocity relative to its parent's
    motion. Free joints are left out, as `load_mjcf` leaves their armature out."""
    free, slide = mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_SLIDE
    kind = m.jnt_type[m.dof_jntid]  # (nv,)
    rows, rates = [], []
    for body in range(1, m.nbody):
        own = np.flatnonzero(m.dof_bodyid == body)
        if not np.any((m.dof_armature[own] > 0.0) & (kind[own] != free)):
            continue
        parent = m.body_parentid[body]
        relative_spin, relative_drift = ang_vel[body - 1], vel[body - 1]
        if parent:  # the parent's motion carried to this body's centre
            arm = pos[body - 1] - pos[parent - 1]
            relative_spin = relative_spin - ang_vel[parent - 1]
            relative_drift = relative_drift - vel[parent - 1] - np.cross(ang_vel[parent - 1], arm)
        rate = np.zeros(m.nv)
        turning, sliding = own[kind[own] != slide], own[kind[own] == slide]
        if len(turning):  # a body's own dofs: its Jacobians' columns there are relative to its parent
            rate[turning] = np.linalg.lstsq(angular[body - 1][:, turning], relative_spin, rcond=None)[0]
        if len(sliding):
            turned = linear[body - 1][:, turning] @ rate[turning]
            rate[sliding] = np.linalg.lstsq(linear[body - 1][:, sliding], relative_drift - turned, rcond=None)[0]
        for k in own[(m.dof_armature[own] > 0.0) & (kind[own] != free)]:
            weight = np.sqrt(m.dof_armature[k])
            rows.append(np.zeros(m.nv))
            rows[-1][k] = weight
            rates.append(weight * rate[k])
    return np.reshape(rows, (-1, m.nv)), np.asarray(rates)
