"""A real Gymnasium client: Stable-Baselines3 PPO on gymnasium.make("dbdjax/IKChainReach-v0").

Needs the `sb3` extra (torch, stable-baselines3), which CI does not install: skipped there.
All marked slow: compiling the env step alone takes ~20 s of CPU here, training a few minutes.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

pytestmark = pytest.mark.slow

pytest.importorskip("torch")
pytest.importorskip("stable_baselines3")

from stable_baselines3.common.env_checker import check_env as sb3_check_env  # noqa: E402

from dbdjax.training import sb3_ppo  # noqa: E402

# -O0 compiles the env step in a fraction of the time; these checks are about the API, not speed.
API_KWARGS = {**sb3_ppo.ENV_KWARGS, "jit_options": {"xla_backend_optimization_level": 0}}


@pytest.fixture(scope="module")
def sb3_env():
    env = sb3_ppo.make_env(API_KWARGS)
    yield env
    env.close()


def test_sb3_check_env_passes_on_the_env_sb3_trains(sb3_env):
    # SB3's checker asserts numpy observations in the observation space, Box actions in [-1, 1],
    # float rewards and bool flags, and that reset(seed=s) repeats; warnings are not failures.
    sb3_check_env(sb3_env, warn=False)


def test_sb3_env_gives_numpy_float32_observations_and_success_info(sb3_env):
    obs, info = sb3_env.reset(seed=3)
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float32
    assert sb3_env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = sb3_env.step(np.zeros(sb3_env.action_space.shape, np.float32))
    assert isinstance(obs, np.ndarray) and isinstance(reward, float)
    assert isinstance(terminated, bool) and isinstance(truncated, bool)
    # SB3's Monitor/logger reads info["is_success"] at the end of an episode.
    assert np.asarray(info["is_success"]).dtype == bool


def test_sb3_env_is_the_registered_gymnasium_env(sb3_env):
    assert sb3_env.unwrapped.spec.id == "dbdjax/IKChainReach-v0"
    assert sb3_env.unwrapped.func_env.num_links == sb3_ppo.ENV_KWARGS["num_links"]
    assert isinstance(sb3_env.unwrapped, gym.Env)


def test_ppo_raises_the_success_rate_over_the_untrained_policy():
    # 20,480 steps (20 rollouts of 4 x 256) evaluated on 200 fixed episodes, deterministic policy.
    # Measured (benchmarks/results/sb3_ik_chain.json, seeds 0-2): the untrained policy (its mean
    # action ~0: the chain held straight) succeeds in 0 of 200; after 20,480 steps MIN_AFTER..MAX_AFTER.
    # The margin is below the lowest seed's rise by more than 2 binomial standard errors.
    result = sb3_ppo.run(timesteps=20_480, seed=0, n_envs=4, episodes=200)
    before, after = result["before"], result["after"]
    assert after["success_rate"] - before["success_rate"] >= 0.05, (before["success_rate"], after["success_rate"])
    assert after["final_distance_m"]["median"] < 0.5 * before["final_distance_m"]["median"]
