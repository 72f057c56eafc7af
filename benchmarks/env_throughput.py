"""Env steps per second of the JAX-native vector envs (gymnasium.make_vec with
vectorization_mode="vector_entry_point"): random actions made on the device, one jitted call per
step, autoreset included. Also the time of the first call (compile + one step). Writes
benchmarks/results/env_throughput.json, with the machine and its load average (the timings are
wall clock; cpu_s_per_step, the process's CPU time per batched step, moves less with other load).

    python benchmarks/env_throughput.py [--envs dbdjax/IKChainReach-v0 ...] [--batches 1 64 1024] [--steps 20]

One env step is frame_skip physics steps (2 for every dbdjax env), so physics steps/s = 2 x env steps/s.
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

import dbdjax.envs  # noqa: F401 (registers the envs)


def measure(env_id: str, batch: int, steps: int) -> dict:
    envs = gym.make_vec(env_id, num_envs=batch, vectorization_mode="vector_entry_point")
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
            run = measure(env_id, batch, args.steps)
            print(json.dumps(run), flush=True)
            results["runs"].append(run)
            out.write_text(json.dumps(results, indent=1) + "\n")  # after every run: a long run keeps its rows
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
