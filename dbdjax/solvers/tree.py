"""An exact linear solve over the joint tree: Algorithm 1's initial guess, and the direct steps of
`tree_solve` (the points after the sweeps, then the joints whole after the last).

Why. Gauss-Seidel moves a correction one joint per colour sweep, so from the guess dX = 0 it
cannot build the tension of a long chain within a few iterations (DBD 10.1: "it requires N - 1
updates to propagate a displacement from one end of the chain to the other, even with perfect
ordering"); the smooth error modes of a chain of N joints decay by only 1 - O(1/N^2) per sweep.
A 20-link chain whose free end whips carries several times its weight at the root, and every
substep the prediction X* stretches each joint by about (tension / link mass) h^2. With 8 substeps
of 10 sweeps the red-black iterations left 2.8 mm of it (5.7 mm with the magnitude form of the
point constraint); over-relaxation (xi = 1.7: 1.1 mm), symmetric colour order (worse per sweep),
and warm-starting the multipliers from the previous substep (unstable: it diverged at the whip)
do not remove it, only O(N^2) sweeps do (8 x 100: 0.17 mm).
Algorithm 1 allows "a better initial guess"; this module supplies the best linear one, the
solution at X* of

    (J M~^-1 J^T + alpha) kappa = -c(X*),      dX = M~^-1 J^T kappa                  DBD (49)

for the point constraint of every ball, hinge, fixed, universal and gimbal joint in its vector form
c = p_a - p_b (DBD (64)-(66), the block `rows.point_block` solves joint by joint). The non-linear Gauss-Seidel
iterations then start from it, with each joint's point multiplier set to its kappa, and only
have the non-linear remainder and the other rows left to remove. In the linear limit the guess
is exactly the point they converge to from dX = 0. Angular rows, limits, drives, contacts,
sliders and the joints that close a loop are left to the iterations.

With `finalize(tree_solve=True)` the same solve, linearised where the sweep left the bodies, also
ends every iteration but the last, where the whole-joint solve follows (block Gauss-Seidel: the
tree's points one block, solved directly; the solver's `TreeStep`), so the points hold to second
order whatever the sweeps left. After the last sweep one more solve takes each tree joint whole:
with its point, its rotation lock (a hinge's axle alignment, a universal's lock, a fixed joint's),
its rotors (armature), its hinge or universal / gimbal soft angle limits past their bounds and its
drive (DBD 9) while inside its torque limit, each in the compliance form of DBD (49) beside the
point rows (`angular_rows`; a degree of freedom's rotor, limit and drive as one row: up to 9 rows a
joint instead of 3). Without
them the direct steps closed the points by swinging joints whose rotors are heavy and bending them
through their limits, which the sweeps then fought (Brax's ant sank to 0.18 m), and undid what the
sweeps' drives had held (a driven arm sagged 0.61 rad). Those rows stay out of the solves inside
the sweeps: there the sweeps' soft limits let go of what a solve had pushed past a bound and the
ant blew up within 4 steps. Rigid limits stay with the sweeps: in the solve they made the standing
ragdoll, its knees on their limits, creep up and fall within 10 s. That last solve ends with a
chord step on the joints' points (`_closing_step`): its own factors, the gaps measured again where it
left the bodies (one solve leaves the second order of its turn: 1.0 mm on the landing ant).
The contacts of a tree body with the world are rows of every direct solve (solvers/tree_contacts.py:
each adds to its one body's block, as a joint to the fixed world would), unilateral and within the
friction cone by one active-set step with the drives' torque limits (`direct_step`); without them a
standing doll's direct steps pulled its feet toward the body and it collapsed.

How. Bodies and joints form a forest (a joint closing a loop is left out). The saddle-point system
[[M~, J^T], [J, -alpha]] [dX; -kappa] = [0; -c] is eliminated from the leaves to the roots and
back-substituted without fill-in, in time linear in the number of joints (Baraff 1996,
"Linear-time dynamics using Lagrange multipliers"). A level of the tree is one step of a
`lax.scan`, all the (joint, child body) pairs of the level at once: sequential in the depth of
the tree, parallel across it (each level as narrow as the tree's height allows, `schedule`;
floating roots, the last level alone, after the scan, `_Slots`). Writing
S_j = alpha + J_jb D_b^-1 J_jb^T for a joint j whose child body b has the eliminated block D_b (its
mass plus the stiffness its own children add):

    leaves -> roots:  z_j = -c_j - J_jb D_b^-1 z_b;   D_p += J_jp^T S_j^-1 J_jp;   z_p += J_jp^T S_j^-1 z_j
    roots -> leaves:  kappa_j = S_j^-1 (z_j - J_jp dX_p);   dX_b = D_b^-1 (z_b + J_jb^T kappa_j)

with D_b = M~_b and z_b = 0 before the children of b are added, and dX = 0 for the world. With the
angular rows, c_j stacks each row's c + alpha lambda and S_j is (R, R), inverted by 3 x 3 blocks.
The schedule (`schedule`) is static: numpy on the host, at trace time.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import indexing, math, sharding
from dbdjax.constraints import joints as joint_family
from dbdjax.constraints import rows as row
from dbdjax.constraints.rows import BodyPair, BodySet
from dbdjax.indexing import take
from dbdjax.model import BALL, FIXED, GIMBAL, HINGE, UNIVERSAL, Model, Structure
from dbdjax.solvers import tree_contacts

# Joint kinds whose point constraint is a full 3-D one (a slider's acts only across its axis).
POINT_KINDS = (BALL, HINGE, FIXED, UNIVERSAL, GIMBAL)


def schedule(
    body_a: np.ndarray, body_b: np.ndarray, kind: np.ndarray, num_bodies: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levels of the joint forest, leaves first. Host side, numpy, at trace time.

    body_a/b: (J,) solver body indices (num_bodies stands for the world); kind: (J,) joint kinds.
    Returns (tree_joint, tree_body, tree_parent), each (L, W) int32. Slot w of level l holds a
    joint, its child body (the side away from the root) and its parent body (num_bodies for the
    world). A floating tree's root body has joint J (none). Empty slots hold (J, N, N). The
    children of every body sit at earlier levels: the jointed bodies in as many levels as they are
    high, each as narrow as can be (`_narrowest_levels`), then the floating roots, if any, alone in
    one more. No tree joint: arrays of shape (0, 1).
    Trees are rooted at the world where attached, else at their lowest body index; a joint that
    would close a loop (or joins two static sides) is left out, as is every slider.
    """
    num_joints, world = len(body_a), num_bodies
    group = list(range(num_bodies + 1))  # union-find over bodies and the world

    def find(x: int) -> int:
        while group[x] != x:
            group[x] = group[group[x]]
            x = group[x]
        return x

    neighbours: list[list[tuple[int, int]]] = [[] for _ in range(num_bodies + 1)]
    for j in range(num_joints):
        a, b = int(body_a[j]), int(body_b[j])
        if kind[j] not in POINT_KINDS or find(a) == find(b):
            continue
        group[find(a)] = find(b)
        neighbours[a].append((j, b))
        neighbours[b].append((j, a))

    up_joint = np.full(num_bodies + 1, num_joints)
    up_body = np.full(num_bodies + 1, world)
    seen = np.zeros(num_bodies + 1, dtype=bool)
    order: list[int] = []  # bodies, every parent before its children
    for root in [world] + [b for b in range(num_bodies) if neighbours[b]]:
        if seen[root]:
            continue
        seen[root] = True
        if root != world:
            order.append(root)
        stack = [root]
        while stack:
            node = stack.pop()
            for j, other in neighbours[node]:
                if not seen[other]:
                    seen[other] = True
                    up_joint[other], up_body[other] = j, node
                    order.append(other)
                    stack.append(other)
    if not order:
        empty = np.zeros((0, 1), dtype=np.int32)
        return empty, empty, empty

    height = np.zeros(num_bodies + 1, dtype=np.int64)  # 0 for a leaf, 1 + the highest child
    for body in reversed(order):
        if up_body[body] != world:
            height[up_body[body]] = max(height[up_body[body]], height[body] + 1)
    # A floating root has no joint: it waits in a last level of its own (`_Slots.roots`), and the
    # jointed bodies take the levels below it, a floating root's children as roots of their own.
    floating = [b for b in order if up_joint[b] == num_joints]
    jointed = [b for b in order if up_joint[b] != num_joints]
    parent = np.where(up_joint[up_body] == num_joints, world, up_body)  # (the world's own entry is J too)
    levels = _narrowest_levels(jointed, parent, world, int(height[jointed].max()) + 1)
    if floating:
        levels.append(sorted(floating))
    width = max(len(members) for members in levels)
    tree_joint = np.full((len(levels), width), num_joints, dtype=np.int32)
    tree_body = np.full((len(levels), width), world, dtype=np.int32)
    tree_parent = np.full((len(levels), width), world, dtype=np.int32)
    for k, members in enumerate(levels):
        for w, body in enumerate(members):
            tree_joint[k, w], tree_body[k, w], tree_parent[k, w] = up_joint[body], body, up_body[body]
    return tree_joint, tree_body, tree_parent


def _narrowest_levels(order: list[int], parent: np.ndarray, world: int, count: int) -> list[list[int]]:
    """The bodies of `order` (every parent before its children; parent[b] its parent body, `world`
    for a root) in `count` levels, each body at a later level than its children, the widest level
    as narrow as can be: every level is padded to it, so it sets the work of every level's step.

    By Hu's rule (T. C. Hu 1961, "Parallel sequencing and assembly line problems": for a forest of
    unit tasks whose every task has one successor, it meets the least number of steps of any
    schedule on `width` processors): level by level from the leaves, take up to `width` of the
    bodies whose children are all placed, those farthest from their root first; the narrowest
    `width` whose schedule fits in `count` levels (the tree's height: no schedule has fewer). Brax's
    humanoid: levels of 3, 3, 3, 1, 1 bodies instead of the leaves-first 4, 4, 1, 1, 1 (the upper
    arms wait beside the pelvis, one forearm beside the thighs): 15 slots instead of 20."""
    depth = {}  # edges to the root
    for body in order:
        depth[body] = 0 if parent[body] == world else depth[int(parent[body])] + 1
    children = {body: 0 for body in order}
    for body in order:
        if parent[body] != world:
            children[int(parent[body])] += 1
    for width in range(-(-len(order) // count), len(order) + 1):
        waiting, ready, levels = dict(children), [b for b in order if children[b] == 0], []
        while ready and len(levels) < count:
            ready.sort(key=lambda b: (-depth[b], b))
            level, ready = sorted(ready[:width]), ready[width:]
            levels.append(level)
            for body in level:
                up = int(parent[body])
                if up != world:
                    waiting[up] -= 1
                    if waiting[up] == 0:
                        ready.append(up)
        if not ready and sum(len(level) for level in levels) == len(order):
            return levels
    raise AssertionError("unreachable: at the width of every body a schedule of `count` levels fits")


def _mv(a: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """a (..., n, k) @ v (..., k) as k broadcast products."""
    total = a[..., :, 0] * v[..., None, 0]
    for k in range(1, a.shape[-1]):
        total = total + a[..., :, k] * v[..., None, k]
    return total


def _transposed_mv(a: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """a (..., k, n) transposed times v (..., k) as k broadcast products (no transposed copy of a)."""
    total = a[..., 0, :] * v[..., 0, None]
    for k in range(1, a.shape[-2]):
        total = total + a[..., k, :] * v[..., k, None]
    return total


def _point_jacobian(sign: np.ndarray, arm: jnp.ndarray) -> jnp.ndarray:
    """d(delta p)/d(dx, dtheta) of one side of a joint, (..., 3, 6) = sign (1, -[arm]x): DBD (65)."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=arm.dtype), arm.shape[:-1] + (3, 3))
    return jnp.asarray(sign, arm.dtype)[..., None, None] * jnp.concatenate([eye, -math.skew(arm)], axis=-1)


def forest(structure: Structure) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`schedule` of a model's joints (static: numpy, evaluated when the step is traced)."""
    return schedule(structure.joint_body_a.array, structure.joint_body_b.array, structure.joint_kind.array,
                    structure.num_bodies)  # fmt: skip


def point_gaps(model: Model, bodies: BodySet) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(delta, arm_a, arm_b), each (J, 3): the point constraint of every joint at X* + dX (DBD (53)-(54)).

    bodies: the solver's per-body table, (N + 1, ...) with the world as the last row.
    """
    structure = model.structure
    ends = np.stack([structure.joint_body_a.array, structure.joint_body_b.array], axis=-1)  # (J, 2)
    pairs = jax.tree.map(lambda column: take(column, ends), bodies)

    def one(joint, flag, two):
        pair = BodyPair.of(two)
        return joint_family.joint_points(joint, flag, pair, *pair.current_quats())

    return jax.vmap(one)(model.joints, joint_family.flags(structure), pairs)


class RowGroups(NamedTuple):
    """`_row_groups`: per kind of angular row, its groups."""

    locks: list
    rotors: list
    limits: list
    drives: list


def _row_groups(structure: Structure) -> RowGroups:
    """The joints whose angular rows the direct solve takes, by kind: (lock groups, rotor groups,
    limit groups, drive groups), each group (kind, the universal / gimbal kind to trace, (J, 3) bool: the rows of
    each joint it covers), only kinds that occur. Host side, numpy."""
    flag = joint_family.flags(structure)
    first = np.arange(3) == 0
    kind = structure.joint_kind.array
    locks = [
        ("hinge", frozenset(), (kind == HINGE)[:, None] & (np.arange(3) < 2)),
        ("universal", frozenset(), (kind == UNIVERSAL)[:, None] & first),
        ("fixed", frozenset(), np.repeat((kind == FIXED)[:, None], 3, axis=1)),
    ]
    universal = np.asarray(flag.universal)[:, None]
    # Soft limits only: with the rigid ones in the solve, the standing ragdoll (knees resting on their
    # rigid limits) crept upward and had fallen by 10 s; the sweeps keep those.
    soft = np.asarray(flag.soft_limits)[:, None]
    euler_rotor, euler_limit = np.asarray(flag.rotor_euler), np.asarray(flag.euler_limited) & soft
    hinge_limit = (np.asarray(flag.has_angle_limits) & np.asarray(flag.hinge))[:, None] & first & soft
    rotors = [
        ("rotor_hinge", frozenset(), np.asarray(flag.rotor_hinge)[:, None] & first),
        ("rotor_euler", frozenset({"universal"}), euler_rotor & universal),
        ("rotor_euler", frozenset({"gimbal"}), euler_rotor & ~universal),
        ("rotor_ball", frozenset(), np.repeat(np.asarray(flag.rotor_ball)[:, None], 3, axis=1)),
    ]
    limits = [
        ("has_angle_limits", frozenset(), hinge_limit),
        ("euler_limited", frozenset({"universal"}), euler_limit & universal),
        ("euler_limited", frozenset({"gimbal"}), euler_limit & ~universal),
    ]
    drive = np.asarray(flag.euler_drive)[:, None] & (np.arange(3) < np.where(flag.universal, 2, 3)[:, None])
    drives = [
        ("hinge_drive", frozenset(), np.asarray(flag.hinge_drive)[:, None] & first),
        ("euler_drive", frozenset({"universal"}), drive & universal),
        ("euler_drive", frozenset({"gimbal"}), drive & ~universal),
        ("ball_drive", frozenset(), np.repeat(np.asarray(flag.ball_drive)[:, None], 3, axis=1)),
    ]
    return RowGroups(*([g for g in groups if g[2].any()] for groups in (locks, rotors, limits, drives)))


class AngularRows(NamedTuple):
    """The joints' angular rows the direct solve takes beside their points, (J, K, ...) each: three
    rows of rotation lock, then three spring rows, one per degree of freedom, each block where the
    model has any (K = 3 or 6), each row in the compliance form of DBD (49) with J = (0, d) on b and
    (0, -d) on a. Rows a joint lacks are off (J = 0, no error).

    A degree of freedom's rotor, soft angle limit and drive are springs along the same d (the
    dq_k / dtheta_b of its angle), so they act as one row: with W the rest of the system along d,
    the rows W mu + alpha_s mu_s = -r_s (s = rotor, limit, drive) are the one row
    (W + alpha) mu = -r with mu = sum mu_s, 1 / alpha = sum 1 / alpha_s and r = alpha sum r_s / alpha_s,
    and each mu_s = (r + alpha mu - r_s) / alpha_s after (`angular_increments`). Exact, and three
    rows fewer per block than taking them apart. The `spring_*` fields hold each one's own row to split by:
    (S, J, 3) for the S kinds the model has (rotors, limits, drives, in that order), off where a
    joint lacks it, a limit is not past its bound or a drive is at its torque limit."""

    on: jnp.ndarray  # (J, K) bool
    directions: jnp.ndarray  # (J, K, 3) d
    compliance: jnp.ndarray  # (J, K) alpha
    residual: jnp.ndarray  # (J, K) c + alpha lambda now (0 where off)
    lock_basis: jnp.ndarray | None  # (J, 3, 3) a lock row's multiplier: basis_k . L (`joints.lock_rows`)
    upper: jnp.ndarray | None  # (J, 3) bool: a limit row is its upper bound's (multiplier -mu), else its lower's
    spring_on: jnp.ndarray | None  # (S, J, 3) bool
    spring_compliance: jnp.ndarray | None  # (S, J, 3) alpha_s (1 where off)
    spring_residual: jnp.ndarray | None  # (S, J, 3) r_s = c_s + alpha_s lambda_s now


def has_angular_rows(structure: Structure) -> bool:
    """Whether the direct solve takes angular rows for this model (`angular_rows` is not None)."""
    return any(_row_groups(structure))


def angular_rows(model: Model, bodies: BodySet, multipliers: jnp.ndarray | None, targets: joint_family.Targets,
                 h: float, saturated: jnp.ndarray | None = None) -> AngularRows | None:  # fmt: skip
    """Every joint's rotation lock, rotor, angle limit and drive rows at the configuration of
    `bodies`, or None for a model with none of them. bodies: the solver's per-body table (N + 1,
    ...), the world as the last row.
    multipliers: (J, joints.NUM_MULTIPLIERS) each joint's multipliers so far this substep (None:
    zero). targets: the substep's `joints.Targets` (rotor offsets, torques, references, drive
    targets). h: s. saturated: (J, 3) bool, drive rows to leave out (`direct_step`), or None.

    A lock is rigid, alpha the joint's regularisation (`joints.lock_rows`: a hinge's axle alignment,
    without which the solve turned hinges off their axles and the sweeps turned them back). A rotor
    is a spring row with k h^2 = armature toward where the rotor's inertia carries its
    coordinate (`joints.rotor_rows`): alpha = 1 / armature. A soft limit past its bound pushes as a
    spring and damper (`joints.limit_rows`); the rows are those past their bounds where this solve
    is taken (rigid limits are left to the sweeps, `_row_groups`). Without them the direct step closes the points by
    swinging joints whose rotors are heavy (Brax's ant: armature 40-120 x its legs' inertia) and
    bending them through their limits, and the sweeps must fight that back each iteration. A drive
    is a spring and damper toward its target (`joints.drive_rows`): alpha = 1 / (k h^2 + nu h); one
    at its torque limit (DBD (114)) after the sweeps, or in `saturated`, is left out.
    """
    structure = model.structure
    lock_groups, rotor_groups, limit_groups, drive_groups = _row_groups(structure)
    if not (lock_groups or rotor_groups or limit_groups or drive_groups):
        return None
    num_joints, dtype = structure.num_joints, bodies.inv_inertia.dtype
    lam = jnp.zeros((num_joints, joint_family.NUM_MULTIPLIERS), dtype) if multipliers is None else multipliers
    flag = joint_family.flags(structure)
    ends = np.stack([structure.joint_body_a.array, structure.joint_body_b.array], axis=-1)  # (J, 2)

    def measured(groups, measure):
        """measure(joint, flags, target, pair, kind, traced) per group, on its own joints only (no
        angle of a joint without those axes): each output (J, 3, ...) with zeros elsewhere, read
        from the groups' outputs stacked over a row of zeros (`take`: no scatter, nor one in the
        gradient; a joint in two groups reads the last one's, as `.at[members].set` in turn did)."""
        outputs, reads, count = [], np.full(num_joints, -1), 0
        for kind, traced, rows in groups:
            members = np.flatnonzero(rows.any(axis=1))
            pick = lambda x, members=members: take(x, members)  # noqa: E731
            pairs = jax.tree.map(lambda column, members=members: take(column, ends[members]), bodies)
            one = lambda j, f, t, two, kind=kind, traced=traced: measure(j, f, t, BodyPair.of(two), kind, traced)  # noqa: E731
            outputs.append(jax.vmap(one)(jax.tree.map(pick, model.joints), jax.tree.map(pick, flag),
                                         jax.tree.map(pick, targets), pairs))  # fmt: skip
            reads[members] = count + np.arange(len(members))
            count += len(members)
        reads[reads < 0] = count  # the row of zeros
        stacked = (jnp.concatenate([*column, jnp.zeros((1,) + column[0].shape[1:], column[0].dtype)])
                   for column in zip(*outputs, strict=True))  # fmt: skip
        return [take(column, reads) for column in stacked]

    parts = []  # (on, directions, compliance, residual) per block of three rows
    springs = []  # the same, per kind of spring row, merged into one block below
    upper = basis = None
    if lock_groups:
        error, directions, basis = measured(
            lock_groups, lambda j, f, t, pair, kind, traced: joint_family.lock_rows(j, f, pair, kind)
        )
        on = np.any([rows for _, _, rows in lock_groups], axis=0)
        compliance = jnp.broadcast_to(model.joints.regularization[:, None], on.shape)
        taken = jnp.einsum("jkc,jc->jk", basis, lam[:, joint_family.ROTATION_LOCK : joint_family.ROTATION_LOCK + 3])
        parts.append((jnp.asarray(on), directions, compliance, error + compliance * taken))
    if rotor_groups:
        error, directions = measured(
            rotor_groups, lambda j, f, t, pair, kind, traced: joint_family.rotor_rows(j, f, t, pair, kind, h, traced)
        )
        on = np.any([rows for _, _, rows in rotor_groups], axis=0)
        armature = jnp.where(np.asarray(flag.rotor_ball)[:, None], model.joints.armature[:, :1], model.joints.armature)
        residual, compliance, _ = row.spring_compliance(armature, 0.0, error, 0.0)  # k h^2 = armature
        taken = lam[:, joint_family.ROTOR : joint_family.ROTOR + 3]
        springs.append((jnp.asarray(on), directions, compliance, residual + compliance * taken))
    if limit_groups:
        limits = measured(limit_groups, lambda j, f, t, pair, kind, traced: tuple(
            joint_family.limit_rows(j, f, pair, kind, h, traced)))  # fmt: skip
        limits = joint_family.LimitRows(*limits)
        hinge = np.asarray(flag.hinge)[:, None]
        lower_taken = jnp.where(hinge, lam[:, joint_family.ANGLE_LOWER, None], lam[:, _EULER_LOWER])
        upper_taken = jnp.where(hinge, lam[:, joint_family.ANGLE_UPPER, None], lam[:, _EULER_UPPER])
        taken = jnp.where(limits.upper, -upper_taken, lower_taken)
        on = np.any([rows for _, _, rows in limit_groups], axis=0) & limits.active
        springs.append((on, limits.directions, limits.compliance, limits.residual + limits.compliance * taken))
        upper = limits.upper
    if drive_groups:
        drives = joint_family.DriveRows(*measured(drive_groups, lambda j, f, t, pair, kind, traced: tuple(
            joint_family.drive_rows(j, f, t, pair, kind, h, traced))))  # fmt: skip
        taken = lam[:, _DRIVE]
        # A drive at its torque limit (DBD (114)) keeps the torque the sweeps gave it: a linear row
        # would push past the limit.
        size, bound = _drive_torque(model, taken, h)
        free = size < bound  # an unlimited drive stores bound = inf
        if saturated is not None:
            free = free & ~saturated
        on = np.any([rows for _, _, rows in drive_groups], axis=0) & drives.active & free
        springs.append((on, drives.directions, drives.compliance, drives.residual + drives.compliance * taken))
    spring_on = spring_compliance = spring_residual = None
    if springs:
        stacked = (jnp.stack(column) for column in zip(*springs, strict=True))
        spring_on, each_direction, spring_compliance, spring_residual = stacked
        # A spring row without compliance (a limit row whose joint cannot turn along it, `joints.limit_rows`
        # with w = 0) moves nothing: off, rather than an infinite stiffness in the sum.
        spring_on = spring_on & (spring_compliance > 0.0)
        spring_compliance = jnp.where(spring_on, spring_compliance, 1.0)
        spring_residual = jnp.where(spring_on, spring_residual, 0.0)
        stiffness = jnp.sum(jnp.where(spring_on, 1.0 / spring_compliance, 0.0), axis=0)  # sum of 1 / alpha_s
        on = jnp.any(spring_on, axis=0)
        compliance = 1.0 / jnp.where(on, stiffness, 1.0)
        residual = compliance * jnp.sum(jnp.where(spring_on, spring_residual / spring_compliance, 0.0), axis=0)
        # The kinds share d where they are on (the same angle's gradient); take it from one that is.
        directions = jnp.sum(jnp.where(spring_on[..., None] & (jnp.cumsum(spring_on, axis=0) == 1)[..., None],
                                       each_direction, 0.0), axis=0)  # fmt: skip
        parts.append((on, directions, compliance, residual))
    on, directions, compliance, residual = (jnp.concatenate(column, axis=1) for column in zip(*parts, strict=True))
    return AngularRows(
        on=on,
        directions=jnp.where(on[..., None], directions, 0.0),
        compliance=jnp.where(on, compliance, 1.0),
        residual=jnp.where(on, residual, 0.0),
        lock_basis=basis,
        upper=upper,
        spring_on=spring_on,
        spring_compliance=spring_compliance,
        spring_residual=spring_residual,
    )


# Slices, not index arrays: a numpy index traced once under `jax.enable_x64` left a 64-bit index
# that a later float32 trace of the same model tripped over (session 28's test order).
_EULER_LOWER = slice(joint_family.EULER_LOWER, joint_family.EULER_LOWER + 3)
_EULER_UPPER = slice(joint_family.EULER_UPPER, joint_family.EULER_UPPER + 3)
_DRIVE = slice(joint_family.DRIVE, joint_family.DRIVE + 3)
_POINT = slice(joint_family.POINT, joint_family.POINT + 3)


def _drive_torque(model: Model, multipliers: jnp.ndarray, h: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(size, bound), each (J, 3) or (J, 1): how far each drive row's multiplier (J, 3) reaches
    against its torque limit times h^2 (DBD (114)): a ball drive's as one vector, a hinge's or a
    universal / gimbal's per hinge, as `joints.project` clamps them."""
    ball = np.asarray(joint_family.flags(model.structure).ball_drive)[:, None]
    size = jnp.where(ball, math.safe_norm(multipliers, keepdims=True), jnp.abs(multipliers))
    return size, model.joints.drive_max_torque[:, None] * h**2


def angular_increments(structure: Structure, rows: AngularRows, step: jnp.ndarray) -> jnp.ndarray:
    """(J, joints.NUM_MULTIPLIERS): the multiplier steps of the angular rows' solve `step` (J, K),
    in the joint multipliers' layout: a lock's through its basis, a spring row's split among its
    rotor, limit and drive (`AngularRows`), a limit's mu to its lower row, or -mu to its upper row."""
    lock_groups, rotor_groups, limit_groups, drive_groups = _row_groups(structure)
    increments = jnp.zeros((structure.num_joints, joint_family.NUM_MULTIPLIERS), step.dtype)
    if lock_groups:
        lock = jnp.einsum("jkc,jk->jc", rows.lock_basis, step[:, :3])
        increments = increments.at[:, joint_family.ROTATION_LOCK : joint_family.ROTATION_LOCK + 3].set(lock)
        step = step[:, 3:]
    if not (rotor_groups or limit_groups or drive_groups):
        return increments
    merged = rows.residual[:, -3:] + rows.compliance[:, -3:] * step[:, :3]  # r + alpha mu = -W mu
    shares = iter(jnp.where(rows.spring_on, (merged - rows.spring_residual) / rows.spring_compliance, 0.0))
    if rotor_groups:
        increments = increments.at[:, joint_family.ROTOR : joint_family.ROTOR + 3].set(next(shares))
    if limit_groups:
        hinge = np.asarray(joint_family.flags(structure).hinge)
        limit = next(shares)
        lower, upper = jnp.where(rows.upper, 0.0, limit), jnp.where(rows.upper, -limit, 0.0)
        increments = increments.at[:, _EULER_LOWER].set(jnp.where(hinge[:, None], 0.0, lower))
        increments = increments.at[:, _EULER_UPPER].set(jnp.where(hinge[:, None], 0.0, upper))
        increments = increments.at[:, joint_family.ANGLE_LOWER].set(jnp.where(hinge, lower[:, 0], 0.0))
        increments = increments.at[:, joint_family.ANGLE_UPPER].set(jnp.where(hinge, upper[:, 0], 0.0))
    if drive_groups:
        increments = increments.at[:, _DRIVE].set(next(shares))
    return increments


class Factors(NamedTuple):
    """The saddle-point system of the joint tree eliminated at one configuration, per level slot
    (L, W) and for the floating roots after them (`_Slots`): what `solve` needs besides the gaps.
    Built by `factor`: at X* for the initial guess, and where each sweep left the bodies for
    `tree_solve`."""

    indices: np.ndarray  # (L, W, 2) child body, parent body (num_bodies for the world)
    joint: np.ndarray  # (L, W) the slot's joint (0 in empty slots)
    empty: np.ndarray  # (L, W) bool
    roots: np.ndarray  # (K,) the floating roots eliminated after the levels
    matrices: jnp.ndarray  # (L, W, R, 13) [J_child | J_parent | alpha], R = 3 point rows (+ K angular rows)
    # (L, W, max(6, R), 2 (6 + R)) [D_b^-1 | S_j^-1 | J_child D_b^-1 | J_parent^T S_j^-1], each in
    # its top rows: the two products too, which `factor` forms anyway and every solve's elimination reads.
    inverses: jnp.ndarray
    root_inverses: jnp.ndarray  # (K, 6, 6) D_b^-1 of each of `roots`


def _inverses(inverse: jnp.ndarray, rows: int) -> tuple[jnp.ndarray, ...]:
    """(D_b^-1 (..., 6, 6), S_j^-1 (..., R, R), J_child D_b^-1 (..., R, 6), J_parent^T S_j^-1 (..., 6, R))
    of slots' packed `Factors.inverses` (..., max(6, R), 2 (6 + R))."""
    return (inverse[..., :6, :6], inverse[..., :rows, 6 : 6 + rows], inverse[..., :rows, 6 + rows : 12 + rows],
            inverse[..., :6, 12 + rows :])  # fmt: skip


class _Slots(NamedTuple):
    """The level slots' layout (`Factors`' first fields). The floating roots (Brax's humanoid's and
    ant's torso), the schedule's last level, are `roots`, not a level: a floating root has no
    joint, so all its level would do is invert its block, padded to the widest level's rows and
    joints' row blocks; after the levels it is one 6 x 6 inverse a root."""

    indices: np.ndarray  # (L, W, 2) child body, parent body (num_bodies for the world)
    joint: np.ndarray  # (L, W) the slot's joint (0 in empty slots)
    empty: np.ndarray  # (L, W) bool
    roots: np.ndarray  # (K,) floating roots after the levels


def _slots(structure: Structure) -> _Slots:
    tree_joint, tree_body, tree_parent = forest(structure)
    empty = tree_joint == structure.num_joints
    indices = np.stack([tree_body, tree_parent], axis=-1)
    roots = np.zeros(0, np.int32)
    if len(tree_joint) and empty[-1].all():  # the floating roots' level (`schedule`)
        roots = tree_body[-1][tree_body[-1] != structure.num_bodies]
        width = max(1, int((~empty[:-1]).sum(axis=1).max()))  # the jointed levels', each filled from the left
        indices, empty, tree_joint = indices[:-1, :width], empty[:-1, :width], tree_joint[:-1, :width]
    return _Slots(indices, np.where(empty, 0, tree_joint), empty, roots)


def factor(model: Model, bodies: BodySet, held: jnp.ndarray | None = None, points=None,
           angular: AngularRows | None = None,
           contact: tree_contacts.ContactRows | None = None) -> Factors:  # fmt: skip
    """Eliminate the tree's linearised point constraints (and angular rows) at the configuration of
    `bodies`.

    bodies: the solver's per-body table (N + 1, ...), the world as the last row: inv_mass (N + 1,)
    1/kg, inv_inertia (N + 1, 3, 3) M~^-1, and dx, dtheta where the Jacobians are taken.
    held: (N + 1, 6, 6) added to the bodies' blocks (`tree_contacts.contact_hold`), or None. points:
    `point_gaps(model, bodies)` where the caller has it already. angular: `angular_rows` at the
    same configuration, eliminated with the joints' points (R = 3 + K rows a joint), or None (R = 3).
    contact: `tree_contacts.contact_rows` at the same configuration (rows to the world: each adds
    to its body's block), or None.
    """
    inv_mass, inv_inertia = bodies.inv_mass, bodies.inv_inertia
    structure = model.structure
    world = structure.num_bodies
    dtype = inv_inertia.dtype
    _, arm_a, arm_b = point_gaps(model, bodies) if points is None else points

    # Body blocks M~ = diag(m 1, I~) (6, 6). The world row is a stand-in identity: empty slots
    # (body = world, zero Jacobians, alpha = 1) then invert identities and leave the world at 0.
    is_world = np.arange(world + 1) == world
    mass = 1.0 / jnp.where(is_world, 1.0, inv_mass)
    inertia = math.inverse3(jnp.where(is_world[:, None, None], jnp.eye(3, dtype=dtype), inv_inertia))
    zero33 = jnp.zeros((world + 1, 3, 3), dtype)
    top = jnp.concatenate([mass[:, None, None] * jnp.eye(3, dtype=dtype), zero33], axis=-1)
    blocks = jnp.concatenate([top, jnp.concatenate([zero33, inertia], axis=-1)], axis=-2)
    if held is not None:
        blocks = blocks + held
    if contact is not None:
        blocks = blocks + tree_contacts.added_blocks(contact, world)

    # Per slot (L, W): the joint's Jacobian toward its child body and toward its parent body.
    indices, joint, empty, roots = _slots(structure)
    tree_body, tree_parent = indices[..., 0], indices[..., 1]
    child_is_a = structure.joint_body_a.array[joint] == tree_body
    sign = np.where(empty, 0.0, np.where(child_is_a, 1.0, -1.0))
    parent_sign = np.where(tree_parent == world, 0.0, -sign)
    j_child = _point_jacobian(sign, jnp.where(child_is_a[..., None], arm_a[joint], arm_b[joint]))
    j_parent = _point_jacobian(parent_sign, jnp.where(child_is_a[..., None], arm_b[joint], arm_a[joint]))
    alpha = jnp.where(empty, 1.0, model.joints.regularization[joint])  # S = 1 in empty slots
    alpha = jnp.broadcast_to(alpha[..., None], alpha.shape + (3,))  # (L, W, 3): one per row
    if angular is not None:
        # K more rows per joint (`angular_rows`): J = (0, d) on b, (0, -d) on a. Rows that are off
        # have J = 0 and alpha = 1 (decoupled, no error); so do empty slots.
        on = angular.on[joint] & ~empty[..., None]  # (L, W, K)
        directions = jnp.where(on[..., None], angular.directions[joint], 0.0)  # (L, W, K, 3)
        rotation = jnp.concatenate([jnp.zeros_like(directions), directions], axis=-1)
        j_child = jnp.concatenate([j_child, -sign[..., None, None] * rotation], axis=-2)  # (L, W, R, 6)
        j_parent = jnp.concatenate([j_parent, -parent_sign[..., None, None] * rotation], axis=-2)
        alpha = jnp.concatenate([alpha, jnp.where(on, angular.compliance[joint], 1.0)], axis=-1)

    # Each level's inputs, carry and outputs are packed into one array apiece: on CPU every array a
    # loop step slices or updates is one more kernel, and the levels run one after another.
    matrices = jnp.concatenate([j_child, j_parent, alpha[..., None]], axis=-1)  # (L, W, R, 13)
    rows = matrices.shape[-2]
    eye = jnp.eye(rows, dtype=dtype)
    height = max(6, rows)  # each slot's D_b^-1 (6, 6) and S_j^-1 (R, R) side by side, padded to this

    def padded(matrix):
        return jnp.concatenate([matrix, jnp.zeros((len(matrix), height - matrix.shape[1], matrix.shape[2]), dtype)], 1)

    def eliminate(carry, level):
        packed, (child, at_parent) = level  # carry: D_b (N + 1, 6, 6), the children added so far
        jc, jp, alpha = packed[..., :6], packed[..., 6:12], packed[..., 12]
        # Both positive definite up to a skew part (a velocity-dependent inertia, a sliding contact's
        # tilted row): a body's M~ plus what its children add, a joint's rows' effective inverse
        # mass plus their compliance.
        d_inv = math.gauss_jordan_inverse(take(carry, indexing.Rows(*child)))
        child_products = math.matmul(jc, d_inv)
        s_inv = math.gauss_jordan_inverse(alpha[:, :, None] * eye + math.matmul(child_products, jc, transpose_b=True))
        parent_products = math.matmul(jp, s_inv, transpose_a=True)
        carry = indexing.added(carry, math.matmul(parent_products, jp), indexing.Rows(*at_parent))
        packed = [padded(d_inv), padded(s_inv), padded(child_products), padded(parent_products)]
        return carry, jnp.concatenate(packed, axis=-1)  # (W, max(6, R), 2 (6 + R))

    level_rows = _level_rows(indices, world + 1)
    levels = (matrices, (tuple(level_rows.children), tuple(level_rows.at_parents)))
    blocks, inverses = jax.lax.scan(eliminate, sharding.varying_like(blocks, blocks, matrices), levels)
    return Factors(indices=indices, joint=joint, empty=empty, roots=roots, matrices=matrices, inverses=inverses,
                   root_inverses=math.gauss_jordan_inverse(take(blocks, roots)))  # fmt: skip


class _LevelRows(NamedTuple):
    """Each level's reads and sums of the bodies' rows as `indexing.Rows`, stacked over the levels
    to scan with them (their transposes sum and gather without scattering)."""

    children: indexing.Rows  # the slots' child bodies
    parents: indexing.Rows  # their parents
    at_parents: indexing.Rows  # `indexing.added` at the parents: `.at[parent].add` in its order
    at_children: indexing.Rows  # `indexing.added` at the children


def _level_rows(indices: np.ndarray, count: int) -> _LevelRows:
    """`_LevelRows` of the level slots' (L, W, 2) [child, parent] bodies among `count` rows."""
    child, parent = indices[..., 0], indices[..., 1]
    own = np.arange(count)
    return _LevelRows(
        indexing.stacked_rows(child, count),
        indexing.stacked_rows(parent, count),
        indexing.stacked_rows([np.concatenate([own, level]) for level in parent], count),
        indexing.stacked_rows([np.concatenate([own, level]) for level in child], count),
    )


def _slot_rows(factors: Factors, rows: jnp.ndarray) -> jnp.ndarray:
    """(L, W, R) each level slot's part of a per-joint row array (J, R) (0 in empty slots)."""
    return jnp.where(factors.empty[..., None], 0.0, take(rows, factors.joint))


def _joint_rows(factors: Factors, slots: jnp.ndarray, num_joints: int) -> jnp.ndarray:
    """(J, R) a per-slot row array (L, W, R) gathered back to the joints (0 outside the tree)."""
    slot = np.zeros(num_joints, np.int32)  # each joint's slot, flattened
    in_tree = np.zeros(num_joints, bool)
    real = np.flatnonzero(~factors.empty.reshape(-1))
    slot[factors.joint.reshape(-1)[real]], in_tree[factors.joint.reshape(-1)[real]] = real, True
    gathered = take(slots.reshape((-1,) + slots.shape[2:]), slot)
    return jnp.where(in_tree.reshape((-1,) + (1,) * (gathered.ndim - 1)), gathered, 0.0)


def _eliminate_and_substitute(factors: Factors, gap: jnp.ndarray, start: jnp.ndarray
                              ) -> tuple[jnp.ndarray, jnp.ndarray]:  # fmt: skip
    """The factored system solved for one right-hand side: each slot's rows' gaps (L, W, R) and
    what is added to each body's z before the children's, start (N + 1, 6). Returns the step x
    (N + 1, 6) and each slot's multiplier step (L, W, R)."""
    rows = factors.matrices.shape[-2]

    level_rows = _level_rows(factors.indices, start.shape[0])

    def eliminate(z, level):
        inverse, c, (child, at_parent) = level  # z: (N + 1, 6), what the children added so far
        _, _, child_products, parent_products = _inverses(inverse, rows)
        z_body = take(z, indexing.Rows(*child))
        z_joint = -c - _mv(child_products, z_body)
        z = indexing.added(z, _mv(parent_products, z_joint), indexing.Rows(*at_parent))
        return z, jnp.concatenate([z_body, z_joint], axis=-1)  # (W, 6 + R)

    levels = (factors.inverses, gap, (tuple(level_rows.children), tuple(level_rows.at_parents)))
    z, right = jax.lax.scan(eliminate, sharding.varying_like(start, start, levels[:2]), levels)
    # The floating roots (no joint): dX_root = D_root^-1 z_root, where the levels' substitution starts.
    x = jnp.zeros_like(start)
    if len(factors.roots):
        x = indexing.segment_sum(_mv(factors.root_inverses, take(z, factors.roots)), factors.roots, len(x))

    def substitute(x, level):
        packed, inverse, z, empty, (parent, at_child) = level
        jc, jp = packed[..., :6], packed[..., 6:12]
        d_inv, s_inv, _, _ = _inverses(inverse, rows)
        kappa = _mv(s_inv, z[:, 6:] - _mv(jp, take(x, indexing.Rows(*parent))))
        # Each body is one level's child once, its row still 0: added, as set. Empty slots' (the
        # world's) add nothing, so the world stays put.
        moved = jnp.where(empty[:, None], 0.0, _mv(d_inv, z[:, :6] + _transposed_mv(jc, kappa)))
        return indexing.added(x, moved, indexing.Rows(*at_child)), kappa

    levels = (factors.matrices, factors.inverses, right, factors.empty,
              (tuple(level_rows.parents), tuple(level_rows.at_children)))  # fmt: skip
    return jax.lax.scan(substitute, sharding.varying_like(x, levels[:3]), levels, reverse=True)


def solve(model: Model, factors: Factors, bodies: BodySet, multipliers: jnp.ndarray | None = None, points=None,
          angular: AngularRows | None = None, contact: tree_contacts.ContactRows | None = None,
          loads: jnp.ndarray | None = None, load: jnp.ndarray | None = None):  # fmt: skip
    """The exact step of the linearised point constraints of the joint tree from where `bodies` are.

    factors: `factor` of the same model (at this configuration, or at one close to it: then the
    step is a chord step, exact for the gaps to first order in how far the bodies moved since).
    bodies: the solver's per-body table (N + 1, ...) with its current dx, dtheta. multipliers:
    (J, 3) kg m, the point multipliers each joint has taken so far this substep (None: zero), which
    a regularised joint's constraint c + alpha lambda = 0 reads (DBD (47)). angular: the
    `angular_rows` the factors were built with (their residuals read their own multipliers), or None.
    contact: the `tree_contacts.contact_rows` the factors were built with, or None.
    Returns dx (N + 1, 3) m and dtheta (N + 1, 3) rad to add (world row 0), kappa (J, R), the
    multiplier step of each joint's rows (a point's: the impulse on body a, -kappa on b; 0 outside
    the tree), and the contact rows' multiplier steps (R_c,) (None without `contact`).
    loads: (K, N + 1, 6) loads (force, torque on each body) solved for in the same pass with every
    row's gap at zero, or None; with them a fifth result: the steps A^-1 load (K, N + 1, 6), A the
    system `factors` eliminated. load: (N + 1, 6) a load (force, torque, in multiplier units: kg m,
    kg m^2) on each body, added to the step's right-hand side, or None.
    """
    dtype = factors.inverses.dtype
    world, num_joints = model.structure.num_bodies, model.structure.num_joints
    delta, _, _ = point_gaps(model, bodies) if points is None else points
    if multipliers is not None:
        delta = delta + model.joints.regularization[:, None] * multipliers
    rows = factors.matrices.shape[-2]
    if rows != 3 + (0 if angular is None else angular.on.shape[1]):
        raise ValueError("tree.solve: angular rows must be those the factors were built with")
    if angular is not None:
        delta = jnp.concatenate([delta, angular.residual], axis=-1)  # (J, R)
    gap = _slot_rows(factors, delta)  # (L, W, R)

    start = jnp.zeros((world + 1, 6), dtype)
    if contact is not None:  # a contact row's child is the world: z_j = -r, added to its body's z
        start = tree_contacts.added_right_sides(contact, world)
    if load is not None:
        start = start + load.astype(dtype)
    if loads is None:
        x, kappa_slots = _eliminate_and_substitute(factors, gap, start)
    else:
        # One pass for all right-hand sides: on CPU a pass costs its kernels' launches far more
        # than their arithmetic, so K more columns cost little beside K more passes.
        xs, kappa_all = jax.vmap(lambda g, z: _eliminate_and_substitute(factors, g, z))(
            jnp.concatenate([gap[None], jnp.zeros((len(loads),) + gap.shape, dtype)]),
            jnp.concatenate([start[None], loads.astype(dtype)]),
        )
        x, kappa_slots = xs[0], kappa_all[0]
    # c = p_a - p_b whichever side is the child, so kappa is the impulse on body a (-kappa on b).
    kappa = _joint_rows(factors, kappa_slots, num_joints)
    contact_steps = None if contact is None else tree_contacts.row_steps(contact, x)
    if loads is not None:
        return x[:, :3], x[:, 3:], kappa, contact_steps, xs[1:]
    return x[:, :3], x[:, 3:], kappa, contact_steps


def initial_guess(model: Model, bodies: BodySet) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Solve the linearised point constraints of the joint tree at X* exactly.

    bodies: the solver's per-body table at X* (dx = dtheta = 0), (N + 1, ...) with the world as
    the last row: inv_mass (N + 1,) 1/kg, inv_inertia (N + 1, 3, 3) M~^-1 (0 for the world).
    Returns dx (N + 1, 3) m, dtheta (N + 1, 3) rad (world row 0) and kappa (J, 3) kg m, the
    integrated impulse times h on body a of each joint (-kappa on b; 0 outside the tree).
    """
    dx, dtheta, increments, _ = direct_step(model, bodies)
    return dx, dtheta, increments[:, _POINT]


class _Solved(NamedTuple):
    """One `factor` and `solve` (`_solve_once`): the steps and the rows they solved."""

    dx: jnp.ndarray  # (N + 1, 3)
    dtheta: jnp.ndarray  # (N + 1, 3)
    increments: jnp.ndarray  # (J, joints.NUM_MULTIPLIERS)
    angular: AngularRows | None
    contact: tree_contacts.ContactRows | None
    contact_steps: jnp.ndarray | None  # (R_c,)
    factors: Factors
    jammed: jnp.ndarray | None = None  # () bool: its contact rows `jammed` or `slides_with_its_friction` (None: none)


def _solve_once(model: Model, bodies: BodySet, touching, multipliers, targets, saturated=None,
                settled=None, load=None) -> _Solved:  # fmt: skip
    """One `factor` and `solve` at the configuration of `bodies`. touching: as `direct_step`'s, with
    settled its active set (`tree_contacts.unsettled` for a first solve, else `settle`'s); saturated:
    `angular_rows`'; load: `solve`'s."""
    structure = model.structure
    points = point_gaps(model, bodies)
    angular = None if targets is None else angular_rows(model, bodies, multipliers, *targets, saturated)
    point_multipliers = None if multipliers is None else multipliers[:, _POINT]
    held = contact = tilts = None
    if touching is not None:
        held = touching.held
        contact = tree_contacts.contact_rows(model, bodies, touching, forest(structure)[1], settled)
        # Painleve's check (`tree_contacts.jammed`) needs the responses to the sliding points' tilts:
        # they ride along the solve as more right-hand sides. Taken as separate passes, under a
        # lax.cond that skipped them where nothing slides, they cost Brax's ant with random controls
        # 24% (batch 1) and 27% (batch 16) of its step; riding along, 11% and 15% (session 31).
        index, count = tree_contacts.tilted(contact)
        tilts = jax.lax.stop_gradient(tree_contacts.tilts(contact, index, structure.num_bodies))
    factors = factor(model, bodies, held, points, angular, contact)
    solved = solve(model, factors, bodies, point_multipliers, points, angular, contact, tilts, load)
    dx, dtheta, kappa, contact_steps = solved[:4]
    jammed = None
    if tilts is not None:  # a decision only: no gradient flows through it
        stop = jax.lax.stop_gradient
        frozen = contact._replace(jacobian=stop(contact.jacobian), compliance=stop(contact.compliance),
                                  gap=stop(contact.gap))  # fmt: skip
        step = stop(jnp.concatenate([dx, dtheta], axis=-1))
        jammed = tree_contacts.jammed(frozen, index, count, stop(solved[4]))
        jammed = jammed | tree_contacts.slides_with_its_friction(frozen, step)
    increments = jnp.zeros((structure.num_joints, joint_family.NUM_MULTIPLIERS), kappa.dtype)
    if angular is not None:
        increments = angular_increments(structure, angular, kappa[:, 3:])
    increments = increments.at[:, _POINT].set(kappa[:, :3])
    return _Solved(dx, dtheta, increments, angular, contact, contact_steps, factors, jammed)


def _closing_step(model: Model, factors: Factors, bodies: BodySet, multipliers: jnp.ndarray
                  ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:  # fmt: skip
    """A chord step on what a solve's linearisation left of the joints' point gaps at `bodies`
    (after the step): the factors of that solve, the points' gaps (DBD (53)-(54), plus alpha
    lambda, (47)) measured again, every other row's error held where it is. Returns (dx, dtheta)
    (N + 1, 3) to add and the joints' point multiplier steps (J, 3).

    Why. A solve is one Newton step: it leaves of each gap the second order of its rotation (a
    leg turned by theta leaves about theta^2 / 2 of its length). Brax's ant landing at dt = 0.01
    with one sweep (dbd-tree-1): the sweep's solve turned its legs 0.089 rad, leaving 0.91 mm of
    its 10 mm; the whole solve turned them back 0.088 rad (the armature and limits it adds), and
    left 0.76 mm. The chord step reuses that solve's factors (no new factor, one more pass), so
    the gaps it leaves are of the order of the step times how far the Jacobians moved. The other
    rows (angular, contacts) are asked to stay put to first order, and their multipliers take no
    step: the correction is of the size of the gaps it closes."""
    world, num_joints = model.structure.num_bodies, model.structure.num_joints
    delta, _, _ = point_gaps(model, bodies)
    delta = delta + model.joints.regularization[:, None] * multipliers[:, _POINT]
    rows = factors.matrices.shape[-2]
    delta = jnp.concatenate([delta, jnp.zeros((num_joints, rows - 3), delta.dtype)], axis=-1)
    gap = _slot_rows(factors, delta)  # (L, W, R)
    x, kappa_slots = _eliminate_and_substitute(factors, gap, jnp.zeros((world + 1, 6), delta.dtype))
    kappa = _joint_rows(factors, kappa_slots, num_joints)
    return x[:, :3], x[:, 3:], kappa[:, :3]


class _ActiveSet(NamedTuple):
    """What one solve of `direct_step`'s active-set step is taken with."""

    contact_multipliers: tuple  # `Touching.multipliers`, plus the loads of the points settled ((): no contacts)
    multipliers: jnp.ndarray  # (J, joints.NUM_MULTIPLIERS) the joints', plus the saturated drives' loads
    saturated: jnp.ndarray | None  # (J, 3) bool: drive rows left out (None: no drive has a torque limit)
    settled: tree_contacts.Settled | None  # the contacts' active set (None: no contacts)
    load: jnp.ndarray  # (N + 1, 6) the left-out rows' loads on their bodies (force, torque)
    drive_load: jnp.ndarray  # (J, 3) each saturated drive row's multiplier step


def direct_step(model: Model, bodies: BodySet, touching: tree_contacts.Touching | None = None,
                multipliers: jnp.ndarray | None = None, targets: tuple | None = None, close: bool = False,
                ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, tuple]:  # fmt: skip
    """`factor` and `solve` at the configuration of `bodies`, its joints measured once: (dx, dtheta)
    (N + 1, 3) to add, the joints' multiplier steps (J, joints.NUM_MULTIPLIERS) and the contact
    groups' ((C, 4 P) each, () without `touching`).
    touching: the substep's contacts and their multipliers so far (`tree_contacts.Touching`): the
    points between a body of the tree and the world are rows of the solve, the bodies of contacts
    between two moving bodies held along their normals; None: no contacts.
    multipliers: (J, joints.NUM_MULTIPLIERS) so far this substep (None: zero). targets: (the
    substep's `joints.Targets`, h) to solve the joints' rotation locks, rotors, angle limits and
    drives with their points (`angular_rows`), or None for the points alone. close: end with a
    chord step on what the solve's linearisation left of the joints' point gaps (`_closing_step`).

    Inequalities by one step of an active set. A contact point the solve would have pull lets go,
    and one whose friction would leave its cone slides on it (`tree_contacts.settle`). A drive with
    a torque limit (DBD (114)) is a linear row only while it stays inside it: one the solve takes
    past its limit is held at the limit's torque (without it, one sweep of a torque-limited arm
    followed by the solve held the arm up with 2.5 times the limit; a drive the sweeps left at its
    limit is out from the start). Each such row's new multiplier step is a load on its bodies, and
    the solve is taken again without the row, at the same configuration, with the load in its
    right-hand side. A solve whose sliding points' tilted rows make it ill-posed
    (`tree_contacts.jammed`, Painleve's case), or whose sliding friction ends up pushing along its
    point's slip (`tree_contacts.slides_with_its_friction`), is not kept: a first solve is taken
    again with every point sticking, a second gives way to the first.
    """
    structure = model.structure
    lam = multipliers
    if lam is None:
        lam = jnp.zeros((structure.num_joints, joint_family.NUM_MULTIPLIERS), bodies.inv_inertia.dtype)

    def chord_factors(factors):  # what the closing step needs of a solve's factors (none without it)
        return (factors.matrices, factors.inverses, factors.root_inverses) if close else ()

    def closed(result, factors):
        if not close:
            return result
        dx, dtheta, increments, contacts = result
        after = bodies._replace(dx=bodies.dx + dx, dtheta=bodies.dtheta + dtheta)
        chord_dx, chord_dtheta, chord_kappa = _closing_step(model, factors, after, lam + increments)
        return dx + chord_dx, dtheta + chord_dtheta, increments.at[:, _POINT].add(chord_kappa), contacts

    limited = targets is not None and bool(_row_groups(structure).drives) and structure.joint_drive_limited.array.any()
    if not limited and touching is None:
        first = _solve_once(model, bodies, None, multipliers, targets)
        return closed((first.dx, first.dtheta, first.increments, ()), first.factors)

    def solved_with(active: _ActiveSet):
        """One solve with `active`: (its result and the factors the closing step needs, the solve)."""
        touching_now = None if touching is None else touching._replace(multipliers=active.contact_multipliers)
        solved = _solve_once(model, bodies, touching_now, active.multipliers, targets, active.saturated,
                             active.settled, active.load)  # fmt: skip
        contacts = ()
        if touching is not None:
            contacts = tree_contacts.increments(touching, solved.contact_steps + active.settled.load)
        result = (solved.dx, solved.dtheta, solved.increments.at[:, _DRIVE].add(active.drive_load), contacts)
        return (result, *chord_factors(solved.factors)), solved

    def active_set_after(first: _Solved, active: _ActiveSet):
        """The active set a second solve is taken with after the `first` (taken with `active`), and
        () bool whether any row changed."""
        changed = jnp.zeros((), bool)
        saturated, drive_load = active.saturated, jnp.zeros_like(lam[:, _DRIVE])
        load = jnp.zeros((structure.num_bodies + 1, 6), bodies.dx.dtype)  # force and torque on each body
        if limited:
            _, h = targets
            before, after = lam[:, _DRIVE], lam[:, _DRIVE] + first.increments[:, _DRIVE]
            size, bound = _drive_torque(model, after, h)
            saturated = first.angular.spring_on[-1] & (size > bound)
            changed = jnp.any(saturated)
            # (114); bound and size read only where saturated (an unlimited drive's inf bound would
            # make the branch that is not taken inf, and its zero cotangent NaN in reverse mode).
            scale = jnp.where(saturated, bound, 0.0) / jnp.where(saturated, size, 1.0)
            drive_load = jnp.where(saturated, after * scale - before, 0.0)  # each saturated row's multiplier step
            # The load turns b by d load and a by -d load, d each row's direction.
            torque = jnp.einsum("jkc,jk->jc", first.angular.directions[:, -3:], drive_load)
            ends = np.stack([structure.joint_body_a.array, structure.joint_body_b.array], axis=-1)  # (J, 2)
            load = load.at[ends.reshape(-1), 3:].add(jnp.stack([-torque, torque], axis=1).reshape(-1, 3))
        settled, contact_multipliers = active.settled, active.contact_multipliers
        if touching is not None:
            settled = tree_contacts.settle(touching, first.contact, first.contact_steps,
                                           jnp.concatenate([first.dx, first.dtheta], axis=-1))  # fmt: skip
            # A first solve the sliding points' tilts made ill-posed is taken again with every point
            # sticking, and that is the step (its active set unsettled).
            jammed = first.jammed
            settled = jax.tree.map(lambda a, b: jnp.where(jammed, a, b), tree_contacts.sticking(settled), settled)
            changed = changed | settled.changed
            load = load + tree_contacts.applied(first.contact, settled.load, structure.num_bodies)
            loads = tree_contacts.increments(touching, settled.load)
            contact_multipliers = tuple(
                lam_c + load_c for lam_c, load_c in zip(touching.multipliers, loads, strict=True)
            )
        # The load is a right-hand side of the second solve, linearised where the first was. (Moving
        # the bodies first by their free response M~^-1 load and linearising there turned a leg of
        # Brax's ant 0.99 rad before the solve when two feet let go on landing; the rows measured
        # there were far off, and its joints opened 0.6-5 mm in one step instead of 0.007-0.7.)
        again = _ActiveSet(contact_multipliers, lam.at[:, _DRIVE].add(drive_load), saturated, settled, load, drive_load)
        return again, changed

    # Both solves are one traced `solved_with`, in a scan of two turns: the second only where a row
    # changed (unbatched; under vmap both run, as a select, which under shard_map `sharding.cond`
    # writes out). Traced as two copies, grad of a rollout of Brax's humanoid (dbd-tree-1) took 176 s
    # to lower and compile, 160 s as one (the rollout 26 -> 22 s), its step as fast. With `close`,
    # the kept solve's factors come out too, so the closing step runs once, after.
    def in_turn(carry, second):
        active, kept, changed = carry

        def take(_):
            new, solved = solved_with(active)
            if touching is not None:  # a second solve that jams gives way to the first
                new = jax.tree.map(lambda a, b: jnp.where(second & solved.jammed, a, b), kept, new)
            # After the second solve nothing follows: its active set is not worked out (the turn is
            # not batched, so this is a branch under vmap too).
            again, changed_now = jax.lax.cond(second, lambda _: (active, changed),
                                              lambda _: active_set_after(solved, active), None)  # fmt: skip
            return again, new, changed_now

        return sharding.cond(second & ~changed, lambda _: carry, take, None), None

    first = _ActiveSet(
        contact_multipliers=() if touching is None else touching.multipliers,
        multipliers=lam,
        saturated=jnp.zeros((structure.num_joints, 3), bool) if limited else None,
        settled=None if touching is None else tree_contacts.unsettled(touching),
        load=jnp.zeros((structure.num_bodies + 1, 6), bodies.dx.dtype),
        drive_load=jnp.zeros_like(lam[:, _DRIVE]),
    )
    # The kept solve, a placeholder until the first turn fills it (a scan's carry is shaped before it runs).
    kept = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(lambda: solved_with(first)[0]))
    start = sharding.varying_like((first, kept, jnp.zeros((), bool)), bodies, lam, touching, targets)  # (shard_map)
    (_, kept, _), _ = jax.lax.scan(in_turn, start, jnp.arange(2) == 1)
    result, *kept_factors = kept
    if not close:
        return result
    return closed(result, Factors(*_slots(structure), *kept_factors))
