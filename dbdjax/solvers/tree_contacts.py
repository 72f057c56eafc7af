"""The contacts in the direct solves of `tree_solve` (solvers/tree.py): rows to the fixed world,
unilateral and inside the friction cone by one active-set step.

Why. Without them a direct step closes the joints by pulling a standing doll's feet toward its
body, and it collapses. Session 24 held the touching bodies along their normals instead (a
stiffness with no error and no multiplier, `contact_hold`, now only for contacts between two
moving bodies): that hold carried the weight the contacts should (the standing ragdoll's feet took
29 N of its 687 N), glued the feet in both directions and did not pull a rising heel back, so a leaning doll
toppled forwards as a rigid plank (docs/brax_comparison.md, session 26).

How. A contact point between a moving body and the world has three rows (DBD (84)-(91): the gap
along n and the slip along t1, t2, as `contacts.project_contacts` has them), each touching one
body: as a joint whose other side is the fixed world, it adds J^T alpha^-1 J to that body's block
and J^T alpha^-1 (-r) to its right-hand side, and no loop to the tree (tree.py: a row whose child
is the world has S = alpha). Its multiplier step after the solve is kappa = -(r + J dX) / alpha,
DBD (49). The rows are rigid, alpha a regularisation 1 / (HOLD m) that leaves an error of
kappa / (HOLD m) (a resting body's g h^2 / HOLD), plus the model's contact compliance on the normal
row (r = c + compliance lambda_n, as the sweeps take it).

Which rows (`contact_rows`, then one active-set step, `settle`, taken with the drives' torque limits
in `tree.direct_step`). A point is in the solve where its slot is active and it pushes (lambda_n >
0) or penetrates, and sticks, unless it was sliding at the start of the substep and the sweeps left
its friction on the cone |kappa_t| = mu lambda_n (93): then it slides, without friction rows, its
normal row pushing along J_n + mu s J_t (s its friction's direction), so that its friction stays mu
lambda_n as lambda_n changes. After the solve: a point whose total lambda_n would pull lets go
(lambda_n and its friction to 0); a sticking point whose friction leaves its cone, or every sticking
point of a pair whose friction in all exceeds the sum of its points' cones, slides (its friction on
the cone of its lambda_n so far); a point that was out and that the solve takes into the floor
comes in. Each change is a load on its body, and the solve is taken again with it (`tree.direct_step`).

Painleve's case (`jammed`). A tilted row is not symmetric: with the other rows pinning its body
(a foot held by its other points and the leg's joints), a sliding point's friction can drive it
into the floor faster than its normal row pushes it out, and the solve flips the sign of its
lambda_n or multiplies it many times over (the standing ragdoll's foot at 2 x 2 went from 0.2 to
40 m/s in two steps). Each solve with tilted rows measures how much the tilts change the points'
normal responses (one more right-hand side of the solve per tilted point, at most TILTED); where
they could more than double them or turn their sign, the point jams: sticking is the answer, as
for a rigid body in Painleve's paradox. A jammed first solve is taken again with every point
sticking; a jammed second solve gives way to the first.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from dbdjax import integrator, math
from dbdjax.constraints import contacts as contact_family
from dbdjax.constraints.rows import BodySet
from dbdjax.indexing import segment_sum
from dbdjax.model import Model, with_world_row

# The regularisation of a contact row, alpha = 1 / (HOLD m) with m its body's mass: the row then
# leaves 1 / HOLD of what its body alone would move (its effective inverse mass is 1/m to a few
# times that). Session 24's hold used the same stiffness (1000 m) to keep the standing ragdoll's
# bodies within 0.8 mm of their build pose over 4 s.
HOLD = 1000.0
# A friction the sweeps left within this fraction of its cone is on the cone.
ON_THE_CONE = 1e-4
# At most this many sliding points are checked for Painleve's case (`jammed`) in one solve.
TILTED = 4
# A sliding point's slip (m) below which its direction says nothing (`slides_with_its_friction`).
SLIP = 1e-6


class Touching(NamedTuple):
    """What the direct solves read of the substep's contacts."""

    slots: tuple  # the substep's `collision.ContactSlots`, one per contact group
    multipliers: tuple  # (C, 4 P) per group: (lambda_n, kappa_t1, kappa_t2, unused) per point so far
    compliance_h2: float  # the model's contact compliance / h^2
    held: jnp.ndarray | None = None  # (N + 1, 6, 6) `contact_hold` of the substep, or None


class ContactRows(NamedTuple):
    """The rows of every contact group's points with the world, flattened: R = sum of 3 C P (n, t1,
    t2 per point, group by group), each on one moving body."""

    body: np.ndarray  # (R,) the moving body (the world for a row that is never on)
    jacobian: jnp.ndarray  # (R, 6) dc / d(dx, dtheta) of that body
    push: jnp.ndarray  # (R, 6) what a unit multiplier does to it: J, tilted by the friction of a sliding point
    compliance: jnp.ndarray  # (R,) alpha
    residual: jnp.ndarray  # (R,) r = c + alpha_compliance lambda (0 where off)
    on: jnp.ndarray  # (R,) bool
    multipliers: jnp.ndarray  # (R,) lambda so far
    slide: jnp.ndarray  # (R,) a sliding point's friction rows: mu s_k, its step per unit normal step (else 0)
    gap: jnp.ndarray  # (R,) each row's error c now, on or off (a normal row's: the gap along n)
    touches: jnp.ndarray  # (R,) bool: the rows of points that may touch (slot active, a tree body on the world)


class Settled(NamedTuple):
    """`settle`'s active-set step, per row (R,) in `ContactRows` order."""

    off: jnp.ndarray  # bool: the rows of the points that let go
    sliding: jnp.ndarray  # bool: the rows of the points that slide (friction on the cone, no friction rows)
    direction: jnp.ndarray  # a sliding point's rows: (0, s_1, s_2), its friction's unit direction in the plane
    enter: jnp.ndarray  # bool: the rows of points that were out and the solve took into the floor
    load: jnp.ndarray  # the multiplier step each row takes instead of the solve's (0: none)
    changed: jnp.ndarray  # () bool: whether any point let go or slides


def _sides(model: Model, group, tree_bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Host side: (moving (C,), b_moves (C,), usable (C,)) of a contact group's pairs: the body
    that moves, whether it is side b, and whether the pair is one moving body of the joint forest
    (`tree_bodies`, its slots' bodies) against the world (a pair of two moving bodies would close a
    loop; a body outside the forest gets no direct solve)."""
    world = model.structure.num_bodies
    pair = group.bodies.array
    b_moves = pair[:, 0] == world
    moving = np.where(b_moves, pair[:, 1], pair[:, 0])
    in_forest = np.zeros(world + 1, dtype=bool)
    in_forest[np.asarray(tree_bodies).reshape(-1)] = True
    in_forest[world] = False
    return moving, b_moves, ((pair == world).sum(axis=1) == 1) & in_forest[moving]


def _grouped(rows: jnp.ndarray, touching: Touching) -> list[jnp.ndarray]:
    """A flattened (R, ...) row array split into its contact groups' parts, (C, P, 3, ...) each."""
    parts, start = [], 0
    for slots in touching.slots:
        pairs, points = slots.active.shape
        parts.append(rows[start : start + 3 * pairs * points].reshape((pairs, points, 3) + rows.shape[1:]))
        start += 3 * pairs * points
    return parts


def _mu(slots) -> jnp.ndarray:
    """(C, P) each point's friction coefficient: its dynamic one where it slid at the start of the substep."""
    return jnp.where(slots.sliding, slots.dynamic_friction[:, None], slots.friction[:, None])


def _point_multipliers(slots, lam: jnp.ndarray) -> jnp.ndarray:
    """(C, P, 3) each point's multipliers so far (lambda_n, kappa_t1, kappa_t2), from its group's (C, 4 P)."""
    pairs, points = slots.active.shape
    return lam.reshape(pairs, points, contact_family.MULTIPLIERS_PER_POINT)[..., :3]


def _friction_direction(lam: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Of each point's multipliers (C, P, 3): its friction's direction as rows (C, P, 3), (0, s_1, s_2)
    with s its unit direction in the plane (0 where it has none), and its size |kappa_t| (C, P)."""
    direction, size = math.safe_normalize(jnp.concatenate([lam[..., 1:], jnp.zeros_like(lam[..., :1])], -1))
    return jnp.concatenate([jnp.zeros_like(size)[..., None], direction[..., :2]], axis=-1), size


def unsettled(touching: Touching) -> Settled:
    """The active set the first direct solve is taken with, before any `settle`: no point let go or
    entered, and a point slides where it was already sliding at the start of the substep and the
    sweeps left its friction on the cone |kappa_t| = mu lambda_n (93), along that friction (a point
    at rest sticks first, `settle`); per row (R,) in `ContactRows` order, as `settle` gives it."""
    slidings, directions = [], []
    for slots, lam in zip(touching.slots, touching.multipliers, strict=True):
        mu, lam = _mu(slots), _point_multipliers(slots, lam)
        direction, size = _friction_direction(lam)
        on_cone = (size > 0.0) & (size >= (1.0 - ON_THE_CONE) * mu * lam[..., 0])
        slidings.append(jnp.repeat((slots.sliding & on_cone)[..., None], 3, axis=-1).reshape(-1))
        directions.append(direction.reshape(-1))
    sliding, direction = jnp.concatenate(slidings), jnp.concatenate(directions)
    false = jnp.zeros_like(sliding)
    return Settled(off=false, sliding=sliding, direction=direction, enter=false,
                   load=jnp.zeros_like(direction), changed=jnp.zeros((), bool))  # fmt: skip


def contact_rows(model: Model, bodies: BodySet, touching: Touching, tree_bodies: np.ndarray,
                 settled: Settled) -> ContactRows:  # fmt: skip
    """The rows of every point between a moving body of the joint forest and the world, at the
    configuration of `bodies` (the solver's table, N + 1 rows, the world last). tree_bodies: the
    forest's slot bodies (`tree.forest(structure)[1]`). settled: the active set (`unsettled` for a
    first solve, then the step `settle` took): points that let go are off, points that entered are
    on, sliding points have no friction rows; every other point that pushes sticks."""
    parts = []
    mass = with_world_row(model.bodies.mass)
    # per group, per point (each point's three rows share these)
    fields = (settled.enter, settled.off, settled.sliding, settled.direction)
    settled_parts = zip(*(_grouped(x, touching) for x in fields), strict=True)
    for group, slots, lam in zip(model.structure.contact_groups, touching.slots, touching.multipliers, strict=True):
        moving, b_moves, usable = _sides(model, group, tree_bodies)
        mu, lam = _mu(slots), _point_multipliers(slots, lam)
        flip = b_moves[:, None, None]
        local = jnp.where(flip, slots.local_b, slots.local_a)  # (C, P, 3) on the moving body
        fixed = jnp.where(flip, slots.local_a, slots.local_b)  # (C, P, 3) world coordinates
        quat = integrator.displaced_quat(bodies.quat[moving], bodies.dtheta[moving])  # X* + dX
        arm = math.quat_rotate(quat[:, None, :], local)
        point = (bodies.origin[moving][:, None] - fixed) + bodies.dx[moving][:, None] + arm  # moving - fixed
        sign = np.where(b_moves, 1.0, -1.0)[:, None, None]
        separation = sign * point  # p_b - p_a
        directions = contact_family.row_directions(slots.normal)  # (C, P, 3, 3)
        # the gap (p_b - p_a) . n (84) less the depth the point may keep this substep, and the slip
        # in the plane (89), as the sweeps measure them
        error = jnp.einsum("cpki,cpi->cpk", directions, separation - slots.offset)
        gap = jnp.einsum("cpi,cpi->cp", directions[..., 0, :], separation)
        error = error.at[..., 0].set(gap + slots.allowed_depth)
        jacobian = sign[..., None] * jnp.concatenate([directions, math.cross(arm[..., None, :], directions)], -1)
        regularisation = 1.0 / (HOLD * jnp.where(usable, mass[moving], 1.0))[:, None, None]  # finite off the forest
        normal_row = np.arange(3) == 0
        compliance = regularisation + jnp.where(normal_row, touching.compliance_h2, 0.0)
        residual = error + jnp.where(normal_row, touching.compliance_h2 * lam, 0.0)
        touches = usable[:, None] & slots.active  # (C, P)
        enter, off, slides, direction = next(settled_parts)
        pushes = (touches & ((lam[..., 0] > 0.0) | (error[..., 0] < 0.0) | enter[..., 0])) & ~off[..., 0]
        sliding = pushes & slides[..., 0]
        friction_direction = direction[..., 1:]
        # A sliding point (its friction on the cone |kappa_t| = mu lambda_n, (93)) has no friction
        # rows: its friction stays mu lambda_n along s = kappa_t / |kappa_t| as lambda_n changes,
        # so its normal row pushes along J_n + mu (s_1 J_t1 + s_2 J_t2).
        tilt = jnp.where(sliding[..., None], mu[..., None] * friction_direction, 0.0)  # (C, P, 2)
        push = jacobian.at[..., 0, :].add(jnp.einsum("cpk,cpkj->cpj", tilt, jacobian[..., 1:, :]))
        on = jnp.stack([pushes, pushes & ~sliding, pushes & ~sliding], axis=-1)
        slide = jnp.concatenate([jnp.zeros_like(tilt[..., :1]), tilt], axis=-1)
        body = np.broadcast_to(np.where(usable, moving, model.structure.num_bodies)[:, None, None], on.shape)
        parts.append((body, jacobian, push, jnp.broadcast_to(compliance, on.shape), residual, on, lam, slide, error,
                      jnp.broadcast_to(touches[..., None], on.shape)))  # fmt: skip
    body, jacobian, push, compliance, residual, on, lam, slide, error, touches = (
        [part.reshape((-1,) + part.shape[3:]) for part in column] for column in zip(*parts, strict=True)
    )
    on = jnp.concatenate(on)
    return ContactRows(
        body=np.concatenate(body),
        jacobian=jnp.concatenate(jacobian),
        push=jnp.concatenate(push),
        compliance=jnp.concatenate(compliance),
        residual=jnp.where(on, jnp.concatenate(residual), 0.0),
        on=on,
        multipliers=jnp.concatenate(lam),
        slide=jnp.concatenate(slide),
        gap=jnp.concatenate(error),
        touches=jnp.concatenate(touches),
    )


def _per_body(values: jnp.ndarray, body, count: int) -> jnp.ndarray:
    """values (R, ...) summed per body (count, ...): without a scatter where `body` is known when
    tracing (`indexing.segment_sum`), as a scatter where the rows came through a jit as arguments."""
    if isinstance(body, np.ndarray):
        return segment_sum(values, body, count)
    return jnp.zeros((count,) + values.shape[1:], values.dtype).at[body].add(values)


def added_blocks(rows: ContactRows, num_bodies: int) -> jnp.ndarray:
    """(N + 1, 6, 6) what the rows that are on add to their bodies' blocks: sum P^T alpha^-1 J, P the
    row's push (J, or tilted by a sliding point's friction: then the block is not symmetric)."""
    weight = jnp.where(rows.on, 1.0 / rows.compliance, 0.0)  # (R,)
    block = weight[:, None, None] * rows.push[:, :, None] * rows.jacobian[:, None, :]
    return _per_body(block, rows.body, num_bodies + 1)


def added_right_sides(rows: ContactRows, num_bodies: int) -> jnp.ndarray:
    """(N + 1, 6) what the rows that are on add to their bodies' right-hand sides z: sum P^T alpha^-1 (-r)."""
    right = jnp.where(rows.on, -rows.residual / rows.compliance, 0.0)[:, None] * rows.push
    return _per_body(right, rows.body, num_bodies + 1)


def row_moves(rows: ContactRows, step: jnp.ndarray) -> jnp.ndarray:
    """(R,) J dX: how far a solve's step (N + 1, 6) of every body moves each row."""
    return jnp.sum(rows.jacobian * step[rows.body], axis=-1)


def sliding_points(rows: ContactRows) -> jnp.ndarray:
    """(R / 3,) bool: the points that slide (normal row on, friction rows off; `contact_rows`)."""
    return rows.on[::3] & ~rows.on[1::3]


def row_steps(rows: ContactRows, step: jnp.ndarray) -> jnp.ndarray:
    """(R,) each row's multiplier step kappa = -(r + J dX) / alpha, given the solve's (N + 1, 6) step
    (dx, dtheta) of every body, a sliding point's friction mu s times its normal's; 0 where off."""
    steps = jnp.where(rows.on, -(rows.residual + row_moves(rows, step)) / rows.compliance, 0.0).reshape(-1, 3)
    return (steps + rows.slide.reshape(-1, 3) * steps[:, :1]).reshape(-1)


def settle(touching: Touching, rows: ContactRows, steps: jnp.ndarray, step: jnp.ndarray) -> Settled:
    """One active-set step on the solve's contact multiplier steps (R,), every point that pushes
    sticking. A point whose total lambda_n would pull lets go: its three multipliers to 0, its rows
    off. A point whose friction would leave the cone |kappa_t| <= mu lambda_n (DBD (93)) slides:
    its friction goes on the cone of its lambda_n so far, along where the solve took it, and the
    solve taken again has its normal row push along the friction too (`contact_rows`). (A point
    the sweeps left sliding is taken as sticking first: with one sweep its lambda_n is still short
    of its load, and a box held on a 25-degree slope by mu = 0.5 crept 7 mm/s as four sliding corners.)
    A point that was out of the solve and that its step (N + 1, 6) takes into the floor enters it.
    (Without, Brax's ant at 4 iterations rebounded 0.3 J after landing: the solve pushed feet that
    had only just touched into the floor.)"""
    offs, slidings, directions, loads, enters = [], [], [], [], []
    changed = jnp.zeros((), bool)
    per_group = (_grouped(x, touching) for x in (rows.multipliers, rows.on, steps, rows.jacobian[:, :3],
                                                  rows.gap + row_moves(rows, step), rows.touches))  # fmt: skip
    for slots, lam, on, step_here, along, gap_after, touches in zip(touching.slots, *per_group, strict=True):
        total = lam + step_here  # along: +-(n, t1, t2); gap_after: linearised
        enter = touches[..., 0] & ~on[..., 0] & (gap_after[..., 0] < 0.0)
        lets_go = on[..., 0] & (total[..., 0] < 0.0)  # (C, P)
        mu = _mu(slots)
        direction, size = _friction_direction(total)  # direction (0, s_1, s_2)
        sticking = on[..., 1] & ~lets_go
        capacity = mu * jnp.maximum(total[..., 0], 0.0)
        # Each point within its own cone, and each pair within the sum of its points' cones: a body
        # whose friction in all exceeds what its points can give slides on all of them (its points'
        # frictions are not unique, and a solve that put more of it where there is more load would
        # still exceed; without this a stack on a 35-degree slope, mu = 0.5, stuck with its downhill
        # corners past their cones once its uphill ones slid).
        friction = jnp.where(sticking[..., None], total[..., 1:], 0.0)
        world_friction = jnp.einsum("cpk,cpki->ci", friction, along[..., 1:, :])
        pair_slides = math.safe_norm(world_friction) > jnp.sum(jnp.where(sticking, capacity, 0.0), axis=-1)  # (C,)
        slides = sticking & ((size > capacity) | pair_slides[:, None])
        slid = on[..., 0] & ~on[..., 1] & ~lets_go  # sliding in this solve already: stays so
        friction = mu[..., None] * lam[..., :1] * direction[..., 1:] - lam[..., 1:]
        load = jnp.where(lets_go[..., None], -lam, 0.0)
        load = load.at[..., 1:].add(jnp.where(slides[..., None], friction, 0.0))
        loads.append(load.reshape(-1))
        offs.append(jnp.repeat(lets_go[..., None], 3, axis=-1).reshape(-1))
        slidings.append(jnp.repeat((slides | slid)[..., None], 3, axis=-1).reshape(-1))
        directions.append(direction.reshape(-1))
        enters.append(jnp.repeat(enter[..., None], 3, axis=-1).reshape(-1))
        changed = changed | jnp.any(lets_go) | jnp.any(slides) | jnp.any(enter)
    off, sliding, direction, load, enter = (jnp.concatenate(x) for x in (offs, slidings, directions, loads, enters))
    return Settled(off=off, sliding=sliding, direction=direction, load=load, changed=changed, enter=enter)


def tilted(rows: ContactRows) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The points whose normal rows are tilted (sliding, `contact_rows`): (TILTED,) their indices
    (R / 3 where fewer slide) and () how many slide."""
    sliding = sliding_points(rows)
    (index,) = jnp.nonzero(sliding, size=TILTED, fill_value=len(sliding))
    return index, jnp.sum(sliding)


def tilts(rows: ContactRows, index: jnp.ndarray, num_bodies: int) -> jnp.ndarray:
    """(TILTED, N + 1, 6) the load that each tilted point's tilt (`tilted`) is on its body:
    u = mu (s_1 J_t1 + s_2 J_t2) (0 for padding)."""
    u = jnp.concatenate([rows.push[::3] - rows.jacobian[::3], jnp.zeros((1, 6), rows.push.dtype)])[index]
    body = jnp.asarray(np.append(rows.body[::3], num_bodies))[index]
    return jnp.zeros((len(index), num_bodies + 1, 6), u.dtype).at[jnp.arange(len(index)), body].set(u)


def jammed(rows: ContactRows, index: jnp.ndarray, count: jnp.ndarray, response: jnp.ndarray) -> jnp.ndarray:
    """() bool: whether the sliding points' tilts make the solve ill-posed, from its responses
    A^-1 u (TILTED, N + 1, 6) to each tilted point's tilt (`tilted`, `tilts`).
    Q[i, k] = J_n,i A^-1 u_k / alpha_i says how far point k's tilt moves point i along its normal, in
    units of its row; by Woodbury, the points' normal responses with the tilts are (1 - Q) times
    those without them (A the tilted system, as the solve factored it: with Q_0 the same measured
    on the untilted one, 1 - Q = (1 + Q_0)^-1, so one solve gives both). Jammed: a point whose row
    of Q sums to 1 or more in magnitude. Below that every eigenvalue of 1 - Q lies in the right
    half-plane within 2 of 0 (Gershgorin): the tilts at most double the normal responses and never
    turn their sign. Above it, Painleve's case: a friction that drives its point into the floor (the
    standing ragdoll's foot, one point pinned by its neighbours, went to 40 m/s in two steps). More
    than TILTED sliding points: jammed too."""
    real = index < len(rows.body) // 3
    safe = jnp.where(real, index, 0)
    jacobian, compliance = rows.jacobian[::3][safe], rows.compliance[::3][safe]
    body = jnp.asarray(rows.body[::3])[safe]
    couplings = jnp.einsum("ij,kij->ik", jacobian, response[:, body]) / compliance[:, None]  # Q (TILTED, TILTED)
    reach = jnp.sum(jnp.abs(jnp.where(real[None, :], couplings, 0.0)), axis=1)
    return jnp.any(real & (reach >= 1.0)) | (count > TILTED)


def slides_with_its_friction(rows: ContactRows, step: jnp.ndarray) -> jnp.ndarray:
    """() bool: whether a sliding point's friction pushes along its slip after the solve's step
    (N + 1, 6) rather than against it (kinetic friction, DBD (92)-(93), opposes the slip). Its direction
    was chosen before the solve (the sweeps' friction, or where `settle` found the sticking
    friction); a solve that then moves the point along it has its friction do work on the body.
    Brax's ant landing with random controls: a foot that `settle` turned to sliding slid 0.27 m in
    one step along its friction, and the ant's energy went from 6.5 J to 77 J."""
    slip = (rows.gap + row_moves(rows, step)).reshape(-1, 3)[:, 1:]  # along t1, t2 this substep
    along = jnp.sum(rows.slide.reshape(-1, 3)[:, 1:] * slip, axis=-1)
    return jnp.any(sliding_points(rows) & (along > 0.0) & (math.safe_norm(slip) > SLIP))


def sticking(settled: Settled) -> Settled:
    """`settled` with every point that pushes sticking in the solve taken again (none let go, none
    slides, none enters, no loads)."""
    false = jnp.zeros_like(settled.off)
    return Settled(off=false, sliding=false, direction=jnp.zeros_like(settled.direction), enter=false,
                   load=jnp.zeros_like(settled.load), changed=jnp.ones((), bool))  # fmt: skip


def applied(rows: ContactRows, load: jnp.ndarray, num_bodies: int) -> jnp.ndarray:
    """(N + 1, 6) the force and torque J^T load that the rows' loads (R,) put on their bodies."""
    return _per_body(load[:, None] * rows.jacobian, rows.body, num_bodies + 1)


def increments(touching: Touching, steps: jnp.ndarray) -> tuple[jnp.ndarray, ...]:
    """The rows' multiplier steps (R,) in the contact families' layout: (C, 4 P) per group."""
    return tuple(
        jnp.concatenate([step, jnp.zeros_like(step[..., :1])], axis=-1).reshape(len(step), -1)
        for step in _grouped(steps, touching)
    )


def contact_hold(model: Model, bodies: BodySet, contacts: tuple) -> jnp.ndarray | None:
    """(N + 1, 6, 6) stiffness that holds the bodies of contacts between two moving bodies (which
    would close loops as rows) along their normals in the direct solve: k J^T J per slot and side,
    J = n^T [1, -[r]x] the point's normal row, k = HOLD x the body's mass. No error and no
    multiplier: it shapes the step, the sweeps' contact rows keep the last word. None where no
    contact group has such pairs. contacts: the substep's `collision.ContactSlots`."""
    world = model.structure.num_bodies
    dtype = bodies.inv_inertia.dtype
    held = None
    mass = with_world_row(model.bodies.mass)
    for group, slots in zip(model.structure.contact_groups, contacts, strict=True):
        both_move = (group.bodies.array != world).all(axis=1)
        if not both_move.any():
            continue
        held = jnp.zeros((world + 1, 6, 6), dtype) if held is None else held
        for side, local in enumerate((slots.local_a, slots.local_b)):
            body = np.where(both_move, group.bodies.array[:, side], world)  # (C,)
            arm = math.quat_rotate(bodies.quat[body][:, None, :], local)  # (C, P, 3) from the centre
            normal = jnp.concatenate([slots.normal, math.cross(arm, slots.normal)], axis=-1)  # n . (dx + dtheta x r)
            k = HOLD * mass[body][:, None] * (slots.active & both_move[:, None]).astype(dtype)  # (C, P)
            held = held.at[body].add(jnp.sum(k[..., None, None] * normal[..., :, None] * normal[..., None, :], axis=1))
    return held
