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


# Measured by `python -m dbdjax.training.sb3_ppo --timesteps 20480 --eval-every 10240 --seeds 0 1 2`
# (benchmarks/results/sb3_ik_chain.json), 200 fixed evaluation episodes, deterministic policy:
# untrained, every seed succeeds in 0 of 200 (its mean action is ~0: the chain held straight) with a
# median final distance of 0.51 m; after 20,480 steps seeds 0 / 1 / 2 succeed in 0.15 / 0.05 / 0.12
# (median distance 0.117 / 0.134 / 0.107 m). The margin is the lowest seed's rate less two binomial
# standard errors (0.05 - 2 sqrt(0.05 x 0.95 / 200) = 0.019), rounded down; the distance must at
# least halve (it fell to 0.21-0.26 of the untrained one).
TIMESTEPS = 20_480
EPISODES = 200
MARGIN = 0.015


def test_ppo_raises_the_success_rate_over_the_untrained_policy():
    result = sb3_ppo.run(timesteps=TIMESTEPS, seed=0, n_envs=4, episodes=EPISODES)
    before, after = result["before"], result["after"]
    assert result["timesteps"] == TIMESTEPS
    assert after["success_rate"] - before["success_rate"] >= MARGIN, (before["success_rate"], after["success_rate"])
    assert after["final_distance_m"]["median"] < 0.5 * before["final_distance_m"]["median"]
