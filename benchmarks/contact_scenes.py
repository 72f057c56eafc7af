"""Contact scenes of issue 4, measured: bounce height, friction ramp, stacks (and their cost).

    .venv/bin/python benchmarks/contact_scenes.py     # writes benchmarks/results/contact_scenes.json

Each scene is compiled once (the compile time is reported) and run; numbers are what the tests
in tests/test_contacts.py assert on, here with the settings they are sensitive to.
"""

from __future__ import annotations

import json
import math
import pathlib
import platform
import time

import jax
import numpy as np

import dbdjax as dbd


def run(model, steps):
    start = dbd.init(model)
    rollout = dbd.jit(lambda s: dbd.rollout(model, s, steps=steps))
    clock = time.perf_counter()
    compiled = rollout.lower(start).compile()
    compile_s = time.perf_counter() - clock
    clock = time.perf_counter()
    final, trajectory = jax.block_until_ready(compiled(start))
    run_s = time.perf_counter() - clock
    return trajectory, {"compile_s": round(compile_s, 2), "ms_per_step": round(1e3 * run_s / steps, 3)}


def bounce(substeps):
    b = dbd.ModelBuilder()
    ball = b.add_body(pos=(0, 0, 1.1))
    b.add_sphere(ball, 0.1, restitution=0.8)
    b.add_plane(restitution=0.8)
    trajectory, cost = run(b.finalize(dt=1 / 60, substeps=substeps, iterations=8), 200)
    height = np.asarray(trajectory.pos[:, 0, 2]) - 0.1
    peak = float(height[int(np.argmax(np.diff(height) > 0)) :].max())
    return {"substeps": substeps, "peak_m": round(peak, 4), "expected_m": 0.64, **cost}


def ramp(substeps, iterations, mu_s=0.5, mu_d=0.5, angle=35.0):
    slope = math.radians(angle)
    normal = np.array([-math.sin(slope), 0.0, math.cos(slope)])
    b = dbd.ModelBuilder()
    box = b.add_body(pos=0.1 * normal, quat=(math.cos(-slope / 2), 0, math.sin(-slope / 2), 0))
    b.add_box(box, (0.1, 0.1, 0.1), friction=mu_s, dynamic_friction=mu_d)
    b.add_plane(normal=normal, friction=mu_s, dynamic_friction=mu_d)
    trajectory, cost = run(b.finalize(dt=1 / 60, substeps=substeps, iterations=iterations), 120)
    travelled = np.linalg.norm(np.asarray(trajectory.pos[:, 0]) - 0.1 * normal, axis=1)
    acceleration = 2.0 * np.polyfit(np.arange(1, 121) / 60, travelled, 2)[0]
    expected = 9.81 * (math.sin(slope) - mu_d * math.cos(slope)) if math.tan(slope) > mu_s else 0.0
    return {"angle_deg": angle, "mu_s": mu_s, "mu_d": mu_d, "substeps": substeps, "iterations": iterations,
            "acceleration": round(float(acceleration), 4), "expected": round(expected, 4),
            "travel_2s_m": round(float(travelled[-1]), 5), **cost}  # fmt: skip


def boxes(name, positions, substeps, iterations, steps=300):
    b = dbd.ModelBuilder()
    for pos in positions:
        b.add_box(b.add_body(pos=pos), (0.1, 0.1, 0.1))
    b.add_plane()
    model = b.finalize(dt=1 / 60, substeps=substeps, iterations=iterations)
    trajectory, cost = run(model, steps)
    drift = np.linalg.norm(np.asarray(trajectory.pos) - np.asarray(positions), axis=2)
    return {"scene": name, "substeps": substeps, "iterations": iterations, "seconds": steps / 60,
            "max_drift_mm": round(float(np.nanmax(drift)) * 1e3, 3), "colours": model.structure.num_colours,
            **cost}  # fmt: skip


def main():
    stack = [(0.0, 0.0, 0.1 + 0.2 * i) for i in range(5)]
    pyramid = [((k - (3 - row) / 2) * 0.21, 0.0, 0.1 + 0.2 * row) for row in range(4) for k in range(4 - row)]
    results = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}",
        "bounce": [bounce(s) for s in (1, 4, 16)],
        "ramp": [ramp(4, 8), ramp(1, 16), ramp(4, 8, 0.5, 0.4), ramp(4, 8, 0.5, 0.3, angle=25.0)],
        "stacks": [boxes("stack5", stack, 1, 16), boxes("stack5", stack, 4, 8), boxes("pyramid10", pyramid, 1, 16)],
    }
    out = pathlib.Path(__file__).parent / "results" / "contact_scenes.json"
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
