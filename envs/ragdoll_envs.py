"""dbdjax/RagdollStand-v0 and dbdjax/RagdollTrack-v0: the driven ragdoll of `dbdjax.ragdoll`.

Both share the model, the action mapping, the observation, the fall and the pushes
(`RagdollEnv`); they differ in the reward (and Track adds the reference to the observation).

The doll (`ragdoll.build`, default 1.8 m, 70 kg, 15 bodies, 14 joints, a floor) stands in its
build pose facing a random heading. Its 14 joint drives (DBD section 9) are the actuators: 26
drive targets, 3 per ball joint (waist, neck, shoulders, hips: a rotation vector in the parent's
frame) and 1 per hinge (elbows, wrists, knees, ankles: an angle), all from the build pose.

Action (26,) in [-1, 1]: the drive targets relative to the build pose, as legged-robot RL does
(legged_gym: default pose + scale x action): target = clip(scale x action, low, high) within the
joints' target ranges (`doll.control_low` .. `doll.control_high`, from the joint limits), scale =
max(high, -low) per entry (`control_scale`: the farther end of the range is reached at +-1).
Action 0 is the build pose, standing straight (`control_home` = 0). Symmetric ranges (waist,
neck, shoulders, wrists, hips) map -1 -> low, +1 -> high; a knee or elbow (0 .. 2.4 rad) flexes
by 2.4 a for a > 0 and stays straight for a <= 0; an ankle (-0.5 .. 0.8 rad) follows 0.8 a down to
-0.5 at a = -0.625. (Earlier versions mapped action 0 to the middle of every range: a crouch with
1.2 rad knees that falls within half a second.) Entries outside [-1, 1] are clipped; a NaN/inf entry ends the
episode with info["nonfinite_action"].

Observation (float32), in the heading frame (world rotated by the pelvis' yaw, so the heading
never shows): pelvis height (1); the pelvis' and the torso's up axes (3 + 3); the other 14 bodies'
positions relative to the pelvis (42); the pelvis' linear and angular velocity (3 + 3); the joint
positions in the layout of the drive targets (26) and their rates x 0.1 (26); the previous action
(26). 133 numbers for Stand; Track adds the reference targets of the next step (26) and the sine
and cosine of the reference phase (2): 161.

Termination: the pelvis centre below `fall_height` (default 0.55 x its standing height), or a
non-finite action or physics state (info flags). Truncation: `max_episode_steps` (300 when
registered: 10 s at 30 Hz). Physics: dt = 1/60 s, `substeps` 4 (`SUBSTEPS`), the ragdoll module's
`iterations` (8), `frame_skip` 2.

The solver budget decides how stiff the drives are under the body's weight. The ankles carry the
whole doll on two 1.2 kg feet, and Gauss-Seidel passes that load up the chain a little per sweep:
with 2 substeps x 8 iterations (the ragdoll module's default, 16 sweeps per physics step) an
ankle target of -0.036 rad (action -0.045, leaning the centre of mass 4 cm forward) sagged to
-0.105 and -0.127 rad, the heels lifted and the doll fell on its face 2.9 s after the start with
no push; the same lean holds at -0.051 rad with 32 sweeps (4 x 8, 2 x 16 or 8 x 4 alike) and
at -0.043 with 64 (2 x 32 and 8 x 8 agree, yet short of convergence: the drive's own sag under
that load is 1.5 mrad, to -0.0375 rad, where `tree_solve` holds it; README, session 26). With the
pushes on, the home pose with that lean ramped in over 1 s and held stands through 41 of 48
episodes of 300 steps at 4 x 8, and 0 of 48 at 2 x 8 (whose best constant lean, -0.01 or -0.02,
stands 15 of 48). Each step costs twice as much (335 against 666 env steps/s at batch 64, one core).

Pushes: the torso's velocity changes by a horizontal kick of random direction and a magnitude
uniform in `push_speed` (m/s), once every `push_interval` seconds. `push_schedule` says when:
"regular" (the default): at the start of env steps k x round(push_interval / dt), k = 1, 2, ...
(steps 60, 120, 180 and 240 of a 300-step episode at the default 2 s), as legged_gym pushes its
robots (every `push_interval_s`); "random": at each step with probability dt / push_interval (a
Poisson process: one push every push_interval on average, the only schedule until session 43).
info["push"] is the kick of the step (zeros without one).

Default push range 0.2-0.6 m/s (it was 0.5-1.5 m/s before): the range a doll that keeps its feet
in place can survive. By the capture point of the linear inverted pendulum (README, "Can the
pushes be survived?"), a torso kick is recoverable without a step up to 0.76 m/s forwards or
backwards with the centre of mass over the middle of the feet (0.98 m/s sideways), but only
0.24 m/s backwards from the build pose, whose centre of mass is 2 cm from the heel edge; so
every default push alone can be survived by balancing (leaning, ankle and hip torques), and the build
pose alone survives few episodes (9 of 48 full 300-step episodes, where a forward ankle lean of
0.036 rad, ramped in over 1 s, survives 41 of 48; at the former 2 substeps: 1 of 32, and 10 of
32 for the best lean, 0.008 rad). Most kicks of the old range need a step, which left the
learners no strategy within reach (`push_speed=(0.5, 1.5)` gives it back). (The build-pose and
lean counts above are of the random schedule.) Under the random schedule an episode's pushes
together are another matter: about 5 per 300 steps, some in the first steps (before any lean) and
some a few steps apart in about the same direction. An ideal balance with the feet in place, run on
each episode's own pushes (`benchmarks/ragdoll_push_recovery.py`, section 7), loses 4% of the
episodes as a point mass and 9-10% as the rigid doll, and 2-3% even knowing every push in advance
(README: "How many episodes can be survived with the feet in place?"): no policy that keeps its
feet in place survives them all. Hence the regular schedule, the default since session 43: every
push meets a doll that has stood 2 s since the last one (README: "Regular pushes").
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode

import dbdjax as dbd
from dbdjax import math, ragdoll
from dbdjax.envs.core import DbdFuncEnv, EnvState, joint_coordinates, yaw_rotate_inverse
from dbdjax.envs.wrappers import DbdEnv, DbdVectorEnv

PUSH_SCHEDULES = ("random", "regular")  # RagdollEnv's push_schedule (module docstring)
SUBSTEPS = 4  # the envs' substeps per physics step (module docstring: why not ragdoll.SUBSTEPS)


class RagdollState(NamedTuple):
    """Task variables: time () s since the start (+ the reference phase offset for Track),
    previous_action (26,), push (3,) m/s the kick of the last step."""

    time: jnp.ndarray
    previous_action: jnp.ndarray
    push: jnp.ndarray


def _hashable(value: Any) -> Any:
    return tuple(sorted(value.items())) if isinstance(value, Mapping) else value


class RagdollEnv(DbdFuncEnv):
    """The shared part of the ragdoll tasks (see the module docstring); subclasses set the reward.

    height (m), mass (kg), drive_stiffness, drive_damping, max_torque: `ragdoll.build`'s
    (None: its defaults). push_interval: s between pushes (None: no pushes). push_speed: (low,
    high) m/s (module docstring: why 0.2-0.6). push_schedule: "regular" (one push every
    push_interval exactly) or "random" (at that rate on average; module docstring).
    backward_push_share: the share of pushes whose direction is drawn within 45 degrees of
    backwards (-x, the doll's back at build) instead of from every direction alike (0: none): the
    pushes trained policies fall after (README, session 44), made more common for training (one
    30-minute PPO run at 0.25 learned no faster per step; README, session 46). fall_height:
    m, the pelvis height that ends the episode (None: 0.55 x the standing height). smooth_weight:
    weight of the action-change penalty.
    dt, substeps, iterations, tree_solve: the physics (`ModelBuilder.finalize`). tree_solve=True is
    not fit for training yet: at 2 substeps x 2 iterations it survived scripted pushes as the default
    4 x 8 sweeps do (session 27), but under a PPO policy's actions a foot point that starts sliding
    blows the leg up from rest (12 of 128 episodes; README, session 28). relaxation: xi of the
    doll's joint rows (`ragdoll.build`): at 4 x 4 sweeps with 1.3 the leaning doll stands through
    scripted kicks as at 4 x 8 with 1.0, 1.7-1.85x cheaper, but PPO learned to balance worse on it
    (72% against 90-93% in 30 minutes, one run; README, session 45).
    """

    default_max_episode_steps = 300
    observation_extra = 0  # numbers a subclass appends

    def __init__(
        self,
        height: float = ragdoll.REFERENCE_HEIGHT,
        mass: float = ragdoll.REFERENCE_MASS,
        drive_stiffness: float | Mapping[str, float] | None = None,
        drive_damping: float | Mapping[str, float] | None = None,
        max_torque: float | Mapping[str, float] | None = None,
        push_interval: float | None = None,
        push_speed: tuple[float, float] = (0.2, 0.6),
        push_schedule: str = "regular",
        backward_push_share: float = 0.0,
        fall_height: float | None = None,
        smooth_weight: float = 0.1,
        dt: float = ragdoll.DT,
        substeps: int = SUBSTEPS,
        iterations: int = ragdoll.ITERATIONS,
        frame_skip: int = 2,
        max_episode_steps: int | None = None,
        config: dict[str, Any] | None = None,
        tree_solve: bool = False,
        relaxation: float = 1.0,
    ):
        base = dict(
            height=height, mass=mass, drive_stiffness=_hashable(drive_stiffness),
            drive_damping=_hashable(drive_damping), max_torque=_hashable(max_torque), push_interval=push_interval,
            push_speed=tuple(push_speed), push_schedule=push_schedule, backward_push_share=backward_push_share,
            fall_height=fall_height,
            smooth_weight=smooth_weight, dt=dt,
            substeps=substeps, iterations=iterations, frame_skip=frame_skip, max_episode_steps=max_episode_steps,
            tree_solve=tree_solve, relaxation=relaxation,
        )  # fmt: skip
        if push_interval is not None and not push_interval > 0.0:
            raise ValueError(f"{type(self).__name__}: push_interval must be positive or None, got {push_interval!r}")
        if push_schedule not in PUSH_SCHEDULES:
            raise ValueError(
                f"{type(self).__name__}: push_schedule must be one of {PUSH_SCHEDULES}, got {push_schedule!r}"
            )
        if not 0.0 <= backward_push_share <= 1.0:
            raise ValueError(
                f"{type(self).__name__}: backward_push_share must be in [0, 1], got {backward_push_share!r}"
            )
        low_speed, high_speed = (float(v) for v in push_speed)
        if not 0.0 <= low_speed <= high_speed:
            raise ValueError(f"{type(self).__name__}: push_speed must be (low, high) with 0 <= low <= high")
        builder, doll = ragdoll.build(
            height=height, mass=mass, drive_stiffness=drive_stiffness, drive_damping=drive_damping,
            max_torque=max_torque, relaxation=relaxation,
        )  # fmt: skip
        model = builder.finalize(dt=dt, substeps=substeps, iterations=iterations, tree_solve=tree_solve)
        if model.num_controls != doll.num_controls:
            raise ValueError("RagdollEnv: the doll must be the only thing with controls in its model")
        self.doll = doll
        self.joint_names = tuple(doll.controls)  # in control order
        self.joint_indices = tuple(doll.joints[name] for name in self.joint_names)
        self.joint_kinds = tuple(doll.joint_kinds[name] for name in self.joint_names)
        self.pelvis = doll.bodies["pelvis"]
        self.torso = doll.bodies["torso"]
        self.feet = (doll.bodies["foot_l"], doll.bodies["foot_r"])
        self.others = tuple(index for name, index in doll.bodies.items() if name != "pelvis")
        self.rest_height = float(doll.rest_height)
        self.fall_height = 0.55 * self.rest_height if fall_height is None else float(fall_height)
        self.push_interval = None if push_interval is None else float(push_interval)
        self.push_speed = (low_speed, high_speed)
        self.push_schedule = push_schedule
        self.backward_push_share = float(backward_push_share)
        self.smooth_weight = float(smooth_weight)
        super().__init__(
            model,
            control_low=doll.control_low,
            control_high=doll.control_high,
            control_home=np.zeros(doll.num_controls),  # the build pose (module docstring)
            frame_skip=frame_skip,
            max_episode_steps=max_episode_steps,
            config={**base, **(config or {})},
        )

    # ------------------------------------------------------------------------ measurements
    def heading(self, physics: dbd.State) -> jnp.ndarray:
        """() rad, yaw of the pelvis' forward (+x at build) axis about world z."""
        forward = math.quat_rotate(physics.quat[self.pelvis], jnp.array([1.0, 0.0, 0.0], physics.quat.dtype))
        return math.safe_atan2(forward[1], forward[0])

    def up(self, physics: dbd.State, body: int) -> jnp.ndarray:
        """(3,) the world direction of a body's build-time z axis."""
        return math.quat_rotate(physics.quat[body], jnp.array([0.0, 0.0, 1.0], physics.quat.dtype))

    def joints(self, physics: dbd.State) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Joint positions (26,) rad and rates (26,) rad/s in the drive-target layout."""
        return joint_coordinates(self.model, physics, self.joint_indices, self.joint_kinds)

    def pelvis_height(self, state: EnvState) -> jnp.ndarray:
        return state.physics.pos[self.pelvis, 2]

    def capture_offset(self, physics: dbd.State) -> jnp.ndarray:
        """(2,) m, world x and y: the capture point of the linear inverted pendulum, xi = c + v / omega
        with omega = sqrt(g / c_z) (c, v: the doll's centre of mass and its velocity), less the middle
        of the feet (each foot's origin lies over the middle of its sole, heel to toe). Where xi
        stands the centre of mass comes to rest over it; held over the feet's middle it leaves the
        largest push a balance without stepping can still take (module docstring)."""
        centre, velocity = dbd.diagnostics.centre_of_mass(self.model, physics)
        # The height floored at a tenth of the standing one: a doll lying flat keeps a finite omega.
        omega = jnp.sqrt(-self.model.gravity[2] / jnp.maximum(centre[2], 0.1 * self.rest_height))
        feet = 0.5 * (physics.pos[self.feet[0], :2] + physics.pos[self.feet[1], :2])
        return centre[:2] + velocity[:2] / omega - feet

    # ------------------------------------------------------------------------ task hooks
    def initial_time(self, key: jnp.ndarray) -> jnp.ndarray:
        return jnp.zeros((), self.dtype)

    def task_initial(self, key: jnp.ndarray):
        yaw_key, time_key = jax.random.split(key)
        physics = dbd.init(self.model)
        yaw = jax.random.uniform(yaw_key, (), self.dtype, -jnp.pi, jnp.pi)
        # Turn the standing doll about the vertical through its feet (the world origin).
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        x, y = physics.pos[:, 0], physics.pos[:, 1]
        pos = jnp.stack([c * x - s * y, s * x + c * y, physics.pos[:, 2]], axis=-1)
        turn = math.quat_exp(jnp.stack([0.0 * yaw, 0.0 * yaw, yaw]))
        quat = math.quat_multiply(jnp.broadcast_to(turn, physics.quat.shape), physics.quat)
        physics = dbd.State(pos=pos, quat=quat, vel=physics.vel, ang_vel=physics.ang_vel)
        task = RagdollState(
            time=self.initial_time(time_key),
            previous_action=jnp.zeros((self.action_size,), self.dtype),
            push=jnp.zeros((3,), self.dtype),
        )
        return physics, task

    def kick(self, key: jnp.ndarray, step: jnp.ndarray) -> jnp.ndarray:
        """(3,) m/s, world frame: the torso kick of the env step that starts at `step` (int, steps
        since reset), drawn by the step's key (zeros on most steps, always without pushes). Step
        t's key is the second half of `jax.random.split` of the state's key."""
        if self.push_interval is None:
            return jnp.zeros((3,), self.dtype)
        # Split alike for both schedules: the schedule alone decides which steps' draws are pushes.
        when, direction, size = jax.random.split(key, 3)
        if self.push_schedule == "regular":
            every = max(1, round(self.push_interval / self.dt))
            pushed = (step > 0) & (step % every == 0)
        else:
            pushed = jax.random.uniform(when, (), self.dtype) < self.dt / self.push_interval
        angle = jax.random.uniform(direction, (), self.dtype, -jnp.pi, jnp.pi)
        if self.backward_push_share > 0.0:  # without it, the same draws as before the option
            pick, cone = jax.random.split(jax.random.fold_in(direction, 1))
            backward = jax.random.uniform(cone, (), self.dtype, 0.75 * jnp.pi, 1.25 * jnp.pi)
            angle = jnp.where(jax.random.uniform(pick, (), self.dtype) < self.backward_push_share, backward, angle)
        speed = jax.random.uniform(size, (), self.dtype, *self.push_speed)
        change = speed * jnp.stack([jnp.cos(angle), jnp.sin(angle), 0.0 * angle])
        return jnp.where(pushed, change, 0.0)

    def task_before_physics(self, state: EnvState, action: jnp.ndarray, key: jnp.ndarray) -> dbd.State:
        physics = state.physics
        return dbd.State(
            pos=physics.pos,
            quat=physics.quat,
            vel=physics.vel.at[self.torso].add(self.kick(key, state.step)),
            ang_vel=physics.ang_vel,
        )

    def task_update(self, state: EnvState, action: jnp.ndarray, physics: dbd.State) -> RagdollState:
        # The same key split as _advance, so the kick recorded is the one applied.
        _, step_key = jax.random.split(state.key)
        return RagdollState(
            time=state.task.time + self.dt, previous_action=action, push=self.kick(step_key, state.step)
        )

    def observe_body(self, state: EnvState) -> jnp.ndarray:
        """The 133 numbers every ragdoll task observes (module docstring)."""
        physics = state.physics
        yaw = self.heading(physics)
        pelvis = physics.pos[self.pelvis]
        others = physics.pos[np.asarray(self.others)] - pelvis
        position, rate = self.joints(physics)
        return jnp.concatenate([
            pelvis[2:3],
            yaw_rotate_inverse(yaw, self.up(physics, self.pelvis)),
            yaw_rotate_inverse(yaw, self.up(physics, self.torso)),
            yaw_rotate_inverse(yaw, others).reshape(-1),
            yaw_rotate_inverse(yaw, physics.vel[self.pelvis]),
            yaw_rotate_inverse(yaw, physics.ang_vel[self.pelvis]),
            position,
            0.1 * rate,
            state.task.previous_action,
        ])  # fmt: skip

    def task_observation(self, state: EnvState) -> jnp.ndarray:
        return self.observe_body(state)

    def task_failed(self, state: EnvState) -> jnp.ndarray:
        return self.pelvis_height(state) < self.fall_height

    def task_info(self, state: EnvState) -> dict[str, jnp.ndarray]:
        return {"pelvis_height": self.pelvis_height(state), "push": state.task.push}

    def smooth_penalty(self, state: EnvState, action: jnp.ndarray) -> jnp.ndarray:
        return -self.smooth_weight * jnp.mean((action - state.task.previous_action) ** 2)

    def render_scene(self, state: EnvState):
        """The doll and the floor from a camera that follows the pelvis."""
        from dbdjax import render  # noqa: PLC0415 (pictures are optional)

        camera = render.camera_looking_at((0.0, 0.0, 0.9), distance=4.0, azimuth=-60.0, elevation=15.0)
        return self.model, state.physics, {"camera": camera, "track": self.pelvis}


class RagdollStand(RagdollEnv):
    """dbdjax/RagdollStand-v0: stay upright and in place under pushes.

    Everything but the reward is `RagdollEnv`'s (module docstring); a push every 2 s (at steps 60,
    120, 180, 240), 0.2-0.6 m/s on the torso in a random direction (each survivable with the feet in
    place: module docstring). Reward per step, the sum of:
      alive   = `alive_bonus` (1.0) while the episode runs,
      upright = -`upright_weight` (1.0) x (1 - z of the torso's up axis) (0 standing straight),
      height  = -`height_weight` (2.0) x |pelvis height - standing height| (m),
      drift   = -`drift_weight` (0.1) x |horizontal pelvis velocity|^2 ((m/s)^2),
      smooth  = -`smooth_weight` (0.1) x mean((action - previous action)^2),
      capture = -`capture_weight` (0.0) x |capture point - middle of the feet|^2 (m^2,
                `capture_offset`): a shaping term for training (0 in the registered task).
                With `capture_scale` s (m; None: unbounded) it saturates, -w s^2 (1 - exp(-d^2 / s^2))
                for d = |offset|: about -w d^2 near the feet, never below -w s^2 per step, so that
                with w s^2 under the alive bonus a falling doll's steps do not cost more than
                living pays (session 51: unbounded, runs learnt to fall sooner to end the penalty).
    info: "pelvis_height", "push", the reward terms and the flags.
    """

    reward_terms = ("alive", "upright", "height", "drift", "smooth", "capture")

    def __init__(
        self,
        push_interval: float | None = 2.0,
        alive_bonus: float = 1.0,
        upright_weight: float = 1.0,
        height_weight: float = 2.0,
        drift_weight: float = 0.1,
        capture_weight: float = 0.0,
        capture_scale: float | None = None,
        **kwargs,
    ):
        self.alive_bonus = float(alive_bonus)
        self.upright_weight = float(upright_weight)
        self.height_weight = float(height_weight)
        self.drift_weight = float(drift_weight)
        self.capture_weight = float(capture_weight)
        if not self.capture_weight >= 0.0 or not np.isfinite(self.capture_weight):
            raise ValueError(f"RagdollStand: capture_weight must be finite and >= 0, got {capture_weight!r}")
        self.capture_scale = None if capture_scale is None else float(capture_scale)
        if self.capture_scale is not None and not (self.capture_scale > 0.0 and np.isfinite(self.capture_scale)):
            raise ValueError(f"RagdollStand: capture_scale must be None or finite and > 0 (m), got {capture_scale!r}")
        config = dict(alive_bonus=alive_bonus, upright_weight=upright_weight, height_weight=height_weight,
                      drift_weight=drift_weight, capture_weight=capture_weight,
                      capture_scale=capture_scale)  # fmt: skip
        super().__init__(push_interval=push_interval, config=config, **kwargs)

    def task_reward(self, state: EnvState, action: jnp.ndarray, next_state: EnvState) -> dict[str, jnp.ndarray]:
        physics = next_state.physics
        speed = physics.vel[self.pelvis, :2]
        return {
            "alive": jnp.asarray(self.alive_bonus, self.dtype),
            "upright": -self.upright_weight * (1.0 - self.up(physics, self.torso)[2]),
            "height": -self.height_weight * jnp.abs(self.pelvis_height(next_state) - self.rest_height),
            "drift": -self.drift_weight * jnp.sum(speed**2),
            "smooth": self.smooth_penalty(state, action),
            "capture": (  # last and exactly zero at weight 0: the other terms' sum is as without it
                self.capture_penalty(physics) if self.capture_weight else jnp.zeros((), self.dtype)
            ),
        }

    def capture_penalty(self, physics: dbd.State) -> jnp.ndarray:
        """() the capture term (class docstring): -w d^2, or -w s^2 (1 - exp(-d^2 / s^2)) with a scale."""
        squared = jnp.sum(self.capture_offset(physics) ** 2)
        if self.capture_scale is None:
            return -self.capture_weight * squared
        scale_squared = self.capture_scale**2
        # -w s^2 (1 - exp(-d^2 / s^2)) = w s^2 expm1(-d^2 / s^2), exact for small d too
        return self.capture_weight * scale_squared * jnp.expm1(-squared / scale_squared)


# Reference motion of RagdollTrack: marching in place with arm swing, joint targets
# q_ref(t) = offset + amplitude sin(2 pi t / period). Entries: joint -> (offset, amplitude), a
# rotation vector (x, y, z) for a ball joint (parent frame = world axes of the standing doll:
# a leg or arm swings forward about -y), an angle for a hinge. The right side is the left half a
# period later (amplitude negated).
MARCH = {
    "hip_l": ((0.0, -0.3, 0.0), (0.0, -0.3, 0.0)),
    "hip_r": ((0.0, -0.3, 0.0), (0.0, 0.3, 0.0)),
    "knee_l": (0.55, 0.55),
    "knee_r": (0.55, -0.55),
    "ankle_l": (0.1, 0.1),
    "ankle_r": (0.1, -0.1),
    "shoulder_l": ((0.0, 0.0, 0.0), (0.0, 0.35, 0.0)),
    "shoulder_r": ((0.0, 0.0, 0.0), (0.0, -0.35, 0.0)),
    "elbow_l": (0.4, 0.25),
    "elbow_r": (0.4, -0.25),
}


class RagdollTrack(RagdollEnv):
    """dbdjax/RagdollTrack-v0: follow a procedurally generated reference motion.

    The reference is a march in place with arm swing (`MARCH`): every drive target follows
    q_ref(t) = offset + amplitude sin(2 pi t / `period`) (period 1.2 s), the legs and arms of the
    two sides half a period apart; no data is loaded. Each episode starts at a random phase.
    Everything else is `RagdollEnv`'s (module docstring; no pushes by default); the observation
    adds q_ref at the end of the step (26) and (sin, cos) of the phase (2). Reward per step:
      pose     = `pose_weight` (1.0) x exp(-`pose_scale` (4.0) x mean((q - q_ref)^2)), in (0, 1],
      velocity = `velocity_weight` (0.1) x exp(-0.1 x mean((dq - dq_ref)^2)),
      upright  = -`upright_weight` (0.5) x (1 - z of the torso's up axis),
      alive    = `alive_bonus` (0.2),
      smooth   = -`smooth_weight` (0.1) x mean((action - previous action)^2),
    with q, dq the joint positions and rates (drive-target layout) after the step and q_ref, dq_ref
    the reference at that time. info["pose_error"]: the rms of q - q_ref (rad).
    """

    reward_terms = ("pose", "velocity", "upright", "alive", "smooth")
    observation_extra = 28

    def __init__(
        self,
        period: float = 1.2,
        pose_weight: float = 1.0,
        pose_scale: float = 4.0,
        velocity_weight: float = 0.1,
        upright_weight: float = 0.5,
        alive_bonus: float = 0.2,
        push_interval: float | None = None,
        **kwargs,
    ):
        if not period > 0.0:
            raise ValueError(f"RagdollTrack: period must be positive, got {period!r}")
        self.period = float(period)
        self.pose_weight = float(pose_weight)
        self.pose_scale = float(pose_scale)
        self.velocity_weight = float(velocity_weight)
        self.upright_weight = float(upright_weight)
        self.alive_bonus = float(alive_bonus)
        config = dict(period=period, pose_weight=pose_weight, pose_scale=pose_scale, velocity_weight=velocity_weight,
                      upright_weight=upright_weight, alive_bonus=alive_bonus)  # fmt: skip
        # The reference's offset and amplitude vectors, built on the doll's control layout.
        _, doll = ragdoll.build(floor=False)
        offset = np.zeros(doll.num_controls)
        amplitude = np.zeros(doll.num_controls)
        for name, (center, swing) in MARCH.items():
            offset[doll.controls[name]] = center
            amplitude[doll.controls[name]] = swing
        if np.any(offset - np.abs(amplitude) < doll.control_low) or np.any(
            offset + np.abs(amplitude) > doll.control_high
        ):
            raise ValueError("RagdollTrack: the reference leaves the joints' target ranges")
        self.reference_offset = offset
        self.reference_amplitude = amplitude
        super().__init__(push_interval=push_interval, config=config, **kwargs)

    def reference(self, time: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(q_ref (26,) rad, dq_ref (26,) rad/s) at `time` s."""
        omega = 2.0 * jnp.pi / self.period
        offset = jnp.asarray(self.reference_offset, self.dtype)
        amplitude = jnp.asarray(self.reference_amplitude, self.dtype)
        return offset + amplitude * jnp.sin(omega * time), amplitude * omega * jnp.cos(omega * time)

    def reference_action(self, time: jnp.ndarray) -> jnp.ndarray:
        """The action whose drive targets are q_ref(time): the open-loop baseline."""
        return self.action_of_control(self.reference(time)[0])

    def initial_time(self, key: jnp.ndarray) -> jnp.ndarray:
        return jax.random.uniform(key, (), self.dtype, 0.0, self.period)

    def task_observation(self, state: EnvState) -> jnp.ndarray:
        time = state.task.time + self.dt  # the end of the coming step
        target, _ = self.reference(time)
        phase = 2.0 * jnp.pi * time / self.period
        return jnp.concatenate([self.observe_body(state), target, jnp.stack([jnp.sin(phase), jnp.cos(phase)])])

    def tracking_error(self, state: EnvState) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(mean squared position error rad^2, mean squared rate error (rad/s)^2) against the reference."""
        position, rate = self.joints(state.physics)
        target, target_rate = self.reference(state.task.time)
        return jnp.mean((position - target) ** 2), jnp.mean((rate - target_rate) ** 2)

    def task_reward(self, state: EnvState, action: jnp.ndarray, next_state: EnvState) -> dict[str, jnp.ndarray]:
        position_error, rate_error = self.tracking_error(next_state)
        return {
            "pose": self.pose_weight * jnp.exp(-self.pose_scale * position_error),
            "velocity": self.velocity_weight * jnp.exp(-0.1 * rate_error),
            "upright": -self.upright_weight * (1.0 - self.up(next_state.physics, self.torso)[2]),
            "alive": jnp.asarray(self.alive_bonus, self.dtype),
            "smooth": self.smooth_penalty(state, action),
        }

    def task_info(self, state: EnvState) -> dict[str, jnp.ndarray]:
        info = super().task_info(state)
        info["pose_error"] = math.safe_sqrt(self.tracking_error(state)[0])
        return info


# ---------------------------------------------------------------------------- Gymnasium entry points
class RagdollStandEnv(DbdEnv):
    """`gymnasium.make("dbdjax/RagdollStand-v0")`; kwargs go to `RagdollStand`."""

    def __init__(self, render_mode: str | None = None, jit_options: dict | None = None, **kwargs):
        super().__init__(RagdollStand(**kwargs), render_mode=render_mode, jit_options=jit_options)


class RagdollStandVectorEnv(DbdVectorEnv):
    """`gymnasium.make_vec("dbdjax/RagdollStand-v0", num_envs, vectorization_mode="vector_entry_point")`."""

    def __init__(
        self,
        num_envs: int = 1,
        render_mode: str | None = None,
        max_episode_steps: int | None = RagdollEnv.default_max_episode_steps,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        jit_options: dict | None = None,
        **kwargs,
    ):
        task = RagdollStand(max_episode_steps=max_episode_steps, **kwargs)
        super().__init__(task, num_envs, autoreset_mode, render_mode, jit_options)


class RagdollTrackEnv(DbdEnv):
    """`gymnasium.make("dbdjax/RagdollTrack-v0")`; kwargs go to `RagdollTrack`."""

    def __init__(self, render_mode: str | None = None, jit_options: dict | None = None, **kwargs):
        super().__init__(RagdollTrack(**kwargs), render_mode=render_mode, jit_options=jit_options)


class RagdollTrackVectorEnv(DbdVectorEnv):
    """`gymnasium.make_vec("dbdjax/RagdollTrack-v0", num_envs, vectorization_mode="vector_entry_point")`."""

    def __init__(
        self,
        num_envs: int = 1,
        render_mode: str | None = None,
        max_episode_steps: int | None = RagdollEnv.default_max_episode_steps,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        jit_options: dict | None = None,
        **kwargs,
    ):
        task = RagdollTrack(max_episode_steps=max_episode_steps, **kwargs)
        super().__init__(task, num_envs, autoreset_mode, render_mode, jit_options)
