import sys
from pathlib import Path

import jax
import pytest

sys.path.insert(0, str(Path(__file__).parent))


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
