"""Gymnasium faces of a `DbdFuncEnv`: one environment, and a JAX-native vector of them.

`DbdEnv` (a `gymnasium.Env`) runs one episode with one jitted call per step. Observations and
info values are JAX arrays (metadata "jax": True, as Gymnasium's own functional JAX envs); reward,
terminated and truncated are Python float/bool (one device-to-host read per step, which a loop
of `if terminated:` needs anyway). `gymnasium.wrappers.JaxToNumpy(env)` gives numpy
observations; `gymnasium.utils.env_checker.check_env` applies it itself.

`DbdVectorEnv` (a `gymnasium.vector.VectorEnv`) steps all `num_envs` copies in one jitted call
(vmap of the core's step, autoreset inside the same program) and returns JAX arrays that stay on
the device: nothing is read back to the host per step. `gymnasium.wrappers.vector.JaxToNumpy`
serves numpy users. Autoreset follows https://farama.org/Vector-Autoreset-Mode, chosen with
`autoreset_mode` and declared in `metadata["autoreset_mode"]`:

- NEXT_STEP (default, Gymnasium's default and the mode its vector observation wrappers accept):
  the step that ends an episode returns its last observation; the next call resets that copy,
  ignores its action and returns the first observation with reward 0, terminated and truncated
  False.
- SAME_STEP: the step that ends an episode resets the copy at once and returns the first
  observation of the new episode (and its reset info); the last observation and info of the
  ended episode are in info["final_obs"] (num_envs, obs) and info["final_info"], valid where
  info["_final_obs"] / info["_final_info"] (dense arrays with a mask, the JAX-native form of
  Gymnasium's object arrays).
- DISABLED: no autoreset; reset copies with `reset(options={"reset_mask": mask})`.

info is a dict of (num_envs,) arrays with the same keys at every step (no "_key" masks: every copy
has every key). Seeding: `reset(seed=s)` gives copy i the key split(PRNGKey(s), num_envs + 1)[i + 1]
(a list of num_envs seeds gives copy i PRNGKey(seeds[i])); later unseeded resets continue the
chain, and a copy's autoreset draws its next episode from its own key, so the same seed gives the
same trajectories for the same actions.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from dbdjax.compiling import merged_options
from dbdjax.envs.core import DbdFuncEnv, EnvState, seed_key

RENDER_MODES = ["rgb_array"]
# fold_in stream of the key an autoreset draws a copy's next episode from.
_RESET_STREAM = 0x5E5E7


def _batched_reset(func_env: DbdFuncEnv, keys: jnp.ndarray):
    return jax.vmap(func_env.reset)(keys)


def _masked_reset(func_env: DbdFuncEnv, state: EnvState, keys: jnp.ndarray, mask: jnp.ndarray):
    fresh, _, _ = jax.vmap(func_env.reset)(keys)
    state = _select(mask, fresh, state)
    return state, jax.vmap(func_env.observation)(state), jax.vmap(func_env.state_info)(state)


def _batched_step(
    func_env: DbdFuncEnv, mode: AutoresetMode, state: EnvState, autoreset: jnp.ndarray, actions: jnp.ndarray
):
    """vmap of func_env.step with the autoreset of `mode`; returns (state, autoreset, obs, reward,
    terminated, truncated, info)."""
    stepped, obs, reward, terminated, truncated, info = jax.vmap(func_env.step)(state, actions)
    if mode == AutoresetMode.DISABLED:
        return stepped, autoreset, obs, reward, terminated, truncated, info

    if mode == AutoresetMode.NEXT_STEP:
        # Copies whose episode ended on the previous call start a new one from their own key.
        keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(state.key, _RESET_STREAM)
        fresh, fresh_obs, fresh_info = jax.vmap(func_env.reset)(keys)
        state = _select(autoreset, fresh, stepped)
        obs = _select(autoreset, fresh_obs, obs)
        reward = jnp.where(autoreset, jnp.zeros_like(reward), reward)
        terminated = terminated & ~autoreset
        truncated = truncated & ~autoreset
        info = _select(autoreset, fresh_info, info)
        return state, terminated | truncated, obs, reward, terminated, truncated, info

    # SAME_STEP: copies whose episode ends now start a new one in this call.
    done = terminated | truncated
    keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(stepped.key, _RESET_STREAM)
    fresh, fresh_obs, fresh_info = jax.vmap(func_env.reset)(keys)
    state = _select(done, fresh, stepped)
    out_info = _select(done, fresh_info, info)
    out_info.update(final_obs=obs, _final_obs=done, final_info=info, _final_info=done)
    return state, autoreset, _select(done, fresh_obs, obs), reward, terminated, truncated, out_info


def _single_reset(func_env: DbdFuncEnv, key: jnp.ndarray):
    return func_env.reset(key)


def _single_step(func_env: DbdFuncEnv, state: EnvState, action: jnp.ndarray):
    return func_env.step(state, action)


@functools.cache
def _jitted(function: Callable, static: int, options: tuple) -> Callable:
    """jax.jit of a module function whose first `static` arguments are static (the task, the
    autoreset mode). Tasks of equal config hash alike, so every env of one config shares one
    compilation; `options` are XLA compiler options as sorted (name, value) pairs."""
    return jax.jit(function, static_argnums=tuple(range(static)), compiler_options=dict(options) or None)


def _options(jit_options: dict | None) -> tuple:
    """dbdjax's compiler options (`dbdjax.compiler_options`) with the caller's over them."""
    return tuple(sorted((merged_options(jit_options) or {}).items()))


def render_frame(func_env: DbdFuncEnv, state: EnvState, **kwargs) -> np.ndarray:
    """(H, W, 3) uint8 picture of one env state, drawn by `dbdjax.render`.

    Raises NotImplementedError while `dbdjax.render` is not available in this checkout.
    """
    try:
        from dbdjax import render  # noqa: PLC0415 (optional module)
    except ImportError as error:
        raise NotImplementedError(
            "render_mode='rgb_array' draws with dbdjax.render, which this installation does not have yet"
        ) from error
    model, physics, options = func_env.render_scene(state)
    frame = render.render(model, physics, **{**options, **kwargs})
    return np.asarray(frame, dtype=np.uint8)


def _check_render_mode(render_mode: str | None) -> None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")


def _initial_key(np_random: np.random.Generator) -> jnp.ndarray:
    return seed_key(int(np_random.integers(0, 2**31 - 1)))


class DbdEnv(gym.Env):
    """One environment of a `DbdFuncEnv` task (see the module docstring for the conventions).

    func_env: the task. render_mode: None or "rgb_array". jit_options: XLA compiler options for
    the jitted reset/step, applied over `dbdjax.compiler_options()` (a value of None drops one of
    those; e.g. {"xla_backend_optimization_level": 0} compiles faster, runs slower).
    `state` is the current `EnvState` (None before the first reset).
    """

    metadata = {"render_modes": RENDER_MODES, "render_fps": 30, "jax": True}

    def __init__(self, func_env: DbdFuncEnv, render_mode: str | None = None, jit_options: dict | None = None):
        _check_render_mode(render_mode)
        self.func_env = func_env
        self.observation_space = func_env.observation_space
        self.action_space = func_env.action_space
        self.metadata = {**type(self).metadata, "render_fps": func_env.render_fps}
        self.render_mode = render_mode
        self.state: EnvState | None = None
        self._key: jnp.ndarray | None = None
        options = _options(jit_options)
        self._reset = functools.partial(_jitted(_single_reset, 1, options), func_env)
        self._step = functools.partial(_jitted(_single_step, 1, options), func_env)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode. seed: int -> PRNGKey(seed) (deterministic); None continues the key
        chain (drawn from Gymnasium's np_random on the first reset). Returns (obs, info)."""
        super().reset(seed=seed)
        if seed is not None:
            self._key = seed_key(seed)
        elif self._key is None:
            self._key = _initial_key(self.np_random)
        self._key, key = jax.random.split(self._key)
        self.state, observation, info = self._reset(key)
        return observation, info

    def step(self, action: Any):
        """(obs, reward float, terminated bool, truncated bool, info). action: (action_size,) in
        [-1, 1], clipped; NaN/inf entries end the episode (info["nonfinite_action"]); any other
        shape raises ValueError."""
        if self.state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        action = jnp.asarray(action, dtype=jnp.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{type(self).__name__}: action must have shape {self.action_space.shape} = action_space.shape, "
                f"got {action.shape}"
            )
        self.state, observation, reward, terminated, truncated, info = self._step(self.state, action)
        return observation, float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        if self.state is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        return render_frame(self.func_env, self.state)


class DbdVectorEnv(gym.vector.VectorEnv):
    """`num_envs` copies of a `DbdFuncEnv` task stepped together in one jitted call.

    func_env: the task. num_envs: copies. autoreset_mode: an `AutoresetMode` (or its value
    string), NEXT_STEP by default. render_mode: None or "rgb_array" (render() returns one frame
    per copy). jit_options: XLA compiler options (see DbdEnv). `state` is the batched `EnvState`
    (leading axis num_envs).
    """

    metadata = {"render_modes": RENDER_MODES, "render_fps": 30, "jax": True, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        func_env: DbdFuncEnv,
        num_envs: int,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
        jit_options: dict | None = None,
    ):
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        _check_render_mode(render_mode)
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        self.func_env = func_env
        self.num_envs = int(num_envs)
        self.single_observation_space = func_env.observation_space
        self.single_action_space = func_env.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.metadata = {
            **type(self).metadata,
            "render_fps": func_env.render_fps,
            "autoreset_mode": self.autoreset_mode,
        }
        self.render_mode = render_mode
        self.state: EnvState | None = None
        self._autoreset = jnp.zeros((self.num_envs,), dtype=bool)
        self._key: jnp.ndarray | None = None
        options = _options(jit_options)
        self._reset_all = functools.partial(_jitted(_batched_reset, 1, options), func_env)
        self._reset_some = functools.partial(_jitted(_masked_reset, 1, options), func_env)
        self._step = functools.partial(_jitted(_batched_step, 2, options), func_env, self.autoreset_mode)

    # ------------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict | None = None):
        """Reset every copy, or those in options["reset_mask"] ((num_envs,) bool).

        seed: int (copy i gets split(PRNGKey(seed), num_envs + 1)[i + 1]), a sequence of num_envs
        ints (copy i gets PRNGKey(seed[i])), or None (continue the key chain).
        Returns (obs (num_envs, obs_size), info dict of (num_envs,) arrays).
        """
        if seed is None or isinstance(seed, (int, np.integer)):
            super().reset(seed=None if seed is None else int(seed))
            if seed is not None:
                self._key = seed_key(seed)
            elif self._key is None:
                self._key = _initial_key(self.np_random)
            keys = jax.random.split(self._key, self.num_envs + 1)
            self._key, keys = keys[0], keys[1:]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"reset: a list of seeds needs one per copy ({self.num_envs}), got {len(seeds)}")
            super().reset(seed=int(seeds[0]))
            keys = jnp.stack([seed_key(s) for s in seeds])
            self._key = jax.random.fold_in(keys[0], self.num_envs)

        mask = None if options is None else options.get("reset_mask")
        if mask is None:
            self.state, obs, info = self._reset_all(keys)
            self._autoreset = jnp.zeros((self.num_envs,), dtype=bool)
            return obs, info
        if self.state is None:
            raise gym.error.ResetNeeded("reset(options={'reset_mask': ...}) needs a full reset() first")
        mask = jnp.asarray(mask)
        if mask.shape != (self.num_envs,) or mask.dtype != jnp.bool_:
            raise ValueError(f"reset_mask must be a ({self.num_envs},) bool array, got {mask.shape} {mask.dtype}")
        self.state, obs, info = self._reset_some(self.state, keys, mask)
        self._autoreset = self._autoreset & ~mask
        return obs, info

    def step(self, actions: Any):
        """Step every copy: (obs, reward, terminated, truncated, info), JAX arrays on the device.

        actions: (num_envs, action_size) in [-1, 1] (clipped; NaN/inf entries end that copy's
        episode with info["nonfinite_action"]); another shape raises ValueError.
        """
        if self.state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        actions = jnp.asarray(actions, dtype=jnp.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(
                f"{type(self).__name__}: actions must have shape {self.action_space.shape} = (num_envs, action_size), "
                f"got {actions.shape}"
            )
        self.state, self._autoreset, obs, reward, terminated, truncated, info = self._step(
            self.state, self._autoreset, actions
        )
        return obs, reward, terminated, truncated, info

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode != "rgb_array":
            return None
        if self.state is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        return tuple(
            render_frame(self.func_env, jax.tree.map(lambda x, i=i: x[i], self.state)) for i in range(self.num_envs)
        )


def _select(mask: jnp.ndarray, on_true: Any, on_false: Any) -> Any:
    """Per copy (leading axis), the leaves of on_true where mask else those of on_false."""

    def pick(a, b):
        return jnp.where(jnp.reshape(mask, mask.shape + (1,) * (a.ndim - 1)), a, b)

    return jax.tree.map(pick, on_true, on_false)
