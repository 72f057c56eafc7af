"""Helpers for the tests that read a traced program (a jaxpr)."""

from collections.abc import Iterator


def equations(jaxpr) -> Iterator:
    """Every equation of a jaxpr, those of its sub-jaxprs (custom derivatives, loops, branches,
    jitted calls) included, each after the equation that holds it."""
    for equation in jaxpr.eqns:
        yield equation
        for param in equation.params.values():
            for value in param if isinstance(param, (list, tuple)) else [param]:
                inner = getattr(value, "jaxpr", value)
                if hasattr(inner, "eqns"):
                    yield from equations(inner)
