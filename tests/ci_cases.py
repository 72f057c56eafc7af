"""Which cases of a parametrized test `make test` (CI) runs: the rest are marked slow and run with
`make test-slow`. Session 69 found the suite taking 63 minutes on this 2-core machine against the
20 or so it should, and left one or two cases of each parametrized family in CI (whole tests marked
slow then are listed in its closing note and named in the README's `make test` paragraph)."""

import pytest


def slow_except(cases, kept) -> list:
    """`cases` for `pytest.mark.parametrize`, every one not in `kept` marked slow. A tuple case is
    spread over the test's arguments, as parametrize spreads it."""
    return [
        case if case in kept else pytest.param(*(case if isinstance(case, tuple) else (case,)), marks=pytest.mark.slow)
        for case in cases
    ]
