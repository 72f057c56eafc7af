"""A batched step under `jax.vmap` (batch axis first) against `dbd.vmap` (the batch the trailing
axis of every intermediate, dbdjax/trailing_batch.py), side by side in one process.

    python benchmarks/trailing_batch.py                       # humanoid, ant, ragdoll at 16, 64, 256
    python benchmarks/trailing_batch.py --models humanoid --batches 256 1024 --rounds 9

Each (model, batch) compiles both programs (a jitted lax.scan of `--chunk` steps of random
controls, compiled with `dbd.compiler_options()`), checks they agree, then times them in
alternating calls, `--rounds` of each: recorded are the least time of each (ms per batched step,
wall clock), the median of the rounds' ratios (jax.vmap / dbd.vmap: above 1, dbd.vmap is faster)
and the first call of each (compile + one run). `--tile N`: dbd.vmap's tile (0: the whole batch
as one tile). Models: Brax's humanoid.xml and ant.xml
(tests/assets) at 1 substep x 4 iterations as benchmarks/brax_comparison.py runs them, and the
ragdoll of RagdollStand-v0 (4 substeps x 8 iterations, pose targets). Writes
benchmarks/results/trailing_batch_cpu.json (or --out).
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import machine  # benchmarks/machine.py, beside this script
import numpy as np

import dbdjax as dbd
from dbdjax import trailing_batch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # envs/ (the ragdoll's env)
ASSETS = ROOT / "tests" / "assets"
RESULTS = Path(__file__).resolve().parent / "results"


def model_and_controls(name: str, batch: int, chunk: int, seed: int = 0):
    """(model, controls (chunk, batch, num_controls)) uniform in the actuators' ranges."""
    if name == "ragdoll":
        from envs.ragdoll_envs import RagdollStand

        model = RagdollStand().model
    else:
        model = dbd.load_mjcf(ASSETS / f"{name}.xml", substeps=1, iterations=4)
    low, high = np.asarray(model.control_range).T
    rng = np.random.default_rng(seed)
    controls = low + rng.uniform(size=(chunk, batch, len(low))) * (high - low)
    return model, jnp.asarray(controls, jnp.float32)


def chunked(mapping, model, controls):
    """A jitted run of len(controls) batched steps, `mapping` jax.vmap or dbd.vmap."""
    step = mapping(dbd.step, in_axes=(None, 0, 0))
    return dbd.jit(lambda state: jax.lax.scan(lambda s, c: (step(model, s, c), None), state, controls)[0])


def measure(name: str, batch: int, chunk: int, rounds: int, tile: int | None = trailing_batch.TILE) -> dict:
    model, controls = model_and_controls(name, batch, chunk)
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), dbd.init(model))
    runs, first_call, finals = {}, {}, {}
    tiled = functools.partial(dbd.vmap, tile=tile)
    for label, mapping in (("jax.vmap", jax.vmap), ("dbd.vmap", tiled)):
        run = chunked(mapping, model, controls)
        started = time.perf_counter()
        finals[label] = jax.block_until_ready(run(state))
        first_call[label] = round(time.perf_counter() - started, 2)
        runs[label] = run
    pairs = zip(jax.tree.leaves(finals["jax.vmap"]), jax.tree.leaves(finals["dbd.vmap"]), strict=True)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in pairs)
    times: dict[str, list[float]] = {label: [] for label in runs}
    for r in range(rounds):
        order = list(runs) if r % 2 == 0 else list(runs)[::-1]
        for label in order:
            started = time.perf_counter()
            jax.block_until_ready(runs[label](state))
            times[label].append((time.perf_counter() - started) / chunk)
    ratios = [a / b for a, b in zip(times["jax.vmap"], times["dbd.vmap"], strict=True)]
    result = {
        "model": name,
        "batch": batch,
        "tile": tile,
        "ms_per_batched_step": {label: round(1e3 * min(t), 3) for label, t in times.items()},
        "steps_per_s": {label: round(batch / min(t), 1) for label, t in times.items()},
        "median_ratio": round(statistics.median(ratios), 3),
        "ratio_quartiles": [round(float(q), 3) for q in np.percentile(ratios, [25, 75])],
        "first_call_s": first_call,
        "largest_difference_after_chunk": gap,
    }
    ms = result["ms_per_batched_step"]
    print(f"{name:8s} batch {batch:5d}: jax.vmap {ms['jax.vmap']:9.3f} ms, dbd.vmap {ms['dbd.vmap']:9.3f} ms, "
          f"ratio {result['median_ratio']:.2f} {result['ratio_quartiles']}, first calls {first_call}, "
          f"largest difference {gap:.2e}", flush=True)  # fmt: skip
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["humanoid", "ant", "ragdoll"])
    parser.add_argument("--batches", nargs="+", type=int, default=[16, 64, 256])
    parser.add_argument("--chunk", type=int, default=10, help="steps per timed call")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--tile", type=int, default=trailing_batch.TILE, help="dbd.vmap's tile (0: one tile)")
    parser.add_argument("--out", type=Path, default=RESULTS / "trailing_batch_cpu.json")
    args = parser.parse_args()
    results = {"machine": machine.describe(), "command": " ".join(sys.argv), "results": []}
    for name in args.models:
        for batch in args.batches:
            results["results"].append(measure(name, batch, args.chunk, args.rounds, args.tile or None))
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
