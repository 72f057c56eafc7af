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
