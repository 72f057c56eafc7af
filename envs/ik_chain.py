"""dbdjax/IKChainReach-v0: an N-link 3D chain of driven hinges reaches for a random point.

The expert baseline is inverse kinematics by displacement-based dynamics (`dbdjax.ik`, DBD
section 11): `expert_action` solves for the joint angles that put the tip on the goal and sends
them as the drive targets; `evaluate_expert` measures how often and how fast that succeeds.
"""

from __future__ import annotations

import functools
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode

import dbdjax as dbd
from dbdjax import host_math, ik, math
from dbdjax.envs.core import DbdFuncEnv, EnvState, joint_coordinates
from dbdjax.envs.wrappers import DbdEnv, DbdVectorEnv


class ReachTask(NamedTuple):
    """Task variables of IKChainReach: goal (3,) m, world."""

    goal: jnp.ndarray


class IKChainReach(DbdFuncEnv):
    """Reach a random point with the tip of an N-link 3D chain of driven hinges.

    Model: `num_links` links of `link_length` m and `link_mass` kg (capsules of `link_radius`,
    slender-rod inertia) in series from a world anchor at the origin, straight along +x in the
    build pose. The hinge axes alternate z, y, z, y, ... (yaw, pitch, ...: the tip reaches a 3D
    workspace). Every hinge has limits +-`joint_range` rad and a torque-limited drive (DBD section
    9: `drive_stiffness` N m/rad, `drive_damping` N m s/rad, `max_torque` N m). No self-collision
    (the links may pass through each other, as in Gymnasium's Reacher). `gravity` defaults to 0:
    the arm is gravity-compensated, as a robot arm's controller would make it; with gravity on,
    position drives sag by torque / stiffness and 1 cm becomes much harder for the expert.
    Physics: dt = 1/60 s, `substeps` 4, `iterations` 16, `frame_skip` 2 (the env runs at 30 Hz).
    The solver budget is what makes the drives track: at 2 substeps x 8 iterations a held IK
    target is within 1 cm in 44% of episodes after 3.3 s, at 4 x 16 in all of them (16 episodes).

    Action (num_links,) in [-1, 1]: the hinge drive targets, a * joint_range rad (clipped to the
    box; a NaN/inf entry ends the episode with info["nonfinite_action"]).

    Observation (3 num_links + 9,) float32: cos and sin of the hinge angles (num_links each), their
    rates (rad/s), the tip position, the goal position and goal - tip (m, relative to the anchor).

    Episode start: hinge angles uniform in +-`start_range` x joint_range, at rest; the goal is
    the tip position at angles uniform in +-`goal_range` x joint_range, so it is reachable.

    Reward per step = progress + effort, with d the tip-goal distance (m) and L the chain's reach:
      progress = `progress_weight` (d_before - d_after) / L  (telescopes: an episode earns
                 progress_weight (d_0 - d_T) / L),
      effort   = -`effort_weight` mean(a^2)  (like Reacher's control cost).
    info["is_success"]: d < `success_distance` (1 cm); info["distance"]: d. Success does not end
    the episode (the policy should hold the goal). Termination: only a non-finite action or
    physics state (info flags). Truncation: `max_episode_steps` (100 when registered, 3.3 s).

    `joint="ball"`: unlimited ball joints instead (3 drive targets each, a rotation vector in the
    parent's frame, each component a * joint_range; action and angles (3 num_links,)).

    Sensitivity (an engine issue, reported): with driven hinges one physics step amplifies
    rounding. Moving one link by 1e-9 m changes the angular velocities after a step by up to tens
    of rad/s at the default 4 substeps x 16 iterations (float64 too). It grows with the iterations
    (5-hinge chain, 1 substep, float64: 2.6e-6 rad/s at 8 iterations, 4e-5 at 32 with damping 30,
    3.4 at 32 without damping), is 1e-7 without drives, and is absent with driven ball joints
    (7e-8 at 32 iterations): the hinge's axle-alignment row takes its direction from a normalised
    cross product of nearly parallel axes. So trajectories are reproducible for one compiled
    program and seed, two differently compiled programs (another XLA optimisation level, eager vs
    jit) drift apart within a step, and the gradient of a hinge chain's return over 8 steps
    overflows float32; the ball-joint chain's is finite.

    Expert baseline (`evaluate_expert`, `benchmarks/ik_chain_expert.py`): the DBD IK solution
    (32 updates from the measured angles, every step) as the action. Measured on this repository's
    2-core CPU, 256 episodes, seed 0, default env: see README "IKChainReach-v0" for the numbers.
    """

    reward_terms = ("progress", "effort")
    default_max_episode_steps = 100

    def __init__(
        self,
        num_links: int = 5,
        joint: str = "hinge",
        link_length: float = 0.3,
        link_mass: float = 1.0,
        link_radius: float = 0.04,
        joint_range: float = 2.0,
        drive_stiffness: float = 300.0,
        drive_damping: float = 30.0,
        max_torque: float = 200.0,
        gravity: float = 0.0,
        start_range: float = 0.3,
        goal_range: float = 0.8,
        success_distance: float = 0.01,
        progress_weight: float = 10.0,
        effort_weight: float = 0.01,
        dt: float = 1.0 / 60.0,
        substeps: int = 4,
        iterations: int = 16,
        frame_skip: int = 2,
        max_episode_steps: int | None = None,
    ):
        config = dict(
            num_links=num_links, joint=joint, link_length=link_length, link_mass=link_mass, link_radius=link_radius,
            joint_range=joint_range, drive_stiffness=drive_stiffness, drive_damping=drive_damping,
            max_torque=max_torque, gravity=gravity, start_range=start_range, goal_range=goal_range,
            success_distance=success_distance, progress_weight=progress_weight, effort_weight=effort_weight,
            dt=dt, substeps=substeps, iterations=iterations, frame_skip=frame_skip,
            max_episode_steps=max_episode_steps,
        )  # fmt: skip
        if not isinstance(num_links, (int, np.integer)) or num_links < 1:
            raise ValueError(f"IKChainReach: num_links must be a positive integer, got {num_links!r}")
        if joint not in ("hinge", "ball"):
            raise ValueError(f"IKChainReach: joint must be 'hinge' or 'ball', got {joint!r}")
        if not 0.0 < joint_range <= np.pi:
            raise ValueError(f"IKChainReach: joint_range must be in (0, pi], got {joint_range!r}")
        for what, value in (("start_range", start_range), ("goal_range", goal_range)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"IKChainReach: {what} must be in [0, 1] (a fraction of joint_range), got {value!r}")
        n = int(num_links)
        builder = dbd.ModelBuilder(gravity=(0.0, 0.0, -float(gravity)))
        inertia_across = link_mass * link_length**2 / 12.0
        along_x = host_math.z_to(np.array([1.0, 0.0, 0.0]))  # capsules lie along local z
        bodies, joints = [], []
        for k in range(n):
            body = builder.add_body(
                pos=((k + 0.5) * link_length, 0.0, 0.0),
                mass=link_mass,
                inertia=(link_mass * link_radius**2 / 2.0, inertia_across, inertia_across),
                name=f"link {k}",
            )
            # Visual only (contype = conaffinity = 0): no contact slots, so no self-collision.
            builder.add_capsule(body, link_radius, link_length / 2.0 - link_radius, quat=along_x,
                                contype=0, conaffinity=0)  # fmt: skip
            axis = (0.0, 0.0, 1.0) if k % 2 == 0 else (0.0, 1.0, 0.0)
            parent = dbd.WORLD if k == 0 else bodies[-1]
            anchor = (k * link_length, 0.0, 0.0)
            if joint == "hinge":
                index = builder.add_hinge_joint(parent, body, anchor=anchor, axis=axis,
                                                limits=(-joint_range, joint_range), name=f"hinge {k}")  # fmt: skip
            else:  # unlimited (the IK chain takes no cone or twist limits); the targets are bounded
                index = builder.add_ball_joint(parent, body, anchor=anchor, name=f"ball {k}")
            builder.add_drive(index, drive_stiffness, drive_damping, max_torque)
            bodies.append(body)
            joints.append(index)
        dofs = n if joint == "hinge" else 3 * n
        builder.set_control_range(slice(0, dofs), -joint_range, joint_range)
        model = builder.finalize(dt=dt, substeps=substeps, iterations=iterations)
        # For pictures only: the same chain and a free marker body whose sphere shows the goal.
        marker = builder.add_body(pos=(0.0, 0.0, 0.0), mass=1.0, inertia=(1.0, 1.0, 1.0), name="goal")
        builder.add_sphere(marker, 2.0 * link_radius, contype=0, conaffinity=0)
        self.render_model = builder.finalize(dt=dt, substeps=substeps, iterations=iterations)

        self.num_links = n
        self.joint = joint
        self.num_dofs = dofs
        self.joints = tuple(joints)
        self.bodies = tuple(bodies)
        self.link_length = float(link_length)
        self.joint_range = float(joint_range)
        self.tip_local = np.array([link_length / 2.0, 0.0, 0.0])  # end of the last link, its frame
        self.reach = float(n * link_length)
        self.start_range = float(start_range)
        self.goal_range = float(goal_range)
        self.success_distance = float(success_distance)
        self.progress_weight = float(progress_weight)
        self.effort_weight = float(effort_weight)
        # The IK description of the same chain (DBD section 11): angles = hinge drive targets.
        self.chain = ik.Chain.from_model(model, bodies[-1], tip=tuple(self.tip_local))
        super().__init__(
            model,
            control_low=np.full(dofs, -joint_range),
            control_high=np.full(dofs, joint_range),
            frame_skip=frame_skip,
            max_episode_steps=max_episode_steps,
            config=config,
        )

    # ------------------------------------------------------------------------ kinematics
    def chain_state(self, angles: jnp.ndarray) -> dbd.State:
        """The physics State with the joints at `angles` (num_dofs,) rad, at rest."""
        chain = self.chain.astype(self.dtype)
        poses = ik.forward_kinematics(chain, jnp.asarray(angles, self.dtype))
        index = np.asarray(self.bodies)
        bodies = self.model.bodies
        pos = bodies.initial_pos.at[index].set(poses.origin)  # link frame = body frame, origin = com
        quat = bodies.initial_quat.at[index].set(poses.quat)
        zeros = jnp.zeros_like(pos)
        return dbd.State(pos=pos, quat=quat, vel=zeros, ang_vel=zeros)

    def tip(self, physics: dbd.State) -> jnp.ndarray:
        """(3,) m, world position of the chain's tip."""
        last = self.bodies[-1]
        return physics.pos[last] + math.quat_rotate(physics.quat[last], jnp.asarray(self.tip_local, physics.pos.dtype))

    def angles(self, physics: dbd.State) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Joint angles (rad) and rates (rad/s) in the drive-target layout, (num_dofs,) each."""
        return joint_coordinates(self.model, physics, self.joints, (self.joint,) * self.num_links)

    def distance(self, state: EnvState) -> jnp.ndarray:
        """() m, tip-goal distance."""
        return math.safe_norm(self.tip(state.physics) - state.task.goal)

    def render_scene(self, state: EnvState):
        """The chain and a sphere at the goal, from a fixed camera that frames the workspace."""
        from dbdjax import render  # noqa: PLC0415 (pictures are optional)

        physics = state.physics
        goal = state.task.goal[None]
        scene = dbd.State(
            pos=jnp.concatenate([physics.pos, goal]),
            quat=jnp.concatenate([physics.quat, math.quat_identity((1,)).astype(physics.quat.dtype)]),
            vel=jnp.concatenate([physics.vel, jnp.zeros_like(goal)]),
            ang_vel=jnp.concatenate([physics.ang_vel, jnp.zeros_like(goal)]),
        )
        camera = render.camera_looking_at((0.0, 0.0, 0.0), distance=2.6 * self.reach, azimuth=-60.0, elevation=30.0)
        return self.render_model, scene, {"camera": camera}

    # ------------------------------------------------------------------------ task hooks
    def task_initial(self, key: jnp.ndarray):
        start_key, goal_key = jax.random.split(key)
        limit = self.joint_range
        start = jax.random.uniform(start_key, (self.num_dofs,), self.dtype, -1.0, 1.0) * self.start_range * limit
        goal_angles = jax.random.uniform(goal_key, (self.num_dofs,), self.dtype, -1.0, 1.0) * self.goal_range * limit
        goal = ik.end_effector(self.chain.astype(self.dtype), goal_angles)
        return self.chain_state(start), ReachTask(goal=goal)

    def task_observation(self, state: EnvState) -> jnp.ndarray:
        angle, rate = self.angles(state.physics)
        tip = self.tip(state.physics)
        goal = state.task.goal
        return jnp.concatenate([jnp.cos(angle), jnp.sin(angle), rate, tip, goal, goal - tip])

    def task_reward(self, state: EnvState, action: jnp.ndarray, next_state: EnvState) -> dict[str, jnp.ndarray]:
        progress = self.distance(state) - self.distance(next_state)
        return {
            "progress": self.progress_weight * progress / self.reach,
            "effort": -self.effort_weight * jnp.mean(action**2),
        }

    def task_info(self, state: EnvState) -> dict[str, jnp.ndarray]:
        distance = self.distance(state)
        return {"distance": distance, "is_success": distance < self.success_distance}


# ---------------------------------------------------------------------------- the expert
def expert_action(env: IKChainReach, state: EnvState, iterations: int = 32, method: str = "dbd") -> jnp.ndarray:
    """(num_links,) the action whose drive targets are the IK solution for the goal.

    Solves `ik.solve(chain, measured angles, goal, method, iterations)` (DBD section 11; "pinv"
    for the pseudo-inverse) from the hinge angles the chain has now, and maps the solution to
    [-1, 1]. Pure: jit and vmap it over a batch of states.
    """
    angles, _ = env.angles(state.physics)
    solution = ik.solve(env.chain.astype(env.dtype), angles, state.task.goal, method=method, iterations=iterations)
    return env.action_of_control(solution)


def expert_rollout(env: IKChainReach, keys: jnp.ndarray, iterations: int = 32, method: str = "dbd", steps=None):
    """Episodes driven by `expert_action` from reset(keys[i]); keys (B, 2).

    Returns (distance (B, steps) m after each step, success (B, steps) bool, reward (B, steps)).
    """
    steps = steps or env.max_episode_steps or env.default_max_episode_steps

    def episode(key):
        state, _, _ = env.reset(key)

        def one(state, _):
            action = expert_action(env, state, iterations, method)
            state, _, reward, _, _, info = env.step(state, action)
            return state, (info["distance"], info["is_success"], reward)

        _, out = jax.lax.scan(one, state, None, length=steps)
        return out

    return jax.vmap(episode)(keys)


@functools.cache
def _compiled_rollout(env: IKChainReach, iterations: int, method: str, steps: int):
    return dbd.jit(functools.partial(expert_rollout, env, iterations=iterations, method=method, steps=steps))


def evaluate_expert(
    env: IKChainReach | None = None,
    episodes: int = 256,
    seed: int = 0,
    iterations: int = 32,
    method: str = "dbd",
    steps: int | None = None,
) -> dict[str, Any]:
    """Success rate and timing of the IK expert on `episodes` episodes (seeds from `seed`).

    Returns a dict: success_rate (tip within success_distance at the last step), ever_success_rate,
    time_to_success_s (median over the episodes that succeed, seconds of simulated time to the
    first success), final_distance_m (median, 90th percentile, max), mean_return, and wall-clock
    timings on this machine: compile_s, rollout_s (all episodes, batched), ik_solve_ms (one batched
    IK call for all episodes, the expert's per-step cost), env_steps_per_s.
    """
    env = env if env is not None else IKChainReach(max_episode_steps=IKChainReach.default_max_episode_steps)
    steps = steps or env.max_episode_steps or env.default_max_episode_steps
    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    rollout = _compiled_rollout(env, iterations, method, steps)
    start = time.perf_counter()
    compiled = rollout.lower(keys).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    distance, success, reward = jax.block_until_ready(compiled(keys))
    rollout_s = time.perf_counter() - start

    states = dbd.jit(jax.vmap(lambda key: env.reset(key)[0]))(keys)
    solve = dbd.jit(jax.vmap(functools.partial(expert_action, env, iterations=iterations, method=method)))
    jax.block_until_ready(solve(states))
    start = time.perf_counter()
    repeats = 5
    for _ in range(repeats):
        jax.block_until_ready(solve(states))
    ik_solve_ms = (time.perf_counter() - start) / repeats * 1e3

    distance, success, reward = np.asarray(distance), np.asarray(success), np.asarray(reward)
    ever = success.any(axis=1)
    first = np.argmax(success, axis=1)
    return {
        "episodes": episodes,
        "steps": steps,
        "method": method,
        "ik_iterations": iterations,
        "success_rate": float(success[:, -1].mean()),
        "ever_success_rate": float(ever.mean()),
        "time_to_success_s": float(np.median((first[ever] + 1) * env.dt)) if ever.any() else None,
        "final_distance_m": {
            "median": float(np.median(distance[:, -1])),
            "p90": float(np.percentile(distance[:, -1], 90)),
            "max": float(distance[:, -1].max()),
        },
        "mean_return": float(reward.sum(axis=1).mean()),
        "compile_s": compile_s,
        "rollout_s": rollout_s,
        "ik_solve_ms": ik_solve_ms,
        "env_steps_per_s": episodes * steps / rollout_s,
    }


# ---------------------------------------------------------------------------- Gymnasium entry points
class IKChainReachEnv(DbdEnv):
    """`gymnasium.make("dbdjax/IKChainReach-v0")`: one IKChainReach episode at a time.

    kwargs go to `IKChainReach` (max_episode_steps there defaults to None: the registered
    TimeLimit of 100 steps truncates)."""

    def __init__(self, render_mode: str | None = None, jit_options: dict | None = None, **kwargs):
        super().__init__(IKChainReach(**kwargs), render_mode=render_mode, jit_options=jit_options)


class IKChainReachVectorEnv(DbdVectorEnv):
    """`gymnasium.make_vec("dbdjax/IKChainReach-v0", num_envs, vectorization_mode="vector_entry_point")`."""

    def __init__(
        self,
        num_envs: int = 1,
        render_mode: str | None = None,
        max_episode_steps: int | None = IKChainReach.default_max_episode_steps,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        jit_options: dict | None = None,
        **kwargs,
    ):
        task = IKChainReach(max_episode_steps=max_episode_steps, **kwargs)
        super().__init__(task, num_envs, autoreset_mode, render_mode, jit_options)
