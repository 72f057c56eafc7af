"""A driven ragdoll on the floor: it stands, spreads and raises its arms, waves and bends its knees, driven to
a new pose every second (`ragdoll.pose_control`: one call per animation frame). Prints what
happened (pelvis height, largest joint gap, lowest point, finiteness) and writes
demo_output/ragdoll_demo.gif and a strip of six frames, demo_output/ragdoll_demo.png.

    python examples/ragdoll_demo.py [--width 320 --height 240]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dbdjax as dbd
from dbdjax import ragdoll
from dbdjax import render as pictures
from dbdjax.video import save_image, save_video

OUTPUT = Path(__file__).resolve().parents[1] / "demo_output"
# One pose per second (joint name -> hinge angle or ball rotation vector, rad; the rest: build pose).
KEYFRAMES = [
    {},  # stand
    {"shoulder_l": (-1.2, 0.0, 0.0), "shoulder_r": (1.2, 0.0, 0.0)},  # arms out
    {"shoulder_l": (-2.2, 0.0, 0.0), "shoulder_r": (2.2, 0.0, 0.0)},  # arms up
    {"shoulder_r": (2.2, 0.0, 0.0), "elbow_r": 1.2, "neck": (0.0, 0.0, 0.5)},  # wave
    {"shoulder_r": (2.2, 0.0, 0.0), "elbow_r": 0.2, "neck": (0.0, 0.0, -0.5)},
    # knees bent: shins forward (ankles), thighs forward (hips), so the pelvis stays over the feet
    {"knee_l": 0.5, "knee_r": 0.5, "ankle_l": -0.25, "ankle_r": -0.25, "hip_l": (0.0, -0.25, 0.0),
     "hip_r": (0.0, -0.25, 0.0), "waist": (0.0, 0.2, 0.0)},
]  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    args = parser.parse_args()

    builder, doll = ragdoll.build()
    model = builder.finalize(dt=ragdoll.DT, substeps=ragdoll.SUBSTEPS, iterations=ragdoll.ITERATIONS)
    steps_per_key = int(round(1.0 / model.dt))
    rows = []
    for pose in KEYFRAMES:
        control = ragdoll.pose_control(doll, pose)
        rows += [control] * steps_per_key
    controls = jnp.asarray(np.stack(rows), jnp.float32)

    options = model.options
    print(f"ragdoll: {model.num_bodies} bodies, {len(doll.joints)} joints, {model.num_controls} drive targets, "
          f"dt {model.dt:.4f} s, {options.substeps} substeps x {options.iterations} iterations")  # fmt: skip
    started = time.perf_counter()
    run = dbd.jit(lambda s, c: dbd.rollout(model, s, c))
    final, trajectory = run(dbd.init(model), controls)
    jax.block_until_ready(final)
    seconds = time.perf_counter() - started

    pelvis = np.asarray(trajectory.pos[:, doll.bodies["pelvis"], 2])
    gaps = np.asarray(dbd.diagnostics.joint_gaps(model, trajectory)).max(axis=-1)
    lowest = np.asarray(jax.vmap(lambda s: ragdoll.lowest_point(model, s))(trajectory))
    for k, pose in enumerate(KEYFRAMES):
        window = slice(k * steps_per_key, (k + 1) * steps_per_key)
        name = ", ".join(sorted(pose))[:40] or "stand"
        print(f"  second {k + 1}: {name:<42} pelvis {pelvis[window].min():.3f}..{pelvis[window].max():.3f} m, "
              f"largest joint gap {gaps[window].max() * 1e3:.2f} mm, "
              f"lowest point {lowest[window].min() * 1e3:+.1f} mm")  # fmt: skip
    print(f"  {len(controls)} steps in {seconds:.1f} s (compile included); all finite: {bool(dbd.is_finite(final))}")

    every = max(1, round(1.0 / (model.dt * 20)))  # 20 frames per second
    states = jax.tree.map(lambda x: x[::every], trajectory)
    camera = pictures.camera_looking_at((0.0, 0.0, 0.9), distance=4.0, azimuth=-60.0, elevation=12.0,
                                        width=args.width, height=args.height)  # fmt: skip
    frames = np.asarray(pictures.render_rollout(model, states, camera))
    OUTPUT.mkdir(exist_ok=True)
    gif = save_video(frames, OUTPUT / "ragdoll_demo.gif", fps=20)
    strip = np.concatenate([frames[i] for i in np.linspace(0, len(frames) - 1, 6).astype(int)], axis=1)
    png = save_image(strip, OUTPUT / "ragdoll_demo.png")
    print(f"wrote {gif} ({len(frames)} frames) and {png}")


if __name__ == "__main__":
    main()
