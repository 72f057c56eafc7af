"""Which kernels a physics step runs and how long each takes, from XLA's own profile
(`jax.profiler`, written as a perfetto trace), on whatever backend JAX has: on a GPU the CUDA
kernels and memory copies, on CPU XLA:CPU's fused kernels.

On the GPU dbdjax's step costs about the same from batch 1 to 256 (benchmarks/results/
brax_comparison_gpu.json): its time is a sequence of kernels, not arithmetic. This script counts
that sequence, per engine, so that a change can be judged by kernels per step and where their time
goes: one jitted call of `--steps` vmapped steps is traced after two untimed calls, and every
complete event of the trace is summed per process (host threads, each device stream) and per name.

    python benchmarks/kernel_trace.py --models humanoid --engines dbdjax-dbd brax-positional \\
        --batch 4096 --out benchmarks/results/kernel_trace_gpu.json

The engines are brax_comparison.py's (same models, dt, controls, 1 substep x 4 iterations).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import tempfile
from pathlib import Path

import brax_comparison  # beside this script
import jax
import machine


def traced_run(engine: brax_comparison.Engine, batch: int, steps: int, directory: Path) -> None:
    """Trace one jitted call of `steps` vmapped steps of `batch` copies (compiled beforehand)."""
    run, state = brax_comparison.batched_chunk(engine, batch, steps)
    state = jax.block_until_ready(run(jax.block_until_ready(run(state))))  # compile, and settle weak types
    with jax.profiler.trace(str(directory), create_perfetto_trace=True):
        jax.block_until_ready(run(state))


def summarise(directory: Path, steps: int, top: int) -> dict:
    """Per thread of the trace (a device stream on a GPU, an XLA thread pool on CPU): complete
    events per step, their summed time per step (us; events nest on host threads, so there the sum
    can exceed the wall time), and the `top` names by time (count and us per step). The Python
    tracer's events (names starting with '$') are left out."""
    (path,) = directory.rglob("perfetto_trace.json.gz")
    events = json.loads(gzip.decompress(path.read_bytes()))
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {(e["pid"], e.get("tid")): e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name")}  # fmt: skip
    durations: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for event in events:
        if event.get("ph") != "X" or event["name"].startswith("$"):
            continue
        pid, tid = event["pid"], event.get("tid")
        where = f"{names.get((pid, None), pid)} {names.get((pid, tid), tid)}"
        durations[where][event["name"]] += float(event.get("dur", 0.0))
        counts[where][event["name"]] += 1
    return {
        where: {
            "events_per_step": round(sum(counts[where].values()) / steps, 1),
            "us_per_step": round(sum(times.values()) / steps, 1),
            "top": [
                {
                    "name": name[:120],
                    "per_step": round(counts[where][name] / steps, 2),
                    "us_per_step": round(us / steps, 2),
                }
                for name, us in times.most_common(top)
            ],
        }
        for where, times in durations.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["humanoid"])
    parser.add_argument("--engines", nargs="+", default=["dbdjax-dbd", "brax-positional"])
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--steps", type=int, default=10, help="steps in the traced call")
    parser.add_argument("--top", type=int, default=15, help="names listed per process")
    parser.add_argument("--out", type=Path, help="write the summary here (JSON)")
    args = parser.parse_args()
    results = {"machine": machine.describe(), "batch": args.batch, "steps": args.steps, "models": {}}
    for model_name in args.models:
        engines, skipped = brax_comparison.make_engines(brax_comparison.ASSETS / f"{model_name}.xml", args.engines)
        per_engine = results["models"].setdefault(model_name, {"skipped": skipped} if skipped else {})
        for engine in engines:
            with tempfile.TemporaryDirectory() as directory:
                traced_run(engine, args.batch, args.steps, Path(directory))
                per_engine[engine.name] = summarise(Path(directory), args.steps, args.top)
            for process, part in per_engine[engine.name].items():
                print(f"{model_name} {engine.name} batch {args.batch} [{process}]: {part['events_per_step']} events, "
                      f"{part['us_per_step']} us per step")  # fmt: skip
            if args.out:  # after each engine, so that a run cut short keeps what it measured
                args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
