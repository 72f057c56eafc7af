"""Gymnasium environments of dbdjax (`import dbdjax.envs` registers them).

    import gymnasium as gym
    import dbdjax.envs

    env = gym.make("dbdjax/IKChainReach-v0")                       # one env, JAX arrays out
    envs = gym.make_vec("dbdjax/IKChainReach-v0", num_envs=1024,
                        vectorization_mode="vector_entry_point")     # one jitted call per step

Every task is a pure functional core (`core.DbdFuncEnv`, a Gymnasium FuncEnv: `reset(key)`,
`step(state, action)`, jit/vmap/grad-able) with two Gymnasium faces (`wrappers.DbdEnv`,
`wrappers.DbdVectorEnv`) and a Brax face (`brax_adapter.BraxEnv`). The conventions (action
scaling and clipping, NaN handling, seeding, autoreset) are in the docstrings of `core` and
`wrappers`; each task's observation, reward and termination in its class docstring.
"""

from __future__ import annotations

import gymnasium

from dbdjax.envs.core import DbdFuncEnv, EnvState, seed_key
from dbdjax.envs.ik_chain import IKChainReach, IKChainReachEnv, IKChainReachVectorEnv, evaluate_expert, expert_action
from dbdjax.envs.ragdoll_envs import RagdollEnv, RagdollStand, RagdollTrack
from dbdjax.envs.wrappers import DbdEnv, DbdVectorEnv

# id -> the task class (the functional core)
TASKS = {
    "dbdjax/IKChainReach-v0": IKChainReach,
    "dbdjax/RagdollStand-v0": RagdollStand,
    "dbdjax/RagdollTrack-v0": RagdollTrack,
}

# id -> (single-env entry point, vector entry point, max_episode_steps)
ENVIRONMENTS = {
    "dbdjax/IKChainReach-v0": (
        "dbdjax.envs.ik_chain:IKChainReachEnv",
        "dbdjax.envs.ik_chain:IKChainReachVectorEnv",
        IKChainReach.default_max_episode_steps,
    ),
    "dbdjax/RagdollStand-v0": (
        "dbdjax.envs.ragdoll_envs:RagdollStandEnv",
        "dbdjax.envs.ragdoll_envs:RagdollStandVectorEnv",
        RagdollEnv.default_max_episode_steps,
    ),
    "dbdjax/RagdollTrack-v0": (
        "dbdjax.envs.ragdoll_envs:RagdollTrackEnv",
        "dbdjax.envs.ragdoll_envs:RagdollTrackVectorEnv",
        RagdollEnv.default_max_episode_steps,
    ),
}


def register_all() -> None:
    """Register every dbdjax environment with Gymnasium (once; `import dbdjax.envs` does it).

    The single envs return JAX arrays, so Gymnasium's passive checker (which expects numpy) is
    disabled for them, as for Gymnasium's own JAX envs; `check_env` wraps them in JaxToNumpy.
    """
    for env_id, (entry_point, vector_entry_point, max_episode_steps) in ENVIRONMENTS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point=entry_point,
            vector_entry_point=vector_entry_point,
            max_episode_steps=max_episode_steps,
            disable_env_checker=True,
        )


register_all()

__all__ = [
    "ENVIRONMENTS",
    "TASKS",
    "DbdEnv",
    "DbdFuncEnv",
    "DbdVectorEnv",
    "EnvState",
    "IKChainReach",
    "IKChainReachEnv",
    "IKChainReachVectorEnv",
    "RagdollEnv",
    "RagdollStand",
    "RagdollTrack",
    "evaluate_expert",
    "expert_action",
    "register_all",
    "seed_key",
]
