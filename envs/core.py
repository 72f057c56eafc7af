"""The functional core every dbdjax environment shares: a pure reset/step pair.

A task subclasses `DbdFuncEnv` (a `gymnasium.experimental.functional.FuncEnv`) and supplies a
Model, how an episode starts, what the agent sees, the reward and when it fails. Everything else
is here, written once:

    reset(key)           -> (EnvState, obs, info)
    step(state, action)  -> (EnvState, obs, reward, terminated, truncated, info)

Both are pure functions of arrays (the Model is closed over): they jit, vmap over any batch of
states and keys, and differentiate: `jax.grad` of a sum of rewards over a rollout with respect to
the actions goes through `dbd.step` (the engine is differentiable with respect to its controls).
The FuncEnv methods (`initial`, `transition`, `observation`, `reward`, `terminal`, `state_info`,
`transition_info`) are the same computation split the way Gymnasium's functional API wants, with
its signatures (Gymnasium's own `FunctionalJaxEnv` adapter is not exercised by the tests); the
wrappers in `dbdjax.envs.wrappers` use the fused `reset`/`step` (one jitted call per step).

Conventions every task follows:

- Actions are drive targets scaled to [-1, 1] (`action_space` is Box(-1, 1)), centred on the
  task's *home* targets (`control_home`; default the middle of each control's range, a legged
  robot's default pose for the ragdoll): target = clip(home + scale x action, low, high) with
  scale = max(high - home, home - low) per control (`control_scale`), the convention of
  legged-robot RL (legged_gym: default pose + scale x action). Action 0 holds the home targets;
  one slope per control (no kink at home) that reaches the farther end of the range at +-1 and
  the nearer end before it (held beyond): every target in the range is reachable. With the
  default home this is the plain linear map, -1 the low end, +1 the high end. Entries outside
  [-1, 1] are clipped (the clip passes no gradient outside the box). A non-finite entry (NaN,
  inf) is replaced by 0 (the home target) for the physics step, and the episode terminates with
  `info["nonfinite_action"]`.
- If the physics state goes non-finite, the last finite physics state is kept (so observations
  stay finite), the episode terminates and `info["nonfinite_state"]` is set.
- A wrong action shape raises ValueError (shapes are static, so this also holds under jit).
- Randomness (start poses, goals, pushes) comes only from `EnvState.key`, split at every step:
  the same key gives the same trajectory for the same actions.
- `truncated` is `step >= max_episode_steps` (None: never; the Gymnasium single env leaves it to
  `gymnasium.make`'s TimeLimit, the Brax adapter to Brax's EpisodeWrapper); a step that
  terminates is not also truncated.
- info always has the same keys (reset included, reward terms zero there): "nonfinite_action",
  "nonfinite_state", "reward_<term>" for every reward term, and the task's own keys.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.experimental.functional import FuncEnv

import dbdjax as dbd
from dbdjax import math
from dbdjax.model import Model, State


@dataclasses.dataclass(frozen=True)
class EnvState:
    """Everything an episode is, as a pytree of arrays (leading axes are batch axes).

    physics: the engine `State` (pos, quat, vel, ang_vel of every body).
    task: the task's own variables (goal, reference phase, previous action, ...), a pytree.
    step: () int32, env steps since reset.
    key: (2,) uint32 PRNG key, the source of every random number of the episode.
    nonfinite_action: () bool, the action that led here had a NaN or inf entry.
    nonfinite_state: () bool, the physics went non-finite on the step that led here (the physics
      kept is the last finite one).
    """

    physics: State
    task: Any
    step: jnp.ndarray
    key: jnp.ndarray
    nonfinite_action: jnp.ndarray
    nonfinite_state: jnp.ndarray


EnvState = jax.tree_util.register_dataclass(
    EnvState,
    data_fields=["physics", "task", "step", "key", "nonfinite_action", "nonfinite_state"],
    meta_fields=[],
)


def seed_key(seed: int) -> jnp.ndarray:
    """The PRNG key of an integer seed: `jax.random.PRNGKey(seed)`, (2,) uint32 (a raw key, as
    Brax and gymnax use, so it vmaps and crosses jit boundaries as a plain array)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return jax.random.PRNGKey(int(seed))


class DbdFuncEnv(FuncEnv):
    """Base class of dbdjax tasks; subclasses implement the `task_*` hooks below.

    model: the engine Model the task simulates.
    control_low, control_high: (num_controls,) the drive-target range actions map onto.
    control_home: (num_controls,) the targets of action 0, within [low, high] (None: the middle
      of each range, so that -1 -> low and +1 -> high); see the module docstring for the map.
    frame_skip: physics steps (of model.dt) per env step, all with the same control.
    max_episode_steps: truncation (None: never).
    config: the task's constructor arguments (hashable values). Two tasks of one class with equal
      configs compare equal and hash alike, so the wrappers' jitted functions (which take the
      task as a static argument) compile once for both; None: identity.
    """

    #: Names of the reward terms (info["reward_<name>"]); the reward is their sum.
    reward_terms: tuple[str, ...] = ()
    #: Episode length a task is registered with.
    default_max_episode_steps: int = 1000

    def __init__(
        self,
        model: Model,
        control_low: Sequence[float] | np.ndarray,
        control_high: Sequence[float] | np.ndarray,
        frame_skip: int = 1,
        max_episode_steps: int | None = None,
        config: dict[str, Any] | None = None,
        control_home: Sequence[float] | np.ndarray | None = None,
    ):
        super().__init__()
        if not isinstance(frame_skip, (int, np.integer)) or isinstance(frame_skip, bool) or frame_skip < 1:
            raise ValueError(f"frame_skip must be a positive integer, got {frame_skip!r}")
        if max_episode_steps is not None and (
            not isinstance(max_episode_steps, (int, np.integer)) or max_episode_steps < 1
        ):
            raise ValueError(f"max_episode_steps must be a positive integer or None, got {max_episode_steps!r}")
        low = np.asarray(control_low, dtype=np.float64).reshape(-1)
        high = np.asarray(control_high, dtype=np.float64).reshape(-1)
        if low.shape != (model.num_controls,) or high.shape != low.shape:
            raise ValueError(
                f"control_low/high must have shape ({model.num_controls},) = (model.num_controls,), "
                f"got {low.shape} and {high.shape}"
            )
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
            raise ValueError("control_low/high must be finite with low < high for every control")
        home = 0.5 * (low + high) if control_home is None else np.asarray(control_home, np.float64).reshape(-1)
        if home.shape != low.shape or not np.all((low <= home) & (home <= high)):
            raise ValueError(f"control_home must have shape {low.shape} and lie within [control_low, control_high]")
        self._config = None if config is None else (type(self), tuple(sorted(config.items())))
        self.model = model
        self.frame_skip = int(frame_skip)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.control_low = low
        self.control_high = high
        self.control_home = home
        self.control_scale = np.maximum(high - home, home - low)  # > 0 as low < high
        self.action_size = int(model.num_controls)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.action_size,), dtype=np.float32)
        observation = jax.eval_shape(lambda key: self.reset(key)[1], jax.ShapeDtypeStruct((2,), jnp.uint32))
        if len(observation.shape) != 1:
            raise ValueError(f"task observations must be 1-D, got shape {observation.shape}")
        self.observation_size = int(observation.shape[0])
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(self.observation_size,), dtype=np.float32)

    def __eq__(self, other: object) -> bool:
        if self._config is None or not isinstance(other, DbdFuncEnv):
            return self is other
        return self._config == other._config

    def __hash__(self) -> int:
        return id(self) if self._config is None else hash(self._config)

    # ------------------------------------------------------------------------ derived facts
    @property
    def dt(self) -> float:
        """Seconds per env step (model.dt x frame_skip)."""
        return float(self.model.dt) * self.frame_skip

    @property
    def render_fps(self) -> int:
        return max(1, round(1.0 / self.dt))

    @property
    def dtype(self):
        """The float type of the physics (float32 unless the model was built under x64)."""
        return self.model.bodies.mass.dtype

    # ------------------------------------------------------------------------ task hooks
    def task_initial(self, key: jnp.ndarray) -> tuple[State, Any]:
        """(physics State, task variables) at the start of an episode drawn with `key`."""
        raise NotImplementedError

    def task_observation(self, state: EnvState) -> jnp.ndarray:
        """(observation_size,) what the agent sees."""
        raise NotImplementedError

    def task_reward(self, state: EnvState, action: jnp.ndarray, next_state: EnvState) -> dict[str, jnp.ndarray]:
        """{term name: () reward term} for the transition (action already clipped and finite)."""
        raise NotImplementedError

    def task_failed(self, state: EnvState) -> jnp.ndarray:
        """() bool, the task's own termination (a fall); default never."""
        return jnp.zeros((), dtype=bool)

    def task_info(self, state: EnvState) -> dict[str, jnp.ndarray]:
        """Extra info of a state (same keys for every state)."""
        return {}

    def task_before_physics(self, state: EnvState, action: jnp.ndarray, key: jnp.ndarray) -> State:
        """The physics state the step starts from (e.g. with a push applied); default unchanged."""
        return state.physics

    def task_update(self, state: EnvState, action: jnp.ndarray, physics: State) -> Any:
        """The task variables after a step; default unchanged."""
        return state.task

    def render_scene(self, state: EnvState) -> tuple[Model, State, dict[str, Any]]:
        """(model, physics state, keyword arguments of `dbdjax.render.render`) that draw one
        (unbatched) state; default: the task's own model and physics, the default camera."""
        return self.model, state.physics, {}

    # ------------------------------------------------------------------------ actions
    def check_action(self, action: Any) -> jnp.ndarray:
        """`action` as a float array of shape (action_size,); ValueError for any other shape."""
        shape = jnp.shape(action)
        if shape != (self.action_size,):
            raise ValueError(
                f"{type(self).__name__}: action must have shape ({self.action_size},) = action_space.shape, got {shape}"
            )
        return jnp.asarray(action, dtype=self.dtype)

    def clean_action(self, action: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(action clipped to [-1, 1] with non-finite entries replaced by 0, () bool all finite)."""
        finite = jnp.isfinite(action)
        return jnp.where(finite, jnp.clip(action, -1.0, 1.0), 0.0), jnp.all(finite)

    def control(self, action: jnp.ndarray) -> jnp.ndarray:
        """Drive targets (num_controls,) of an action in [-1, 1]: clip(home + scale a, low, high)
        (`control_home`, `control_scale`; module docstring)."""
        low, high, home, scale = self._control_map()
        return jnp.clip(home + scale * action, low, high)

    def action_of_control(self, control: jnp.ndarray) -> jnp.ndarray:
        """The inverse of `control` on the range: the action in [-1, 1] whose targets are `control`
        ((control - home) / scale, clipped to [-1, 1]; a target outside the range gets the action
        of the range's end)."""
        low, high, home, scale = self._control_map()
        return jnp.clip((jnp.clip(control, low, high) - home) / scale, -1.0, 1.0)

    def _control_map(self) -> tuple[jnp.ndarray, ...]:
        arrays = (self.control_low, self.control_high, self.control_home, self.control_scale)
        return tuple(jnp.asarray(x, self.dtype) for x in arrays)

    # ------------------------------------------------------------------------ the fused pair
    def reset(self, key: jnp.ndarray) -> tuple[EnvState, jnp.ndarray, dict[str, jnp.ndarray]]:
        """Start an episode: (state, observation (observation_size,) float32, info)."""
        state = self._initial(key)
        return state, self._observation(state), self._info(state, None)

    def step(self, state: EnvState, action: Any):
        """One env step: (next state, observation, reward, terminated, truncated, info).

        action: (action_size,) in [-1, 1] (clipped; non-finite entries end the episode).
        reward: () in the physics dtype; terminated, truncated: () bool.
        """
        action, finite = self.clean_action(self.check_action(action))
        next_state = self._advance(state, action, finite)
        terms = self.task_reward(state, action, next_state)
        reward = sum(terms.values(), jnp.zeros((), self.dtype))
        terminated = self._terminal(next_state)
        truncated = self._truncated(next_state) & ~terminated
        return next_state, self._observation(next_state), reward, terminated, truncated, self._info(next_state, terms)

    # ------------------------------------------------------------------------ internals
    def _initial(self, key: jnp.ndarray) -> EnvState:
        key = jnp.asarray(key)
        if key.shape != (2,) or key.dtype != jnp.uint32:
            raise ValueError(f"key must be a raw PRNG key of shape (2,) uint32 (jax.random.PRNGKey), got {key}")
        episode_key, task_key = jax.random.split(key)
        physics, task = self.task_initial(task_key)
        false = jnp.zeros((), dtype=bool)
        return EnvState(physics, task, jnp.zeros((), jnp.int32), episode_key, false, false)

    def _advance(self, state: EnvState, action: jnp.ndarray, finite: jnp.ndarray) -> EnvState:
        key, step_key = jax.random.split(state.key)
        start = self.task_before_physics(state, action, step_key)
        control = self.control(action)

        def physics_step(physics, _):
            return dbd.step(self.model, physics, control), None

        moved, _ = jax.lax.scan(physics_step, start, None, length=self.frame_skip)
        moved_finite = dbd.is_finite(moved)
        # Keep the last finite physics (observations stay finite); the flag ends the episode.
        physics = jax.tree.map(lambda new, old: jnp.where(moved_finite, new, old), moved, state.physics)
        task = self.task_update(state, action, physics)
        return EnvState(physics, task, state.step + 1, key, ~finite, ~moved_finite)

    def _observation(self, state: EnvState) -> jnp.ndarray:
        return jnp.asarray(self.task_observation(state), jnp.float32)

    def _terminal(self, state: EnvState) -> jnp.ndarray:
        return self.task_failed(state) | state.nonfinite_action | state.nonfinite_state

    def _truncated(self, state: EnvState) -> jnp.ndarray:
        if self.max_episode_steps is None:
            return jnp.zeros((), dtype=bool)
        return state.step >= self.max_episode_steps

    def _info(self, state: EnvState, terms: dict[str, jnp.ndarray] | None) -> dict[str, jnp.ndarray]:
        info = {"nonfinite_action": state.nonfinite_action, "nonfinite_state": state.nonfinite_state}
        for name in self.reward_terms:
            value = jnp.zeros((), self.dtype) if terms is None else terms[name]
            info[f"reward_{name}"] = jnp.asarray(value, self.dtype)
        info.update(self.task_info(state))
        return info

    # ------------------------------------------------------------------------ FuncEnv API
    # The same computation split as Gymnasium's functional API wants. `rng` is accepted for that
    # signature and unused: the randomness of a step comes from state.key (so it is a function
    # of the state alone). `params` is unused (the Model is closed over).
    def initial(self, rng: Any, params: Any = None) -> EnvState:
        return self._initial(rng)

    def transition(self, state: EnvState, action: Any, rng: Any = None, params: Any = None) -> EnvState:
        action, finite = self.clean_action(self.check_action(action))
        return self._advance(state, action, finite)

    def observation(self, state: EnvState, rng: Any = None, params: Any = None) -> jnp.ndarray:
        return self._observation(state)

    def reward(self, state: EnvState, action: Any, next_state: EnvState, rng: Any = None, params: Any = None):
        action, _ = self.clean_action(self.check_action(action))
        return sum(self.task_reward(state, action, next_state).values(), jnp.zeros((), self.dtype))

    def terminal(self, state: EnvState, rng: Any = None, params: Any = None) -> jnp.ndarray:
        return self._terminal(state)

    def state_info(self, state: EnvState, params: Any = None) -> dict:
        return self._info(state, None)

    def transition_info(self, state: EnvState, action: Any, next_state: EnvState, params: Any = None) -> dict:
        action, _ = self.clean_action(self.check_action(action))
        return self._info(next_state, self.task_reward(state, action, next_state))

    def render_init(self, params: Any = None, **kwargs) -> None:
        return None

    def render_image(self, state: EnvState, render_state: Any = None, params: Any = None):
        from dbdjax.envs.wrappers import render_frame  # noqa: PLC0415 (render is optional)

        return render_state, render_frame(self, state)

    def render_close(self, render_state: Any, params: Any = None) -> None:
        return None


# ---------------------------------------------------------------------------- shared helpers
def hinge_angles(model: Model, physics: State, joints: Sequence[int]) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Angles (rad, from the build pose) and rates (rad/s) of hinge joints, each (len(joints),).

    The angle is the twist of q_a^-1 q_b rest^-1 about the hinge axle in a's frame (the engine's
    hinge convention: a drive target is this angle), the rate is (w_b - w_a) . axle in the world.
    """
    structure = model.structure
    index = np.asarray(joints, dtype=np.int32)
    body_a = structure.joint_body_a.array[index]
    body_b = structure.joint_body_b.array[index]
    quat = jnp.concatenate([physics.quat, math.quat_identity((1,)).astype(physics.quat.dtype)])
    ang_vel = jnp.concatenate([physics.ang_vel, jnp.zeros((1, 3), physics.ang_vel.dtype)])
    # The world is index N in the structure's tables: row N of the padded ones (identity, at rest).
    quat_a, quat_b = quat[body_a], quat[body_b]
    rest = model.joints.rest_rotation[index]
    axis = model.joints.local_axis_a[index]
    relative = math.quat_multiply(math.quat_multiply(math.quat_conjugate(quat_a), quat_b), math.quat_conjugate(rest))
    angle = math.quat_twist_angle(relative, axis)
    world_axis = math.quat_rotate(quat_a, axis)
    rate = math.dot(ang_vel[body_b] - ang_vel[body_a], world_axis)
    return angle, rate


def joint_coordinates(
    model: Model, physics: State, joints: Sequence[int], kinds: Sequence[str]
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Joint positions and rates in the layout of their drive targets, each (D,).

    joints: joint indices; kinds: "ball" or "hinge" per joint. A ball joint gives 3 entries, the
    rotation vector (rad) of q_a^-1 q_b rest^-1 in a's frame (the engine's ball drive target) and
    the relative angular velocity in a's frame (rad/s); a hinge gives 1, its angle and rate
    (`hinge_angles`). D = 3 x balls + hinges, in the order given.
    """
    if len(joints) != len(kinds) or any(kind not in ("ball", "hinge") for kind in kinds):
        raise ValueError(f"joint_coordinates: need one kind ('ball' or 'hinge') per joint, got {kinds!r}")
    structure = model.structure
    index = np.asarray(joints, dtype=np.int32)
    body_a = structure.joint_body_a.array[index]
    body_b = structure.joint_body_b.array[index]
    quat = jnp.concatenate([physics.quat, math.quat_identity((1,)).astype(physics.quat.dtype)])
    ang_vel = jnp.concatenate([physics.ang_vel, jnp.zeros((1, 3), physics.ang_vel.dtype)])
    quat_a = quat[body_a]
    relative = math.quat_multiply(
        math.quat_multiply(math.quat_conjugate(quat_a), quat[body_b]),
        math.quat_conjugate(model.joints.rest_rotation[index]),
    )
    axis = model.joints.local_axis_a[index]
    relative_rate = ang_vel[body_b] - ang_vel[body_a]  # world frame
    ball_position = math.quat_log(relative)
    ball_rate = math.quat_rotate_inverse(quat_a, relative_rate)
    hinge_position = math.quat_twist_angle(relative, axis)
    hinge_rate = math.dot(relative_rate, math.quat_rotate(quat_a, axis))
    positions, rates = [], []
    for k, kind in enumerate(kinds):
        if kind == "ball":
            positions.append(ball_position[k])
            rates.append(ball_rate[k])
        else:
            positions.append(hinge_position[k, None])
            rates.append(hinge_rate[k, None])
    return jnp.concatenate(positions), jnp.concatenate(rates)


def yaw_rotate_inverse(yaw: jnp.ndarray, vectors: jnp.ndarray) -> jnp.ndarray:
    """vectors (..., 3) seen in the heading frame: rotated by -yaw (rad) about world z."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    x, y = vectors[..., 0], vectors[..., 1]
    return jnp.stack([c * x + s * y, -s * x + c * y, vectors[..., 2]], axis=-1)
