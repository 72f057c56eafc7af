"""How dbdjax's programs are best compiled: XLA options per compiled program, and `jit` with them.

A DBD step is a long chain of small operations (each constraint row moves the pair of bodies the
next row reads), inside loops over iterations and colours. Session 11's profile found XLA:CPU's
default fusion emitters building that chain into a few large fused kernels that evaluate shared
parts again for every output they feed; with `xla_cpu_use_fusion_emitters` off the step runs
faster (why exactly was not profiled after the change). Measured on Brax's
humanoid.xml (1 substep, 4 iterations, float32, one core; `benchmarks/brax_comparison.py` runs
every engine with these options, README "Compiling"): a step 1.3x faster at batch 1, 1.7x at
16, 1.9x at 256; grad of a 100-step rollout compiled in 94 s instead of 157 s and ran in 0.64 s
instead of 0.95 s. Results differ only by rounding.

The options go to one compiled program (`jax.jit(..., compiler_options=...)`), not the process:
nothing else a user compiles is touched. On other backends there are none yet (not measured).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax

_OPTIONS = {
    "cpu": {"xla_cpu_use_fusion_emitters": False},
}


def compiler_options(backend: str | None = None) -> dict[str, Any]:
    """The XLA compiler options dbdjax's programs run fastest with on `backend` ("cpu", "gpu",
    "tpu"; None: JAX's default backend), for `jax.jit(..., compiler_options=...)`. A new dict."""
    return dict(_OPTIONS.get(backend or jax.default_backend(), {}))


def jit(function: Callable | None = None, /, *, compiler_options: dict[str, Any] | None = None, **jit_kwargs):
    """`jax.jit` with `compiler_options()` of the default backend; the caller's
    `compiler_options` are applied over them (a value of None drops that option). Usable as a
    decorator, with or without arguments: `@dbd.jit`, `@dbd.jit(static_argnames="n")`.

        step = dbd.jit(dbd.step)          # as jax.jit(dbd.step): the model is a pytree argument
        state = step(model, state, control)
    """
    options = merged_options(compiler_options)
    if function is None:
        return lambda f: jax.jit(f, compiler_options=options, **jit_kwargs)
    return jax.jit(function, compiler_options=options, **jit_kwargs)


def merged_options(overrides: dict[str, Any] | None = None, backend: str | None = None) -> dict[str, Any] | None:
    """`compiler_options(backend)` with `overrides` applied (None values remove an option);
    None where nothing is left, as jax.jit takes it."""
    options = compiler_options(backend)
    for name, value in (overrides or {}).items():
        if value is None:
            options.pop(name, None)
        else:
            options[name] = value
    return options or None
