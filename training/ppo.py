"""PPO on the JAX-native vector env: `num_envs` copies of a `DbdFuncEnv` under `jax.vmap`, every
training iteration (rollout, GAE, all epochs and minibatches of updates) one jitted function.

    from dbdjax.envs import RagdollStand
    from dbdjax.training import ppo
    task = RagdollStand(max_episode_steps=300, push_interval=2.0)
    result = ppo.train(task, ppo.PPOConfig(), total_steps=200_000)      # or time_budget_s=1800
    result.params, result.history, result.evaluation                       # params: policy, value, log_std, obs stats

    python -m dbdjax.training.ppo --env dbdjax/RagdollStand-v0 --minutes 30 --out runs/ppo

Written in the style of PureJaxRL (one file, plain JAX and optax, no framework): an iteration
collects `unroll_length` steps from each of `num_envs` envs with a Gaussian policy (state-free
log std), computes generalised advantage estimates (Schulman et al. 2016), and runs
`update_epochs` passes of `num_minibatches` minibatches of the clipped surrogate objective
(Schulman et al. 2017) with a value loss and an entropy bonus; Adam after global-norm clipping.
The Python loop around the jitted iteration only logs, draws the progress bar and checks the
time budget. The policy is `training.rl`'s: the build pose ("home" action) plus an MLP of the
normalised observation; the value network is a separate MLP of the same observation. After each
update of the observation statistics both networks' first layers absorb it (they compute what they
computed before it: `PPOConfig.absorb_normaliser_updates`).

Episode ends: a termination (a fall) has value 0 after it; a truncation (the time limit) is
bootstrapped with the value of the episode's last observation, so the time limit, which the
observation does not show, is not mistaken for a fall. Ended envs reset in the same step (their
next observation is the new episode's first).

Why this trainer and not Brax's `ppo.train` through `envs/brax_adapter.py`: both were run on
RagdollStand-v0 on this repository's shared 2-core CPU (load average 12-18 from other jobs), with
the home-pose offset added to Brax's actions by a wrapper (benchmarks/brax_ppo_trial.py,
benchmarks/results/brax_ppo_trial.json). Physics dominates both: Brax's trainer spent 3.8 ms of
CPU per env step (32 envs, steady state), this one 3.4 ms (64 envs, updates included); Brax's
first update came after 85 s of CPU (compilation), this one's after 124 s (compilation plus an
evaluation of the untrained policy). So neither is decisively faster here; this one is kept
because it is slightly cheaper per step, bootstraps at the time limit (Brax's
`bootstrap_on_timeout` needs a `time_out` entry the adapter does not provide), resets an ended
episode from a fresh random start (Brax's AutoResetWrapper replays each slot's first start),
spends nothing on Brax's separate evaluation rollouts, and is one file whose every step can be
read. In the trial's 15,360 steps Brax's training episodes stayed at 23-24 steps; this trainer's
were at 29 steps after a similar number (ppo_ragdoll_stand.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dbdjax import trailing_batch
from dbdjax.compiling import jit
from dbdjax.envs.core import DbdFuncEnv

from . import rl


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters. The run in benchmarks/results/ppo_ragdoll_stand.json used these with
    unroll_length 16, num_minibatches 2 and noise_correlation 0.9 (README: Reinforcement learning);
    the starting learning rate is 3e-5 since a start at 3e-4 moved the policy by a KL of 111.

    num_envs: envs stepped together (vmap). unroll_length: steps per env per iteration; an
    iteration has num_envs x unroll_length transitions, split into num_minibatches minibatches
    and passed over update_epochs times. gamma: discount; gae_lambda: GAE's lambda.
    clip_epsilon: the ratio clip. value_coef, entropy_coef: loss weights. learning_rate: Adam's
    (linearly decayed to 10% over the run when total_steps is known); max_grad_norm: global-norm
    clip. hidden: widths of both MLPs. init_log_std: log std of the initial policy (per action
    entry, in action units: 1 is a drive's `control_scale`, e.g. 1.6 rad at a hip). Small by
    default (std 0.01): the ragdoll's drives are stiff (hips 10000 N m/rad, ankles 8000), so a
    target error of 0.01 rad is already 80-100 N m, and at std 0.1 the exploration noise alone
    topples the standing doll within about 34 steps (the deterministic home pose stands through
    58 of 60 on the same pushes). normalise_observations: running
    mean/std normalisation. reward_scale: multiplies rewards before the value targets.
    desired_kl: None, or the KL-adaptive learning rate of rsl_rl (legged_gym's PPO): before each
    minibatch step the learning rate is divided by 1.5 when the policy's KL from the rollout
    policy (`policy_kl`: N(mean(s), std^2), the policy without memory of its noise) exceeds
    2 x desired_kl and multiplied by 1.5 when it is under desired_kl / 2
    (kept in [1e-5, 1e-2]); `learning_rate` is then its starting value (no decay). A small
    exploration std makes a fixed Adam step a large change of the policy (the KL of a mean shift
    grows as 1 / std^2): the adaptive rate keeps each update's change of the policy bounded.
    noise_correlation: rho in [0, 1), the exploration noise is AR(1) in time, noise_t = rho
    noise_{t-1} + sqrt(1 - rho^2) std xi_t (stationary std `exp(log_std)`, correlation time
    1 / (1 - rho) steps; a new episode starts from a stationary draw). 0: independent per step.
    The step's policy is N(mean(s_t) + rho (a_{t-1} - mean(s_{t-1})), (sqrt(1 - rho^2) std)^2):
    the last noise is the policy's own (`step_distribution_mean`). Until session 17 it was held
    fixed as a part of the state (`Transition.shift`), which credits mean(s_t) with the effect of
    a deviation that lasts the correlation time; on RagdollStand-v0 (the PPO test's setting, rho
    0.9) that grew a state-dependent ankle feedback every iteration (its spread over the batch
    0.001 -> 0.029 action units in 100 iterations) while the training return fell 91 -> 55
    (iterations 10 -> 100). With the likelihood right it is worse still there (a backward lean
    of 0.014 and a spread of 0.031 in 20 iterations, return 95 -> 64): the noise's effect on the
    doll shows in the observation, and the policy learns to counter its own noise, which the
    noise-free policy that is evaluated does not have. Independent noise (0, the default) raised
    the training return 95 -> 177 over the same 100 iterations (README: Reinforcement learning).
    explored_actions: None (every action entry explores), or the indices of the action entries
    that do: the others get no noise and no part in the log-probability, so no gradient reaches
    their output weights (zero at the start) and the policy keeps acting their home value. On
    RagdollStand-v0 noise of std 0.01 on the 24 non-ankle entries alone shortens the 150-step
    episodes of the home pose from 128 to 82 steps (no full episode of 32), the same noise on
    the two ankles to 112: exploring everywhere, PPO learns from a policy far worse than the
    deterministic one it is evaluated as.
    init_log_std_of: ((index, log std), ...) action entries whose initial log std is not
    `init_log_std`: noise in each drive's own measure (a std of 0.01 is 0.016 rad at a hip, whose
    drive is 10000 N m/rad, and 0.008 rad at an ankle, 8000 N m/rad), or a gentler start for the
    entries a policy leans on least. Only the start: log_std is learnt per entry as before.
    step_scale_of: ((index, scale), ...) action entries whose mean learns at `scale` times the
    step of the others: Adam's updates of the policy's last layer for that output (its weights and
    bias) are multiplied by `scale`. Adam moves every weight by about the rate whatever its
    gradient, so an entry explored at a fifth of the others' std moves its mean as far per step
    as they do, five of its own stds. With the hips' roll and pitch at std 0.002 and the ankles at
    0.01 the training return fell from the untrained 120 to about 50 for nine minutes (README):
    the hips' mean moving did it (their noise with their step scaled by 1e-6 did not: the return
    rose as with the ankles alone); at a scale of 0.2 it still fell, at 0.05 it fell for about 50
    iterations (README: "What collapsed the hips' runs").
    absorb_normaliser_updates: after each update of the observation statistics, change the first
    layers of both networks so that they compute what they computed before it
    (`rl.absorb_normaliser_update`): the statistics then only condition the learning and never
    move the policy themselves. Without it, on RagdollStand-v0 in the test's setting, the
    statistics' updates alone moved the rollout policy by a KL of 0.009-0.028 per iteration
    (the `normaliser_kl` metric, iterations 80-200), as much as the gradient steps, after the
    training return peaked (191 at iteration 61), and the return fell to 55-75 (README:
    Reinforcement learning).
    trailing_batch: step and reset the envs under `dbd.vmap` (the batch the trailing axis of every
    intermediate: the same values up to rounding, faster on XLA:CPU for the ragdoll's physics,
    README "dbd.vmap") instead of `jax.vmap`.
    policy_average: d in [0, 1), the policy that is evaluated and exported is an exponential moving
    average of the trained one's weights, average <- d average + (1 - d) policy after every
    iteration (a memory of about 1 / (1 - d) iterations; Polyak averaging of the iterates); the
    training itself does not change (the rollouts act the trained policy). The average absorbs the
    statistics' updates as the networks do. 0: the trained policy itself.
    final_step_scale: s in (0, 1], every update of both networks (and the log std) is scaled by a
    factor falling linearly from 1 at the start of the run to s at its end (the run's fraction done
    by steps or by wall time, whichever budget is nearer its end: `rl.run`), as CleanRL anneals its
    learning rate; with the KL-adaptive rate the rule judges the KL the unscaled steps would have
    made (policy_kl / scale^2), so the rule does not raise the rate to undo the annealing (its
    bounds and target scale with it). 1: no annealing.
    """

    num_envs: int = 32
    unroll_length: int = 32
    num_minibatches: int = 4
    update_epochs: int = 4
    gamma: float = 0.97
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    value_coef: float = 0.5
    entropy_coef: float = 0.0
    learning_rate: float = 3e-5
    max_grad_norm: float = 0.5
    hidden: tuple[int, ...] = (128, 128)
    init_log_std: float = -4.6
    normalise_observations: bool = True
    reward_scale: float = 0.1
    desired_kl: float | None = 0.01
    noise_correlation: float = 0.0
    explored_actions: tuple[int, ...] | None = None
    init_log_std_of: tuple[tuple[int, float], ...] = ()
    step_scale_of: tuple[tuple[int, float], ...] = ()
    absorb_normaliser_updates: bool = True
    trailing_batch: bool = False
    policy_average: float = 0.0
    final_step_scale: float = 1.0

    @property
    def batch_size(self) -> int:
        """Transitions per iteration."""
        return self.num_envs * self.unroll_length


class TrainState(NamedTuple):
    """Everything that changes during training (a pytree; `train` returns it in Result.params form)."""

    params: dict  # {"policy": MLP, "value": MLP, "log_std": (A,)}
    opt_state: Any
    stats: rl.Normaliser
    env_state: Any  # the vmapped EnvState
    obs: jnp.ndarray  # (num_envs, obs_size)
    episode_return: jnp.ndarray  # (num_envs,) return so far of the running episodes
    episode_length: jnp.ndarray  # (num_envs,) int32
    key: jnp.ndarray
    noise: jnp.ndarray  # (num_envs, A) the exploration noise of the last action (action - mean)
    previous_obs: jnp.ndarray  # (num_envs, obs_size) the observation the last action was taken in
    previous_action: jnp.ndarray  # (num_envs, A) the last action
    continuing: jnp.ndarray  # (num_envs,) bool: the last action belongs to the running episode
    average_policy: list  # the policy MLP evaluated and exported (`PPOConfig.policy_average`)


# The TrainState fields with one row per env: split over the devices (`rl.distribute`).
BATCH_FIELDS = (*rl.ENV_FIELDS, "noise", "previous_obs", "previous_action", "continuing")


class Transition(NamedTuple):
    obs: jnp.ndarray
    action: jnp.ndarray
    shift: jnp.ndarray  # the correlated part of the noise, rho x the last noise (zeros when rho = 0)
    mean: jnp.ndarray  # the rollout policy's mean action at obs
    previous_obs: jnp.ndarray  # the observation of the episode's previous step (see `continuing`)
    previous_action: jnp.ndarray  # the action of the episode's previous step
    continuing: jnp.ndarray  # False at an episode's first step: its shift is a fresh stationary draw
    log_prob: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    next_obs: jnp.ndarray  # the observation after the action (the ended episode's last one at a reset)
    terminated: jnp.ndarray
    truncated: jnp.ndarray


Result = rl.Result


def init_params(task: DbdFuncEnv, config: PPOConfig, key: jax.Array) -> dict:
    """{"policy": MLP obs -> residual action (last layer zero: the untrained policy's mean is exactly
    the home action, whatever the observation statistics), "value": MLP obs -> (), "log_std": (A,)}."""
    policy_key, value_key = jax.random.split(key)
    sizes = (task.observation_size, *config.hidden)
    return {
        "policy": rl.init_mlp(policy_key, (*sizes, task.action_size), last_scale=0.0),
        "value": rl.init_mlp(value_key, (*sizes, 1), last_scale=1.0),
        "log_std": initial_log_std(task, config),
    }


def _checked_entries(task: DbdFuncEnv, field: str, indices) -> np.ndarray:
    """indices as an int array, or a ValueError naming `field` when one is not an action entry
    (an integer in 0..A-1: a float is not truncated, a negative index does not wrap) or repeats."""
    checked: list[int] = []
    for index in indices:
        if not isinstance(index, int | np.integer) or not 0 <= index < task.action_size:
            raise ValueError(f"PPOConfig.{field}: {index!r} is not an action entry (0..{task.action_size - 1})")
        if index in checked:
            raise ValueError(f"PPOConfig.{field}: action entry {index} is given twice")
        checked.append(int(index))
    return np.asarray(checked, np.int64)


def _per_entry(task: DbdFuncEnv, field: str, default: float, pairs) -> jnp.ndarray:
    """(A,) float32: `default` everywhere but the (index, value) pairs of PPOConfig.`field`."""
    values = np.full((task.action_size,), default, np.float32)
    if pairs:
        entries, given = zip(*pairs, strict=True)
        values[_checked_entries(task, field, entries)] = given
    return jnp.asarray(values)


def initial_log_std(task: DbdFuncEnv, config: PPOConfig) -> jnp.ndarray:
    """(A,) float32: `init_log_std` everywhere but the entries of `init_log_std_of`."""
    return _per_entry(task, "init_log_std_of", config.init_log_std, config.init_log_std_of)


def output_step_scale(task: DbdFuncEnv, config: PPOConfig) -> jnp.ndarray:
    """(A,) float32: 1 everywhere but the entries of `step_scale_of` (each scale positive)."""
    for index, scale in config.step_scale_of:
        if not (math.isfinite(scale) and scale > 0.0):  # a NaN or inf scale would make every step non-finite
            raise ValueError(f"PPOConfig.step_scale_of: entry {index}'s scale {scale!r} is not positive and finite")
    return _per_entry(task, "step_scale_of", 1.0, config.step_scale_of)


def scale_policy_output_steps(scale: jnp.ndarray) -> optax.GradientTransformation:
    """Multiplies the updates of the policy's last layer (weights (H, A) and bias (A,)) by scale (A,)
    per output entry; every other update passes unchanged."""

    def scale_updates(updates: dict, params=None) -> dict:
        last = updates["policy"][-1]
        return {**updates, "policy": [*updates["policy"][:-1], {"w": last["w"] * scale, "b": last["b"] * scale}]}

    return optax.stateless(scale_updates)


def _innovation_log_std(log_std, rho):
    """log std of the fresh part of AR(1) noise of stationary std exp(log_std): sqrt(1 - rho^2) x std."""
    return log_std + 0.5 * math.log(1.0 - rho**2)


def _gaussian_log_prob(mean, log_std, x, explored):
    """log density (...,) of x (..., A) under N(mean, exp(log_std)^2) over the explored entries
    (explored: (A,) 1.0 or 0.0; the others are deterministic and carry no probability)."""
    per_entry = -0.5 * ((x - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * math.log(2.0 * math.pi)
    return jnp.sum(explored * per_entry, axis=-1)


def explored_mask(task: DbdFuncEnv, config: PPOConfig) -> jnp.ndarray:
    """(A,) float32: 1.0 on the action entries that explore (`PPOConfig.explored_actions`), 0.0 elsewhere."""
    if config.explored_actions is None:
        return jnp.ones((task.action_size,), jnp.float32)
    entries = _checked_entries(task, "explored_actions", config.explored_actions)
    return jnp.zeros((task.action_size,), jnp.float32).at[entries].set(1.0)


def _adapt_learning_rate(opt_state, approx_kl, desired_kl):
    """rsl_rl's rule on the learning rate held in opt_state[1] (optax.inject_hyperparams(adam))."""
    adam = opt_state[1]
    rate = adam.hyperparams["learning_rate"]
    rate = jnp.where(approx_kl < 0.5 * desired_kl, rate * 1.5, rate)
    rate = jnp.where(approx_kl > 2.0 * desired_kl, adam.hyperparams["learning_rate"] / 1.5, rate)
    rate = jnp.clip(rate, 1e-5, 1e-2)
    return (opt_state[0], adam._replace(hyperparams={**adam.hyperparams, "learning_rate": rate}), *opt_state[2:])


def make_optimiser(
    config: PPOConfig, iterations: int | None, step_scale: jnp.ndarray | None = None
) -> optax.GradientTransformation:
    """Global-norm clipping then Adam: a fixed rate (linearly decayed to 10% over `iterations` when
    known) or, with `config.desired_kl`, the KL-adaptive rate (held in the optimiser state); then
    the policy output's updates scaled per entry by step_scale (A,) (`output_step_scale`) if given."""
    clip = optax.clip_by_global_norm(config.max_grad_norm)
    scaled = () if step_scale is None else (scale_policy_output_steps(step_scale),)
    if config.desired_kl is not None:
        adam = optax.inject_hyperparams(optax.adam)(learning_rate=config.learning_rate, eps=1e-5)
        return optax.chain(clip, adam, *scaled)
    rate = (
        config.learning_rate
        if iterations is None
        else optax.linear_schedule(
            config.learning_rate, 0.1 * config.learning_rate, iterations * config.update_epochs * config.num_minibatches
        )
    )
    return optax.chain(clip, optax.adam(rate, eps=1e-5), *scaled)


def policy_and_value(task: DbdFuncEnv, params: dict, stats: rl.Normaliser, obs: jnp.ndarray):
    """(the policy's mean action (..., A), the value (...,)) at observations obs (..., obs_size)."""
    x = rl.normalise(stats, obs)
    mean = rl.home_action(task) + rl.apply_mlp(params["policy"], x)
    value = rl.apply_mlp(params["value"], x)[..., 0]
    return mean, value


def step_distribution_mean(task: DbdFuncEnv, config: PPOConfig, params: dict, stats: rl.Normaliser, batch: Transition):
    """(the policy's mean at s_t, the mean of the step's action distribution) under `params`, (..., A) each.

    The step's mean is mean(s_t) + rho (a_{t-1} - mean(s_{t-1})): the last noise depends on the
    policy too, so a policy whose mean changes by d(s) draws its steps around d(s_t) - rho d(s_{t-1}).
    Holding the recorded shift fixed instead (as this trainer did before) credits mean(s_t) with
    the return of a deviation that persists for the noise's correlation time (1 / (1 - rho)
    steps). An episode's first shift is a stationary draw, not the policy's, and an unroll's first
    shift comes from the previous iteration's policy: both are taken as recorded."""
    mean, _ = policy_and_value(task, params, stats, batch.obs)
    previous_mean, _ = policy_and_value(task, params, stats, batch.previous_obs)
    own_shift = config.noise_correlation * (batch.previous_action - previous_mean)
    return mean, mean + jnp.where(batch.continuing[..., None], own_shift, batch.shift)


def make_iteration(task: DbdFuncEnv, config: PPOConfig, optimiser: optax.GradientTransformation):
    """The jitted training iteration: (TrainState, fraction of the run done, a float32 scalar in
    [0, 1]) -> (TrainState, metrics dict of scalars)."""
    if config.batch_size % config.num_minibatches:
        raise ValueError(f"num_envs x unroll_length ({config.batch_size}) must divide into {config.num_minibatches}")
    mapping = trailing_batch.vmap if config.trailing_batch else jax.vmap
    step_envs = mapping(task.step)
    reset_envs = mapping(task.reset)
    explored = explored_mask(task, config)

    networks = functools.partial(policy_and_value, task)
    step_mean = functools.partial(step_distribution_mean, task, config)

    def env_step(carry: TrainState, _):
        params, stats = carry.params, carry.stats
        key, action_key, reset_key, noise_key = jax.random.split(carry.key, 4)
        mean, value = networks(params, stats, carry.obs)
        # AR(1) exploration noise: noise_t = rho noise_{t-1} + sqrt(1 - rho^2) std xi_t (stationary
        # std exp(log_std)); the policy of the step is N(mean + rho noise_{t-1}, (sqrt(1 - rho^2) std)^2),
        # the last noise being part of the state the action is drawn in (stored as `shift`).
        rho = config.noise_correlation
        shift = rho * carry.noise
        innovation = _innovation_log_std(params["log_std"], rho)
        action = mean + shift + explored * jnp.exp(innovation) * jax.random.normal(action_key, mean.shape)
        log_prob = _gaussian_log_prob(mean + shift, innovation, action, explored)
        env_state, next_obs, reward, terminated, truncated, _ = step_envs(carry.env_state, action)
        reward = reward.astype(jnp.float32)
        done = terminated | truncated
        # Reset the ended envs in the same step, from fresh keys.
        fresh_state, fresh_obs, _ = reset_envs(jax.random.split(reset_key, config.num_envs))
        env_state = jax.tree.map(
            lambda new, old: jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old),
            fresh_state,
            env_state,
        )
        obs = jnp.where(done[:, None], fresh_obs, next_obs)
        episode_return = carry.episode_return + reward
        episode_length = carry.episode_length + 1
        ended = {
            "count": jnp.sum(done),
            "return": jnp.sum(jnp.where(done, episode_return, 0.0)),
            "length": jnp.sum(jnp.where(done, episode_length, 0)),
            "full": jnp.sum(truncated),
        }
        # A new episode draws its first noise from the stationary distribution.
        fresh_noise = explored * jnp.exp(params["log_std"]) * jax.random.normal(noise_key, mean.shape)
        new_carry = carry._replace(
            noise=jnp.where(done[:, None], fresh_noise, action - mean),
            previous_obs=carry.obs,
            previous_action=action,
            continuing=~done,
            env_state=env_state,
            obs=obs,
            episode_return=jnp.where(done, 0.0, episode_return),
            episode_length=jnp.where(done, 0, episode_length),
            key=key,
        )
        transition = Transition(obs=carry.obs, action=action, shift=shift, mean=mean, previous_obs=carry.previous_obs,
                                previous_action=carry.previous_action, continuing=carry.continuing,
                                log_prob=log_prob, value=value, reward=reward, next_obs=next_obs,
                                terminated=terminated, truncated=truncated)  # fmt: skip
        return new_carry, (transition, ended)

    def rollout(state: TrainState):
        return jax.lax.scan(env_step, state, None, length=config.unroll_length)

    def advantages(params, stats, batch: Transition):
        """GAE over the unroll (time-major (T, N)); value targets = advantages + values."""
        _, next_value = networks(params, stats, batch.next_obs)
        # Termination: no value after it; truncation: bootstrap from the last observation (next_value).
        delta = config.reward_scale * batch.reward + config.gamma * next_value * (1.0 - batch.terminated) - batch.value
        not_done = 1.0 - (batch.terminated | batch.truncated)

        def backwards(gae, x):
            delta_t, not_done_t = x
            gae = delta_t + config.gamma * config.gae_lambda * not_done_t * gae
            return gae, gae

        _, advantage = jax.lax.scan(backwards, jnp.zeros_like(delta[0]), (delta, not_done), reverse=True)
        return advantage, advantage + batch.value

    def loss_function(params, stats, minibatch, advantage, target):
        _, value = networks(params, stats, minibatch.obs)
        mean, mean_of_step = step_mean(params, stats, minibatch)
        innovation = _innovation_log_std(params["log_std"], config.noise_correlation)
        log_prob = _gaussian_log_prob(mean_of_step, innovation, minibatch.action, explored)
        ratio = jnp.exp(log_prob - minibatch.log_prob)
        normalised = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
        surrogate = jnp.minimum(
            ratio * normalised, jnp.clip(ratio, 1.0 - config.clip_epsilon, 1.0 + config.clip_epsilon) * normalised
        )
        policy_loss = -jnp.mean(surrogate)
        value_loss = 0.5 * jnp.mean((value - target) ** 2)
        entropy = jnp.sum(explored * (params["log_std"] + 0.5 * math.log(2.0 * math.pi * math.e)))
        total = policy_loss + config.value_coef * value_loss - config.entropy_coef * entropy
        approx_kl = jnp.mean((ratio - 1.0) - jnp.log(ratio))
        # The trust region the learning rate keeps (`desired_kl`) is on the policy's mean, the policy
        # the evaluation acts: the KL of N(mean(s), std^2) from the rollout's. With correlated noise
        # the step's ratio is no measure of it, as a slowly varying change d(s) of the mean moves a
        # step's distribution only by about d(s_t) - rho d(s_{t-1}). With independent noise the two
        # are the same KL, up to a change of the std, which only the ratio sees.
        change = explored * (mean - minibatch.mean) / jnp.exp(params["log_std"])
        policy_kl = jnp.mean(jnp.sum(0.5 * change**2, axis=-1))
        return total, {"policy_loss": policy_loss, "value_loss": value_loss, "approx_kl": approx_kl,
                       "policy_kl": policy_kl}  # fmt: skip

    def update_minibatch(carry, minibatch):
        params, opt_state, stats, step_scale = carry
        batch, advantage, target = minibatch
        grads, info = jax.grad(loss_function, has_aux=True)(params, stats, batch, advantage, target)
        if config.desired_kl is not None:
            # The rule judges the KL the unscaled steps would have made (a KL grows as the square of
            # a small step), so the annealing is not undone by the rule raising the rate.
            opt_state = _adapt_learning_rate(opt_state, info["policy_kl"] / step_scale**2, config.desired_kl)
            info["learning_rate"] = step_scale * opt_state[1].hyperparams["learning_rate"]
        updates, opt_state = optimiser.update(grads, opt_state, params)
        params = optax.apply_updates(params, jax.tree.map(lambda update: step_scale * update, updates))
        info["grad_norm"] = optax.global_norm(grads)
        return (params, opt_state, stats, step_scale), info

    def update_epoch(carry, key):
        params, opt_state, stats, step_scale, data = carry
        permutation = jax.random.permutation(key, config.batch_size)
        shuffled = jax.tree.map(lambda x: x[permutation].reshape((config.num_minibatches, -1) + x.shape[1:]), data)
        (params, opt_state, stats, step_scale), info = jax.lax.scan(
            update_minibatch, (params, opt_state, stats, step_scale), shuffled
        )
        return (params, opt_state, stats, step_scale, data), info

    @jit
    def iteration(state: TrainState, fraction_done: jnp.ndarray):
        # An unroll's first step keeps the noise it is drawn with as recorded (`continuing` False):
        # the last iteration's policy made that noise, so recomputing it from the current policy's
        # mean would give a step this rollout did not take (a likelihood ratio off 1 before any update).
        state, (batch, ended) = rollout(state._replace(continuing=jnp.zeros_like(state.continuing)))
        # The statistics are updated before the updates (as Brax's PPO does): the networks are
        # fitted on the normalisation the next rollout will act with.
        stats = rl.update_normaliser(state.stats, batch.obs) if config.normalise_observations else state.stats
        advantage, target = advantages(state.params, state.stats, batch)
        params, average_policy = state.params, state.average_policy
        if config.absorb_normaliser_updates:
            params = {**params, "policy": rl.absorb_normaliser_update(params["policy"], state.stats, stats),
                      "value": rl.absorb_normaliser_update(params["value"], state.stats, stats)}  # fmt: skip
            average_policy = rl.absorb_normaliser_update(average_policy, state.stats, stats)
        # How far the new statistics alone move the rollout policy (its KL, before any update): with
        # a small exploration std a small shift of the normalisation is a large change of the policy.
        # Measured as `policy_kl` is (at the stationary std; until session 17 at the innovation std,
        # which made it 1 / (1 - rho^2) larger: 5.3x at rho 0.9, the setting of the README's figures).
        mean_before, _ = networks(state.params, state.stats, batch.obs)
        mean_after, _ = networks(params, stats, batch.obs)
        change = explored * (mean_after - mean_before) / jnp.exp(state.params["log_std"])
        normaliser_kl = jnp.mean(jnp.sum(0.5 * change**2, axis=-1))
        flat = jax.tree.map(lambda x: x.reshape((config.batch_size,) + x.shape[2:]), (batch, advantage, target))
        key, epoch_key = jax.random.split(state.key)
        # `final_step_scale`: every update scaled by a factor falling linearly from 1 over the run.
        step_scale = 1.0 - (1.0 - config.final_step_scale) * fraction_done
        (params, opt_state, _, _, _), info = jax.lax.scan(
            update_epoch,
            (params, state.opt_state, stats, step_scale, flat),
            jax.random.split(epoch_key, config.update_epochs),
        )
        if config.policy_average:
            weight = config.policy_average
            average_policy = jax.tree.map(lambda old, new: weight * old + (1.0 - weight) * new,
                                          average_policy, params["policy"])  # fmt: skip
        else:
            average_policy = params["policy"]
        ended = jax.tree.map(jnp.sum, ended)
        count = jnp.maximum(ended["count"], 1)
        metrics = {
            "episodes": ended["count"],
            "episode_return": jnp.where(ended["count"] > 0, ended["return"] / count, jnp.nan),
            "episode_length": jnp.where(ended["count"] > 0, ended["length"] / count, jnp.nan),
            "full_episodes": jnp.where(ended["count"] > 0, ended["full"] / count, jnp.nan),
            "reward_per_step": jnp.mean(batch.reward),
            "std": jnp.sum(explored * jnp.exp(params["log_std"])) / jnp.sum(explored),
            "normaliser_kl": normaliser_kl,
            "step_scale": step_scale,
            **{name: jnp.mean(value) for name, value in info.items()},
        }
        state = state._replace(params=params, opt_state=opt_state, stats=stats, key=key, average_policy=average_policy)
        return state, metrics

    return iteration


def export_params(state: TrainState) -> dict:
    """The parameters a checkpoint holds (numpy): networks (the policy's the average of
    `PPOConfig.policy_average`, the trained one itself by default), log std and observation
    statistics."""
    params = jax.tree.map(np.asarray, {**state.params, "policy": state.average_policy})
    return dict(params, obs_mean=np.asarray(state.stats.mean), obs_var=np.asarray(state.stats.var),
                obs_count=np.asarray(state.stats.count))  # fmt: skip


act = rl.act  # the deterministic policy of exported (or loaded) params


def init_state(task: DbdFuncEnv, config: PPOConfig, optimiser: optax.GradientTransformation, seed: int) -> TrainState:
    """The state before the first iteration: fresh networks, `num_envs` envs reset, each with a
    stationary draw of the exploration noise."""
    key = jax.random.PRNGKey(seed)
    key, init_key, env_key, noise_key = jax.random.split(key, 4)
    params = init_params(task, config, init_key)
    envs = rl.fresh_envs(task, config.num_envs, env_key)
    noise = (
        explored_mask(task, config)
        * jnp.exp(params["log_std"])
        * jax.random.normal(noise_key, (config.num_envs, task.action_size))
    )
    return TrainState(
        params=params,
        opt_state=optimiser.init(params),
        key=key,
        noise=noise,
        previous_obs=envs["obs"],
        previous_action=jnp.broadcast_to(rl.home_action(task), noise.shape),
        **envs,
        continuing=jnp.zeros((config.num_envs,), bool),
        average_policy=params["policy"],
    )


def train(
    task: DbdFuncEnv,
    config: PPOConfig = PPOConfig(),
    total_steps: int | None = None,
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
    """Train a PPO policy on `task` (its max_episode_steps is the time limit; it must have one).

    Stops after `total_steps` env steps (rounded up to whole iterations) or once `time_budget_s`
    wall-clock seconds (compilation included, evaluations not) have passed, whichever comes first;
    at least one must be given. eval_every: run a deterministic evaluation of `eval_episodes`
    episodes every that many iterations (0: only at the end). evaluate_initial: also evaluate the
    untrained policy first (Result.initial_evaluation). devices: the envs split over the most of
    these (default: every local device) that divides num_envs (`rl.env_devices`). keep_best: return
    the policy that did best on validation episodes (`rl.run`). eval_task: the env every evaluation
    runs (default `task`, as Brax's `eval_env`; `rl.run`). Returns a `Result`.
    """
    if total_steps is None and time_budget_s is None:
        raise ValueError("train: give total_steps or time_budget_s")
    if task.max_episode_steps is None:
        raise ValueError("train: the task needs max_episode_steps (the time limit PPO bootstraps at)")
    iterations = None if total_steps is None else max(1, -(-total_steps // config.batch_size))
    optimiser = make_optimiser(config, iterations, output_step_scale(task, config) if config.step_scale_of else None)
    clock = rl.Clock()
    if not 0.0 <= config.noise_correlation < 1.0:
        raise ValueError(f"train: noise_correlation must be in [0, 1), got {config.noise_correlation!r}")
    if not 0.0 < config.final_step_scale <= 1.0:
        raise ValueError(f"train: final_step_scale must be in (0, 1], got {config.final_step_scale!r}")
    if not 0.0 <= config.policy_average < 1.0:
        raise ValueError(f"train: policy_average must be in [0, 1), got {config.policy_average!r}")
    devices = rl.env_devices(config.num_envs, devices)
    state = rl.distribute(init_state(task, config, optimiser, seed), BATCH_FIELDS, devices)

    def failure(row: dict) -> str | None:
        finite = all(math.isfinite(row[name]) for name in ("policy_loss", "value_loss", "std"))
        return None if finite else "a loss went non-finite"

    result = rl.run(
        "ppo", task, make_iteration(task, config, optimiser), state, export_params, clock,
        steps_per_iteration=config.batch_size, iterations=iterations, time_budget_s=time_budget_s, seed=seed,
        eval_every=eval_every, eval_episodes=eval_episodes, evaluate_initial=evaluate_initial, progress=progress,
        bar_metric="episode_return", line=_line, failure=failure, keep_best=keep_best,
        eval_task=eval_task,
        summary={"algorithm": "ppo", "config": dataclasses.asdict(config), "devices": len(devices)},
    )  # fmt: skip
    result.summary["iterations"] = len(result.history)
    return result


def _line(row: dict) -> str:
    return (f"it {row['iteration']:5d} steps {row['env_steps']:8d} wall {row['wall_s']:7.1f}s "
            f"return {row['episode_return']:7.2f} length {row['episode_length']:6.1f} "
            f"full {row['full_episodes']:.2f} std {row['std']:.3f} kl {row['approx_kl']:.4f}")  # fmt: skip


def load(path: str | Path) -> tuple[dict, dict]:
    """(params, metadata) of a checkpoint written by the CLI/`rl.save_result` (no pickle)."""
    from . import checkpoint

    return checkpoint.load(path)


def _entry_value(text: str) -> tuple[int, float]:
    """'17=-6.2' -> (17, -6.2), for argparse."""
    index, _, value = text.partition("=")
    try:
        return int(index), float(value)
    except ValueError:  # also a missing "=" (value "")
        raise argparse.ArgumentTypeError(f"expected INDEX=VALUE (an int and a float), got {text!r}") from None


def main(argv: list[str] | None = None) -> Result:
    defaults = PPOConfig()
    parser = argparse.ArgumentParser(
        prog="python -m dbdjax.training.ppo",
        description="Train a PPO policy on a dbdjax env (JAX-native vector env, jitted iterations). Writes "
        "<out>/<name>.npz (checkpoint, no pickle), <name>.json (settings, timings, per-iteration metrics) and "
        "<name>.png (return and episode-length curves).",
    )
    rl.add_common_arguments(parser, "ppo", defaults.num_envs, defaults.learning_rate, defaults.hidden)
    parser.add_argument("--steps", type=int, default=None, help="env steps to train for (default: until --minutes)")
    parser.add_argument("--unroll", type=int, default=defaults.unroll_length, help="steps per env per iteration")
    parser.add_argument("--minibatches", type=int, default=defaults.num_minibatches)
    parser.add_argument("--epochs", type=int, default=defaults.update_epochs)
    parser.add_argument("--gamma", type=float, default=defaults.gamma)
    parser.add_argument("--gae-lambda", type=float, default=defaults.gae_lambda, help="GAE's lambda")
    parser.add_argument("--entropy", type=float, default=defaults.entropy_coef)
    parser.add_argument("--init-log-std", type=float, default=defaults.init_log_std)
    parser.add_argument(
        "--init-log-std-of", nargs="+", default=[], metavar="INDEX=LOG_STD", type=_entry_value,
        help="action entries whose initial log std is not --init-log-std, e.g. 17=-6.2 22=-6.2",
    )  # fmt: skip
    parser.add_argument(
        "--step-scale-of", nargs="+", default=[], metavar="INDEX=SCALE", type=_entry_value,
        help="action entries whose mean learns at SCALE times the others' step, e.g. 17=0.2 22=0.2",
    )  # fmt: skip
    parser.add_argument("--reward-scale", type=float, default=defaults.reward_scale)
    parser.add_argument(
        "--noise-correlation", type=float, default=defaults.noise_correlation,
        help="rho of the AR(1) exploration noise in time (0: independent per step)",
    )  # fmt: skip
    parser.add_argument(
        "--explored-actions", type=int, nargs="+", default=None,
        help="indices of the action entries that explore (default: all; the others act their mean)",
    )  # fmt: skip
    parser.add_argument(
        "--desired-kl",
        type=float,
        default=defaults.desired_kl,
        help=f"the KL-adaptive learning rate's target KL from the rollout policy (rsl_rl's rule; default "
        f"{defaults.desired_kl})",
    )
    parser.add_argument("--no-normalise", action="store_true", help="feed the networks the raw observations")
    parser.add_argument(
        "--trailing-batch", action="store_true",
        help="step the envs under dbd.vmap, the batch the trailing axis (PPOConfig.trailing_batch)",
    )  # fmt: skip
    parser.add_argument(
        "--no-absorb-normaliser", action="store_true",
        help="let each update of the observation statistics move the policy (PPOConfig.absorb_normaliser_updates)",
    )  # fmt: skip
    parser.add_argument(
        "--policy-average", type=float, default=defaults.policy_average,
        help="evaluate and keep a moving average of the policy's weights, this much of the old one kept "
        "each iteration (PPOConfig.policy_average; 0: the trained policy)",
    )  # fmt: skip
    parser.add_argument(
        "--final-step-scale", type=float, default=defaults.final_step_scale,
        help="anneal every update by a factor falling linearly from 1 to this over the run "
        "(PPOConfig.final_step_scale; 1: no annealing)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.steps is None and args.minutes is None:
        parser.error("give --steps or --minutes")
    rl.use_cpu_devices(args.cpu_devices)  # before JAX computes anything
    config = PPOConfig(num_envs=args.num_envs, unroll_length=args.unroll, num_minibatches=args.minibatches,
                       update_epochs=args.epochs, learning_rate=args.lr, gamma=args.gamma,
                       gae_lambda=args.gae_lambda, entropy_coef=args.entropy,
                       init_log_std=args.init_log_std, init_log_std_of=tuple(args.init_log_std_of),
                       step_scale_of=tuple(args.step_scale_of),
                       reward_scale=args.reward_scale,
                       desired_kl=args.desired_kl, noise_correlation=args.noise_correlation,
                       explored_actions=None if args.explored_actions is None else tuple(args.explored_actions),
                       normalise_observations=not args.no_normalise,
                       absorb_normaliser_updates=not args.no_absorb_normaliser, hidden=tuple(args.hidden),
                       trailing_batch=args.trailing_batch, policy_average=args.policy_average,
                       final_step_scale=args.final_step_scale)  # fmt: skip
    budget = None if args.minutes is None else 60.0 * args.minutes
    task, eval_task = rl.tasks_of(args)
    result = train(task, config, total_steps=args.steps, time_budget_s=budget, seed=args.seed,
                   eval_every=args.eval_every, eval_episodes=args.eval_episodes, evaluate_initial=True,
                   progress=not args.no_progress, keep_best=args.keep_best, eval_task=eval_task)  # fmt: skip
    rl.finish(args, "ppo", result, "")
    return result


if __name__ == "__main__":
    main()
