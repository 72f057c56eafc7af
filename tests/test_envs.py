"""Gymnasium environments (dbdjax.envs): the Gymnasium API as check_env and the vector-env docs
define it, autoreset modes, seeding, bad actions, the IK expert baseline, gradients through an
episode, and the Brax adapter.

Compiling `dbd.step` dominates the time here, so every env below is built from one of a few task
configs (equal configs share one compilation, see `DbdFuncEnv.config`) and compiled with LLVM at
-O0 (these tests check behaviour, not speed).
"""

from __future__ import annotations

import dataclasses
import functools

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import dbdjax.envs as envs
from dbdjax.envs import IKChainReach, expert_action

QUICK = {"xla_backend_optimization_level": 0}
quick_jit = functools.partial(jax.jit, compiler_options=QUICK)
IK_ID = "dbdjax/IKChainReach-v0"
SHORT = 3  # episode length of the vector-env tests (autoreset comes quickly)


@pytest.fixture(scope="module")
def single():
    """gymnasium.make's IKChainReach (jax arrays out), compiled at -O0."""
    env = gym.make(IK_ID, jit_options=QUICK)
    yield env
    env.close()


@pytest.fixture(scope="module")
def task():
    """The IKChainReach core with the registered episode length."""
    return IKChainReach(max_episode_steps=IKChainReach.default_max_episode_steps)


@functools.cache
def vector_env(num_envs=4, mode=AutoresetMode.NEXT_STEP):
    return gym.make_vec(
        IK_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", max_episode_steps=SHORT,
        autoreset_mode=mode, jit_options=QUICK,
    )  # fmt: skip


def rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    observations, rewards = [np.asarray(obs)], []
    for action in actions:
        obs, reward, *_ = env.step(action)
        observations.append(np.asarray(obs))
        rewards.append(np.asarray(reward))
    return np.stack(observations), np.stack(rewards)


# ------------------------------------------------------------------------------------ registration
def test_import_registers_every_env_with_both_entry_points():
    for env_id in envs.ENVIRONMENTS:
        spec = gym.spec(env_id)
        assert spec.entry_point.startswith("dbdjax.envs.") and spec.vector_entry_point.startswith("dbdjax.envs.")
        assert spec.max_episode_steps is not None


def test_check_env_passes_for_ik_chain_reach(single):
    # check_env wraps a metadata["jax"] env in JaxToNumpy itself; the render check makes an
    # rgb_array copy through the spec and draws a frame with dbdjax.render.
    check_env(single.unwrapped)


def test_single_env_metadata_and_spaces(single):
    unwrapped = single.unwrapped
    assert unwrapped.metadata["jax"] is True
    assert unwrapped.metadata["render_modes"] == ["rgb_array"]
    assert unwrapped.metadata["render_fps"] == 30
    assert single.action_space.shape == (5,) and single.action_space.low.min() == -1.0
    assert single.observation_space.shape == (24,)
    assert isinstance(single, gym.wrappers.TimeLimit) and single.spec.max_episode_steps == 100


def test_same_seed_gives_the_same_trajectory_and_another_seed_another(single):
    actions = np.random.default_rng(0).uniform(-1, 1, size=(4, 5)).astype(np.float32)
    first, first_rewards = rollout(single, 7, actions)
    again, again_rewards = rollout(single, 7, actions)
    other, _ = rollout(single, 8, actions)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first_rewards, again_rewards)
    assert np.abs(first[0] - other[0]).max() > 1e-3  # another start and goal


# ------------------------------------------------------------------------------------ bad actions
def test_actions_outside_the_box_are_clipped(single):
    env = single.unwrapped
    env.reset(seed=1)
    start = env.state
    outside = np.array([5.0, -7.0, 1.5, -1.0, 0.3], np.float32)
    obs_out, reward_out, *_ = env.step(outside)
    env.state = start
    obs_in, reward_in, *_ = env.step(np.clip(outside, -1, 1))
    np.testing.assert_array_equal(np.asarray(obs_out), np.asarray(obs_in))
    assert reward_out == reward_in


def test_nan_action_ends_the_episode_with_a_flag_and_a_finite_state(single):
    env = single.unwrapped
    env.reset(seed=2)
    obs, reward, terminated, truncated, info = env.step(np.array([0.1, np.nan, 0.0, np.inf, 0.2], np.float32))
    assert terminated and not truncated
    assert bool(info["nonfinite_action"]) and not bool(info["nonfinite_state"])
    assert np.all(np.isfinite(np.asarray(obs))) and np.isfinite(reward)
    assert bool(jax.tree.reduce(lambda a, b: a & b, jax.tree.map(lambda x: jnp.all(jnp.isfinite(x)), env.state)))


def test_finite_actions_do_not_raise_the_flags(single):
    env = single.unwrapped
    env.reset(seed=2)
    _, _, terminated, _, info = env.step(np.zeros(5, np.float32))
    assert not terminated and not bool(info["nonfinite_action"]) and not bool(info["nonfinite_state"])


def test_nonfinite_physics_ends_the_episode_and_keeps_the_last_finite_state(single):
    env = single.unwrapped
    env.reset(seed=3)
    huge = env.state.physics.vel.at[2].set(jnp.array([3e38, 3e38, 3e38], jnp.float32))  # overflows in the step
    start = dataclasses.replace(env.state, physics=dataclasses.replace(env.state.physics, vel=huge))
    env.state = start
    obs, _, terminated, _, info = env.step(np.zeros(5, np.float32))
    assert terminated and bool(info["nonfinite_state"]) and not bool(info["nonfinite_action"])
    np.testing.assert_array_equal(np.asarray(env.state.physics.pos), np.asarray(start.physics.pos))


def test_wrong_action_shapes_raise_value_errors(single, task):
    single.reset(seed=0)
    for bad in (np.zeros(4, np.float32), np.zeros((1, 5), np.float32), np.float32(0.0)):
        with pytest.raises(ValueError, match="action must have shape"):
            single.step(bad)
    state, _, _ = task.reset(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"action must have shape \(5,\)"):
        task.step(state, jnp.zeros(6))
    envs4 = vector_env()
    envs4.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(4, 5\)"):
        envs4.step(np.zeros((3, 5), np.float32))


# ------------------------------------------------------------------------------------ vector env
def test_vector_env_spaces_and_metadata():
    envs4 = vector_env()
    assert envs4.num_envs == 4
    assert envs4.single_action_space.shape == (5,) and envs4.action_space.shape == (4, 5)
    assert envs4.single_observation_space.shape == (24,) and envs4.observation_space.shape == (4, 24)
    assert envs4.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert envs4.metadata["jax"] is True and envs4.metadata["render_fps"] == 30
    obs, info = envs4.reset(seed=0)
    assert obs.shape == (4, 24) and obs.dtype == jnp.float32 and isinstance(obs, jax.Array)
    assert np.asarray(obs) in envs4.observation_space
    assert all(value.shape == (4,) for value in info.values())


def test_vector_env_same_seed_same_trajectories_and_copies_differ():
    envs4 = vector_env()
    actions = np.random.default_rng(1).uniform(-1, 1, size=(5, 4, 5)).astype(np.float32)
    first, first_rewards = rollout(envs4, 11, actions)
    again, again_rewards = rollout(envs4, 11, actions)
    np.testing.assert_array_equal(first, again)  # through an autoreset (episodes of 3 steps)
    np.testing.assert_array_equal(first_rewards, again_rewards)
    assert np.abs(first[0, 0] - first[0, 1]).max() > 1e-3  # each copy has its own start and goal
    listed, _ = envs4.reset(seed=[3, 3, 4, 4])
    listed = np.asarray(listed)
    np.testing.assert_array_equal(listed[0], listed[1])
    assert np.abs(listed[0] - listed[2]).max() > 1e-3


def test_next_step_autoreset_resets_a_done_copy_on_the_following_step():
    envs4 = vector_env()
    obs, _ = envs4.reset(seed=5)
    zeros = jnp.zeros((4, 5))
    for step in range(1, SHORT + 1):
        last, reward, terminated, truncated, _ = envs4.step(zeros)
        assert not np.any(np.asarray(terminated))
        assert np.all(np.asarray(truncated)) == (step == SHORT)
    ended_key = envs4.state.key
    # The next step ignores the actions of the done copies, returns the first observation of a
    # new episode with reward 0 and no end flags, drawn from each copy's own key.
    obs, reward, terminated, truncated, info = envs4.step(jnp.full((4, 5), 0.9))
    assert np.all(np.asarray(reward) == 0.0)
    assert not np.any(np.asarray(terminated)) and not np.any(np.asarray(truncated))
    assert np.all(np.asarray(envs4.state.step) == 0)
    keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(ended_key, 0x5E5E7)
    expected = np.stack([np.asarray(envs4.unwrapped.func_env.reset(k)[1]) for k in keys])
    # The same computation, eager here and jitted under vmap in the env: float32 rounding apart.
    np.testing.assert_allclose(np.asarray(obs), expected, rtol=0, atol=1e-5)
    assert np.abs(np.asarray(obs) - np.asarray(last)).max() > 1e-3
    _, reward, _, _, _ = envs4.step(zeros)  # and the new episode runs on
    assert np.all(np.asarray(envs4.state.step) == 1) and np.any(np.asarray(reward) != 0.0)


@pytest.mark.slow
def test_same_step_autoreset_returns_the_new_episode_and_the_final_observation():
    envs4 = vector_env(mode=AutoresetMode.SAME_STEP)
    assert envs4.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    envs4.reset(seed=5)
    zeros = jnp.zeros((4, 5))
    for _ in range(SHORT - 1):
        _, _, _, truncated, info = envs4.step(zeros)
        assert not np.any(np.asarray(info["_final_obs"]))
    before = envs4.state
    obs, reward, terminated, truncated, info = envs4.step(zeros)
    assert np.all(np.asarray(truncated)) and np.all(np.asarray(info["_final_obs"]))
    assert np.all(np.asarray(envs4.state.step) == 0)  # already the new episode
    # The goal (observation entries 18:21) is fixed within an episode: final_obs is the ended
    # episode's last observation, obs the new episode's first. (Comparing whole observations with
    # a separately compiled step would not do: see the sensitivity note in envs/ik_chain.py.)
    goal = slice(18, 21)
    np.testing.assert_array_equal(np.asarray(info["final_obs"])[:, goal], np.asarray(before.task.goal))
    np.testing.assert_array_equal(np.asarray(obs)[:, goal], np.asarray(envs4.state.task.goal))
    assert np.abs(np.asarray(envs4.state.task.goal) - np.asarray(before.task.goal)).max(axis=1).min() > 1e-3
    func_env = envs4.unwrapped.func_env
    first = np.asarray(jax.vmap(func_env.observation)(envs4.state))  # eager: float32 rounding apart
    np.testing.assert_allclose(np.asarray(obs), first, rtol=0, atol=1e-5)
    assert np.all(np.asarray(info["final_info"]["distance"]) > 0.0)


def test_a_nan_action_ends_only_its_own_copy():
    envs4 = vector_env()
    envs4.reset(seed=9)
    actions = np.zeros((4, 5), np.float32)
    actions[2, 1] = np.nan
    obs, _, terminated, _, info = envs4.step(actions)
    np.testing.assert_array_equal(np.asarray(terminated), [False, False, True, False])
    np.testing.assert_array_equal(np.asarray(info["nonfinite_action"]), [False, False, True, False])
    assert np.all(np.isfinite(np.asarray(obs)))


def test_vector_step_keeps_arrays_on_the_device():
    envs4 = vector_env()
    envs4.reset(seed=0)
    actions = jax.device_put(jnp.zeros((4, 5)))
    envs4.step(actions)  # compiled already; now no transfer may happen in either direction
    with jax.transfer_guard("disallow"):
        obs, reward, terminated, truncated, info = envs4.step(actions)
    assert all(isinstance(x, jax.Array) for x in (obs, reward, terminated, truncated, *info.values()))


def test_reset_mask_resets_only_the_masked_copies():
    envs4 = vector_env(mode=AutoresetMode.NEXT_STEP)
    envs4.reset(seed=4)
    envs4.step(jnp.zeros((4, 5)))
    before = np.asarray(envs4.state.physics.pos)
    obs, _ = envs4.reset(options={"reset_mask": np.array([True, False, False, True])})
    after = np.asarray(envs4.state.physics.pos)
    np.testing.assert_array_equal(np.asarray(envs4.state.step), [0, 1, 1, 0])
    np.testing.assert_array_equal(after[1:3], before[1:3])
    assert np.abs(after[0] - before[0]).max() > 1e-3


# ------------------------------------------------------------------------------------ IK expert
@pytest.mark.slow
def test_ik_expert_reaches_the_goal_in_most_episodes(task):
    # Measured with evaluate_expert (benchmarks/ik_chain_expert.py): 64 of 64 episodes end within
    # 1 cm (seed 0). The bound leaves room for a rare local minimum of the local IK method on
    # other seeds: at least 14 of 16 here.
    episodes = 16
    keys = jax.random.split(jax.random.PRNGKey(123), episodes)
    state, _, _ = quick_jit(jax.vmap(task.reset))(keys)
    act = quick_jit(jax.vmap(functools.partial(expert_action, task)))
    step = quick_jit(jax.vmap(task.step))
    for _ in range(task.max_episode_steps):
        state, _, _, terminated, _, info = step(state, act(state))
        assert not np.any(np.asarray(terminated))
    success = np.asarray(info["is_success"])
    distance = np.asarray(info["distance"])
    print(f"\nIK expert: {success.sum()}/{episodes} within 1 cm; final distance median {np.median(distance):.1e} m")
    assert success.sum() >= 14


# ------------------------------------------------------------------------------------ gradients
@pytest.mark.slow
def test_gradient_of_the_return_wrt_the_actions_is_finite_and_a_step_along_it_helps():
    # The ball-joint chain: with hinges, dbd.step's Gauss-Seidel sweeps amplify perturbations
    # (about 1.75x per iteration with drives: the axle-alignment row's direction is normalised
    # from a near-zero cross product), so over 8 steps the hinge chain's gradient overflows
    # float32; the ball-joint chain's iterations contract (envs/ik_chain.py, "Sensitivity").
    task = IKChainReach(joint="ball", max_episode_steps=IKChainReach.default_max_episode_steps)
    state, _, _ = task.reset(jax.random.PRNGKey(4))
    horizon = 8

    def episode_return(actions):
        def one(state, action):
            state, _, reward, _, _, _ = task.step(state, action)
            return state, reward

        return jnp.sum(jax.lax.scan(one, state, actions)[1])

    actions = jnp.zeros((horizon, task.action_size))
    value_and_grad = quick_jit(jax.value_and_grad(episode_return))
    value, gradient = value_and_grad(actions)
    gradient = np.asarray(gradient)
    assert np.all(np.isfinite(gradient)) and np.abs(gradient).max() > 0.0
    better, _ = value_and_grad(actions + 0.05 * gradient / np.abs(gradient).max())
    print(f"\nreturn {float(value):.4f} -> {float(better):.4f} after a step along the gradient")
    assert float(better) > float(value)


# ------------------------------------------------------------------------------------ Brax
def test_brax_adapter_resets_and_steps_like_the_core(task):
    pytest.importorskip("brax")
    from dbdjax.envs.brax_adapter import BraxEnv, make_brax_env

    with pytest.raises(ValueError, match="max_episode_steps=None"):
        BraxEnv(task)
    env = make_brax_env(IK_ID)
    assert env.observation_size == 24 and env.action_size == 5 and env.backend == "dbdjax"
    core = env.func_env
    key = jax.random.PRNGKey(0)
    action = jnp.full(5, 0.5)

    @quick_jit
    def both(key):
        # One program for both: separately compiled programs may round differently, and this
        # chain's step amplifies rounding (see envs/ik_chain.py).
        state = env.reset(key)
        return state, env.step(state, action), core.step(core.reset(key)[0], action)

    state, stepped, expected = both(key)
    np.testing.assert_array_equal(np.asarray(stepped.obs), np.asarray(expected[1]))
    assert float(stepped.reward) == float(expected[2]) and float(stepped.done) == 0.0
    assert set(stepped.metrics) == set(state.metrics) >= {"is_success", "reward_progress", "nonfinite_action"}


@pytest.mark.slow
def test_brax_ppo_trains_on_the_ik_env_through_the_adapter():
    pytest.importorskip("brax")
    from brax.training.agents.ppo import train as ppo

    from dbdjax.envs.brax_adapter import make_brax_env, restore_device_put_replicated

    restore_device_put_replicated()  # brax 0.14.2 calls what JAX 0.10 removed
    steps = []
    make_policy, params, metrics = ppo.train(
        make_brax_env(IK_ID), num_timesteps=800, episode_length=20, num_envs=4, batch_size=4, num_minibatches=2,
        unroll_length=5, num_updates_per_batch=1, num_evals=2, run_evals=False, seed=0,
        progress_fn=lambda step, _: steps.append(step),
    )  # fmt: skip
    assert steps[-1] >= 800
    assert np.isfinite(float(metrics["training/total_loss"]))
    policy = make_policy(params, deterministic=True)
    action, _ = policy(jnp.zeros((1, 24)), jax.random.PRNGKey(0))
    assert action.shape == (1, 5) and np.all(np.abs(np.asarray(action)) <= 1.0)


# ------------------------------------------------------------------------------------ ragdoll envs
@pytest.fixture(scope="module")
def stand():
    return envs.RagdollStand()


@pytest.fixture(scope="module")
def track():
    return envs.RagdollTrack()


def test_ragdoll_observation_does_not_depend_on_the_heading(stand):
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    state, obs, _ = quick_jit(jax.vmap(stand.reset))(keys)
    headings = np.asarray(jax.vmap(stand.heading)(state.physics))
    first, last = np.argmin(headings), np.argmax(headings)
    assert headings[last] - headings[first] > 0.5  # different headings: the bodies are elsewhere
    assert np.abs(np.asarray(state.physics.pos[first] - state.physics.pos[last])).max() > 0.05
    np.testing.assert_allclose(np.asarray(obs[1:]), np.broadcast_to(np.asarray(obs[0]), obs[1:].shape), atol=2e-6)
    assert obs.shape == (3, 133) and stand.observation_size == 133 and stand.action_size == 26


def test_joint_coordinates_are_zero_at_the_build_pose_and_the_chain_angles_of_an_ik_pose(stand, task):
    state, _, _ = stand.reset(jax.random.PRNGKey(1))  # the build pose, turned about z
    position, rate = stand.joints(state.physics)
    assert position.shape == (26,) and float(jnp.max(jnp.abs(position))) < 1e-5
    assert float(jnp.max(jnp.abs(rate))) == 0.0
    angles = jnp.array([0.4, -0.7, 1.2, 0.3, -1.5])
    measured, _ = envs.core.joint_coordinates(task.model, task.chain_state(angles), task.joints, ("hinge",) * 5)
    np.testing.assert_allclose(np.asarray(measured), np.asarray(angles), atol=2e-6)


def test_ragdoll_action_zero_is_the_build_pose_and_one_slope_reaches_every_target(stand, task):
    """Ragdoll actions are targets about the build pose (legged_gym's default + scale x action):
    0 -> all targets 0; +-1 -> the ends of the symmetric ranges; a knee or elbow (0 .. 2.4) is
    straight for a <= 0 and fully flexed at +1; an ankle (-0.5 .. 0.8) reaches -0.5 at -0.625;
    action_of_control inverts control on the whole range. The IK chain keeps the plain linear map."""
    np.testing.assert_array_equal(np.asarray(stand.control(jnp.zeros(26))), 0.0)
    np.testing.assert_array_equal(np.asarray(stand.action_of_control(jnp.zeros(26))), 0.0)
    np.testing.assert_allclose(np.asarray(stand.control(jnp.ones(26))), stand.control_high, atol=1e-6)
    controls = stand.doll.controls
    low_end = np.asarray(stand.control(-jnp.ones(26)))
    for name in ("waist", "neck", "shoulder_l", "wrist_r", "hip_l", "hip_r"):
        np.testing.assert_allclose(low_end[controls[name]], stand.control_low[controls[name]], atol=1e-6)
    for name in ("knee_l", "knee_r", "elbow_l", "elbow_r"):
        entry = controls[name]
        np.testing.assert_array_equal(low_end[entry], 0.0)
        half = np.asarray(stand.control(jnp.zeros(26).at[entry].set(0.5)))[entry]
        np.testing.assert_allclose(half, 1.2, atol=1e-6)  # 0.5 x 2.4 rad
    ankle = controls["ankle_l"]
    for action, target in ((-0.625, -0.5), (-1.0, -0.5), (-0.25, -0.2), (0.5, 0.4)):
        value = np.asarray(stand.control(jnp.zeros(26).at[ankle].set(action)))[ankle]
        np.testing.assert_allclose(value, target, atol=1e-6)
    targets = np.random.default_rng(5).uniform(stand.control_low, stand.control_high)
    round_trip = stand.control(stand.action_of_control(jnp.asarray(targets, jnp.float32)))
    np.testing.assert_allclose(np.asarray(round_trip), targets, atol=1e-5)
    actions = jnp.asarray(np.random.default_rng(6).uniform(-1, 1, size=5), jnp.float32)
    linear = task.control_low + 0.5 * (np.asarray(actions) + 1.0) * (task.control_high - task.control_low)
    np.testing.assert_allclose(np.asarray(task.control(actions)), linear, atol=1e-6)
    np.testing.assert_allclose(task.control_home, 0.0)


def test_random_pushes_come_at_the_documented_rate_with_horizontal_kicks_of_the_documented_size():
    stand = envs.RagdollStand(push_schedule="random")
    count = 40_000
    keys = jax.random.split(jax.random.PRNGKey(2), count)
    kicks = np.asarray(quick_jit(jax.vmap(stand.kick))(keys, jnp.arange(count) % 300))
    pushed = np.linalg.norm(kicks, axis=1) > 0
    rate = stand.dt / stand.push_interval  # 1/60 per step
    assert abs(pushed.mean() - rate) < 4 * np.sqrt(rate * (1 - rate) / count)
    speed = np.linalg.norm(kicks[pushed], axis=1)
    # The default range, 0.2-0.6 m/s (envs/ragdoll_envs.py: survivable with the feet in place).
    assert np.all(kicks[:, 2] == 0.0) and speed.min() >= 0.2 - 1e-6 and speed.max() <= 0.6 + 1e-6
    assert speed.min() < 0.22 and speed.max() > 0.58  # the whole range is drawn (~670 kicks)


def test_regular_pushes_come_every_two_seconds_from_the_start_in_every_direction(stand):
    assert stand.push_schedule == "regular"  # RagdollStand-v0's default
    episodes, steps = 400, 300
    keys = jax.random.split(jax.random.PRNGKey(2), episodes * steps)
    step = jnp.tile(jnp.arange(steps), episodes)
    kicks = np.asarray(quick_jit(jax.vmap(stand.kick))(keys, step)).reshape(episodes, steps, 3)
    pushed = np.linalg.norm(kicks, axis=-1) > 0
    every = round(stand.push_interval / stand.dt)  # 60 steps: 2 s at 30 Hz
    expected = np.zeros(steps, bool)
    expected[every::every] = True  # steps 60, 120, 180, 240: none at the start, four an episode
    assert pushed.sum(1).tolist() == [4] * episodes and np.all(pushed == expected)
    speed = np.linalg.norm(kicks[pushed], axis=-1)
    assert np.all(kicks[..., 2] == 0.0) and speed.min() >= 0.2 - 1e-6 and speed.max() <= 0.6 + 1e-6
    assert speed.min() < 0.21 and speed.max() > 0.59  # the whole range is drawn (1,600 kicks)
    angle = np.arctan2(kicks[pushed][:, 1], kicks[pushed][:, 0])
    counts = np.histogram(angle, bins=8, range=(-np.pi, np.pi))[0]
    assert counts.min() > 150 and counts.max() < 250  # every direction alike (200 a bin expected)


def test_a_backward_push_share_draws_that_share_from_behind_and_the_rest_as_before():
    episodes, steps = 200, 300
    keys = jax.random.split(jax.random.PRNGKey(2), episodes * steps)
    step = jnp.tile(jnp.arange(steps), episodes)
    kicks = {}
    for share in (0.0, 0.5, 1.0):
        env = envs.RagdollStand(backward_push_share=share)
        kicks[share] = np.asarray(quick_jit(jax.vmap(env.kick))(keys, step))
    default = np.asarray(quick_jit(jax.vmap(envs.RagdollStand().kick))(keys, step))
    np.testing.assert_array_equal(kicks[0.0], default)  # share 0: the registered env's pushes, bit for bit
    pushed = np.linalg.norm(default, axis=-1) > 0
    for share, drawn in kicks.items():
        assert np.array_equal(np.linalg.norm(drawn, axis=-1) > 0, pushed)  # the same steps, the same speeds
        np.testing.assert_allclose(np.linalg.norm(drawn[pushed], axis=-1), np.linalg.norm(default[pushed], axis=-1),
                                   rtol=1e-6)  # fmt: skip
        angle = np.arctan2(drawn[pushed][:, 1], drawn[pushed][:, 0])
        behind = np.abs(angle) >= 0.75 * np.pi - 1e-6  # within 45 degrees of -x
        expected = share + (1.0 - share) * 0.25  # the cone is a quarter of every direction
        assert abs(behind.mean() - expected) < 4 * np.sqrt(expected * (1 - expected) / pushed.sum()) + 1e-9, share
    with pytest.raises(ValueError, match="backward_push_share must be in"):
        envs.RagdollStand(backward_push_share=1.5)


def test_the_kick_of_a_step_lands_on_the_torso_before_the_physics(stand):
    state, _, _ = stand.reset(jax.random.PRNGKey(3))
    state = dataclasses.replace(state, step=jnp.asarray(120, state.step.dtype))  # a push step
    key = jax.random.PRNGKey(4)
    kick = stand.kick(key, state.step)
    assert float(jnp.linalg.norm(kick)) >= 0.2
    kicked = stand.task_before_physics(state, jnp.zeros(26), key)
    expected = state.physics.vel.at[stand.torso].add(kick)
    np.testing.assert_array_equal(np.asarray(kicked.vel), np.asarray(expected))


def test_the_capture_term_is_the_squared_capture_point_offset_and_a_backward_push_makes_it_worse():
    """-w |xi - feet|^2 with xi = c + v / sqrt(g / c_z), computed here from the bodies in numpy; the
    build pose's centre of mass is 4.8 cm behind the feet's middle, so a kick from the front moves
    the capture point backwards, away from it, and one from behind brings it nearer."""
    weight = 50.0
    shaped = envs.RagdollStand(capture_weight=weight)
    state, _, _ = shaped.reset(jax.random.PRNGKey(6))
    yaw = float(shaped.heading(state.physics))
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    mass = np.asarray(shaped.model.bodies.mass)

    def term(kick):
        vel = state.physics.vel.at[shaped.torso].add(jnp.asarray(kick, state.physics.vel.dtype))
        kicked = dataclasses.replace(state, physics=dataclasses.replace(state.physics, vel=vel))
        got = float(shaped.task_reward(state, jnp.zeros(26), kicked)["capture"])
        pos, v = np.asarray(state.physics.pos, np.float64), np.asarray(vel, np.float64)
        centre, velocity = mass @ pos / mass.sum(), mass @ v / mass.sum()
        xi = centre[:2] + velocity[:2] / np.sqrt(9.81 / centre[2])
        feet = 0.5 * (pos[shaped.feet[0], :2] + pos[shaped.feet[1], :2])
        np.testing.assert_allclose(got, -weight * np.sum((xi - feet) ** 2), rtol=1e-4)
        return got, (xi - feet) @ forward[:2]

    at_rest, along = term(np.zeros(3))
    assert -0.05 < along < -0.045  # the build pose's centre of mass, 4.8 cm behind the feet's middle
    pushed_forward, along_forward = term(0.4 * forward)  # a kick from behind
    pushed_backward, along_backward = term(-0.4 * forward)
    # The kick changes the centre of mass's velocity by the torso's share of it, the capture point
    # by that over omega, along the heading.
    centre_height = mass @ np.asarray(state.physics.pos, np.float64)[:, 2] / mass.sum()
    share_over_omega = mass[shaped.torso] / mass.sum() * 0.4 / np.sqrt(9.81 / centre_height)
    np.testing.assert_allclose([along_forward - along, along - along_backward], share_over_omega, rtol=1e-3)
    assert pushed_backward < at_rest < pushed_forward < 0.0
    # The registered task: the term is exactly zero, and the other terms are those of the shaped task.
    kicked = dataclasses.replace(state, physics=dataclasses.replace(state.physics, vel=state.physics.vel + 0.1))
    plain, with_capture = (task.task_reward(state, jnp.zeros(26), kicked) for task in (envs.RagdollStand(), shaped))
    assert float(plain["capture"]) == 0.0 and float(with_capture["capture"]) < 0.0
    for name in ("alive", "upright", "height", "drift", "smooth"):
        assert float(plain[name]) == float(with_capture[name]), name
    with pytest.raises(ValueError, match="capture_weight must be finite and >= 0"):
        envs.RagdollStand(capture_weight=-1.0)


def test_the_bounded_capture_term_is_the_quadratic_near_the_feet_and_never_below_its_floor():
    """With capture_scale s the term is -w s^2 (1 - exp(-d^2 / s^2)) of the same offset d: within
    2% of -w d^2 at the build pose (d = 4.8 cm, s = 30 cm), at most -w s^2 however hard the kick,
    and a harder kick still costs more (it saturates, it does not turn)."""
    weight, scale = 50.0, 0.3
    quadratic = envs.RagdollStand(capture_weight=weight)
    bounded = envs.RagdollStand(capture_weight=weight, capture_scale=scale)
    state, _, _ = quadratic.reset(jax.random.PRNGKey(6))
    yaw = float(quadratic.heading(state.physics))
    forward = jnp.asarray([np.cos(yaw), np.sin(yaw), 0.0], state.physics.vel.dtype)

    def terms(speed):
        vel = state.physics.vel.at[quadratic.torso].add(-speed * forward)  # a kick from the front
        kicked = dataclasses.replace(state, physics=dataclasses.replace(state.physics, vel=vel))
        squared = float(jnp.sum(quadratic.capture_offset(kicked.physics) ** 2))
        plain, saturating = (float(task.task_reward(state, jnp.zeros(26), kicked)["capture"])
                             for task in (quadratic, bounded))  # fmt: skip
        np.testing.assert_allclose(plain, -weight * squared, rtol=1e-5)
        np.testing.assert_allclose(saturating, -weight * scale**2 * (1.0 - np.exp(-squared / scale**2)), rtol=1e-5)
        return squared, plain, saturating

    squared, plain, saturating = terms(0.0)
    assert 0.045**2 < squared < 0.05**2 and abs(saturating / plain - 1.0) < 0.02
    costs = [terms(speed) for speed in (1.0, 3.0, 10.0)]
    assert all(plain < -weight * scale**2 for _, plain, _ in costs[1:])  # the unbounded term passes the floor
    saturating = [cost[2] for cost in costs]
    assert -weight * scale**2 < saturating[2] < saturating[1] < saturating[0] < 0.0
    assert saturating[2] < -0.99 * weight * scale**2
    for bad in (0.0, -0.1, float("inf")):
        with pytest.raises(ValueError, match="capture_scale must be None or finite and > 0"):
            envs.RagdollStand(capture_weight=weight, capture_scale=bad)


def test_a_push_schedule_that_is_not_known_is_refused():
    with pytest.raises(ValueError, match="push_schedule must be one of"):
        envs.RagdollStand(push_schedule="poisson")


def test_a_fall_ends_the_episode(stand):
    state, _, _ = stand.reset(jax.random.PRNGKey(5))
    assert not bool(stand.terminal(state))
    low = state.physics.pos.at[:, 2].add(-(stand.rest_height - 0.9 * stand.fall_height))
    fallen = dataclasses.replace(state, physics=dataclasses.replace(state.physics, pos=low))
    assert bool(stand.terminal(fallen))


def test_track_reference_stays_in_range_and_its_rate_is_its_derivative(track):
    times = jnp.linspace(0.0, track.period, 97)
    target, rate = jax.vmap(track.reference)(times)
    low, high = track.control_low, track.control_high
    assert np.all(np.asarray(target) >= low - 1e-6) and np.all(np.asarray(target) <= high + 1e-6)
    derivative = jax.vmap(jax.jacfwd(lambda t: track.reference(t)[0]))(times)  # d q_ref / dt by autodiff
    np.testing.assert_allclose(np.asarray(rate), np.asarray(derivative), rtol=1e-6, atol=1e-6)
    controls = track.doll.controls
    half = jax.vmap(track.reference)(times + track.period / 2)[0]
    for left, right in (("knee_l", "knee_r"), ("hip_l", "hip_r"), ("elbow_l", "elbow_r")):
        np.testing.assert_allclose(
            np.asarray(target[:, controls[right]]), np.asarray(half[:, controls[left]]), atol=1e-5
        )
    assert float(jnp.ptp(target[:, controls["knee_l"]])) > 1.0  # the legs do march


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["dbdjax/RagdollStand-v0", "dbdjax/RagdollTrack-v0"])
def test_check_env_passes_for_the_ragdoll_envs(env_id):
    env = gym.make(env_id, jit_options=QUICK)
    check_env(env.unwrapped)
    frame = env.unwrapped.spec.make(render_mode="rgb_array", jit_options=QUICK)
    frame.reset(seed=0)
    first = frame.render()
    for _ in range(5):
        frame.step(frame.action_space.sample())
    later = frame.render()
    assert first.shape == (240, 320, 3) and first.dtype == np.uint8
    assert first.std() > 10  # not blank
    assert np.abs(first.astype(int) - later.astype(int)).max() > 50  # the doll moved


def test_the_standing_doll_holds_a_forward_ankle_lean_at_the_env_physics():
    """The ankles carry the doll on two light feet; at 2 substeps x 8 iterations the solver left
    them about ten times softer than their stiffness, and a 0.036 rad lean (centre of mass 4 cm
    forward) sagged to 0.1 rad and toppled the doll (envs/ragdoll_envs.py). At the env's physics the
    lean holds: the doll stands 5 s and the ankles stay within 0.02 rad of their target."""
    task = envs.RagdollStand(push_interval=None)
    ankles = jnp.array([task.doll.controls["ankle_l"].start, task.doll.controls["ankle_r"].start])
    lean = -0.045  # action: -0.036 rad on both ankles, ramped in over 1 s

    @quick_jit
    def run(key):
        state, _, _ = task.reset(key)

        def body(carry, t):
            state, fell = carry
            action = jnp.zeros(task.action_size).at[ankles].set(lean * jnp.minimum(1.0, (t + 1.0) / 30.0))
            state, _, _, terminated, _, _ = task.step(state, action)
            return (state, fell | terminated), None

        (state, fell), _ = jax.lax.scan(body, (state, False), jnp.arange(150.0))
        return fell, task.joints(state.physics)[0][ankles], task.pelvis_height(state)

    fell, angles, height = run(jax.random.PRNGKey(0))
    target = float(task.control(jnp.zeros(task.action_size).at[ankles].set(lean))[ankles[0]])
    assert target == pytest.approx(-0.036, abs=1e-6)
    assert not bool(fell) and float(height) > 0.97 * task.rest_height
    np.testing.assert_allclose(np.asarray(angles), target, atol=0.02)
