"""Env steps per second of the JAX-native vector envs (gymnasium.make_vec with
vectorization_mode="vector_entry_point"): random actions made on the device, one jitted call per
step, autoreset included. Also the time of the first call (compile + one step). Writes
benchmarks/results/env_throughput.json, with the machine and its load average (the timings are
wall clock; cpu_s_per_step, the process's CPU time per batched step, moves less with other load).

    python benchmarks/env_throughput.py [--envs dbdjax/IKChainReach-v0 ...] [--batches 1 64 1024] [--steps 20]

One env step is frame_skip physics steps (2 for every dbdjax env), so physics steps/s = 2 x env steps/s.
The envs compile with `dbdjax.compiler_options()`; --xla-defaults-too also measures each env and
batch compiled with XLA's defaults, just before, so that the two can be compared under one load.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import gymnasium as gym
import jax
import machine  # benchmarks/machine.py, beside this script

import dbdjax as dbd
import dbdjax.envs  # noqa: F401 (registers the envs)


def measure(env_id: str, batch: int, steps: int, xla_defaults: bool = False) -> dict:
    # A None value drops one of dbdjax's compiler options (envs/wrappers.py).
    jit_options = {name: None for name in dbd.compiler_options()} if xla_defaults else None
    envs = gym.make_vec(env_id, num_envs=batch, vectorization_mode="vector_entry_point", jit_options=jit_options)
    envs.reset(seed=0)
    key = jax.random.PRNGKey(0)
    shape = envs.action_space.shape
    actions = jax.random.uniform(key, (steps + 1,) + shape, minval=-1.0, maxval=1.0)
    started = time.perf_counter()
    jax.block_until_ready(envs.step(actions[0]))
    first_call = time.perf_counter() - started  # compile + one step
    started, cpu_started = time.perf_counter(), time.process_time()
    for i in range(1, steps + 1):
        out = envs.step(actions[i])
    jax.block_until_ready(out)
    seconds, cpu_seconds = time.perf_counter() - started, time.process_time() - cpu_started
    frame_skip = envs.unwrapped.func_env.frame_skip
    envs.close()
    return {
        "env": env_id,
        "batch": batch,
        "compiler_options": {} if xla_defaults else dbd.compiler_options(),
        "steps": steps,
        "first_call_s": round(first_call, 2),
        "env_steps_per_s": round(batch * steps / seconds, 1),
        "physics_steps_per_s": round(batch * steps * frame_skip / seconds, 1),
        "wall_ms_per_step": round(seconds / steps * 1e3, 3),
        "cpu_s_per_step": round(cpu_seconds / steps, 4),
        "frame_skip": frame_skip,
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=sorted(dbdjax.envs.ENVIRONMENTS))
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--xla-defaults-too", action="store_true", help="also measure with XLA's default options")
    args = parser.parse_args()
    device = jax.devices()[0]
    results = {
        "command": " ".join(["python benchmarks/env_throughput.py", *sys.argv[1:]]),
        "device": str(device),
        "machine": machine.describe(),
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
        "runs": [],
    }
    out = args.out or Path(__file__).parent / "results" / "env_throughput.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    for env_id in args.envs:
        for batch in args.batches:
            for xla_defaults in (True, False) if args.xla_defaults_too else (False,):
                run = measure(env_id, batch, args.steps, xla_defaults)
                print(json.dumps(run), flush=True)
                results["runs"].append(run)
                out.write_text(json.dumps(results, indent=1) + "\n")  # after every run: a long run keeps its rows
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
