"""Where the time of one dbdjax step goes on CPU, on Brax's humanoid.xml and ant.xml (tests/assets):
ms per step of a jitted 100-step rollout at batch 1 and 16, the compile time of step (first batch)
and rollout, the compiled step's HLO (while loops, gathers, scatters, fusions, instructions, XLA's
flop estimate), with --parts the parts of one substep compiled alone (prediction, contact
detection, the constraint solve, the restitution pass), and Brax positional's step on the same
model, control and dt.

On XLA:CPU at small batch the step's time follows the number of compiled kernels (fusions) it
runs, not its arithmetic: each joint colour of each Gauss-Seidel iteration runs its projection's
few hundred kernels on arrays of a handful of joints. `hlo_step.fusion` counts them in the
program text (a loop body once, though it runs colours x iterations times).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/profile_step.py                    # print only
    PYTHONPATH=$PWD .venv/bin/python benchmarks/profile_step.py --baseline DIR --out \\
        benchmarks/results/profile_step_cpu.json

--baseline DIR: also measure the dbdjax found in DIR (a checkout of an earlier commit, e.g.
`git archive <commit> | tar -x -C DIR`), in child processes interleaved with this checkout's, so
that both are timed in one run under the same load (the load average is recorded with each).
--rounds N: N such before/after pairs per model, alternating, each recorded with its load
average and its CPU-time ratio (before / after), so that a ratio can be told from the noise.
--paired N (with --baseline): instead, both checkouts compile their rollouts in two resident
child processes, then time N rollout calls each, one after the other in alternating order, so
that each pair of calls meets the same load; recorded: every pair's CPU times, the median of the
pairs' ratios and the ratio of the two minima. On a loaded machine this is the steadiest ratio.
With --compiler-options both compile with `dbd.jit` (dbdjax's XLA options, as brax_comparison.py
does) instead of jax.jit's defaults: a change can run faster under one and slower under the other.
The settings are brax_comparison.py's (--solver: dbdjax's solver, dbd by default; dbd-tree: DBD
with tree_solve; dbd-tree-1: the same at one sweep): 1 substep, 4 iterations (1 for dbd-tree-1),
float32, uniform random controls in the actuators' ctrlrange, the XML's dt. Times: the best of
`--repeats` timed calls (wall and this process's CPU time; on a shared machine CPU time is the
steadier of the two).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script
import numpy as np

ASSETS = Path(__file__).resolve().parents[1] / "tests" / "assets"
HORIZON = 100


def _controls(control_range: np.ndarray, shape: tuple[int, ...]) -> jnp.ndarray:
    low, high = control_range[:, 0], control_range[:, 1]
    unit = np.random.default_rng(0).uniform(size=shape + (len(control_range),))
    return jnp.asarray(low + unit * (high - low), jnp.float32)


def _timed(function, *args, repeats: int) -> tuple[float, float]:
    """(best wall s, best CPU s) of one call, after a warm call."""
    jax.block_until_ready(function(*args))
    wall = cpu = np.inf
    for _ in range(repeats):
        clock, clock_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(function(*args))
        wall, cpu = min(wall, time.perf_counter() - clock), min(cpu, time.process_time() - clock_cpu)
    return wall, cpu


def hlo_counts(compiled) -> dict:
    """Op counts of a compiled program's HLO text, and XLA's cost estimate."""
    text = compiled.as_text()
    ops = collections.Counter(re.findall(r"=\s*[a-z0-9\[\]{},:\s]*?\s([a-z\-]+)\(", text))
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else (cost or {})
    return {
        "instructions": sum(ops.values()),
        "while": ops.get("while", 0),
        "fusion": ops.get("fusion", 0),
        "gather": ops.get("gather", 0),
        "scatter": ops.get("scatter", 0),
        "dynamic-slice": ops.get("dynamic-slice", 0),
        "dynamic-update-slice": ops.get("dynamic-update-slice", 0),
        "custom-call": ops.get("custom-call", 0),
        "flops": cost.get("flops"),
        "bytes_accessed": cost.get("bytes accessed"),
    }


def _dbdjax_settings(solver: str) -> dict:
    """The `finalize` settings brax_comparison.py runs dbdjax's `solver` with (one substep)."""
    from brax_comparison import DBD_ITERATIONS, DBDJAX_VARIANTS  # beside this script: the same settings

    return {"substeps": 1, "iterations": DBD_ITERATIONS, **DBDJAX_VARIANTS[solver]}


def engine(name: str, kind: str, solver: str = "dbd"):
    """(init state, step(state, control), control range, dt) of dbdjax (its `solver`: dbd, impulse,
    dbd-tree: DBD with `finalize(tree_solve=True)`, or dbd-tree-1: the same at one sweep) or
    brax-positional on a model."""
    xml = ASSETS / f"{name}.xml"
    if kind == "dbdjax":
        import dbdjax as dbd

        model = dbd.load_mjcf(xml, **_dbdjax_settings(solver))
        return dbd.init(model), lambda s, c: dbd.step(model, s, c), np.asarray(model.control_range), model
    from brax.io import mjcf
    from brax.positional import pipeline

    system = mjcf.load(str(xml))
    state = pipeline.init(system, system.init_q, jnp.zeros(system.qd_size()))
    return state, lambda s, c: pipeline.step(system, s, c), np.asarray(system.mj_model.actuator_ctrlrange), None


def measure(name: str, kind: str, batches: list[int], repeats: int, hlo: bool, parts_too: bool = False,
            solver: str = "dbd") -> dict:  # fmt: skip
    state, step, control_range, model = engine(name, kind, solver)
    result: dict = {"load_average_at_start": [round(x, 2) for x in os.getloadavg()], "batches": []}
    for batch in batches:
        controls = _controls(control_range, (HORIZON, batch))
        batched = jax.tree.map(lambda x, b=batch: jnp.broadcast_to(x, (b,) + x.shape), state)
        one = jax.vmap(step)

        def rollout(s, cs, one=one):
            return jax.lax.scan(lambda s, c: (one(s, c), None), s, cs)[0]

        clock = time.perf_counter()
        compiled_rollout = jax.jit(rollout).lower(batched, controls).compile()
        rollout_compile = time.perf_counter() - clock
        wall, cpu = _timed(compiled_rollout, batched, controls, repeats=repeats)
        entry = {
            "batch": batch,
            "ms_per_step_wall": round(1e3 * wall / HORIZON, 4),
            "ms_per_step_cpu": round(1e3 * cpu / HORIZON, 4),
            "compile_rollout100_s": round(rollout_compile, 2),
            "load_average": [round(x, 2) for x in os.getloadavg()],
        }
        if batch == batches[0]:  # the step alone, at the first batch only: its compile time, a call, its HLO
            clock = time.perf_counter()
            compiled_step = jax.jit(one).lower(batched, controls[0]).compile()
            entry["compile_step_s"] = round(time.perf_counter() - clock, 2)
            call_wall, _ = _timed(compiled_step, batched, controls[0], repeats=5 * repeats)
            entry["ms_per_step_call_wall"] = round(1e3 * call_wall, 4)  # one jitted step called from Python
            if hlo:
                entry["hlo_step"] = hlo_counts(compiled_step)
        result["batches"].append(entry)
        print(f"  {name:9s} {kind:16s} batch {batch:3d}: {entry['ms_per_step_wall']:.3f} ms/step wall, "
              f"{entry['ms_per_step_cpu']:.3f} cpu, compile rollout {rollout_compile:.1f} s, "
              f"load {entry['load_average'][0]:.1f}", flush=True)  # fmt: skip
    if model is not None and parts_too:
        result["parts_batch1_ms"] = parts(model, state, control_range, repeats)
    result["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    return result


def parts(model, state, control_range, repeats: int) -> dict:
    """ms of each part of one substep at batch 1, each compiled alone (an upper bound on its share:
    the whole step fuses across the parts)."""
    from dbdjax import collision, integrator
    from dbdjax.solvers import dbd as solver

    h = model.options.dt / model.options.substeps
    control = _controls(control_range, (1,))[0]
    predicted = integrator.predict(model, state, h, control)
    slots = collision.detect(model, state, predicted, h)
    _, _, normal, _ = solver.solve(model, predicted, control, slots, h, start=state)
    functions = {
        "predict": (jax.jit(lambda s, c: integrator.predict(model, s, h, c)), (state, control)),
        "detect": (jax.jit(lambda s, p: collision.detect(model, s, p, h)), (state, predicted)),
        "solve": (
            jax.jit(lambda p, c, sl, s: solver.solve(model, p, c, sl, h, start=s)),
            (predicted, control, slots, state),
        ),  # fmt: skip
        "restitution": (jax.jit(lambda s, sl, n: solver.restitution(model, s, sl, n, h)), (state, slots, normal)),
    }
    out = {}
    for key, (function, args) in functions.items():
        wall, _ = _timed(function, *args, repeats=20 * repeats)
        out[key] = round(1e3 * wall, 4)
    return out


def serve(args) -> None:
    """Resident child of --paired: compile the rollout at each batch, print "ready", then answer each
    line "<batch index>" on stdin with one timed call's "<cpu s> <wall s>"."""
    state, step, control_range, _ = engine(args.model, "dbdjax", args.solver)
    calls = []
    for batch in args.batches:
        controls = _controls(control_range, (HORIZON, batch))
        batched = jax.tree.map(lambda x, b=batch: jnp.broadcast_to(x, (b,) + x.shape), state)
        one = jax.vmap(step)
        rollout = lambda s, cs, one=one: jax.lax.scan(lambda s, c: (one(s, c), None), s, cs)[0]  # noqa: E731
        if args.compiler_options:  # what brax_comparison.py compiles with (`dbd.jit`)
            import dbdjax as dbd

            compiled = dbd.jit(rollout)
        else:
            compiled = jax.jit(rollout)
        compiled = compiled.lower(batched, controls).compile()
        jax.block_until_ready(compiled(batched, controls))
        calls.append((compiled, batched, controls))
    print("ready", flush=True)
    for line in sys.stdin:
        function, batched, controls = calls[int(line)]
        clock, clock_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(function(batched, controls))
        print(f"{time.process_time() - clock_cpu} {time.perf_counter() - clock}", flush=True)


def paired(baseline: str, here: str, model: str, args) -> dict:
    """--paired: N alternating timed calls of the baseline's and this checkout's rollouts."""
    command = [sys.executable, __file__, "--serve", "--model", model, "--solver", args.solver,
               "--batches", *map(str, args.batches)]  # fmt: skip
    command += ["--compiler-options"] if args.compiler_options else []
    servers = [
        subprocess.Popen(
            command, env=dict(os.environ, PYTHONPATH=path), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )  # fmt: skip
        for path in (baseline, here)
    ]
    for server in servers:
        while server.stdout.readline().strip() != "ready":
            pass
    times = {batch: ([], []) for batch in args.batches}  # (before, after) CPU s per call
    loads = []
    for k in range(args.paired):
        for index, batch in enumerate(args.batches):
            for which in (0, 1) if k % 2 == 0 else (1, 0):
                servers[which].stdin.write(f"{index}\n")
                servers[which].stdin.flush()
                times[batch][which].append(float(servers[which].stdout.readline().split()[0]))
        loads.append(round(os.getloadavg()[0], 2))
    for server in servers:
        server.stdin.close()
        server.wait()
    out = {"load_average_1min": [min(loads), max(loads)], "load_averages": loads}
    for batch, (before, after) in times.items():
        ratios = np.asarray(before) / np.asarray(after)
        out[f"batch_{batch}"] = {
            "cpu_ms_per_step_before": [round(1e3 * t / HORIZON, 4) for t in before],
            "cpu_ms_per_step_after": [round(1e3 * t / HORIZON, 4) for t in after],
            "cpu_ratio_median": round(float(np.median(ratios)), 3),  # before / after: > 1 is faster
            "cpu_ratio_quartiles": [round(float(q), 3) for q in np.percentile(ratios, [25, 75])],
            "cpu_ratio_of_minima": round(min(before) / min(after), 3),
        }
        got = out[f"batch_{batch}"]
        print(f"{model} batch {batch} paired x{args.paired}: CPU ratio median {got['cpu_ratio_median']} (quartiles "
              f"{got['cpu_ratio_quartiles']}), of minima {got['cpu_ratio_of_minima']}, load {min(loads)}-{max(loads)}",
              flush=True)  # fmt: skip
    return out


def child(args) -> None:
    """Measure one (model, engine) in this process and print its JSON on the last line."""
    result = measure(args.model, args.kind, args.batches, args.repeats, args.hlo, args.parts, args.solver)
    print(json.dumps(result))


def _ratios(before: dict, after: dict) -> dict:
    """Per batch: CPU and wall ms/step before and after, their ratios (before / after: > 1 is
    faster), and the load averages the two children measured under."""
    out = {}
    for old, new in zip(before["batches"], after["batches"], strict=True):
        out[f"batch_{new['batch']}"] = {
            "cpu_ms_before": old["ms_per_step_cpu"],
            "cpu_ms_after": new["ms_per_step_cpu"],
            "cpu_ratio": round(old["ms_per_step_cpu"] / new["ms_per_step_cpu"], 3),
            "wall_ratio": round(old["ms_per_step_wall"] / new["ms_per_step_wall"], 3),
            "load_before": old.get("load_average", before["load_average_at_start"])[0],
            "load_after": new.get("load_average", after["load_average_at_start"])[0],
        }
    return out


def run_child(path: str, model: str, kind: str, args) -> dict:
    env = dict(os.environ, PYTHONPATH=path)
    command = [sys.executable, __file__, "--child", "--model", model, "--kind", kind, "--repeats", str(args.repeats),
               "--solver", args.solver, "--batches", *map(str, args.batches)]  # fmt: skip
    command += ["--hlo"] if kind == "dbdjax" else []
    command += ["--parts"] if kind == "dbdjax" and args.parts else []
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
    lines = done.stdout.strip().splitlines()
    print("\n".join(lines[:-1]), flush=True)
    return json.loads(lines[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["humanoid", "ant"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 16])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--baseline", help="a directory holding an earlier dbdjax to time side by side")
    parser.add_argument("--no-brax", action="store_true")
    parser.add_argument("--parts", action="store_true", help="also time the parts of one substep (batch 1)")
    parser.add_argument("--rounds", type=int, default=1, help="before/after child pairs per model (0: --paired only)")
    parser.add_argument("--out", help="write the results here (JSON)")
    parser.add_argument("--note", default="")
    parser.add_argument(
        "--solver",
        default="dbd",
        choices=["dbd", "impulse", "dbd-tree", "dbd-tree-1"],
        help="dbdjax's solver (dbd-tree: tree_solve; dbd-tree-1: tree_solve at one sweep)",
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--model", help=argparse.SUPPRESS)
    parser.add_argument("--kind", help=argparse.SUPPRESS)
    parser.add_argument("--hlo", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--paired", type=int, default=0, help="N alternating timed calls (with --baseline)")
    parser.add_argument("--compiler-options", action="store_true",
                        help="--paired: compile with dbd.jit (dbdjax's XLA options, as brax_comparison.py) "
                             "instead of jax.jit's defaults")  # fmt: skip
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.parts and args.solver != "dbd":
        parser.error("--parts times the DBD solver's parts: leave --solver at dbd")
    if args.child:
        child(args)
        return
    if args.serve:
        serve(args)
        return
    here = str(Path(__file__).resolve().parents[1])
    started = time.perf_counter()
    results: dict = {
        "settings": f"solver {args.solver}, 1 substep, {_dbdjax_settings(args.solver)['iterations']} iterations, "
        "float32, the XML's dt, "
        "uniform random controls in ctrlrange; "
        f"ms/step of a jitted {HORIZON}-step rollout (lax.scan of the vmapped step), best of {args.repeats}",
        "machine": machine.describe(),
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
        "note": args.note,
        "models": {},
    }
    for model in args.models:
        entry = {}
        if args.paired and args.baseline:
            entry["paired"] = paired(str(Path(args.baseline).resolve()), here, model, args)
        for round_index in range(args.rounds if args.baseline else 1):
            if args.baseline:
                before = run_child(str(Path(args.baseline).resolve()), model, "dbdjax", args)
            after = run_child(here, model, "dbdjax", args)
            if round_index == 0:
                entry["dbdjax"] = after
                if args.baseline:
                    entry["dbdjax_before"] = before
                    entry["rounds"] = []
            else:
                entry.setdefault("dbdjax_more", []).append(after)
                entry.setdefault("dbdjax_before_more", []).append(before)
            if args.baseline:
                entry["rounds"].append(_ratios(before, after))
                print(f"{model} round {round_index}: {entry['rounds'][-1]}", flush=True)
        if not args.no_brax:
            entry["brax_positional"] = run_child(here, model, "brax", args)
        results["models"][model] = entry
        if args.out:  # after each model, so that a run cut short keeps what it measured
            Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
        for batch_index, batch in enumerate(args.batches if "dbdjax" in entry else []):  # --rounds 0: paired only
            ours = entry["dbdjax"]["batches"][batch_index]["ms_per_step_wall"]
            line = f"{model} batch {batch}: dbdjax {ours:.3f} ms"
            if args.baseline:
                before = entry["dbdjax_before"]["batches"][batch_index]["ms_per_step_wall"]
                cpu = [r[f"batch_{batch}"]["cpu_ratio"] for r in entry["rounds"]]
                line += f" (before {before:.3f} ms, x{before / ours:.2f} faster; CPU time ratios {cpu})"
            if not args.no_brax:
                brax = entry["brax_positional"]["batches"][batch_index]["ms_per_step_wall"]
                line += f", brax positional {brax:.3f} ms (dbdjax / brax = {ours / brax:.2f})"
            print(line, flush=True)
    results["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    results["wall_s"] = round(time.perf_counter() - started, 1)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
