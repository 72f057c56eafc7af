"""Physics steps per second of a 16-body ball-joint chain at batch 1, 64 and 1024, and the
compile time of `step` and of grad-of-rollout. Writes benchmarks/results/chain_throughput_<host>.json.

    python benchmarks/chain_throughput.py [--batches 1 64 1024] [--seconds 2]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script

import dbdjax as dbd

LINKS = 16


def chain_model() -> dbd.Model:
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    previous = dbd.WORLD
    for i in range(LINKS):
        link = b.add_body(pos=((i + 0.5) * 0.1, 0.0, 1.0), mass=0.1, inertia=(5e-6, 8.3e-5, 8.3e-5))
        b.add_ball_joint(previous, link, anchor=(i * 0.1, 0.0, 1.0))
        previous = link
    return b.finalize(dt=1 / 60, substeps=1, iterations=8)


def timed(function, *args):
    started = time.perf_counter()
    jax.block_until_ready(function(*args))
    return time.perf_counter() - started


def measure_batch(model, batch: int, seconds: float) -> dict:
    start = dbd.init(model)
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), start)
    chunk = 10  # steps per call, in a scan, so Python overhead does not count
    run = dbd.jit(
        lambda s: jax.lax.scan(
            lambda s, _: (jax.vmap(dbd.step, in_axes=(None, 0))(model, s), None), s, None, length=chunk
        )[0]
    )
    compile_seconds = timed(run, state)
    calls, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        state = run(state)
        calls += 1
    jax.block_until_ready(state)
    elapsed = time.perf_counter() - started
    steps = calls * chunk
    return {
        "batch": batch,
        "compile_s": round(compile_seconds, 3),
        "us_per_batched_step": round(elapsed / steps * 1e6, 2),
        "physics_steps_per_s": round(batch * steps / elapsed, 1),
        "all_finite": bool(jnp.all(dbd.is_finite(state))),
    }


def grad_compile_time(model, horizon: int = 32) -> float:
    def loss(vel):
        final, _ = dbd.rollout(model, dbd.State(model.bodies.initial_pos, model.bodies.initial_quat, vel,
                                                model.bodies.initial_ang_vel), steps=horizon)  # fmt: skip
        return jnp.sum(final.pos[:, 2])

    return timed(dbd.jit(jax.grad(loss)), model.bodies.initial_vel)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()

    model = chain_model()
    step_compile = timed(dbd.jit(dbd.step).lower(model, dbd.init(model)).compile)
    results = {
        "scene": f"{LINKS}-body ball-joint chain, dt=1/60, 1 substep, 8 iterations, float32",
        "engine": f"dbdjax {dbd.__version__}",
        "machine": machine.describe(),
        "compile_step_s": round(step_compile, 3),
        "compile_grad_rollout32_s": round(grad_compile_time(model), 3),
        "batches": [measure_batch(model, batch, args.seconds) for batch in args.batches],
    }
    print(json.dumps(results, indent=2))
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    name = f"chain_throughput_{jax.devices()[0].platform}.json"
    (out / name).write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {out / name}")


if __name__ == "__main__":
    main()
