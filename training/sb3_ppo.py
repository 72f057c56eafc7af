"""Stable-Baselines3 PPO on `gymnasium.make("dbdjax/IKChainReach-v0")`: dbdjax as a plain Gymnasium env.

    python -m dbdjax.training.sb3_ppo --timesteps 20480 --eval-every 10240 --seeds 0 1 2 \\
        --out benchmarks/results/sb3_ik_chain.json

What a third-party Gymnasium client sees: SB3 wants numpy observations, so each `gym.make` env
is wrapped in Gymnasium's own `JaxToNumpy` (the single env returns JAX arrays, metadata
"jax": True, as Gymnasium's functional JAX envs do; `gymnasium.utils.env_checker.check_env`
applies that wrapper itself, SB3's `check_env` needs it applied) and then in SB3's `Monitor`
(episode returns and `info["is_success"]` at the episode's end). Training runs on SB3's
`DummyVecEnv` of `n_envs` such envs (one jitted dbdjax step per env per step).

Evaluation (`evaluate`): the deterministic policy (the Gaussian's mean) on `episodes` episodes at
once, through `gym.make_vec(..., vectorization_mode="vector_entry_point")` and Gymnasium's
vector `JaxToNumpy` (one jitted call steps every episode; the same task and seeds every time).
An episode succeeds when `info["is_success"]` holds at its last step (the tip within
`success_distance` of the goal when the 100-step episode is truncated).

The task (`ENV_KWARGS`): the registered env with `num_links=2` and `success_distance=0.05`
(5 cm), chosen so that a few minutes of PPO on a 2-core CPU shows a measurable rise: the 2-link
chain steps about 4x faster here (345 vs 83 env steps/s with random actions through `gym.make`),
and SB3 PPO on the default task (5 links, 1 cm) was not tried at this budget (the IK expert,
`dbdjax.envs.expert_action`, is that task's baseline). `--env-kwargs` changes it.
Needs the `sb3` extra (torch 2.13.0 CPU first, then stable-baselines3; README "Stable-Baselines3").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import jax
import numpy as np
import torch
from gymnasium.wrappers import JaxToNumpy
from gymnasium.wrappers.vector import JaxToNumpy as VectorJaxToNumpy
from stable_baselines3 import PPO
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

import dbdjax.envs  # noqa: F401 (registers the envs)

ENV_ID = "dbdjax/IKChainReach-v0"
#: The task the test and the recorded result use (see the module docstring).
ENV_KWARGS: dict[str, Any] = {"num_links": 2, "success_distance": 0.05}
#: PPO settings: SB3's defaults (batch 64, 10 epochs, lr 3e-4, GAE 0.95, 64-64 MLP) except a shorter
#: rollout (4 envs x 256 steps: an update every ~10 episodes of 100 steps), gamma 0.95 (the progress
#: reward pays at once; an episode is 100 steps) and a smaller initial action noise (std 0.61, not 1:
#: actions are absolute joint targets, and std 1 mostly lands on the clipped ends). Not tuned further.
PPO_KWARGS: dict[str, Any] = {
    "n_steps": 256,
    "batch_size": 64,
    "n_epochs": 10,
    "learning_rate": 3e-4,
    "gamma": 0.95,
    "gae_lambda": 0.95,
    "policy_kwargs": {"log_std_init": -0.5, "net_arch": [64, 64]},
}


def make_env(env_kwargs: dict[str, Any] | None = None) -> gym.Env:
    """One `gym.make(ENV_ID)` env as SB3 takes it: JaxToNumpy, then Monitor."""
    return Monitor(JaxToNumpy(gym.make(ENV_ID, **(ENV_KWARGS if env_kwargs is None else env_kwargs))))


def make_vec_env(n_envs: int, seed: int, env_kwargs: dict[str, Any] | None = None) -> DummyVecEnv:
    """SB3's DummyVecEnv of `n_envs` `make_env` envs, env i seeded with seed + i."""
    envs = DummyVecEnv([lambda: make_env(env_kwargs)] * n_envs)
    envs.seed(seed)
    return envs


def make_model(envs: DummyVecEnv, seed: int, ppo_kwargs: dict[str, Any] | None = None) -> PPO:
    """An untrained PPO (MLP policy, on the CPU) for `envs`; seed fixes its weights and sampling."""
    kwargs = {**PPO_KWARGS, **(ppo_kwargs or {})}
    return PPO("MlpPolicy", envs, seed=seed, device="cpu", verbose=0, **kwargs)


def evaluate(model: PPO, episodes: int = 200, seed: int = 10_000, env_kwargs: dict[str, Any] | None = None):
    """The deterministic policy of `model` on `episodes` episodes of the JAX vector env.

    seed: `reset(seed=seed)` of the vector env (episode i gets its own key from it), so every call
    with the same seed plays the same start states and goals. Returns a dict: success_rate,
    successes (per episode, 0/1), final_distance_m (median, mean), mean_return, seconds.
    """
    kwargs = ENV_KWARGS if env_kwargs is None else env_kwargs
    envs = VectorJaxToNumpy(gym.make_vec(ENV_ID, num_envs=episodes, vectorization_mode="vector_entry_point", **kwargs))
    steps = envs.unwrapped.func_env.max_episode_steps
    started = time.perf_counter()
    obs, _ = envs.reset(seed=seed)
    total = np.zeros(episodes)
    for _ in range(steps):
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, info = envs.step(action)
        total += reward
        if np.any(terminated):  # only a non-finite action or state terminates
            raise RuntimeError(f"evaluate: {int(np.sum(terminated))} episodes ended early (non-finite)")
    # The last step truncates every episode (NEXT_STEP autoreset): its info is the episode's end.
    assert np.all(truncated)
    success = np.asarray(info["is_success"], dtype=bool)
    distance = np.asarray(info["distance"], dtype=np.float64)
    envs.close()
    return {
        "episodes": episodes,
        "seed": seed,
        "success_rate": float(success.mean()),
        "successes": success.astype(int).tolist(),
        "final_distance_m": {"median": float(np.median(distance)), "mean": float(distance.mean())},
        "mean_return": float(total.mean()),
        "seconds": time.perf_counter() - started,
    }


def run(
    timesteps: int = 20_480,
    seed: int = 0,
    n_envs: int = 4,
    episodes: int = 200,
    eval_seed: int = 10_000,
    env_kwargs: dict[str, Any] | None = None,
    ppo_kwargs: dict[str, Any] | None = None,
    torch_threads: int = 1,
    progress_bar: bool = False,
    eval_every: int | None = None,
    verbose: bool = False,
) -> dict[str, Any]:
    """Evaluate an untrained PPO, train it for `timesteps` env steps, evaluate it again.

    eval_every: also evaluate after every `eval_every` training steps (a learning curve; `learn`
    is called once per chunk and continues where it stopped; a chunk that is not a whole number of
    rollouts, n_steps x n_envs, is rounded up to one by SB3).
    Returns a dict with "before" and "after" (`evaluate` results on the same episodes), "curve"
    (timesteps, success rate, median final distance after each chunk), "train_s" and
    "train_cpu_s" (wall-clock and process CPU seconds in `learn`, the first compilation of the env
    step included), the settings, and the
    number of training episodes SB3's Monitor logged. verbose: print each curve point.
    """
    torch.set_num_threads(torch_threads)  # the env's XLA threads share the same cores
    env_kwargs = ENV_KWARGS if env_kwargs is None else env_kwargs
    envs = make_vec_env(n_envs, seed, env_kwargs)
    model = make_model(envs, seed, ppo_kwargs)
    before = evaluate(model, episodes, eval_seed, env_kwargs)
    chunk = eval_every or timesteps
    train_s, train_cpu_s, curve = 0.0, 0.0, []
    while model.num_timesteps < timesteps:
        started, cpu_started = time.perf_counter(), time.process_time()
        model.learn(min(chunk, timesteps - model.num_timesteps), reset_num_timesteps=False, progress_bar=progress_bar)
        train_s += time.perf_counter() - started
        train_cpu_s += time.process_time() - cpu_started
        after = evaluate(model, episodes, eval_seed, env_kwargs)
        curve.append([model.num_timesteps, after["success_rate"], after["final_distance_m"]["median"]])
        if verbose:
            print(f"seed {seed}: {curve[-1][0]} steps, {train_s:.0f} s, success {curve[-1][1]:.3f}", flush=True)
    monitor = [env.get_episode_rewards() for env in envs.envs]
    envs.close()
    return {
        "env": ENV_ID,
        "env_kwargs": env_kwargs,
        "ppo_kwargs": {**PPO_KWARGS, **(ppo_kwargs or {})},
        "timesteps": int(model.num_timesteps),
        "seed": seed,
        "n_envs": n_envs,
        "torch_threads": torch_threads,
        "train_s": train_s,
        "train_cpu_s": train_cpu_s,
        "train_env_steps_per_s": model.num_timesteps / train_s,
        "training_episodes": sum(len(rewards) for rewards in monitor),
        "before": before,
        "after": after,
        "curve": {"columns": ["timesteps", "success_rate", "median_final_distance_m"], "rows": curve},
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--timesteps", type=int, default=20_480, help="env steps of PPO training")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds (one run each)")
    parser.add_argument("--n-envs", type=int, default=4, help="envs in SB3's DummyVecEnv")
    parser.add_argument("--episodes", type=int, default=200, help="evaluation episodes")
    parser.add_argument("--eval-every", type=int, default=None, help="evaluate every this many steps too")
    parser.add_argument("--eval-seed", type=int, default=10_000)
    parser.add_argument("--env-kwargs", type=json.loads, default=None, help=f"JSON, default {json.dumps(ENV_KWARGS)}")
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--progress", action="store_true", help="SB3's progress bar (needs tqdm and rich)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    load_at_start = [round(x, 2) for x in os.getloadavg()]  # wall times depend on what else runs
    out = {
        "command": " ".join(["python -m dbdjax.training.sb3_ppo", *(sys.argv[1:] if argv is None else argv)]),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "torch": torch.__version__,
            "jax": jax.__version__,
        },
        "load_average_at_start": load_at_start,
        "runs": [],
    }
    for seed in args.seeds:
        result = run(args.timesteps, seed, args.n_envs, args.episodes, args.eval_seed, args.env_kwargs, None,
                     args.torch_threads, args.progress, args.eval_every, verbose=True)  # fmt: skip
        summary = {key: result[key] for key in ("seed", "train_s", "train_cpu_s", "training_episodes")}
        summary.update(before=result["before"]["success_rate"], after=result["after"]["success_rate"])
        print(json.dumps(summary), flush=True)
        out["runs"].append(result)
        out["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
        if args.out is not None:  # after every seed, so a long run keeps what it finished
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(out, indent=1) + "\n")
            print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
