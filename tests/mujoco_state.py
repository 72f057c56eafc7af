"""A dbdjax state of a model loaded from MJCF, carried into MuJoCo's generalized coordinates, so
that MuJoCo itself can step from the very state dbdjax reached (tests/test_tree.py).

Covers the models whose joints are one free root and single hinges (Brax's ant): each dbdjax body
is a MuJoCo body with a joint, its jointless children fused into it, at its centre of mass with
its inertial frame (`dbdjax.mjcf`). A dbdjax state's joints may be open by a little, so its body
velocities need not be any qvel's: qvel is the least-squares fit weighted by the bodies' masses and
inertias and the joints' rotors (the kinetic energy of what the joints cannot carry, made least).
"""

from __future__ import annotations

import mujoco
import numpy as np

import dbdjax as dbd


def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def _conjugate(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(v, float), np.asarray(q, float))
    return out


def _jointed(m: mujoco.MjModel, ours: list[int], body: int) -> int:
    """The MuJoCo body with a joint that `body` is fused into (itself, or its nearest such ancestor)."""
    while body not in ours:
        body = m.body_parentid[body]
    return body


def to_mujoco(xml: str, model: dbd.Model, state: dbd.State) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """(MjModel of `xml`, MjData at the pose and velocities of `state`), an unbatched state of
    `model = dbd.load_mjcf(xml)`. Raises ValueError for joints other than a free root and hinges."""
    m = mujoco.MjModel.from_xml_path(str(xml))
    kinds = [int(k) for k in m.jnt_type]
    if kinds[:1] != [mujoco.mjtJoint.mjJNT_FREE] or any(k != mujoco.mjtJoint.mjJNT_HINGE for k in kinds[1:]):
        raise ValueError(f"to_mujoco: {xml}: only a free root with hinges below it is covered, not joint types {kinds}")
    pos, quat, vel, ang_vel = (np.asarray(x, float) for x in (state.pos, state.quat, state.vel, state.ang_vel))
    rest = dbd.init(model)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)  # qpos0: dbdjax's build pose
    ours = [1] + [int(m.jnt_bodyid[j]) for j in range(1, m.njnt)]  # the MuJoCo body of each dbdjax body
    if len(ours) != len(pos):
        raise ValueError(f"to_mujoco: {xml}: {len(ours)} jointed MuJoCo bodies against {len(pos)} dbdjax bodies")
    # Each dbdjax body's frame in its MuJoCo body's frame, fixed: (rotation, centre of mass).
    frame = [_product(_conjugate(d.xquat[b]), np.asarray(rest.quat[k], float)) for k, b in enumerate(ours)]
    centre = [_rotate(_conjugate(d.xquat[b]), np.asarray(rest.pos[k], float) - d.xpos[b]) for k, b in enumerate(ours)]

    def body_quat(k):  # the MuJoCo body's world orientation from dbdjax body k's
        return _product(quat[k], _conjugate(frame[k]))

    qpos = m.qpos0.copy()
    qpos[3:7] = body_quat(0)
    qpos[0:3] = pos[0] - _rotate(qpos[3:7], centre[0])
    for j in range(1, m.njnt):  # parents first: each hinge's angle from its parent's pose so far
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        b = m.jnt_bodyid[j]
        relative = _product(_conjugate(d.xquat[m.body_parentid[b]]), body_quat(ours.index(b)))
        turn = _product(_conjugate(m.body_quat[b]), relative)  # the hinge's own rotation
        qpos[m.jnt_qposadr[j]] = 2.0 * np.arctan2(np.dot(turn[1:], m.jnt_axis[j]), turn[0])
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    rows, targets = [], []
    inertia = np.asarray(dbd.integrator.world_inertia(model, state), float)
    for k, b in enumerate(ours):
        linear, angular = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, linear, angular, pos[k], b)
        root = np.linalg.cholesky(inertia[k]).T  # |root w|^2 = w . I w
        rows += [np.sqrt(float(model.bodies.mass[k])) * linear, root @ angular]
        targets += [np.sqrt(float(model.bodies.mass[k])) * vel[k], root @ ang_vel[k]]
    for j in range(1, m.njnt):  # each rotor's own energy, 1/2 armature qdot^2 (`dbd.diagnostics.rotor_energy`)
        b, dof = m.jnt_bodyid[j], m.jnt_dofadr[j]
        k, parent = ours.index(b), ours.index(_jointed(m, ours, m.body_parentid[b]))
        axis = _rotate(d.xquat[b], m.jnt_axis[j])
        weight = np.sqrt(m.dof_armature[dof])
        rows.append(weight * np.eye(m.nv)[dof][None])
        targets.append(weight * np.dot(axis, ang_vel[k] - ang_vel[parent])[None])
    d.qvel[:] = np.linalg.lstsq(np.concatenate(rows), np.concatenate(targets), rcond=None)[0]
    mujoco.mj_forward(m, d)
    return m, d


def energies(m: mujoco.MjModel, d: mujoco.MjData) -> tuple[float, float]:
    """(total, rotors) J: kinetic energy in joint space (armature included) plus gravity's
    potential, and the armature's share 1/2 sum armature qdot^2, as `dbd.diagnostics.energy` and
    `rotor_energy` count them."""
    mujoco.mj_forward(m, d)
    momentum = np.zeros(m.nv)
    mujoco.mj_mulM(m, d, momentum, d.qvel)
    potential = -np.sum(m.body_mass[:, None] * m.opt.gravity[None] * d.xipos)
    return 0.5 * float(d.qvel @ momentum) + float(potential), 0.5 * float(np.sum(m.dof_armature * d.qvel**2))
