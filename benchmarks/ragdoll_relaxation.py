"""Over-relaxed joints on the driven ragdoll (DBD 4.2, `ragdoll.build(relaxation=xi)`): how many
sweeps the doll of RagdollStand-v0 needs to stand and recover with xi > 1, what they cost, and
what they leave in violent motion.

    .venv/bin/python benchmarks/ragdoll_relaxation.py   # writes benchmarks/results/ragdoll_relaxation.json

For each (substeps, iterations, xi) of --settings, at dt = 1/60, batch 1:
- kicked lean: the ankles driven to -0.036 rad (the env's action -0.045), ramped in over 1 s,
  the torso kicked at 2, 4, 6 and 8 s (0.45 m/s backwards, 0.45 forwards, 0.5 to its left, 0.35
  back and right), 10 s; whether the pelvis stays above 0.9 m, the largest distance of the pelvis
  from the reference setting's (the first of --settings, many sweeps), the joint angles' largest
  and RMS difference from it (the env's 26 joint coordinates), and the ankles 2 s in (before any
  kick; the drive's own sag under the load, converged, is -0.0375 rad);
- sideways fall: the doll at its build pose kicked over at 2 m/s; the fastest body afterwards,
  the largest joint gap, the kinetic energy 4 s later;
- CPU ms per physics step of the kicked-lean rollout (batch 1), and with --batch B of the env's
  physics at batch B (16-step jitted rollouts, zero control, best of 5).
Times are this process's CPU time; run it alone (one core is enough: `taskset -c 0`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dbdjax as dbd  # noqa: E402
from dbdjax import ragdoll  # noqa: E402
from envs.ragdoll_envs import RagdollStand  # noqa: E402

LEAN_ACTION = -0.045  # the ankles' action of the leaning doll (target 0.8 x action rad)
ANKLES = (20, 25)  # the ankles' entries of the action and of the joint coordinates
KICKS = {120: (-0.45, 0.0), 240: (0.45, 0.0), 360: (0.0, 0.5), 480: (-0.35, -0.35)}  # env step: (x, y) m/s
STEPS = 600
DEFAULT_SETTINGS = ["4x64x1.0", "4x8x1.0", "4x8x1.3", "4x6x1.0", "4x4x1.0", "4x4x1.3", "4x4x1.5", "3x6x1.3",
                    "2x8x1.3"]  # fmt: skip


def parse(setting: str) -> tuple[int, int, float]:
    substeps, iterations, relaxation = setting.split("x")
    return int(substeps), int(iterations), float(relaxation)


def kicked_lean(substeps: int, iterations: int, relaxation: float) -> dict:
    """The leaning doll through the four kicks: pelvis path, joint coordinates, CPU ms per step."""
    env = RagdollStand(push_interval=None, substeps=substeps, iterations=iterations, relaxation=relaxation)
    model, torso, pelvis = env.model, env.torso, env.pelvis
    action = np.zeros(env.action_size, np.float32)
    action[list(ANKLES)] = LEAN_ACTION
    control = env.control(jnp.asarray(action))
    kicks = np.zeros((STEPS, 3), np.float32)
    for step, (x, y) in KICKS.items():
        kicks[step, :2] = (x, y)

    def one(state, inputs):
        step, kick = inputs
        state = dataclasses.replace(state, vel=state.vel.at[torso].add(kick))
        state = dbd.step(model, state, control * jnp.minimum(step / 60.0, 1.0))
        return state, (state.pos[pelvis], env.joints(state)[0])

    run = jax.jit(lambda s: jax.lax.scan(one, s, (jnp.arange(STEPS), jnp.asarray(kicks)))[1])
    start = dbd.init(model)
    compiled = run.lower(start).compile()
    jax.block_until_ready(compiled(start))
    clock = time.process_time()
    pelvis_path, angles = jax.block_until_ready(compiled(start))
    ms = 1e3 * (time.process_time() - clock) / STEPS
    return {"pelvis": np.asarray(pelvis_path), "angles": np.asarray(angles), "ms_per_step": ms}


def sideways_fall(substeps: int, iterations: int, relaxation: float, speed: float = 2.0) -> dict:
    """The doll kicked over sideways at its build pose: the fastest body after, gaps, energy at the end."""
    builder, doll = ragdoll.build(relaxation=relaxation)
    model = builder.finalize(dt=ragdoll.DT, substeps=substeps, iterations=iterations)
    torso = doll.bodies["torso"]

    def one(state, _):
        state = dbd.step(model, state, jnp.zeros(model.num_controls))
        speed_now = jnp.max(jnp.linalg.norm(state.vel, axis=-1))
        return state, (speed_now, jnp.max(dbd.diagnostics.joint_gaps(model, state)))

    kicked = dataclasses.replace(dbd.init(model), vel=dbd.init(model).vel.at[torso, 1].add(speed))
    final, (speeds, gaps) = jax.jit(lambda s: jax.lax.scan(one, s, None, length=240))(kicked)
    still = dataclasses.replace(final, vel=jnp.zeros_like(final.vel), ang_vel=jnp.zeros_like(final.ang_vel))
    energy = dbd.diagnostics.energy(model, final) - dbd.diagnostics.energy(model, still)  # kinetic, spin included
    return {
        "fastest_body_m_s": round(float(speeds.max()), 2),
        "largest_joint_gap_mm": round(1e3 * float(gaps.max()), 2),
        "kinetic_energy_after_4s_j": round(float(energy), 4),
    }


def env_physics_ms(substeps: int, iterations: int, relaxation: float, batch: int) -> float:
    """CPU ms per physics step of the env's model at `batch` (best of 5 16-step rollouts)."""
    model = RagdollStand(substeps=substeps, iterations=iterations, relaxation=relaxation).model
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), dbd.init(model))
    controls = jnp.zeros((16, batch, model.num_controls))
    one = jax.vmap(lambda s, c: dbd.step(model, s, c))
    compiled = jax.jit(lambda s: jax.lax.scan(lambda s, c: (one(s, c), None), s, controls)[0]).lower(state).compile()
    jax.block_until_ready(compiled(state))
    best = np.inf
    for _ in range(5):
        clock = time.process_time()
        jax.block_until_ready(compiled(state))
        best = min(best, time.process_time() - clock)
    return 1e3 * best / 16


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--settings", nargs="+", default=DEFAULT_SETTINGS,
                        help="SUBSTEPSxITERATIONSxRELAXATION; the first is the reference")  # fmt: skip
    parser.add_argument("--batch", type=int, default=32, help="batch of the env-physics timing (0: none)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "ragdoll_relaxation.json")
    args = parser.parse_args()
    result = {"machine": machine.describe(), "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
              "dt": ragdoll.DT, "kicks": {str(k): v for k, v in KICKS.items()}, "reference": args.settings[0],
              "settings": []}  # fmt: skip
    reference = None
    for setting in args.settings:
        substeps, iterations, relaxation = parse(setting)
        lean = kicked_lean(substeps, iterations, relaxation)
        if reference is None:
            reference = lean
        difference = lean["angles"] - reference["angles"]
        entry = {
            "setting": setting,
            "stands": bool(lean["pelvis"][:, 2].min() > 0.9),
            "pelvis_min_height_m": round(float(lean["pelvis"][:, 2].min()), 4),
            "pelvis_from_reference_mm": round(1e3 * float(np.abs(lean["pelvis"] - reference["pelvis"]).max()), 1),
            "joint_angles_max_difference_rad": round(float(np.abs(difference).max()), 4),
            "joint_angles_rms_difference_rad": round(float(np.sqrt(np.mean(difference**2))), 5),
            "ankles_at_2s_rad": [round(float(a), 4) for a in lean["angles"][119, list(ANKLES)]],
            "ms_per_step_batch1": round(lean["ms_per_step"], 3),
            "sideways_fall": sideways_fall(substeps, iterations, relaxation),
        }
        if args.batch:
            entry[f"env_physics_ms_per_step_batch{args.batch}"] = round(
                env_physics_ms(substeps, iterations, relaxation, args.batch), 2
            )
        result["settings"].append(entry)
        print(json.dumps(entry), flush=True)
    result["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
