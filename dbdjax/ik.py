"""Inverse kinematics of a joint chain by displacement-based dynamics (DBD section 11).

A `Chain` is N rigid links in series, anchored to a base frame (the world unless given). Joint k
turns link k relative to link k - 1 (the base for k = 0) about its pivot. A hinge joint has one
angle about an axis fixed in the parent; a ball joint has three numbers, the rotation vector of
the joint rotation in the parent's frame. `angles` is one flat vector: one entry per hinge, three
per ball, in chain order (`Chain.num_dofs` long). The pose of link k is

    Q_k = Q_{k-1} exp(r_k) rest_k,      pivot_k = origin_{k-1} + Q_{k-1} parent_anchor_k,
    origin_k = pivot_k - Q_k child_anchor_k,

with r_k = theta_k axis_k for a hinge and the rotation vector itself for a ball. This is the
engine's joint convention (q_b = q_a X rest, `constraints/joints.py`), so angles from
`Chain.from_model` are the engine's hinge angles and can be used as drive targets.

`solve` moves the end effector (a point fixed in the last link) onto a target. When link k turns
by a small rotation vector omega_k about its pivot, the end effector moves by omega_k x s_k, s_k
the vector from pivot k to the end effector (Fig. 9), so the Jacobian block of the constraint
x_end - x_T = 0 is -[s_k]x and J^T d lambda = s_k x d lambda. Every update is (135)-(136):

    mu         = [J M^-1 J^T + alpha 1]^-1 = [-sum_k [s_k]x M_k^-1 [s_k]x + alpha 1]^-1   (135)
    d lambda   = -mu delta x                                                              (136)
    d theta_k  = M_k^-1 (s_k x d lambda)                                                  (136)

evaluated at the latest pose (the non-linear update of 4.1; ball links turn by the quaternion
q(d theta) q(theta)). For a hinge the generalised coordinate is the angle about the world axis
a_k: its Jacobian is a_k . (s_k x .), its inertia a_k^T M_k a_k. constraint="distance" uses the
scalar constraint c = |x_end - x_T| of (131) with the row (134), (s_k x n)^T, instead of the three
rows of the point (slower: the scalar row moves the end effector along J M^-1 J^T n, which is
not n, so each update also pushes it sideways).

method "dbd": M_k is the inertia of everything beyond joint k about its pivot, by the parallel
axis theorem (133), so the update is the displacement of least kinetic energy (it minimises
dtheta^T M dtheta) and a chain bends where it is light (Fig. 10). method "pinv": M_k = 1, the
pseudo-inverse (126)-(130), which minimises |dtheta|^2. The regularisation alpha of (135), 4.3,
keeps mu finite where J M^-1 J^T is singular (a straight chain cannot move its end along
itself). inertia="per_frame" computes the M_k once, at the pose a `solve` call starts from (one
call is one frame), instead of at every update (the paragraph after (136)).

lambda starts from 0 at every update. Carried over, as in (136) within one frame, its -alpha
lambda term makes alpha a compliance: the update then converges to c = -alpha lambda, not to the
target (residuals of order 1 cm on a 1.5 m chain at the default alpha). Restarted, the
update is the damped least-squares step of (49) in the metric M, which converges to the target,
or, for an unreachable one, to the pose closest to it: the chain straight toward it.

Two safeguards keep the linearisation honest: the error one update aims to remove is clamped to
`max_step` (Buss's ClampMag), and a backtracking line search tries the step at lengths 1, 1/2,
1/4, ... at once and keeps the one that ends closest (the step is a descent direction of
|delta x|^2, so a short enough one always helps). Without them, an update near the singular
straight pose overshoots into a cycle.

Hinge limits are kept by a projected step: a joint at a limit whose step would push it further
out is taken out of J M^-1 J^T for that iteration (so the free joints take the whole
correction), and every hinge angle is clamped to its limits after the step.

It is a local method: a chain folded back on itself, or held at its limits, can end in a local
minimum of |delta x| (where the projected gradient is zero) short of a target that another pose
reaches; a straight chain pointing exactly away from a target is a stationary point it does not
leave. The mass weighting also makes "dbd" slow to straighten the heavy root of a chain toward an
unreachable target (hundreds of updates on an 8-link chain, where "pinv" needs tens).

Everything is a pure function of float arrays with static loop counts (`lax.scan`): `solve`
jits, vmaps over angles/targets/chains, and differentiates with `jax.grad` w.r.t. the target, the
start angles and the float leaves of `Chain`.
"""

from __future__ import annotations

import dataclasses
import functools
import math as pymath
from collections import deque
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import host_math, math
from dbdjax.model import BALL, FIXED, HINGE, JOINT_KIND_NAMES, WORLD, Model

JOINT_KINDS = ("hinge", "ball")
METHODS = ("dbd", "pinv")
INERTIA_MODES = ("per_iteration", "per_frame")
CONSTRAINTS = ("point", "distance")

# Default regularisation, relative to the chain's own J M^-1 J^T scale (see `reference_alpha`).
DEFAULT_RELATIVE_ALPHA = 1e-3
# Default max_step, relative to the chain's reach.
DEFAULT_RELATIVE_STEP = 0.2


@dataclasses.dataclass(frozen=True)
class Chain:
    """N links in series from a base frame; float fields are pytree leaves, the rest static.

    base_pos: (3,) m, origin of the base frame (the frame joint 0's parent anchor is given in).
    base_quat: (4,) base frame orientation (w, x, y, z).
    parent_anchor: (N, 3) m, pivot of joint k in the frame of link k - 1 (the base for k = 0).
    child_anchor: (N, 3) m, the same pivot in the frame of link k.
    axis: (N, 3) unit hinge axis in the parent's frame (unused for ball joints).
    rest: (N, 4) joint rotation at zero angle: Q_k = Q_{k-1} exp(r_k) rest_k.
    mass: (N,) kg. com: (N, 3) m, centre of mass of link k in its frame.
    inertia: (N, 3, 3) kg m^2, about the centre of mass, in the link frame.
    lower, upper: (N,) rad, hinge limits (used where `limited`).
    tip: (3,) m, the end effector in the frame of the last link.
    kinds: ("hinge" | "ball", ...) per joint. limited: (bool, ...) per joint. names: per joint.
    """

    base_pos: jnp.ndarray
    base_quat: jnp.ndarray
    parent_anchor: jnp.ndarray
    child_anchor: jnp.ndarray
    axis: jnp.ndarray
    rest: jnp.ndarray
    mass: jnp.ndarray
    com: jnp.ndarray
    inertia: jnp.ndarray
    lower: jnp.ndarray
    upper: jnp.ndarray
    tip: jnp.ndarray
    kinds: tuple[str, ...]
    limited: tuple[bool, ...]
    names: tuple[str, ...]

    @property
    def num_links(self) -> int:
        return len(self.kinds)

    @property
    def num_dofs(self) -> int:
        """Length of the flat `angles` vector: 1 per hinge, 3 per ball."""
        return sum(1 if kind == "hinge" else 3 for kind in self.kinds)

    @property
    def dof_offsets(self) -> tuple[int, ...]:
        """Index of joint k's first entry in `angles`."""
        offsets, position = [], 0
        for kind in self.kinds:
            offsets.append(position)
            position += 1 if kind == "hinge" else 3
        return tuple(offsets)

    def zero_angles(self, dtype=None) -> jnp.ndarray:
        """(num_dofs,) zeros: the pose the chain was described in."""
        return jnp.zeros((self.num_dofs,), dtype=dtype if dtype is not None else self.mass.dtype)

    def astype(self, dtype) -> Chain:
        """The same chain with every float leaf cast to `dtype` (e.g. jnp.float32)."""
        return jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf, dtype=dtype), self)

    # ------------------------------------------------------------------------ constructors
    @classmethod
    def from_links(
        cls,
        lengths: Sequence[float] | np.ndarray,
        masses: float | Sequence[float] | None = None,
        inertias: Any = None,
        axes: str | Sequence[float] | Sequence[Sequence[float]] = "alternate",
        limits: Any = None,
        kinds: str | Sequence[str] = "hinge",
        base_pos: Sequence[float] = (0.0, 0.0, 0.0),
        base_quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
    ) -> Chain:
        """A straight chain of N links along the base frame's +x at zero angles.

        lengths: (N,) m, pivot-to-pivot (the last one pivot to end effector).
        masses: kg, None (1 kg each), one number, or (N,).
        inertias: kg m^2 about each link's centre (at its middle): None (a slender rod of radius
          length / 20: m l^2 / 12 across, m r^2 / 2 along x), (N,) or (N, 3) principal moments
          about the link's x, y, z, or (N, 3, 3).
        axes: hinge axes in the parent frame: "alternate" (z, y, z, y, ...: yaw then pitch, a
          chain that reaches in 3D), one (3,) axis for all (a planar chain), or (N, 3).
        limits: None, one (lower, upper) for every hinge, or N entries each None or (lo, hi);
          radians in [-pi, pi].
        kinds: "hinge", "ball", or one per joint. Ball joints take no axis and no limits.
        """
        lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
        n = lengths.shape[0]
        if n == 0:
            raise ValueError("Chain.from_links: at least one link is needed")
        if not np.all(np.isfinite(lengths)) or np.any(lengths <= 0.0):
            raise ValueError(f"Chain.from_links: lengths must be positive and finite, got {lengths.tolist()}")
        kinds = (kinds,) * n if isinstance(kinds, str) else tuple(kinds)
        if len(kinds) != n or any(kind not in JOINT_KINDS for kind in kinds):
            raise ValueError(f"Chain.from_links: kinds must be {JOINT_KINDS} (one or {n} of them), got {kinds!r}")

        masses = np.broadcast_to(np.asarray(1.0 if masses is None else masses, dtype=np.float64), (n,)).copy()
        if not np.all(np.isfinite(masses)) or np.any(masses <= 0.0):
            raise ValueError(f"Chain.from_links: masses must be positive, got {masses.tolist()}")
        if inertias is None:
            radius = lengths / 20.0
            moments = np.stack([masses * radius**2 / 2, masses * lengths**2 / 12, masses * lengths**2 / 12], -1)
            inertia = np.stack([np.diag(m) for m in moments])
        else:
            inertia = np.asarray(inertias, dtype=np.float64)
            if inertia.shape == (n,):
                inertia = np.stack([np.eye(3) * i for i in inertia])
            elif inertia.shape == (n, 3):
                inertia = np.stack([np.diag(m) for m in inertia])
            elif inertia.shape != (n, 3, 3):
                raise ValueError(f"Chain.from_links: inertias must be (N,), (N, 3) or (N, 3, 3), got {inertia.shape}")
        for k in range(n):
            _check_inertia(inertia[k], f"Chain.from_links: link {k}")

        if isinstance(axes, str):
            if axes != "alternate":
                raise ValueError(f"Chain.from_links: axes must be 'alternate', one axis or N axes, got {axes!r}")
            axis = np.array([[0.0, 0.0, 1.0] if k % 2 == 0 else [0.0, 1.0, 0.0] for k in range(n)])
        else:
            axis = np.asarray(axes, dtype=np.float64)
            axis = np.broadcast_to(axis, (n, 3)).copy() if axis.shape == (3,) else axis
            if axis.shape != (n, 3):
                raise ValueError(f"Chain.from_links: axes must be (3,) or ({n}, 3), got {axis.shape}")
        norms = np.linalg.norm(axis, axis=-1)
        for k in range(n):
            if kinds[k] == "hinge" and not norms[k] > 1e-9:
                raise ValueError(f"Chain.from_links: hinge {k} has a zero axis")
        axis = axis / np.where(norms > 1e-9, norms, 1.0)[:, None]

        lower, upper, limited = _limit_rows(limits, kinds, "Chain.from_links")
        half = np.stack([lengths / 2, np.zeros(n), np.zeros(n)], -1)
        parent_anchor = np.concatenate([np.zeros((1, 3)), 2 * half[:-1]], axis=0)
        base_quat = np.asarray(base_quat, dtype=np.float64)
        return cls(
            base_pos=jnp.asarray(np.asarray(base_pos, dtype=np.float64)),
            base_quat=jnp.asarray(base_quat / np.linalg.norm(base_quat)),
            parent_anchor=jnp.asarray(parent_anchor),
            child_anchor=jnp.zeros((n, 3)),  # the link frame sits at its pivot
            axis=jnp.asarray(axis),
            rest=jnp.asarray(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))),
            mass=jnp.asarray(masses),
            com=jnp.asarray(half),
            inertia=jnp.asarray(inertia),
            lower=jnp.asarray(lower),
            upper=jnp.asarray(upper),
            tip=jnp.asarray(2 * half[-1]),
            kinds=kinds,
            limited=limited,
            names=tuple(f"{kind} joint {k}" for k, kind in enumerate(kinds)),
        )

    @classmethod
    def from_model(cls, model: Model, end_body: int, tip: Sequence[float] = (0.0, 0.0, 0.0)) -> Chain:
        """The chain of joints from the world to `end_body` in a dbdjax `Model`.

        The path is found in the joint graph (a joint may be crossed from either side). Hinge and
        unlimited ball joints on it become the chain's joints (with the engine's angle
        convention: angle 0 is the built pose, hinge limits are the model's); fixed joints weld
        their bodies into the link before them. Every body that a path joint moves and that is
        not on the path (a branch, a welded body) is merged, rigid at its built pose, into the
        last link on its way from the world, so the DBD inertia (133) sees the whole sub-tree.
        tip: the end effector in `end_body`'s frame, m from its centre of mass.

        Raises ValueError naming the joint for a slider or a limited ball joint on the path, and
        for an end body that no joint path connects to the world or a loop of joints.
        """
        structure = model.structure
        n_bodies = structure.num_bodies
        if not isinstance(end_body, (int, np.integer)) or not 0 <= end_body < n_bodies:
            raise ValueError(f"Chain.from_model: end_body {end_body!r} is not a body index (0..{n_bodies - 1})")
        body_a = [WORLD if b == n_bodies else int(b) for b in structure.joint_body_a.array]
        body_b = [WORLD if b == n_bodies else int(b) for b in structure.joint_body_b.array]
        names = structure.joint_names
        kinds = [int(k) for k in structure.joint_kind.array]

        # Breadth-first tree from the world: parent joint of every body that joints reach.
        incident: dict[int, list[int]] = {}
        for j in range(structure.num_joints):
            incident.setdefault(body_a[j], []).append(j)
            incident.setdefault(body_b[j], []).append(j)
        parent_joint: dict[int, int | None] = {WORLD: None}
        queue, used = deque([WORLD]), set()
        while queue:
            body = queue.popleft()
            for j in incident.get(body, []):
                if j in used:
                    continue
                used.add(j)
                other = body_b[j] if body_a[j] == body else body_a[j]
                if other in parent_joint:
                    raise ValueError(
                        f"Chain.from_model: joint {names[j]!r} closes a loop; only a tree of joints forms a chain"
                    )
                parent_joint[other] = j
                queue.append(other)
        if end_body not in parent_joint:
            raise ValueError(
                f"Chain.from_model: body {end_body} ({structure.body_names[end_body]!r}) is not connected "
                "to the world by joints"
            )

        def route(body: int) -> list[tuple[int, int]]:
            """(joint, child body) pairs from the world down to `body`."""
            steps = []
            while body != WORLD:
                j = parent_joint[body]
                steps.append((j, body))
                body = body_a[j] if body_b[j] == body else body_b[j]
            return steps[::-1]

        path = route(end_body)
        moving = []  # (joint, child body) of the chain's joints, in order
        for j, child in path:
            if kinds[j] == HINGE or (kinds[j] == BALL and not _ball_limited(structure, j)):
                moving.append((j, child))
            elif kinds[j] == BALL:
                raise ValueError(
                    f"Chain.from_model: ball joint {names[j]!r} has cone or twist limits, which the IK chain "
                    "cannot express (only unlimited ball joints)"
                )
            elif kinds[j] != FIXED:
                raise ValueError(
                    f"Chain.from_model: joint {names[j]!r} is a {JOINT_KIND_NAMES[kinds[j]]} joint; the IK chain "
                    "takes hinge, unlimited ball and fixed joints"
                )
        if not moving:
            raise ValueError(f"Chain.from_model: no hinge or ball joint between the world and body {end_body}")

        pos0 = np.asarray(model.bodies.initial_pos, dtype=np.float64)
        quat0 = np.asarray(model.bodies.initial_quat, dtype=np.float64)
        joints = model.joints
        anchor_a = np.asarray(joints.local_anchor_a, dtype=np.float64)
        anchor_b = np.asarray(joints.local_anchor_b, dtype=np.float64)
        axis_a = np.asarray(joints.local_axis_a, dtype=np.float64)
        axis_b = np.asarray(joints.local_axis_b, dtype=np.float64)
        rest = np.asarray(joints.rest_rotation, dtype=np.float64)
        lower = np.asarray(joints.lower, dtype=np.float64)
        upper = np.asarray(joints.upper, dtype=np.float64)
        identity = np.array([1.0, 0.0, 0.0, 0.0])

        def frame(body: int) -> tuple[np.ndarray, np.ndarray]:
            return (np.zeros(3), identity) if body == WORLD else (pos0[body], quat0[body])

        # Link k's frame is the frame of the body right after chain joint k; the base is the world.
        link_body = [child for _, child in moving]
        rows = {key: [] for key in ("parent_anchor", "child_anchor", "axis", "rest", "lower", "upper")}
        chain_kinds, chain_limited, chain_names = [], [], []
        previous = WORLD
        for j, child in moving:
            parent_side = body_b[j] if body_a[j] == child else body_a[j]
            forward = body_b[j] == child  # crossed from a to b
            p_pos, p_quat = frame(parent_side)
            f_pos, f_quat = frame(previous)  # the parent link's frame
            if forward:  # q_b = q_a exp(theta u_a) rest
                local_anchor, local_axis, joint_rest, child_anchor = anchor_a[j], axis_a[j], rest[j], anchor_b[j]
            else:  # q_a = q_b exp(theta (-u_b)) rest^-1: the same angle, seen from b
                local_anchor, local_axis, child_anchor = anchor_b[j], -axis_b[j], anchor_a[j]
                joint_rest = host_math.conjugate(rest[j])
            # The joint's parent body may be welded to the link frame: W = Q_link^-1 q_parent.
            weld = host_math.multiply(host_math.conjugate(f_quat), p_quat)
            pivot_world = p_pos + host_math.rotate(p_quat, local_anchor)
            rows["parent_anchor"].append(host_math.rotate(host_math.conjugate(f_quat), pivot_world - f_pos))
            rows["axis"].append(host_math.rotate(weld, local_axis))
            rows["rest"].append(host_math.multiply(weld, joint_rest))
            rows["child_anchor"].append(child_anchor)
            is_hinge = kinds[j] == HINGE
            has_limits = bool(structure.joint_has_limits.array[j]) and is_hinge
            rows["lower"].append(lower[j] if has_limits else -pymath.pi)
            rows["upper"].append(upper[j] if has_limits else pymath.pi)
            chain_kinds.append("hinge" if is_hinge else "ball")
            chain_limited.append(has_limits)
            chain_names.append(names[j])
            previous = child

        # Mass properties: every body moved by chain joint k (and by no later one) is part of link k.
        chain_joints = [j for j, _ in moving]
        n = len(moving)
        mass = np.zeros(n)
        first_moment = np.zeros((n, 3))
        about_origin = np.zeros((n, 3, 3))  # inertia about the link frame's origin, link frame
        body_inertia = np.asarray(model.bodies.inertia, dtype=np.float64)
        body_mass = np.asarray(model.bodies.mass, dtype=np.float64)
        for body in range(n_bodies):
            if body not in parent_joint:
                continue
            on_route = [chain_joints.index(j) for j, _ in route(body) if j in chain_joints]
            if not on_route:
                continue  # not moved by the chain
            k = on_route[-1]
            l_pos, l_quat = frame(link_body[k])
            r = host_math.rotate(host_math.conjugate(l_quat), pos0[body] - l_pos)
            rotation = host_math.to_matrix(host_math.multiply(host_math.conjugate(l_quat), quat0[body]))
            mass[k] += body_mass[body]
            first_moment[k] += body_mass[body] * r
            own = rotation @ np.diag(body_inertia[body]) @ rotation.T
            about_origin[k] += own + body_mass[body] * host_math.parallel_axis(r)
        com = first_moment / mass[:, None]
        shift = np.stack([host_math.parallel_axis(c) for c in com])
        inertia = about_origin - mass[:, None, None] * shift  # parallel axes
        for k in range(n):
            _check_inertia(inertia[k], f"Chain.from_model: link of joint {chain_names[k]!r}")

        # The base frame: the world, shifted to the first pivot so that the chain is solved in
        # coordinates relative to its root (precise far from the origin).
        root = rows["parent_anchor"][0]
        parent_anchor = np.stack(rows["parent_anchor"])
        parent_anchor[0] = 0.0
        end_pos, end_quat = frame(end_body)
        l_pos, l_quat = frame(link_body[-1])
        tip_world = end_pos + host_math.rotate(end_quat, np.asarray(tip, dtype=np.float64))
        return cls(
            base_pos=jnp.asarray(root),
            base_quat=jnp.asarray(identity),
            parent_anchor=jnp.asarray(parent_anchor),
            child_anchor=jnp.asarray(np.stack(rows["child_anchor"])),
            axis=jnp.asarray(np.stack(rows["axis"])),
            rest=jnp.asarray(np.stack(rows["rest"])),
            mass=jnp.asarray(mass),
            com=jnp.asarray(com),
            inertia=jnp.asarray(inertia),
            lower=jnp.asarray(np.asarray(rows["lower"])),
            upper=jnp.asarray(np.asarray(rows["upper"])),
            tip=jnp.asarray(host_math.rotate(host_math.conjugate(l_quat), tip_world - l_pos)),
            kinds=tuple(chain_kinds),
            limited=tuple(chain_limited),
            names=tuple(chain_names),
        )


Chain = jax.tree_util.register_dataclass(
    Chain,
    data_fields=[
        "base_pos", "base_quat", "parent_anchor", "child_anchor", "axis", "rest", "mass", "com",
        "inertia", "lower", "upper", "tip",
    ],
    meta_fields=["kinds", "limited", "names"],
)  # fmt: skip


class LinkPoses(NamedTuple):
    """World poses of a chain at some angles (leading batch axes follow `angles`).

    pivot: (N, 3) m, joint k's pivot. quat: (N, 4) orientation of link k's frame.
    origin: (N, 3) m, link k's frame origin. com: (N, 3) m, link k's centre of mass.
    end_effector: (3,) m.
    """

    pivot: jnp.ndarray
    quat: jnp.ndarray
    origin: jnp.ndarray
    com: jnp.ndarray
    end_effector: jnp.ndarray


# ---------------------------------------------------------------------------- host-side helpers
def _check_inertia(inertia: np.ndarray, label: str) -> None:
    if not np.all(np.isfinite(inertia)) or not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-12):
        raise ValueError(f"{label}: inertia must be a finite symmetric 3x3 matrix, got {inertia.tolist()}")
    if np.linalg.eigvalsh(inertia)[0] <= 0.0:
        raise ValueError(f"{label}: inertia must be positive definite, got {inertia.tolist()}")


def _ball_limited(structure, j: int) -> bool:
    return bool(structure.joint_has_limits.array[j]) or bool(structure.joint_has_cone.array[j])


def _limit_rows(limits, kinds: tuple[str, ...], label: str):
    n = len(kinds)
    if limits is None:
        entries = [None] * n
    elif len(limits) == 2 and all(np.ndim(x) == 0 and x is not None for x in limits):
        entries = [tuple(limits)] * n
    else:
        entries = list(limits)
        if len(entries) != n:
            raise ValueError(f"{label}: limits must be None, one (lower, upper) or {n} entries, got {limits!r}")
    lower, upper, limited = [], [], []
    for k, entry in enumerate(entries):
        if entry is None or kinds[k] == "ball":
            if entry is not None:
                raise ValueError(f"{label}: joint {k} is a ball joint; limits apply to hinges only")
            lower.append(-pymath.pi), upper.append(pymath.pi), limited.append(False)
            continue
        lo, hi = float(entry[0]), float(entry[1])
        if not (pymath.isfinite(lo) and pymath.isfinite(hi)) or lo > hi or lo < -pymath.pi or hi > pymath.pi:
            raise ValueError(f"{label}: joint {k} limits must satisfy -pi <= lower <= upper <= pi, got {entry!r}")
        lower.append(lo), upper.append(hi), limited.append(True)
    return np.asarray(lower), np.asarray(upper), tuple(limited)


# ---------------------------------------------------------------------------- kinematics
def _static_tables(chain: Chain) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gather index (N, 3) into [angles, 0], hinge mask (N,), limited mask (N,)): compile-time."""
    d = chain.num_dofs
    index = np.full((chain.num_links, 3), d, dtype=np.int32)
    for k, (kind, offset) in enumerate(zip(chain.kinds, chain.dof_offsets, strict=True)):
        index[k, : 1 if kind == "hinge" else 3] = np.arange(offset, offset + (1 if kind == "hinge" else 3))
    hinge = np.asarray([kind == "hinge" for kind in chain.kinds])
    return index, hinge, np.asarray(chain.limited, dtype=bool) & hinge


def _flat_positions(chain: Chain) -> np.ndarray:
    """(num_dofs,) position of each angle in the (N, 3) per-joint table, flattened."""
    index, _, _ = _static_tables(chain)
    rows, columns = np.nonzero(index < chain.num_dofs)
    return (rows * 3 + columns)[np.argsort(index[rows, columns])]


def _check_angles(chain: Chain, angles: jnp.ndarray) -> None:
    if jnp.shape(angles) != (chain.num_dofs,):
        raise ValueError(
            f"angles must have shape ({chain.num_dofs},) = (chain.num_dofs,) for joints {chain.kinds}, "
            f"got {jnp.shape(angles)}"
        )


def joint_rotation_vectors(chain: Chain, angles: jnp.ndarray) -> jnp.ndarray:
    """(N, 3) rotation vector r_k of every joint in its parent's frame (theta axis for a hinge)."""
    index, hinge, _ = _static_tables(chain)
    padded = jnp.concatenate([angles, jnp.zeros((1,), angles.dtype)])
    gathered = padded[index]
    return jnp.where(hinge[:, None], gathered[:, :1] * chain.axis, gathered)


def _relative_poses(chain: Chain, rotation_vectors: jnp.ndarray):
    """Poses relative to base_pos (precision: never differences of large absolute positions).

    Returns (parent_quat (N, 4), pivot (N, 3), quat (N, 4), origin (N, 3), com (N, 3), tip (3,)).
    """
    # One pass from the base out (a loop over links: its body is traced once, so the program
    # stays small however long the chain; an associative scan traces log2(N) levels of it).
    # pivot_{k+1} = pivot_k + Q_k (parent_anchor_{k+1} - child_anchor_k).
    ends = jnp.concatenate([chain.parent_anchor[1:], chain.tip[None]])  # next pivot / tip, link frame
    local = math.quat_multiply(math.quat_exp(rotation_vectors), chain.rest)

    def link(carry, row):
        parent_quat, pivot = carry
        joint, span = row
        quat = math.quat_multiply(parent_quat, joint)
        return (quat, pivot + math.quat_rotate(quat, span)), (parent_quat, pivot, quat)

    first = math.quat_rotate(chain.base_quat, chain.parent_anchor[0])
    (_, tip), (parent_quat, pivot, quat) = jax.lax.scan(
        link, (chain.base_quat, first), (local, ends - chain.child_anchor)
    )
    origin = pivot - math.quat_rotate(quat, chain.child_anchor)
    com = origin + math.quat_rotate(quat, chain.com)
    return parent_quat, pivot, quat, origin, com, tip


@jax.jit
def forward_kinematics(chain: Chain, angles: jnp.ndarray) -> LinkPoses:
    """World poses of every link and the end effector at `angles` (num_dofs,) rad."""
    _check_angles(chain, angles)
    _, pivot, quat, origin, com, tip = _relative_poses(chain, joint_rotation_vectors(chain, angles))
    base = chain.base_pos
    return LinkPoses(pivot=base + pivot, quat=quat, origin=base + origin, com=base + com, end_effector=base + tip)


@jax.jit
def end_effector(chain: Chain, angles: jnp.ndarray) -> jnp.ndarray:
    """(3,) m, world position of the end effector at `angles`."""
    return forward_kinematics(chain, angles).end_effector


def pivot_inertias(chain: Chain, pivot: jnp.ndarray, quat: jnp.ndarray, com: jnp.ndarray) -> jnp.ndarray:
    """(N, 3, 3) kg m^2, world inertia of links k..N-1 about pivot k, DBD (133).

    M_k = sum_{i >= k} (I_i - m_i [d_ki]x [d_ki]x), d_ki = com_i - pivot_k. The pairwise
    differences (N x N, masked to i >= k) keep it exact far from the origin; for the chain
    lengths IK is used on this costs less than the recursive form's sequential pass.
    """
    rotation = math.quat_to_matrix(quat)
    # (N, 3, 3) about each com
    world = math.matmul(math.matmul(rotation, chain.inertia), rotation, transpose_b=True)
    d = com[None, :, :] - pivot[:, None, :]  # (k, i, 3)
    eye = jnp.eye(3, dtype=d.dtype)
    shifted = chain.mass[None, :, None, None] * (
        math.dot(d, d)[..., None, None] * eye - d[..., :, None] * d[..., None, :]
    )  # -m [d]x [d]x
    beyond = jnp.asarray(np.triu(np.ones((chain.num_links, chain.num_links))), dtype=d.dtype)  # i >= k
    return jnp.sum(beyond[:, :, None, None] * (world[None] + shifted), axis=1)


# ---------------------------------------------------------------------------- the solver
@functools.partial(jax.jit, static_argnames="method")
def reference_alpha(chain: Chain, method: str = "dbd") -> jnp.ndarray:
    """The scale of J M^-1 J^T for this chain: sum_k |s_k|^2 / m_k at zero angles.

    s_k: pivot k to end effector; m_k = trace(M_k) / 3 (133) for "dbd", 1 for "pinv". The
    default alpha is DEFAULT_RELATIVE_ALPHA times this, so the regularisation means the same
    for chains of any size and mass. Units: m^2 for "pinv", 1/kg for "dbd".
    """
    _, pivot, quat, _, com, tip = _relative_poses(chain, jnp.zeros((chain.num_links, 3), chain.mass.dtype))
    reach = math.dot(tip - pivot, tip - pivot)
    if method == "pinv":
        return jnp.sum(reach)
    moments = jnp.trace(pivot_inertias(chain, pivot, quat, com), axis1=-2, axis2=-1) / 3.0
    return jnp.sum(reach / moments)


class _Metric(NamedTuple):
    """What a frame keeps of the joint-space metric: M_k and M_k^-1 in the world, (N, 3, 3)."""

    inertia: jnp.ndarray
    inverse: jnp.ndarray


def _metric(chain: Chain, method: str, pivot, quat, com) -> _Metric:
    if method == "pinv":
        eye = jnp.broadcast_to(jnp.eye(3, dtype=pivot.dtype), (chain.num_links, 3, 3))
        return _Metric(eye, eye)
    inertia = pivot_inertias(chain, pivot, quat, com)
    _, hinge, _ = _static_tables(chain)
    return _Metric(inertia, None if hinge.all() else math.inverse3(inertia))  # balls use M_k^-1


def _apply(chain: Chain, angles, rotation_vectors, parent_quat, hinge_turn, ball_turn):
    """Angles after turning hinge k by hinge_turn_k (rad) and ball link k by ball_turn_k (a world
    rotation vector): exp(Q_{k-1}^-1 omega) exp(r_k) in the parent, the latest orientation
    q(d theta) q(theta) of (136). Hinge angles are clamped to their limits."""
    index, hinge, limited = _static_tables(chain)
    new_hinge = angles[index[:, 0]]
    if hinge_turn is not None:
        new_hinge = new_hinge + hinge_turn
        new_hinge = jnp.where(limited, jnp.clip(new_hinge, chain.lower, chain.upper), new_hinge)
    if hinge.all():
        return new_hinge
    omega = math.quat_rotate_inverse(parent_quat, ball_turn)
    new_ball = math.quat_log(math.quat_multiply(math.quat_exp(omega), math.quat_exp(rotation_vectors)))
    per_joint = jnp.where(hinge[:, None], jnp.concatenate([new_hinge[:, None], new_ball[:, 1:]], -1), new_ball)
    return per_joint.reshape(-1)[_flat_positions(chain)]


def _iteration(chain, method, constraint, angles, target, alpha, max_step, scales, frame_metric):
    """One update of (136) at the latest angles, lambda starting at 0; target relative to base_pos.

    Returns (angles, distance |x_end - x_T| before the update).
    """
    index, hinge, limited = _static_tables(chain)
    rotation_vectors = joint_rotation_vectors(chain, angles)
    parent_quat, pivot, quat, _, com, tip = _relative_poses(chain, rotation_vectors)
    direction, distance = math.safe_normalize(tip - target)  # delta x of (131)
    # The error one step aims to remove, clamped (Buss's ClampMag) so the linearisation holds.
    aim = jnp.minimum(distance, max_step)
    lever = tip - pivot  # s_k of Fig. 9
    metric = _metric(chain, method, pivot, quat, com) if frame_metric is None else frame_metric
    eye = jnp.eye(3, dtype=tip.dtype)

    # The end effector moves by dx = omega_k x s_k when link k turns by omega_k, so the point
    # constraint's Jacobian block is -[s_k]x and J^T d lambda = s_k x d lambda (136).
    # Hinge k (omega = theta a_k): dx/dtheta = v_k = a_k x s_k, inertia a_k^T M_k a_k (133).
    # Ball k: omega = M_k^-1 (s_k x d lambda), mobility -[s_k]x M_k^-1 [s_k]x.
    # Which joints are hinges, balls or limited is static: only what the chain has is traced.
    has_hinge, has_ball, has_limits = bool(hinge.any()), not bool(hinge.all()), bool(limited.any())
    zeros = jnp.zeros_like(lever)
    if has_hinge:
        world_axis = math.quat_rotate(parent_quat, chain.axis)
        velocity = math.cross(world_axis, lever)
        hinge_inertia = math.dot(world_axis, math.matvec(metric.inertia, world_axis))
        hinge_inertia = jnp.where(hinge, hinge_inertia, 1.0)  # ball rows: unused, kept finite
        hinge_mobility = velocity[:, :, None] * velocity[:, None, :] / hinge_inertia[:, None, None]
        hinge_mobility = jnp.where(hinge[:, None, None], hinge_mobility, 0.0)
    if has_ball:
        skew = math.skew(lever)
        turned = math.matmul(math.matmul(skew, metric.inverse), skew)
        ball_mobility = jnp.sum(jnp.where(hinge[:, None, None], 0.0, -turned), 0)
    else:
        ball_mobility = jnp.zeros_like(eye)

    def impulse(free):
        """d lambda (a world 3-vector) with the joints in `free` moving (135)."""
        mobility = ball_mobility  # J M^-1 J^T, summed over the moving joints
        if has_hinge:
            mobility = mobility + jnp.sum(jnp.where(free[:, None, None], hinge_mobility, 0.0), axis=0)
        if constraint == "point":  # mu = [J M^-1 J^T + alpha 1]^-1, a 3x3 (135)
            return -math.matvec(math.inverse3(mobility + alpha * eye), direction * aim)
        # "distance": the scalar row (134) J = (s_k x n)^T, mu = [n . J M^-1 J^T n + alpha]^-1 (135)
        denominator = math.dot(direction, math.matvec(mobility, direction)) + alpha
        return -direction * (aim / denominator)[..., None]

    # Projected step: a hinge at a limit that descent would push further out (the sign of
    # -d|delta x|^2/d theta_k = -v_k . delta x, the condition of a bound-constrained minimum) is
    # held still, and the free joints take the whole correction.
    free = jnp.ones(hinge.shape, dtype=bool)
    if has_limits:
        hinge_angles = angles[index[:, 0]]
        descent = -math.dot(velocity, direction)
        at_upper = limited & (hinge_angles >= chain.upper) & (descent > 0.0)
        at_lower = limited & (hinge_angles <= chain.lower) & (descent < 0.0)
        free = ~(at_upper | at_lower)
    d_lambda = impulse(free)
    hinge_turn = jnp.where(free & hinge, math.dot(velocity, d_lambda) / hinge_inertia, 0.0) if has_hinge else None
    ball_turn = math.matvec(metric.inverse, math.cross(lever, d_lambda)) if has_ball else zeros  # (136)

    # Backtracking along the step, all candidate lengths at once: keep the one that ends closest.
    # The step is a descent direction of |delta x|^2 (e^T K (K + alpha)^-1 e >= 0), so a short
    # enough one always helps; this stops the overshoot cycles a full Newton step falls into
    # near the singular straight pose of an unreachable target.
    def candidate(scale):
        turn = None if hinge_turn is None else scale * hinge_turn
        moved = _apply(chain, angles, rotation_vectors, parent_quat, turn, scale * ball_turn)
        _, _, _, _, _, moved_tip = _relative_poses(chain, joint_rotation_vectors(chain, moved))
        return moved, math.safe_norm(moved_tip - target)

    if len(scales) == 1:
        return candidate(scales[0])[0], distance
    moved, reached = jax.vmap(candidate)(jnp.asarray(scales, dtype=tip.dtype))
    return moved[jnp.argmin(reached)], distance


@jax.jit
def reach(chain: Chain) -> jnp.ndarray:
    """() m, the sum of the pivot-to-pivot (and last pivot to end effector) distances."""
    ends = jnp.concatenate([chain.parent_anchor[1:], chain.tip[None]])  # the next pivot, in link k's frame
    spans = ends - chain.child_anchor
    return jnp.sum(math.safe_norm(spans))


@functools.partial(
    jax.jit, static_argnames=("method", "iterations", "inertia", "constraint", "line_search", "return_error")
)
def solve(
    chain: Chain,
    angles: jnp.ndarray,
    target: jnp.ndarray,
    method: str = "dbd",
    iterations: int = 64,
    alpha: float | jnp.ndarray | None = None,
    inertia: str = "per_iteration",
    constraint: str = "point",
    max_step: float | jnp.ndarray | None = None,
    line_search: int = 8,
    return_error: bool = False,
) -> jnp.ndarray | tuple[jnp.ndarray, jnp.ndarray]:
    """Joint angles that put the end effector on `target`, DBD section 11.

    chain: a `Chain`. angles: (num_dofs,) rad, the start pose. target: (3,) m, world.
    method: "dbd" (mass/inertia weighted, (131)-(136)) or "pinv" (pseudo-inverse, (126)-(130)).
    iterations: updates (static; `lax.scan`). inertia: "per_iteration" recomputes the M_k of
      (133) at every update, "per_frame" once from `angles` (one call is one frame) and keeps
      it (the paragraph after (136)).
    alpha: the regularisation of (135), in 1/kg for "dbd" and m^2 for "pinv"; None means
      DEFAULT_RELATIVE_ALPHA x `reference_alpha(chain, method)`.
    constraint: "point" (x_end = x_T, three rows solved together with the 3x3 mu of (135)) or
      "distance" (the scalar |x_end - x_T| = 0 of (131) with the row (134)).
    max_step: m, the most error one update aims to remove (None: 0.2 x `reach(chain)`).
    line_search: how many step lengths 1, 1/2, 1/4, ... each update tries (1: the plain update).
    Returns the angles (num_dofs,), and with return_error=True also the distance |x_end - x_T|
    (m) before each update, (iterations,).
    """
    if method not in METHODS:
        raise ValueError(f"ik.solve: method must be one of {METHODS}, got {method!r}")
    if constraint not in CONSTRAINTS:
        raise ValueError(f"ik.solve: constraint must be one of {CONSTRAINTS}, got {constraint!r}")
    if inertia not in INERTIA_MODES:
        raise ValueError(f"ik.solve: inertia must be one of {INERTIA_MODES}, got {inertia!r}")
    for what, count in (("iterations", iterations), ("line_search", line_search)):
        if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
            raise ValueError(f"ik.solve: {what} must be a positive integer (static), got {count!r}")
    _check_angles(chain, angles)
    if jnp.shape(target) != (3,):
        raise ValueError(f"ik.solve: target must have shape (3,), got {jnp.shape(target)}")
    dtype = jnp.result_type(angles, chain.mass)
    angles = jnp.asarray(angles, dtype)
    target = jnp.asarray(target, dtype) - chain.base_pos
    alpha = DEFAULT_RELATIVE_ALPHA * reference_alpha(chain, method) if alpha is None else jnp.asarray(alpha, dtype)
    max_step = DEFAULT_RELATIVE_STEP * reach(chain) if max_step is None else jnp.asarray(max_step, dtype)
    scales = tuple(0.5**i for i in range(line_search))

    frame_metric = None
    if inertia == "per_frame":
        _, pivot, quat, _, com, _ = _relative_poses(chain, joint_rotation_vectors(chain, angles))
        frame_metric = _metric(chain, method, pivot, quat, com)

    def iteration(angles, _):
        return _iteration(chain, method, constraint, angles, target, alpha, max_step, scales, frame_metric)

    angles, errors = jax.lax.scan(iteration, angles, None, length=iterations)
    return (angles, errors) if return_error else angles
