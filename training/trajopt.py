"""Trajectory optimisation: an open-loop control sequence optimised by gradients through `dbd.rollout`.

    from dbdjax.training import trajopt
    task = trajopt.ik_chain_task(links=3, horizon=30)          # or ragdoll_pose_task(), ragdoll_jump_task()
    result = trajopt.optimise(task, steps=200, learning_rate=0.05)
    trajopt.save(result, task, "runs/ik_chain")                 # result.npz, metrics.json/.csv, plot.png

    python -m dbdjax.training.trajopt --task ik_chain --steps 200 --out runs/ik_chain

A `Task` is a model, a start state, a horizon T and a differentiable cost of the trajectory and
the controls (T, num_controls). `optimise` runs optax (gradient clipping by global norm, then
Adam) on the controls, projecting them into the task's control range after each update.

Long horizons: reverse mode stores every intermediate of the rollout (solver sweeps included)
unless told otherwise. Two rematerialisation knobs, usable together:
- `finalize(checkpoint=True)` (the `checkpoint` argument of the task builders, `--remat-substeps`)
  recomputes each substep's solver sweeps in the backward pass;
- `remat_chunk=k` (`--remat-chunk k`) wraps every k consecutive steps in `jax.checkpoint`: the
  forward pass keeps only the states at chunk boundaries (T / k of them), the backward pass
  re-runs one chunk at a time. Memory ~ T / k + k states instead of T x (solver intermediates),
  for about one extra forward pass of compute.
Both give the same gradient as the plain rollout (tests/test_trajopt.py checks it).

Tasks:
- `ik_chain_task`: an N-link chain of driven ball (or hinge) joints hanging from the world; its
  tip follows a target moving on a circle. Cost: mean over time of |tip - target|^2 (m^2) plus
  `effort` times the mean squared control.
- `ragdoll_pose_task`: the ragdoll of `dbdjax.ragdoll` (floor contacts) raises both arms into a
  V over its head and holds it while standing. Cost: mean over the second half of the horizon
  of the squared distances of hands, head and pelvis to their pose targets, plus effort.
- `ragdoll_jump_task`: the ragdoll jumps. Cost: minus the maximum pelvis height over the horizon
  (m; a smooth maximum) plus effort.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

import dbdjax as dbd
from dbdjax import math as dmath
from dbdjax.model import Model, State

from . import checkpoint

TASKS = ("ik_chain", "ragdoll_pose", "ragdoll_jump")


@dataclasses.dataclass(frozen=True)
class Task:
    """An open-loop control problem.

    name: a label. model, start: what `dbd.rollout` runs from. horizon: T steps.
    cost: (trajectory State with leading axis T, controls (T, num_controls)) -> scalar loss.
    initial_controls: (T, num_controls) where the optimiser starts.
    control_low, control_high: (num_controls,) bounds the controls are projected into after
      every update (None: unbounded).
    draw: (matplotlib Axes, trajectory State as numpy) -> None, the task's picture of a trajectory;
      projection: the Axes projection it wants ("3d" or None).
    settings: JSON-serialisable parameters of the task (saved with the result).
    report: trajectory State -> dict of task-specific numbers (floats) for the summary, e.g. the
      RMS tip error or the jump's peak height.
    """

    name: str
    model: Model
    start: State
    horizon: int
    cost: Callable[[State, jnp.ndarray], jnp.ndarray]
    initial_controls: np.ndarray
    control_low: np.ndarray | None = None
    control_high: np.ndarray | None = None
    draw: Callable[[Any, State], None] | None = None
    projection: str | None = None
    settings: dict = dataclasses.field(default_factory=dict)
    report: Callable[[State], dict] | None = None


@dataclasses.dataclass
class Result:
    """What `optimise` returns.

    controls: (T, num_controls) the optimised controls (after the last update).
    losses: (steps,) the loss of the controls before each update; final_loss: after the last.
    grad_norms: (steps,) global gradient norm before clipping. seconds: (steps,) wall time since
    the first update began (the first entry includes compilation). trajectory: the State
    trajectory (numpy, leading axis T) of the final controls. diverged: True when a loss or
    gradient went non-finite and the run stopped there (the controls are the last finite ones).
    """

    task: str
    controls: np.ndarray
    losses: np.ndarray
    grad_norms: np.ndarray
    seconds: np.ndarray
    final_loss: float
    trajectory: State
    compile_seconds: float
    diverged: bool
    settings: dict

    @property
    def reduction(self) -> float:
        """initial loss / final loss (meaningful for positive losses, like the IK chain's)."""
        return float(self.losses[0] / self.final_loss)


# ----------------------------------------------------------------------------- rollouts


def rollout(model: Model, state: State, controls: jnp.ndarray, remat_chunk: int | None = None) -> tuple[State, State]:
    """`dbd.rollout` with every `remat_chunk` consecutive steps wrapped in `jax.checkpoint`.

    controls: (T, num_controls). remat_chunk: None or 0 for the plain rollout; k >= 1 to keep only
    the states at chunk boundaries for the backward pass (the last chunk may be shorter).
    Returns (final state, trajectory with leading axis T), the same values as `dbd.rollout`.
    """
    horizon = controls.shape[0]
    if not remat_chunk or remat_chunk >= horizon:
        if remat_chunk:
            return jax.checkpoint(dbd.rollout)(model, state, controls)
        return dbd.rollout(model, state, controls)
    chunks, rest = divmod(horizon, remat_chunk)
    run_chunk = jax.checkpoint(dbd.rollout)  # model is an argument, so its leaves stay differentiable

    def one_chunk(s, chunk_controls):
        return run_chunk(model, s, chunk_controls)

    blocked = controls[: chunks * remat_chunk].reshape((chunks, remat_chunk) + controls.shape[1:])
    final, trajectory = jax.lax.scan(one_chunk, state, blocked)
    trajectory = jax.tree.map(lambda x: x.reshape((chunks * remat_chunk,) + x.shape[2:]), trajectory)
    if rest:
        final, tail = run_chunk(model, final, controls[chunks * remat_chunk :])
        trajectory = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), trajectory, tail)
    return final, trajectory


def loss_function(task: Task, remat_chunk: int | None = None) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """controls (T, num_controls) -> the task's scalar loss of the rollout from task.start."""

    def loss(controls: jnp.ndarray) -> jnp.ndarray:
        _, trajectory = rollout(task.model, task.start, controls, remat_chunk)
        return task.cost(trajectory, controls)

    return loss


# ----------------------------------------------------------------------------- tasks


def _point(trajectory: State, body: int, offset: jnp.ndarray) -> jnp.ndarray:
    """World position (T, 3) of a point fixed `offset` (body frame) on `body`."""
    return trajectory.pos[:, body] + dmath.quat_rotate(trajectory.quat[:, body], offset)


def ik_chain_task(
    links: int = 3,
    horizon: int = 30,
    joint: str = "ball",
    dt: float = 1.0 / 30.0,
    substeps: int = 1,
    iterations: int = 4,
    link_length: float = 0.25,
    link_mass: float = 0.5,
    stiffness: float = 300.0,
    damping: float = 10.0,
    radius: float | None = None,
    effort: float = 1e-4,
    gravity: float = 9.81,
    checkpoint: bool = False,
) -> Task:
    """A chain of `links` rods (length link_length m, mass link_mass kg) hanging from the world at
    the origin, every joint driven (`add_drive`: stiffness N m/rad, damping N m s/rad); its tip
    (the free end of the last rod) should follow a target moving once round a circle.

    joint: "ball" (3 controls per joint: the target rotation vector) or "hinge" (1 control per
    joint; axes alternate x, y, so the tip still moves in 3D). The circle (radius m, default 0.3 x
    the chain's length) starts at the resting tip, lies in the plane of x and (y + z) / sqrt(2),
    and is run once over the horizon. Cost: mean over the T steps of |tip - target|^2 (m^2) plus
    effort x the mean over steps of |control|^2 (rad^2). Controls are bounded to +-1.8 rad per
    entry for ball drives (+-3 for hinges), so no target passes pi. dt, substeps, iterations,
    checkpoint: `finalize` arguments (checkpoint=True rematerialises each substep).
    """
    if joint not in ("ball", "hinge"):
        raise ValueError(f"ik_chain_task: joint must be 'ball' or 'hinge', got {joint!r}")
    if links < 1 or horizon < 1:
        raise ValueError(f"ik_chain_task: need links >= 1 and horizon >= 1, got {links}, {horizon}")
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -gravity))
    along = link_mass * 0.02**2 / 2.0  # a rod of radius 2 cm: m r^2 / 2 about its axis
    across = link_mass * link_length**2 / 12.0
    previous = dbd.WORLD
    for i in range(links):
        body = b.add_body(pos=(0.0, 0.0, -(i + 0.5) * link_length), mass=link_mass, inertia=(across, across, along))
        anchor = (0.0, 0.0, -i * link_length)
        if joint == "ball":
            index = b.add_ball_joint(previous, body, anchor=anchor)
        else:
            index = b.add_hinge_joint(previous, body, anchor=anchor, axis=(1.0, 0.0, 0.0) if i % 2 else (0.0, 1.0, 0.0))
        b.add_drive(index, stiffness=stiffness, damping=damping)
        previous = body
    model = b.finalize(dt=dt, substeps=substeps, iterations=iterations, checkpoint=checkpoint)
    start = dbd.init(model)

    reach = links * link_length
    radius = 0.3 * reach if radius is None else float(radius)
    tip_offset = jnp.array([0.0, 0.0, -0.5 * link_length])
    rest_tip = np.array([0.0, 0.0, -reach])
    times = dt * np.arange(1, horizon + 1)
    phase = 2.0 * np.pi * times / (dt * horizon)
    across_x = np.array([1.0, 0.0, 0.0])
    across_yz = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)
    target = rest_tip + radius * (np.sin(phase)[:, None] * across_x + (1.0 - np.cos(phase))[:, None] * across_yz)
    last = links - 1

    def cost(trajectory: State, controls: jnp.ndarray) -> jnp.ndarray:
        tip = _point(trajectory, last, tip_offset.astype(trajectory.pos.dtype))
        error = tip - jnp.asarray(target, dtype=tip.dtype)
        return jnp.mean(jnp.sum(error * error, axis=-1)) + effort * jnp.mean(jnp.sum(controls * controls, axis=-1))

    def draw(ax, trajectory: State) -> None:
        tip = np.asarray(_point(trajectory, last, tip_offset))
        ax.plot(*target.T, "--", color="tab:red", label="target")
        ax.plot(*tip.T, color="tab:blue", label="tip")
        for t in np.linspace(0, horizon - 1, 5).astype(int):  # the chain at five instants
            # rod i spans joint i .. joint i + 1 with its centre halfway: next = 2 centre - this
            points = [np.zeros(3)]
            for i in range(links):
                points.append(2.0 * np.asarray(trajectory.pos[t, i]) - points[-1])
            ax.plot(*np.asarray(points).T, "-o", color="0.4", alpha=0.2 + 0.8 * t / max(horizon - 1, 1), markersize=3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        ax.set_title("IK chain: tip vs moving target")
        ax.legend(loc="upper left")

    settings = dict(links=links, horizon=horizon, joint=joint, dt=dt, substeps=substeps, iterations=iterations,
                    link_length=link_length, link_mass=link_mass, stiffness=stiffness, damping=damping,
                    radius=radius, effort=effort, gravity=gravity, checkpoint=checkpoint)  # fmt: skip

    def report(trajectory: State) -> dict:
        error = np.asarray(_point(trajectory, last, tip_offset)) - target
        distance = np.linalg.norm(error, axis=-1)
        return {"rms_tip_error_m": float(np.sqrt(np.mean(distance**2))), "max_tip_error_m": float(distance.max())}

    # Drive targets are rotations: a ball target beyond pi in norm (a hinge target beyond pi) is
    # the same pose reached the short way round, so the controls jump there. Bounds per entry keep
    # a ball target's norm within sqrt(3) x 1.8 < pi.
    bound = np.full(model.num_controls, 1.8 if joint == "ball" else 3.0)
    initial = np.zeros((horizon, model.num_controls), dtype=np.asarray(start.pos).dtype)
    return Task("ik_chain", model, start, horizon, cost, initial, -bound, bound, draw=draw, projection="3d",
                settings=settings, report=report)  # fmt: skip


def _ragdoll_model(horizon, dt, substeps, iterations, contact_compliance, checkpoint, height):
    from dbdjax import ragdoll

    if horizon < 1:
        raise ValueError(f"ragdoll task: horizon must be >= 1, got {horizon}")
    builder, doll = ragdoll.build(height=height)
    # None: the doll's own defaults (ragdoll.DT, SUBSTEPS, ITERATIONS: what its standing tests use)
    model = builder.finalize(
        dt=ragdoll.DT if dt is None else dt,
        substeps=ragdoll.SUBSTEPS if substeps is None else substeps,
        iterations=ragdoll.ITERATIONS if iterations is None else iterations,
        checkpoint=checkpoint,
        contact_compliance=contact_compliance,
    )
    return ragdoll, doll, model


def _draw_doll(ax, ragdoll, doll, positions: np.ndarray, view: int, **style) -> None:
    """A stick figure: every body centre joined to its parent's, seen along world axis `view`
    (0: front view, y right-left and z up; 1: side view, x and z)."""
    horizontal = 1 if view == 0 else 0
    for part in ragdoll.PARTS:
        if part.parent is not None:
            a, b = positions[doll.bodies[part.parent]], positions[doll.bodies[part.name]]
            ax.plot([a[horizontal], b[horizontal]], [a[2], b[2]], "-", **style)
            style.pop("label", None)  # one legend entry per figure


# Where the pose task wants its keypoints, for a doll of reference height 1.8 m standing at the
# origin facing +x: both arms raised 2.2 rad from hanging, out to the sides (a V over the head;
# the hand centre is 0.62 m from the shoulder, at (0, +-0.2, 1.43)), elbows straight; head and
# pelvis where they stand. Scaled with the doll's height.
POSE_TARGETS = {
    "hand_l": (0.0, 0.2 + 0.62 * math.sin(2.2), 1.43 - 0.62 * math.cos(2.2)),
    "hand_r": (0.0, -0.2 - 0.62 * math.sin(2.2), 1.43 - 0.62 * math.cos(2.2)),
}
POSE_STILL = ("head", "pelvis", "foot_l", "foot_r")  # these keep their standing positions


def ragdoll_pose_task(
    horizon: int = 60,
    dt: float | None = None,
    substeps: int | None = None,
    iterations: int | None = None,
    effort: float = 1e-3,
    contact_compliance: float = 0.0,
    height: float = 1.8,
    checkpoint: bool = False,
) -> Task:
    """The ragdoll (`dbdjax.ragdoll.build`, on its floor) strikes a pose: both arms raised in a V
    over the head (`POSE_TARGETS`), while head, pelvis and feet stay where they stand.

    Cost: over the second half of the horizon, the mean of the summed squared distances (m^2) of
    the hands, head, pelvis and feet to their targets, plus effort x the mean over steps of
    |control|^2 (rad^2). Controls are drive targets, bounded by the doll's control range. dt,
    substeps, iterations (None: the doll's defaults ragdoll.DT, SUBSTEPS, ITERATIONS),
    contact_compliance, checkpoint: `finalize` arguments.
    """
    ragdoll, doll, model = _ragdoll_model(horizon, dt, substeps, iterations, contact_compliance, checkpoint, height)
    start = dbd.init(model)
    standing = np.asarray(start.pos)
    scale = height / ragdoll.REFERENCE_HEIGHT
    names = list(POSE_TARGETS) + list(POSE_STILL)
    bodies = np.array([doll.bodies[name] for name in names])
    target = np.array([scale * np.asarray(POSE_TARGETS[name]) for name in POSE_TARGETS]
                      + [standing[doll.bodies[name]] for name in POSE_STILL])  # fmt: skip
    hold = horizon // 2  # the pose is judged over steps hold .. T - 1

    def cost(trajectory: State, controls: jnp.ndarray) -> jnp.ndarray:
        error = trajectory.pos[hold:, bodies] - jnp.asarray(target, dtype=trajectory.pos.dtype)
        return jnp.mean(jnp.sum(error * error, axis=(-2, -1))) + effort * jnp.mean(
            jnp.sum(controls * controls, axis=-1)
        )

    def draw(ax, trajectory: State) -> None:
        _draw_doll(ax, ragdoll, doll, standing, view=0, color="0.7", label="start")
        _draw_doll(ax, ragdoll, doll, np.asarray(trajectory.pos[-1]), view=0, color="tab:blue", marker="o",
                   markersize=3, label="last step")  # fmt: skip
        ax.plot(target[:, 1], target[:, 2], "x", color="tab:red", markersize=9, label="targets")
        ax.set_aspect("equal")
        ax.set_xlabel("y (m)")
        ax.set_ylabel("z (m)")
        ax.set_title("ragdoll pose: start (grey), last step (blue)")
        ax.legend(loc="lower right")

    settings = dict(horizon=horizon, dt=model.dt, substeps=model.options.substeps,
                    iterations=model.options.iterations, effort=effort,
                    contact_compliance=contact_compliance, height=height, checkpoint=checkpoint)  # fmt: skip

    def report(trajectory: State) -> dict:
        error = np.linalg.norm(np.asarray(trajectory.pos[hold:, bodies]) - target, axis=-1)
        hands = [names.index(name) for name in POSE_TARGETS]
        return {"rms_keypoint_error_m": float(np.sqrt(np.mean(error**2))),
                "final_hand_error_m": float(np.max(error[-1, hands])),
                "final_pelvis_height_m": float(trajectory.pos[-1, doll.bodies["pelvis"], 2])}  # fmt: skip

    initial = np.zeros((horizon, model.num_controls), dtype=standing.dtype)
    return Task("ragdoll_pose", model, start, horizon, cost, initial, doll.control_low, doll.control_high, draw,
                settings=settings, report=report)  # fmt: skip


def ragdoll_jump_task(
    horizon: int = 45,
    dt: float | None = None,
    substeps: int | None = None,
    iterations: int | None = None,
    effort: float = 1e-4,
    sharpness: float = 0.01,
    contact_compliance: float = 0.0,
    height: float = 1.8,
    checkpoint: bool = False,
) -> Task:
    """The ragdoll jumps: cost = - (smooth) maximum over the horizon of the pelvis centre's height
    (m), sharpness * logsumexp(z / sharpness) (within sharpness * log T of the maximum), plus effort
    x the mean over steps of |control|^2 (rad^2). Starts standing with zero controls (the build
    pose). dt, substeps, iterations (None: the doll's defaults), contact_compliance, checkpoint:
    `finalize` arguments.
    """
    ragdoll, doll, model = _ragdoll_model(horizon, dt, substeps, iterations, contact_compliance, checkpoint, height)
    start = dbd.init(model)
    pelvis = doll.bodies["pelvis"]

    def cost(trajectory: State, controls: jnp.ndarray) -> jnp.ndarray:
        peak = sharpness * jax.nn.logsumexp(trajectory.pos[:, pelvis, 2] / sharpness)
        return -peak + effort * jnp.mean(jnp.sum(controls * controls, axis=-1))

    def draw(ax, trajectory: State) -> None:
        times = model.dt * np.arange(1, horizon + 1)
        heights = np.asarray(trajectory.pos[:, pelvis, 2])
        ax.plot(times, heights, color="tab:blue", label="pelvis centre")
        ax.axhline(float(start.pos[pelvis, 2]), color="0.6", linestyle="--", label="standing")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("height (m)")
        ax.set_title(f"ragdoll jump: peak {heights.max():.3f} m")
        ax.legend(loc="lower right")

    settings = dict(horizon=horizon, dt=model.dt, substeps=model.options.substeps,
                    iterations=model.options.iterations, effort=effort,
                    sharpness=sharpness, contact_compliance=contact_compliance, height=height,
                    checkpoint=checkpoint)  # fmt: skip

    def report(trajectory: State) -> dict:
        heights = np.asarray(trajectory.pos[:, pelvis, 2])
        lowest = np.asarray(ragdoll.lowest_point(model, jax.tree.map(jnp.asarray, trajectory)))
        feet = lowest[:, [doll.shapes["foot_l"], doll.shapes["foot_r"]]].min(axis=-1)
        return {"peak_pelvis_height_m": float(heights.max()), "standing_pelvis_height_m": float(start.pos[pelvis, 2]),
                "peak_feet_clearance_m": float(feet.max())}  # fmt: skip

    initial = np.zeros((horizon, model.num_controls), dtype=np.asarray(start.pos).dtype)
    return Task("ragdoll_jump", model, start, horizon, cost, initial, doll.control_low, doll.control_high, draw,
                settings=settings, report=report)  # fmt: skip


# ----------------------------------------------------------------------------- optimiser


def optimiser(
    learning_rate: float = 0.05, clip_norm: float | None = 1.0, decay_steps: int | None = None, final_fraction=0.1
) -> optax.GradientTransformation:
    """Adam after clipping the gradient to global norm `clip_norm` (None: no clipping).

    decay_steps: None for a constant learning rate; else a cosine decay from `learning_rate` to
    `final_fraction` of it over that many steps (Adam's steps are ~lr per coordinate whatever the
    gradient's size, so a constant rate keeps jittering the controls once the loss is small).
    """
    rate = (
        learning_rate
        if decay_steps is None
        else optax.cosine_decay_schedule(learning_rate, decay_steps, final_fraction)
    )
    adam = optax.adam(rate)
    return adam if clip_norm is None else optax.chain(optax.clip_by_global_norm(clip_norm), adam)


def make_update(task: Task, transform: optax.GradientTransformation, remat_chunk: int | None = None) -> Callable:
    """A jitted optimiser step:
    (controls, opt_state) -> (new controls, new opt_state, loss, grad_norm, trajectory).

    loss, grad_norm (before clipping) and trajectory are those of the controls passed in (before
    the update); the new controls are projected into [task.control_low, task.control_high] when
    the task has bounds.
    """

    def loss_and_trajectory(controls):
        _, trajectory = rollout(task.model, task.start, controls, remat_chunk)
        return task.cost(trajectory, controls), trajectory

    low = None if task.control_low is None else jnp.asarray(task.control_low)
    high = None if task.control_high is None else jnp.asarray(task.control_high)

    @dbd.jit
    def update(controls, opt_state):
        (value, trajectory), gradient = jax.value_and_grad(loss_and_trajectory, has_aux=True)(controls)
        updates, opt_state = transform.update(gradient, opt_state, controls)
        new_controls = optax.apply_updates(controls, updates)
        if low is not None or high is not None:
            new_controls = jnp.clip(new_controls, low, high)
        return new_controls, opt_state, value, jnp.sqrt(jnp.sum(gradient * gradient)), trajectory

    return update


class _Progress:
    """A progress bar: tqdm if installed, else rich, else a line every 10% (none if disabled)."""

    def __init__(self, total: int, description: str, enabled: bool):
        self.total, self.description, self.kind, self.count = total, description, None, 0
        if not enabled:
            return
        try:
            from tqdm.auto import tqdm

            self.bar, self.kind = tqdm(total=total, desc=description), "tqdm"
            return
        except ImportError:
            pass
        try:
            from rich import progress

            columns = (*progress.Progress.get_default_columns(), progress.TextColumn("loss {task.fields[loss]}"))
            self.bar, self.kind = progress.Progress(*columns), "rich"
            self.bar.start()
            self.task = self.bar.add_task(description, total=total, loss="?")
        except ImportError:
            self.kind = "print"

    def update(self, loss: float) -> None:
        self.count += 1
        if self.kind == "tqdm":
            self.bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
            self.bar.update(1)
        elif self.kind == "rich":
            self.bar.update(self.task, advance=1, loss=f"{loss:.4g}")
        elif self.kind == "print" and (self.count % max(self.total // 10, 1) == 0 or self.count == self.total):
            print(f"{self.description}: step {self.count}/{self.total}, loss {loss:.4g}", flush=True)

    def close(self) -> None:
        if self.kind in ("tqdm", "rich"):
            self.bar.close() if self.kind == "tqdm" else self.bar.stop()


def optimise(
    task: Task,
    steps: int = 200,
    learning_rate: float = 0.05,
    clip_norm: float | None = 1.0,
    decay: bool = True,
    remat_chunk: int | None = None,
    progress: bool = True,
    controls: np.ndarray | None = None,
) -> Result:
    """Optimise the task's controls for `steps` optimiser steps: Adam (learning rate
    `learning_rate`, cosine-decayed to a tenth over the run if `decay`) after clipping the
    gradient to global norm `clip_norm`. remat_chunk: see `rollout`. controls: (T, num_controls)
    start (default task.initial_controls).

    Stops early, with `diverged=True`, if the loss or the gradient goes non-finite (the controls
    are then the last ones with a finite loss and gradient).
    """
    transform = optimiser(learning_rate, clip_norm, decay_steps=steps if decay else None)
    update = make_update(task, transform, remat_chunk)
    current = jnp.asarray(task.initial_controls if controls is None else controls)
    opt_state = transform.init(current)
    losses, norms, seconds = [], [], []
    diverged, compile_seconds = False, 0.0
    bar = _Progress(steps, task.name, progress)
    begin = time.perf_counter()
    try:
        for index in range(steps):
            proposed, new_state, loss, norm, _ = update(current, opt_state)
            loss, norm = float(loss), float(norm)
            if index == 0:
                compile_seconds = time.perf_counter() - begin
            if not (math.isfinite(loss) and math.isfinite(norm)):
                diverged = True
                break
            losses.append(loss)
            norms.append(norm)
            seconds.append(time.perf_counter() - begin)
            current, opt_state = proposed, new_state
            bar.update(loss)
    finally:
        bar.close()
    # The loss and trajectory of the final controls: one more call (its update is discarded).
    _, _, final_loss, _, trajectory = update(current, opt_state)
    return Result(
        task=task.name,
        controls=np.asarray(current),
        losses=np.asarray(losses),
        grad_norms=np.asarray(norms),
        seconds=np.asarray(seconds),
        final_loss=float(final_loss),
        trajectory=jax.tree.map(np.asarray, trajectory),
        compile_seconds=compile_seconds,
        diverged=diverged,
        settings=dict(
            task=task.settings,
            steps=steps,
            learning_rate=learning_rate,
            clip_norm=clip_norm,
            decay=decay,
            remat_chunk=remat_chunk,
        ),  # fmt: skip
    )


# ----------------------------------------------------------------------------- results


def save(result: Result, task: Task, out: str | Path, plot: bool = True) -> dict[str, Path]:
    """Write a result to the folder `out`: result.npz (controls, losses, gradient norms, times,
    the final trajectory; a `checkpoint` file, loadable without pickle), metrics.json (settings
    and the numbers), metrics.csv (step, loss, grad_norm, seconds) and, if plot and matplotlib is
    installed, plot.png (loss curve and the task's trajectory). Returns the paths written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = dict(task=result.task, settings=result.settings, initial_loss=float(result.losses[0]) if len(
        result.losses) else None, final_loss=result.final_loss, steps_run=len(result.losses),
        compile_seconds=result.compile_seconds, seconds=float(result.seconds[-1]) if len(result.seconds) else 0.0,
        diverged=result.diverged)  # fmt: skip
    if task.report is not None:
        summary["report"] = task.report(result.trajectory)
    tree = dict(controls=result.controls, losses=result.losses, grad_norms=result.grad_norms, seconds=result.seconds,
                trajectory=result.trajectory)  # fmt: skip
    paths = {"result": checkpoint.save(out / "result.npz", tree, metadata=summary)}
    paths["json"] = out / "metrics.json"
    paths["json"].write_text(json.dumps(dict(summary, losses=result.losses.tolist()), indent=1))
    paths["csv"] = out / "metrics.csv"
    with paths["csv"].open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["step", "loss", "grad_norm", "seconds"])
        for row in zip(range(len(result.losses)), result.losses, result.grad_norms, result.seconds, strict=True):
            writer.writerow([row[0], *(f"{value:.9g}" for value in row[1:])])
    if plot:
        try:
            paths["plot"] = plot_result(result, task, out / "plot.png")
        except ImportError:
            print("matplotlib is not installed: no plot (pip install 'dbdjax[train]')", file=sys.stderr)
    return paths


def figure_result(result: Result, task: Task):
    """A matplotlib Figure: the loss curve (left) and the task's picture of the final trajectory
    (right). Made without pyplot, so it changes no backend (notebooks display it inline)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 4.5))
    curve = figure.add_subplot(1, 2, 1)
    losses = np.append(result.losses, result.final_loss)
    curve.plot(np.arange(len(losses)), losses, color="tab:blue")
    if np.all(losses > 0):
        curve.set_yscale("log")
    curve.set_xlabel("optimiser step")
    curve.set_ylabel("loss")
    curve.set_title(f"{task.name}: loss {losses[0]:.3g} -> {losses[-1]:.3g}")
    curve.grid(True, alpha=0.3)
    if task.draw is not None:
        task.draw(figure.add_subplot(1, 2, 2, projection=task.projection), result.trajectory)
    figure.tight_layout()
    return figure


def plot_result(result: Result, task: Task, path: str | Path) -> Path:
    """Write `figure_result` to `path` as a PNG (100 dpi). Returns the path."""
    figure_result(result, task).savefig(path, dpi=100)
    return Path(path)


# ----------------------------------------------------------------------------- command line


def make_task(name: str, horizon: int | None = None, checkpoint_substeps: bool = False, **options: Any) -> Task:
    """The task called `name` (one of TASKS) with its defaults, or the given horizon and options."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {TASKS}")
    builders = {"ik_chain": ik_chain_task, "ragdoll_pose": ragdoll_pose_task, "ragdoll_jump": ragdoll_jump_task}
    if horizon is not None:
        options["horizon"] = horizon
    return builders[name](checkpoint=checkpoint_substeps, **options)


def main(argv: list[str] | None = None) -> Result:
    parser = argparse.ArgumentParser(
        prog="python -m dbdjax.training.trajopt",
        description="Optimise an open-loop control sequence by gradients through dbd.rollout (optax Adam with "
        "gradient clipping); writes result.npz, metrics.json, metrics.csv and plot.png to --out.",
    )
    parser.add_argument("--task", choices=TASKS, default="ik_chain")
    parser.add_argument("--steps", type=int, default=200, help="optimiser steps (default 200)")
    parser.add_argument("--horizon", type=int, default=None, help="control steps T (default: the task's)")
    parser.add_argument("--lr", type=float, default=None, help="Adam learning rate (default: the task's)")
    parser.add_argument("--clip", type=float, default=1.0, help="clip gradients to this global norm (0: off)")
    parser.add_argument("--no-decay", action="store_true", help="constant learning rate (default: cosine decay)")
    parser.add_argument("--links", type=int, default=3, help="ik_chain: number of links")
    parser.add_argument("--joint", choices=("ball", "hinge"), default="ball", help="ik_chain: joint type")
    parser.add_argument("--remat-chunk", type=int, default=0, help="jax.checkpoint every K steps (0: off)")
    parser.add_argument("--remat-substeps", action="store_true", help="finalize(checkpoint=True): remat substeps")
    parser.add_argument("--x64", action="store_true", help="run in float64")
    parser.add_argument("--out", default="trajopt_output", help="output folder (default trajopt_output/<task>)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-plot", action="store_true", help="no plot.png")
    args = parser.parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)

    options: dict[str, Any] = {}
    if args.task == "ik_chain":
        options.update(links=args.links, joint=args.joint)
    task = make_task(args.task, horizon=args.horizon, checkpoint_substeps=args.remat_substeps, **options)
    learning_rate = DEFAULT_LEARNING_RATES[args.task] if args.lr is None else args.lr
    result = optimise(
        task,
        steps=args.steps,
        learning_rate=learning_rate,
        clip_norm=args.clip or None,
        decay=not args.no_decay,
        remat_chunk=args.remat_chunk or None,
        progress=not args.no_progress,
    )
    out = Path(args.out) / args.task
    paths = save(result, task, out, plot=not args.no_plot)
    print(f"{task.name}: loss {result.losses[0]:.6g} -> {result.final_loss:.6g} in {len(result.losses)} steps "
          f"({result.seconds[-1]:.1f} s, {result.compile_seconds:.1f} s of it compiling)"
          + (" DIVERGED" if result.diverged else ""))  # fmt: skip
    if task.report is not None:
        print("  " + ", ".join(f"{key} {value:.4g}" for key, value in task.report(result.trajectory).items()))
    for kind, path in paths.items():
        print(f"  {kind}: {path}")
    return result


DEFAULT_LEARNING_RATES = {"ik_chain": 0.05, "ragdoll_pose": 0.02, "ragdoll_jump": 0.02}

if __name__ == "__main__":
    main()
