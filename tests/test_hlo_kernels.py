"""benchmarks/hlo_kernels.py: kernels per step counted from XLA's optimised HLO, by source line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from benchmark_scripts import BENCHMARKS, KERNELS_LINE, SCANNED_PROGRAM, load


@pytest.fixture(scope="module")
def hlo_kernels():
    return load("hlo_kernels", BENCHMARKS / "hlo_kernels.py")


def _dumped(directory: Path, length: int) -> Path:
    """The optimised HLO of SCANNED_PROGRAM with a scan of `length`, compiled on CPU in a fresh process."""
    script = directory / f"program_{length}.py"
    script.write_text(SCANNED_PROGRAM.replace("LENGTH", str(length)))
    dump = directory / f"dump_{length}"
    environment = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_dump_to={dump}")
    subprocess.run([sys.executable, str(script)], env=environment, check=True, timeout=300)
    (path,) = dump.glob("*jit_f*after_optimizations.txt")
    return path


def test_kernels_in_a_loop_count_once_per_trip_and_name_their_source_line(hlo_kernels, tmp_path):
    line = KERNELS_LINE
    counted = {}
    for length in (3, 7):
        result = hlo_kernels.count(_dumped(tmp_path, length), steps=1, within=f"program_{length}.py")
        counted[length] = result["per_source_line"][f"program_{length}.py:{line} f.<locals>.body"]
        assert result["loops_without_known_trip_count"] == []
    # the sort and the product/tanh/add are kernels of their own, run once per trip
    assert counted[3] >= 2 * 3
    assert counted[7] * 3 == counted[3] * 7


def test_a_functions_kernels_include_those_of_the_functions_it_calls(hlo_kernels, tmp_path):
    """`per_function` counts a kernel for every function on its stack: the loop body's kernels are
    f's too, once each, however many of f's lines the stack passes through."""
    result = hlo_kernels.count(_dumped(tmp_path, 3), steps=1, within="program_3.py")
    per_function = result["per_function"]
    body = per_function["program_3.py f.<locals>.body"]
    assert body == result["per_source_line"][f"program_3.py:{KERNELS_LINE} f.<locals>.body"] >= 2 * 3
    assert per_function["program_3.py f"] >= body
    assert per_function["program_3.py f"] == result["kernels_per_step"] - result["per_source_line"].get("(outside)", 0)


HELPER = """
import jax.numpy as jnp
def wave(c):
    return jnp.sin(c) * 3.0 + jnp.cos(c)
"""

CALLER = """
import jax, jax.numpy as jnp
import wave_helper
def f(x):
    return jnp.sort(wave_helper.wave(x), axis=-1)  # CALLS THE HELPER
jax.block_until_ready(jax.jit(f)(jnp.ones((4, 8))))
"""


def test_a_kernel_made_in_a_file_outside_the_selection_counts_for_the_line_that_called_it(hlo_kernels, tmp_path):
    """The walk up the stack frames: the sine's kernel is made in wave_helper.py, called from f in
    caller.py; with only caller.py selected it is f's line (not "(outside)")."""
    (tmp_path / "wave_helper.py").write_text(HELPER)
    (tmp_path / "caller.py").write_text(CALLER)
    dump = tmp_path / "dump"
    environment = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_dump_to={dump}", PYTHONPATH=str(tmp_path))
    subprocess.run([sys.executable, str(tmp_path / "caller.py")], env=environment, check=True, timeout=300)
    (path,) = dump.glob("*jit_f*after_optimizations.txt")
    line = 1 + CALLER.splitlines().index("    return jnp.sort(wave_helper.wave(x), axis=-1)  # CALLS THE HELPER")
    result = hlo_kernels.count(path, steps=1, within="caller.py")
    assert "(outside)" not in result["per_source_line"], result["per_source_line"]
    assert result["per_source_line"][f"caller.py:{line} f"] >= 2  # the helper's arithmetic and the sort
    helper = hlo_kernels.count(path, steps=1, within="wave_helper.py")["per_source_line"]
    assert any(where.startswith("wave_helper.py:") for where in helper), helper


def test_the_h200_dump_counts_the_kernels_its_trace_saw(hlo_kernels):
    """Session 46's dump of the DBD humanoid step (batch 4096, a scan of 10 steps) against the kernels
    the profiler recorded on that GPU for the same program (kernel_trace_gpu_solvers.json)."""
    results = BENCHMARKS / "results"
    traced = json.loads((results / "kernel_trace_gpu_solvers.json").read_text())["models"]["humanoid"]
    ((stream, seen),) = [(k, v) for k, v in traced["dbdjax-dbd"].items() if "GPU" in k]
    result = hlo_kernels.count(results / "hlo" / "dbd_humanoid_4096_h200.txt.gz", steps=10, within="dbdjax/")
    assert result["loops_without_known_trip_count"] == []
    assert abs(result["kernels_per_step"] - seen["events_per_step"]) < 0.05 * seen["events_per_step"], stream
    # the stack frames name a dbdjax line for all but a few kernels (the loop around the steps, the
    # state's layout in and out)
    assert result["per_source_line"]["(outside)"] < 0.1 * result["kernels_per_step"]
