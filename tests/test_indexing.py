"""dbdjax.indexing: gathers and segment sums whose derivatives do not scatter."""

import jax
import jax.numpy as jnp
import jaxprs
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

import dbdjax as dbd
from dbdjax import indexing

INDEX = np.array([[2, 0], [2, 5], [1, 1]])  # repeats, and rows read by nothing (3, 4)
SEGMENTS = np.array([3, 0, 3, 1, 4, 4, 0])  # segment 2 empty


def _loss(take, segment_sum):
    def loss(x):
        taken = take(x, INDEX)
        summed = segment_sum(jnp.concatenate([x, x[:1]]) * 2.0, SEGMENTS, 6)
        return jnp.sum(jnp.sin(taken) ** 2) + jnp.sum(jnp.cos(summed) * summed)

    return loss


ours = _loss(indexing.take, indexing.segment_sum)
jaxs = _loss(lambda x, index: x[index], jax.ops.segment_sum)


def test_take_and_segment_sum_equal_jax_indexing_and_segment_sum(float64):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(6, 3)))
    np.testing.assert_array_equal(indexing.take(x, INDEX), x[INDEX])
    np.testing.assert_array_equal(indexing.segment_sum(x, SEGMENTS[:6], 6), jax.ops.segment_sum(x, SEGMENTS[:6], 6))
    np.testing.assert_array_equal(jax.jit(ours)(x), jaxs(x))
    empty = indexing.segment_sum(x[:0], np.zeros(0, int), 4)
    np.testing.assert_array_equal(empty, np.zeros((4, 3)))


def test_their_derivatives_equal_jaxs_in_every_mode(float64):
    x = jnp.asarray(np.random.default_rng(1).normal(size=(6, 3)))
    for mode in (jax.jacrev, jax.jacfwd, jax.hessian):
        np.testing.assert_allclose(jax.jit(mode(ours))(x), mode(jaxs)(x), rtol=1e-12, atol=1e-12, err_msg=str(mode))
    batch = jnp.asarray(np.random.default_rng(2).normal(size=(4, 6, 3)))
    for axis in (0, 1, 2):
        moved = jnp.moveaxis(batch, 0, axis)
        got = jax.vmap(jax.grad(ours), in_axes=axis)(moved)
        np.testing.assert_allclose(got, jax.vmap(jax.grad(jaxs), in_axes=axis)(moved), rtol=1e-12, err_msg=str(axis))


def test_their_gradients_hold_no_scatter():
    """The point of the pair: reverse mode transposes each into the other, not into a scatter (which
    XLA:CPU runs as a loop of kernels per row); jax's own gather does scatter."""
    x = jnp.ones((6, 3))
    primitives = lambda f: {e.primitive.name for e in jaxprs.equations(jax.make_jaxpr(jax.grad(f))(x).jaxpr)}  # noqa: E731
    assert not any("scatter" in name for name in primitives(ours))
    assert {"dbdjax_take", "dbdjax_segment_sum"} <= primitives(ours)
    assert any("scatter" in name for name in primitives(jaxs))


def test_added_is_at_index_add_to_the_bit_and_in_derivative(float64):
    """`added`: x.at[index].add(values) (each row's own value first, then the values in order)."""
    rng = np.random.default_rng(5)
    x, values = jnp.asarray(rng.normal(size=(5, 3))), jnp.asarray(rng.normal(size=(6, 3)) * 1e3)
    index = np.array([4, 1, 4, 0, 4, 1])
    at = indexing.added_rows(index, 5)
    np.testing.assert_array_equal(indexing.added(x, values, at), x.at[index].add(values))

    def loss(add):
        return lambda x, v: jnp.sum(jnp.sin(add(x, v)) ** 2)

    mine = loss(lambda x, v: indexing.added(x, v, at))
    theirs = loss(lambda x, v: x.at[index].add(v))
    for mine_d, theirs_d in zip(jax.grad(mine, (0, 1))(x, values), jax.grad(theirs, (0, 1))(x, values), strict=True):
        np.testing.assert_allclose(mine_d, theirs_d, rtol=1e-12, atol=1e-12)


def test_rows_scanned_per_iteration_give_jaxs_values_and_gradients(float64):
    """`stacked_rows`: one set of rows per iteration of a lax.scan (the solver's colours), as traced
    arrays, with the tables their transposes need."""
    x = jnp.asarray(np.random.default_rng(3).normal(size=(6, 3)))
    indices = np.array([[0, 2, 4], [5, 5, 1], [3, 3, 3]])
    stacked = indexing.stacked_rows(indices, 6)
    assert stacked.table.shape == (3, 6, 3)  # the widest: row 3 read three times

    def scanned(x, take):
        def body(total, at):
            return total + jnp.sum(jnp.sin(take(x * total, at)) ** 2), None

        return jax.lax.scan(body, 1.0, stacked if take is indexing.take else indices)[0]

    theirs = lambda x: scanned(x, lambda x, index: x[index])  # noqa: E731
    mine = lambda x: scanned(x, indexing.take)  # noqa: E731
    np.testing.assert_allclose(mine(x), theirs(x), rtol=1e-14)
    for mode in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(jax.jit(mode(mine))(x), mode(theirs)(x), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(jax.grad(jax.checkpoint(mine))(x), jax.grad(theirs)(x), rtol=1e-12, atol=1e-14)


def test_numpy_stays_numpy_and_bad_indices_are_refused():
    table = np.arange(12).reshape(6, 2)
    assert isinstance(indexing.take(table, INDEX), np.ndarray)
    with pytest.raises(ValueError, match=r"lie in \[0, 6\)"):
        indexing.take(jnp.ones((6, 3)), np.array([0, 6]))
    with pytest.raises(ValueError, match=r"lie in \[0, 3\)"):
        indexing.segment_sum(jnp.ones((2, 3)), np.array([0, -1]), 3)
    with pytest.raises(TypeError, match="integer"):
        indexing.take(jnp.ones((6, 3)), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="3 segment ids for 2 rows"):
        indexing.segment_sum(jnp.ones((2, 3)), np.array([0, 1, 1]), 3)
    with pytest.raises(ValueError, match="width 1 below the 2"):
        indexing.rows(np.array([1, 1]), 3, width=1)


def test_under_shard_map_they_give_the_same_values_and_gradients():
    """Types that name a mesh take JAX's own operations (as math's products do): same results."""
    mesh = jax.make_mesh((1,), ("b",))
    x = jnp.asarray(np.random.default_rng(4).normal(size=(6, 3)), jnp.float32)
    mapped = jax.shard_map(jax.grad(ours), mesh=mesh, in_specs=P(), out_specs=P())
    np.testing.assert_allclose(jax.jit(mapped)(x), jax.grad(jaxs)(x), rtol=1e-6)


def test_a_dbd_step_and_its_gradient_hold_no_scatter_on_brax_humanoid():
    """The default solver's step (prediction, contacts, sweeps, velocity passes) reads and sums its
    rows without scattering, forward and in reverse: each scatter is a loop of kernels on CPU."""
    model = dbd.load_mjcf("tests/assets/humanoid.xml", iterations=2)
    state = dbd.init(model)
    control = jnp.zeros(model.num_controls)

    def loss(state, control):
        return jnp.sum(dbd.step(model, state, control).pos[:, 2])

    for f in (jax.jit(loss), jax.jit(jax.grad(loss, argnums=(0, 1)))):
        text = f.lower(state, control).as_text()
        assert "scatter" not in text, [line for line in text.splitlines() if "scatter" in line][:3]
