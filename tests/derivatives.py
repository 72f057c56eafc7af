"""Helpers for the derivative tests: finite differences in float64 and a quick jit."""

import functools

import jax
import numpy as np

# These tests check derivatives, not speed: LLVM at -O0 more than halves their compile time.
quick_jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


def central_difference(function, x, epsilon=1e-6):
    """d function / dx by central differences, one coordinate at a time (x as float64)."""
    x = np.asarray(x, dtype=np.float64)
    gradient = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        step = np.zeros_like(x)
        step[index] = epsilon
        gradient[index] = (function(x + step) - function(x - step)) / (2 * epsilon)
    return gradient


def relative_error(a, b):
    """|a - b| / |b| (b's norm floored at 1e-12)."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(np.asarray(b)), 1e-12))
