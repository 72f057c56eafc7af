"""dbdjax.compiling: the XLA options dbdjax's programs are compiled with, and `dbd.jit`."""

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dbdjax as dbd
import dbdjax.envs  # noqa: F401 (registers the envs)
from dbdjax.compiling import merged_options

ANT = "tests/assets/ant.xml"


def test_cpu_options_turn_the_fusion_emitters_off_and_other_backends_get_none():
    assert dbd.compiler_options("cpu") == {"xla_cpu_use_fusion_emitters": False}
    assert dbd.compiler_options("gpu") == {} and dbd.compiler_options("tpu") == {}
    dbd.compiler_options("cpu")["xla_cpu_use_fusion_emitters"] = True  # a copy: the next call is unchanged
    assert dbd.compiler_options("cpu") == {"xla_cpu_use_fusion_emitters": False}


def test_caller_options_apply_over_dbdjax_options_and_none_drops_one():
    quick = {"xla_backend_optimization_level": 0}
    assert merged_options(quick, "cpu") == {"xla_cpu_use_fusion_emitters": False, **quick}
    assert merged_options({"xla_cpu_use_fusion_emitters": True}, "cpu") == {"xla_cpu_use_fusion_emitters": True}
    assert merged_options({"xla_cpu_use_fusion_emitters": None}, "cpu") is None  # nothing left: jax.jit's None
    assert merged_options(None, "gpu") is None


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the options measured are XLA:CPU's")
def test_dbd_jit_compiles_another_program_that_computes_the_same_step(float64):
    model = dbd.load_mjcf(ANT)
    state = dbd.init(model)
    control = jnp.linspace(-1.0, 1.0, model.num_controls)
    run = lambda s, c: dbd.rollout(model, s, jnp.broadcast_to(c, (20, model.num_controls)))[0]  # noqa: E731
    # XLA's default, named: the suite's processes compile without the fusion emitters (conftest.py)
    default = jax.jit(run, compiler_options={"xla_cpu_use_fusion_emitters": True}).lower(state, control).compile()
    ours = dbd.jit(run).lower(state, control).compile()
    assert default.as_text() != ours.as_text()  # the options reached XLA
    expected_leaves, got_leaves = jax.tree.leaves(default(state, control)), jax.tree.leaves(ours(state, control))
    for expected, got in zip(expected_leaves, got_leaves, strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0, atol=1e-9)


def test_dbd_jit_decorates_with_and_without_arguments():
    @dbd.jit
    def double(x):
        return 2.0 * x

    @dbd.jit(static_argnames="power")
    def raised(x, power):
        return x**power

    assert float(double(1.5)) == 3.0
    assert float(raised(2.0, power=3)) == 8.0


def test_envs_compile_with_dbdjax_options_unless_the_caller_overrides_them():
    quick = {"xla_backend_optimization_level": 0}
    env = gym.make("dbdjax/IKChainReach-v0", jit_options=quick).unwrapped
    # XLA's default fusion emitters, named (None would drop dbdjax's option and leave the suite's
    # process default, which conftest.py sets to ours)
    plain = gym.make("dbdjax/IKChainReach-v0", jit_options={**quick, "xla_cpu_use_fusion_emitters": True}).unwrapped
    key = jax.random.PRNGKey(0)
    with_ours = env._reset.func.lower(env.func_env, key).compile().as_text()
    without = plain._reset.func.lower(plain.func_env, key).compile().as_text()
    if jax.default_backend() == "cpu":
        assert with_ours != without
    obs, _ = env.reset(seed=3)
    plain_obs, _ = plain.reset(seed=3)
    np.testing.assert_allclose(np.asarray(obs), np.asarray(plain_obs), rtol=1e-6, atol=1e-6)
