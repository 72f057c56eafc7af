"""What `finalize(tree_solve=True)` buys and costs: each DBD iteration ending with the direct solve
of the joint tree's points (solvers/tree.py), against the sweeps alone.

    python benchmarks/tree_solve.py            # all four sections, about 5 minutes on 2 cores

1. accuracy per step: from states of Brax's humanoid dropped with zero control (1 substep x 4,
   the brax_comparison setting), one step of each setting against a converged step (256 sweeps):
   largest body position and angular velocity error, largest joint gap;
2. cost: physics steps/s of the same settings, batch 1 and 16, measured in turn in one process
   (the ratios are the result; this machine is shared);
3. a 20-link chain at dt = 1/30 whose free end whips (tests/scenes.py's chain): largest joint gap
   over 5 s and largest energy rise;
4. the standing ragdoll (2 x 8, zero control): how far any body moves from its build pose in 4 s,
   and hung from the world by its pelvis.

Writes benchmarks/results/tree_solve_<platform>.json.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script
import numpy as np

import dbdjax as dbd
from dbdjax import ragdoll

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
import scenes  # noqa: E402  tests/scenes.py: the chain

RESULTS = ROOT / "benchmarks" / "results"
HUMANOID = ROOT / "tests" / "assets" / "humanoid.xml"
SETTINGS = [("sweeps", 4), ("sweeps", 8), ("tree_solve", 1), ("tree_solve", 2), ("tree_solve", 4)]
STATES = [10, 49, 50, 52, 100, 200, 400]  # steps of the drop: free fall, the landing, lying


def _rounded(values, digits: int) -> list[float]:
    return [round(float(v), digits) for v in np.asarray(values).ravel()]


def with_options(model, **options):
    return dataclasses.replace(model, options=dataclasses.replace(model.options, **options))


def accuracy_per_step(model) -> list[dict]:
    zero = jnp.zeros(model.num_controls)
    trajectory = jax.jit(lambda s: jax.lax.scan(lambda s, _: (dbd.step(model, s, zero),) * 2, s, None,
                                                length=max(STATES)))(dbd.init(model))[1]  # fmt: skip
    states = jax.tree.map(lambda x: x[np.asarray(STATES) - 1], trajectory)
    converged = jax.jit(jax.vmap(lambda s: dbd.step(with_options(model, iterations=256), s, zero)))(states)
    rows = []
    for kind, iterations in SETTINGS:
        variant = with_options(model, iterations=iterations, tree_solve=kind == "tree_solve")
        stepped = jax.jit(jax.vmap(lambda s, m=variant: dbd.step(m, s, zero)))(states)
        gaps = jax.vmap(lambda s: jnp.max(dbd.diagnostics.joint_gaps(model, s)))(stepped)
        rows.append({
            "setting": kind, "iterations": iterations, "after_step": STATES,
            "position_error_mm": _rounded(np.abs(stepped.pos - converged.pos).max(axis=(1, 2)) * 1e3, 4),
            "angular_velocity_error_rad_s": _rounded(np.abs(stepped.ang_vel - converged.ang_vel).max(axis=(1, 2)), 3),
            "joint_gap_mm": _rounded(gaps * 1e3, 4),
        })  # fmt: skip
        print(f"  {kind} {iterations}: position error {rows[-1]['position_error_mm']} mm", flush=True)
    return rows


def throughput(model, batches=(1, 16), steps=20, repeats=5) -> list[dict]:
    compiled = {}
    for batch in batches:
        state = jax.vmap(lambda _: dbd.init(model))(jnp.arange(batch))
        control = jnp.zeros((batch, model.num_controls))
        for kind, iterations in SETTINGS:
            variant = with_options(model, iterations=iterations, tree_solve=kind == "tree_solve")
            run = jax.jit(
                lambda s, m=variant, u=control: jax.lax.scan(
                    lambda s, _: (jax.vmap(lambda s, u: dbd.step(m, s, u))(s, u), None), s, None, length=steps
                )[0]
            )
            run = run.lower(state).compile()
            jax.block_until_ready(run(state))
            compiled[(batch, kind, iterations)] = (run, state)
    best = {key: np.inf for key in compiled}
    for _ in range(repeats):  # interleaved, so a burst of load falls on every setting alike
        for key, (run, state) in compiled.items():
            started = time.perf_counter()
            jax.block_until_ready(run(state))
            best[key] = min(best[key], time.perf_counter() - started)
    rows = [{"batch": b, "setting": k, "iterations": i, "steps_per_s": round(steps * b / best[(b, k, i)])}
            for (b, k, i) in compiled]  # fmt: skip
    for row in rows:
        print(f"  batch {row['batch']} {row['setting']} {row['iterations']}: {row['steps_per_s']} steps/s", flush=True)
    return rows


def whipping_chain() -> list[dict]:
    rows = []
    for substeps, iterations, tree_solve in [(8, 10, False), (8, 10, True), (1, 10, False), (1, 10, True),
                                              (1, 4, True)]:  # fmt: skip
        model = scenes.chain(20, dt=1 / 30, substeps=substeps, iterations=iterations, tree_solve=tree_solve)
        start = dbd.init(model)
        _, trajectory = jax.jit(lambda s, m=model: dbd.rollout(m, s, steps=150))(start)
        energy = np.asarray(jax.vmap(lambda s, m=model: dbd.diagnostics.energy(m, s))(trajectory))
        rows.append({
            "substeps": substeps, "iterations": iterations, "tree_solve": tree_solve,
            "max_joint_gap_mm": round(float(jnp.max(dbd.diagnostics.joint_gaps(model, trajectory))) * 1e3, 4),
            "max_energy_rise_J": round(float(energy.max() - dbd.diagnostics.energy(model, start)), 4),
        })  # fmt: skip
        print(f"  chain {rows[-1]}", flush=True)
    return rows


def standing_ragdoll() -> list[dict]:
    rows = []
    for hung in (False, True):
        builder, doll = ragdoll.build()
        finalize = {"dt": ragdoll.DT, "substeps": ragdoll.SUBSTEPS, "iterations": ragdoll.ITERATIONS}
        model = builder.finalize(**finalize)
        if hung:
            pelvis = doll.bodies["pelvis"]
            builder.add_fixed_joint(dbd.WORLD, pelvis, anchor=tuple(np.asarray(model.bodies.initial_pos[pelvis])))
            model = builder.finalize(**finalize)
        for tree_solve in (False, True):
            variant = with_options(model, tree_solve=tree_solve)
            controls = jnp.zeros((240, doll.num_controls))
            _, trajectory = jax.jit(lambda c, m=variant: dbd.rollout(m, dbd.init(m), c))(controls)
            moved = np.abs(np.asarray(trajectory.pos - model.bodies.initial_pos)).max(axis=(1, 2))
            at_times = _rounded(moved[[29, 59, 119, 239]] * 1e3, 2)
            rows.append({"hung_by_the_pelvis": hung, "tree_solve": tree_solve,
                         "largest_move_from_build_pose_mm_at_0.5_1_2_4_s": at_times})  # fmt: skip
            print(f"  ragdoll {rows[-1]}", flush=True)
    return rows


def main() -> None:
    results = {"machine": machine.describe(), "settings": "humanoid.xml at 1 substep; iterations as listed"}
    humanoid = dbd.load_mjcf(HUMANOID, substeps=1, iterations=4)
    print("1. accuracy per step (dropped humanoid)", flush=True)
    results["accuracy_per_step"] = accuracy_per_step(humanoid)
    print("2. throughput (humanoid)", flush=True)
    results["throughput"] = throughput(humanoid)
    print("3. whipping 20-link chain", flush=True)
    results["whipping_chain"] = whipping_chain()
    print("4. standing ragdoll", flush=True)
    results["standing_ragdoll"] = standing_ragdoll()
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"tree_solve_{jax.devices()[0].platform}.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
