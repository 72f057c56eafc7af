"""What the RL trainers (`dbdjax.training.ppo`, `dbdjax.training.apg`) share: the policy network,
observation normalisation, evaluation episodes, and the result files (checkpoint, JSON, plot).

Policy: an MLP from the normalised observation to a residual action added to the env's *home*
action, the action whose drive targets are the build pose (`task.action_of_control(0)`; for the
ragdoll: standing straight). An untrained policy (last layer near zero) therefore holds the pose
the model was built in. The ragdoll tasks and IKChainReach map action 0 to the build pose
themselves (their home action is 0); the offset keeps the convention for any task whose action 0
is elsewhere (e.g. the middle of a one-sided range). It changes where the search starts, not
what the agent may do (every action in [-1, 1] stays reachable).

Devices: the trainers split their envs (and `evaluate` its episodes) over the local devices along
the batch axis (`env_devices`, `distribute`; `dbdjax.sharding`): every env is independent, so XLA
runs each device's share on its own, and the networks are replicated. On CPU the CLIs give JAX
one device per core they may run on (`--cpu-devices`): XLA:CPU runs a small batched program on
one thread, so a second core does nothing for one device. On this machine's two cores the PPO
iteration of the README's 30-minute runs took 1.2 s against 2.4 s on one (README: Many devices).

Observation normalisation: running mean and variance over every observation seen in training
(batched Welford/Chan update), the network sees (obs - mean) / (sqrt(var) + 0.01) clipped to +-10
(`NORMALISER_EPS`). PPO lets its networks' first layers absorb each update of the statistics
(`absorb_normaliser_update`), so that the statistics never move the policy themselves.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import platform
import re
import resource
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dbdjax import sharding
from dbdjax.compiling import jit
from dbdjax.envs.core import DbdFuncEnv

from . import checkpoint

# The validation episodes (`run`'s keep_best) are those of the reported episodes' seed plus this:
# far from any seed a run is given, so no run's validation episodes are another's reported ones.
VALIDATION_SEED_OFFSET = 100_000

# ----------------------------------------------------------------------------- networks


def init_mlp(key: jax.Array, sizes: Sequence[int], last_scale: float = 1.0) -> list[dict[str, jnp.ndarray]]:
    """Parameters of an MLP with layer widths `sizes` (input first): a list of {"w": (m, n), "b": (n,)}.

    Orthogonal weights with gain sqrt(2) on hidden layers and `last_scale` on the last (PPO's
    usual init: a small last layer starts the policy near its offset), zero biases."""
    layers = []
    keys = jax.random.split(key, len(sizes) - 1)
    for index, (key_i, fan_in, fan_out) in enumerate(zip(keys, sizes[:-1], sizes[1:], strict=True)):
        gain = last_scale if index == len(sizes) - 2 else math.sqrt(2.0)
        weight = jax.nn.initializers.orthogonal(gain)(key_i, (fan_in, fan_out), jnp.float32)
        layers.append({"w": weight, "b": jnp.zeros((fan_out,), jnp.float32)})
    return layers


def apply_mlp(layers: list[dict[str, jnp.ndarray]], x: jnp.ndarray) -> jnp.ndarray:
    """The MLP on x (..., sizes[0]) -> (..., sizes[-1]); tanh between layers, linear output."""
    for layer in layers[:-1]:
        x = jnp.tanh(x @ layer["w"] + layer["b"])
    return x @ layers[-1]["w"] + layers[-1]["b"]


class Normaliser(NamedTuple):
    """Running statistics of observations: mean (D,), var (D,), count () float32."""

    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray


def init_normaliser(size: int) -> Normaliser:
    return Normaliser(jnp.zeros((size,), jnp.float32), jnp.ones((size,), jnp.float32), jnp.zeros((), jnp.float32))


def update_normaliser(stats: Normaliser, batch: jnp.ndarray) -> Normaliser:
    """Merge a batch (..., D) into the statistics (Chan et al.'s parallel variance update)."""
    batch = batch.reshape(-1, batch.shape[-1]).astype(jnp.float32)
    n = jnp.asarray(batch.shape[0], jnp.float32)
    batch_mean = jnp.mean(batch, axis=0)
    batch_var = jnp.var(batch, axis=0)
    total = stats.count + n
    delta = batch_mean - stats.mean
    mean = stats.mean + delta * n / total
    m2 = stats.var * stats.count + batch_var * n + delta**2 * stats.count * n / total
    return Normaliser(mean, m2 / total, total)


#: Added to each observation's standard deviation before dividing by it (rsl_rl's
#: EmpiricalNormalization, legged_gym's PPO, adds the same 0.01): it bounds the network's gain on
#: an observation to 100 / unit. With 1e-8 instead, an entry that barely moves while the doll
#: stands (53 of the 133 ragdoll observations have a std under 1e-3 in the first rollout) is
#: blown up to the +-10 clip by sub-millimetre motion. (This alone did not stop APG's collapse on
#: RagdollStand-v0: README, "Why training made the policy worse".)
NORMALISER_EPS = 0.01


def _divisor(stats: Normaliser) -> jnp.ndarray:
    """(D,) what `normalise` divides by: std + `NORMALISER_EPS`."""
    return jnp.sqrt(stats.var) + NORMALISER_EPS


def normalise(stats: Normaliser, obs: jnp.ndarray) -> jnp.ndarray:
    """(obs - mean) / (std + `NORMALISER_EPS`), clipped to +-10 (before any update, with mean 0 and
    var 1: obs / 1.01)."""
    return jnp.clip((obs - stats.mean) / _divisor(stats), -10.0, 10.0)


def absorb_normaliser_update(layers: list[dict], before: Normaliser, after: Normaliser) -> list[dict]:
    """The MLP `layers` with its first layer changed so that on `after`'s normalisation it computes
    what it computed on `before`'s (exactly, for observations the +-10 clip leaves alone).

    With x = (obs - mean) / (std + eps): x_before = a x_after + c, a = (std_after + eps) /
    (std_before + eps), c = (mean_after - mean_before) / (std_before + eps), so w' = a w (row-wise)
    and b' = b + c w. Why: a statistics update otherwise moves a trained policy as much as a
    gradient step might; with a small exploration std that is a large change of the policy (PPO
    on RagdollStand-v0 lost its gain this way: README, Reinforcement learning). The first update
    (`before.count` 0: the placeholder statistics, mean 0 and variance 1) is not absorbed: the
    network was initialised for unit-scale inputs, and absorbing would scale its first layer by
    the observations' raw stds instead. (In PPO the policy's last layer is still zero at that
    update, so its output does not change; APG updates the statistics after its first gradient
    step, which that first update therefore moves.)"""
    fresh = before.count == 0
    scale = _divisor(after) / _divisor(before)
    offset = (after.mean - before.mean) / _divisor(before)
    first = layers[0]
    absorbed = {"w": scale[:, None] * first["w"], "b": first["b"] + offset @ first["w"]}
    return [jax.tree.map(lambda new, old: jnp.where(fresh, old, new), absorbed, first), *layers[1:]]


def home_action(task: DbdFuncEnv) -> jnp.ndarray:
    """(action_size,) the action whose drive targets are all zero: the build pose."""
    return jnp.asarray(task.action_of_control(jnp.zeros((task.action_size,), task.dtype)), jnp.float32)


def policy_action(task: DbdFuncEnv, policy: list[dict], stats: Normaliser, obs: jnp.ndarray) -> jnp.ndarray:
    """The deterministic action (..., action_size): home action + MLP(normalised obs), before the
    env's clip to [-1, 1]."""
    return home_action(task) + apply_mlp(policy, normalise(stats, obs))


# ----------------------------------------------------------------------------- evaluation


def act(task: DbdFuncEnv, params: dict) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """The deterministic policy of trained (or loaded) params {"policy": MLP, "obs_mean", "obs_var",
    "obs_count", ...}: obs (..., obs_size) -> action (..., action_size)."""
    return functools.partial(apply_policy, task, params)


def apply_policy(task: DbdFuncEnv, params: dict, obs: jnp.ndarray) -> jnp.ndarray:
    """`policy_action` with the network and observation statistics taken from `params`."""
    stats = Normaliser(jnp.asarray(params["obs_mean"]), jnp.asarray(params["obs_var"]),
                       jnp.asarray(params["obs_count"]))  # fmt: skip
    return policy_action(task, jax.tree.map(jnp.asarray, params["policy"]), stats, obs)


@functools.lru_cache(maxsize=32)
def _episodes(task: DbdFuncEnv, num_episodes: int, steps: int) -> Callable:
    """The jitted evaluation run (params, keys) -> (returns, lengths, alive), one compilation per
    task, batch and length (tasks hash by their settings) whatever the parameters' values."""

    @jit
    def run(params, keys):
        state, obs, _ = jax.vmap(task.reset)(keys)

        def body(carry, _):
            state, obs, alive, total, length = carry
            state, obs, reward, terminated, _, _ = jax.vmap(task.step)(state, apply_policy(task, params, obs))
            total = total + jnp.where(alive, reward, 0.0)
            length = length + alive.astype(jnp.int32)
            return (state, obs, alive & ~terminated, total, length), None

        zeros = jnp.zeros((num_episodes,))
        start = (state, obs, jnp.ones((num_episodes,), bool), zeros, jnp.zeros((num_episodes,), jnp.int32))
        (_, _, alive, total, length), _ = jax.lax.scan(body, start, None, length=steps)
        return total, length, alive

    return run


def evaluate(
    task: DbdFuncEnv,
    params: dict,
    num_episodes: int = 16,
    seed: int = 1,
    max_steps: int | None = None,
) -> dict[str, Any]:
    """Run `num_episodes` episodes of `task` with the deterministic policy of `params` (`act`), in
    one vmapped, jitted scan (compiled once per task, batch and length).

    An episode runs until it terminates or reaches `max_steps` (default task.max_episode_steps).
    The same seed gives the same episodes (start headings, pushes) for any policy. Returns numpy
    arrays "returns" and "lengths" (num_episodes,), "survived" (num_episodes,) bool (reached max_steps
    without terminating: a fall on the last step has length max_steps and survived False), and floats
    "mean_return", "mean_length", "survival" (the fraction survived).
    """
    steps = max_steps or task.max_episode_steps
    if steps is None:
        raise ValueError("evaluate: give max_steps for a task without max_episode_steps")
    keys = jax.random.split(jax.random.PRNGKey(seed), num_episodes)
    keys = sharding.shard_batch(keys, sharding.batch_mesh(env_devices(num_episodes)))
    returns, lengths, alive = (np.asarray(x) for x in _episodes(task, num_episodes, steps)(params, keys))
    return {
        "returns": returns,
        "lengths": lengths,
        "survived": alive,
        "mean_return": float(returns.mean()),
        "mean_length": float(lengths.mean()),
        "survival": float(alive.mean()),
    }


# ----------------------------------------------------------------------------- devices


def env_devices(num_envs: int, devices: Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The most of `devices` (default: every local device) over which `num_envs` envs split evenly."""
    devices = list(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("env_devices: no devices given")
    count = max(n for n in range(1, len(devices) + 1) if num_envs % n == 0)
    return devices[:count]


def distribute(state: Any, batch_fields: Sequence[str], devices: Sequence[jax.Device]) -> Any:
    """A trainer's state (a NamedTuple) placed for its jitted iteration: the `batch_fields` (the
    per-env arrays, leading axis num_envs) split along that axis over `devices`, everything else
    replicated. The iteration's outputs keep the placement (XLA propagates it)."""
    mesh = sharding.batch_mesh(devices)
    batched = set(batch_fields)
    unknown = batched - set(state._fields)
    if unknown:
        raise ValueError(f"distribute: {type(state).__name__} has no fields {sorted(unknown)}")
    return type(state)(**{
        name: sharding.shard_batch(value, mesh) if name in batched else sharding.replicate(value, mesh)
        for name, value in zip(state._fields, state, strict=True)
    })  # fmt: skip


def use_cpu_devices(count: int | None) -> int:
    """Give JAX `count` CPU devices (default: one per core this process may run on, so a `taskset`
    pin counts). Must run before JAX computes anything; if it already has, JAX keeps the devices it
    made and a note says so. Returns the number of CPU devices JAX has."""
    if count is None:
        count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if count < 1:
        raise ValueError(f"use_cpu_devices: count must be at least 1, got {count}")
    try:
        jax.config.update("jax_num_cpu_devices", int(count))
    except RuntimeError:  # the backend has started: its device count is fixed
        print(f"note: JAX has already started; it keeps {len(jax.devices('cpu'))} CPU devices", file=sys.stderr)
    return len(jax.devices("cpu"))


# ----------------------------------------------------------------------------- the training loop


# The per-env fields `fresh_envs` starts a trainer's state with (leading axis num_envs).
ENV_FIELDS = ("env_state", "obs", "episode_return", "episode_length")


def fresh_envs(task: DbdFuncEnv, num_envs: int, key: jax.Array) -> dict[str, Any]:
    """The fields both trainers' states start with: `num_envs` envs reset from `key` ("env_state",
    "obs"), no returns or lengths counted yet, and the placeholder observation statistics."""
    env_state, obs, _ = jit(jax.vmap(task.reset))(jax.random.split(key, num_envs))
    return {
        "stats": init_normaliser(task.observation_size),
        "env_state": env_state,
        "obs": obs,
        "episode_return": jnp.zeros((num_envs,), jnp.float32),
        "episode_length": jnp.zeros((num_envs,), jnp.int32),
    }


@dataclasses.dataclass
class Result:
    """What `ppo.train` and `apg.train` return: params (numpy; the checkpoint's content, `act`
    makes a policy of it: the last policy, or with keep_best the one chosen on the validation
    episodes), history (one dict per iteration: env_steps, wall_s, cpu_s, the trainer's metrics,
    eval_* where an evaluation ran: on the validation episodes with keep_best), evaluation (the
    final deterministic `evaluate` of params, on the reported episodes), initial_evaluation (of the
    untrained policy, or None), summary (settings, timings, machine; JSON-serialisable)."""

    params: dict
    history: list[dict]
    evaluation: dict
    initial_evaluation: dict | None
    summary: dict


def run(
    name: str,
    task: DbdFuncEnv,
    iteration: Callable,
    state: Any,
    export_params: Callable,
    clock: Clock,
    steps_per_iteration: int,
    iterations: int | None,
    time_budget_s: float | None,
    seed: int,
    eval_every: int,
    eval_episodes: int,
    evaluate_initial: bool,
    progress: bool,
    bar_metric: str,
    line: Callable[[dict], str],
    failure: Callable[[dict], str | None] = lambda row: None,
    summary: dict | None = None,
    keep_best: bool = False,
    eval_task: DbdFuncEnv | None = None,
) -> Result:
    """Run `iteration(state, fraction_done) -> (state, metrics)` (jitted by the caller) until
    `iterations` or `time_budget_s` wall seconds of `clock` (compilation included, evaluations not:
    the summary's `evaluation_wall_s` has them), logging one history row each. fraction_done: a
    float32 in [0, 1], how much of the run was done before the iteration, by iterations or by wall
    time, whichever budget is nearer its end (a trainer may anneal by it; the row keeps it),
    evaluating every `eval_every` iterations and at the end. failure(row): a reason to stop early,
    or None. summary: the trainer's own entries (algorithm, config, ...); timings, evaluations and
    the machine are added here. eval_task: the env every evaluation runs (validation and reported
    episodes; default `task`, the one trained on), as Brax's `eval_env`: train on a varied env,
    judge on the one that matters.

    The reported evaluation runs the episodes of seed + 1. keep_best: the evaluations every
    `eval_every` iterations and of the last policy run other episodes instead, the validation
    episodes of seed + 1 + `VALIDATION_SEED_OFFSET`, and the policy returned (and reported on
    the seed + 1 episodes) is the one that did best on them; the summary keeps the last policy's
    report too (`last_evaluation`). Choosing on the reported episodes themselves would flatter
    the choice."""
    from .trajopt import _Progress

    judged = task if eval_task is None else eval_task
    for size in ("observation_size", "action_size"):
        if getattr(judged, size, None) != getattr(task, size, None):
            raise ValueError(f"{name}: eval_task's {size} ({getattr(judged, size, None)}) is not the trained "
                             f"task's ({getattr(task, size, None)})")  # fmt: skip
    report_seed = seed + 1
    validation_seed = report_seed + VALIDATION_SEED_OFFSET if keep_best else report_seed

    evaluations: dict[tuple[int, int], dict] = {}  # (iteration, episodes' seed) -> its evaluation
    best = None  # keep_best: (validation mean return, iteration, params on the host)

    def evaluate_once(at: int, params, episodes_seed: int) -> dict:
        """The evaluation of iteration `at`'s policy on the episodes of `episodes_seed`, run once
        (the clock stops: evaluations report on the training, they are not part of it)."""
        if (at, episodes_seed) not in evaluations:
            with clock.excluding():
                evaluations[at, episodes_seed] = evaluate(judged, params, num_episodes=eval_episodes,
                                                          seed=episodes_seed)  # fmt: skip
        return evaluations[at, episodes_seed]

    def validate(row: dict, at: int, params) -> None:
        """Evaluate iteration `at`'s policy on the validation episodes into `row`; keep_best keeps
        it if it is the best so far."""
        nonlocal best
        validation = evaluate_once(at, params, validation_seed)
        row.update(_eval_entries(validation))
        if keep_best and (best is None or validation["mean_return"] > best[0]):
            best = (validation["mean_return"], at, jax.tree.map(np.asarray, params))

    initial_evaluation = evaluate_once(0, export_params(state), report_seed) if evaluate_initial else None
    history: list[dict] = []
    bar = _Progress(iterations or 10**9, name, progress and iterations is not None)
    compile_s, index = None, 0
    try:
        while True:
            done = [index / iterations] if iterations is not None else []
            done += [clock.wall() / time_budget_s] if time_budget_s is not None else []
            fraction_done = min(max(done, default=0.0), 1.0)
            state, metrics = iteration(state, np.float32(fraction_done))
            metrics = {"fraction_done": fraction_done, **{key: float(value) for key, value in metrics.items()}}
            if compile_s is None:
                compile_s = clock.wall()
            index += 1
            row = {"iteration": index, "env_steps": index * steps_per_iteration, "wall_s": clock.wall(),
                   "cpu_s": clock.cpu(), **metrics}  # fmt: skip
            if eval_every and index % eval_every == 0:
                validate(row, index, export_params(state))
            history.append(row)
            bar.update(metrics[bar_metric])
            if progress and iterations is None and (index == 1 or index % 10 == 0):
                print(line(row), flush=True)
            reason = failure(row)
            if reason is not None:
                print(f"{name}: {reason}; stopping", file=sys.stderr)
                break
            if iterations is not None and index >= iterations:
                break
            if time_budget_s is not None and clock.wall() >= time_budget_s:
                break
    finally:
        bar.close()
    train_wall, train_cpu = clock.wall(), clock.cpu()
    if keep_best and "eval_mean_return" not in history[-1]:  # the last policy competes too
        validate(history[-1], index, export_params(state))
    last_evaluation = evaluate_once(index, export_params(state), report_seed)  # run already if eval_every hit it
    kept, params = (best[1], best[2]) if keep_best else (index, export_params(state))
    evaluation = evaluate_once(kept, params, report_seed)
    if not keep_best:
        history[-1].update(_eval_entries(evaluation))

    def scalars(result: dict) -> dict:
        return {key: value for key, value in result.items() if not isinstance(value, np.ndarray)}

    summary = dict(summary or {}, seed=seed, env_steps=index * steps_per_iteration, compile_wall_s=compile_s,
                   train_wall_s=train_wall, train_cpu_s=train_cpu,
                   env_steps_per_s=index * steps_per_iteration / train_wall,
                   evaluation_wall_s=clock.excluded_wall,
                   load_average_at_start=clock.load_at_start, max_episode_steps=judged.max_episode_steps,
                   evaluation=scalars(evaluation), evaluation_lengths=evaluation["lengths"].tolist(),
                   evaluation_returns=evaluation["returns"].tolist(),
                   evaluation_seed=report_seed, keep_best=keep_best,
                   validation_seed=validation_seed if keep_best else None,
                   best_iteration=kept,
                   last_evaluation=scalars(last_evaluation),
                   last_evaluation_returns=last_evaluation["returns"].tolist(),
                   initial_evaluation=None if initial_evaluation is None else scalars(initial_evaluation),
                   initial_evaluation_returns=None if initial_evaluation is None
                   else initial_evaluation["returns"].tolist(),
                   machine=machine())  # fmt: skip
    return Result(params, history, evaluation, initial_evaluation, summary)


def _eval_entries(evaluation: dict) -> dict:
    return {"eval_mean_return": evaluation["mean_return"], "eval_mean_length": evaluation["mean_length"],
            "eval_survival": evaluation["survival"]}  # fmt: skip


# ----------------------------------------------------------------------------- command lines


def add_common_arguments(parser, name: str, num_envs: int, learning_rate: float, hidden: Sequence[int]) -> None:
    """The arguments every trainer's CLI takes (env, budget, batch, learning rate, network,
    evaluation, seed, output); `name` is the trainer ("ppo", "apg")."""
    from dbdjax.envs import TASKS

    parser.add_argument("--env", default="dbdjax/RagdollStand-v0", choices=sorted(TASKS))
    parser.add_argument("--minutes", type=float, default=None, help="wall-clock budget, compile included")
    parser.add_argument("--episode-steps", type=int, default=None, help="time limit (default: the env's)")
    parser.add_argument(
        "--env-arg", action="append", default=[], metavar="NAME=VALUE",
        help="a keyword argument of the env's constructor, VALUE read as JSON (e.g. push_speed=[0.2,0.6]); repeatable",
    )  # fmt: skip
    parser.add_argument(
        "--train-env-arg", action="append", default=[], metavar="NAME=VALUE",
        help="as --env-arg, for the env trained on only: the evaluations run the env without it "
        "(e.g. push_schedule=\"random\" to train on pushes at random times and judge on the regular ones)",
    )  # fmt: skip
    parser.add_argument("--num-envs", type=int, default=num_envs)
    parser.add_argument("--lr", type=float, default=learning_rate)
    parser.add_argument("--hidden", type=int, nargs="+", default=list(hidden))
    parser.add_argument("--eval-every", type=int, default=0, help="evaluate every N iterations (0: at the end)")
    parser.add_argument("--eval-episodes", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--keep-best", action="store_true",
        help="evaluate every --eval-every iterations on validation episodes and keep the best policy there",
    )  # fmt: skip
    parser.add_argument("--out", default=f"{name}_output", help="output folder")
    parser.add_argument("--name", default=None, help=f"file stem (default {name}_<env name in snake case>)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-plot", action="store_true")
    parser.add_argument(
        "--cpu-devices", type=int, default=None,
        help="CPU devices to split the envs over (default: one per core this process may run on; `rl.use_cpu_devices`)",
    )  # fmt: skip


def task_of(args, training: bool = False) -> DbdFuncEnv:
    """The env `--env` names, with `--episode-steps` as its time limit (default: the env's) and the
    `--env-arg NAME=VALUE` keyword arguments (VALUE as JSON; lists become tuples); training: with
    the `--train-env-arg` ones too (they win over --env-arg's)."""
    from dbdjax.envs import TASKS

    kwargs = {}
    flags = [("--env-arg", "env_arg")] + ([("--train-env-arg", "train_env_arg")] if training else [])
    for flag, field in flags:
        for item in getattr(args, field, []):
            name, sep, value = item.partition("=")
            if not sep or not name:
                raise SystemExit(f"{flag} wants NAME=VALUE, got {item!r}")
            parsed = json.loads(value)
            kwargs[name] = tuple(parsed) if isinstance(parsed, list) else parsed
    cls = TASKS[args.env]
    return cls(max_episode_steps=args.episode_steps or cls.default_max_episode_steps, **kwargs)


def tasks_of(args) -> tuple[DbdFuncEnv, DbdFuncEnv | None]:
    """(the env trained on, the env the evaluations run or None where it is the same): `task_of`
    with and without `--train-env-arg`."""
    return task_of(args, training=True), (task_of(args) if getattr(args, "train_env_arg", []) else None)


def finish(args, name: str, result: Result, counts: str) -> None:
    """Write the CLI's result files (`save_result`) and print what was trained; counts: the
    trainer's own "N updates, " style prefix."""
    stem = args.name or f"{name}_" + env_stem(args.env)
    env_args = list(getattr(args, "env_arg", []))
    train_env_args = list(getattr(args, "train_env_arg", []))
    title = f"{name.upper()} on {args.env}" + (f" ({', '.join(env_args)})" if env_args else "")
    if train_env_args:
        title += f", trained with {', '.join(train_env_args)}"
    command = "python -m dbdjax.training." + name + " " + " ".join(sys.argv[1:])
    result.summary.update(env=args.env, env_args=env_args, train_env_args=train_env_args, title=title,
                          command=command)  # fmt: skip
    paths = save_result(args.out, stem, result.params, result.history, result.summary, plot=not args.no_plot)
    s, e = result.summary, result.evaluation
    print(f"{name} on {args.env}: {counts}{s['env_steps']} env steps in {s['train_wall_s']:.0f} s wall "
          f"({s['train_cpu_s']:.0f} s CPU, compile {s['compile_wall_s']:.0f} s); evaluation: return "
          f"{e['mean_return']:.1f}, length {e['mean_length']:.0f}, survival {e['survival']:.2f}")  # fmt: skip
    for kind, path in paths.items():
        print(f"  {kind}: {path}")


# ----------------------------------------------------------------------------- bookkeeping


class Clock:
    """Wall and CPU seconds since construction, less the time spent in `excluding()` blocks (the
    evaluations, which only report on the training), and the load average (Unix) at the start."""

    def __init__(self):
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        self.excluded_wall = self.excluded_cpu = 0.0
        self.load_at_start = _load()

    def wall(self) -> float:
        return time.perf_counter() - self.wall0 - self.excluded_wall

    def cpu(self) -> float:
        return time.process_time() - self.cpu0 - self.excluded_cpu

    @contextlib.contextmanager
    def excluding(self):
        """A block whose time does not count (`excluded_wall`, `excluded_cpu` collect it)."""
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.excluded_wall += time.perf_counter() - wall
            self.excluded_cpu += time.process_time() - cpu


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def env_stem(env_id: str) -> str:
    """ "dbdjax/RagdollStand-v0" -> "ragdoll_stand", "dbdjax/IKChainReach-v0" -> "ik_chain_reach"."""
    name = env_id.split("/")[-1].split("-")[0]
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name).lower()


def machine() -> dict[str, Any]:
    """What ran it: platform, CPU count, JAX backend and devices, load average now, peak RSS (MB)."""
    return {
        "platform": platform.platform(),
        "processor": platform.machine(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(device) for device in jax.devices()],
        "load_average_at_end": _load(),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
    }


def save_result(
    out: str | Path,
    name: str,
    params: Any,
    history: list[dict[str, float]],
    summary: dict[str, Any],
    plot: bool = True,
) -> dict[str, Path]:
    """Write `<out>/<name>.npz` (the parameters, a `checkpoint` file: no pickle), `<name>.json`
    (summary + the per-iteration history) and, if `plot`, `<name>.png` (`plot_history`).
    Returns the paths written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"checkpoint": checkpoint.save(out / f"{name}.npz", params, metadata=summary)}
    paths["json"] = out / f"{name}.json"
    paths["json"].write_text(json.dumps(dict(summary, history=history), indent=1, allow_nan=True))
    if plot:
        paths["plot"] = plot_history(history, summary, out / f"{name}.png")
    return paths


def figure_history(history: list[dict[str, float]], summary: dict[str, Any]):
    """A matplotlib Figure (no pyplot): the training return and episode length against env steps,
    with the wall-clock time on a second axis, and the evaluations of the deterministic policy."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 4.2))
    steps = np.array([row["env_steps"] for row in history], float)
    title = summary.get("title", summary.get("algorithm", ""))
    panels = [("episode_return", "eval_mean_return", "episode return"),
              ("episode_length", "eval_mean_length", "episode length (steps)")]  # fmt: skip
    walls = np.array([row.get("wall_s", np.nan) for row in history], float) / 60.0
    clock_axis = None  # (env steps -> minutes, minutes -> env steps) for the top axis
    if len(steps) > 1 and np.all(np.isfinite(walls)) and walls[-1] > walls[0] and steps[-1] > steps[0]:
        # Extended linearly past both ends at the run's mean rate: clamped, every tick past the
        # last iteration (a 35 beside the 30) was drawn at the right edge.
        reach = 1e3 * (steps[-1] - steps[0])
        rate = (walls[-1] - walls[0]) / (steps[-1] - steps[0])
        step_axis = np.concatenate([[steps[0] - reach], steps, [steps[-1] + reach]])
        wall_axis = np.concatenate([[walls[0] - reach * rate], walls, [walls[-1] + reach * rate]])
        clock_axis = (lambda s: np.interp(s, step_axis, wall_axis), lambda m: np.interp(m, wall_axis, step_axis))
    for index, (key, eval_key, label) in enumerate(panels):
        ax = figure.add_subplot(1, 2, index + 1)
        values = np.array([row.get(key, np.nan) for row in history], float)
        noise = " (stochastic)" if summary.get("algorithm") == "ppo" else ""
        window = len(values) // 50  # a long run's per-iteration means are a few episodes each: smooth them
        faint = {"alpha": 0.25, "linewidth": 0.6} if window > 1 else {}
        ax.plot(steps, values, color="tab:blue", label=f"training episodes{noise}", **faint)
        if window > 1:
            ax.plot(
                steps, _running_mean(values, window), color="tab:blue", label=f"the same, mean of {window} iterations"
            )
        evals = [(row["env_steps"], row[eval_key]) for row in history if eval_key in row]
        initial = summary.get("initial_evaluation")
        validated = summary.get("keep_best", False)  # then the evals ran other episodes than the report
        if initial and not validated:  # the untrained policy, at step 0
            evals.insert(0, (0, initial[eval_key.removeprefix("eval_")]))
        if evals:
            where = " on the validation episodes" if validated else ""
            ax.plot(*np.array(evals).T, "o-", color="tab:red", label=f"evaluation{where} (deterministic)")
        if validated and summary.get("evaluation"):
            entry = eval_key.removeprefix("eval_")
            kept = steps[min(summary["best_iteration"], len(steps)) - 1]
            reported = [(0, initial[entry])] if initial else []
            label = ("untrained and " if initial else "") + "kept policy, reported episodes"
            ax.plot(*np.array(reported + [(kept, summary["evaluation"][entry])]).T, "*", color="black",
                    markersize=10, label=label)  # fmt: skip
        if key == "episode_length" and summary.get("max_episode_steps"):
            ax.axhline(summary["max_episode_steps"], color="0.5", linestyle="--", label="full episode")
        ax.set_xlabel("env steps")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        if clock_axis is not None:
            ax.secondary_xaxis("top", functions=clock_axis).set_xlabel(
                "training minutes (wall clock, evaluations left out)"
            )
        ax.legend(loc="lower right", fontsize=8)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    return figure


def _running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """The mean of the finite values among the `window` around each (NaN where there are none)."""
    finite = np.isfinite(values)
    kernel = np.ones(window)
    total = np.convolve(np.where(finite, values, 0.0), kernel, "same")
    count = np.convolve(finite.astype(float), kernel, "same")
    return np.where(count > 0, total / np.maximum(count, 1.0), np.nan)


def plot_history(history: list[dict[str, float]], summary: dict[str, Any], path: str | Path) -> Path:
    figure_history(history, summary).savefig(path, dpi=100)
    return Path(path)
