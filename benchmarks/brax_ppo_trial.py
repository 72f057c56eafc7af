"""A short run of Brax's own PPO trainer (`brax.training.agents.ppo.train`) on dbdjax/RagdollStand-v0
through `dbdjax.envs.brax_adapter`, to compare with `dbdjax.training.ppo` (which was kept: see its
module docstring). Records compile time, wall and CPU seconds, env steps per second and the
training episodes' return and length at each of Brax's progress calls. Brax's actions get the
same home-pose offset as `dbdjax.training.rl`'s policy (a wrapper adds it), so the two start from
the same untrained behaviour. Writes benchmarks/results/brax_ppo_trial.json.

    python benchmarks/brax_ppo_trial.py [--steps 20480]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from brax.envs.base import Wrapper
from brax.training.agents.ppo import train as brax_ppo

from dbdjax.envs.brax_adapter import make_brax_env, restore_device_put_replicated
from dbdjax.training import rl


class HomeOffset(Wrapper):
    """Adds the build pose's action to the policy's (the residual convention of training.rl)."""

    def __init__(self, env):
        super().__init__(env)
        self.home = rl.home_action(env.func_env)

    def step(self, state, action):
        return self.env.step(state, self.home + action)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=20480)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "brax_ppo_trial.json"))
    args = parser.parse_args()
    restore_device_put_replicated()
    env = HomeOffset(make_brax_env("dbdjax/RagdollStand-v0"))
    load_at_start = os.getloadavg()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    log = []

    def progress(steps, metrics):
        row = {"env_steps": int(steps), "wall_s": time.perf_counter() - wall0, "cpu_s": time.process_time() - cpu0}
        row.update({k: float(v) for k, v in metrics.items() if k in ("episode/sum_reward", "episode/length")})
        log.append(row)
        print(row, flush=True)

    settings = dict(num_timesteps=args.steps, num_envs=32, episode_length=300, batch_size=32, num_minibatches=4,
                    unroll_length=20, num_updates_per_batch=4, discounting=0.97, learning_rate=3e-4,
                    entropy_cost=1e-3, normalize_observations=True, num_evals=5, run_evals=False,
                    log_training_metrics=True, max_grad_norm=1.0, seed=0)  # fmt: skip
    brax_ppo.train(env, progress_fn=progress, **settings)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    first, last = log[0], log[-1]
    steps, seconds, cpu_seconds = (last[k] - first[k] for k in ("env_steps", "wall_s", "cpu_s"))
    result = {
        "what": "brax.training.agents.ppo.train on dbdjax/RagdollStand-v0 via envs/brax_adapter.py (home-pose offset)",
        "settings": settings,
        "load_average_at_start": [round(x, 2) for x in load_at_start],
        "wall_s": wall,
        "cpu_s": cpu,
        "first_progress_wall_s": first["wall_s"],
        "first_progress_cpu_s": first["cpu_s"],
        "train_env_steps_per_wall_s": (log[-1]["env_steps"] - first["env_steps"])
        / (log[-1]["wall_s"] - first["wall_s"]),
        "train_cpu_ms_per_env_step": 1e3
        * (log[-1]["cpu_s"] - first["cpu_s"])
        / (log[-1]["env_steps"] - first["env_steps"]),
        "progress": log,
        "machine": rl.machine(),
    }
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "progress"}, indent=1))


if __name__ == "__main__":
    main()
