"""Cost of the driven ragdoll (dbdjax.ragdoll) at dt = 1/60 on CPU: compile time and ms per step.

    .venv/bin/python benchmarks/ragdoll_step.py     # writes benchmarks/results/ragdoll_step.json

For batch 1 and batch 64 (jax.vmap over states and controls): the compile time of the jitted step
(lower + compile) and the time per step of the compiled step called from Python once per step,
as an environment does (the best of a few repeats; batch 64 also per doll). At batch 1 the step
is split into its parts (prediction, collision detection, the constraint solve, the restitution
pass, each compiled alone for one substep) to show where the time goes, and the standing doll is
checked to stay up over the steps timed. Times are this process's CPU time (time.process_time),
which a machine shared with other jobs inflates far less than wall time (also recorded, with the
load average): on a busy machine the wall time is several times the CPU time.
"""

from __future__ import annotations

import json
import os
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import dbdjax as dbd
from dbdjax import collision, integrator, ragdoll
from dbdjax.solvers import dbd as solver


def best_ms(function, *args, repeats: int = 5, calls: int = 50) -> float:
    """The best mean CPU time of this process over `repeats` of `calls` calls, ms."""
    jax.block_until_ready(function(*args))
    best = np.inf
    for _ in range(repeats):
        cpu = time.process_time()
        for _ in range(calls):
            out = function(*args)
        jax.block_until_ready(out)
        best = min(best, (time.process_time() - cpu) / calls)
    return 1e3 * best


def stepping_ms(step, state, control, steps: int, repeats: int = 3) -> tuple[float, float, object]:
    """(wall ms, CPU ms of this process) per step of `steps` consecutive steps from `state`, each the
    best of `repeats`, and the final state."""
    wall, cpu, final = np.inf, np.inf, None
    for _ in range(repeats):
        current = state
        clock, clock_cpu = time.perf_counter(), time.process_time()
        for _ in range(steps):
            current = step(current, control)
        jax.block_until_ready(current)
        wall = min(wall, (time.perf_counter() - clock) / steps)
        cpu, final = min(cpu, (time.process_time() - clock_cpu) / steps), current
    return 1e3 * wall, 1e3 * cpu, final


def measure(substeps: int, iterations: int, batch: int, steps: int = 120) -> dict:
    builder, doll = ragdoll.build()
    model = builder.finalize(dt=ragdoll.DT, substeps=substeps, iterations=iterations)
    state = dbd.init(model)
    control = jnp.zeros(model.num_controls)
    function = lambda s, c: dbd.step(model, s, c)  # noqa: E731
    if batch > 1:
        state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), state)
        control = jnp.broadcast_to(control, (batch, model.num_controls))
        function = jax.vmap(function)
    clock, clock_cpu = time.perf_counter(), time.process_time()
    step = dbd.jit(function).lower(state, control).compile()
    compile_s, compile_cpu_s = time.perf_counter() - clock, time.process_time() - clock_cpu
    wall, ms, final = stepping_ms(step, state, control, steps)
    pelvis = np.asarray(final.pos[..., doll.bodies["pelvis"], 2])
    result = {"batch": batch, "substeps": substeps, "iterations": iterations, "compile_cpu_s": round(compile_cpu_s, 2),
              "compile_wall_s": round(compile_s, 2), "cpu_ms_per_step": round(ms, 3),
              "cpu_ms_per_doll_step": round(ms / batch, 4), "wall_ms_per_step": round(wall, 3),
              "pelvis_drop_mm_after_steps": round(float(np.max(doll.rest_height - pelvis)) * 1e3, 2),
              "steps_timed": steps}  # fmt: skip
    print(json.dumps(result), flush=True)
    return result


def breakdown(substeps: int, iterations: int) -> dict:
    """ms of each part of one substep at batch 1, and with no floor (joints alone)."""
    parts = {}
    for floor in (True, False):
        builder, doll = ragdoll.build(floor=floor)
        model = builder.finalize(dt=ragdoll.DT, substeps=substeps, iterations=iterations)
        h = model.options.dt / substeps
        state, control = dbd.init(model), jnp.zeros(model.num_controls)
        predicted = integrator.predict(model, state, h, control)
        slots = collision.detect(model, state, predicted, h)
        _, _, normal, _ = solver.solve(model, predicted, control, slots, h)
        key = "" if floor else "no_floor_"
        parts[key + "solve_ms"] = best_ms(dbd.jit(lambda p, s, c, m=model, h=h: solver.solve(m, p, c, s, h)),
                                          predicted, slots, control)  # fmt: skip
        if floor:
            parts["predict_ms"] = best_ms(dbd.jit(lambda s, c, m=model, h=h: integrator.predict(m, s, h, c)), state,
                                          control)  # fmt: skip
            parts["detect_ms"] = best_ms(dbd.jit(lambda s, p, m=model, h=h: collision.detect(m, s, p, h)),
                                         state, predicted)  # fmt: skip
            parts["restitution_ms"] = best_ms(
                dbd.jit(lambda s, c, n, m=model, h=h: solver.restitution(m, s, c, n, h)), state, slots, normal
            )
            parts["colours"] = model.structure.num_colours
            parts["contact_pairs"] = sum(len(g.shapes.array) for g in model.structure.contact_groups)
    rounded = {k: round(v, 3) if isinstance(v, float) else v for k, v in parts.items()}
    result = {"substeps": substeps, "iterations": iterations, "per_substep": rounded}
    print(json.dumps(result), flush=True)
    return result


def main():
    results = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}, "
        f"{os.cpu_count()} cpus",
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
        "dt": ragdoll.DT,
        "defaults": {"substeps": ragdoll.SUBSTEPS, "iterations": ragdoll.ITERATIONS},
        "step": [
            measure(ragdoll.SUBSTEPS, ragdoll.ITERATIONS, 1),
            measure(ragdoll.SUBSTEPS, ragdoll.ITERATIONS, 64),
            measure(4, 8, 1),
        ],
        "breakdown": breakdown(ragdoll.SUBSTEPS, ragdoll.ITERATIONS),
        "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
    }
    out = pathlib.Path(__file__).parent / "results" / "ragdoll_step.json"
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
