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
4. The env's own pushes (every 2 s) of several speed ranges, 32 episodes of 300 steps: the
   fraction that survives the whole episode.
5. The solver budget: an ankle lean of -0.036 rad ramped in over 1 s, no pushes, 150 steps, at
   several substeps x iterations: where the ankles end and whether the doll stands (at 2 x 8 the
   ankles sag to -0.1 rad and it falls: docs/reinforcement_learning.md, "The solver budget sets the ankles' stiffness").
6. Ramped ankle leans under the env's pushes, 48 episodes of 300 steps, at two budgets.
7. The feet-in-place bound under the env's own push sequences: the capture point of an inverted
   pendulum (a point mass, and the rigid doll turning on its feet) kicked by each episode's pushes
   (the same episodes as `rl.evaluate`'s for a seed), driven back to the middle of the support as
   fast as a centre of pressure anywhere on the feet allows (an ideal ankle strategy), or steered
   knowing every kick in advance. The episodes the second loses are lost to any balance with the
   feet in place (to the pendulum's accuracy); the policies' falls are set beside both.

    python benchmarks/ragdoll_push_recovery.py [--out benchmarks/results/ragdoll_push_recovery.json]
    python benchmarks/ragdoll_push_recovery.py --only budgets ramped   # sections 5 and 6 (the file keeps the rest)
    python benchmarks/ragdoll_push_recovery.py --only capture --compare benchmarks/results/ppo_*.json

`--push-schedule` (regular, the env's default since session 43, or random) sets the env's pushes
of sections 4, 6 and 7; the results kept from before session 43 are of the random schedule (each
section's rows say which, where recorded).
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
from dbdjax import diagnostics, ragdoll
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

    @dbd.jit
    def run(key):
        state, _, _ = jax.vmap(task.reset)(jnp.broadcast_to(key, (n, 2)))
        yaw = jax.vmap(task.heading)(state.physics)

        def body(carry, _):
            state, alive = carry
            state, _, _, terminated, _, _ = jax.vmap(task.step)(state, jnp.asarray(actions))
            com, _ = dbd.diagnostics.centre_of_mass(task.model, state.physics)
            return (state, alive & ~terminated), (yaw_rotate_inverse(yaw, com)[:, 0], alive)

        _, (com_x, alive) = jax.lax.scan(body, (state, jnp.ones(n, bool)), None, length=steps)
        return com_x, alive

    com_x, alive = (np.asarray(x) for x in run(jax.random.PRNGKey(0)))
    return {"ankle_target_rad": list(ankle_targets), "steps": steps,
            "com_forward_m_at_steps": {str(k): com_x[k].round(3).tolist() for k in (10, 30, 60, 149)},
            "survived": alive[-1].astype(int).tolist()}  # fmt: skip


def env_pushes(speed_ranges, episodes: int = 32, steps: int = 300, push_schedule: str = "regular") -> list[dict]:
    rows = []
    for low, high in speed_ranges:
        task = RagdollStand(max_episode_steps=steps, push_speed=(low, high), push_interval=2.0 if high > 0 else None,
                            push_schedule=push_schedule)  # fmt: skip

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
                     "push_schedule": push_schedule,
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


def episode_kicks(task: RagdollStand, episodes: int, seed: int, steps: int, heading_error: float = 0.0) -> np.ndarray:
    """(episodes, steps, 2) m/s: the torso kick of every step of the episodes `rl.evaluate(task, ...,
    episodes, seed)` runs (the same keys), in the doll's starting heading frame (x forward, y
    left). The kicks come from the key chain alone, so they are the pushes of those episodes
    whatever the policy does (past a fall too); the doll's heading is taken as the one it starts
    with (it turns little while it stands), plus `heading_error` rad to see what that costs."""

    @jax.jit
    def run(keys):
        def one(key):
            state, _, _ = task.reset(key)

            def body(key, step):
                key, step_key = jax.random.split(key)
                return key, task.kick(step_key, step)

            _, kicks = jax.lax.scan(body, state.key, jnp.arange(steps))
            return yaw_rotate_inverse(task.heading(state.physics) + heading_error, kicks)[:, :2]

        return jax.vmap(one)(keys)

    return np.asarray(run(jax.random.split(jax.random.PRNGKey(seed), episodes)), np.float64)


def pendulum_models(task: RagdollStand) -> dict:
    """The two inverted pendulums of the standing doll (all joints held) on the support of its feet.

    Each has a capture point xi = x + v / omega (x, v: the COM's horizontal offset and velocity)
    with d xi / dt = omega (xi - p), p the centre of pressure, and a torso kick dv moves xi by
    `xi_per_kick` x dv (it does not move x).
      point mass (linear inverted pendulum): omega = sqrt(g / z), the COM velocity changes by
        share x dv (`support`);
      rigid block pivoting on its feet: the whole doll turns about the floor under the ankles,
        I_pivot theta'' = m g (x - p): omega = sqrt(m g z / I_pivot), and the kick's angular
        momentum about the pivot, m_torso z_torso dv, turns it: v = z theta' changes by
        m_torso z_torso z dv / I_pivot. The torso sits above the COM, so a kick does more than
        the point mass says.
    """
    feet = support(task)
    physics = dbd.init(task.model)
    # I_pivot: the angular momentum of the doll turning as one body at 1 rad/s about the world's y
    # axis (the floor line under the ankles: the build pose stands on the origin).
    turn = jnp.array([0.0, 1.0, 0.0], physics.pos.dtype)
    turning = dbd.State(pos=physics.pos, quat=physics.quat, vel=jnp.cross(turn, physics.pos),
                        ang_vel=jnp.broadcast_to(turn, physics.pos.shape))  # fmt: skip
    pivot_inertia = float(diagnostics.angular_momentum(task.model, turning)[1])
    total = float(np.sum(task.model.bodies.mass))
    height, torso_height = float(feet["com_m"][2]), float(physics.pos[task.torso, 2])
    torso_mass = feet["torso_mass_share"] * total
    omega_block = float(np.sqrt(total * GRAVITY * height / pivot_inertia))
    return {
        "point mass": {"omega_per_s": feet["omega_per_s"],
                       "xi_per_kick_s": feet["torso_mass_share"] / feet["omega_per_s"]},
        "rigid block": {"omega_per_s": omega_block,
                        "xi_per_kick_s": torso_mass * torso_height * height / pivot_inertia / omega_block,
                        "pivot_inertia_kg_m2": pivot_inertia, "torso_height_m": torso_height},
    }  # fmt: skip


def capture_point_survival(kicks: np.ndarray, low, high, omega: float, xi_per_kick: float, dt: float,
                           start, aim) -> np.ndarray:  # fmt: skip
    """The ideal feet-in-place balance under given kicks: for each episode the first step at which
    the capture point leaves the support (the pendulum can no longer be stopped), or -1 if it never
    does. kicks: (episodes, steps, 2) m/s in the heading frame; low, high: (2,) m the support's
    bounds on the capture point (x forward from the ankles, y left); start: (2,) the capture point
    at the start (the build pose at rest: its COM); aim: (2,) where it is driven back to.

    Between kicks the centre of pressure sits at the support's edge beyond the capture point, which
    moves it back to `aim` as fast as any centre of pressure on the feet can (per axis: xi - p =
    (xi0 - p) e^(omega t)), and then holds it there (p = xi)."""
    low, high, aim = (np.asarray(x, np.float64) for x in (low, high, aim))
    episodes, steps, _ = kicks.shape
    xi = np.broadcast_to(np.asarray(start, np.float64), (episodes, 2)).copy()
    failed_at = np.full(episodes, -1)
    growth = np.exp(omega * dt)
    for step in range(steps):
        xi += xi_per_kick * kicks[:, step]
        out = ((xi <= low) | (xi >= high)).any(1) & (failed_at < 0)
        failed_at[out] = step
        back_down = np.maximum(aim, high + (xi - high) * growth)  # p at the high edge
        back_up = np.minimum(aim, low + (xi - low) * growth)  # p at the low edge
        xi = np.where(xi > aim, back_down, back_up)
    return failed_at


def clairvoyant_survival(kicks: np.ndarray, low, high, omega: float, xi_per_kick: float, dt: float,
                         start) -> np.ndarray:  # fmt: skip
    """`capture_point_survival` for a balance that knows every kick in advance: the first step at
    which no centre of pressure on the feet could have kept the capture point on them, or -1. Per
    axis the capture points reachable so far form an interval [a, b] (from `start`); between kicks
    it widens at the rate the edges allow (a with p at the high edge, b at the low one), a kick
    shifts it, and it is cut to the feet; an empty interval loses the episode."""
    low, high = (np.asarray(x, np.float64) for x in (low, high))
    episodes, steps, _ = kicks.shape
    a = np.broadcast_to(np.asarray(start, np.float64), (episodes, 2)).copy()
    b = a.copy()
    failed_at = np.full(episodes, -1)
    growth = np.exp(omega * dt)
    for step in range(steps):
        a = np.maximum(a + xi_per_kick * kicks[:, step], low)
        b = np.minimum(b + xi_per_kick * kicks[:, step], high)
        out = (a > b).any(1) & (failed_at < 0)
        failed_at[out] = step
        a, b = np.maximum(low, high + (a - high) * growth), np.minimum(high, low + (b - low) * growth)
    return failed_at


def pushes_before_falls(kicks: np.ndarray, lengths: np.ndarray, survived: np.ndarray) -> list[dict]:
    """For each episode a policy lost (`rl.evaluate`'s "lengths" and "survived"), the step it fell
    (its length: the last step's number for a fall on the last step) and the pushes before it:
    [step, forward, left] m/s in the starting heading frame (`episode_kicks`' (episodes, steps, 2)),
    and whether one of them was a hard backward push (> 0.5 m/s, within 45 degrees of backwards),
    the kick a balance with the feet in place has least margin for (section 1)."""
    rows = []
    for episode in np.flatnonzero(~survived):
        kicked = kicks[episode, : lengths[episode]]
        pushed = np.flatnonzero(np.abs(kicked).sum(-1) > 0)
        forward, left = kicked[pushed, 0], kicked[pushed, 1]
        hard_backward = (np.hypot(forward, left) > 0.5) & (-forward > np.abs(left))
        rows.append({"episode": int(episode), "fell_at_step": int(lengths[episode]),
                     "pushes": [[int(step), *np.round(kicked[step], 3).tolist()] for step in pushed],
                     "after_a_hard_backward_push": bool(hard_backward.any())})  # fmt: skip
    return rows


def _falls_beside(fell: np.ndarray, lost: dict[str, np.ndarray]) -> dict:
    """How a policy's falls (episodes,) split over the episodes each ideal balance loses or keeps."""
    row = {"survived": int((~fell).sum()), "episodes": len(fell)}
    for name, model_lost in lost.items():
        row[f"falls in episodes the {name} loses"] = int((fell & model_lost).sum())
        row[f"falls in episodes the {name} survives"] = int((fell & ~model_lost).sum())
    return row


def feet_in_place_bound(task: RagdollStand, episodes: int, seed: int, compare: list[str], checkpoints: list[str],
                        policy_episodes: int = 1024, policy_seed: int = 11,
                        aims=(0.02, 0.03, 0.04, 0.05, 0.06, 0.07), choice_episodes: int = 4096,
                        choice_seed: int = 7) -> dict:  # fmt: skip
    """Section 7: which of the episodes of `seed` an ideal feet-in-place balance survives, reacting
    to each kick as it comes (`capture_point_survival`: the capture point driven back sideways to
    the middle and forwards to the one of `aims` that survives the most of `choice_episodes` other
    episodes, of `choice_seed`) or knowing them all in advance (`clairvoyant_survival`), for both
    pendulums of `pendulum_models`; for each results file in `compare` run on those episodes, where
    its policy fell; and each policy checkpoint of `checkpoints` (`training.checkpoint` files)
    evaluated on `policy_episodes` episodes of `policy_seed` beside the same balances there."""
    steps = task.max_episode_steps
    feet = support(task)
    low = np.array([feet["heel_x_m"], -feet["feet_half_width_m"]])
    high = np.array([feet["toe_x_m"], feet["feet_half_width_m"]])
    start = np.array([feet["com_m"][0], 0.0])  # the build pose at rest
    kicks = {"reported": episode_kicks(task, episodes, seed, steps),
             "choice": episode_kicks(task, choice_episodes, choice_seed, steps),
             "policies": episode_kicks(task, policy_episodes, policy_seed, steps) if checkpoints else None}  # fmt: skip
    result = {"episodes": episodes, "seed": seed, "steps": steps, "support_low_m": low.tolist(),
              "support_high_m": high.tolist(), "start_m": start.tolist(), "choice_episodes": choice_episodes,
              "choice_seed": choice_seed, "policy_episodes": policy_episodes, "policy_seed": policy_seed,
              "pushes_per_episode": float((np.abs(kicks["reported"]).sum(-1) > 0).sum(1).mean()),
              "models": {}}  # fmt: skip
    lost = {"reported": {}, "policies": {}}
    for name, model in pendulum_models(task).items():
        omega, xi_per_kick = model["omega_per_s"], model["xi_per_kick_s"]

        def reacting(kicks, aim_x, omega=omega, xi_per_kick=xi_per_kick):
            return capture_point_survival(kicks, low, high, omega, xi_per_kick, task.dt, start, [aim_x, 0.0])

        def knowing(kicks, omega=omega, xi_per_kick=xi_per_kick):
            return clairvoyant_survival(kicks, low, high, omega, xi_per_kick, task.dt, start)

        by_aim = {f"{aim:g}": float((reacting(kicks["choice"], aim) < 0).mean()) for aim in aims}
        aim = max(aims, key=lambda aim: by_aim[f"{aim:g}"])
        failed, failed_knowing = reacting(kicks["reported"], aim), knowing(kicks["reported"])
        lost["reported"][name] = failed >= 0
        lost["reported"][f"{name} knowing the kicks"] = failed_knowing >= 0
        result["models"][name] = dict(
            model,
            survival_of_choice_episodes_by_aim_m=by_aim,
            aim_m=aim,
            survived=int((failed < 0).sum()),
            lost_episodes={int(e): int(failed[e]) for e in np.flatnonzero(failed >= 0)},  # episode: step
            # the heading is the starting one; while the policies stand it turns by 0.1 rad (median)
            survived_heading_off_by_0_1_rad=[
                int((reacting(episode_kicks(task, episodes, seed, steps, error), aim) < 0).sum())
                for error in (-0.1, 0.1)
            ],
            knowing_the_kicks={"survived": int((failed_knowing < 0).sum()),
                               "lost_episodes": {int(e): int(failed_knowing[e])
                                                 for e in np.flatnonzero(failed_knowing >= 0)},
                               "survival_of_choice_episodes": float((knowing(kicks["choice"]) < 0).mean())},
        )  # fmt: skip
        if checkpoints:
            lost["policies"][name] = reacting(kicks["policies"], aim) >= 0
            lost["policies"][f"{name} knowing the kicks"] = knowing(kicks["policies"]) >= 0
            result["models"][name]["survival_of_policy_episodes"] = float((~lost["policies"][name]).mean())
            result["models"][name]["knowing_the_kicks"]["survival_of_policy_episodes"] = float(
                (~lost["policies"][f"{name} knowing the kicks"]).mean()
            )
        print(name, result["models"][name], flush=True)
    # The check of the models against the doll: the largest backward kick the build pose (every
    # drive holding it, no control) survives, against each model's heel margin / xi_per_kick.
    speeds = np.round(np.arange(0.15, 0.2451, 0.01), 3)
    kicked = single_kicks(RagdollStand(max_episode_steps=steps, push_interval=None), speeds, np.array([np.pi]))
    survived = np.asarray(kicked["survived"])[:, 0].astype(bool)
    result["largest_backward_kick_from_the_build_pose_m_per_s"] = {
        "doll (build pose held), survived / fell": [float(speeds[survived].max(initial=0.0)),
                                                    float(speeds[~survived].min(initial=np.inf))],
        **{name: float((start[0] - low[0]) / model["xi_per_kick_s"]) for name, model in result["models"].items()},
    }  # fmt: skip
    print(result["largest_backward_kick_from_the_build_pose_m_per_s"], flush=True)
    result["policies"] = []
    for path in compare:
        run = json.loads(Path(path).read_text())
        lengths = np.asarray(run.get("evaluation_lengths", []))
        evaluated_on = run.get("evaluation_seed", run.get("seed", 0) + 1)
        if evaluated_on != seed or len(lengths) != episodes or run.get("max_episode_steps") != steps:
            continue
        result["policies"].append({"results": Path(path).name, **_falls_beside(lengths < steps, lost["reported"])})
        print(result["policies"][-1], flush=True)
    result["checkpoints"] = []
    for path in checkpoints:
        from dbdjax.training import checkpoint, rl  # noqa: PLC0415 (the train extra, only for this)

        params, _ = checkpoint.load(path)
        evaluation = rl.evaluate(task, params, policy_episodes, seed=policy_seed)
        lengths, survived = np.asarray(evaluation["lengths"]), np.asarray(evaluation["survived"])
        falls = pushes_before_falls(kicks["policies"], lengths, survived)
        result["checkpoints"].append({"checkpoint": Path(path).name, "mean_return": evaluation["mean_return"],
                                      **_falls_beside(~survived, lost["policies"]),
                                      "falls_after_a_hard_backward_push": sum(f["after_a_hard_backward_push"]
                                                                              for f in falls),
                                      "falls": falls, "lengths": lengths.tolist()})  # fmt: skip
        print({key: value for key, value in result["checkpoints"][-1].items() if key not in ("lengths", "falls")},
              flush=True)  # fmt: skip
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "ragdoll_push_recovery.json"))
    parser.add_argument(
        "--only",
        nargs="+",
        choices=["support", "kicks", "leans", "pushes", "budgets", "ramped", "capture"],
        help="run these sections alone (default: all)",
    )
    parser.add_argument("--compare", nargs="*", default=[], help="training results files (JSON) whose reported "
                        "episodes' falls section 7 sets beside the bound (those run on its episodes)")  # fmt: skip
    parser.add_argument("--episodes", type=int, default=128, help="section 7's episodes (default 128, of seed 1: "
                        "the training runs' reported episodes)")  # fmt: skip
    parser.add_argument("--checkpoints", nargs="*", default=[], help="policy checkpoints (.npz) that section 7 "
                        "evaluates on --policy-episodes other episodes beside the bound")  # fmt: skip
    parser.add_argument("--policy-episodes", type=int, default=1024)
    parser.add_argument("--push-schedule", choices=["regular", "random"], default="regular",
                        help="the env's push schedule in sections 4, 6 and 7 (default: the env's, regular); "
                        "section 7 writes `feet_in_place_bound` for random, `feet_in_place_bound_regular` for "
                        "regular")  # fmt: skip
    args = parser.parse_args()
    if args.checkpoints and "capture" in (args.only or ["capture"]):
        from dbdjax.training import rl  # noqa: PLC0415 (the train extra, only for the checkpoints)

        rl.use_cpu_devices(None)  # their evaluations split over the cores, as the trainers' are
    sections = set(args.only or ["support", "kicks", "leans", "pushes", "budgets", "ramped", "capture"])
    start = time.perf_counter()
    task = RagdollStand(max_episode_steps=300, push_interval=None)
    out = Path(args.out)
    # Sections run now replace theirs in an existing file; the others' results stay.
    result = json.loads(out.read_text()) if out.exists() else {}
    if "wall_s" in result:  # a file from before runs were listed
        result["runs"] = [{"sections": "all", "wall_s": result.pop("wall_s"),
                           "load_average_at_end": result.pop("load_average_at_end", None)}]  # fmt: skip
    result.update(env_substeps=task.model.options.substeps, env_iterations=task.model.options.iterations)
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
        result["random_pushes"] = env_pushes([(0.0, 0.0), (0.3, 0.6), (0.5, 1.5)], push_schedule=args.push_schedule)
    if "budgets" in sections:
        result["solver_budgets"] = solver_budgets([(2, 8), (4, 4), (3, 8), (4, 6), (2, 16), (4, 8), (8, 4), (2, 32),
                                                   (8, 8)])  # fmt: skip
    if "ramped" in sections:
        result["ramped_leans_under_pushes"] = []
        for substeps in (2, 4):
            row = ramped_lean_episodes(np.array([0.0, -0.01, -0.02, -0.03, -0.045, -0.06, -0.08]), 48, 300,
                                       substeps=substeps, iterations=8, push_schedule=args.push_schedule)  # fmt: skip
            result["ramped_leans_under_pushes"].append(dict(row, substeps=substeps, iterations=8,
                                                            push_schedule=args.push_schedule))  # fmt: skip
            print(result["ramped_leans_under_pushes"][-1], flush=True)
    if "capture" in sections:
        key = "feet_in_place_bound" + ("" if args.push_schedule == "random" else f"_{args.push_schedule}")
        task = RagdollStand(max_episode_steps=300, push_schedule=args.push_schedule)
        result[key] = feet_in_place_bound(task, args.episodes, 1, args.compare, args.checkpoints,
                                          policy_episodes=args.policy_episodes)  # fmt: skip
        result[key]["push_schedule"] = args.push_schedule
    run = {
        "sections": sorted(sections),
        "push_schedule": args.push_schedule,
        "wall_s": time.perf_counter() - start,
        "load_average_at_end": os.getloadavg(),
    }
    result.setdefault("runs", []).append(run)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out} ({run['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
