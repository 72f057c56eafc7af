"""dbdjax tasks as `brax.envs.Env` objects, so Brax's trainers (ppo, sac, apg) run on them.

    from brax.training.agents.ppo import train as ppo
    from dbdjax.envs.brax_adapter import make_brax_env

    env = make_brax_env("dbdjax/IKChainReach-v0")
    make_policy, params, metrics = ppo.train(env, num_timesteps=..., episode_length=100, ...)

`BraxEnv.reset(rng)` and `BraxEnv.step(state, action)` are the task's pure `reset`/`step`;
the Brax `State` carries the task's `EnvState` as `pipeline_state`, the observation, the reward
(float32), `done` (1.0 when the task terminates: a fall, a non-finite action or physics state)
and, in `metrics`, every scalar entry of the Gymnasium info as float32 (reward terms, flags,
"is_success", ...), which Brax's EpisodeWrapper sums per episode (vector entries, such as the
ragdoll's "push", are left out: Brax's wrappers keep one number per env and metric); metric
keys that Brax's wrappers add (EvalWrapper's "reward") are kept from step to step. The task is built with
`max_episode_steps=None`: Brax's own EpisodeWrapper (`episode_length`) truncates and sets
info["truncation"], which its trainers use to bootstrap at time limits.

Brax's AutoResetWrapper restarts a finished episode from the first state of that env slot (its
stored `first_pipeline_state`), not from a fresh random reset: under Brax's trainers every slot
replays the start (and goal) it was first given. That is Brax's convention; the Gymnasium vector
env draws a new episode at each autoreset.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State

from dbdjax.envs.core import DbdFuncEnv


class BraxEnv(Env):
    """A `DbdFuncEnv` task behind Brax's `Env` interface (see the module docstring).

    func_env: the task, with max_episode_steps=None (Brax's EpisodeWrapper truncates).
    """

    def __init__(self, func_env: DbdFuncEnv):
        if func_env.max_episode_steps is not None:
            raise ValueError(
                "BraxEnv: build the task with max_episode_steps=None; Brax's EpisodeWrapper "
                f"(episode_length) truncates, got max_episode_steps={func_env.max_episode_steps}"
            )
        self.func_env = func_env

    def reset(self, rng: jax.Array) -> State:
        """rng: (2,) uint32 PRNG key (as Brax's VmapWrapper passes one per env)."""
        task_state, obs, info = self.func_env.reset(rng)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=task_state, obs=obs, reward=zero, done=zero, metrics=_metrics(info), info={})

    def step(self, state: State, action: jax.Array) -> State:
        """action: (action_size,) in [-1, 1] (clipped; NaN/inf entries end the episode)."""
        task_state, obs, reward, terminated, _, info = self.func_env.step(state.pipeline_state, action)
        return state.replace(
            pipeline_state=task_state,
            obs=obs,
            reward=jnp.asarray(reward, jnp.float32),
            done=jnp.asarray(terminated, jnp.float32),
            # Keep metrics that wrappers added (Brax's EvalWrapper puts "reward" there at reset and
            # its EpisodeWrapper's action-repeat scan needs the same keys in and out).
            metrics={**state.metrics, **_metrics(info)},
        )

    @property
    def observation_size(self) -> int:
        return self.func_env.observation_size

    @property
    def action_size(self) -> int:
        return self.func_env.action_size

    @property
    def backend(self) -> str:
        return "dbdjax"

    @property
    def dt(self) -> float:
        """Seconds per env step."""
        return self.func_env.dt


def _metrics(info: dict[str, Any]) -> dict[str, jnp.ndarray]:
    # Scalars only: Brax's EpisodeWrapper and EvalWrapper keep one number per env per metric
    # (a (3,) entry such as the ragdoll's "push" fails their broadcast against (num_envs,)).
    return {name: jnp.asarray(value, jnp.float32) for name, value in info.items() if jnp.ndim(value) == 0}


def make_brax_env(env_id: str, **kwargs) -> BraxEnv:
    """The Brax env of a registered id ("dbdjax/IKChainReach-v0", ...); kwargs go to the task."""
    from dbdjax.envs import TASKS  # noqa: PLC0415 (the registry imports this module's siblings)

    if env_id not in TASKS:
        raise ValueError(f"make_brax_env: unknown env id {env_id!r}; known: {sorted(TASKS)}")
    if kwargs.get("max_episode_steps") is not None:
        raise ValueError("make_brax_env: max_episode_steps is Brax's episode_length here (its EpisodeWrapper)")
    kwargs["max_episode_steps"] = None
    return BraxEnv(TASKS[env_id](**kwargs))


def restore_device_put_replicated() -> bool:
    """Give `jax` back `device_put_replicated` where it was removed (JAX 0.10) and Brax's trainers
    still call it (brax 0.14.2: ppo/sac/apg `train`, `brax.training.pmap`). Returns True when it
    installed the function, False when jax already has one.

    The replacement is the drop-in of https://docs.jax.dev/en/latest/migrate_pmap.html: the value
    stacked once per device along a new leading axis, sharded over those devices. Call it once
    before `brax.training.agents.*.train`; it changes the `jax` module for the whole process.
    """
    try:
        jax.device_put_replicated  # noqa: B018 (the attribute access is the test)
        return False
    except AttributeError:
        pass

    def device_put_replicated(x: Any, devices: list) -> Any:
        mesh = jax.sharding.Mesh(np.asarray(devices), ("devices",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("devices"))
        return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)

    jax.device_put_replicated = device_put_replicated
    return True
