"""Batched rollouts sharded over a device mesh (four CPU devices in a subprocess, since the
device count is fixed when jax starts)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

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


def test_batched_rollout_sharded_over_four_cpu_devices_matches_one_device():
    tests = Path(__file__).parent
    environment = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    environment["PYTHONPATH"] = os.pathsep.join([str(tests), str(tests.parent), environment.get("PYTHONPATH", "")])
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=environment, capture_output=True, text=True, timeout=600, check=False
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in result.stdout.strip().splitlines())
    assert lines["devices"] == "4"  # the output stays split over the four devices
    assert float(lines["max_difference"]) < 1e-5
    assert lines["finite"] == "True"
    assert lines["uneven"] == "True"  # a batch of 6 over 4 devices is refused with a clear error
