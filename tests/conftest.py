import os
import sys
from pathlib import Path

# The suite's time is mostly XLA compiling its programs (about 82% of it, session 69), and its
# checks are of numbers, not speed. So every program of the test processes is compiled without
# XLA:CPU's fusion emitters (as dbdjax's own programs are: `dbd.compiler_options()`) and without
# LLVM's optimisation passes (level 0 of 3): the same operations, rounded at most differently, and
# `make test`'s tests in 423 s instead of 994 (session 70). A test that compares two programs to the bit
# takes `optimised_compile`. Set before JAX starts its backend, which reads XLA_FLAGS once;
# subprocesses that a test starts with its own XLA_FLAGS keep theirs.
QUICK_COMPILE = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {QUICK_COMPILE}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

from dbdjax import compiling  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture
def optimised_compile(monkeypatch):
    """`dbd.jit`'s programs (the trainers', the envs') compiled with LLVM's optimisation passes, at
    XLA's default level 3 as outside the suite, not at the suite's level 0: for a test that compares
    two such programs to the bit or to 1e-12, which holds only where XLA compiles their shared part
    alike (at level 0 two PPO programs were 2.3e-10 apart, two humanoid rollouts 1.8e-12)."""
    optimised = {**compiling._OPTIONS["cpu"], "xla_backend_optimization_level": 3}
    monkeypatch.setitem(compiling._OPTIONS, "cpu", optimised)


@pytest.fixture
def float64():
    """Run the test in double precision (finite-difference and exactness checks)."""
    with jax.enable_x64(True):
        yield


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
    """Refuse a mark that decorates a helper rather than a test: pytest ignores it silently. (A
    `@pytest.mark.slow` once slid onto a helper inserted below it, and its 3-minute test ran in
    every CI run since.) Runs before `-m` deselects anything, so every collected module is seen."""
    modules = {item.module for item in items if getattr(item, "module", None) is not None}
    misplaced = [
        f"{module.__name__}.{name}"
        for module in modules
        for name, value in vars(module).items()
        if callable(value)
        and not name.startswith(("test", "Test"))  # test functions and classes carry their marks
        and getattr(value, "__module__", None) == module.__name__
        and getattr(value, "pytestmark", None)
    ]
    if misplaced:
        raise pytest.UsageError(f"pytest marks on functions that are not tests (they do nothing there): {misplaced}")
