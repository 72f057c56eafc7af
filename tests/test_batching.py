"""step/rollout are pure functions: vmap, rollout and jit agree with plain repeated steps."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes

import dbdjax as dbd


def test_vmap_of_step_equals_step_of_each_element():
    model = scenes.chain(5, dt=1 / 60, iterations=4)
    start = dbd.init(model)
    kicks = jnp.asarray(np.random.default_rng(0).normal(size=(3, 5, 3)))
    batch = jax.vmap(lambda kick: start.__class__(start.pos, start.quat, start.vel + kick, start.ang_vel))(kicks)
    stepped = jax.jit(jax.vmap(dbd.step, in_axes=(None, 0)))(model, batch)
    for i in range(3):
        one = jax.tree.map(lambda x, i=i: x[i], batch)
        single = jax.jit(dbd.step)(model, one)
        element = jax.tree.map(lambda x, i=i: x[i], stepped)
        for a, b in zip(jax.tree.leaves(element), jax.tree.leaves(single), strict=True):
            np.testing.assert_allclose(a, b, atol=1e-5)


def test_rollout_equals_repeated_step():
    model = scenes.chain(4, dt=1 / 60, substeps=2, iterations=4)
    state = dbd.init(model)
    final, trajectory = jax.jit(lambda s: dbd.rollout(model, s, steps=10))(state)
    step = jax.jit(dbd.step)
    for t in range(10):
        state = step(model, state)
        np.testing.assert_allclose(trajectory.pos[t], state.pos, atol=1e-5)
    np.testing.assert_allclose(final.quat, state.quat, atol=1e-5)


def test_rollout_takes_controls_of_the_right_shape():
    model = scenes.chain(2, dt=1 / 60)
    final, trajectory = dbd.rollout(model, dbd.init(model), jnp.zeros((7, model.num_controls)))
    assert trajectory.pos.shape == (7, 2, 3)
    with pytest.raises(ValueError, match="controls must have shape"):
        dbd.rollout(model, dbd.init(model), jnp.zeros((7, 3)))
    with pytest.raises(ValueError, match="control must have shape"):
        dbd.step(model, dbd.init(model), jnp.zeros(2))


def test_jacobi_mode_runs_and_converges_slower_than_gauss_seidel():
    gaps = {}
    for jacobi in (False, True):
        model = scenes.chain(10, dt=1 / 60, iterations=6, jacobi=jacobi)
        _, trajectory = jax.jit(lambda s, m=model: dbd.rollout(m, s, steps=60))(dbd.init(model))
        gaps[jacobi] = float(jnp.max(dbd.diagnostics.joint_gaps(model, trajectory)))
    assert np.isfinite(gaps[True])
    assert gaps[False] < gaps[True]


def test_is_finite_flags_a_non_finite_state():
    model = scenes.chain(2, dt=1 / 60)
    state = dbd.init(model)
    assert bool(dbd.is_finite(state))
    broken = state.__class__(state.pos.at[1, 2].set(jnp.nan), state.quat, state.vel, state.ang_vel)
    assert not bool(dbd.is_finite(broken))
    batch = jax.tree.map(lambda a, b: jnp.stack([a, b]), state, broken)
    np.testing.assert_array_equal(dbd.is_finite(batch), [True, False])
