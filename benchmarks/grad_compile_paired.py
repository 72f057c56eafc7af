"""Compile times of dbdjax checkouts side by side: the step, a 100-step rollout and grad of that
rollout (`brax_comparison.compiled_programs`, compiled as the benchmark compiles), the grad's time
split between JAX (tracing: the forward pass, linearize, remat and transpose, and lowering, all
in Python) and XLA's compile, and the best and median of 7 runs of the compiled grad.

Each checkout is measured in a child process of its own, the checkouts in turn, `--rounds` times,
so that a slow spell of this shared machine falls on both (the 2-core machine's compile times
move 1.8-2.4x from run to run: compare within a run).

    .venv/bin/python benchmarks/grad_compile_paired.py --checkouts DIR . --rounds 1 \\
        --out benchmarks/results/grad_compile_paired_session68.json

(session 68's file, from the script before it compiled each program once; session 69's,
`--checkouts . --rounds 1`, is the code of that session alone).

(The children run with PYTHONPATH emptied: each imports its checkout's dbdjax alone, and this
script's brax_comparison.py, the same harness for all.) Each program is compiled once
(`brax_comparison.compiled_programs`) and the grad run as compiled there.

DIR: an earlier commit's tree (`git archive <commit> | tar -x -C DIR`, its tests/assets/
included).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def measure(root: Path, model: str, solver: str) -> dict:
    """In this process: the compile times and grad runs of `root`'s dbdjax on `model`, measured by
    this script's brax_comparison.py (the same harness for every checkout)."""
    sys.path[:0] = [str(root), str(Path(__file__).parent)]  # the checkout's dbdjax, this harness
    import brax_comparison
    import jax
    import numpy as np

    import dbdjax

    if not Path(dbdjax.__file__).resolve().is_relative_to(root.resolve()):
        raise RuntimeError(f"dbdjax imported from {dbdjax.__file__}, not from {root}")
    engine = brax_comparison.dbdjax_engine(root / "tests" / "assets" / f"{model}.xml", solver)
    programs = brax_comparison.compiled_programs(engine)
    result = {}
    for name, (lowering, compiling, compiled) in programs.items():
        if lowering is None:
            raise RuntimeError(f"{name} failed to compile: {compiled!r}")
        result[f"{name}_s"] = round(lowering + compiling, 2)
    lowering, compiling, grad = programs["grad_rollout100"]
    controls = brax_comparison.random_controls(engine, (100,))  # the controls it was compiled for
    jax.block_until_ready(grad(controls))  # warm
    runs = []
    for _ in range(7):
        start = time.perf_counter()
        jax.block_until_ready(grad(controls))
        runs.append(time.perf_counter() - start)
    return {
        **result,
        "grad_trace_and_lower_s": round(lowering, 2),
        "grad_xla_compile_s": round(compiling, 2),
        "grad_run_best_s": round(min(runs), 3),
        "grad_run_median_s": round(float(np.median(runs)), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkouts", nargs="+", type=Path, default=[], help="dbdjax trees to compare")
    parser.add_argument("--model", default="humanoid", choices=["humanoid", "ant"])
    parser.add_argument("--solver", default="dbd", help="brax_comparison.dbdjax_engine's solver")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--note", default="")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.model, args.solver)))
        return
    if not args.checkouts:
        parser.error("--checkouts: name at least one dbdjax tree")
    runs = []
    for round_ in range(args.rounds):
        for root in args.checkouts:
            command = [sys.executable, __file__, "--child", str(root.resolve()), "--model", args.model,
                       "--solver", args.solver]  # fmt: skip
            load = os.getloadavg()[0]
            output = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": ""})
            if output.returncode:
                raise SystemExit(f"{root}: the measuring process failed:\n{output.stderr[-3000:]}")
            row = {"checkout": str(root), "round": round_, "load_average": round(load, 2),
                   **json.loads(output.stdout.strip().splitlines()[-1])}  # fmt: skip
            print(row, flush=True)
            runs.append(row)
    if args.out:
        record = {"model": args.model, "solver": args.solver, "note": args.note, "runs": runs}
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
