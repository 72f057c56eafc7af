"""DBD against sequential impulses (and Brax's positional pipeline) on the scenes solver authors use to break solvers.

    .venv/bin/python benchmarks/solver_comparison.py           # dt 1/240 .. 1/15 x iterations 1 .. 20
    .venv/bin/python benchmarks/solver_comparison.py --quick   # dt 1/60, 1/30 x iterations 2, 8
    .venv/bin/python benchmarks/solver_comparison.py --scenes heavy_ball_chain,box_stack --solvers dbd,impulse
    .venv/bin/python benchmarks/solver_comparison.py --out part.json --resume --stop-after 60
    .venv/bin/python benchmarks/solver_comparison.py --merge partA.json partB.json   # -> --out, plots

writes benchmarks/results/solver_comparison.json (the settings it ran, the results, and the
planned runs that have none yet as `unfinished`; rewritten after every run, so a run cut short
keeps what finished and `--resume` goes on from it), solver_comparison.png (per scene, its main
metric against 1 / dt per solver and iteration count) and solver_comparison_blow_up.png (which
runs blew up). The scenes follow Erin Catto's Solver2D study (box2d.org/posts/2024/02/solver2d):
a heavy ball on a 40-link chain (mass ratio 100:1), a chain started at twice its link spacing
(recovery from a large error), a grid of jointed bodies, a vertical stack and a pyramid of boxes,
a big box on small boxes (mass ratio 100:1), a friction ramp, overlapping boxes pushed apart
(overlap recovery), a pile of three ragdolls (dbdjax.ragdoll, drives holding the build pose)
dropped onto each other, and a chain and the ragdoll pile 10 km from the origin (against the same
scene at the origin).

Every scene runs for the same simulated time at each time step, one substep per step (so the
step is the solver's step), with both solvers at the same iteration count. The time step is an
argument of the compiled rollout (it enters the step only as h = dt / substeps), so each
(scene, solver, iterations) compiles once for every dt, in chunks of CHUNK steps; a far scene
shares its twin's compilation. The runs go one iteration count at a time (8 first), so a sweep
cut short has whole iteration counts.

Brax (brax.positional.pipeline, when installed and not --no-brax) runs the scenes that MJCF and
Brax can express, written from the dbdjax scene (bodies in the same order, the same masses and
principal moments at the body origins, the same boxes, plane and friction; a ball joint as three
hinges, since Brax has none), at the same dt, float32, one physics step per step. It has no
iteration count: one position-level pass of joint and contact corrections per step
(joint_scale_pos 0.5, joint_scale_ang 0.2, collide_scale 1, baumgarte_erp 0.1: mjcf.load's
defaults); its rows have iterations null. Skipped (recorded with the reason, BRAX_SKIPPED): the
stretched chain (a Brax state comes from generalized coordinates, so its joints cannot start
open), the joint grid (closed loops), the ragdoll piles (no ranges on ball joints), and the heavy-ball
chain for its compile time (over 14 minutes here; the 20-link far chain takes about 9).

Measured per run (Brax's trajectory goes through the same functions: its links are the scene's bodies):
  gap_max_mm, gap_final_mm   largest joint gap over the run / over its last 10 %
  penetration_max_mm, penetration_final_mm   deepest contact, likewise (collision.collide)
  energy_drift               (E_end - E_start) / (M |g| L), E kinetic + potential relative to
                             the start, M the total mass, L the scene's size
  energy_gain                the largest E_t - E_start over the run, in the same unit (> 0: the
                             solver made energy)
  max_speed, max_turn        the largest body speed (m/s) and the largest angle a body turns in one
                             step at its angular velocity (|w| dt, rad)
  blew_up                    a non-finite state, a body faster than 100 m/s, or one turning more
                             than half a revolution per step (|w| dt > pi: the step no longer
                             resolves its rotation; a chain tumbling so is not a solution either)
  compile_s, ms_per_step     XLA compile time (0: reused from an earlier dt) and wall time per
                             step of the compiled chunks (this machine, shared: noisy)
plus a figure of merit per scene (`extra`): the top box's drift for stacks, the acceleration
error on the ramp, the push-apart speed of the overlapping boxes, the far scenes' difference to
the same scene at the origin.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import pathlib
import platform
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import dbdjax as dbd
from dbdjax import collision, diagnostics
from dbdjax.math import quat_multiply, quat_rotate
from dbdjax.model import with_world_row

GRAVITY = 9.81
LINK = 0.1  # m, chain link length
LINK_MASS = 0.1
LINK_INERTIA = (LINK_MASS * 0.01**2 / 2, LINK_MASS * LINK**2 / 12, LINK_MASS * LINK**2 / 12)
BLOW_UP_SPEED = 100.0  # m/s
BLOW_UP_TURN = math.pi  # rad turned by a body in one step
PILE_SPACING = 0.55  # m between the dolls of the ragdoll pile


@dataclasses.dataclass
class Scene:
    """A built scene: the model, its start state, how long to run, its size L (m) for the energy
    unit, and a figure of merit computed from the trajectory (name, function)."""

    model: dbd.Model
    start: dbd.State
    seconds: float
    size: float
    extra: tuple[str, Callable] | None = None
    twin: dbd.Model | None = None  # a model of the same structure run through the same compiled step
    twin_start: dbd.State | None = None  # the twin's start (None: dbd.init(twin))
    twin_name: str | None = None  # the scene the twin is (its offsets are reused when that scene ran)


# ------------------------------------------------------------------------------------ scenes


def _chain_builder(links, origin, gravity=(0.0, 0.0, -GRAVITY)):
    b = dbd.ModelBuilder(gravity=gravity)
    origin = np.asarray(origin, dtype=np.float64)
    previous = dbd.WORLD
    for i in range(links):
        body = b.add_body(pos=origin + ((i + 0.5) * LINK, 0, 0), mass=LINK_MASS, inertia=LINK_INERTIA)
        b.add_ball_joint(previous, body, anchor=origin + (i * LINK, 0, 0))
        previous = body
    return b, previous


def heavy_ball_chain(**finalize) -> Scene:
    """40 rods of 0.1 kg in a horizontal chain pinned at one end, a 10 kg ball (100:1) at the
    other; released, it falls and swings."""
    b, last = _chain_builder(40, (0.0, 0.0, 5.0))
    ball = b.add_body(pos=(40 * LINK + 0.1, 0, 5.0), mass=100 * LINK_MASS, inertia=(0.04,) * 3)
    b.add_ball_joint(last, ball, anchor=(40 * LINK, 0, 5.0))
    model = b.finalize(**finalize)
    return Scene(model, dbd.init(model), 2.0, 4.2)


def stretched_chain(**finalize) -> Scene:
    """A 20-link chain started with every body at twice its spacing from the pivot: each joint
    opens by a link length at t = 0 (recovery from a large error)."""
    b, _ = _chain_builder(20, (0.0, 0.0, 2.0))
    model = b.finalize(**finalize)
    start = dbd.init(model)
    pivot = jnp.array([0.0, 0.0, 2.0])
    start = dataclasses.replace(start, pos=pivot + 2.0 * (start.pos - pivot))
    return Scene(model, start, 2.0, 2.0)


def joint_grid(**finalize) -> Scene:
    """An 8 x 8 grid of 0.1 kg spheres 0.2 m apart in a horizontal plane, each joined to its
    neighbours by ball joints at the midpoints, pinned at two corners: it falls as a net."""
    b = dbd.ModelBuilder()
    count, spacing = 8, 0.2
    index = {}
    for i in range(count):
        for j in range(count):
            index[i, j] = b.add_body(pos=(i * spacing, j * spacing, 2.0), mass=0.1, inertia=(4e-4,) * 3)
    for (i, j), body in index.items():
        for di, dj in ((1, 0), (0, 1)):
            if (i + di, j + dj) in index:
                anchor = ((i + di / 2) * spacing, (j + dj / 2) * spacing, 2.0)
                b.add_ball_joint(body, index[i + di, j + dj], anchor=anchor)
    for corner in ((0, 0), (count - 1, 0)):
        b.add_ball_joint(dbd.WORLD, index[corner], anchor=(corner[0] * spacing, corner[1] * spacing - 0.05, 2.0))
    model = b.finalize(**finalize)
    return Scene(model, dbd.init(model), 2.0, 1.4)


def _boxes(positions, sizes=None, masses=None, **finalize):
    b = dbd.ModelBuilder()
    for k, pos in enumerate(positions):
        body = b.add_body(pos=pos, mass=None if masses is None else masses[k])
        b.add_box(body, (0.1, 0.1, 0.1) if sizes is None else sizes[k])
    b.add_plane()
    return b.finalize(**finalize)


def _drift_of(body, start_pos):
    def drift(trajectory):
        return float(np.nanmax(np.linalg.norm(np.asarray(trajectory.pos[:, body]) - start_pos, axis=-1)) * 1e3)

    return drift


def box_stack(**finalize) -> Scene:
    """Five 0.2 m cubes stacked on the ground; figure of merit: the top box's largest drift (mm)."""
    positions = np.array([(0.0, 0.0, 0.1 + 0.2 * i) for i in range(5)])
    model = _boxes(positions, **finalize)
    return Scene(model, dbd.init(model), 2.0, 1.0, ("top_drift_mm", _drift_of(4, positions[4])))


def box_pyramid(**finalize) -> Scene:
    """Ten 0.2 m cubes in a pyramid of four rows, 1 cm apart; figure of merit: the largest drift
    of any box (mm)."""
    positions = np.array([((k - (3 - row) / 2) * 0.21, 0.0, 0.1 + 0.2 * row) for row in range(4)
                          for k in range(4 - row)])  # fmt: skip
    model = _boxes(positions, **finalize)

    def drift(trajectory):
        return float(np.nanmax(np.linalg.norm(np.asarray(trajectory.pos) - positions, axis=-1)) * 1e3)

    return Scene(model, dbd.init(model), 2.0, 0.8, ("max_drift_mm", drift))


def big_box_on_small_boxes(**finalize) -> Scene:
    """A 100 kg slab (2 m x 0.6 m x 0.2 m) resting on two 1 kg cubes (mass ratio 100:1); figure
    of merit: how far the slab sank or moved (mm)."""
    positions = np.array([(-0.8, 0.0, 0.1), (0.8, 0.0, 0.1), (0.0, 0.0, 0.3)])
    model = _boxes(positions, sizes=[(0.1, 0.1, 0.1), (0.1, 0.1, 0.1), (1.0, 0.3, 0.1)], masses=[1.0, 1.0, 100.0],
                   **finalize)  # fmt: skip
    return Scene(model, dbd.init(model), 2.0, 0.4, ("slab_drift_mm", _drift_of(2, positions[2])))


def friction_ramp(**finalize) -> Scene:
    """A cube on a 35 degree ramp, mu 0.5: it slides at g (sin 35 - 0.5 cos 35) = 1.61 m/s^2;
    figure of merit: the relative error of the fitted acceleration (%)."""
    slope = math.radians(35.0)
    normal = np.array([-math.sin(slope), 0.0, math.cos(slope)])
    b = dbd.ModelBuilder()
    box = b.add_body(pos=0.1 * normal, quat=(math.cos(-slope / 2), 0, math.sin(-slope / 2), 0))
    b.add_box(box, (0.1, 0.1, 0.1), friction=0.5)
    b.add_plane(normal=normal, friction=0.5)
    model = b.finalize(**finalize)
    expected = GRAVITY * (math.sin(slope) - 0.5 * math.cos(slope))

    def error(trajectory):
        travelled = np.linalg.norm(np.asarray(trajectory.pos[:, 0]) - 0.1 * normal, axis=1)
        time_s = np.arange(1, len(travelled) + 1) * model.dt
        if not np.all(np.isfinite(travelled)):
            return float("nan")
        return float(abs(2.0 * np.polyfit(time_s, travelled, 2)[0] - expected) / expected * 100)

    return Scene(model, dbd.init(model), 1.5, 2.0, ("acceleration_error_pct", error))


def overlapping_boxes(**finalize) -> Scene:
    """Two cubes on the ground overlapping by 10 cm (half their width); figure of merit: the
    largest speed the push-apart gives them (m/s: a solver that pushes out by velocity flings them)."""
    positions = np.array([(-0.05, 0.0, 0.1), (0.05, 0.0, 0.1)])
    model = _boxes(positions, **finalize)

    def speed(trajectory):
        return float(np.nanmax(np.linalg.norm(np.asarray(trajectory.vel), axis=-1)))

    return Scene(model, dbd.init(model), 1.5, 0.2, ("push_speed", speed))


def far_chain(**finalize) -> Scene:
    """A 20-link chain 10 km from the origin, released horizontal; the same chain at the origin
    runs through the same compiled step. Figure of merit: the largest difference of body
    positions between the two, relative to their start (mm)."""
    far = np.array([1e4, -1e4, 1e4]) / np.sqrt(3.0)
    b, _ = _chain_builder(20, far)
    model = b.finalize(**finalize)
    near_builder, _ = _chain_builder(20, (0.0, 0.0, 0.0))
    near = near_builder.finalize(**finalize)
    return Scene(model, dbd.init(model), 2.0, 2.0, ("difference_to_origin_mm", None), twin=near)


def _ragdoll_pile(origin, dolls: int = 3, **finalize) -> tuple[dbd.Model, dbd.State]:
    """`dolls` ragdolls (dbdjax.ragdoll, 1.8 m, 70 kg, drives holding the build pose) lying on
    their backs, each turned 60 degrees about z from the one below and PILE_SPACING = 0.55 m above
    it (centres at 0.3, 0.85, 1.4 m over `origin`), dropped onto each other and the floor. The dolls
    touch each other and the floor but not themselves (doll k: contype 2 << k, conaffinity 1 | the
    others' bits): 675 capsule pairs between three dolls, 45 capsule-plane pairs. Nothing overlaps
    at the start (at 0.4 m the limbs crossed by 64 mm, at 0.45 m by 27 mm), so penetration_max is
    what the solvers let the falling dolls sink into each other and the floor."""
    from dbdjax import host_math, ragdoll

    origin = np.asarray(origin, dtype=np.float64)
    bits = [2 << k for k in range(dolls)]
    b, built = None, []
    for k in range(dolls):
        b, doll = ragdoll.build(b, pos=origin, floor=k == 0, contype=bits[k], conaffinity=1 | (sum(bits) - bits[k]))
        built.append(doll)
    model = b.finalize(**finalize)
    start = dbd.init(model)
    pos, quat = np.array(start.pos, np.float64), np.array(start.quat, np.float64)
    on_back = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # 90 degrees about x
    for k, doll in enumerate(built):
        yaw = k * math.pi / 3
        turn = host_math.multiply(np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]), on_back)
        index = np.array(list(doll.bodies.values()))
        centre = origin + (0.05 * k, -0.05 * k, 0.3 + PILE_SPACING * k)
        pos[index] = centre + np.stack([host_math.rotate(turn, p - origin - (0, 0, 0.9)) for p in pos[index]])
        quat[index] = np.stack([host_math.multiply(turn, q) for q in quat[index]])
    start = dataclasses.replace(start, pos=jnp.asarray(pos, start.pos.dtype), quat=jnp.asarray(quat, start.quat.dtype))
    return model, start


def ragdoll_pile(**finalize) -> Scene:
    """Three ragdolls dropped onto each other and the floor (see `_ragdoll_pile`); zero control:
    every drive holds the build pose."""
    model, start = _ragdoll_pile((0.0, 0.0, 0.0), **finalize)
    return Scene(model, start, 2.0, 1.8)


def far_ragdoll_pile(**finalize) -> Scene:
    """The ragdoll pile 10 km from the origin; figure of merit: the largest difference of body
    positions to the pile at the origin, relative to their start (mm)."""
    far = np.array([1e4, -1e4, 1e4]) / np.sqrt(3.0)
    model, start = _ragdoll_pile(far, **finalize)
    near, near_start = _ragdoll_pile((0.0, 0.0, 0.0), **finalize)
    return Scene(model, start, 2.0, 1.8, ("difference_to_origin_mm", None), twin=near, twin_start=near_start,
                 twin_name="ragdoll_pile")  # fmt: skip


SCENES = {
    "heavy_ball_chain": heavy_ball_chain,
    "stretched_chain": stretched_chain,
    "joint_grid": joint_grid,
    "box_stack": box_stack,
    "box_pyramid": box_pyramid,
    "big_box_on_small_boxes": big_box_on_small_boxes,
    "friction_ramp": friction_ramp,
    "overlapping_boxes": overlapping_boxes,
    "far_chain": far_chain,
    "ragdoll_pile": ragdoll_pile,
    "far_ragdoll_pile": far_ragdoll_pile,
}


# ------------------------------------------------------------------------------------ measures


def penetration_function(model: dbd.Model) -> Callable | None:
    """A jitted (pos (F, N, 3), quat (F, N, 4)) -> deepest penetration per frame (F,) m, over
    every contact pair of `model` (0 where nothing touches), from collision.collide at margin 0."""
    groups = model.structure.contact_groups
    if not groups:
        return None
    shapes = model.shapes

    def frame(pos, quat):
        pos = with_world_row(pos)
        quat = with_world_row(quat, jnp.array([1.0, 0.0, 0.0, 0.0], quat.dtype))
        deepest = jnp.zeros((), pos.dtype)
        for group in groups:
            poses = []
            for side in (0, 1):
                shape, body = group.shapes.array[:, side], group.bodies.array[:, side]
                poses.append((shapes.size[shape], pos[body] + quat_rotate(quat[body], shapes.local_pos[shape]),
                              quat_multiply(quat[body], shapes.local_quat[shape])))  # fmt: skip
            one = functools.partial(collision.collide, group.kind_a, group.kind_b)
            contacts = jax.vmap(one, in_axes=(0, 0, 0, 0, 0, 0, None))(*poses[0], *poses[1], 0.0)
            deepest = jnp.minimum(deepest, jnp.min(jnp.where(contacts.active, contacts.distance, 0.0)))
        return -deepest

    return dbd.jit(jax.vmap(frame))


def deepest_over(penetration: Callable, trajectory: dbd.State, chunk: int = 64) -> np.ndarray:
    """Penetration per frame, in chunks of a fixed size (one compilation for every run length)."""
    frames = trajectory.pos.shape[0]
    result = []
    for begin in range(0, frames, chunk):
        pos, quat = trajectory.pos[begin : begin + chunk], trajectory.quat[begin : begin + chunk]
        pad = chunk - pos.shape[0]
        pos = jnp.concatenate([pos, jnp.repeat(pos[-1:], pad, axis=0)])
        quat = jnp.concatenate([quat, jnp.repeat(quat[-1:], pad, axis=0)])
        result.append(np.asarray(penetration(pos, quat))[: chunk - pad])
    return np.concatenate(result)


def energy(model: dbd.Model, start: dbd.State, trajectory: dbd.State) -> np.ndarray:
    """Kinetic plus potential energy relative to the start positions (J), per frame: positions
    enter as differences, so a scene 10 km out is measured as precisely as one at the origin."""
    mass = np.asarray(model.bodies.mass)
    vel, ang_vel = np.asarray(trajectory.vel, np.float64), np.asarray(trajectory.ang_vel, np.float64)
    rotation = np.asarray(dbd.math.quat_to_matrix(trajectory.quat), np.float64)
    inertia = np.einsum("tnij,nj,tnkj->tnik", rotation, np.asarray(model.bodies.inertia, np.float64), rotation)
    kinetic = 0.5 * np.sum(mass * np.sum(vel**2, -1), -1) + 0.5 * np.einsum("tni,tnij,tnj->t", ang_vel, inertia,
                                                                          ang_vel)  # fmt: skip
    height = np.asarray(trajectory.pos - start.pos, np.float64)
    potential = -np.sum(mass * (height @ np.asarray(model.gravity, np.float64)), -1)
    start_kinetic = 0.5 * np.sum(mass * np.sum(np.asarray(start.vel, np.float64) ** 2, -1))
    return kinetic + potential - start_kinetic  # rotation at rest at the start in every scene


CHUNK = 30  # steps per call of the compiled rollout: every run is a whole number of these
CANONICAL_DT = 1.0 / 60.0  # the dt in the compiled model's static options (the real dt is an argument)


def _rollout_chunk(model: dbd.Model, state: dbd.State, dt: jnp.ndarray) -> tuple[dbd.State, dbd.State]:
    """CHUNK steps of `model` at a traced dt: the step uses options.dt only in h = dt / substeps,
    so one compilation per (scene, solver, iterations) serves every time step."""
    model = dataclasses.replace(model, options=dataclasses.replace(model.options, dt=dt))
    return dbd.rollout(model, state, steps=CHUNK)


def _canonical(model: dbd.Model) -> dbd.Model:
    return dataclasses.replace(model, options=dataclasses.replace(model.options, dt=CANONICAL_DT))


def compiled_rollout(model: dbd.Model, start: dbd.State, cache: dict) -> tuple[Callable, float]:
    """(run(model, start, dt, steps) -> (final, trajectory), compile seconds (0 when reused)).
    Models of the same structure and options (a scene and its far twin) share one compilation."""
    key = jax.tree.structure((_canonical(model), start))
    compile_s = 0.0
    if key not in cache:
        clock = time.perf_counter()
        dt = jnp.asarray(CANONICAL_DT, start.pos.dtype)
        cache[key] = dbd.jit(_rollout_chunk).lower(_canonical(model), start, dt).compile()
        compile_s = time.perf_counter() - clock
    chunk = cache[key]

    def run_steps(model, start, dt, steps):
        """(final state, trajectory (steps, ...), seconds the compiled steps took)."""
        model, dt = _canonical(model), jnp.asarray(dt, start.pos.dtype)
        state, pieces = start, []
        clock = time.perf_counter()
        for _ in range(math.ceil(steps / CHUNK)):
            state, piece = chunk(model, state, dt)
            pieces.append(piece)
        jax.block_until_ready(state)
        seconds = time.perf_counter() - clock
        trajectory = jax.tree.map(lambda *x: np.concatenate(x)[:steps], *pieces)
        return jax.tree.map(lambda x: x[-1], trajectory), trajectory, seconds

    return run_steps, compile_s


def measure(scene_name: str, scene: Scene, trajectory: dbd.State, dt: float, steps: int, caches: dict) -> dict:
    """The metrics of one run from its trajectory (a dbd.State stacked over steps; positions,
    orientations and velocities are all that is read, so any engine's bodies in the scene's order
    can be measured)."""
    model, start = scene.model, scene.start
    pos = np.asarray(trajectory.pos)
    finite = bool(np.all(np.isfinite(pos)) and np.all(np.isfinite(np.asarray(trajectory.vel))))
    speed = np.linalg.norm(np.asarray(trajectory.vel), axis=-1)
    max_speed = float(np.nanmax(speed)) if np.any(np.isfinite(speed)) else float("inf")
    spin = np.linalg.norm(np.asarray(trajectory.ang_vel), axis=-1)
    max_turn = float(np.nanmax(spin)) * dt if np.any(np.isfinite(spin)) else float("inf")
    result = {
        "blew_up": (not finite) or max_speed > BLOW_UP_SPEED or max_turn > BLOW_UP_TURN,
        "max_speed": round(max_speed, 4),
        "max_turn": round(max_turn, 4),
    }
    tail = max(1, steps // 10)
    if model.num_joints:
        gaps = np.asarray(diagnostics.joint_gaps(model, trajectory))
        result["gap_max_mm"] = float(np.nanmax(gaps) * 1e3) if finite else float("nan")
        result["gap_final_mm"] = float(np.nanmax(gaps[-tail:]) * 1e3) if finite else float("nan")
    if model.structure.contact_groups:
        family = scene.twin_name or scene_name  # a far scene measures with its twin's function
        if family not in caches["penetration"]:
            caches["penetration"][family] = penetration_function(model)
        depth = deepest_over(caches["penetration"][family], trajectory) if finite else np.array([np.nan])
        result["penetration_max_mm"] = float(np.max(depth) * 1e3)
        result["penetration_final_mm"] = float(np.max(depth[-tail:]) * 1e3)
    unit = float(np.sum(model.bodies.mass)) * GRAVITY * scene.size
    e = energy(model, start, trajectory) / unit
    result["energy_drift"] = float(e[-1])
    result["energy_gain"] = float(np.max(e))
    return result


def run(scene_name: str, solver: str, dt: float, iterations: int, caches: dict) -> dict:
    """One scene on one solver at one (dt, iterations), one substep per step; the metrics of
    `measure` plus compile_s, ms_per_step and the scene's figure of merit."""
    scene = SCENES[scene_name](dt=dt, substeps=1, iterations=iterations, solver=solver)
    model, start = scene.model, scene.start
    steps = int(round(scene.seconds / dt))
    rollout, compile_s = compiled_rollout(model, start, caches["rollout"])
    _, trajectory, seconds = rollout(model, start, dt, steps)
    ms_per_step = 1e3 * seconds / (math.ceil(steps / CHUNK) * CHUNK)
    result = {"scene": scene_name, "solver": solver, "dt": dt, "iterations": iterations, "steps": steps}
    result.update(measure(scene_name, scene, trajectory, dt, steps, caches))
    offset = np.asarray(trajectory.pos - start.pos, np.float64)
    caches["offsets"][scene_name, solver, iterations, dt] = offset  # for a far twin of this scene
    if scene.extra is not None:
        name, figure = scene.extra
        if scene.twin is not None:  # the twin at the origin, through the same compiled step
            near_offset = caches["offsets"].get((scene.twin_name, solver, iterations, dt))
            if near_offset is None:
                twin_start = dbd.init(scene.twin) if scene.twin_start is None else scene.twin_start
                _, near, _ = rollout(scene.twin, twin_start, dt, steps)
                near_offset = np.asarray(near.pos - twin_start.pos, np.float64)
            result[name] = float(np.nanmax(np.abs(offset - near_offset)) * 1e3)
        else:
            result[name] = figure(trajectory) if np.all(np.isfinite(offset)) else float("nan")
    result["compile_s"] = round(compile_s, 2)
    result["ms_per_step"] = round(ms_per_step, 4)
    return _rounded(result)


def _rounded(result: dict) -> dict:
    """Numbers to 6 decimals (dt kept whole: it is part of a run's key)."""
    return {
        k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) and k != "dt" else v) for k, v in result.items()
    }


# ------------------------------------------------------------------------------------ Brax

BRAX = "brax-positional"
BRAX_NOTE = "brax.positional.pipeline, float32, one position-level pass per step (no iteration count)"


def brax_available() -> bool:
    try:
        import brax.positional.pipeline  # noqa: F401
    except ImportError:
        return False
    return True


BRAX_TOO_SLOW = {  # expressible, and written (brax_mjcf), but not run
    "heavy_ball_chain": "compile time: brax.positional's step on this 41-body chain was still compiling after 14 "
    "minutes (session 7; the 20-body far chain took 539 s in session 6), on the shared 2-core machine",
}
BRAX_SKIPPED = {
    "stretched_chain": "Brax's state comes from generalized coordinates: its joints cannot start open",
    "joint_grid": "closed loops: a Brax system is a kinematic tree",
    "ragdoll_pile": "Brax supports no ranges on ball joints (the doll's cone and twist limits)",
    "far_ragdoll_pile": "Brax supports no ranges on ball joints (the doll's cone and twist limits)",
    **BRAX_TOO_SLOW,
}


def _numbers(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))


def _inertial(model: dbd.Model, body: int) -> str:
    """The body's mass and principal moments from the dbdjax model, at the body origin."""
    mass, inertia = float(model.bodies.mass[body]), np.asarray(model.bodies.inertia[body])
    return f'<inertial pos="0 0 0" mass="{mass:.9g}" diaginertia="{_numbers(inertia)}"/>'


def _chain_mjcf(model: dbd.Model, origin, links: int, ball: bool) -> str:
    """The chain (and heavy ball) as nested bodies; a ball joint is three hinges at the anchor
    (Brax has no ball joints: "ball joints not supported"); no collisions."""
    origin = np.asarray(origin, dtype=np.float64)
    body = f'<body name="link0" pos="{_numbers(origin + (0.5 * LINK, 0, 0))}">'
    xml, closing = [], []
    for i in range(links + ball):
        length = 0.1 if i == links else 0.5 * LINK  # anchor to centre
        previous = 0.5 * LINK
        pos = f"{previous + length:.9g} 0 0" if i else None
        xml.append(body if i == 0 else f'<body name="link{i}" pos="{pos}">')
        xml.append(_inertial(model, i))
        for axis in ("1 0 0", "0 1 0", "0 0 1"):
            xml.append(f'<joint type="hinge" pos="{-length:.9g} 0 0" axis="{axis}" damping="0"/>')
        xml.append('<geom type="sphere" size="0.005" mass="0"/>')  # Brax wants a geom; it collides with nothing
        closing.append("</body>")
    return ('<mujoco><option timestep="0.01" gravity="0 0 -9.81"/><default><geom contype="0" conaffinity="0"/>'
            "</default><worldbody>" + "".join(xml) + "".join(closing) + "</worldbody></mujoco>")  # fmt: skip


def _free_boxes_mjcf(model: dbd.Model, start: dbd.State, plane_normal=(0.0, 0.0, 1.0)) -> str:
    """Free bodies with one box each (the dbdjax model's shapes, masses, inertia, friction) on a plane."""
    shapes = model.shapes
    body_of = np.full(shapes.size.shape[0], -1)  # -1: the world (with_world_row's last row)
    for group in model.structure.contact_groups:
        for side in (0, 1):
            body = np.asarray(group.bodies.array[:, side])
            body_of[np.asarray(group.shapes.array[:, side])] = np.where(body < model.num_bodies, body, -1)
    xml = []
    normal = np.asarray(plane_normal, dtype=np.float64)
    plane_friction = float(shapes.friction[np.flatnonzero(body_of < 0)[0]]) if np.any(body_of < 0) else 0.5
    xml.append(f'<geom type="plane" size="0 0 1" zaxis="{_numbers(normal)}" friction="{plane_friction:.9g} 0 0"/>')
    for body in range(model.num_bodies):
        shape = int(np.flatnonzero(body_of == body)[0])
        pos, quat = np.asarray(start.pos[body]), np.asarray(start.quat[body])
        xml.append(f'<body pos="{_numbers(pos)}" quat="{_numbers(quat)}"><freejoint/>{_inertial(model, body)}'
                   f'<geom type="box" size="{_numbers(shapes.size[shape])}" '
                   f'friction="{float(shapes.friction[shape]):.9g} 0 0"/></body>')  # fmt: skip
    return ('<mujoco><option timestep="0.01" gravity="0 0 -9.81"/><worldbody>' + "".join(xml)
            + "</worldbody></mujoco>")  # fmt: skip


def brax_mjcf(scene_name: str, scene: Scene) -> str | tuple[str, str]:
    """The MJCF of a scene for Brax (a pair (far, near) for a far scene)."""
    if scene_name == "heavy_ball_chain":
        return _chain_mjcf(scene.model, (0.0, 0.0, 5.0), 40, True)
    if scene_name == "far_chain":
        far = np.array([1e4, -1e4, 1e4]) / np.sqrt(3.0)
        return _chain_mjcf(scene.model, far, 20, False), _chain_mjcf(scene.twin, (0.0, 0.0, 0.0), 20, False)
    if scene_name == "friction_ramp":
        slope = math.radians(35.0)
        return _free_boxes_mjcf(scene.model, scene.start, (-math.sin(slope), 0.0, math.cos(slope)))
    return _free_boxes_mjcf(scene.model, scene.start)


def _brax_rollout(caches: dict, system, key: tuple):
    """(run(system, dt, steps) -> (trajectory as a dbd.State, seconds), compile seconds): CHUNK
    steps of brax.positional per call at a traced timestep; one compilation per `key` (a scene's
    system: a System's mj_model is static in its pytree, and two systems' tree structures can
    compare equal yet be refused by the other's compiled function)."""
    from brax.positional import pipeline

    def chunk(system, state, dt):
        system = system.tree_replace({"opt.timestep": dt})
        act = jnp.zeros(system.act_size())

        def one(s, _):
            s = pipeline.step(system, s, act)
            return s, (s.x.pos, s.x.rot, s.xd.vel, s.xd.ang)

        return jax.lax.scan(one, state, None, length=CHUNK)

    def begin(system):
        return pipeline.init(system, system.init_q, jnp.zeros(system.qd_size()))

    compile_s = 0.0
    if key not in caches["rollout"]:
        clock = time.perf_counter()
        dt = jnp.asarray(0.01, jnp.float32)
        caches["rollout"][key] = (dbd.jit(chunk).lower(system, dbd.jit(begin)(system), dt).compile(), dbd.jit(begin))
        compile_s = time.perf_counter() - clock
    compiled, start = caches["rollout"][key]

    def run_steps(system, dt, steps):
        state, pieces = start(system), []
        dt = jnp.asarray(dt, jnp.float32)
        clock = time.perf_counter()
        for _ in range(math.ceil(steps / CHUNK)):
            state, piece = compiled(system, state, dt)
            pieces.append(piece)
        jax.block_until_ready(state)
        seconds = time.perf_counter() - clock
        pos, quat, vel, ang_vel = (np.concatenate(x)[:steps] for x in zip(*pieces, strict=True))
        return dbd.State(pos=pos, quat=quat, vel=vel, ang_vel=ang_vel), seconds

    return run_steps, compile_s


def run_brax(scene_name: str, dt: float, caches: dict) -> dict:
    """One scene on Brax's positional pipeline (MJCF from the dbdjax scene), measured as `run`
    measures: the Brax bodies are the scene's bodies in its order, centres of mass at the body
    origins, so joint gaps, penetration and energy come from the same functions. A far scene's
    figure of merit: its difference to the same system at the origin."""
    result = {"scene": scene_name, "solver": BRAX, "dt": dt, "iterations": None}
    if scene_name in BRAX_SKIPPED:
        return dict(result, skipped=BRAX_SKIPPED[scene_name])
    from brax.io import mjcf

    scene = SCENES[scene_name](dt=dt, substeps=1, iterations=1, solver="dbd")
    if scene_name not in caches.setdefault("brax_systems", {}):  # one System per scene: its mj_model is
        xml = brax_mjcf(scene_name, scene)  # static in the pytree, so a new one would compile again
        caches["brax_systems"][scene_name] = [mjcf.loads(x) for x in (xml if isinstance(xml, tuple) else (xml,))]
    systems = caches["brax_systems"][scene_name]
    steps = int(round(scene.seconds / dt))
    rollout, compile_s = _brax_rollout(caches, systems[0], (BRAX, scene_name, 0))
    trajectory, seconds = rollout(systems[0], dt, steps)
    from brax import kinematics

    placed, _ = kinematics.forward(systems[0], systems[0].init_q, jnp.zeros(systems[0].qd_size()))
    start = np.asarray(scene.start.pos)
    if np.max(np.abs(np.asarray(placed.pos) - start)) > 1e-3 * max(1.0, np.abs(start).max()):
        raise ValueError(f"{scene_name}: the Brax system's bodies do not start where the scene's do")
    result["steps"] = steps
    result.update(measure(scene_name, scene, trajectory, dt, steps, caches))
    if scene.extra is not None:
        name, figure = scene.extra
        offset = np.asarray(trajectory.pos, np.float64) - np.asarray(scene.start.pos, np.float64)
        if scene.twin is not None:  # its own compilation: a System's mj_model is static
            near_rollout, near_compile_s = _brax_rollout(caches, systems[1], (BRAX, scene_name, 1))
            near, _ = near_rollout(systems[1], dt, steps)
            compile_s += near_compile_s
            twin_start = dbd.init(scene.twin) if scene.twin_start is None else scene.twin_start
            near_offset = np.asarray(near.pos, np.float64) - np.asarray(twin_start.pos, np.float64)
            result[name] = float(np.nanmax(np.abs(offset - near_offset)) * 1e3)
        else:
            result[name] = figure(trajectory) if np.all(np.isfinite(offset)) else float("nan")
    result["compile_s"] = round(compile_s, 2)
    result["ms_per_step"] = round(1e3 * seconds / (math.ceil(steps / CHUNK) * CHUNK), 4)
    return _rounded(result)


# ------------------------------------------------------------------------------------ plot

PRIMARY = {  # the metric each scene's panel shows
    "heavy_ball_chain": "gap_max_mm",
    "stretched_chain": "gap_final_mm",
    "joint_grid": "gap_max_mm",
    "box_stack": "top_drift_mm",
    "box_pyramid": "max_drift_mm",
    "big_box_on_small_boxes": "penetration_max_mm",
    "friction_ramp": "acceleration_error_pct",
    "overlapping_boxes": "push_speed",
    "far_chain": "difference_to_origin_mm",
    "ragdoll_pile": "gap_max_mm",
    "far_ragdoll_pile": "difference_to_origin_mm",
}
COLOURS = {"dbd": "tab:blue", "impulse": "tab:red", BRAX: "tab:green"}


def plot(results: list[dict], path: pathlib.Path) -> None:
    """Per scene, its PRIMARY metric against 1 / dt: one line per solver and iteration count
    (Brax: one line); x at y = 1: a run that blew up."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = [r for r in results if "error" not in r]
    scenes = [s for s in SCENES if any(r["scene"] == s for r in results)]
    columns = 3
    rows = math.ceil(len(scenes) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.6 * columns, 3.5 * rows), squeeze=False)
    iteration_counts = sorted({r["iterations"] for r in results if r["iterations"] is not None})
    styles = dict(zip(iteration_counts, ["-", "--", ":", "-.", (0, (1, 3)), (0, (5, 1))], strict=False))
    widths = dict(zip(iteration_counts, [0.8, 1.1, 1.4, 1.8, 2.4, 3.0], strict=False))
    for axis, scene in zip(axes.flat, scenes, strict=False):
        metric = PRIMARY[scene]
        for solver, colour in COLOURS.items():
            for count in [None] if solver == BRAX else iteration_counts:
                rows_ = sorted((r for r in results if r["scene"] == scene and r["solver"] == solver
                                and r["iterations"] == count), key=lambda r: r["dt"])  # fmt: skip
                if not rows_:
                    continue
                x = [1 / r["dt"] for r in rows_]
                y = [r.get(metric, float("nan")) if not r.get("blew_up", True) else float("nan") for r in rows_]
                label = solver if count is None else f"{solver} {count} it"
                axis.plot(x, y, linestyle=styles.get(count, "-"), lw=widths.get(count, 1.5), color=colour, marker="o",
                          ms=2.5, label=label)  # fmt: skip
                blown = [1 / r["dt"] for r in rows_ if r.get("blew_up")]
                axis.plot(blown, [1.0] * len(blown), "x", color=colour, ms=8)
        axis.set_xscale("log", base=2)
        if any(np.any(np.asarray(line.get_ydata(), float) > 0) for line in axis.get_lines()):
            axis.set_yscale("log")
        axis.set_xlabel("steps per second (1 / dt)")
        axis.set_title(f"{scene}: {metric}", fontsize=9)
    for axis in list(axes.flat)[len(scenes) :]:
        axis.axis("off")
    axes.flat[0].legend(fontsize=5.5, ncol=2)
    figure.suptitle("DBD (blue) vs sequential impulses (red) vs Brax positional (green), 1 substep; "
                    "line width: iterations; x: blew up", fontsize=10)  # fmt: skip
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_blow_up(results: list[dict], path: pathlib.Path) -> None:
    """A map per scene: rows solver x iterations, columns dt; red (x): blew up, white: stayed
    finite, under BLOW_UP_SPEED and BLOW_UP_TURN, grey: no result (not run, skipped or an error)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    scenes = [s for s in SCENES if any(r["scene"] == s for r in results)]
    dts = sorted({round(r["dt"], 6) for r in results}, reverse=True)
    rows = sorted({(r["solver"], r["iterations"] or 0) for r in results})
    columns = 4
    grid_rows = math.ceil(len(scenes) / columns)
    height = (0.22 * len(rows) + 1.6) * grid_rows
    figure, axes = plt.subplots(grid_rows, columns, figsize=(3.4 * columns, height), squeeze=False)
    colours = ListedColormap(["white", "lightgrey", "tab:red"])
    for axis, scene in zip(axes.flat, scenes, strict=False):
        cell = np.ones((len(rows), len(dts)))
        for r in results:
            if r["scene"] == scene and "blew_up" in r:
                row, column = rows.index((r["solver"], r["iterations"] or 0)), dts.index(round(r["dt"], 6))
                cell[row, column] = 2.0 if r["blew_up"] else 0.0
        axis.imshow(cell, cmap=colours, vmin=0, vmax=2, aspect="auto")
        for row, column in zip(*np.nonzero(cell == 2.0), strict=True):
            axis.text(column, row, "x", ha="center", va="center", fontsize=6)
        axis.set_xticks(range(len(dts)), [f"1/{round(1 / d)}" for d in dts], fontsize=6)
        axis.set_yticks(range(len(rows)), [f"{s} {i}" if i else s for s, i in rows], fontsize=5)
        axis.set_title(scene, fontsize=8)
    for axis in list(axes.flat)[len(scenes) :]:
        axis.axis("off")
    figure.suptitle("blew up (red x: non-finite, a body over 100 m/s, or one turning over pi in a step; white: did "
                    "not; grey: no result)", fontsize=9)  # fmt: skip
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


# ------------------------------------------------------------------------------------ sweep


def _key(result: dict) -> tuple:
    return result["scene"], result["solver"], result["iterations"], round(result["dt"], 6)


def plan(scenes: list[str], solvers: list[str], dts: list[float], iteration_counts: list[int]) -> list[tuple]:
    """Every run as (scene, solver, iterations, dt), in the order they run: all scenes at the
    first iteration count, then the next, ...: a run cut short has whole iteration counts. Brax
    (no iteration count: `iterations` None) runs with the first."""
    runs = []
    for position, iterations in enumerate(iteration_counts):
        for scene in scenes:
            for solver in solvers:
                if solver == BRAX:
                    if position == 0:
                        runs += [(scene, solver, None, dt) for dt in dts]
                else:
                    runs += [(scene, solver, iterations, dt) for dt in dts]
    return runs


def write(path: pathlib.Path, settings: dict, results: list[dict], planned: list[tuple]) -> None:
    """The JSON (settings, results, and the planned runs that have no result yet as `unfinished`)."""
    done = {_key(r) for r in results}
    unfinished = [list(run) for run in planned if (run[0], run[1], run[2], round(run[3], 6)) not in done]
    summary = dict(settings, results=results, unfinished=unfinished)
    path.write_text(json.dumps(summary, indent=1) + "\n")


TABLE_VALUES = {  # the numbers each scene's table row shows, in order
    "heavy_ball_chain": ("gap_max_mm", "energy_gain", "max_turn"),
    "stretched_chain": ("gap_final_mm", "gap_max_mm", "energy_gain", "max_turn"),
    "joint_grid": ("gap_max_mm", "energy_gain", "max_turn"),
    "box_stack": ("top_drift_mm", "penetration_final_mm", "energy_gain"),
    "box_pyramid": ("max_drift_mm", "penetration_final_mm", "energy_gain"),
    "big_box_on_small_boxes": ("penetration_max_mm", "penetration_final_mm", "energy_gain"),
    "friction_ramp": ("acceleration_error_pct", "penetration_final_mm", "energy_gain"),
    "overlapping_boxes": ("push_speed", "penetration_final_mm", "energy_gain"),
    "far_chain": ("difference_to_origin_mm", "gap_max_mm", "energy_gain"),
    "ragdoll_pile": ("gap_max_mm", "penetration_max_mm", "penetration_final_mm", "energy_gain"),
    "far_ragdoll_pile": ("difference_to_origin_mm", "gap_max_mm", "penetration_final_mm", "energy_gain"),
}


def tables(results: list[dict], dts: list[float], columns: list[tuple[str, int | None]]) -> str:
    """A markdown table: one row per (scene, dt), one column per (solver, iterations); each cell
    the scene's TABLE_VALUES in order ("blew up" first where the run did; "-": no result)."""

    def cell(result: dict | None, scene: str) -> str:
        if result is None:
            return "-"
        if "skipped" in result:
            return "skipped"
        if "error" in result:
            return "error"
        numbers = " / ".join(f"{result.get(v, float('nan')):.3g}" for v in TABLE_VALUES[scene])
        return f"**blew up** {numbers}" if result.get("blew_up") else numbers

    found = {_key(r): r for r in results}
    head = ["scene", "values", "dt"] + [
        f"{solver} {iterations}" if iterations else solver for solver, iterations in columns
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene in SCENES:
        for dt in dts:
            cells = [
                cell(found.get((scene, solver, iterations, round(dt, 6))), scene) for solver, iterations in columns
            ]
            lines.append(
                f"| {scene} | {', '.join(TABLE_VALUES[scene])} | 1/{round(1 / dt)} | " + " | ".join(cells) + " |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="dt 1/60, 1/30 and 2, 8 iterations only")
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scene names")
    parser.add_argument("--solvers", default=f"dbd,impulse,{BRAX}", help="comma-separated: dbd, impulse, " + BRAX)
    parser.add_argument("--no-brax", action="store_true", help="leave Brax out (also left out when not installed)")
    parser.add_argument("--iterations", default=None, help="comma-separated iteration counts, in the order to run")
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/solver_comparison.json)")
    parser.add_argument("--resume", action="store_true", help="keep the runs already in --out and do the rest")
    parser.add_argument("--stop-after", type=float, default=None, help="minutes: start no run after this")
    parser.add_argument("--merge", nargs="+", default=None, help="JSON files to merge into --out (no runs)")
    parser.add_argument("--tables", action="store_true", help="print --out's results as markdown tables (no runs)")
    args = parser.parse_args()
    dts = [1 / 60, 1 / 30] if args.quick else [1 / 240, 1 / 120, 1 / 60, 1 / 30, 1 / 15]
    iteration_counts = [2, 8] if args.quick else [8, 2, 20, 1, 4]  # the order they run in
    if args.iterations:
        iteration_counts = [int(x) for x in args.iterations.split(",")]
    names = args.scenes.split(",")
    for name in names:
        if name not in SCENES:
            raise SystemExit(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    solvers = args.solvers.split(",")
    if BRAX in solvers and (args.no_brax or not brax_available()):
        solvers.remove(BRAX)
    out = pathlib.Path(args.out) if args.out else pathlib.Path(__file__).parent / "results" / "solver_comparison.json"
    settings = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}",
        "jax": jax.__version__,
        "dts": dts,
        "iterations": sorted(iteration_counts),
        "substeps": 1,
        "quick": args.quick,
        "solvers": solvers,
        "brax": BRAX_NOTE if BRAX in solvers else None,
    }
    if args.tables:
        results = json.loads(out.read_text())["results"]
        counts = sorted({r["iterations"] for r in results if r["iterations"]})
        both = [(solver, n) for solver in ("dbd", "impulse") for n in counts] + [(BRAX, None)]
        print(f"### Large steps: dt 1/30 and 1/15, every iteration count\n\n{tables(results, dts[-2:], both)}")
        eight = [("dbd", 8), ("impulse", 8), (BRAX, None)]
        print(f"### Small steps: dt 1/240 to 1/60, 8 iterations\n\n{tables(results, dts[:-2], eight)}")
        return
    if args.merge:
        merged = {}
        for path in args.merge:  # the first result of a run wins
            for result in json.loads(pathlib.Path(path).read_text())["results"]:
                if "error" in result:
                    result["error"] = result["error"][:400]
                merged.setdefault(_key(result), result)
        results = list(merged.values())
        order = {name: k for k, name in enumerate(SCENES)}
        results.sort(key=lambda r: (order[r["scene"]], r["solver"], r["iterations"] or 0, r["dt"]))
        settings["solvers"] = [s for s in ("dbd", "impulse", BRAX) if any(r["solver"] == s for r in results)]
        settings["brax"] = BRAX_NOTE if BRAX in settings["solvers"] else None
        write(out, settings, results, plan(list(SCENES), settings["solvers"], dts, iteration_counts))
        plot(results, out.with_suffix(".png"))
        plot_blow_up(results, out.with_name(out.stem + "_blow_up.png"))
        return
    planned = plan(names, solvers, dts, iteration_counts)
    results = json.loads(out.read_text())["results"] if args.resume and out.exists() else []
    done = {_key(r) for r in results}
    caches = {"rollout": {}, "penetration": {}, "offsets": {}}
    began = time.perf_counter()
    for count, (name, solver, iterations, dt) in enumerate(planned):
        if (name, solver, iterations, round(dt, 6)) in done:
            continue
        if args.stop_after is not None and time.perf_counter() - began > 60 * args.stop_after:
            print(f"stopping: {args.stop_after} minutes passed; the rest is recorded as unfinished", flush=True)
            break
        try:
            result = run_brax(name, dt, caches) if solver == BRAX else run(name, solver, dt, iterations, caches)
        except Exception as error:  # a long sweep keeps going; the error is in the JSON
            result = {"scene": name, "solver": solver, "dt": dt, "iterations": iterations, "error": repr(error)[:400]}
        result["load_average"] = round(os.getloadavg()[0], 2)  # the machine is shared: timings are noisy
        results.append(result)
        write(out, settings, results, planned)  # a checkpoint after every run
        elapsed = time.perf_counter() - began
        print(f"[{count + 1}/{len(planned)} {elapsed / 60:.1f} min load {os.getloadavg()[0]:.1f}] "
              + json.dumps(result), flush=True)  # fmt: skip
    write(out, settings, results, planned)
    plot(results, out.with_suffix(".png"))
    plot_blow_up(results, out.with_name(out.stem + "_blow_up.png"))


if __name__ == "__main__":
    main()
