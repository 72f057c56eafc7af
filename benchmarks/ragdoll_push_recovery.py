"""Can the ragdoll of dbdjax/RagdollStand-v0 survive its pushes without stepping? Measurements of
the build pose (action 0, every drive holding the standing pose) and the capture-point bound.

1. The support: the feet are capsules whose flat bottom runs from `heel` to `toe` (m, along the
   foot, from the ankle); the centre of mass (COM) of the standing doll and its height; the share
   of the mass in the torso (a torso kick dv changes the whole-body COM velocity by share x dv).
   Capture point of the linear inverted pendulum: with feet in place, a COM velocity v towards an
   edge d away can be stopped only if v <= omega d, omega = sqrt(g / COM height); the largest
   kick so absorbed is omega d / share.
2. One kick of each speed in each of 8 directions (relative to the heading) at step 30, no other
   pushes, 150 steps: who falls, and when.
3. Ankle targets (a lean) with no pushes, 150 steps: the COM's forward position and who falls.
4. The env's own random pushes (every 2 s on average) of several speed ranges, 32 episodes of
   300 steps: the fraction that survives the whole episode.
5. The solver budget: an ankle lean of -0.036 rad ramped in over 1 s, no pushes, 150 steps, at
   several substeps x iterations: where the ankles end and whether the doll stands (at 2 x 8 the
   ankles sag to -0.1 rad and it falls: README, "The solver budget sets the ankles' stiffness").
6. Ramped ankle leans under the env's pushes, 48 episodes of 300 steps, at two budgets.

    python benchmarks/ragdoll_push_recovery.py [--out benchmarks/results/ragdoll_push_recovery.json]
    python benchmarks/ragdoll_push_recovery.py --only budgets ramped   # sections 5 and 6 alone
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dbdjax as dbd
from dbdjax import ragdoll
from dbdjax.envs import RagdollStand
from dbdjax.envs.core import yaw_rotate_inverse

GRAVITY = 9.81


def support(task: RagdollStand) -> dict:
    """Feet, COM and the capture-point bounds of the build pose."""
    physics = dbd.init(task.model)
    mass = np.asarray(task.model.bodies.mass)[: physics.pos.shape[0]]
    com = (mass[:, None] * np.asarray(physics.pos)).sum(0) / mass.sum()
    foot = next(part for part in ragdoll.PARTS if part.name == "foot_l")
    heel = foot.start[0] + foot.radius  # the flat bottom of the capsule: its axis between the cap centres
    toe = foot.end[0] - foot.radius
    half_width = abs(foot.start[1])  # the feet's contact lines are at y = +-0.09 m
    omega = float(np.sqrt(GRAVITY / com[2]))
    share = float(mass[task.torso] / mass.sum())

    def largest_kick(d: float) -> float:
        return omega * d / share

    centred = 0.5 * (toe - heel)
    return {
        "heel_x_m": heel, "toe_x_m": toe, "feet_half_width_m": half_width, "com_m": com.tolist(),
        "omega_per_s": omega, "torso_mass_share": share,
        "largest_kick_without_stepping_m_per_s": {
            "build pose, backwards": largest_kick(float(com[0]) - heel),
            "build pose, forwards": largest_kick(toe - float(com[0])),
            "COM centred over the foot, forwards or backwards": largest_kick(centred),
            "sideways (feet at +-0.09 m)": largest_kick(half_width),
        },
    }  # fmt: skip


def single_kicks(task: RagdollStand, speeds, directions, steps: int = 150, at: int = 30) -> dict:
    speed, direction = (x.ravel() for x in np.meshgrid(speeds, directions, indexing="ij"))
    n = len(speed)

    @dbd.jit
    def run(key):
        state, _, _ = jax.vmap(task.reset)(jnp.broadcast_to(key, (n, 2)))
        yaw = jax.vmap(task.heading)(state.physics)

        def body(carry, t):
            state, alive, length = carry
            angle = yaw + direction
            kick = (
                jnp.where(t == at, 1.0, 0.0)
                * speed[:, None]
                * jnp.stack([jnp.cos(angle), jnp.sin(angle), 0 * angle], -1)
            )
            physics = state.physics
            physics = dataclasses.replace(physics, vel=physics.vel.at[:, task.torso].add(kick))
            state, _, _, terminated, _, _ = jax.vmap(task.step)(dataclasses.replace(state, physics=physics),
                                                                 jnp.zeros((n, 26)))  # fmt: skip
            return (state, alive & ~terminated, length + alive), None

        start = (state, jnp.ones(n, bool), jnp.zeros(n, jnp.int32))
        (_, alive, length), _ = jax.lax.scan(body, start, jnp.arange(steps))
        return alive, length

    alive, length = (np.asarray(x).reshape(len(speeds), len(directions)) for x in run(jax.random.PRNGKey(0)))
    return {"speeds_m_per_s": list(speeds), "directions_deg": np.degrees(directions).round().tolist(),
            "kick_at_step": at, "steps": steps, "survived": alive.astype(int).tolist(),
            "steps_standing": length.tolist()}  # fmt: skip


def leans(task: RagdollStand, ankle_targets, steps: int = 150) -> dict:
    n = len(ankle_targets)
    actions = np.zeros((n, 26), np.float32)
    for name in ("ankle_l", "ankle_r"):
        entry = task.doll.controls[name].start
        actions[:, entry] = np.asarray(ankle_targets) / task.control_scale[entry]
    mass = jnp.asarray(task.model.bodies.mass)

    @dbd.jit
    def run(key):
        state, _, _ = jax.vmap(task.reset)(jnp.broadcast_to(key, (n, 2)))
        yaw = jax.vmap(task.heading)(state.physics)

        def body(carry, _):
            state, alive = carry
            state, _, _, terminated, _, _ = jax.vmap(task.step)(state, jnp.asarray(actions))
            weights = mass[: state.physics.pos.shape[1]]
            com = jnp.sum(weights[None, :, None] * state.physics.pos, 1) / jnp.sum(weights)
            return (state, alive & ~terminated), (yaw_rotate_inverse(yaw, com)[:, 0], alive)

        _, (com_x, alive) = jax.lax.scan(body, (state, jnp.ones(n, bool)), None, length=steps)
        return com_x, alive

    com_x, alive = (np.asarray(x) for x in run(jax.random.PRNGKey(0)))
    return {"ankle_target_rad": list(ankle_targets), "steps": steps,
            "com_forward_m_at_steps": {str(k): com_x[k].round(3).tolist() for k in (10, 30, 60, 149)},
            "survived": alive[-1].astype(int).tolist()}  # fmt: skip


def random_pushes(speed_ranges, episodes: int = 32, steps: int = 300) -> list[dict]:
    rows = []
    for low, high in speed_ranges:
        task = RagdollStand(max_episode_steps=steps, push_speed=(low, high), push_interval=2.0 if high > 0 else None)

        @dbd.jit
        def run(keys, task=task):
            state, _, _ = jax.vmap(task.reset)(keys)

            def body(carry, _):
                state, alive, length = carry
                state, _, _, terminated, _, _ = jax.vmap(task.step)(state, jnp.zeros((episodes, 26)))
                return (state, alive & ~terminated, length + alive), None

            start = (state, jnp.ones(episodes, bool), jnp.zeros(episodes, jnp.int32))
            (_, alive, length), _ = jax.lax.scan(body, start, None, length=steps)
            return alive, length

        alive, length = (np.asarray(x) for x in run(jax.random.split(jax.random.PRNGKey(1), episodes)))
        rows.append({"push_speed_m_per_s": [low, high], "push_interval_s": 2.0 if high > 0 else None,
                     "survival": float(alive.mean()), "mean_steps": float(length.mean())})  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def ramped_lean_episodes(ankle_action: np.ndarray, episodes: int, steps: int, ramp: int = 30, **env_kwargs) -> dict:
    """RagdollStand (default pushes, `env_kwargs` for the physics) with the build pose plus one ankle
    action per row, ramped in linearly over `ramp` steps and then held; `episodes` episodes (seed 1)
    per row. Returns per row: the final ankle angles (rad, mean of both ankles, fallen episodes
    included), the survival and the mean episode length."""
    task = RagdollStand(max_episode_steps=steps, **env_kwargs)
    ankles = np.array([task.doll.controls[name].start for name in ("ankle_l", "ankle_r")])
    rows = len(ankle_action)
    per_episode = jnp.repeat(jnp.asarray(ankle_action, jnp.float32), episodes)
    keys = jnp.tile(jax.random.split(jax.random.PRNGKey(1), episodes), (rows, 1))

    @dbd.jit
    def run(keys):
        state, _, _ = jax.vmap(task.reset)(keys)

        def body(carry, t):
            state, alive, length = carry
            lean = per_episode * jnp.minimum(1.0, (t + 1.0) / ramp)
            action = jnp.zeros((len(per_episode), task.action_size)).at[:, ankles].set(lean[:, None])
            state, _, _, terminated, _, _ = jax.vmap(task.step)(state, action)
            return (state, alive & ~terminated, length + alive), None

        start = (state, jnp.ones(len(per_episode), bool), jnp.zeros(len(per_episode), jnp.int32))
        (state, alive, length), _ = jax.lax.scan(body, start, jnp.arange(steps, dtype=jnp.float32))
        angles = jax.vmap(task.joints)(state.physics)[0][:, ankles].mean(-1)
        return angles, alive, length

    angles, alive, length = (np.asarray(x).reshape(rows, episodes) for x in run(keys))
    return {"ankle_action": [float(a) for a in ankle_action],
            "ankle_target_rad": [float(a * task.control_scale[ankles[0]]) for a in ankle_action],
            "ankle_angle_rad": angles.mean(1).round(4).tolist(), "survived": alive.sum(1).tolist(),
            "episodes": episodes, "mean_steps": length.mean(1).round(1).tolist()}  # fmt: skip


def solver_budgets(budgets, ankle_action: float = -0.045) -> list[dict]:
    """Section 5: one ramped lean with no pushes, 150 steps, at each (substeps, iterations)."""
    rows = []
    for substeps, iterations in budgets:
        row = ramped_lean_episodes(np.array([ankle_action]), 1, 150, push_interval=None, substeps=substeps,
                                   iterations=iterations)  # fmt: skip
        rows.append({"substeps": substeps, "iterations": iterations, "sweeps_per_step": substeps * iterations,
                     "ankle_target_rad": row["ankle_target_rad"][0], "stood_150_steps": bool(row["survived"][0]),
                     # where the ankles ended: meaningless once the doll lies on the floor
                     "ankle_angle_rad": row["ankle_angle_rad"][0] if row["survived"][0] else None})  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "ragdoll_push_recovery.json"))
    parser.add_argument(
        "--only",
        nargs="+",
        choices=["support", "kicks", "leans", "pushes", "budgets", "ramped"],
        help="run these sections alone (default: all)",
    )
    args = parser.parse_args()
    sections = set(args.only or ["support", "kicks", "leans", "pushes", "budgets", "ramped"])
    start = time.perf_counter()
    task = RagdollStand(max_episode_steps=300, push_interval=None)
    result = {"env_substeps": task.model.options.substeps, "env_iterations": task.model.options.iterations}
    if "support" in sections:
        result["support"] = support(task)
        print(json.dumps(result["support"], indent=1), flush=True)
    if "kicks" in sections:
        result["single_kicks"] = single_kicks(task, np.array([0.3, 0.6, 1.0, 1.5]), np.arange(8) * np.pi / 4)
        print(result["single_kicks"], flush=True)
    if "leans" in sections:
        result["leans"] = leans(task, [-0.1, -0.05, -0.025, 0.0, 0.025, 0.05])
        print(result["leans"], flush=True)
    if "pushes" in sections:
        result["random_pushes"] = random_pushes([(0.0, 0.0), (0.3, 0.6), (0.5, 1.5)])
    if "budgets" in sections:
        result["solver_budgets"] = solver_budgets([(2, 8), (4, 4), (3, 8), (4, 6), (2, 16), (4, 8), (8, 4), (2, 32),
                                                   (8, 8)])  # fmt: skip
    if "ramped" in sections:
        result["ramped_leans_under_pushes"] = []
        for substeps in (2, 4):
            row = ramped_lean_episodes(np.array([0.0, -0.01, -0.02, -0.03, -0.045, -0.06, -0.08]), 48, 300,
                                       substeps=substeps, iterations=8)  # fmt: skip
            result["ramped_leans_under_pushes"].append(dict(row, substeps=substeps, iterations=8))
            print(result["ramped_leans_under_pushes"][-1], flush=True)
    result["wall_s"] = time.perf_counter() - start
    result["load_average_at_end"] = list(os.getloadavg())
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out} ({result['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
