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

--by-line: also the time per source line. The traced program is compiled with XLA's dump of its
optimised HLO, each kernel of the trace is found there by name and attributed to the innermost
line of the engine's own package (dbdjax/ or brax/) that made it (`hlo_kernels.source`), and the
kernels' time is summed per line (`by_line`: us and kernels per step). A fused kernel carries the
line of the operation it ends with (XLA keeps its root's metadata), so a line's time includes the
producers fused into it. --dump DIR keeps each program's dump in DIR/MODEL-ENGINE (for
hlo_kernels.py). Checked on CPU, where XLA's profile names each kernel after its HLO instruction:

    python benchmarks/kernel_trace.py --models humanoid --engines dbdjax-dbd brax-positional \\
        --batch 256 --by-line --top 40 --out benchmarks/results/kernel_trace_cpu_by_line.json
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import tempfile
from pathlib import Path

import brax_comparison  # beside this script
import hlo_kernels
import jax
import machine


def traced_run(engine: brax_comparison.Engine, batch: int, steps: int, directory: Path, dump: Path | None = None):
    """Trace one jitted call of `steps` vmapped steps of `batch` copies (compiled beforehand).
    dump: a directory for XLA's dump of the compiled program's HLO (None: no dump)."""
    options = None
    if dump is not None:
        options = {**brax_comparison.COMPILER_OPTIONS, "xla_dump_to": str(dump), "xla_dump_hlo_as_text": True}
    run, state = brax_comparison.batched_chunk(engine, batch, steps, compiler_options=options)
    state = jax.block_until_ready(run(jax.block_until_ready(run(state))))  # compile, and settle weak types
    with jax.profiler.trace(str(directory), create_perfetto_trace=True):
        jax.block_until_ready(run(state))


def summarise(directory: Path, steps: int, top: int) -> dict:
    """Per thread of the trace (a device stream on a GPU, an XLA thread pool on CPU): complete
    events per step, their summed time per step (us; events nest on host threads, so there the sum
    can exceed the wall time), and the `top` names by time (count and us per step). The Python
    tracer's events (names starting with '$') are left out."""
    events = _events(directory)
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


def _events(directory: Path) -> list[dict]:
    (path,) = directory.rglob("perfetto_trace.json.gz")
    events = json.loads(gzip.decompress(path.read_bytes()))
    return events["traceEvents"] if isinstance(events, dict) else events


def by_line(directory: Path, dump: Path, steps: int, top: int, within: str = "dbdjax/") -> dict:
    """The traced kernels' time per source line: every complete event whose name is a kernel of the
    dumped program (a fusion, copy or library call; matched with '.' and '_' alike, as GPU kernels
    are named) counted for the innermost line under `within` that made it (`hlo_kernels.source`).
    The program is the largest optimised module in `dump`; the events of other names (loops, the
    runtime's own) are left out. Returns the `top` lines by time, and the kernels found per step
    and their time (us, summed over the threads that ran them)."""
    modules = sorted(dump.glob("*after_optimizations.txt"), key=lambda p: p.stat().st_size)
    if not modules:
        raise FileNotFoundError(f"no optimised HLO in {dump}: compile the traced program with xla_dump_to={dump}")
    path = modules[-1]
    text = hlo_kernels.read(path)
    frames, locations = hlo_kernels.tables(text)
    bodies, _ = hlo_kernels.computations(text)
    key = lambda name: name.replace(".", "_")  # noqa: E731
    line_of = {key(name): hlo_kernels.source(rest, frames, locations, within)
               for instructions in bodies.values() for name, opcode, rest in instructions
               if opcode in hlo_kernels.KERNELS}  # fmt: skip
    times: collections.Counter = collections.Counter()
    counts: collections.Counter = collections.Counter()
    for event in _events(directory):
        line = line_of.get(key(event["name"])) if event.get("ph") == "X" else None
        if line is not None:
            times[line] += float(event.get("dur", 0.0))
            counts[line] += 1
    return {
        "hlo": path.name,
        "kernel_us_per_step": round(sum(times.values()) / steps, 1),
        "kernels_per_step": round(sum(counts.values()) / steps, 1),
        "top": [
            {"line": line, "us_per_step": round(us / steps, 2), "kernels_per_step": round(counts[line] / steps, 1)}
            for line, us in times.most_common(top)
        ],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["humanoid"])
    parser.add_argument("--engines", nargs="+", default=["dbdjax-dbd", "brax-positional"])
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--steps", type=int, default=10, help="steps in the traced call")
    parser.add_argument("--top", type=int, default=15, help="names listed per process")
    parser.add_argument("--by-line", action="store_true", help="also the kernels' time per source line")
    parser.add_argument("--dump", type=Path, help="with --by-line: keep each program's HLO dump in DIR/MODEL-ENGINE")
    parser.add_argument("--out", type=Path, help="write the summary here (JSON)")
    args = parser.parse_args()
    results = {"machine": machine.describe(), "batch": args.batch, "steps": args.steps, "models": {}}
    for model_name in args.models:
        engines, skipped = brax_comparison.make_engines(brax_comparison.ASSETS / f"{model_name}.xml", args.engines)
        per_engine = results["models"].setdefault(model_name, {"skipped": skipped} if skipped else {})
        for engine in engines:
            with tempfile.TemporaryDirectory() as directory:
                trace, dump = Path(directory) / "trace", None
                if args.by_line:
                    dump = (args.dump or Path(directory)) / f"{model_name}-{engine.name}"
                traced_run(engine, args.batch, args.steps, trace, dump)
                per_engine[engine.name] = summarise(trace, args.steps, args.top)
                if dump is not None:
                    within = "dbdjax/" if engine.name.startswith("dbdjax") else "brax/"  # the engine's own lines
                    per_engine[engine.name]["by_line"] = lines = by_line(trace, dump, args.steps, args.top, within)
            for process, part in per_engine[engine.name].items():
                if process != "by_line":
                    print(f"{model_name} {engine.name} batch {args.batch} [{process}]: {part['events_per_step']} "
                          f"events, {part['us_per_step']} us per step")  # fmt: skip
            if args.by_line:
                print(f"  kernels found in the program: {lines['kernels_per_step']} per step, "
                      f"{lines['kernel_us_per_step']} us per step; by line:")  # fmt: skip
                for entry in lines["top"]:
                    print(f"  {entry['us_per_step']:10.1f} us {entry['kernels_per_step']:7.1f}  {entry['line']}")
            if args.out:  # after each engine, so that a run cut short keeps what it measured
                args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
