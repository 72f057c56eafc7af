"""DBD against sequential impulses on the scenes solver authors use to break solvers.

    .venv/bin/python benchmarks/solver_comparison.py           # dt 1/240 .. 1/15 x iterations 1 .. 20
    .venv/bin/python benchmarks/solver_comparison.py --quick   # dt 1/60, 1/30 x iterations 2, 8
    .venv/bin/python benchmarks/solver_comparison.py --scenes heavy_ball_chain,box_stack

writes benchmarks/results/solver_comparison.json (the settings it ran are recorded in it) and
solver_comparison.png beside it. The scenes follow Erin Catto's Solver2D study (box2d.org/posts/2024/02/solver2d):
a heavy ball on a 40-link chain (mass ratio 100:1), a chain started at twice its link spacing
(recovery from a large error), a grid of jointed bodies, a vertical stack and a pyramid of boxes,
a big box on small boxes (mass ratio 100:1), a friction ramp, overlapping boxes pushed apart
(overlap recovery), and a chain 10 km from the origin (against the same chain at the origin).
A ragdoll pile is left out: the engine has no ragdoll builder yet. Brax's positional pipeline is
not run here either.

Every scene runs for the same simulated time at each time step, one substep per step (so the
step is the solver's step), with both solvers at the same iteration count. Measured per run:
  gap_max_mm, gap_final_mm   largest joint gap over the run / over its last 10 %
  penetration_max_mm, penetration_final_mm   deepest contact, likewise (collision.collide)
  energy_drift               (E_end - E_start) / (M |g| L), E kinetic + potential relative to
                             the start, M the total mass, L the scene's size
  energy_gain                the largest E_t - E_start over the run, in the same unit (> 0: the
                             solver made energy)
  max_speed, blew_up         the largest body speed (m/s); blew_up: a non-finite state or a body
                             faster than 100 m/s
  compile_s, ms_per_step     XLA compile time and wall time per step after it (this machine)
plus a figure of merit per scene (`extra`): the top box's drift for stacks, the acceleration
error on the ramp, the separation of the pushed-apart boxes, the far chain's difference to the
chain at the origin.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
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

    return jax.jit(jax.vmap(frame))


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


def run(scene_name: str, solver: str, dt: float, iterations: int, penetration_cache: dict) -> dict:
    scene = SCENES[scene_name](dt=dt, substeps=1, iterations=iterations, solver=solver)
    model, start = scene.model, scene.start
    steps = int(round(scene.seconds / dt))
    rollout = jax.jit(lambda m, s: dbd.rollout(m, s, steps=steps))
    clock = time.perf_counter()
    compiled = rollout.lower(model, start).compile()
    compile_s = time.perf_counter() - clock
    clock = time.perf_counter()
    final, trajectory = jax.block_until_ready(compiled(model, start))
    ms_per_step = 1e3 * (time.perf_counter() - clock) / steps

    finite = bool(dbd.is_finite(final)) and bool(np.all(np.isfinite(np.asarray(trajectory.pos))))
    speed = np.linalg.norm(np.asarray(trajectory.vel), axis=-1)
    max_speed = float(np.nanmax(speed)) if np.any(np.isfinite(speed)) else float("inf")
    result = {"scene": scene_name, "solver": solver, "dt": dt, "iterations": iterations, "steps": steps,
              "blew_up": (not finite) or max_speed > BLOW_UP_SPEED, "max_speed": round(max_speed, 4)}  # fmt: skip
    tail = max(1, steps // 10)
    if model.num_joints:
        gaps = np.asarray(diagnostics.joint_gaps(model, trajectory))
        result["gap_max_mm"] = float(np.nanmax(gaps) * 1e3) if finite else float("nan")
        result["gap_final_mm"] = float(np.nanmax(gaps[-tail:]) * 1e3) if finite else float("nan")
    if model.structure.contact_groups:
        if scene_name not in penetration_cache:
            penetration_cache[scene_name] = penetration_function(model)
        depth = deepest_over(penetration_cache[scene_name], trajectory) if finite else np.array([np.nan])
        result["penetration_max_mm"] = float(np.max(depth) * 1e3)
        result["penetration_final_mm"] = float(np.max(depth[-tail:]) * 1e3)
    unit = float(np.sum(model.bodies.mass)) * GRAVITY * scene.size
    e = energy(model, start, trajectory) / unit
    result["energy_drift"] = float(e[-1])
    result["energy_gain"] = float(np.max(e))
    if scene.extra is not None:
        name, measure = scene.extra
        if scene.twin is not None:  # the same compiled step on the twin model
            _, near = jax.block_until_ready(compiled(scene.twin, dbd.init(scene.twin)))
            offset = np.asarray(trajectory.pos - start.pos, np.float64)
            near_offset = np.asarray(near.pos - dbd.init(scene.twin).pos, np.float64)
            result[name] = float(np.nanmax(np.abs(offset - near_offset)) * 1e3)
        else:
            result[name] = measure(trajectory) if finite else float("nan")
    result["compile_s"] = round(compile_s, 2)
    result["ms_per_step"] = round(ms_per_step, 4)
    return {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v) for k, v in result.items()}


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
    "far_chain": "gap_max_mm",
}


def plot(results: list[dict], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = [s for s in SCENES if any(r["scene"] == s for r in results)]
    columns = 3
    rows = math.ceil(len(scenes) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.3 * rows), squeeze=False)
    iteration_counts = sorted({r["iterations"] for r in results})
    styles = ["-", "--", ":", "-.", (0, (1, 3))]
    for axis, scene in zip(axes.flat, scenes, strict=False):
        metric = PRIMARY[scene]
        for solver, colour in (("dbd", "tab:blue"), ("impulse", "tab:red")):
            for count, style in zip(iteration_counts, styles, strict=False):
                rows_ = sorted((r for r in results if r["scene"] == scene and r["solver"] == solver
                                and r["iterations"] == count), key=lambda r: r["dt"])  # fmt: skip
                if not rows_:
                    continue
                x = [1 / r["dt"] for r in rows_]
                y = [r.get(metric, float("nan")) if not r["blew_up"] else float("nan") for r in rows_]
                axis.plot(x, y, linestyle=style, color=colour, marker="o", ms=3, label=f"{solver} {count} it")
                blown = [1 / r["dt"] for r in rows_ if r["blew_up"]]
                axis.plot(blown, [1.0] * len(blown), "x", color=colour, ms=8)
        axis.set_xscale("log", base=2)
        axis.set_yscale("log")
        axis.set_xlabel("steps per second (1 / dt)")
        axis.set_title(f"{scene}: {metric}", fontsize=9)
    for axis in list(axes.flat)[len(scenes) :]:
        axis.axis("off")
    axes.flat[0].legend(fontsize=6)
    figure.suptitle("DBD (blue) vs sequential impulses (red), 1 substep; x: blew up", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="dt 1/60, 1/30 and 2, 8 iterations only")
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scene names")
    args = parser.parse_args()
    dts = [1 / 60, 1 / 30] if args.quick else [1 / 240, 1 / 120, 1 / 60, 1 / 30, 1 / 15]
    iteration_counts = [2, 8] if args.quick else [1, 2, 4, 8, 20]
    names = args.scenes.split(",")
    for name in names:
        if name not in SCENES:
            raise SystemExit(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    results, cache = [], {}
    for name in names:
        for solver in ("dbd", "impulse"):
            for iterations in iteration_counts:
                for dt in dts:
                    result = run(name, solver, dt, iterations, cache)
                    results.append(result)
                    print(json.dumps(result), flush=True)
    stem = "solver_comparison"
    out = pathlib.Path(__file__).parent / "results"
    summary = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}",
        "jax": jax.__version__,
        "dts": dts,
        "iterations": iteration_counts,
        "substeps": 1,
        "quick": args.quick,
        "results": results,
    }
    (out / f"{stem}.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(results, out / f"{stem}.png")


if __name__ == "__main__":
    main()
