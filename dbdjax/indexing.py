"""Gathers and sums of rows, as a pair of JAX primitives each of which is the other's transpose,
so that neither a step nor its gradient scatters.

XLA:CPU has no scatter kernel: it runs a scatter as a loop over the scattered rows, about four
kernels a row. `jax.ops.segment_sum` and `x.at[index].add` are scatters, and so is the
reverse-mode derivative of every gather `x[index]`. In Brax's humanoid's DBD step (batch 256, CPU)
the actuators' wrenches, the joints' torque targets and the rotors' inertias summed per body were
420 of its 3,882 kernels; in the gradient of a rollout the scatters that transpose the solver's
gathers (each colour's write-back, the bodies each projection reads) were 6,709 of its 21,662
kernels a step (docs/brax_comparison.md, session 67).

  take(x, index)                     x[index]: a gather; its transpose is a `segment_sum`.
  segment_sum(x, segments, count)    out[s] = the sum of the rows x[k] with segments[k] == s, in
                                     the order of k: a few gathers from a table of each segment's
                                     rows, added (one fused kernel, no scatter); its transpose is a
                                     `take`.

Both act on the leading axis and broadcast over the others. The indices are numpy arrays, known
when tracing, or (`Rows`: inside a `lax.scan` over colours, one set of rows per colour) arrays
built from numpy ones by `rows`, which carry the table the transpose needs. Arguments whose types
name a mesh (`shard_map`, explicit sharding) take JAX's own operations instead, as `math`'s
products do (`math._unsharded`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from dbdjax import math


class Rows(NamedTuple):
    """Rows of an array of `count` rows: index (...,) int, which row each entry reads, and table
    (count, width) int, which entries read row s (the flat positions in index, padded with
    index.size). Arrays: stack several (same shapes, `rows(..., width=)`) to scan over them."""

    index: jnp.ndarray | np.ndarray
    table: jnp.ndarray | np.ndarray


def rows(index, count: int, width: int | None = None) -> Rows:
    """`Rows` of an integer numpy `index` (any shape, values in [0, count)) into `count` rows.
    width: the table's (at least the most entries that read one row; default that)."""
    index = np.asarray(index)
    if index.dtype.kind not in "iu":
        raise TypeError(f"rows: the index must be a numpy integer array, got dtype {index.dtype}")
    if index.size and (index.min() < 0 or index.max() >= count):
        raise ValueError(f"rows: index values must lie in [0, {count}), got {index.min()}..{index.max()}")
    index = index.astype(np.int32)  # one integer type whether or not JAX runs in 64 bits
    flat = index.reshape(-1)
    order = np.argsort(flat, kind="stable")
    sizes = np.bincount(flat, minlength=count)
    widest = int(sizes.max(initial=0))
    if width is not None and width < widest:
        raise ValueError(f"rows: width {width} below the {widest} entries that read one row")
    table = np.full((count, widest if width is None else width), flat.size, np.int32)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
    for s in np.flatnonzero(sizes):
        table[s, : sizes[s]] = order[starts[s] : starts[s] + sizes[s]]
    return Rows(index, table)


def stacked_rows(indices, count: int) -> Rows:
    """`rows` of each index in `indices` (R, ...) int (numpy, same shapes) into `count` rows, stacked
    with one table width: Rows (R, ...) and (R, count, width), to scan over."""
    width = max((rows(index, count).table.shape[1] for index in indices), default=0)
    each = [rows(index, count, width) for index in indices]
    return Rows(np.stack([r.index for r in each]), np.stack([r.table for r in each]))


def added_rows(index, count: int) -> Rows:
    """`rows` of [0, 1, ..., count - 1] followed by `index` (K,): for `added`."""
    return rows(np.concatenate([np.arange(count), np.asarray(index).reshape(-1)]), count)


def added(x: jnp.ndarray, values: jnp.ndarray, at: Rows) -> jnp.ndarray:
    """x.at[index].add(values) without the scatter: x (count, ...), values (K, ...), at =
    `added_rows(index, count)` (or one level of a `stacked_rows` of such). Each row's sum starts
    from its own value and adds the values at it in the order of k, as the scatter adds them."""
    return segment_sum(jnp.concatenate([x, values]), at)


def take(x: jnp.ndarray, index) -> jnp.ndarray:
    """x[index] along the leading axis: index a numpy integer array (any shape) or `Rows`; shape
    index.shape + x.shape[1:]. Its reverse-mode derivative sums without scattering. A numpy x
    with a numpy index gives a numpy array (a constant stays one)."""
    at = index if isinstance(index, Rows) else rows(index, np.shape(x)[0])
    numpy_in = isinstance(x, np.ndarray) and isinstance(at.index, np.ndarray)  # numpy out
    if numpy_in or not math._unsharded(x):
        return x[at.index]
    return _take_p.bind(x, jnp.asarray(at.index), jnp.asarray(at.table))


def segment_sum(x: jnp.ndarray, segments, count: int | None = None) -> jnp.ndarray:
    """The rows of x (K, ...) summed by segment: out (count, ...), out[s] = the sum of x[k] over the
    k with segments[k] == s (a numpy int array (K,), values in [0, count); or `Rows` of such an
    index, whose table gives count), in the order of k; zero where a segment has none.
    `jax.ops.segment_sum` without its scatter."""
    at = segments if isinstance(segments, Rows) else rows(np.asarray(segments).reshape(-1), count)
    if at.index.shape[0] != np.shape(x)[0]:
        raise ValueError(f"segment_sum: {at.index.shape[0]} segment ids for {np.shape(x)[0]} rows")
    if not math._unsharded(x):
        return _summed(x, at.table)
    return _segment_sum_p.bind(x, jnp.asarray(at.table), jnp.asarray(at.index))


def _summed(x: jnp.ndarray, table) -> jnp.ndarray:
    """The written-out segment sum: x (K, ...) summed into table.shape[0] rows, one gather per
    column of `table` (entries K read a zero row), added in column order: each segment's rows in
    the order of k, as a scatter-add adds them."""
    if table.shape[1] == 0:
        return jnp.zeros(table.shape[:1] + x.shape[1:], x.dtype)
    padded = jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])
    total = padded[table[:, 0]]
    for column in range(1, table.shape[1]):
        total = total + padded[table[:, column]]
    return total


def _taken(x: jnp.ndarray, index, table) -> jnp.ndarray:
    return x[index]


def _segment_summed(x: jnp.ndarray, table, index) -> jnp.ndarray:
    return _summed(x, table)


_take_p = Primitive("dbdjax_take")  # (x, index, table) -> x[index]
_segment_sum_p = Primitive("dbdjax_segment_sum")  # (x, table, index) -> _summed(x, table)


def _take_shape(x, index, table) -> ShapedArray:
    return ShapedArray(index.shape + x.shape[1:], x.dtype, weak_type=x.weak_type)


def _segment_sum_shape(x, table, index) -> ShapedArray:
    return ShapedArray(table.shape[:1] + x.shape[1:], x.dtype, weak_type=x.weak_type)


def _linear_jvp(primitive):
    """Both are linear in x (their first operand) and constant in the indices."""

    def jvp(primals, tangents):
        x, *indices = primals
        out = primitive.bind(x, *indices)
        if type(tangents[0]) is ad.Zero:
            return out, ad.Zero.from_primal_value(out)
        return out, primitive.bind(tangents[0], *indices)

    return jvp


def _take_transpose(cotangent, x, index, table):
    if type(cotangent) is ad.Zero:
        return [ad.Zero(x.aval), None, None]
    flat = cotangent.reshape((-1,) + cotangent.shape[index.ndim :])
    return [_segment_sum_p.bind(flat, table, index.reshape(-1)), None, None]


def _segment_sum_transpose(cotangent, x, table, index):
    if type(cotangent) is ad.Zero:
        return [ad.Zero(x.aval), None, None]
    return [_take_p.bind(cotangent, index, table), None, None]


def _leading_axis_batcher(primitive, batch_axis_out):
    """The batch of x moved beside the leading axis (the primitives broadcast over the others); a
    batch of indices (not made by dbdjax) by vmap of the written-out form, JAX's own gathers."""
    written_out = {_take_p: _taken, _segment_sum_p: _segment_summed}[primitive]

    def batched(args, dims):
        (x, first, second), (axis, first_axis, second_axis) = args, dims
        if first_axis is not None or second_axis is not None:
            return jax.vmap(written_out, in_axes=dims)(*args), 0
        return primitive.bind(jnp.moveaxis(x, axis, 1), first, second), batch_axis_out(first, second)

    return batched


for _primitive, _written_out, _shape, _transpose, _batch_axis in (
    (_take_p, _taken, _take_shape, _take_transpose, lambda index, table: index.ndim),
    (_segment_sum_p, _segment_summed, _segment_sum_shape, _segment_sum_transpose, lambda table, index: 1),
):
    _primitive.def_abstract_eval(_shape)
    _primitive.def_impl(_written_out)
    mlir.register_lowering(_primitive, mlir.lower_fun(_written_out, multiple_results=False))
    ad.primitive_jvps[_primitive] = _linear_jvp(_primitive)
    ad.primitive_transposes[_primitive] = _transpose
    batching.primitive_batchers[_primitive] = _leading_axis_batcher(_primitive, _batch_axis)

# For trailing_batch: primitives that act along x's leading axis alone (any further axes broadcast).
LEADING_AXIS = frozenset({_take_p.name, _segment_sum_p.name})
