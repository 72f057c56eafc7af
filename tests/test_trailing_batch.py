"""dbd.vmap (the batch the trailing axis of every intermediate) gives jax.vmap's values and
gradients."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes

import dbdjax as dbd
from dbdjax import indexing, trailing_batch

ASSETS = Path(__file__).parent / "assets"


def _batch(model, size, seed=0):
    """`size` copies of the model's initial state, each given random velocities."""
    start = dbd.init(model)
    rng = np.random.default_rng(seed)
    states = jax.tree.map(lambda x: jnp.broadcast_to(x, (size,) + x.shape), start)
    return dataclasses.replace(states, vel=states.vel + rng.normal(size=states.vel.shape),
                               ang_vel=states.ang_vel + rng.normal(size=states.ang_vel.shape))  # fmt: skip


def _largest_difference(a, b) -> float:
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


@pytest.mark.slow
@pytest.mark.usefixtures("float64")
def test_dbd_vmap_steps_brax_humanoid_as_jax_vmap_does():
    model = dbd.load_mjcf(ASSETS / "humanoid.xml", substeps=1, iterations=4)
    states = _batch(model, 3)
    rng = np.random.default_rng(1)
    low, high = np.asarray(model.control_range).T
    controls = jnp.asarray(low + rng.uniform(size=(3, len(low))) * (high - low))
    expected = jax.jit(jax.vmap(dbd.step, in_axes=(None, 0, 0)))(model, states, controls)
    got = jax.jit(dbd.vmap(dbd.step, in_axes=(None, 0, 0)))(model, states, controls)
    assert got.pos.shape == expected.pos.shape == (3, model.num_bodies, 3)
    assert _largest_difference(got, expected) < 1e-10


@pytest.mark.slow
@pytest.mark.usefixtures("float64")
def test_dbd_vmap_steps_a_falling_ragdoll_with_contacts_and_drives_as_jax_vmap_does():
    model = scenes.ragdoll(height=0.75, drives=True, dt=1 / 60, substeps=2, iterations=4)
    states = _batch(model, 4)
    rollout = lambda mapping: jax.jit(lambda s: jax.lax.scan(  # noqa: E731
        lambda s, _: (mapping(lambda x: dbd.step(model, x))(s), None), s, None, length=20)[0])  # fmt: skip
    expected, got = rollout(jax.vmap)(states), rollout(dbd.vmap)(states)
    assert float(jnp.min(expected.pos[..., 2])) < 0.2  # on the ground: the contacts acted
    assert _largest_difference(got, expected) < 1e-9


@pytest.mark.slow
@pytest.mark.usefixtures("float64")
def test_dbd_vmap_gradient_is_jax_vmaps():
    model = scenes.mixed_tree()
    states = _batch(model, 3)

    def loss(mapping, kick):
        moved = dataclasses.replace(states, vel=states.vel + kick)
        return jnp.sum(mapping(lambda s: dbd.step(model, s))(moved).pos ** 2)

    kick = jnp.zeros_like(states.vel)
    expected = jax.jit(jax.grad(lambda k: loss(jax.vmap, k)))(kick)
    got = jax.jit(jax.grad(lambda k: loss(dbd.vmap, k)))(kick)
    assert np.all(np.isfinite(got)) and float(jnp.max(jnp.abs(expected))) > 1e-3
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def _every_rule(x, index, flag):
    """A per-scene function through the primitives `trailing_batch` has rules for (and some it
    hands to jax.vmap): x (4, 3) floats, index () int, flag () bool."""
    rows = np.array([2, 0, 3, 3])
    gathered = x[rows] * 2.0  # gather with per-scene indices
    summed = jax.ops.segment_sum(gathered, np.array([0, 1, 1, 2]), 3)  # scatter-add
    summed = summed + indexing.segment_sum(indexing.take(x, rows), np.array([2, 1, 1, 0]), 3)  # dbdjax's own
    turned = jnp.einsum("ij,kj->ki", jnp.eye(3) + x[:3], summed)  # small dot_general
    stacked = (
        jnp.concatenate([turned, jnp.stack([x[0], x[1]])], axis=0).reshape(5, 3).T
    )  # concat, stack, reshape, transpose
    padded = jnp.pad(stacked, ((1, 0), (0, 2)))  # pad
    carry, ys = jax.lax.scan(lambda c, row: (c + jnp.sin(row), jnp.cumsum(row)), jnp.zeros(7), padded)  # scan
    chosen = jax.lax.cond(flag, lambda c: c * 3.0, lambda c: c - 1.0, carry)  # cond on a batched predicate
    picked = jax.lax.dynamic_slice(ys, (index, 0), (2, 7))  # a batched index: jax.vmap's rule
    ordered = jnp.sort(chosen)  # no rule of its own: jax.vmap's
    return {"sum": jnp.sum(picked) + jnp.max(ordered), "ys": ys, "chosen": chosen, "constant": jnp.arange(3.0)}


def test_every_rule_gives_jax_vmaps_values():
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(6, 4, 3)), jnp.float32)
    index = jnp.asarray([0, 1, 2, 0, 3, 1])
    flag = jnp.asarray([True, False, True, True, False, False])
    expected = jax.vmap(_every_rule)(x, index, flag)
    got = jax.jit(dbd.vmap(_every_rule))(x, index, flag)
    for key in expected:
        assert got[key].shape == expected[key].shape, key
        np.testing.assert_allclose(got[key], expected[key], rtol=1e-5, atol=1e-5, err_msg=key)


def test_a_batch_in_tiles_with_a_filled_up_last_tile_gives_jax_vmaps_values():
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(7, 4, 3)), jnp.float32)
    index = jnp.asarray(rng.integers(0, 4, size=7))
    flag = jnp.asarray(rng.uniform(size=7) < 0.5)
    expected = jax.vmap(_every_rule)(x, index, flag)
    got = jax.jit(dbd.vmap(_every_rule, tile=3))(x, index, flag)  # tiles of 3, 3 and 1 (+ 2 copies)
    for key in expected:
        assert got[key].shape == expected[key].shape, key
        np.testing.assert_allclose(got[key], expected[key], rtol=1e-5, atol=1e-5, err_msg=key)


def test_trailing_maps_over_the_last_axis_and_returns_it_last():
    x = jnp.arange(24.0).reshape(4, 3, 2)  # two scenes of (4, 3), batch last
    out = trailing_batch.trailing(lambda a, s: jnp.sum(a[1:], axis=0) * s, in_axes=(-1, None))(x, 2.0)
    assert out.shape == (3, 2)
    np.testing.assert_allclose(out, jax.vmap(lambda a: jnp.sum(a[1:], axis=0) * 2.0, in_axes=-1, out_axes=-1)(x))


def test_batches_of_different_sizes_and_a_wrong_number_of_in_axes_are_refused():
    with pytest.raises(ValueError, match="differ in size"):
        trailing_batch.trailing(lambda a, b: a + b)(jnp.zeros((3, 2)), jnp.zeros((3, 4)))
    with pytest.raises(ValueError, match="first axes differ in size"):
        dbd.vmap(lambda a, b: a + b)(jnp.zeros(3), jnp.zeros(4))
    with pytest.raises(ValueError, match="holds a scalar"):
        trailing_batch.trailing(lambda a, b: a + b)(jnp.zeros(3), jnp.float32(1.0))
    with pytest.raises(ValueError, match="holds a scalar"):
        dbd.vmap(lambda a, b: a + b)(jnp.zeros(3), jnp.float32(1.0))
    with pytest.raises(ValueError, match="in_axes has 2 entries for 1 positional arguments"):
        dbd.vmap(lambda a: a, in_axes=(0, None))(jnp.zeros(3))
