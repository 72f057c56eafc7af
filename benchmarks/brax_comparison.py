"""dbdjax side by side with Brax (positional, generalized, mjx pipelines) on the same MJCF model,
dt and control, in one run: physics steps/s at several batch sizes, compile times (step, a
100-step rollout, grad of that rollout), the accuracy of a dropped humanoid (largest joint gap,
spurious energy gain), where the dropped model comes to rest beside MuJoCo's own rest (`rest`),
and the cost of differentiable rollouts (time and peak memory of grad through 100 / 1000 steps,
with and without rematerialisation).

    python benchmarks/brax_comparison.py            # quick: batches 1 16, short timings
    python benchmarks/brax_comparison.py --full     # batches 1 16 256 4096, longer timings
    python benchmarks/brax_comparison.py --tasks accuracy --engines dbdjax-dbd-tree   # one task, one engine
                                                    # (dbd-tree: DBD with finalize(tree_solve=True))

Updates benchmarks/results/brax_comparison_<platform>.json (what a run measures replaces the
file's earlier numbers of those tasks, engines and batches; each number names its run; `--fresh`
starts anew) and prints a table with ratios to Brax positional, starred where the two numbers
come from different runs (`--plot FILE` prints it again). Needs the [brax] extra (brax, mujoco).
The models are Brax's own humanoid.xml and ant.xml (copies in tests/assets), simulated at the
XML's timestep by every engine, one physics step per call of each engine's step (dbdjax: 1
substep), the same random controls in the actuators' ctrlrange. MuJoCo's ctrl and ours are the
same vector (a motor's torque = gear * ctrl).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script
import numpy as np

import dbdjax as dbd

ASSETS = Path(__file__).resolve().parents[1] / "tests" / "assets"
RESULTS = Path(__file__).resolve().parent / "results"
DBD_ITERATIONS = 4  # Gauss-Seidel iterations per substep for dbdjax (Brax's humanoid.xml asks MuJoCo for 8)
# Every engine's programs are compiled with the same XLA options: dbdjax's (`dbd.compiler_options`,
# which make Brax's programs faster too) unless --xla-defaults.
COMPILER_OPTIONS = dbd.compiler_options()


def jit(function: Callable) -> Callable:
    return jax.jit(function, compiler_options=COMPILER_OPTIONS or None)


@dataclasses.dataclass(frozen=True)
class Engine:
    """One engine on one model: pure functions over its own state type."""

    name: str
    dt: float
    num_controls: int
    control_range: np.ndarray  # (num_controls, 2)
    init: Callable[[], Any]  # () -> state
    step: Callable[[Any, jnp.ndarray], Any]  # (state, control) -> state
    joint_gap: Callable[[Any], jnp.ndarray]  # state -> largest joint gap (m)
    energy: Callable[[Any], jnp.ndarray]  # state -> kinetic + potential energy (J)
    height: Callable[[Any], jnp.ndarray]  # state -> summed body heights (a differentiable scalar)
    root_height: Callable[[Any], jnp.ndarray]  # state -> height of the root body's centre of mass (m)
    step_remat: Callable[[Any, jnp.ndarray], Any] | None = None  # step rematerialised for reverse mode
    vmap: Callable = jax.vmap  # how a batch of steps is mapped (dbdjax-dbd-trailing: dbd.vmap)


# ------------------------------------------------------------------------------------------- dbdjax


DBDJAX_VARIANTS = {
    "dbd": {},
    "impulse": {"solver": "impulse"},
    "dbd-tree": {"tree_solve": True},
    "dbd-tree-1": {"tree_solve": True, "iterations": 1},  # one sweep, then the direct solves
    "dbd-1": {"iterations": 1},  # DBD at one sweep: what a Gauss-Seidel sweep costs beside Brax's whole step
    "jacobi-tree": {"jacobi": True, "tree_solve": True},
    "dbd-trailing": {},  # DBD batched by dbd.vmap (the batch the trailing axis) instead of jax.vmap
    "dbd-points": {"point_sweeps": 2},  # DBD, then 2 sweeps of the joints' points alone
}


def dbdjax_engine(xml: Path, solver: str, substeps: int = 1) -> Engine:
    """solver: a key of DBDJAX_VARIANTS: "dbd", "impulse", "dbd-tree" (DBD with `tree_solve`: the
    direct solves of the joint tree, solvers/tree.py), "dbd-tree-1" (the same with one sweep instead
    of DBD_ITERATIONS), "jacobi-tree" (with Jacobi sweeps in place of the coloured Gauss-Seidel
    ones), "dbd-1" (DBD at one sweep), "dbd-trailing" (DBD, a batch mapped by `dbd.vmap` instead of
    `jax.vmap`) or "dbd-points" (DBD with 2 sweeps of the joints' points after its sweeps,
    `finalize(point_sweeps=2)`). substeps: per physics step (1 here; `random_controls.py --substeps`
    tries more)."""
    if solver not in DBDJAX_VARIANTS:
        raise ValueError(f"unknown dbdjax engine {solver!r}: one of {sorted(DBDJAX_VARIANTS)}")
    kwargs = {"substeps": substeps, "iterations": DBD_ITERATIONS, **DBDJAX_VARIANTS[solver]}
    model = dbd.load_mjcf(xml, **kwargs)
    remat_model = dbd.load_mjcf(xml, checkpoint=True, **kwargs)
    control_range = np.asarray(model.control_range)
    return Engine(
        name=f"dbdjax-{solver}",
        dt=model.options.dt,
        num_controls=model.num_controls,
        control_range=control_range,
        init=lambda: dbd.init(model),
        step=lambda state, control: dbd.step(model, state, control),
        step_remat=lambda state, control: dbd.step(remat_model, state, control),
        joint_gap=lambda state: jnp.max(dbd.diagnostics.joint_gaps(model, state)),
        energy=lambda state: dbd.diagnostics.energy(model, state),
        height=lambda state: jnp.sum(state.pos[:, 2]),
        root_height=lambda state: state.pos[0, 2],
        vmap=dbd.vmap if solver == "dbd-trailing" else jax.vmap,
    )


# --------------------------------------------------------------------------------------------- Brax


def brax_engine(xml: Path, backend: str) -> Engine:
    import importlib

    from brax import kinematics
    from brax import math as brax_math
    from brax.io import mjcf

    pipeline = importlib.import_module(f"brax.{backend}.pipeline")
    system = mjcf.load(str(xml))
    parents = np.asarray(system.link_parents)
    jointed = np.flatnonzero(parents >= 0)  # the free root has no joint gap
    inertia = system.link.inertia
    gravity = jnp.asarray(system.gravity)

    def centres(state):
        """Centre of mass position and velocity of each link, world frame."""
        offset = jax.vmap(brax_math.rotate)(inertia.transform.pos, state.x.rot)
        return state.x.pos + offset, state.xd.vel + jnp.cross(state.xd.ang, offset)

    def energy(state):
        pos, vel = centres(state)
        rotation = jax.vmap(brax_math.quat_to_3x3)(state.x.rot)
        world_inertia = rotation @ inertia.i @ jnp.swapaxes(rotation, -1, -2)
        kinetic = 0.5 * jnp.sum(inertia.mass * jnp.sum(vel**2, -1))
        kinetic += 0.5 * jnp.sum(jnp.einsum("ni,nij,nj->n", state.xd.ang, world_inertia, state.xd.ang))
        kinetic += 0.5 * jnp.sum(system.dof.armature * state.qd**2)  # the rotors', as dbdjax's `energy` counts them
        return kinetic - jnp.sum(inertia.mass * (pos @ gravity))

    def joint_gap(state):
        _, _, anchor_parent, anchor_child = kinematics.world_to_joint(system, state.x, state.xd)
        return jnp.max(jnp.linalg.norm(anchor_parent.pos[jointed] - anchor_child.pos[jointed], axis=-1))

    def step_remat(state, control):
        return jax.checkpoint(pipeline.step, static_argnums=())(system, state, control)

    mj = system.mj_model
    return Engine(
        name=f"brax-{backend}",
        dt=float(system.opt.timestep),
        num_controls=system.act_size(),
        control_range=np.asarray(mj.actuator_ctrlrange),
        init=lambda: pipeline.init(system, system.init_q, jnp.zeros(system.qd_size())),
        step=lambda state, control: pipeline.step(system, state, control),
        step_remat=step_remat,
        joint_gap=joint_gap,
        energy=energy,
        height=lambda state: jnp.sum(centres(state)[0][:, 2]),
        root_height=lambda state: centres(state)[0][0, 2],
    )


def make_engines(xml: Path, names: list[str]) -> tuple[list[Engine], dict[str, str]]:
    """The engines that load `xml`, and for each one that refuses it, the reason."""
    engines, skipped = [], {}
    for name in names:
        family, variant = name.split("-", 1)
        try:
            engines.append(dbdjax_engine(xml, variant) if family == "dbdjax" else brax_engine(xml, variant))
        except (TypeError, ValueError, ImportError) as error:
            skipped[name] = f"{type(error).__name__}: {error}"
            print(f"  {name} on {xml.name}: skipped ({skipped[name]})", flush=True)
    return engines, skipped


# ---------------------------------------------------------------------------------------- measures


def _seconds(function, *args) -> float:
    started = time.perf_counter()
    jax.block_until_ready(function(*args))
    return time.perf_counter() - started


def uniform_controls(control_range: np.ndarray, shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    """shape + (num_controls,) controls uniform in each actuator's range (control_range (num_controls, 2))."""
    low, high = control_range[:, 0], control_range[:, 1]
    return low + np.random.default_rng(seed).uniform(size=shape + (len(low),)) * (high - low)


def random_controls(engine: Engine, shape: tuple[int, ...], seed: int = 0) -> jnp.ndarray:
    return jnp.asarray(uniform_controls(engine.control_range, shape, seed), jnp.float32)


def rollout_function(engine: Engine, step: Callable | None = None):
    step = step or engine.step
    return lambda state, controls: jax.lax.scan(lambda s, c: (step(s, c), None), state, controls)[0]


def batched_chunk(engine: Engine, batch: int, chunk: int, compiler_options: dict | None = None):
    """(run, state): `run(state)` steps `batch` copies of the engine's initial `state` together
    through `chunk` steps of random controls (`engine.vmap` inside a lax.scan), jitted with
    `compiler_options` (None: COMPILER_OPTIONS). The program every timing here measures."""
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), engine.init())
    controls = random_controls(engine, (chunk, batch))
    batched = engine.vmap(engine.step)
    options = COMPILER_OPTIONS if compiler_options is None else compiler_options
    run = jax.jit(lambda s: jax.lax.scan(lambda s, c: (batched(s, c), None), s, controls)[0],
                  compiler_options=options or None)  # fmt: skip
    return run, state


def throughput(engine: Engine, batch: int, seconds: float, chunk: int = 10) -> dict:
    """Physics steps per second of `batch` copies stepped together by one jitted call of
    `chunk` steps (so Python overhead does not count)."""
    run, state = batched_chunk(engine, batch, chunk)
    # Two untimed calls: the first compiles, and where an engine's state comes back with other
    # types than it went in (weak types), the second compiles again; timing starts after both.
    started = time.perf_counter()
    state = jax.block_until_ready(run(state))
    state = jax.block_until_ready(run(state))
    compile_s = time.perf_counter() - started
    calls, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or calls < 2:
        state = run(state)
        calls += 1
    jax.block_until_ready(state)
    elapsed = time.perf_counter() - started
    return {
        "batch": batch,
        "steps_per_s": round(batch * calls * chunk / elapsed, 1),
        "us_per_batched_step": round(elapsed / (calls * chunk) * 1e6, 1),
        "first_two_calls_s": round(compile_s, 2),
    }


def compiled_programs(engine: Engine, horizon: int = 100) -> dict[str, tuple[float, float, Any]]:
    """Lower and compile step, a `horizon`-step rollout and grad of its final height with respect
    to the controls: {name: (seconds to trace and lower, seconds in XLA's compile, the compiled
    program)}, or {name: (None, None, the error)} for a program that failed (Brax mjx's solver loop
    has no reverse mode): one failing must not lose the others."""
    state = engine.init()
    controls = random_controls(engine, (horizon,))
    rollout = rollout_function(engine)
    programs = {
        "step": (engine.step, state, controls[0]),
        f"rollout{horizon}": (rollout, state, controls),
        f"grad_rollout{horizon}": (jax.grad(lambda c: engine.height(rollout(state, c))), controls),
    }
    result: dict[str, tuple[Any, Any, Any]] = {}
    for name, (function, *arguments) in programs.items():
        try:
            started = time.perf_counter()
            lowered = jit(function).lower(*arguments)
            traced = time.perf_counter()
            compiled = lowered.compile()
            result[name] = (traced - started, time.perf_counter() - traced, compiled)
        except Exception as error:  # noqa: BLE001
            result[name] = (None, None, error)
    return result


def compile_times(engine: Engine, horizon: int = 100) -> dict:
    """Seconds to lower and compile step, a `horizon`-step rollout and grad of its final height
    with respect to the controls (`compiled_programs`; NAME_s, or NAME_error for one that failed)."""
    result: dict[str, Any] = {}
    for name, (lowering, compiling, compiled) in compiled_programs(engine, horizon).items():
        if lowering is None:
            result[f"{name}_s"] = None
            result[f"{name}_error"] = f"{compiled!r:.300}"
        else:
            result[f"{name}_s"] = round(lowering + compiling, 2)
    return result


def coast(engine: Engine, seconds: float, measure: Callable[[Any], Any]) -> tuple[Any, Any, bool]:
    """Zero control from the initial pose for `seconds`: (the initial state, `measure` of the state
    after each step, stacked, whether the final state is finite)."""
    start = engine.init()

    def one(s, _):
        s = engine.step(s, jnp.zeros(engine.num_controls))
        return s, measure(s)

    steps = int(round(seconds / engine.dt))
    final, measured = jit(lambda s: jax.lax.scan(one, s, None, length=steps))(start)
    return start, measured, bool(np.all(np.isfinite(np.asarray(jax.tree.leaves(final)[0]))))


def dropped_accuracy(engine: Engine, seconds: float = 1.0) -> dict:
    """Zero control from the initial pose for `seconds`: the largest joint gap over the run and
    the largest rise of mechanical energy above its start (contacts and damping only remove
    energy, so any rise is the integrator's or solver's)."""
    start, (gaps, energies), finite = coast(engine, seconds, lambda s: (engine.joint_gap(s), engine.energy(s)))
    level = float(engine.energy(start))
    return {
        "steps": len(gaps),
        "max_joint_gap_m": float(jnp.max(gaps)),
        "max_energy_gain_J": float(jnp.max(energies) - level),
        "energy_change_J": float(energies[-1] - level),
        "finite": finite,
    }


def resting(engine: Engine, seconds: float = 10.0) -> dict:
    """Zero control from the initial pose for `seconds`: the height of the root body's centre of mass
    at the end (where the dropped model came to rest), its range over the last second (still
    moving?) and the largest rise of mechanical energy over the second half above its level at
    the half (a model at rest that gains energy blew up)."""
    _, measured, finite = coast(engine, seconds, lambda s: (engine.root_height(s), engine.energy(s)))
    heights, energies = (np.asarray(x) for x in measured)
    last_second, half = int(round(1.0 / engine.dt)), len(heights) // 2
    return {
        "seconds": seconds,
        "root_height_m": round(float(heights[-1]), 4),
        "root_height_last_second_m": [round(float(f(heights[-last_second:])), 4) for f in (np.min, np.max)],
        "energy_rise_second_half_J": round(float(energies[half:].max() - energies[half - 1]), 3),
        "finite": finite,
    }


def mujoco_rest(xml: Path, longest: float = 120.0) -> dict:
    """MuJoCo's own answer to `resting`: mj_step with zero control until the root body's centre of
    mass stays within 0.1 mm over 5 s (Brax's ant creeps down on its joint damping for 36 s before
    its ankles reach their limits), at most `longest` s (then "settled_after_s" is None)."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(xml))
    data = mujoco.MjData(model)
    window = int(round(5.0 / model.opt.timestep))
    steps = int(round(longest / model.opt.timestep))
    heights = np.zeros(steps)
    settled = None
    for step in range(steps):
        mujoco.mj_step(model, data)
        heights[step] = data.xipos[1, 2]
        recent = heights[max(0, step + 1 - window) : step + 1]
        if step + 1 >= window and recent.max() - recent.min() < 1e-4:
            settled = step + 1
            break
    last = (settled or steps) - 1
    ten_seconds = min(last, int(round(10.0 / model.opt.timestep)) - 1)
    return {
        "root_height_m": round(float(heights[last]), 4),
        "settled_after_s": None if settled is None else round(settled * model.opt.timestep, 2),
        "root_height_after_10_s_m": round(float(heights[ten_seconds]), 4),
    }


def gradient_cost(engine: Engine, horizon: int, remat: bool, repeats: int = 5) -> dict:
    """Time of one grad of the final height w.r.t. the controls through `horizon` steps (the best of
    `repeats` calls after a warm one: a single call of DBD's humanoid took 0.70 s in run 54, a
    probe's best of 7 0.33 s), and the compiled program's temporary memory (XLA's memory analysis:
    deterministic, unlike RSS)."""
    step = engine.step_remat if remat else engine.step
    if step is None:
        return {"skipped": "no rematerialised step"}
    state = engine.init()
    controls = random_controls(engine, (horizon,))
    rollout = rollout_function(engine, step)
    grad = jit(jax.grad(lambda c: engine.height(rollout(state, c))))
    compiled = grad.lower(controls).compile()
    memory = compiled.memory_analysis()
    temp = getattr(memory, "temp_size_in_bytes", None) if memory is not None else None
    result = jax.block_until_ready(compiled(controls))  # warm
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(compiled(controls))
        times.append(time.perf_counter() - started)
    return {
        "horizon": horizon,
        "remat": remat,
        "grad_s": round(min(times), 3),
        "grad_median_s": round(float(np.median(times)), 3),
        "temp_memory_MB": None if temp is None else round(temp / 2**20, 1),
        "grad_finite": bool(jnp.all(jnp.isfinite(result))),
    }


# ------------------------------------------------------------------------------------------- main

TASKS = ("throughput", "accuracy", "rest", "compile", "grad")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--full", action="store_true", help="batches 1 16 256 4096, longer timings, 1000-step grads")
    parser.add_argument("--models", nargs="+", default=["humanoid", "ant"])
    parser.add_argument(
        "--engines",
        nargs="+",
        default=["dbdjax-dbd", "dbdjax-impulse", "brax-positional", "brax-generalized", "brax-mjx"],
    )
    parser.add_argument(
        "--tasks",
        nargs="+",
        choices=TASKS,
        default=list(TASKS),
        help="which tasks to run; the results file's other tasks, engines and batches are kept (merged per engine)",
    )
    parser.add_argument("--batches", type=int, nargs="+", help="throughput's batch sizes (default: as --full or quick)")
    parser.add_argument("--note", default="", help="appended to the JSON's note (e.g. what else loaded the machine)")
    parser.add_argument("--plot", type=Path, help="only print the table and redraw the plot of a results JSON")
    parser.add_argument(
        "--fresh", action="store_true", help="start the results file anew instead of updating its earlier runs"
    )
    parser.add_argument(
        "--xla-defaults",
        action="store_true",
        help="compile every engine with XLA's default options instead of dbdjax.compiler_options()",
    )
    args = parser.parse_args()
    global COMPILER_OPTIONS
    if args.xla_defaults:
        COMPILER_OPTIONS = {}
    if args.plot:
        shown = json.loads(args.plot.read_text())
        for model_name, per_engine in shown["models"].items():
            print_table(model_name, per_engine, shown.get("mujoco_rest", {}).get(model_name))
        plot(args.plot)
        return
    batches = args.batches or ([1, 16, 256, 4096] if args.full else [1, 16])
    seconds = 5.0 if args.full else 1.5
    horizons = [100, 1000] if args.full else [100]

    results: dict[str, Any] = {
        "settings": {
            "dt": "each model's MJCF timestep, every engine",
            "dbdjax": f"1 substep, {DBD_ITERATIONS} iterations, float32",
            "brax": "the XML's options (brax.io.mjcf.load defaults), float32",
            "controls": "uniform random in ctrlrange (throughput); zero (dropped accuracy)",
            "compiler_options": COMPILER_OPTIONS,
        },
        "machine": {
            **machine.describe(),
            "load_average_1_5_15_min_at_start": [round(x, 2) for x in os.getloadavg()],
        },
        "note": "Every engine was measured in this one run, one after another, on the same machine and load: the "
        "ratios between engines are what this file reports; absolute steps/s depend on what else the machine ran.",
        "models": {},
    }
    if args.note:
        results["note"] += " " + args.note
    started = time.perf_counter()
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"brax_comparison_{jax.devices()[0].platform}.json"
    # Every model's engines first, then the tasks in order of what matters most (throughput, the
    # dropped model's gaps, compile times, gradient cost), the JSON rewritten after each task so
    # that a run cut short keeps what it measured (`unfinished` lists the rest).
    # A run updates the file's earlier results: the fields of the tasks, engines and batches it
    # measures are replaced, the others kept, each run's machine and load recorded under "runs" and
    # each measurement tagged with its run (`--fresh` starts the file anew).
    earlier = json.loads(out.read_text()) if out.exists() and not args.fresh else None
    this_run = {"tasks": args.tasks, "engines": args.engines, "batches": batches, "machine": results["machine"],
                "compiler_options": COMPILER_OPTIONS}  # fmt: skip
    if earlier is None:
        results["runs"] = [this_run]  # a later subset run appends to it
    if earlier is not None:
        first = {"tasks": list(TASKS), "machine": earlier["machine"], "note": earlier["note"]}
        results["runs"] = [*earlier.get("runs", [first]), this_run]
        results["models"] = earlier["models"]
        if "mujoco_rest" in earlier:
            results["mujoco_rest"] = earlier["mujoco_rest"]
        results["note"] = (
            "The results were measured in separate runs (`runs`: each run's tasks, engines, machine, load and "
            "note; a measurement's `run` is its index there, none for those measured before session 60). Within "
            "a run every engine was measured one after another: compare engines within one run (the printed "
            "table stars a ratio across runs); absolute numbers depend on what else the machine ran."
        )
    if args.note:
        this_run["note"] = args.note
    run = len(results["runs"]) - 1  # every measurement below carries it: the file mixes runs
    per_model: dict[str, tuple[list[Engine], dict[str, dict]]] = {}
    for model_name in args.models:
        engines, skipped = make_engines(ASSETS / f"{model_name}.xml", args.engines)
        per_engine = results["models"].setdefault(model_name, {})
        for e in engines:
            fields = per_engine.setdefault(e.name, {"dt": e.dt})
            # A throughput run replaces only the batch sizes it measures; grad is measured whole.
            fields["throughput"] = [t for t in fields.get("throughput", []) if "throughput" not in args.tasks
                                    or t["batch"] not in batches]  # fmt: skip
            fields["grad"] = [] if "grad" in args.tasks else fields.get("grad", [])
            rerun = ["batch" if task == "throughput" else task for task in args.tasks]
            errors = [error for error in fields.pop("errors", []) if error.split()[0] not in rerun]
            if errors:
                fields["errors"] = errors
        per_engine.pop("skipped", None)
        if "rest" in args.tasks:
            reference = {**mujoco_rest(ASSETS / f"{model_name}.xml"), "run": run}
            results.setdefault("mujoco_rest", {})[model_name] = reference
        if skipped:
            per_engine["skipped"] = skipped
        per_model[model_name] = (engines, per_engine)
    tasks = []
    if "throughput" in args.tasks:
        tasks += [(m, e, "batch", b) for b in batches for m, (es, _) in per_model.items() for e in es]
    if "accuracy" in args.tasks:
        tasks += [(m, e, "accuracy", None) for m, (es, _) in per_model.items() for e in es]
    if "rest" in args.tasks:
        tasks += [(m, e, "rest", None) for m, (es, _) in per_model.items() for e in es]
    if "compile" in args.tasks:
        tasks += [(m, e, "compile", None) for m, (es, _) in per_model.items() for e in es]
    if "grad" in args.tasks:
        tasks += [(m, e, "grad", (h, r)) for h in horizons for r in (False, True) for m, (es, _) in per_model.items()
                  for e in es if m == "humanoid"]  # fmt: skip
    labels = [
        f"{m} {e.name} {kind} {argument if argument is not None else ''}".strip() for m, e, kind, argument in tasks
    ]
    for index, (model_name, engine, kind, argument) in enumerate(tasks):
        per_engine = per_model[model_name][1]
        task_started = time.perf_counter()
        try:
            if kind == "compile":
                per_engine[engine.name]["compile"] = {**compile_times(engine), "run": run}
            elif kind == "batch":
                measured = {**throughput(engine, argument, seconds), "run": run}
                measured = [*per_engine[engine.name]["throughput"], measured]
                per_engine[engine.name]["throughput"] = sorted(measured, key=lambda t: t["batch"])
            elif kind == "accuracy":
                per_engine[engine.name]["dropped"] = {**dropped_accuracy(engine), "run": run}
            elif kind == "rest":
                per_engine[engine.name]["rest"] = {**resting(engine), "run": run}
            else:
                per_engine[engine.name]["grad"].append({**gradient_cost(engine, *argument), "run": run})
        except Exception as error:  # noqa: BLE001 - one engine failing must not lose the others' numbers
            per_engine[engine.name].setdefault("errors", []).append(f"{kind} {argument}: {error!r:.300}")
        print(f"[{index + 1}/{len(tasks)}] {labels[index]}: {time.perf_counter() - task_started:.0f} s "
              f"(total {time.perf_counter() - started:.0f} s)", flush=True)  # fmt: skip
        results["unfinished"] = labels[index + 1 :]
        results["machine"]["load_average_1_5_15_min_at_end"] = [round(x, 2) for x in os.getloadavg()]
        results["machine"]["wall_s"] = round(time.perf_counter() - started, 1)
        out.write_text(json.dumps(results, indent=2) + "\n")

    for model_name, (_, per_engine) in per_model.items():
        print_table(model_name, per_engine, results.get("mujoco_rest", {}).get(model_name))
    print(f"wrote {out}")
    plot(out)


def plot(path: Path) -> None:
    """Steps/s against batch per engine, one panel per model, next to the JSON (<stem>.png)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    results = json.loads(path.read_text())
    models = results["models"]
    figure, axes = plt.subplots(1, len(models), figsize=(5.5 * len(models), 4.2), squeeze=False)
    for ax, (model_name, per_engine) in zip(axes[0], models.items(), strict=True):
        for name, data in per_engine.items():
            if name == "skipped" or not data.get("throughput"):
                continue
            batches = [t["batch"] for t in data["throughput"]]
            rates = [t["steps_per_s"] for t in data["throughput"]]
            ax.plot(batches, rates, marker="o", label=name)
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("batch")
        ax.set_ylabel("physics steps / s")
        ax.set_title(f"{model_name} ({results['machine']['device_kind']})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    figure.tight_layout()
    out = path.with_suffix(".png")
    figure.savefig(out, dpi=110)
    print(f"wrote {out}")


def print_table(model_name: str, per_engine: dict[str, dict], mujoco: dict | None = None) -> None:
    """Steps/s per batch and compile times, each with its ratio to Brax positional; a ratio of two
    numbers that different runs measured (their "run", an index into the JSON's `runs`; none
    recorded before session 60) is starred. mujoco: MuJoCo's own rest (`mujoco_rest`), beside each
    engine's."""
    reference = per_engine.get("brax-positional", {})
    reference_rate = {t["batch"]: t for t in reference.get("throughput", [])}
    mixed = False

    def ratio(ours: dict, theirs: dict, key: str) -> str:
        nonlocal mixed
        if not ours.get(key) or not theirs.get(key):
            return "-"
        star = ours.get("run") is None or ours.get("run") != theirs.get("run")
        mixed |= star
        return f"{ours[key] / theirs[key]:.2f}" + ("*" if star else "")

    print(f"\n{model_name}")
    header = f"{'engine':<18}{'batch':>6}{'steps/s':>12}{'x brax-pos':>11}{'compile grad100 s':>19}{'x brax-pos':>11}"
    print(header)
    print("-" * len(header))
    for name, data in per_engine.items():
        if name == "skipped":
            for engine, reason in data.items():
                print(f"{engine:<18}skipped: {reason:.200}")
            continue
        compiled = data.get("compile", {})
        grad_compile = compiled.get("grad_rollout100_s")
        compile_ratio = ratio(compiled, reference.get("compile", {}), "grad_rollout100_s")
        for t in data["throughput"]:
            rate_ratio = ratio(t, reference_rate.get(t["batch"], {}), "steps_per_s")
            print(
                f"{name:<18}{t['batch']:>6}{t['steps_per_s']:>12.0f}{rate_ratio:>11}"
                f"{grad_compile if grad_compile is not None else '-':>19}{compile_ratio:>11}"
            )
        if "dropped" in data:
            d = data["dropped"]
            label = "" if data["throughput"] else name  # an engine measured on this task alone
            print(f"{label:<18}dropped 1 s: max joint gap {d['max_joint_gap_m']:.2e} m, "
                  f"energy gain {d['max_energy_gain_J']:.2f} J")  # fmt: skip
        if "rest" in data:
            r = data["rest"]
            label = "" if data["throughput"] or "dropped" in data else name
            versus = ""
            if mujoco is not None and mujoco["settled_after_s"] is None:
                versus = f" (MuJoCo's had not settled after 120 s: {mujoco['root_height_m']:.3f} m)"
            elif mujoco is not None:
                settled = mujoco["settled_after_s"]
                versus = f" (MuJoCo's, settled after {settled:.0f} s: {mujoco['root_height_m']:.3f} m)"
            print(f"{label:<18}at rest after {r['seconds']:.0f} s: root at {r['root_height_m']:.3f} m{versus}, "
                  f"energy rise in the second half {r['energy_rise_second_half_J']:.2f} J")  # fmt: skip
        for error in data.get("errors", []):
            print(f"{'':<18}error: {error}")
    if mixed:
        print("* of numbers from different runs (the JSON's `runs`), or from a run that was not recorded: "
              "the machine's load may differ between them")  # fmt: skip


if __name__ == "__main__":
    main()
