"""DBD Algorithm 1: non-linear Gauss-Seidel over colour groups.

    prepare:  inverse masses and world inverse inertias at X* (once per substep), and each
              colour's constraint parameters gathered into its own arrays
    guess:    dX = 0, or with initial_guess="tree" dX and the joints' point multipliers from the
              exact linear solve of the joint tree's point constraints (solvers/tree.py)
    repeat `iterations` times:                                   (lax.scan)
        for each colour, in order:                               (runs of alike colours: lax.scan)
            for each constraint family present in the colour (each variant of it: the joints by kind):
                project all its nodes at once                    (jax.vmap, constraints/*.py)
            write back the displacements of the bodies moved     (one gather: no conflicts)
        with tree_solve: the exact solve of the joint tree's points from there (solvers/tree.py),
            but after the last sweep where the whole-joint solve below follows
    with tree_solve: one exact solve of the whole joint tree (points, rotation locks, rotors, the
        soft limits past their bounds, drives within their torque limits) from where the sweeps ended

Only displacements dX from X* are accumulated; the caller applies them with (36)-(39).
With `jacobi`, every node is projected at once from the same dX and each body moves by the
average of what its nodes ask (for comparison; it converges more slowly).

`rotor_momentum` and `restitution` are the velocity passes after the position solve: coloured
sweeps over the joints with armature (their rotors' spin the sweeps gave without an impulse
behind it, taken back) and over the contact groups, moving velocities instead of displacements.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import colouring, constraints, indexing, integrator, math, sharding
from dbdjax.collision import ContactSlots
from dbdjax.colouring import write_back_slots
from dbdjax.constraints import Family, joints
from dbdjax.constraints.rows import BodySet
from dbdjax.indexing import take
from dbdjax.model import Colour, Model, State, with_world_row
from dbdjax.solvers import tree, tree_contacts

# Sweeps of the rotor pass: Brax's ant dropped at 4 substeps x 4 iterations peaks at 0.32 J in its
# rotors with one, 0.31 J with two (106 J without the pass, 0.66 J with tree_solve); under random
# controls one and two sweeps run it alike (benchmarks/random_controls.py).
ROTOR_PASS_SWEEPS = 1


def body_table(model: Model, state: State, h: float) -> BodySet:
    """The N + 1 rows every constraint reads (row N is the world), with nothing moved yet."""
    dtype = state.pos.dtype
    zeros = jnp.zeros((model.num_bodies + 1, 3), dtype)
    return BodySet(
        origin=with_world_row(state.pos),
        quat=with_world_row(state.quat, jnp.array([1.0, 0.0, 0.0, 0.0], dtype)),
        inv_mass=with_world_row(1.0 / model.bodies.mass),
        inv_inertia=with_world_row(integrator.inverse_inertia(model, state, h)),
        vel=with_world_row(state.vel),
        ang_vel=with_world_row(state.ang_vel),
        dx=zeros,
        dtheta=zeros,
    )


def _fixed(table: BodySet, index) -> BodySet:
    """The columns of `table` that stay put during the sweeps (all but dx, dtheta), gathered at
    `index` once per solve rather than once per colour and iteration."""
    return jax.tree.map(lambda column: take(column, index), table._replace(dx=None, dtheta=None))


def _project(family: Family, fixed: BodySet, dx, dtheta, multipliers, reads: indexing.Rows):
    """Every node of `family` at once: moved rows (M * S, 3) twice, and new multipliers.
    fixed: `_fixed(table, family.bodies)`. reads: `family.bodies` as the rows of dx it reads."""
    bodies = fixed._replace(dx=take(dx, reads), dtheta=take(dtheta, reads))  # (M, S, ...)
    # Rematerialised in reverse mode: the backward pass recomputes each projection from its inputs
    # instead of keeping its hundreds of small intermediates. Inside the sweeps' scans every kept
    # intermediate is a separate array stacked per colour and iteration (a dynamic-update-slice
    # kernel each, and a slice of it on the way back), which cost more to compile, to store and to
    # read back than recomputing the projection does. Measured on the ant (4 iterations, CPU):
    # grad of a 100-step rollout compiled in 85 s instead of 119 s, ran in 0.30 s instead of
    # 0.55 s, with 3.4 MB of temporaries instead of 35 MB; forward passes are unchanged. Without
    # the barrier that keeps XLA from merging the recomputation with the forward pass (prevent_cse):
    # the sweeps' scans keep them apart already (JAX's advice for a checkpoint inside a scan). Grad
    # of a 100-step rollout of Brax's humanoid (DBD, CPU) ran 10% faster with jax.jit's defaults
    # (0.356 against 0.394 s), as fast with `compiler_options()` (0.325 against 0.322 s).
    project = jax.checkpoint(family.project, prevent_cse=False)
    moved_dx, moved_dtheta, multipliers = jax.vmap(project)(family.params, family.static, bodies, multipliers)
    return moved_dx.reshape(-1, 3), moved_dtheta.reshape(-1, 3), multipliers


def _variants(family: Family) -> tuple:
    """(members, project) of each variant of `family` (the family whole where it has none)."""
    return family.variants or ((np.arange(len(family.bodies)), family.project),)


def _present(colour: Colour, families: list[Family]) -> list[tuple[int, int]]:
    """(family, variant) of every variant with nodes in `colour`."""
    return [(f, v) for f, family in enumerate(families) for v, (members, _) in enumerate(_variants(family))
            if np.intersect1d(colour.nodes[f].array, members).size]  # fmt: skip


def _runs(present: list[list[tuple[int, int]]]) -> list[tuple[int, int]]:
    """Consecutive colours with the same variants present: [(first, stop), ...]."""
    runs: list[list[int]] = []
    for c, fs in enumerate(present):
        if runs and present[runs[-1][0]] == fs:
            runs[-1][1] = c + 1
        else:
            runs.append([c, c + 1])
    return [(first, stop) for first, stop in runs]


class _Run:
    """Colours first..stop-1 with the same variants present: stacked for one `lax.scan` over them
    (or called once, for a colour of its own).

    A family with variants (`Family.variants`: the joints, one per kind) is projected as one
    family per variant, each traced with only its own rows; every colour of a run holds the same
    variants, so none runs a variant's kernels for nodes it does not have. Each projected
    variant's nodes are padded to the run's largest colour by repeating the colour's first: its
    arithmetic stays finite, so no NaN reaches a gradient. The padded rows are never read back,
    since `body_slot` (built here for the padded layout) points every moved body at its real
    node's row.
    """

    def __init__(self, colours: tuple[Colour, ...], families: list[Family], first: int, stop: int,
                 present: list[tuple[int, int]], num_bodies: int):  # fmt: skip
        self.length = stop - first
        self.fs, self.nodes, self.index, self.families = [], [], [], []
        for f, v in present:
            family = families[f]
            members, project = _variants(family)[v]
            per_colour = [np.intersect1d(colours[c].nodes[f].array, members) for c in range(first, stop)]
            width = max(len(nodes) for nodes in per_colour)
            index = np.stack([np.concatenate([nodes, np.repeat(nodes[:1], width - len(nodes))])
                              for nodes in per_colour])  # fmt: skip
            gathered = constraints.gather(family, index.reshape(-1))
            reshape = lambda x, shape=index.shape: x.reshape(shape + x.shape[1:])  # noqa: E731
            self.fs.append(f)
            self.nodes.append(per_colour)  # the real nodes of each colour (family node indices)
            self.index.append(index)  # (R, M) padded node indices
            self.families.append(gathered._replace(
                bodies=reshape(gathered.bodies), params=jax.tree.map(reshape, gathered.params),
                static=jax.tree.map(reshape, gathered.static), project=project, variants=()))  # fmt: skip
        self.body_slot = np.stack(
            [
                write_back_slots(
                    [family.bodies[r] for family in self.families],
                    num_bodies,
                    real=[len(nodes[r]) for nodes in self.nodes],
                )
                for r in range(self.length)
            ]
        )  # (R, N + 1)
        # The colours' gathers as rows (their transposes sum without scattering): the bodies each
        # variant's nodes read from dx, dtheta (N + 1, 3), and each body's row read back from the
        # colour's moved rows followed by dx.
        self.reads = [indexing.stacked_rows(family.bodies, num_bodies + 1) for family in self.families]
        moved_rows = sum(int(np.prod(family.bodies.shape[1:])) for family in self.families)
        self.write_back = indexing.stacked_rows(self.body_slot, moved_rows + num_bodies + 1)


class TreeStep(NamedTuple):
    """The direct solve that ends an iteration with `tree_solve` (solvers/tree.py): a function
    (dx, dtheta, [multipliers (M_f, m_f) of each family in `families`]) -> (dx step, dtheta step,
    [their multiplier steps]), the families it solves (the joints first, then the contact groups),
    and how many of the first sweeps it ends (None: every one)."""

    solve: Callable
    families: tuple[int, ...]
    sweeps: int | None = None

    def after_sweep(self, sweep, iterations: int, step: Callable, carry):
        """`step(carry)` if sweep `sweep` (of `iterations`) is one this solve ends, else `carry`.
        The sweep count is not batched: a branch taken, not a select under vmap."""
        if self.sweeps is None or self.sweeps >= iterations:
            return step(carry)
        if self.sweeps <= 0:
            return carry
        return jax.lax.cond(sweep < self.sweeps, step, lambda c: c, carry)


def gauss_seidel(
    colours: tuple[Colour, ...], families: list[Family], table: BodySet, iterations: int, multipliers: list,
    tree_step: TreeStep | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, list]:  # fmt: skip
    """`iterations` sweeps over the colours; multipliers: one (M_f, m_f) array per family, in
    node order, in and out. Returns (dx, dtheta) (N + 1, 3) and the final multipliers.

    Consecutive colours with the same variants (a ragdoll's ball joints' colours) run as one
    `lax.scan` over the colours (`_Run`), so each variant's projection is compiled once, not once
    per colour: the compile time of a jointed model no longer grows with its number of colours. A
    colour of its own (different variants from its neighbours) is unrolled. What does not change during the
    sweeps (the poses, masses, inertias and velocities of the bodies each node reads) is gathered
    once, before them. tree_step: run after each sweep it ends (`TreeStep.after_sweep`; None: none).
    """
    n = table.dx.shape[0] - 1
    present = [_present(colour, families) for colour in colours]
    runs = [_Run(colours, families, first, stop, present[first], n) for first, stop in _runs(present)]
    run_fixed = [[_fixed(table, family.bodies) for family in run.families] for run in runs]
    start = [[take(multipliers[f], index) for f, index in zip(run.fs, run.index, strict=True)] for run in runs]

    def colour(carry, xs, run):
        """One colour: every family of the run projected at once, the moved bodies written back."""
        dx, dtheta = carry
        parts, slot, colour_lams = xs
        moved = [_project(family._replace(params=params, static=static), rows, dx, dtheta, lam, indexing.Rows(*reads))
                 for family, (params, static, rows, reads), lam in zip(run.families, parts, colour_lams,
                                                                       strict=True)]  # fmt: skip
        slot = indexing.Rows(*slot)
        dx = take(jnp.concatenate([m[0] for m in moved] + [dx]), slot)
        dtheta = take(jnp.concatenate([m[1] for m in moved] + [dtheta]), slot)
        return (dx, dtheta), [m[2] for m in moved]

    def direct_step(carry):
        dx, dtheta, updated = carry
        now = [node_order(updated, f, multipliers[f]) for f in tree_step.families]
        step_dx, step_dtheta, increments = tree_step.solve(dx, dtheta, now)
        steps = dict(zip(tree_step.families, increments, strict=True))
        updated = [[lam + steps[g][index] if g in steps else lam
                    for g, index, lam in zip(run.fs, run.index, run_lams, strict=True)]
                   for run, run_lams in zip(runs, updated, strict=True)]  # fmt: skip
        return dx + step_dx, dtheta + step_dtheta, updated

    def iteration(carry, sweep):
        dx, dtheta, lams = carry
        updated = []
        for run, run_lams, fixed in zip(runs, lams, run_fixed, strict=True):
            parts = [(f.params, f.static, rows, tuple(reads))
                     for f, rows, reads in zip(run.families, fixed, run.reads, strict=True)]  # fmt: skip
            xs = (parts, tuple(run.write_back), run_lams)
            if run.length == 1:  # a colour of its own: no loop
                (dx, dtheta), new = colour((dx, dtheta), jax.tree.map(lambda x: x[0], xs), run)
                new = [lam[None] for lam in new]
            else:
                (dx, dtheta), new = jax.lax.scan(functools.partial(colour, run=run), (dx, dtheta), xs)
            updated.append(new)
        if tree_step is not None:
            dx, dtheta, updated = tree_step.after_sweep(sweep, iterations, direct_step, (dx, dtheta, updated))
        return (dx, dtheta, updated), None

    def node_order(lams, f, default):
        """Family f's multipliers (M_f, m_f) in node order from the runs' padded layout."""
        order, values = [], []
        for run, run_lams in zip(runs, lams, strict=True):
            for k in (k for k, g in enumerate(run.fs) if g == f):
                for r, nodes in enumerate(run.nodes[k]):
                    order.append(nodes)
                    values.append(run_lams[k][r, : len(nodes)])
        return take(jnp.concatenate(values), np.argsort(np.concatenate(order))) if order else default

    first = sharding.varying_like((table.dx, table.dtheta, start), table, [family.params for family in families])
    (dx, dtheta, lams), _ = jax.lax.scan(iteration, first, jnp.arange(iterations))
    return dx, dtheta, [node_order(lams, f, multipliers[f]) for f in range(len(families))]


def jacobi(families: list[Family], table: BodySet, iterations: int, multipliers: list,
           tree_step: TreeStep | None = None):  # fmt: skip
    """Every node at once from the same dX; each body moves by the mean of its nodes' requests.
    tree_step: run after each iteration it ends, as in `gauss_seidel`."""
    n = table.dx.shape[0] - 1
    used = [f for f, family in enumerate(families) if len(family.bodies)]
    touched = np.concatenate([families[f].bodies.reshape(-1) for f in used])
    share = jnp.asarray(1.0 / np.maximum(np.bincount(touched, minlength=n + 1), 1), table.dx.dtype)[:, None]
    fixed = [_fixed(table, families[f].bodies) for f in used]
    reads = [indexing.rows(families[f].bodies, n + 1) for f in used]

    def direct_step(carry):
        dx, dtheta, lams = carry
        k = [used.index(f) for f in tree_step.families]
        step_dx, step_dtheta, increments = tree_step.solve(dx, dtheta, [lams[i] for i in k])
        lams = list(lams)
        for i, increment in zip(k, increments, strict=True):
            lams[i] = lams[i] + increment
        return dx + step_dx, dtheta + step_dtheta, lams

    def iteration(carry, sweep):
        dx, dtheta, lams = carry
        moved = [_project(families[f], rows, dx, dtheta, lam, at)
                 for f, rows, lam, at in zip(used, fixed, lams, reads, strict=True)]  # fmt: skip
        dx_rows = jnp.concatenate([m[0] for m in moved]) - take(dx, touched)
        dtheta_rows = jnp.concatenate([m[1] for m in moved]) - take(dtheta, touched)
        dx = dx + indexing.segment_sum(dx_rows, touched, n + 1) * share
        dtheta = dtheta + indexing.segment_sum(dtheta_rows, touched, n + 1) * share
        lams = [m[2] for m in moved]
        if tree_step is not None and tree_step.families[0] in used:
            dx, dtheta, lams = tree_step.after_sweep(sweep, iterations, direct_step, (dx, dtheta, lams))
        return (dx, dtheta, lams), None

    start = [multipliers[f] for f in used]
    first = sharding.varying_like((table.dx, table.dtheta, start), table, [families[f].params for f in used])
    (dx, dtheta, lams), _ = jax.lax.scan(iteration, first, jnp.arange(iterations))
    result = list(multipliers)
    for f, lam in zip(used, lams, strict=True):
        result[f] = lam
    return dx, dtheta, result


def solve(
    model: Model, predicted: State, control: jnp.ndarray | None, contacts: tuple[ContactSlots, ...], h: float,
    start: State | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, tuple[jnp.ndarray, ...], jnp.ndarray | None]:  # fmt: skip
    """Displacement (N, 3) and rotation (N, 3) that satisfy the constraints from the prediction X*.

    control: (num_controls,) or None, the drive and motor targets of this step. contacts: this
    substep's slots (collision.detect). h: substep (s). start: the state the substep began from
    (the joints' armature rows read the rotor's own motion from it; None: from the prediction).
    Also returns each contact group's normal multipliers lambda_n (C, P) (the restitution pass
    reads which points pushed) and the rotor residuals (R, 3) of the joints `rotor_joints`
    (`joints.rotor_excess`, for `rotor_momentum`; None without such joints).
    """
    structure, options = model.structure, model.options
    n = structure.num_bodies
    dtype = predicted.pos.dtype
    all_families = constraints.families(model, control, contacts, h, dtype, predicted=predicted, start=start)
    multipliers = [jnp.zeros((len(f.bodies), f.num_multipliers), dtype) for f in all_families]
    if any(len(f.bodies) for f in all_families):
        table = body_table(model, predicted, h)
        if options.initial_guess == "tree" and tree.forest(structure)[0].size:
            # Start from the exact linear solve of the tree's point constraints, each joint's point
            # multiplier at the impulse it took there (families[0] are the joints).
            dx, dtheta, kappa = tree.initial_guess(model, table)
            table = table._replace(dx=dx, dtheta=dtheta)
            multipliers[0] = multipliers[0].at[:, joints.POINT : joints.POINT + 3].set(kappa)
        tree_step = angular = None
        if options.tree_solve and tree.forest(structure)[0].size:
            # A sweep ends with the exact solve of the tree's joint points, linearised where the
            # sweep left the bodies (refactored each time: a Newton step; factored once at X*, the
            # chord steps gained energy on a 20-link chain at dt = 1/30), with the contacts with
            # the world as rows (solvers/tree_contacts.py; without them a standing doll collapsed).
            first_contact = len(all_families) - len(contacts)
            solved = (0,) + tuple(range(first_contact, len(all_families)))
            compliance_h2 = options.contact_compliance / h**2
            # Contacts between two moving bodies are held, not rows (tree_contacts.contact_hold): once a
            # substep, at X*, like the rows' bodies' inertias.
            held = tree_contacts.contact_hold(model, table, contacts) if contacts else None

            def direct(dx, dtheta, lams, targets=None):
                bodies = table._replace(dx=dx, dtheta=dtheta)
                touching = None
                if contacts:
                    touching = tree_contacts.Touching(tuple(contacts), tuple(lams[1:]), compliance_h2, held)
                step_dx, step_dtheta, joint_steps, contact_steps = tree.direct_step(
                    model, bodies, touching, lams[0], targets, close=targets is not None
                )
                return step_dx, step_dtheta, [joint_steps, *contact_steps]

            if tree.has_angular_rows(structure):
                angular = (all_families[0].params[1], h)
            # Not after the last sweep where the whole-joint solve follows it: that solve takes the
            # points and contacts again, with the rest of each joint, from where the sweep left
            # them. Brax's humanoid with one sweep (dbd-tree-1), its step 1.25x faster at batch 1,
            # 16 and 256; the dropped humanoid's largest joint gap 0.0002 mm as before, the ant's
            # 0.0052 mm (0.0006 before), the ant at rest after 10 s 0.363 m (0.361; MuJoCo 0.362).
            tree_step = TreeStep(jax.checkpoint(direct, prevent_cse=False), solved,  # (inside the sweeps' scan)
                                 None if angular is None else options.iterations - 1)  # fmt: skip
        if options.jacobi:
            dx, dtheta, multipliers = jacobi(all_families, table, options.iterations, multipliers, tree_step)
        else:
            dx, dtheta, multipliers = gauss_seidel(structure.colours, all_families, table, options.iterations,
                                                    multipliers, tree_step)  # fmt: skip
        if options.point_sweeps and len(all_families[0].bodies):
            swept = table._replace(dx=dx, dtheta=dtheta)
            dx, dtheta, multipliers[0] = sweep_joint_points(model, predicted, all_families[0], swept, multipliers[0])
        if angular is not None:
            # Then one solve of the whole of every tree joint: its point, rotation lock, rotors, the
            # soft angle limits past their bounds and its drive (`tree.angular_rows`). Once, at the end: inside the
            # sweeps the soft limits let go of what the solve had pushed past a bound and Brax's ant
            # blew up within 4 steps; with the points alone at the end of each sweep, a heavy rotor
            # or a limit was left to the sweeps (the ant sank to 0.18 m). It ends with a chord step on
            # what its linearisation left of the joints' gaps (`close`: 1.0 -> 0.046 mm on the
            # landing ant at one sweep).
            # (Without the barrier against merging its recomputation, prevent_cse, as in the sweeps:
            # in a rollout the substep runs inside a scan, which keeps them apart.)
            whole = jax.checkpoint(lambda dx, dtheta, lams: direct(dx, dtheta, lams, angular), prevent_cse=False)
            step_dx, step_dtheta, increments = whole(dx, dtheta, [multipliers[f] for f in solved])
            dx, dtheta = dx + step_dx, dtheta + step_dtheta
            for f, increment in zip(solved, increments, strict=True):
                multipliers[f] = multipliers[f] + increment
    else:
        dx = dtheta = jnp.zeros((n + 1, 3), dtype)
    contact_lams = multipliers[len(all_families) - len(contacts) :]
    normal = tuple(lam.reshape(len(lam), -1, 4)[..., 0] for lam in contact_lams)
    excess = None
    swept = rotor_joints(model)
    if swept.size:  # what the sweeps left of the rotor rows, for the rotor pass, each kind with its own rows

        def residuals(members, rows):
            family = constraints.gather(all_families[0], swept[members])
            bodies = _fixed(table, family.bodies)._replace(
                dx=take(dx, family.bodies), dtheta=take(dtheta, family.bodies)
            )

            def one_joint(params, flag, pair, lam):  # params: (joint, targets), as the joints' family holds them
                return joints.rotor_excess(params[0], flag, params[1], pair, lam, h, rows)

            return jax.vmap(one_joint)(family.params, family.static, bodies, take(multipliers[0], swept[members]))

        excess = joints.by_kind(rotor_kinds(model), residuals)
    return dx[:n], dtheta[:n], normal, excess


def rotor_joints(model: Model) -> np.ndarray:
    """The joints with armature whose rotors the sweeps alone solve (static): with `tree_solve`,
    not the tree's, whose last direct solve takes the rotor rows exactly (`tree.angular_rows`)."""
    structure = model.structure
    rotor = structure.joint_rotor.array
    if rotor.shape[0] != structure.num_joints:  # built without armature
        return np.zeros(0, np.int64)
    swept = rotor.any(axis=-1)
    if model.options.tree_solve and tree.has_angular_rows(structure):
        in_tree = tree.forest(structure)[0]
        swept[in_tree[in_tree < structure.num_joints]] = False
    return np.flatnonzero(swept)


def rotor_kinds(model: Model) -> list[tuple[np.ndarray, frozenset[str]]]:
    """The joints `rotor_joints` grouped by kind as the sweeps group them (`joints.variants`):
    (positions in `rotor_joints` (K,) int, the rows some member has) per kind present. The rotor
    residuals and the rotor pass trace each kind with its own rows: traced with every kind's rows,
    a knee's rotor measured a hip's three hinge angles, and the two took 4.5 of the 11.7 ms of CPU
    of Brax's humanoid's one-sweep step at batch 256 (kind by kind, with `joints.joint_coordinates`
    by kind too: 2.7 of 9.1)."""
    swept = rotor_joints(model)
    kinds = [(np.flatnonzero(np.isin(swept, members)), rows) for members, rows in joints.variants(model.structure)]
    return [(positions, rows) for positions, rows in kinds if positions.size]


def sweep_joint_points(model: Model, predicted: State, joint_family: Family, table: BodySet, multipliers: jnp.ndarray):
    """`Options.point_sweeps` Gauss-Seidel sweeps of the joints' point blocks alone
    (`joints.project_point`) after the whole-joint sweeps, over the joints' own colouring: each
    whole joint's rows move bodies that its neighbours share (an ant's light leg between a hip
    and an ankle whose rotors outweigh it 40-120 times), and a point sweep closes what they left
    open at a fraction of a whole-joint sweep's cost. Each body b carries its joints' rotors
    (`with_rotors`, on body b: a rotor turns with the child it drives), so that a point closes by
    moving the light bodies rather than by spinning their rotors, as in the impulse solver's
    point sweeps (`solvers.impulse.rotor_pass`). joint_family: the solve's joints family (its
    parameters, joints and targets, and flags). table: the bodies after the sweeps (dx, dtheta
    their displacements (N + 1, 3)). multipliers: the joints' (J, NUM_MULTIPLIERS). Returns
    (dx, dtheta, multipliers), the points' continued."""
    structure = model.structure
    rows = joints.rows_in_use(structure)
    # One projection for every kind (no variants): a point block is the same rows in every joint.
    family = joint_family._replace(
        name="joint points",
        params=joint_family.params[0],
        variants=(),
        project=lambda joint, flag, bodies, lam: joints.project_point(joint, flag, bodies, lam, rows),
    )
    colours = colouring.colour_groups([family.bodies], structure.num_bodies)
    heavy = with_rotors(model, predicted, table, on_body_a=False)
    dx, dtheta, (multipliers,) = gauss_seidel(colours, [family], heavy, model.options.point_sweeps, [multipliers])
    return dx, dtheta, multipliers


def rotor_momentum(model: Model, state: State, excess: jnp.ndarray | None, h: float) -> State:
    """The rotor pass after the position solve (`joints.project_rotor_momentum`), on `state` (the
    state after the substep's displacements were applied): the rotors' spin the sweeps gave with
    no impulse behind it (`excess`, (R, 3), of the joints `rotor_joints`; None: nothing to do)
    taken back in ROTOR_PASS_SWEEPS Gauss-Seidel sweeps over the rotor joints' own colouring, kind
    by kind as the position sweeps' (`colouring.kind_classes`): each colour projects one kind.
    The impulse solver runs the same pass on its solved velocities at the start pose, with its
    velocity rows' residuals (`velocity_rows.rotor_excess`), between sweeps of its joints' points
    (`solvers.impulse.solve`)."""
    if excess is None:
        return state
    table = body_table(model, state, h)
    dv, dw = rotor_pass(model, table, excess, h)
    n = model.num_bodies
    return State(pos=state.pos, quat=state.quat, vel=state.vel + dv[:n], ang_vel=state.ang_vel + dw[:n])


def rotor_pass(model: Model, table: BodySet, excess: jnp.ndarray, h: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    """`rotor_momentum`'s sweeps on `table` (velocities in vel/ang_vel; dx/dtheta the changes so
    far, which the pass continues from: its targets are set by vel/ang_vel and `excess`, so a
    second pass after other changes takes the rates back to the same targets, not further).
    Returns the velocity changes (dv, dw) (N + 1, 3), the earlier ones included."""
    nodes = rotor_joints(model)
    structure = model.structure

    def project(rows):
        return lambda params, flag, bodies, lam: joints.project_rotor_momentum(
            params[0], flag, params[1], bodies, lam, h, rows)  # fmt: skip

    every_joint = Family("rotor momentum", structure.family_bodies()[0], model.joints, joints.flags(structure),
                         project(joints.rows_in_use(structure)), 3)  # fmt: skip
    kinds = rotor_kinds(model)
    gathered = constraints.gather(every_joint, nodes)
    family = gathered._replace(params=(gathered.params, excess),
                               variants=tuple((members, project(rows)) for members, rows in kinds))  # fmt: skip
    classes = colouring.kind_classes([members for members, _ in kinds], len(nodes))
    colours = colouring.colour_groups([family.bodies], structure.num_bodies, classes=[classes])
    dv, dw, _ = gauss_seidel(colours, [family], table, ROTOR_PASS_SWEEPS, [jnp.zeros((len(nodes), 3), table.dx.dtype)])
    return dv, dw


def with_rotors(model: Model, state: State, table: BodySet, on_body_a: bool = True) -> BodySet:
    """`table` with each body's inverse inertia taken with its joints' rotors (armature) on it
    (`joints.rotor_inertia`, on both bodies of each joint or, on_body_a False, on its body b):
    for the passes that move bodies without the rotor rows, whose rotors, rigidly on their
    coordinates' rates, must turn with them."""
    if not model.structure.joint_rotor.array.any():
        return table
    rotors = joints.rotor_inertia(model, state, on_body_a)
    inverse = math.inverse3(integrator.world_inertia(model, state) + rotors)
    return table._replace(inv_inertia=with_world_row(inverse))


def restitution(
    model: Model, state: State, contacts: tuple[ContactSlots, ...], normal: tuple[jnp.ndarray, ...], h: float
) -> State:
    """The velocity pass after the position solve (contacts.project_restitution), on `state`
    (the state after the substep's displacements were applied)."""
    if not contacts:
        return state
    families = constraints.restitution_families(model, contacts, h)
    # The pass moves its contacts' bodies alone; each body's rotors (armature) resist its turn
    # about their axes as they resist the joint's.
    table = with_rotors(model, state, body_table(model, state, h))
    dv, dw, _ = gauss_seidel(model.structure.contact_colours, families, table, model.options.restitution_iterations,
                              list(normal))  # fmt: skip
    n = model.num_bodies
    return State(pos=state.pos, quat=state.quat, vel=state.vel + dv[:n], ang_vel=state.ang_vel + dw[:n])
