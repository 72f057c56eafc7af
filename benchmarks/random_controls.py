"""How wild each engine runs a model under random controls: Brax's ant (or humanoid) dropped from
its build pose, `--batch` copies each driven by its own uniform random controls in the actuators'
ctrlrange for `--steps` steps (dbdjax: one physics step per call, `--substeps` substeps, 1 unless
given), and the same controls
stepped by MuJoCo itself (`mujoco.mj_step` at the XML's options) as the physics to compare with.

Per copy: the largest body speed (m/s) and spin (rad/s) over the rollout, and for dbdjax the
largest joint gap (m). A solve that adds energy shows as speeds past MuJoCo's; a joint that opens,
as gaps. The copies diverge chaotically after landing, so compare spreads, not copies.

    python benchmarks/random_controls.py --model ant --engines dbd dbd-tree-1 dbd-tree mujoco

Writes benchmarks/results/random_controls_<model>.json (`--out` for another path).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import brax_comparison  # beside this script: the engines' settings
import jax
import jax.numpy as jnp
import machine
import numpy as np


def dbdjax_spread(xml: Path, variant: str, steps: int, batch: int, seed: int, substeps: int = 1) -> dict:
    """Per copy: largest body speed, spin and joint gap over the rollout of a `brax_comparison`
    dbdjax variant (its settings: `substeps`, DBD_ITERATIONS sweeps unless the variant says)."""
    engine = brax_comparison.dbdjax_engine(xml, variant, substeps)
    drive = brax_comparison.random_controls(engine, (steps, batch), seed)
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), engine.init())

    def one(state, control):
        state = jax.vmap(engine.step)(state, control)
        speed = jnp.max(jnp.linalg.norm(state.vel, axis=-1), axis=-1)
        spin = jnp.max(jnp.linalg.norm(state.ang_vel, axis=-1), axis=-1)
        return state, (speed, spin, jax.vmap(engine.joint_gap)(state))

    _, (speed, spin, gap) = brax_comparison.jit(lambda s, c: jax.lax.scan(one, s, c))(state, drive)
    return {
        "largest_speed_m_s": np.asarray(speed).max(axis=0).round(3).tolist(),
        "largest_spin_rad_s": np.asarray(spin).max(axis=0).round(2).tolist(),
        "largest_joint_gap_m": np.asarray(gap).max(axis=0).tolist(),
        "finite": bool(np.isfinite(np.asarray(speed)).all()),
    }


def mujoco_spread(xml: Path, steps: int, batch: int, seed: int) -> dict:
    """The same for mujoco.mj_step (its joints have no gap: generalized coordinates)."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(xml))
    data = mujoco.MjData(m)
    drive = brax_comparison.uniform_controls(np.asarray(m.actuator_ctrlrange), (steps, batch), seed)
    velocity = np.zeros(6)
    speeds, spins = [], []
    for copy in range(batch):
        mujoco.mj_resetData(m, data)
        speed = spin = 0.0
        for t in range(steps):
            data.ctrl[:] = drive[t, copy]
            mujoco.mj_step(m, data)
            for body in range(1, m.nbody):
                mujoco.mj_objectVelocity(m, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)  # world frame
                spin, speed = max(spin, np.linalg.norm(velocity[:3])), max(speed, np.linalg.norm(velocity[3:]))
        speeds.append(round(speed, 3))
        spins.append(round(spin, 2))
    return {"largest_speed_m_s": speeds, "largest_spin_rad_s": spins, "finite": bool(np.isfinite(speeds).all())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="ant", choices=["ant", "humanoid"])
    parser.add_argument("--engines", nargs="+", default=["dbd", "dbd-tree-1", "dbd-tree", "mujoco"],
                        help=f"mujoco or dbdjax variants: {sorted(brax_comparison.DBDJAX_VARIANTS)}")  # fmt: skip
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--substeps", type=int, default=1, help="dbdjax's substeps per step (MuJoCo's: 1)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    xml = brax_comparison.ASSETS / f"{args.model}.xml"
    results = {}
    for engine in args.engines:
        if engine == "mujoco":
            results[engine] = mujoco_spread(xml, args.steps, args.batch, args.seed)
        else:
            results[f"dbdjax-{engine}"] = dbdjax_spread(xml, engine, args.steps, args.batch, args.seed, args.substeps)
    print(f"{args.model}: {args.batch} copies x {args.steps} steps of random controls (seed {args.seed})")
    print(f"{'engine':<20} {'speed median / max (m/s)':>26} {'spin max (rad/s)':>17} {'gap median / max (mm)':>23}")
    for engine, spread in results.items():
        speed, spin = np.asarray(spread["largest_speed_m_s"]), np.asarray(spread["largest_spin_rad_s"])
        gap = np.asarray(spread.get("largest_joint_gap_m", [np.nan])) * 1e3
        print(f"{engine:<20} {np.median(speed):>12.2f} / {speed.max():>8.2f}   {spin.max():>14.1f}"
              f"   {np.median(gap):>10.4f} / {gap.max():>8.4f}")  # fmt: skip
    out = args.out or brax_comparison.RESULTS / f"random_controls_{args.model}.json"
    out.write_text(json.dumps({
        "machine": machine.describe(), "model": args.model, "steps": args.steps, "batch": args.batch,
        "seed": args.seed,
        "dbdjax": f"{args.substeps} substep(s), {brax_comparison.DBD_ITERATIONS} iterations (dbd-tree-1: 1), float32",
        "engines": results}, indent=1) + "\n")  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
