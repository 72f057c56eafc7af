"""MJCF import: MuJoCo's own compiler reads the file, we convert its compiled model.

`load_mjcf(path_or_xml, **finalize_kwargs)` parses and compiles with the `mujoco` package (an
optional dependency: `pip install mujoco` or `pip install 'dbdjax[mjcf]'`), which resolves
defaults, includes, `fromto` geoms, angle units and inertias; there is no XML parser here. The
compiled `MjModel` at qpos0 is turned into maximal coordinates with the public `ModelBuilder`:

bodies   one rigid body per MuJoCo body at its centre of mass (xipos) with its inertial frame
         (ximat), mass and principal moments (body_inertia). Bodies without joints are fused into
         their parent first (MuJoCo's `fusestatic`); a jointless body MuJoCo keeps (one another
         element names) is welded to its parent with a fixed joint.
joints   hinge -> hinge, slide -> slider, ball -> ball, free -> nothing. Limits are MuJoCo's
         range (radians, whatever the compiler's angle unit) minus qpos0, since our angles count
         from the build pose, which is qpos0; hinge ranges are clipped to [-pi, pi] (our angle
         wraps there). A ball range r becomes cone_limit r and twist limits (-r, r) about the
         bone (MuJoCo limits the total rotation angle; ours bounds swing and twist separately,
         a superset). Several joints on one body:
           2 or 3 mutually perpendicular hinges through one point (the humanoid's abdomen, hips,
             shoulders) -> a universal (2) or gimbal (3) joint: MuJoCo's successive hinges, the
             relative rotation R(axis1, q1) R(axis2, q2) R(axis3, q3) with each hinge's own
             range as a per-hinge limit, exact. The gimbal's middle angle lives in [-pi/2, pi/2]
             (the decomposition is singular at +-pi/2, where axes 1 and 3 align): a middle range
             wider than that is clipped to it, an approximation.
           3 perpendicular hinges that each have a position actuator (dbdjax/assets/ragdoll.xml's
             way of writing a ball joint with a ball drive) -> one ball joint with that drive
             (`_ball_drive`), as below: an approximation of MuJoCo's successive hinges.
           2 or 3 hinges through one point at other angles -> one ball joint: the twist axis is
             the last hinge's axis with that hinge's range as twist limits, and the cone limit
             is the largest |bound| of the other hinges (an approximation: a 2-hinge body gains
             a third rotational freedom and the box of ranges becomes a cone).
           slide, slide, hinge with the hinge axis normal to both slides (the planar roots of
             hopper, walker2d, half_cheetah) -> a planar joint, exact.
           anything else -> ValueError naming the body.
         Joint stiffness (toward springref) and damping become implicit spring rows of the joint
         (`ModelBuilder.add_joint_spring`): exact per hinge on hinge, universal and gimbal joints,
         isotropic (the mean of the dofs) on ball joints and on hinges merged into a ball; on
         slides, an implicit passive force along the axis (`ModelBuilder.add_force`). Planar
         roots refuse them (none of the Brax models has any).
         Armature (rotor inertia on a dof) -> `ModelBuilder.add_armature`: MuJoCo's kinetic energy
         1/2 armature qdot^2 on the joint's own coordinate, as one implicit row per degree of
         freedom (hinge, slide, ball, each hinge of a universal / gimbal joint, a planar joint's
         rotation), which holds whatever the parent does; a motor on such a dof acts through that
         row, so it accelerates bodies and rotor together as in MuJoCo. Not mapped (ignored): the
         armature of free joints, of a planar joint's slides and of hinges merged into a ball.
         Limits are soft as MuJoCo's: solreflimit (timeconst, dampratio) -> `set_limit_softness`,
         a limit row past its bound is a spring and damper per unit effective mass (the joint's
         armature included, as in MuJoCo's joint-space mass) with natural
         frequency 1 / (timeconst dampratio) (timeconst at least 2 dt, MuJoCo's refsafe), so a pose
         built past a limit (the humanoid's knees, the ant's ankles at qpos0) eases back in about
         timeconst instead of being snapped back within one step (`_limit_softness`; solimp's
         impedance below 1 is left out). `load_mjcf(..., soft_limits=False)`: rigid limits.
         Joint solref/solimp (the joint points themselves) and margin are ignored: joints are rigid.
geoms    sphere, capsule, box -> add_sphere/capsule/box in the body's inertial frame; plane ->
         add_plane (world only: normal = the geom's z axis, offset = normal . pos). friction[0]
         -> friction (condim 1: frictionless), contype/conaffinity kept, <exclude> pairs ->
         exclude_collision. Contacts with the world are allowed for bodies jointed to the world
         (MuJoCo's parent filter skips the world). Other geom types raise a ValueError naming the
         geom, unless contype = conaffinity = 0 (visual only; MuJoCo already counted its mass).
actuator motor (gain fixed, no bias) -> add_torque(gear * gain): control = MuJoCo's ctrl. On a
         hinge of a universal / gimbal joint it is the generalised force on that hinge alone.
         position (kp, kv; gear 1, hinge) -> add_drive(stiffness=kp, damping=kv, max_torque from
         a symmetric forcerange): control = target angle - qpos0 (= MuJoCo's ctrl when ref = 0).
         Three position actuators on the hinges of a merged ball joint (about the parent's frame
         axes x, y, z, equal gains) -> its ball drive, the three targets as a rotation vector
         (`_ball_drive`; dbdjax/assets/ragdoll.xml uses this).
         ctrlrange -> `Model.control_range`; `step` does not clip (MuJoCo clips when ctrllimited).
options  timestep -> finalize dt (finalize_kwargs override), gravity -> ModelBuilder gravity.
         MuJoCo's integrator choice, solver settings, iterations and contact parameters are not
         used (the finalize kwargs choose ours).
refused  tendons, equality constraints, explicit contact pairs, flexes, plugins, mocap bodies,
         gravity compensation, fluid forces (density, viscosity, wind), joint frictionloss,
         free-joint damping/stiffness, actuators other than the above: a ValueError naming the
         element. Ignored (no effect on dynamics): sites, sensors, cameras, lights, materials,
         textures, keyframes, custom numerics.
"""

from __future__ import annotations

import math
import os
from typing import Any

import jax.numpy as jnp
import numpy as np

from dbdjax import host_math
from dbdjax import math as dmath
from dbdjax.builder import ModelBuilder
from dbdjax.model import WORLD, Model

_SAME_POINT = 1e-6  # m: joints of one body closer than this share an anchor


def _import_mujoco():
    try:
        import mujoco
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "dbdjax.load_mjcf needs the `mujoco` package (MuJoCo's compiler reads the MJCF): "
            "pip install 'mujoco>=3.2'  (or pip install 'dbdjax[mjcf]')"
        ) from error
    return mujoco


def _spec(mujoco, path_or_xml):
    if isinstance(path_or_xml, os.PathLike) or (
        isinstance(path_or_xml, str) and not path_or_xml.lstrip().startswith("<")
    ):
        path = os.fspath(path_or_xml)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"load_mjcf: no MJCF file at {path!r} (give a path or an XML string)")
        return mujoco.MjSpec.from_file(path)
    if not isinstance(path_or_xml, str):
        raise TypeError(f"load_mjcf: expected a path or an XML string, got {type(path_or_xml).__name__}")
    return mujoco.MjSpec.from_string(path_or_xml)


def _label(m, kind: str, index: int) -> str:
    name = getattr(m, kind)(index).name
    return f"{kind} {name!r}" if name else f"{kind} #{index}"


def _quat_of(mujoco, matrix: np.ndarray) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.asarray(matrix, dtype=np.float64).reshape(9))
    return quat


def _check_supported(mujoco, m) -> None:
    """Refuse, naming the element, what would change the dynamics and has no equivalent here."""
    for kind, count in (("tendon", m.ntendon), ("equality", m.neq), ("pair", m.npair)):
        if count:
            what = {"tendon": "tendons", "equality": "equality constraints", "pair": "explicit contact pairs"}[kind]
            raise ValueError(f"load_mjcf: MJCF {_label(m, kind, 0)}: {what} are not supported")
    if m.nflex:
        raise ValueError("load_mjcf: MJCF flex (deformable) elements are not supported")
    if m.nplugin:
        raise ValueError("load_mjcf: MJCF engine plugins are not supported")
    for i in range(m.nbody):
        if m.body_mocapid[i] >= 0:
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'body', i)} is a mocap body; mocap bodies are not supported")
        if m.body_gravcomp[i] != 0.0:
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'body', i)}: gravcomp is not supported")
    if m.opt.density != 0.0 or m.opt.viscosity != 0.0 or np.any(m.opt.wind != 0.0):
        raise ValueError("load_mjcf: MJCF option density / viscosity / wind (fluid forces) are not supported")
    for j in range(m.njnt):
        dofs = range(m.jnt_dofadr[j], m.jnt_dofadr[j] + _dof_count(mujoco, m.jnt_type[j]))
        if any(m.dof_frictionloss[d] != 0.0 for d in dofs):
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: frictionloss is not supported")


def _dof_count(mujoco, joint_type) -> int:
    return {mujoco.mjtJoint.mjJNT_FREE: 6, mujoco.mjtJoint.mjJNT_BALL: 3}.get(joint_type, 1)


# ------------------------------------------------------------------------- passive slide forces
# MuJoCo's stiffness and damping of a slide joint as an `add_force` element, solved implicitly
# (forces.py): F = -(k (s - s0) + d s_dot) n on b, -F on a at b's centre of mass. (Hinge and ball
# stiffness/damping use the joint's own drive row instead, `ModelBuilder.add_joint_spring`.)


def _linear_passive(pos_a, quat_a, vel_a, ang_vel_a, pos_b, vel_b, params):
    axis = dmath.quat_rotate(quat_a, params["axis"])
    lever = pos_b - pos_a
    travel = dmath.dot(axis, lever - dmath.quat_rotate(quat_a, params["anchor"]))
    speed = dmath.dot(axis, vel_b - vel_a - dmath.cross(ang_vel_a, lever))
    force = -(params["stiffness"] * (travel - params["offset"]) + params["damping"] * speed) * axis
    return force, lever


def linear_passive_pair(pos, quat, vel, ang_vel, params):
    """Passive slide force between bodies (a, b): (force (2, 3), torque (2, 3)), world frame."""
    force, lever = _linear_passive(pos[0], quat[0], vel[0], ang_vel[0], pos[1], vel[1], params)
    zero = jnp.zeros_like(force)
    return jnp.stack([-force, force]), jnp.stack([-dmath.cross(lever, force), zero])


def linear_passive_world(pos, quat, vel, ang_vel, params):
    """Passive slide force on a body jointed to the world: (force (1, 3), torque (1, 3))."""
    zero = jnp.zeros_like(pos[0])
    identity = dmath.quat_identity().astype(quat.dtype)
    force, _ = _linear_passive(zero, identity, zero, zero, pos[0], vel[0], params)
    return force[None], jnp.zeros_like(pos)


# ------------------------------------------------------------------------------------ loading
def mujoco_model(path_or_xml: str | os.PathLike):
    """MuJoCo's compiled `MjModel` of an MJCF file path or XML string, as `load_mjcf` reads it:
    jointless bodies fused into their parents (MuJoCo's `fusestatic`: fewer bodies, no weld gaps),
    so that its body i + 1 is dbdjax body i. For stepping MuJoCo beside dbdjax from one state
    (`dbdjax.mujoco_state`)."""
    mujoco = _import_mujoco()
    spec = _spec(mujoco, path_or_xml)
    spec.compiler.fusestatic = True
    return spec.compile()


def load_mjcf(path_or_xml: str | os.PathLike, soft_limits: bool = True, **finalize_kwargs: Any) -> Model:
    """Build a `Model` from an MJCF file path or XML string (see this module's docstring for
    what maps and how). finalize_kwargs go to `ModelBuilder.finalize` (dt defaults to the
    MJCF timestep). soft_limits: joint limits as soft as the file's solreflimit makes them in
    MuJoCo (False: rigid). Raises ValueError naming the element for what cannot be simulated.

    Controls: one entry per MJCF actuator, in MuJoCo's order (motor: ctrl, a torque of gear *
    ctrl; position: the target angle from qpos0). `model.control_range` holds ctrlrange.
    """
    mujoco = _import_mujoco()
    m = mujoco_model(path_or_xml)
    _check_supported(mujoco, m)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)  # poses at qpos0

    gravity = np.array(m.opt.gravity)
    if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        gravity = np.zeros(3)
    builder = ModelBuilder(gravity=gravity)

    body_index = {0: WORLD}
    body_quat = {0: np.array([1.0, 0.0, 0.0, 0.0])}
    for i in range(1, m.nbody):
        quat = _quat_of(mujoco, d.ximat[i])
        body_quat[i] = quat
        body_index[i] = builder.add_body(pos=d.xipos[i], quat=quat, mass=float(m.body_mass[i]),
                                         inertia=m.body_inertia[i], name=m.body(i).name or None)  # fmt: skip

    joint_of = {}  # MuJoCo joint -> (our joint, how it was mapped)
    positioned = {int(m.actuator_trnid[a, 0]) for a in range(m.nu) if _is_position(mujoco, m, a)}
    for i in range(1, m.nbody):
        _add_body_joints(mujoco, m, d, builder, i, body_index, body_quat, joint_of, positioned)

    for g in range(m.ngeom):
        _add_geom(mujoco, m, d, builder, g, body_index, body_quat)
    for e in range(m.nexclude):
        signature = int(m.exclude_signature[e])
        builder.exclude_collision(body_index[signature >> 16], body_index[signature & 0xFFFF])

    if soft_limits:
        dt = float(finalize_kwargs.get("dt", m.opt.timestep))
        refsafe = not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE
        softened = set()
        for j in range(m.njnt):
            ours = joint_of[j][0] if j in joint_of else None
            # (a range of a full turn or more maps to no limit at all: nothing to soften)
            if m.jnt_limited[j] and ours is not None and ours not in softened and builder.joint_limited(ours):
                builder.set_limit_softness(ours, *_limit_softness(m, j, dt, refsafe))
                softened.add(ours)

    ball_drives: dict[int, int] = {}  # MuJoCo actuators already mapped onto a ball drive -> its control entry
    for a in range(m.nu):
        if a not in ball_drives:
            _add_actuator(mujoco, m, d, builder, a, joint_of, body_quat, ball_drives)

    return builder.finalize(**{"dt": float(m.opt.timestep), **finalize_kwargs})


def _is_position(mujoco, m, a: int) -> bool:
    """A position actuator: fixed gain kp, affine bias (0, -kp, -kv), no activation dynamics."""
    bias = m.actuator_biasprm[a, :3]
    return (m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
            and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE and bias[0] == 0.0
            and bias[1] == -m.actuator_gainprm[a, 0])  # fmt: skip


def _spring(m, builder: ModelBuilder, ours: int, joints: list[int], dofs: list[int], positioned: set[int],
            per_axis: bool = False) -> None:  # fmt: skip
    """MuJoCo hinge/ball stiffness and damping -> the joint's drive row with a fixed target: per
    hinge on universal and gimbal joints (`per_axis`, exact), else the mean over a ball's dofs or
    the hinges merged into a ball (exact for one hinge, an approximation otherwise). A hinge with
    a position actuator gets its damping in that actuator's drive instead."""
    stiffness = float(np.mean([m.jnt_stiffness[j] for j in joints]))
    damping = float(np.mean([m.dof_damping[k] for k in dofs]))
    for j in joints:
        adr, width = m.jnt_qposadr[j], 4 if m.jnt_type[j] == 1 else 1  # mjJNT_BALL = 1
        if m.jnt_stiffness[j] != 0.0 and not np.allclose(m.qpos_spring[adr : adr + width], m.qpos0[adr : adr + width]):
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: a spring reference (springref) other than "
                             "the joint's ref is not supported")  # fmt: skip
    if set(joints) & positioned:
        if stiffness != 0.0:
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', joints[0])}: joint stiffness together with a "
                             "position actuator is not supported")  # fmt: skip
        return
    if per_axis and any(
        m.jnt_stiffness[j] != 0.0 or m.dof_damping[k] != 0.0 for j, k in zip(joints, dofs, strict=True)
    ):
        builder.add_joint_spring(ours, stiffness=[float(m.jnt_stiffness[j]) for j in joints],
                                 damping=[float(m.dof_damping[k]) for k in dofs])  # fmt: skip
    elif not per_axis and (stiffness != 0.0 or damping != 0.0):
        builder.add_joint_spring(ours, stiffness=stiffness, damping=damping)


def _armature(m, builder: ModelBuilder, ours: int, joints: list[int]) -> None:
    """MuJoCo joint armature -> the joint's rotor rows (`ModelBuilder.add_armature`): one number per
    hinge of a universal / gimbal joint, else the joint's one (a ball's three dofs share it)."""
    values = [float(m.dof_armature[m.jnt_dofadr[j]]) for j in joints]
    if any(values):
        builder.add_armature(ours, values if len(values) > 1 else values[0])


def _add_body_joints(mujoco, m, d, builder: ModelBuilder, i: int, body_index, body_quat, joint_of, positioned) -> None:
    J = mujoco.mjtJoint
    parent, child = body_index[int(m.body_parentid[i])], body_index[i]
    joints = list(range(m.body_jntadr[i], m.body_jntadr[i] + m.body_jntnum[i]))
    types = [int(m.jnt_type[j]) for j in joints]
    names = [m.joint(j).name or f"joint #{j}" for j in joints]
    body = _label(m, "body", i)
    if parent == WORLD and joints:
        builder.allow_collision(WORLD, child)  # MuJoCo's parent filter does not apply to the world

    def limits(j: int, clip: bool):
        if not m.jnt_limited[j]:
            return None
        low, high = np.asarray(m.jnt_range[j], dtype=np.float64) - m.qpos0[m.jnt_qposadr[j]]
        if clip:
            low, high = max(low, -math.pi), min(high, math.pi)
            if low <= -math.pi and high >= math.pi:
                return None
        return float(low), float(high)

    if not joints:  # kept by fusestatic (another element names it): welded to the parent
        builder.add_fixed_joint(parent, child, anchor=d.xpos[i], name=f"{m.body(i).name or i} weld")
        return
    if int(J.mjJNT_FREE) in types:
        if len(joints) > 1:
            raise ValueError(f"load_mjcf: MJCF {body}: a free joint combined with other joints is not supported")
        j = joints[0]
        if m.jnt_stiffness[j] != 0.0 or np.any(m.dof_damping[m.jnt_dofadr[j] : m.jnt_dofadr[j] + 6] != 0.0):
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: free-joint stiffness/damping is not supported")
        return
    anchors = np.array([d.xanchor[j] for j in joints])
    axes = np.array([d.xaxis[j] for j in joints])
    if len(joints) > 1 and np.max(np.linalg.norm(anchors - anchors[0], axis=1)) > _SAME_POINT:
        raise ValueError(f"load_mjcf: MJCF {body}: joints {names} do not share one anchor point; stacked joints at "
                         "different points are not supported")  # fmt: skip
    anchor = anchors[0]
    parent_quat = body_quat[int(m.body_parentid[i])]

    if len(joints) == 1:
        j, kind = joints[0], types[0]
        if kind == J.mjJNT_HINGE:
            ours = builder.add_hinge_joint(parent, child, anchor, axes[0], limits(j, clip=True), name=names[0])
            joint_of[j] = (ours, "hinge", axes[0])
            _spring(m, builder, ours, [j], [m.jnt_dofadr[j]], positioned)
            _armature(m, builder, ours, [j])
        elif kind == J.mjJNT_SLIDE:
            ours = builder.add_slider_joint(parent, child, anchor, axes[0], limits(j, clip=False), name=names[0])
            joint_of[j] = (ours, "slide", axes[0])
            _passive_linear(m, d, builder, parent, child, j, axes[0], parent_quat, i)
            _armature(m, builder, ours, [j])
        elif kind == J.mjJNT_BALL:
            cone = None
            if m.jnt_limited[j] and m.jnt_range[j][1] < math.pi:
                cone = float(m.jnt_range[j][1])
            twist = None if cone is None else (-cone, cone)
            ours = builder.add_ball_joint(parent, child, anchor, cone_limit=cone, twist_limits=twist, name=names[0])
            joint_of[j] = (ours, "ball", None)
            _spring(m, builder, ours, [j], [m.jnt_dofadr[j] + k for k in range(3)], positioned)
            _armature(m, builder, ours, [j])
        else:  # pragma: no cover - MuJoCo has no other joint type
            raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: unknown joint type {kind}")
        return

    hinges = [j for j, t in zip(joints, types, strict=True) if t == J.mjJNT_HINGE]
    slides = [j for j, t in zip(joints, types, strict=True) if t == J.mjJNT_SLIDE]
    units = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    perpendicular = all(abs(units[i] @ units[k]) < 1e-6 for i in range(len(joints)) for k in range(i + 1, len(joints)))
    # Three hinges each driven by a position actuator: the ball-drive convention of
    # dbdjax/assets/ragdoll.xml (a ball joint with a rotation-vector target), kept as a ball.
    position_driven = len(joints) == 3 and all(
        any(int(m.actuator_trnid[a, 0]) == j and m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
            and _is_position(mujoco, m, a) for a in range(m.nu))
        for j in joints
    )  # fmt: skip
    if len(hinges) == len(joints) and len(joints) <= 3 and perpendicular and not position_driven:
        # Perpendicular hinges through one point -> a universal (2) or gimbal (3) joint, exact.
        bounds = [limits(j, clip=True) for j in joints]
        if len(joints) == 3 and bounds[1] is not None:  # the gimbal's middle angle lives in [-pi/2, pi/2]
            bounds[1] = (max(bounds[1][0], -math.pi / 2), min(bounds[1][1], math.pi / 2))
        add = builder.add_universal_joint if len(joints) == 2 else builder.add_gimbal_joint
        ours = add(parent, child, anchor, axes, bounds, name="+".join(names))
        for k, j in enumerate(joints):
            joint_of[j] = (ours, "hinge of a multi-hinge body", k)
        _spring(m, builder, ours, joints, [m.jnt_dofadr[j] for j in joints], positioned, per_axis=True)
        _armature(m, builder, ours, joints)
        return
    if len(hinges) == len(joints) and len(joints) <= 3:
        # Hinges through one point at other angles -> a ball joint (approximation: module docstring).
        last = joints[-1]
        twist = limits(last, clip=True)
        others = [limits(j, clip=True) for j in joints[:-1]]
        cone = None
        if all(o is not None for o in others):
            cone = min(max(max(abs(lo), abs(hi)) for lo, hi in others), math.pi)
            cone = max(cone, 1e-3)
        ours = builder.add_ball_joint(parent, child, anchor, cone_limit=cone, twist_limits=twist,
                                      twist_axis=axes[-1], name="+".join(names))  # fmt: skip
        for j, axis in zip(joints, axes, strict=True):
            joint_of[j] = (ours, "merged", axis)
        _spring(m, builder, ours, joints, [m.jnt_dofadr[j] for j in joints], positioned)
        return
    if len(joints) == 3 and len(hinges) == 1 and len(slides) == 2:
        normal = d.xaxis[hinges[0]]
        s1, s2 = d.xaxis[slides[0]], d.xaxis[slides[1]]
        if max(abs(normal @ s1), abs(normal @ s2), abs(s1 @ s2)) < 1e-6:
            for j in joints:
                if m.jnt_limited[j] or m.jnt_stiffness[j] != 0.0 or m.dof_damping[m.jnt_dofadr[j]] != 0.0:
                    raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: limits, stiffness and damping on "
                                     "the joints of a planar (slide, slide, hinge) body are not supported")  # fmt: skip
            ours = builder.add_planar_joint(parent, child, anchor, normal, name="+".join(names))
            for j in joints:
                joint_of[j] = (ours, "planar", None)
            _armature(m, builder, ours, hinges)  # the rotation's; the slides' is not mapped (module docstring)
            return
    kinds = [J(t).name.removeprefix("mjJNT_").lower() for t in types]
    raise ValueError(f"load_mjcf: MJCF {body}: the joint combination {list(zip(names, kinds, strict=True))} is not "
                     "supported (one joint; 2-3 hinges through one point; or slide, slide and a hinge normal "
                     "to both)")  # fmt: skip


def _limit_softness(m, j: int, dt: float, refsafe: bool) -> tuple[float, float]:
    """(time constant s, damping ratio) of MJCF joint j's limit (solreflimit, solimplimit).

    MuJoCo holds a violated constraint to a1 + d (b v + k r) = (1 - d) a0 with b = 2 / (dmax tc),
    k = d / (dmax^2 tc^2 zeta^2): past the impedance's width (d = dmax) the violation r moves as a
    damped oscillator of natural frequency 1 / (tc zeta) and damping ratio zeta, plus the fraction
    1 - d of the unconstrained acceleration a0, which is left out here (5% with the default solimp).
    tc is at least 2 dt unless refsafe is disabled. solref's direct form (-stiffness, -damping)
    maps through the same oscillator: d k = stiffness / dmax, d b = damping."""
    first, second = (float(v) for v in m.jnt_solref[j])
    if first > 0.0:
        return (max(first, 2.0 * dt) if refsafe else first), second
    stiffness, damping = -first / float(m.jnt_solimp[j][1]), -second
    if not (stiffness > 0.0 and damping > 0.0):
        raise ValueError(f"load_mjcf: MJCF {_label(m, 'joint', j)}: solreflimit {tuple(m.jnt_solref[j])} has no "
                         "stiffness or no damping; a limit needs both")  # fmt: skip
    time_constant = 2.0 / damping
    return time_constant, damping / (2.0 * math.sqrt(stiffness))


def _passive_linear(m, d, builder, parent, child, j, world_axis, parent_quat, i) -> None:
    stiffness, damping = float(m.jnt_stiffness[j]), float(m.dof_damping[m.jnt_dofadr[j]])
    if stiffness == 0.0 and damping == 0.0:
        return
    parent_pos = np.zeros(3) if parent == WORLD else d.xipos[int(m.body_parentid[i])]
    params = {
        "axis": host_math.rotate(parent_quat, world_axis, inverse=True),
        "anchor": host_math.rotate(parent_quat, d.xipos[i] - parent_pos, inverse=True),
        "stiffness": np.asarray(stiffness),
        "damping": np.asarray(damping),
        "offset": np.asarray(m.qpos_spring[m.jnt_qposadr[j]] - m.qpos0[m.jnt_qposadr[j]]),
    }
    name = f"passive {m.joint(j).name}"
    if parent == WORLD:
        builder.add_force((child,), linear_passive_world, params, name=name)
    else:
        builder.add_force((parent, child), linear_passive_pair, params, name=name)


def _add_geom(mujoco, m, d, builder: ModelBuilder, g: int, body_index, body_quat) -> None:
    G = mujoco.mjtGeom
    kind, body = int(m.geom_type[g]), int(m.geom_bodyid[g])
    label = _label(m, "geom", g)
    contype, conaffinity = int(m.geom_contype[g]), int(m.geom_conaffinity[g])
    if kind not in (int(G.mjGEOM_PLANE), int(G.mjGEOM_SPHERE), int(G.mjGEOM_CAPSULE), int(G.mjGEOM_BOX)):
        if contype == 0 and conaffinity == 0:
            return  # visual only: its mass is already in the body's inertia
        type_name = G(kind).name.removeprefix("mjGEOM_").lower()
        raise ValueError(
            f"load_mjcf: MJCF {label} on {_label(m, 'body', body)}: geom type {type_name!r} is not supported "
            "(sphere, capsule, box, plane; or make it visual with contype=conaffinity=0)"
        )
    material = {
        "friction": 0.0 if m.geom_condim[g] == 1 else float(m.geom_friction[g, 0]),
        "contype": contype,
        "conaffinity": conaffinity,
        "name": m.geom(g).name or None,
    }
    size = m.geom_size[g]
    geom_quat = _quat_of(mujoco, d.geom_xmat[g])
    if kind == G.mjGEOM_PLANE:
        if body != 0:
            raise ValueError(f"load_mjcf: MJCF {label}: a plane must belong to the world body, not "
                             f"{_label(m, 'body', body)}")  # fmt: skip
        normal = np.asarray(d.geom_xmat[g]).reshape(3, 3)[:, 2]
        builder.add_plane(normal=normal, offset=float(normal @ d.geom_xpos[g]), **material)
        return
    if body == 0:
        pos, quat = np.array(d.geom_xpos[g]), geom_quat
    else:  # in the body's inertial frame, the frame we gave add_body
        pos = host_math.rotate(body_quat[body], d.geom_xpos[g] - d.xipos[body], inverse=True)
        quat = host_math.multiply(host_math.conjugate(body_quat[body]), geom_quat)
    ours = body_index[body]
    if kind == G.mjGEOM_SPHERE:
        builder.add_sphere(ours, radius=float(size[0]), pos=pos, **material)
    elif kind == G.mjGEOM_CAPSULE:
        builder.add_capsule(ours, radius=float(size[0]), half_length=float(size[1]), pos=pos, quat=quat, **material)
    else:
        builder.add_box(ours, half_extents=size[:3], pos=pos, quat=quat, **material)


def _ball_drive(mujoco, m, builder: ModelBuilder, a: int, ours: int, joint_of, body_quat, ball_drives) -> slice:
    """Position actuators on the three hinges of a merged ball joint -> its ball drive (3 controls).

    Supported when actuators a, a+1, a+2 are position actuators with gear 1 and equal kp, kv and
    (symmetric) forcerange on the ball's hinges in their order, and those hinges turn about the
    parent body's frame axes x, y, z: the drive target is then a rotation vector in the parent's
    frame whose components are the three hinge targets (exact for one hinge at a time, the same to
    first order otherwise: MuJoCo composes the hinges in sequence). The forcerange bounds the
    drive's torque vector as a whole. Returns the slice of the drive's 3 control entries.
    """
    label = _label(m, "actuator", a)
    hinges = sorted(j for j, (o, how, _) in joint_of.items() if o == ours and how == "merged")
    actuators = list(range(a, a + len(hinges)))
    ok = len(hinges) == 3 and actuators[-1] < m.nu
    ok = ok and all(int(m.actuator_trnid[b, 0]) == j and m.actuator_trntype[b] == mujoco.mjtTrn.mjTRN_JOINT
                    and _is_position(mujoco, m, b) and float(m.actuator_gear[b, 0]) == 1.0
                    for b, j in zip(actuators, hinges, strict=True))  # fmt: skip
    if ok:
        parent_quat = body_quat[int(m.body_parentid[int(m.jnt_bodyid[hinges[0]])])]
        local = np.array([host_math.rotate(parent_quat, joint_of[j][2], inverse=True) for j in hinges])
        ok = np.allclose(local, np.eye(3), atol=1e-6)
    gains = {(float(m.actuator_gainprm[b, 0]), float(m.actuator_biasprm[b, 2]), float(m.dof_damping[m.jnt_dofadr[j]]),
              bool(m.actuator_forcelimited[b]), tuple(m.actuator_forcerange[b]))
             for b, j in zip(actuators, hinges, strict=True)} if ok else set()  # fmt: skip
    if not ok or len(gains) != 1:
        raise ValueError(f"load_mjcf: MJCF {label}: position actuators on a merged ball joint are supported as one "
                         "per hinge (3, consecutive, in the hinges' order, gear 1, equal kp, kv and forcerange) "
                         "on hinges about the parent body's frame axes x, y, z")  # fmt: skip
    kp, bias_kv, damping, limited, (low, high) = gains.pop()
    max_torque = None
    if limited:
        if low != -high:
            raise ValueError(f"load_mjcf: MJCF {label}: an asymmetric forcerange is not supported")
        max_torque = float(high)
    controls = builder.add_drive(ours, stiffness=kp, damping=-bias_kv + damping, max_torque=max_torque,
                                 name=m.actuator(a).name or None)  # fmt: skip
    for k, (b, j) in enumerate(zip(actuators, hinges, strict=True)):
        ball_drives[b] = controls.start + k
        if m.actuator_ctrllimited[b]:
            offset = float(m.qpos0[m.jnt_qposadr[j]])
            low, high = m.actuator_ctrlrange[b]
            builder.set_control_range(controls.start + k, float(low) - offset, float(high) - offset)
    return controls


def _add_actuator(mujoco, m, d, builder: ModelBuilder, a: int, joint_of, body_quat, ball_drives) -> None:
    label = _label(m, "actuator", a)
    if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
        raise ValueError(f"load_mjcf: MJCF {label}: only joint transmissions are supported, not "
                         f"{mujoco.mjtTrn(m.actuator_trntype[a]).name}")  # fmt: skip
    if m.actuator_dyntype[a] != mujoco.mjtDyn.mjDYN_NONE or m.actuator_gaintype[a] != mujoco.mjtGain.mjGAIN_FIXED:
        raise ValueError(f"load_mjcf: MJCF {label}: actuator dynamics or gain types other than a fixed gain "
                         "(motor, position) are not supported")  # fmt: skip
    j = int(m.actuator_trnid[a, 0])
    ours, how, axis = joint_of.get(j, (None, "free", None))
    gear, gain = float(m.actuator_gear[a, 0]), float(m.actuator_gainprm[a, 0])
    bias = m.actuator_biasprm[a, :3]
    target = f"{_label(m, 'joint', j)} ({how})"
    if m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE:  # motor: force = gain * ctrl * gear
        if m.actuator_forcelimited[a]:
            raise ValueError(f"load_mjcf: MJCF {label}: forcerange on a motor is not supported")
        if how not in ("hinge", "slide", "merged", "hinge of a multi-hinge body"):
            raise ValueError(f"load_mjcf: MJCF {label}: a motor on {target} is not supported")
        euler = how == "hinge of a multi-hinge body"  # the generalised force on that hinge alone
        controls = builder.add_torque(ours, gear=gear * gain, axis=axis if how == "merged" else None,
                                      dof=axis if euler else None, name=m.actuator(a).name or None)  # fmt: skip
        offset = 0.0
    elif _is_position(mujoco, m, a) and how == "merged":
        _ball_drive(mujoco, m, builder, a, ours, joint_of, body_quat, ball_drives)
        return
    elif _is_position(mujoco, m, a):
        # position: force = kp (ctrl - q) - kv q_dot, plus the joint's own damping (see _spring)
        kp, kv = gain, -float(bias[2]) + float(m.dof_damping[m.jnt_dofadr[j]])
        if how != "hinge" or gear != 1.0:
            raise ValueError(f"load_mjcf: MJCF {label}: position actuators are supported on single hinges with "
                             f"gear 1, not on {target} with gear {gear}")  # fmt: skip
        max_torque = None
        if m.actuator_forcelimited[a]:
            low, high = m.actuator_forcerange[a]
            if low != -high:
                raise ValueError(f"load_mjcf: MJCF {label}: an asymmetric forcerange is not supported")
            max_torque = float(high)
        controls = builder.add_drive(ours, stiffness=kp, damping=kv, max_torque=max_torque,
                                     name=m.actuator(a).name or None)  # fmt: skip
        offset = float(m.qpos0[m.jnt_qposadr[j]])
    else:
        raise ValueError(f"load_mjcf: MJCF {label}: only motor and position actuators are supported")
    if m.actuator_ctrllimited[a]:
        low, high = m.actuator_ctrlrange[a]
        builder.set_control_range(controls, float(low) - offset, float(high) - offset)
