"""`vmap` with the batch as the trailing axis of every intermediate array.

`jax.vmap` puts the batch axis first. A dbdjax step is a long chain of operations on small
vectors ((..., 3) positions, (..., 4) quaternions), so every array it computes ends in an axis of
3 or 4 entries; XLA:CPU lays arrays out row-major and runs each kernel's innermost loop over that
last axis, too short to vectorise: the step's arithmetic ran one element at a time (about 3-4
G operations/s a core, `benchmarks/trailing_batch.py`). Here the batch is the last axis instead,
so each kernel's innermost loop runs over the scenes of the batch, contiguous in memory: SIMD
across scenes.

How: the per-scene function is traced once (`jax.make_jaxpr`) and its program evaluated on
arrays with one more, trailing axis, each primitive with a rule that keeps that axis last
(`_rule`): elementwise operations broadcast, shape operations (slice, reshape, transpose,
concatenate, gather with per-scene indices, ...) get the axis appended to their parameters, loops
and calls are evaluated inside. A primitive without such a rule takes JAX's own batching rule
between two transposes (`_by_jax_vmap`), so any program gives vmap's result.

Derivatives are jax.vmap's. The trailing-batch program inlines the function's custom derivative
rules (those that keep a step's gradients finite), so it is never differentiated itself: `vmap` is
a `jax.custom_vjp` whose forward pass is that program and whose backward pass is the VJP of
`jax.vmap(function)`, the rules applied (it computes the forward pass again, batch-first).
Forward-mode differentiation (`jax.jvp`, `jax.jacfwd`) of `vmap` is not available: use `jax.vmap`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core

from dbdjax import indexing, math

# Primitives that act element by element on operands of one shape (a scalar operand broadcasts).
ELEMENTWISE = frozenset({
    "abs", "acos", "acosh", "add", "and", "asin", "asinh", "atan", "atan2", "atanh", "cbrt", "ceil",
    "clamp", "convert_element_type", "copy", "copy_p", "cos", "cosh", "div", "eq", "erf", "exp", "exp2",
    "expm1", "floor", "ge", "gt", "imag", "integer_pow", "is_finite", "le", "log", "log1p", "logistic",
    "lt", "max", "min", "mul", "ne", "neg", "nextafter", "not", "or", "pow", "real", "reduce_precision",
    "rem", "round", "rsqrt", "select_n", "sign", "sin", "sinh", "sqrt", "square", "stop_gradient", "sub",
    "tan", "tanh", "xor",
})  # fmt: skip
# Primitives whose parameters name only per-scene axes (reductions and scans along an axis).
ALONG_AXES = frozenset({
    "argmax", "argmin", "cumlogsumexp", "cummax", "cummin", "cumprod", "cumsum", "reduce_and", "reduce_max",
    "reduce_min", "reduce_or", "reduce_prod", "reduce_sum", "squeeze",
})  # fmt: skip
# Scenes per tile of `vmap` (benchmarks/trailing_batch.py at batch 256: one tile of 256 no faster than
# jax.vmap, tiles of 64 1.25-1.33x faster on the humanoid and the ragdoll; README "Batches").
TILE = 64
# dot_general with at most this many products per output entry is written out as products and sums.
SMALL_DOT_TERMS = 8
# Primitives that call a program of their own, evaluated in place here (forward values).
CALLS = {"jit": "jaxpr", "pjit": "jaxpr", "custom_jvp_call": "call_jaxpr", "custom_vjp_call": "call_jaxpr",
         "remat2": "jaxpr", "checkpoint": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr"}  # fmt: skip


def vmap(function: Callable, in_axes: int | None | Sequence[int | None] = 0, tile: int | None = TILE) -> Callable:
    """`jax.vmap(function, in_axes)` (out_axes 0) computed with the batch as the last axis of
    every intermediate array (module docstring): the same values up to rounding.

    in_axes: 0 (every argument batched along its first axis) or None (not batched), or one of
    these per positional argument, e.g. `dbd.vmap(dbd.step, in_axes=(None, 0, 0))` for a batch of
    states and controls under one model. Every output is batched along its first axis.
    tile: a batch larger than this runs as tiles of `tile` scenes, each tile batch-last and the
    tiles mapped by jax.vmap (the last tile filled up with copies of the last scene); None: one tile.
    Reverse mode gives jax.vmap's gradients (module docstring); forward mode is not available.
    """

    def batched(*args):
        axes = _axes_per_argument(in_axes, len(args))
        sizes = {np.shape(x)[0] if np.ndim(x) else None
                 for a, axis in zip(args, axes, strict=True) if axis == 0 for x in jax.tree.leaves(a)}  # fmt: skip
        if None in sizes:
            raise ValueError("dbd.vmap: a batched argument holds a scalar (no axis to map)")
        if len(sizes) != 1:
            raise ValueError(f"dbd.vmap: the batched arguments' first axes differ in size: {sorted(sizes)}")
        size = sizes.pop()
        tiles = 1 if tile is None or size <= tile else -(-size // tile)
        width = size if tiles == 1 else tile

        def split(x):  # (size, ...) -> (tiles, ..., width)
            x = jnp.asarray(x)
            if tiles * width > size:  # the last tile filled up with copies of the last scene
                x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (tiles * width - size,) + x.shape[1:])])
            return jnp.moveaxis(x.reshape((tiles, width) + x.shape[1:]), 1, -1)

        def join(x):  # (tiles, ..., width) -> (size, ...)
            return jnp.moveaxis(x, -1, 1).reshape((tiles * width,) + x.shape[1:-1])[:size]

        one_tile = trailing(function, [-1 if axis == 0 else None for axis in axes])
        if tiles == 1:
            mapped = [jax.tree.map(lambda x: jnp.moveaxis(x, 0, -1), a) if axis == 0 else a
                      for a, axis in zip(args, axes, strict=True)]  # fmt: skip
            return jax.tree.map(lambda x: jnp.moveaxis(x, -1, 0), one_tile(*mapped))
        mapped = [jax.tree.map(split, a) if axis == 0 else a for a, axis in zip(args, axes, strict=True)]
        per_tile = jax.vmap(one_tile, in_axes=tuple(0 if axis == 0 else None for axis in axes))
        return jax.tree.map(join, per_tile(*mapped))

    def by_jax(*args):
        return jax.vmap(function, in_axes=tuple(_axes_per_argument(in_axes, len(args))))(*args)

    @jax.custom_vjp
    def mapped(*args):
        return batched(*args)

    def forward(*args):
        return batched(*args), args

    def backward(args, cotangent):
        _, pullback = jax.vjp(by_jax, *args)
        return pullback(cotangent)

    mapped.defvjp(forward, backward)
    return mapped


def trailing(function: Callable, in_axes: int | None | Sequence[int | None] = -1) -> Callable:
    """`function` mapped over the LAST axis of its batched arguments (in_axes -1, or None for an
    unbatched one, per positional argument), every output batched along its last axis: for
    callers that keep their arrays batch-last between calls (no transposes). Forward values: its
    program does not apply the function's custom derivative rules (module docstring), so take
    gradients through `vmap`."""

    def batched(*args):
        axes = _axes_per_argument(in_axes, len(args))
        leaves, flags = [], []
        for argument, axis in zip(args, axes, strict=True):
            for leaf in jax.tree.leaves(argument):
                leaves.append(jnp.asarray(leaf))
                flags.append(axis is not None)
        if any(batched and x.ndim == 0 for x, batched in zip(leaves, flags, strict=True)):
            raise ValueError("trailing batch: a batched argument holds a scalar (no axis to map)")
        sizes = {x.shape[-1] for x, batched in zip(leaves, flags, strict=True) if batched}
        if len(sizes) != 1:
            raise ValueError(f"trailing batch: the batched arguments' last axes differ in size: {sorted(sizes)}")
        size = sizes.pop()
        tree = jax.tree.structure(args)
        per_scene = [jax.ShapeDtypeStruct(x.shape[:-1] if batched else x.shape, x.dtype)
                     for x, batched in zip(leaves, flags, strict=True)]  # fmt: skip
        closed, out_shape = jax.make_jaxpr(lambda *xs: function(*jax.tree.unflatten(tree, xs)),
                                           return_shape=True)(*per_scene)  # fmt: skip
        values = _evaluate(closed.jaxpr, _unbatched(closed.consts), list(zip(leaves, flags, strict=True)), size)
        return jax.tree.unflatten(jax.tree.structure(out_shape), [_with_batch(v, size) for v in values])

    return batched


def _axes_per_argument(in_axes, count: int) -> list:
    axes = list(in_axes) if isinstance(in_axes, (list, tuple)) else [in_axes] * count
    if len(axes) != count:
        raise ValueError(f"in_axes has {len(axes)} entries for {count} positional arguments")
    return axes


# ------------------------------------------------------------------------------------ evaluation
# A value is (array, batched): batched arrays carry the trailing batch axis after the per-scene
# shape the program's variable has.


def _unbatched(arrays) -> list:
    return [(x, False) for x in arrays]


def _with_batch(value, size: int) -> jnp.ndarray:
    """The value as a batched array: an unbatched one repeated along a new last axis."""
    x, batched = value
    x = jnp.asarray(x)
    return x if batched else jnp.broadcast_to(x[..., None], x.shape + (size,))


def _evaluate(jaxpr: core.Jaxpr, consts: list, args: list, size: int) -> list:
    env: dict = {}

    def read(var):
        return (var.val, False) if isinstance(var, core.Literal) else env[var]

    for var, value in zip(jaxpr.constvars, consts, strict=True):
        env[var] = value
    for var, value in zip(jaxpr.invars, args, strict=True):
        env[var] = value
    for equation in jaxpr.eqns:
        outputs = _rule(equation, [read(v) for v in equation.invars], size)
        for var, value in zip(equation.outvars, outputs, strict=True):
            env[var] = value
    return [read(v) for v in jaxpr.outvars]


def _program(jaxpr) -> tuple[core.Jaxpr, list]:
    if isinstance(jaxpr, core.ClosedJaxpr):
        return jaxpr.jaxpr, _unbatched(jaxpr.consts)
    return jaxpr, []


def _bind(equation, args, **params) -> list:
    out = equation.primitive.bind(*args, **(params or equation.params))
    return out if equation.primitive.multiple_results else [out]


def _rule(equation, values: list, size: int) -> list:
    """The equation's outputs from its inputs (values), the batch axis kept last."""
    name, params = equation.primitive.name, equation.params
    if name in CALLS:
        return _evaluate(*_program(params[CALLS[name]]), values, size)
    if name == "scan":
        return _scan(equation, values, size)
    if name == "cond":
        return _cond(equation, values, size)
    if not any(batched for _, batched in values):
        return [(x, False) for x in _bind(equation, [x for x, _ in values])]
    shape = tuple(equation.outvars[0].aval.shape)
    if name in ELEMENTWISE:

        def operand(value):  # an unbatched scalar broadcasts as it is; select_n's and clamp's take it whole
            x, batched = value
            if not batched and np.ndim(x) == 0 and name not in ("select_n", "clamp"):
                return x
            return jnp.broadcast_to(_with_batch(value, size), shape + (size,))

        return [(x, True) for x in _bind(equation, [operand(v) for v in values])]
    if name in ALONG_AXES:
        return [(x, True) for x in _bind(equation, [values[0][0]])]
    if name == "broadcast_in_dim":
        dimensions = tuple(params["broadcast_dimensions"]) + (len(params["shape"]),)
        out = _bind(
            equation,
            [_with_batch(values[0], size)],
            **dict(params, shape=tuple(params["shape"]) + (size,), broadcast_dimensions=dimensions),
        )
        return [(out[0], True)]
    if name == "reshape" and params.get("dimensions") is None:
        new_sizes = tuple(params["new_sizes"]) + (size,)
        return [(_bind(equation, [values[0][0]], **dict(params, new_sizes=new_sizes))[0], True)]
    if name == "slice":
        strides = params["strides"]
        out = _bind(
            equation,
            [values[0][0]],
            start_indices=tuple(params["start_indices"]) + (0,),
            limit_indices=tuple(params["limit_indices"]) + (size,),
            strides=None if strides is None else tuple(strides) + (1,),
        )
        return [(out[0], True)]
    if name == "transpose":
        permutation = tuple(params["permutation"])
        return [(_bind(equation, [values[0][0]], permutation=permutation + (len(permutation),))[0], True)]
    if name in ("concatenate", "stack"):
        return [(_bind(equation, [_with_batch(v, size) for v in values])[0], True)]
    if name == "pad" and not values[1][1]:
        config = tuple(params["padding_config"]) + ((0, 0, 0),)
        return [(_bind(equation, [_with_batch(values[0], size), values[1][0]], padding_config=config)[0], True)]
    if name == "gather" and not values[1][1]:  # per-scene indices: the batch axis is one more slice axis
        numbers = params["dimension_numbers"]
        numbers = numbers._replace(offset_dims=tuple(numbers.offset_dims) + (len(shape),))
        out = _bind(
            equation,
            [values[0][0], values[1][0]],
            **dict(params, dimension_numbers=numbers, slice_sizes=tuple(params["slice_sizes"]) + (size,)),
        )
        return [(out[0], True)]
    if name in ("scatter", "scatter-add", "scatter_add") and not values[1][1]:
        updates = _with_batch(values[2], size)
        numbers = params["dimension_numbers"]
        numbers = numbers._replace(update_window_dims=tuple(numbers.update_window_dims) + (updates.ndim - 1,))
        out = _bind(
            equation, [_with_batch(values[0], size), values[1][0], updates], **dict(params, dimension_numbers=numbers)
        )
        return [(out[0], True)]
    if name in indexing.LEADING_AXIS and not values[1][1] and not values[2][1]:  # x's leading axis alone
        return [(_bind(equation, [values[0][0], values[1][0], values[2][0]])[0], True)]
    if name == "dot_general" and _is_small_dot(equation):
        return [(_small_dot(values, params["dimension_numbers"], shape, size), True)]
    if name in math.WRITTEN_OUT:  # math's written-out products: their components, in place
        written_out = math.WRITTEN_OUT[name]
        per_scene = [jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype) for v in equation.invars]
        return _evaluate(*_program(jax.make_jaxpr(written_out)(*per_scene)), values, size)
    return _by_jax_vmap(equation, values)


def _is_small_dot(equation) -> bool:
    """A dot_general of a few products per output (a 3 x 3 matrix's), in the operands' dtype."""
    (contract, _), _ = equation.params["dimension_numbers"]
    terms = int(np.prod([equation.invars[0].aval.shape[d] for d in contract]))
    dtype = equation.params.get("preferred_element_type")
    return terms <= SMALL_DOT_TERMS and dtype in (None, equation.outvars[0].aval.dtype)


def _small_dot(values: list, numbers, shape: tuple, size: int) -> jnp.ndarray:
    """dot_general as products summed over the contracted axes, the batch axis last throughout:
    the products of a physics step are of 3 x 3 matrices and vectors, which fuse with the
    arithmetic around them (a dot op would be a library call of its own, and JAX's batching rule
    would move the batch axis first). Output axes as dot_general's: batch, lhs free, rhs free."""
    (contract_l, contract_r), (batch_l, batch_r) = numbers
    operands = []
    for (x, batched), contract, batch in ((values[0], contract_l, batch_l), (values[1], contract_r, batch_r)):
        x = _with_batch((x, batched), size)
        free = [d for d in range(x.ndim - 1) if d not in contract and d not in batch]
        terms = int(np.prod([x.shape[d] for d in contract]))
        operands.append((jnp.transpose(x, list(batch) + free + list(contract) + [x.ndim - 1]), len(free), terms))
    (lhs, free_l, terms), (rhs, free_r, _) = operands
    nb = len(batch_l)
    # lhs (batch, free_l, contracted, S) and rhs (batch, free_r, contracted, S), each contracted group flattened
    lhs = lhs.reshape(lhs.shape[: nb + free_l] + (terms, size))
    rhs = rhs.reshape(rhs.shape[: nb + free_r] + (terms, size))
    lhs = lhs.reshape(lhs.shape[: nb + free_l] + (1,) * free_r + (terms, size))
    rhs = rhs.reshape(rhs.shape[:nb] + (1,) * free_l + rhs.shape[nb:])
    return math.sum_small(lhs * rhs, axis=-2).reshape(shape + (size,))


def _by_jax_vmap(equation, values: list) -> list:
    """Any other primitive: the batch axis moved first, JAX's batching rule, moved back last."""
    arrays = [jnp.moveaxis(x, -1, 0) if batched else x for x, batched in values]
    axes = [0 if batched else None for _, batched in values]
    outputs = jax.vmap(lambda *xs: _bind(equation, xs), in_axes=axes)(*arrays)
    return [(jnp.moveaxis(x, 0, -1), True) for x in outputs]


def _scan(equation, values: list, size: int) -> list:
    """lax.scan with every carry and output batched (unbatched initial carries repeated)."""
    params = equation.params
    jaxpr, consts = _program(params["jaxpr"])
    num_consts, num_carry = params["num_consts"], params["num_carry"]
    constants, carries, xs = values[:num_consts], values[num_consts:][:num_carry], values[num_consts + num_carry :]
    xs_batched = [batched for _, batched in xs]

    def body(carry, x):
        args = list(constants) + [(c, True) for c in carry] + list(zip(x, xs_batched, strict=True))
        outputs = [_with_batch(v, size) for v in _evaluate(jaxpr, consts, args, size)]
        return outputs[:num_carry], outputs[num_carry:]

    carry, ys = jax.lax.scan(body, [_with_batch(c, size) for c in carries], [x for x, _ in xs],
                             length=params["length"], reverse=params["reverse"], unroll=params["unroll"])  # fmt: skip
    return [(x, True) for x in carry] + [(y, True) for y in ys]


def _cond(equation, values: list, size: int) -> list:
    """lax.cond / switch: one branch where the index is the same for every scene, else every
    branch and a select (as jax.vmap does)."""
    (index, index_batched), *operands = values
    branches = [_program(branch) for branch in equation.params["branches"]]
    shapes = [tuple(v.aval.shape) for v in equation.outvars]

    def run(k):
        outputs = _evaluate(*branches[k], operands, size)
        return [jnp.broadcast_to(_with_batch(v, size), s + (size,)) for v, s in zip(outputs, shapes, strict=True)]

    if not index_batched:
        return [(x, True) for x in jax.lax.switch(index, [lambda k=k: run(k) for k in range(len(branches))])]
    results = [run(k) for k in range(len(branches))]
    return [(jax.lax.select_n(jnp.broadcast_to(index, s + (size,)), *[r[i] for r in results]), True)
            for i, s in enumerate(shapes)]  # fmt: skip
