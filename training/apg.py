"""Analytic policy gradients (APG): a deterministic policy network trained by back-propagating the
return through the simulator, as Brax's `apg` does.

    from dbdjax.envs import RagdollStand
    from dbdjax.training import apg
    task = RagdollStand(max_episode_steps=150)
    result = apg.train(task, apg.APGConfig(), updates=40)      # or time_budget_s=600

    python -m dbdjax.training.apg --env dbdjax/RagdollStand-v0 --minutes 10 --out runs/apg

`num_envs` episodes run side by side (vmap) and carry on from update to update. Each update
unrolls `horizon` env steps from where they are, with actions from the policy, and takes the
gradient of the mean reward per step with respect to the policy parameters through every
`dbd.step` (the policy's actions change the drive targets, which change the next state, which
changes the next observation and action: the whole chain is differentiated). Truncation: the
state an unroll starts from is `stop_gradient`ed, so a gradient spans at most `horizon` steps
however long the episode (the variance and the size of gradients through contact dynamics grow
with the length of the chain). An episode that ends (a fall, the time limit) is reset inside
the unroll; nothing flows across a reset. Then optax: clip to global norm `max_grad_norm`, Adam.

Memory: every env step is wrapped in `jax.checkpoint` (`remat=True`), so reverse mode stores
one state per step and recomputes the solver's sweeps of one step at a time in the backward pass.

Non-finite gradients: a long chain through stiff contacts can overflow float32. An update whose
gradient has a NaN or inf is not applied (the parameters and Adam's moments stay as they were)
and counted in the history ("skipped"); every other update is clipped. Nothing is replaced
inside the gradient itself.

The policy is `training.rl`'s (build pose + MLP of the normalised observation); the observation
statistics are updated from each unroll's observations (outside the gradient).
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dbdjax.compiling import jit
from dbdjax.envs.core import DbdFuncEnv

from . import rl


@dataclasses.dataclass(frozen=True)
class APGConfig:
    """APG hyper-parameters. The defaults are the setting that raised the return on
    RagdollStand-v0 (benchmarks/results/apg_ragdoll_stand_horizon64.json: +12.4 +- 3.2 in 40
    updates); with 8-step unrolls the gradient sees the shaping terms but not the falls, and
    training lowered the return (README: Reinforcement learning).

    num_envs: episodes run side by side. horizon: env steps per update (the gradient's length).
    learning_rate: Adam's (cosine-decayed to 10% when the number of updates is known).
    max_grad_norm: global-norm clip. hidden: MLP widths. remat: `jax.checkpoint` per env step.
    normalise_observations: running mean/std of observations. init_scale: scale of the policy's
    last layer at initialisation (small: the policy starts at the build pose).
    absorb_normaliser_updates: let the policy's first layer absorb each update of the statistics
    (`rl.absorb_normaliser_update`, PPO's default). Off by default: the evidence is mixed (README:
    Reinforcement learning). A 15-minute pair of runs favoured it (paired +13.7 +- 4.1), a
    30-minute one did not (-7.9 +- 3.5); the slow APG test passes either way.
    """

    num_envs: int = 8
    horizon: int = 64
    learning_rate: float = 3e-5
    max_grad_norm: float = 1.0
    hidden: tuple[int, ...] = (64, 64)
    remat: bool = True
    normalise_observations: bool = True
    init_scale: float = 0.0
    absorb_normaliser_updates: bool = False


class TrainState(NamedTuple):
    policy: list
    opt_state: Any
    stats: rl.Normaliser
    env_state: Any
    obs: jnp.ndarray
    episode_return: jnp.ndarray
    episode_length: jnp.ndarray
    key: jnp.ndarray


Result = rl.Result


def make_update(task: DbdFuncEnv, config: APGConfig, optimiser: optax.GradientTransformation):
    """The jitted update: TrainState -> (TrainState, metrics dict of scalars)."""
    step_envs = jax.vmap(task.step)
    reset_envs = jax.vmap(task.reset)

    def env_step(policy, stats, carry, reset_key):
        env_state, obs, episode_return, episode_length = carry
        action = rl.policy_action(task, policy, stats, obs)
        env_state, next_obs, reward, terminated, truncated, _ = step_envs(env_state, action)
        done = terminated | truncated
        fresh_state, fresh_obs, _ = reset_envs(jax.random.split(reset_key, config.num_envs))
        env_state = jax.tree.map(
            lambda new, old: jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old),
            fresh_state,
            env_state,
        )
        obs = jnp.where(done[:, None], fresh_obs, next_obs)
        episode_return = episode_return + jax.lax.stop_gradient(reward)
        episode_length = episode_length + 1
        ended = {
            "count": jnp.sum(done),
            "return": jnp.sum(jnp.where(done, episode_return, 0.0)),
            "length": jnp.sum(jnp.where(done, episode_length, 0)),
            "full": jnp.sum(truncated),
        }
        carry = (env_state, obs, jnp.where(done, 0.0, episode_return), jnp.where(done, 0, episode_length))
        return carry, (reward, jax.lax.stop_gradient(obs), ended)

    if config.remat:
        env_step = jax.checkpoint(env_step)

    def loss_function(policy, state: TrainState, keys):
        start = jax.lax.stop_gradient((state.env_state, state.obs, state.episode_return, state.episode_length))

        def body(carry, key):
            return env_step(policy, state.stats, carry, key)

        carry, (rewards, observations, ended) = jax.lax.scan(body, start, keys)
        return -jnp.mean(rewards), (carry, observations, ended)

    @jit
    def update(state: TrainState, fraction_done: jnp.ndarray):
        del fraction_done  # how far the run is (`rl.run`): APG's steps do not anneal
        key, unroll_key = jax.random.split(state.key)
        keys = jax.random.split(unroll_key, config.horizon)
        (loss, (carry, observations, ended)), grads = jax.value_and_grad(loss_function, has_aux=True)(
            state.policy, state, keys
        )
        grad_norm = optax.global_norm(grads)
        finite = jnp.isfinite(grad_norm)
        updates, opt_state = optimiser.update(grads, state.opt_state, state.policy)
        policy = optax.apply_updates(state.policy, updates)
        # A non-finite gradient: keep the old parameters and optimiser state (counted as skipped).
        policy, opt_state = jax.tree.map(
            lambda new, old: jnp.where(finite, new, old), (policy, opt_state), (state.policy, state.opt_state)
        )
        stats = rl.update_normaliser(state.stats, observations) if config.normalise_observations else state.stats
        if config.absorb_normaliser_updates:
            policy = rl.absorb_normaliser_update(policy, state.stats, stats)
        env_state, obs, episode_return, episode_length = carry
        ended = jax.tree.map(jnp.sum, ended)
        count = jnp.maximum(ended["count"], 1)
        metrics = {
            "loss": loss,
            "reward_per_step": -loss,
            "grad_norm": grad_norm,
            "skipped": (~finite).astype(jnp.int32),
            "episodes": ended["count"],
            "episode_return": jnp.where(ended["count"] > 0, ended["return"] / count, jnp.nan),
            "episode_length": jnp.where(ended["count"] > 0, ended["length"] / count, jnp.nan),
            "full_episodes": jnp.where(ended["count"] > 0, ended["full"] / count, jnp.nan),
        }
        new_state = TrainState(policy, opt_state, stats, env_state, obs, episode_return, episode_length, key)
        return new_state, metrics

    return update


def export_params(state: TrainState) -> dict:
    """The parameters a checkpoint holds (numpy): the policy MLP and the observation statistics."""
    return {"policy": jax.tree.map(np.asarray, state.policy), "obs_mean": np.asarray(state.stats.mean),
            "obs_var": np.asarray(state.stats.var), "obs_count": np.asarray(state.stats.count)}  # fmt: skip


act = rl.act  # the deterministic policy of exported (or loaded) params


def train(
    task: DbdFuncEnv,
    config: APGConfig = APGConfig(),
    updates: int | None = None,
    time_budget_s: float | None = None,
    seed: int = 0,
    eval_every: int = 0,
    eval_episodes: int = 16,
    evaluate_initial: bool = False,
    progress: bool = True,
    devices: Sequence[jax.Device] | None = None,
    keep_best: bool = False,
    eval_task: DbdFuncEnv | None = None,
) -> Result:
    """Train a policy on `task` by analytic policy gradients for `updates` updates or until
    `time_budget_s` wall seconds (compilation included, evaluations not) have passed, whichever
    comes first (at least one must be given). eval_every: a deterministic evaluation of
    `eval_episodes` episodes every that many updates (0: only at the end). devices: the envs split
    over the most of these (default: every local device) that divides num_envs (`rl.env_devices`).
    keep_best: return the policy that did best on validation episodes (`rl.run`). eval_task: the env
    every evaluation runs (default `task`; `rl.run`). Returns a `Result`."""
    if updates is None and time_budget_s is None:
        raise ValueError("train: give updates or time_budget_s")
    if task.max_episode_steps is None:
        raise ValueError("train: the task needs max_episode_steps")
    rate = config.learning_rate if updates is None else optax.cosine_decay_schedule(config.learning_rate, updates, 0.1)
    optimiser = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(rate))
    clock = rl.Clock()
    key, init_key, env_key = jax.random.split(jax.random.PRNGKey(seed), 3)
    policy = rl.init_mlp(init_key, (task.observation_size, *config.hidden, task.action_size), config.init_scale)
    state = TrainState(
        policy=policy,
        opt_state=optimiser.init(policy),
        **rl.fresh_envs(task, config.num_envs, env_key),
        key=key,
    )
    devices = rl.env_devices(config.num_envs, devices)
    state = rl.distribute(state, rl.ENV_FIELDS, devices)  # the per-env fields are fresh_envs'
    result = rl.run(
        "apg", task, make_update(task, config, optimiser), state, export_params, clock,
        steps_per_iteration=config.num_envs * config.horizon, iterations=updates, time_budget_s=time_budget_s,
        seed=seed, eval_every=eval_every, eval_episodes=eval_episodes, evaluate_initial=evaluate_initial,
        progress=progress, bar_metric="reward_per_step", line=_line, keep_best=keep_best,
        eval_task=eval_task,
        summary={"algorithm": "apg", "config": dataclasses.asdict(config), "devices": len(devices)},
    )  # fmt: skip
    result.summary["updates"] = len(result.history)
    result.summary["skipped_updates"] = int(sum(row["skipped"] for row in result.history))
    return result


def _line(row: dict) -> str:
    return (f"update {row['iteration']:5d} steps {row['env_steps']:8d} wall {row['wall_s']:7.1f}s "
            f"reward/step {row['reward_per_step']:7.4f} episode return {row['episode_return']:7.2f} "
            f"length {row['episode_length']:6.1f} |grad| {row['grad_norm']:.3g}")  # fmt: skip


def main(argv: list[str] | None = None) -> Result:
    defaults = APGConfig()
    parser = argparse.ArgumentParser(
        prog="python -m dbdjax.training.apg",
        description="Train a policy on a dbdjax env by analytic policy gradients (the return differentiated "
        "through the simulator over truncated unrolls). Writes <out>/<name>.npz (checkpoint, no pickle), "
        "<name>.json (settings, timings, per-update metrics) and <name>.png (return and episode-length curves).",
    )
    rl.add_common_arguments(parser, "apg", defaults.num_envs, defaults.learning_rate, defaults.hidden)
    parser.add_argument("--updates", type=int, default=None, help="gradient updates (default: until --minutes)")
    parser.add_argument("--horizon", type=int, default=defaults.horizon, help="env steps per gradient (truncation)")
    parser.add_argument("--clip", type=float, default=defaults.max_grad_norm, help="global gradient-norm clip")
    parser.add_argument("--no-remat", action="store_true", help="no jax.checkpoint per env step")
    parser.add_argument(
        "--absorb-normaliser", action="store_true",
        help="the policy's first layer absorbs each update of the observation statistics",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.updates is None and args.minutes is None:
        parser.error("give --updates or --minutes")
    rl.use_cpu_devices(args.cpu_devices)  # before JAX computes anything
    config = APGConfig(num_envs=args.num_envs, horizon=args.horizon, learning_rate=args.lr, max_grad_norm=args.clip,
                       hidden=tuple(args.hidden), remat=not args.no_remat,
                       absorb_normaliser_updates=args.absorb_normaliser)  # fmt: skip
    budget = None if args.minutes is None else 60.0 * args.minutes
    task, eval_task = rl.tasks_of(args)
    result = train(task, config, updates=args.updates, time_budget_s=budget, seed=args.seed,
                   eval_every=args.eval_every, eval_episodes=args.eval_episodes, evaluate_initial=True,
                   progress=not args.no_progress, keep_best=args.keep_best, eval_task=eval_task)  # fmt: skip
    s = result.summary
    rl.finish(args, "apg", result, f"{s['updates']} updates ({s['skipped_updates']} skipped), ")
    return result


if __name__ == "__main__":
    main()
