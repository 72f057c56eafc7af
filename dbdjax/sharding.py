"""Batched simulation past one device: the batch axis sharded over a `jax.sharding.Mesh`.

Every copy of a batched rollout is independent, so the batch axis splits over devices with no
communication: put the batched state and controls on a one-axis mesh with `shard_batch` and call
the jitted, vmapped step or rollout as usual; XLA partitions the computation along the batch and
the results come back sharded the same way. The model (its parameters) is replicated.

    mesh = dbd.sharding.batch_mesh()                       # all local devices, axis "batch"
    states = dbd.sharding.shard_batch(states, mesh)        # leading axis B, B % devices == 0
    final, trajectory = dbd.jit(jax.vmap(dbd.rollout, in_axes=(None, 0, 0)))(model, states, controls)

On CPU, XLA_FLAGS=--xla_force_host_platform_device_count=4 (set before jax is imported) gives
four host devices to try it; across machines, `jax.distributed.initialize()` first.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"


def batch_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh named "batch" over `devices` (default: every device JAX sees)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), (BATCH_AXIS,))


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Place every array of `tree` with its leading (batch) axis split over the mesh's devices.
    Raises ValueError if a leading axis does not divide evenly (name the leaf's shape)."""
    devices = mesh.devices.size
    for leaf in jax.tree.leaves(tree):
        if np.ndim(leaf) == 0 or np.shape(leaf)[0] % devices:
            raise ValueError(
                f"shard_batch: an array of shape {np.shape(leaf)} has no leading batch axis divisible by the "
                f"mesh's {devices} devices"
            )
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Place every array of `tree` whole on every device of the mesh (for a model's parameters)."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def varying_like(tree: Any, *references: Any) -> Any:
    """`tree` with every array made varying over each `jax.shard_map` axis that an array of
    `references` varies over (no change outside shard_map, where nothing varies).

    A `lax.scan` under shard_map requires its carry to come back with the type it went in with; a
    carry that starts as constants (zeros: no multiplier yet) and comes back computed from the
    sharded state would come back varying. So each scan's first carry is made as varying as the
    inputs its body reads (`references`), as JAX's documentation advises (`jax.lax.pcast`)."""
    axes = frozenset().union(*(jax.typeof(leaf).mat.varying for leaf in jax.tree.leaves(references)))
    if not axes:
        return tree

    def cast(leaf):
        missing = tuple(sorted(axes - jax.typeof(leaf).mat.varying))
        return jax.lax.pcast(leaf, missing, to="varying") if missing else leaf

    return jax.tree.map(cast, tree)


def cond(predicate: jax.Array, true_fun: Callable, false_fun: Callable, *operands: Any) -> Any:
    """`jax.lax.cond(predicate, true_fun, false_fun, *operands)`, except where the predicate varies
    over a `jax.shard_map` axis: there both run and their results are selected (what `jax.vmap` makes
    of a cond whose predicate is batched in any case).

    Why: under shard_map's varying-axes checks, vmap of a cond whose predicate is batched fails in JAX
    0.10 ("Primitive add requires varying manual axes to match"): the batching rule selects the
    branches' operands with the now varying predicate, and the branches' constants (index arrays
    closed over) then meet their unvarying literals. Outside shard_map, or with its checks off, this
    is `lax.cond`: a real branch where the predicate is not batched. In the select the branch not
    taken is differentiated too, with a zero cotangent: both branches must stay finite."""
    if not jax.typeof(predicate).mat.varying:
        return jax.lax.cond(predicate, true_fun, false_fun, *operands)
    taken, other = true_fun(*operands), false_fun(*operands)
    return jax.tree.map(lambda a, b: jnp.where(predicate, a, b), taken, other)
