"""Batched rollouts, and the RL trainers' envs, sharded over a device mesh (CPU devices in a
subprocess, since the device count is fixed when jax starts)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    import dbdjax as dbd
    from scenes import chain

    assert len(jax.devices()) == 4, jax.devices()
    model = chain(links=4)
    start = dbd.init(model)
    batch = 8
    kicks = jnp.linspace(0.0, 1.0, batch)[:, None, None] * jnp.array([0.0, 1.0, 0.0])
    states = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), start)
    states = dbd.State(states.pos, states.quat, states.vel + kicks, states.ang_vel)
    run = jax.jit(jax.vmap(lambda s: dbd.rollout(model, s, steps=30)[0]))

    mesh = dbd.sharding.batch_mesh()
    sharded = run(dbd.sharding.shard_batch(states, mesh))
    single = jax.device_put(states, jax.devices()[0])
    whole = run(single)
    print("devices", len(sharded.pos.sharding.device_set))
    print("max_difference", float(np.max(np.abs(np.asarray(sharded.pos) - np.asarray(whole.pos)))))
    print("finite", bool(jnp.all(dbd.is_finite(sharded))))
    try:
        dbd.sharding.shard_batch(jax.tree.map(lambda x: x[:6], states), mesh)
        print("uneven accepted")
    except ValueError as error:
        print("uneven", "divisible" in str(error))
    """
)

SHARD_MAP = textwrap.dedent(
    """
    from pathlib import Path
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import PartitionSpec as P
    import sys
    import dbdjax as dbd

    assert len(jax.devices()) == 2, jax.devices()
    mesh = jax.make_mesh((2,), ("b",), axis_types=(jax.sharding.AxisType.Auto,))
    # check_vma on; compiled as the benchmarks and trainers do (dbd.jit: dbd.compiler_options())
    mapped = lambda f: dbd.jit(jax.shard_map(f, mesh=mesh, in_specs=P("b"), out_specs=P("b")))
    settings = {"dbd": {"solver": "dbd"}, "impulse": {"solver": "impulse"},
                "tree": {"solver": "dbd", "tree_solve": True, "iterations": 1}}  # one sweep, then the direct solves
    for solver in sys.argv[1:]:
        # Brax's ant: contacts (sweeps and restitution; the tree solve's active-set step), armature
        # (the rotor pass), actuators, two substeps (the pipeline's scan); each copy with its own controls
        options = {"iterations": 2, **settings[solver]}
        model = dbd.load_mjcf(Path("tests/assets/ant.xml"), substeps=2, **options)
        low, high = np.asarray(model.control_range).T
        controls = jnp.asarray(low + np.random.default_rng(0).uniform(size=(4, model.num_controls)) * (high - low),
                               jnp.float32)
        states = jax.tree.map(lambda x: jnp.broadcast_to(x, (4,) + x.shape), dbd.init(model))
        functions = {"step": jax.vmap(lambda c, s: dbd.step(model, s, c).pos)}
        if solver != "impulse":
            functions["grad"] = jax.vmap(jax.grad(lambda c, s: jnp.sum(dbd.step(model, s, c).pos[:, 2])))
        for name, function in functions.items():
            one_device = np.asarray(dbd.jit(function)(controls, states))
            difference = np.max(np.abs(np.asarray(mapped(function)(controls, states)) - one_device))
            print(f"{solver}_{name}", f"{difference / np.max(np.abs(one_device)):.3g}")  # relative
    """
)

COND = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import PartitionSpec as P
    from dbdjax import sharding

    mesh = jax.make_mesh((2,), ("b",), axis_types=(jax.sharding.AxisType.Auto,))
    order = np.array([2, 0, 1])  # an index array the branch closes over, as the tree solve's do

    def update(x):  # a branch on each copy's own value: batched by vmap
        return sharding.cond(x[0] > 3.0, lambda v: v, lambda v: v[order] * 2.0, x)

    x = jnp.arange(12.0).reshape(4, 3)
    expected = np.where(np.asarray(x[:, :1]) > 3.0, np.asarray(x), np.asarray(x)[:, order] * 2.0)
    mapped = jax.jit(jax.shard_map(jax.vmap(update), mesh=mesh, in_specs=P("b"), out_specs=P("b")))
    print("shard_map_vmap", float(np.max(np.abs(np.asarray(mapped(x)) - expected))))
    print("vmap", float(np.max(np.abs(np.asarray(jax.jit(jax.vmap(update))(x)) - expected))))
    primitives = {e.primitive.name for e in jax.make_jaxpr(update)(x[0]).eqns}
    print("branch", "cond" in primitives)  # outside shard_map, unbatched: still a branch
    """
)


TRAINERS = textwrap.dedent(
    """
    import jax, numpy as np
    from dbdjax.training import apg, ppo, rl

    print("devices", rl.use_cpu_devices(2))  # before anything computes, as the command lines do
    from dbdjax.envs import IKChainReach

    task = IKChainReach(max_episode_steps=10)
    config = ppo.PPOConfig(num_envs=4, unroll_length=4, num_minibatches=2, update_epochs=2, hidden=(8,),
                           learning_rate=1e-3, desired_kl=None)
    optimiser = ppo.make_optimiser(config, None)
    iteration = ppo.make_iteration(task, config, optimiser)
    finals = {}
    for count in (1, 2):
        devices = rl.env_devices(config.num_envs, jax.devices()[:count])
        state = rl.distribute(ppo.init_state(task, config, optimiser, 0), ppo.BATCH_FIELDS, devices)
        for _ in range(3):
            state, metrics = iteration(state, np.float32(0.0))
        finals[count] = state
    print("split", len(finals[2].obs.sharding.device_set), len(finals[2].env_state.physics.pos.sharding.device_set))
    difference = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                     for a, b in zip(jax.tree.leaves(finals[1].params), jax.tree.leaves(finals[2].params)))
    print("ppo_params_difference", difference)
    params = ppo.export_params(finals[2])
    split = rl.evaluate(task, params, num_episodes=4, seed=3)
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    returns, _, _ = rl._episodes(task, 4, 10)(params, jax.device_put(keys, jax.devices()[0]))
    print("evaluation_difference", float(np.max(np.abs(split["returns"] - np.asarray(returns)))))
    result = apg.train(task, apg.APGConfig(num_envs=4, horizon=4, hidden=(8,)), updates=2, eval_episodes=2,
                       progress=False)
    print("apg", result.summary["devices"], bool(np.isfinite(result.history[-1]["reward_per_step"])))
    """
)


def run_script(script: str, environment: dict[str, str], *arguments: str, timeout: float = 600) -> dict[str, str]:
    """Run `script` in a fresh Python with `environment` (tests/ and the repo on the path) and
    command-line `arguments`, for at most `timeout` s; its printed lines "name value" as a dict."""
    tests = Path(__file__).parent
    environment = dict(environment, JAX_PLATFORMS="cpu")
    environment["PYTHONPATH"] = os.pathsep.join([str(tests), str(tests.parent), environment.get("PYTHONPATH", "")])
    result = subprocess.run(
        [sys.executable, "-c", script, *arguments],
        env=environment,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return dict(line.split(" ", 1) for line in result.stdout.strip().splitlines())


def test_batched_rollout_sharded_over_four_cpu_devices_matches_one_device():
    lines = run_script(SCRIPT, dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4"))
    assert lines["devices"] == "4"  # the output stays split over the four devices
    assert float(lines["max_difference"]) < 1e-5
    assert lines["finite"] == "True"
    assert lines["uneven"] == "True"  # a batch of 6 over 4 devices is refused with a clear error


def test_a_branch_on_each_copy_runs_under_shard_map_and_vmap():
    """`sharding.cond` on a batched predicate under `jax.shard_map` (its checks on) and `jax.vmap`:
    each copy takes its own branch; lax.cond there fails in JAX 0.10's batching rule."""
    lines = run_script(COND, dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2"))
    assert float(lines["shard_map_vmap"]) == 0.0
    assert float(lines["vmap"]) == 0.0
    assert lines["branch"] == "True"


@pytest.mark.slow  # 205 s (compiled with jax.jit's defaults until session 64): under shard_map the
# products take their written-out components (math._unsharded)
def test_step_and_its_gradient_run_under_shard_map_with_its_type_checks():
    """`jax.shard_map` (its varying-axes checks on, as by default) over a batch of Brax's ant: the
    step with both solvers and the DBD step's gradient. The scans' carries that start as
    constants are made varying (`sharding.varying_like`); the results are those of one device."""
    lines = run_script(SHARD_MAP, dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2"),
                       "dbd", "impulse")  # fmt: skip
    # float32 rounding, relative to the largest value: the steps within 1e-5 (measured 7.9e-8), the
    # gradient, whose reverse pass sums more terms, within 1e-4 (measured 2.3e-5 of its ~2e-5
    # entries; both with jax.jit's defaults)
    for name, bound in (("dbd_step", 1e-5), ("impulse_step", 1e-5), ("dbd_grad", 1e-4)):
        assert float(lines[name]) < bound, (name, lines[name])


@pytest.mark.slow  # 514 s: the tree's gradient compiles for minutes, on one device and under shard_map
def test_the_tree_solve_and_its_gradient_run_under_shard_map_with_its_type_checks():
    """The same with `tree_solve` at one sweep: its active-set step's second solve, a branch on
    whether the first changed a row, is a select where that varies over a mesh axis
    (`sharding.cond`); the results are those of one device."""
    environment = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    lines = run_script(SHARD_MAP, environment, "tree", timeout=1800)  # its gradient compiles for minutes
    for name, bound in (("tree_step", 1e-5), ("tree_grad", 1e-4)):  # as above; measured 1.6e-7 and 5.6e-6
        assert float(lines[name]) < bound, (name, lines[name])


@pytest.mark.slow  # 124 s; the sharded rollouts above stay in CI
def test_trainers_split_their_envs_over_two_cpu_devices_and_learn_what_one_device_learns():
    """PPO's iteration on two devices keeps its envs split there and updates the networks as on
    one (the same random numbers: JAX's partitionable threefry); the evaluation's episodes split
    too and return what one device returns; APG trains on both."""
    lines = run_script(TRAINERS, dict(os.environ))
    assert lines["devices"] == "2"
    assert lines["split"] == "2 2"  # observations and physics stay split after three iterations
    assert float(lines["ppo_params_difference"]) < 1e-5
    assert float(lines["evaluation_difference"]) < 1e-4
    assert lines["apg"] == "2 True"
