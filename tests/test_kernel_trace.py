"""benchmarks/kernel_trace.py --by-line: the traced kernels' time summed on the lines that made them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest
from benchmark_scripts import BENCHMARKS, KERNELS_LINE, SCANNED_PROGRAM, load

from dbdjax import compiling


@pytest.fixture(scope="module")
def kernel_trace():
    return load("kernel_trace", BENCHMARKS / "kernel_trace.py")


def test_the_kernels_time_is_summed_on_the_line_that_made_them(kernel_trace, tmp_path):
    (tmp_path / "traced_program.py").write_text(SCANNED_PROGRAM.replace("LENGTH", "5"))
    program = load("traced_program", tmp_path / "traced_program.py")
    dump, trace = tmp_path / "dump", tmp_path / "trace"
    options = {**compiling.compiler_options(), "xla_dump_to": str(dump), "xla_dump_hlo_as_text": True}
    run = jax.jit(program.f, compiler_options=options)
    x, w = jnp.ones((64, 8)), jnp.full((8, 8), 0.1)
    jax.block_until_ready(run(x, w))
    with jax.profiler.trace(str(trace), create_perfetto_trace=True):
        jax.block_until_ready(run(x, w))
    result = kernel_trace.by_line(trace, dump, steps=1, top=10, within="traced_program.py")
    line = KERNELS_LINE
    lines = {entry["line"]: entry for entry in result["top"]}
    body = lines[f"traced_program.py:{line} f.<locals>.body"]
    # the product, the sort and the arithmetic around them: kernels of their own, once per trip of 5
    assert body["kernels_per_step"] >= 2 * 5 and body["kernels_per_step"] % 5 == 0, lines
    assert 0.0 < body["us_per_step"] <= result["kernel_us_per_step"]


def test_a_program_compiled_without_the_dump_is_refused_by_name(kernel_trace, tmp_path):
    (tmp_path / "trace").mkdir()
    with pytest.raises(FileNotFoundError, match="xla_dump_to"):
        kernel_trace.by_line(tmp_path / "trace", tmp_path / "dump", steps=1, top=5)
