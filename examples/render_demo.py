"""Pictures of a simulation: boxes and balls tumble onto the ground next to a swinging chain.

Simulates 3 s, renders every step at 320x240 with `dbdjax.render` (a JAX ray caster: shadows,
checkerboard ground) and writes demo_output/render_demo.gif plus demo_output/render_demo.png
(six frames side by side). Prints the time per frame.

    python examples/render_demo.py [--frames-per-second 30] [--width 320 --height 240]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

import dbdjax as dbd
from dbdjax import render as R
from dbdjax.video import save_image, save_video

SECONDS = 3.0


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """(w, x, y, z) of a rotation by `angle` (rad) about `axis`."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def build() -> dbd.Model:
    b = dbd.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_plane(friction=0.8)
    # a post on the world with a chain of five capsules hanging off its arm, released sideways
    b.add_box(dbd.WORLD, half_extents=(0.06, 0.06, 0.8), pos=(-1.2, 0.6, 0.8))
    b.add_box(dbd.WORLD, half_extents=(0.35, 0.05, 0.05), pos=(-0.9, 0.6, 1.6))
    previous, anchor = dbd.WORLD, np.array([-0.6, 0.6, 1.55])
    for _ in range(5):
        link = b.add_body(pos=anchor + (0.1, 0.0, 0.0))
        b.add_capsule(link, radius=0.035, half_length=0.065, quat=quat_from_axis_angle((0.0, 1.0, 0.0), np.pi / 2))
        b.add_ball_joint(previous, link, anchor=anchor)
        previous, anchor = link, anchor + (0.2, 0.0, 0.0)
    # boxes and balls dropped from above, turned so that they land on edges and tumble
    for i, (x, y, z) in enumerate([(0.2, 0.0, 0.6), (0.35, 0.1, 1.2), (0.1, -0.05, 1.8)]):
        box = b.add_body(pos=(x, y, z), quat=quat_from_axis_angle((1.0, 0.3 * i, 0.2), 0.4 + 0.3 * i))
        b.add_box(box, half_extents=(0.15, 0.12, 0.1), friction=0.6, density=300.0)
    for x, y, z, vx in [(0.9, -0.3, 0.8, -0.8), (-0.3, -0.4, 1.4, 0.6)]:
        ball = b.add_body(pos=(x, y, z), vel=(vx, 0.0, 0.0))
        b.add_sphere(ball, radius=0.12, restitution=0.6, density=400.0)
    return b.finalize(dt=1 / 60, substeps=2, iterations=16)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--frames-per-second", type=float, default=30.0, help="of the GIF (the simulation runs at 60)")
    args = parser.parse_args()

    model = build()
    steps = int(SECONDS / model.dt)
    _, trajectory = dbd.jit(lambda s: dbd.rollout(model, s, steps=steps))(dbd.init(model))
    every = max(1, round(1.0 / (model.dt * args.frames_per_second)))
    states = jax.tree.map(lambda x: x[::every], trajectory)
    frames_count = states.pos.shape[0]
    camera = R.camera_looking_at(
        (-0.2, 0.1, 0.65), distance=3.3, azimuth=-72.0, elevation=14.0, width=args.width, height=args.height
    )

    draw = jax.jit(lambda s: R.render(model, s, camera))
    one = jax.tree.map(lambda x: x[0], states)
    started = time.perf_counter()
    draw(one).block_until_ready()
    compiled = time.perf_counter() - started
    repeats = 10
    started = time.perf_counter()
    for _ in range(repeats):
        draw(one).block_until_ready()
    single = (time.perf_counter() - started) / repeats
    started = time.perf_counter()
    frames = np.asarray(R.render_rollout(model, states, camera))  # compiles, then renders in batches
    whole = time.perf_counter() - started
    started = time.perf_counter()
    frames = np.asarray(R.render_rollout(model, states, camera))
    rolled = time.perf_counter() - started

    out = Path("demo_output")
    gif = save_video(frames, out / "render_demo.gif", fps=args.frames_per_second)
    sheet = np.concatenate([frames[i] for i in np.linspace(0, frames_count - 1, 6).astype(int)], axis=1)
    png = save_image(sheet, out / "render_demo.png")
    save_image(frames[frames_count // 2], out / "render_demo_frame.png")
    shapes = model.structure.shape_kind.array.size
    print(f"{model.num_bodies} bodies, {shapes} shapes, {steps} steps; {frames_count} frames of "
          f"{args.width}x{args.height} on {jax.devices()[0].platform}")  # fmt: skip
    print(f"  one frame: compile {compiled:.1f} s, then {single * 1e3:.1f} ms per frame (with shadows)")
    print(f"  render_rollout: {rolled * 1e3 / frames_count:.1f} ms per frame ({whole:.1f} s with its compile)")
    print(f"  wrote {gif} and {png}")


if __name__ == "__main__":
    main()
