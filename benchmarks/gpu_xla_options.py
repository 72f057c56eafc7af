"""What XLA's GPU options do to a physics step's time, each option set in a process of its own.

On the GPU a dbdjax DBD humanoid step cost about 2.3 ms at batch 1 and hardly more up to batch
4096 (session 12, docs/brax_comparison.md, "Throughput, GPU"): its time is the host launching a long sequence of
small kernels, one loop trip after another, not arithmetic. XLA can record kernels into CUDA
graphs ("command buffers", `xla_gpu_enable_command_buffer`, by default for straight-line
fusions only; `WHILE` and `CONDITIONAL` add loops and branches as graph nodes) or unroll the
loops whose trip count it knows (`xla_gpu_enable_while_loop_unrolling`), so that one launch
replays many kernels. This script measures each such option set on the same engines, models and
batches, side by side in one run:

    python benchmarks/gpu_xla_options.py --models humanoid --engines dbdjax-dbd brax-positional \\
        --batches 1 4096 --out benchmarks/results/gpu_xla_options_h200.json

Every variant runs in a child process with its options in XLA_FLAGS, or, named NAME@options,
passed to `jax.jit(compiler_options=...)` (whether one compiled program can take them, as
`dbd.compiler_options` would hand them out). Variants that unroll every loop time one step per call
(`chunk` 1 in the results): the scan of `--chunk` steps would be unrolled too. The children compile
at the same time; once all have compiled (or `--compile-wait` seconds have passed) they time one
after another under a file lock, so no timing shares the GPU or the host with another child's
compile. A timing is one
jitted call of `--chunk` vmapped steps (a `lax.scan`), called repeatedly for `--seconds` after two
untimed calls, as brax_comparison.py's throughput (same engines, dt, controls, 1 substep x 4
iterations). Results (steps/s, us per batched step, compile s) are written after every child.
On CPU the GPU options are accepted and do nothing; the script runs there for a check of itself.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import brax_comparison  # beside this script
import jax
import jax.numpy as jnp
import machine

# XLA's command buffer kinds: its defaults with loops (WHILE) and branches (CONDITIONAL) added.
# Written out in full: `jax.jit(compiler_options=...)` takes no "+WHILE" form.
COMMAND_BUFFER_KINDS = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,DYNAMIC_SLICE_FUSION,WHILE,CONDITIONAL"
COMMAND_BUFFER_LOOPS = {"xla_gpu_enable_command_buffer": COMMAND_BUFFER_KINDS}
FULL_UNROLL = {"xla_gpu_enable_while_loop_unrolling": "WHILE_LOOP_UNROLLING_FULL_UNROLL"}
VARIANTS = {
    "default": {},
    "graph-loops": COMMAND_BUFFER_LOOPS,
    "graph-loops-unrolled": {
        **COMMAND_BUFFER_LOOPS,
        "xla_gpu_command_buffer_unroll_loops": True,
        "xla_gpu_graph_min_graph_size": 1,
    },
    "unrolled": FULL_UNROLL,
    "unrolled-graph-loops": {**FULL_UNROLL, **COMMAND_BUFFER_LOOPS},
}


def xla_flags(options: dict) -> str:
    """The options as XLA_FLAGS."""
    text = lambda value: str(value).lower() if isinstance(value, bool) else str(value)  # noqa: E731
    return " ".join(f"--{name}={text(value)}" for name, value in options.items())


def split(variant: str) -> tuple[str, str]:
    """ "NAME" -> (NAME, "env"); "NAME@options" -> (NAME, "options")."""
    name, _, how = variant.partition("@")
    return name, how or "env"


def variant_name(text: str) -> str:
    name, how = split(text)
    if name not in VARIANTS or how not in ("env", "options"):
        raise argparse.ArgumentTypeError(f"{text!r}: a variant is one of {sorted(VARIANTS)}, optionally with @options")
    return text


def child(args: argparse.Namespace) -> dict:
    """Compile every (model, engine, batch) program of one variant, wait for the others, then time."""
    name, how = split(args.child)
    options = VARIANTS[name]
    compiler_options = dict(brax_comparison.COMPILER_OPTIONS)
    if how == "options":
        compiler_options.update(options)
    chunk = 1 if FULL_UNROLL.keys() & options.keys() else args.chunk  # a scan of chunk steps would unroll too
    programs, result = [], {"variant": args.child, "options": options, "how": how, "runs": []}
    for model_name in args.models:
        engines, skipped = brax_comparison.make_engines(brax_comparison.ASSETS / f"{model_name}.xml", args.engines)
        for engine_name, reason in skipped.items():
            result["runs"].append({"model": model_name, "engine": engine_name, "skipped": reason})
        for engine in engines:
            for batch in args.batches:
                entry = {"model": model_name, "engine": engine.name, "batch": batch, "chunk": chunk}
                run, state = brax_comparison.batched_chunk(engine, batch, chunk, compiler_options)
                started = time.perf_counter()
                try:  # two untimed calls: the first compiles, the second settles weak types
                    state = jax.block_until_ready(run(jax.block_until_ready(run(state))))
                except Exception as error:  # noqa: BLE001 (an option XLA refuses is a result, not a crash)
                    entry["error"] = f"{type(error).__name__}: {str(error)[:400]}"
                    result["runs"].append(entry)
                    continue
                entry["compile_and_two_calls_s"] = round(time.perf_counter() - started, 2)
                print(f"[{args.child}] compiled {model_name} {engine.name} batch {batch}: "
                      f"{entry['compile_and_two_calls_s']} s", file=sys.stderr, flush=True)  # fmt: skip
                programs.append((entry, run, state))
                result["runs"].append(entry)
    Path(args.barrier, args.child).touch()
    deadline = time.perf_counter() + args.compile_wait
    while len(list(Path(args.barrier).iterdir())) < args.children and time.perf_counter() < deadline:
        time.sleep(0.5)
    with open(Path(args.barrier).parent / "timing.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        for entry, run, state in programs:
            calls, started = 0, time.perf_counter()
            while time.perf_counter() - started < args.seconds or calls < 3:
                state = run(state)
                calls += 1
            jax.block_until_ready(state)
            elapsed = time.perf_counter() - started
            entry["steps_per_s"] = round(entry["batch"] * calls * chunk / elapsed, 1)
            entry["us_per_batched_step"] = round(elapsed / (calls * chunk) * 1e6, 1)
            entry["finite"] = bool(all(jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(state)))
        fcntl.flock(lock, fcntl.LOCK_UN)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", type=variant_name, default=list(VARIANTS),
                        help=f"of {sorted(VARIANTS)}; NAME@options passes NAME's options to jax.jit "
                        "instead of XLA_FLAGS")  # fmt: skip
    parser.add_argument("--models", nargs="+", default=["humanoid"])
    parser.add_argument("--engines", nargs="+", default=["dbdjax-dbd", "brax-positional"])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 4096])
    parser.add_argument("--chunk", type=int, default=10, help="steps per jitted call")
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per program")
    parser.add_argument("--compile-wait", type=float, default=240.0, help="longest wait for the other compiles (s)")
    parser.add_argument("--deadline", type=float, default=1e9, help="stop the children still running after (s)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--child", type=variant_name, help=argparse.SUPPRESS)
    parser.add_argument("--barrier", help=argparse.SUPPRESS)
    parser.add_argument("--children", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args)), flush=True)
        return
    results = {"machine": machine.describe(), "settings": {k: v for k, v in vars(args).items() if k != "out"}}
    results["variants"] = {}
    with tempfile.TemporaryDirectory() as scratch:
        barrier = Path(scratch, "compiled")
        barrier.mkdir()
        started = time.perf_counter()
        children = {}
        for variant in args.variants:
            env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false")  # several processes share the GPU
            name, how = split(variant)
            if how == "env":
                env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + xla_flags(VARIANTS[name])).strip()
            command = [sys.executable, __file__, "--child", variant, "--barrier", str(barrier),
                       "--children", str(len(args.variants)), "--chunk", str(args.chunk),
                       "--seconds", str(args.seconds), "--compile-wait", str(args.compile_wait),
                       "--models", *args.models, "--engines", *args.engines,
                       "--batches", *map(str, args.batches)]  # fmt: skip
            children[variant] = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, text=True)
        while children:  # results as each child ends; at the deadline the rest are stopped
            time.sleep(0.5)
            late = time.perf_counter() - started > args.deadline
            for variant, process in list(children.items()):
                if process.poll() is None and not late:
                    continue
                if process.poll() is None:
                    process.kill()
                output, _ = process.communicate()
                lines = output.strip().splitlines()
                ended = {"variant": variant, "options": VARIANTS[split(variant)[0]], "exit_code": process.returncode}
                if late and process.returncode != 0:
                    ended["stopped_at_deadline_s"] = args.deadline
                results["variants"][variant] = json.loads(lines[-1]) if process.returncode == 0 and lines else ended
                results["wall_s"] = round(time.perf_counter() - started, 1)
                del children[variant]
                if args.out:
                    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print_table(results)


def print_table(results: dict) -> None:
    print(f"{'variant':22} {'model':9} {'engine':16} {'batch':>6} {'steps/s':>12} {'us/step':>9} {'compile s':>9}")
    for variant, result in results["variants"].items():
        for run in result.get("runs", [{"engine": f"exit {result.get('exit_code')}"}]):
            print(f"{variant:22} {run.get('model', ''):9} {run['engine']:16} {run.get('batch', ''):>6} "
                  f"{run.get('steps_per_s', run.get('error', run.get('skipped', '')))!s:>12.12} "
                  f"{run.get('us_per_batched_step', '')!s:>9} "
                  f"{run.get('compile_and_two_calls_s', '')!s:>9}")  # fmt: skip


if __name__ == "__main__":
    main()
