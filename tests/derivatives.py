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


def gradient_and_central_difference(loss, x, epsilon=1e-6):
    """(gradient, central differences) of the scalar loss(x) with respect to every leaf of the
    pytree x (arrays), as pytrees like x, from one compiled program: its value gives the
    differences. (The tests' time is mostly compiling; the value alone was a second program, and on
    their small models the gradient costs little more to run than the value.)"""
    value_and_gradient = quick_jit(jax.value_and_grad(loss))
    analytic = value_and_gradient(x)[1]
    leaves, structure = jax.tree.flatten(x)

    def value_with(k, leaf):
        return float(value_and_gradient(jax.tree.unflatten(structure, leaves[:k] + [leaf] + leaves[k + 1 :]))[0])

    numeric = [
        central_difference(lambda leaf, k=k: value_with(k, leaf), leaf, epsilon) for k, leaf in enumerate(leaves)
    ]
    return analytic, jax.tree.unflatten(structure, numeric)
