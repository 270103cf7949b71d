"""Ensembles: one scene run for a batch of parameter sets, spread over every device.

    batch = jaxmpm.with_values(...)               # or any params pytree with a leading batch axis
    probes = jaxmpm.ensemble(sim, batch)          # {name: (B, T, k)}

The batch runs under `jax.vmap` in one compiled program; its batch axis is sharded over a
one-axis device `Mesh` (`NamedSharding(mesh, PartitionSpec("batch"))`), so the same call uses
one CPU, several GPUs, or the devices of several hosts started with
`jax.distributed.initialize()` (then `jax.devices()` lists them all). A batch that does not
divide evenly is padded with copies of its last member, whose results are dropped. Members are
independent, so the sharded program needs no communication until the results are gathered.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxmpm.errors import SceneError
from jaxmpm.running.tracing import collector_paused
from jaxmpm.kernels.xla_options import jit_with_options


def stack(param_sets) -> dict:
    """One params pytree with a leading batch axis from a list of params pytrees."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack([jnp.asarray(leaf) for leaf in leaves]), *param_sets)


def batch_size(batch) -> int:
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in jax.tree_util.tree_leaves(batch)}
    if len(sizes) != 1 or None in sizes:
        raise SceneError("params_batch: every value needs the same leading batch axis (see jaxmpm.running.ensembles.stack).")
    return sizes.pop()


def batch_mesh(devices=None) -> Mesh:
    """A one-axis mesh named "batch" over `devices` (default: every device JAX sees)."""
    return Mesh(np.asarray(jax.devices() if devices is None else devices), ("batch",))


def spread_over_devices(tree, devices=None):
    """`tree` with every leaf's leading axis sharded over the "batch" mesh of `devices`
    (default all) when that axis divides evenly by their number; as it is otherwise, or on
    one device. A jitted function of the result then runs each slice where it lies."""
    mesh = batch_mesh(devices)
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in jax.tree_util.tree_leaves(tree)}
    if mesh.devices.size == 1 or len(sizes) != 1 or None in sizes or sizes.pop() % mesh.devices.size:
        return tree
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec("batch")))


def is_spread(tree) -> bool:
    """Whether some leaf of `tree` lies on more than one device."""
    return any(len(leaf.sharding.device_set) > 1 for leaf in jax.tree_util.tree_leaves(tree)
               if isinstance(leaf, jax.Array))


def ensemble(sim, params_batch, devices=None) -> dict:
    """Probe histories {name: (B, T, k)} of `sim` for each of the B parameter sets of
    `params_batch` (a params pytree whose every value has a leading axis B, e.g. from
    `stack([params, ...])`), computed on `devices` (default all) with the batch sharded over
    them. Equal, member by member, to `sim.probes(member)`; every member's time step is
    checked as `probes` checks it."""
    count = batch_size(params_batch)
    batch = sim.cast(params_batch)
    for index in range(count):
        sim.check_time_step(jax.tree_util.tree_map(lambda leaf: leaf[index], batch))
    mesh = batch_mesh(devices)
    shards = mesh.devices.size
    padded = -(-count // shards) * shards
    if padded != count:
        batch = jax.tree_util.tree_map(
            lambda leaf: jnp.concatenate([leaf, jnp.repeat(leaf[-1:], padded - count, axis=0)]), batch)
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    batch = jax.device_put(batch, sharding)
    key = ("ensemble", tuple(device.id for device in mesh.devices.flat), padded)
    if key not in sim.compiled_cache:
        fast = sim.forward_only()       # never differentiated in reverse mode here
        member = lambda params: fast._probes(params, fast.initial_state(params))[0]  # noqa: E731
        sim.compiled_cache[key] = jit_with_options(jax.vmap(member), several_fields=sim.several_fields,
                                                   out_shardings=sharding)
    with collector_paused():
        probes = sim.compiled_cache[key](batch)
    if padded == count:
        return probes                   # sharded over the devices as computed
    return {name: values[:count] for name, values in probes.items()}
