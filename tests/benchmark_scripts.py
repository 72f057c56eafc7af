"""What the tests of benchmarks/ scripts share: loading a script as a module, and a small scanned
program whose kernels a test can find by line."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

# A scan of LENGTH trips whose body makes kernels of its own (a product, a sort, the arithmetic
# around them) on the line marked KERNELS; the last line runs it once.
SCANNED_PROGRAM = """
import jax, jax.numpy as jnp
def f(x, w):
    def body(c, _):
        c = jnp.tanh(c @ w) + jnp.sort(c, axis=-1)  # KERNELS
        return c, None
    return jax.lax.scan(body, x, None, length=LENGTH)[0]
jax.block_until_ready(jax.jit(f)(jnp.ones((4, 8)), jnp.ones((8, 8))))
"""
KERNELS_LINE = 1 + SCANNED_PROGRAM.splitlines().index("        c = jnp.tanh(c @ w) + jnp.sort(c, axis=-1)  # KERNELS")


def load(name: str, path: Path):
    """The file at `path` imported as module `name` (registered in sys.modules), with benchmarks/
    on sys.path for the scripts' imports of their neighbours (brax_comparison, machine)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.append(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
