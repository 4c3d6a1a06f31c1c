"""The execution policy of batched simulations, in one place: how a batch of controllers is
laid out on the machine (padding to whole lane groups, sharding over devices, chunking of
large batches), kept apart from what is computed. `Task.evaluate`, `Task.trajectories`,
gradient refinement and the searches all run their batches through `run`.
"""

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .compile import simulation_jit

# Controllers simulated at once per device. Larger batches run as several calls of this size:
# memory stays bounded, and a device's working set (its controllers' regime tables and
# state) stays small enough for its cache. 500 measured fastest here (padded to 504, see
# `LANES`); powers of two are avoided (see `SLOW_POWER`).
CHUNK = 500

# XLA's CPU loops work on groups of 8 float32 lanes; the controllers left over past the last
# whole group run through scalar code whose rounding differs in the last bits, which chaotic
# contact-rich motion amplifies, and batches shorter than 16 compile to different code
# again. Every device's share is therefore at least `MIN_SHARE` and a whole number of
# `LANES` groups: a controller's result is then bitwise the same whatever the batch it comes
# in and the number of devices (with the compiler options of `jaxmotion._sim.compile`).
#
# A share that is a power of two from `SLOW_POWER` up gets one more group: the state's
# component arrays then sit at power-of-two strides and evict each other from the cache.
# Measured on the cube, 1 ms steps, 2 devices: 256 controllers per device 1,550 evals/s,
# 264 per device 2,410/s (so a search with batch 500 ran 35% slower than one with 520);
# 64 against 72 per device 1,610 against 1,900/s.
MIN_SHARE = 16
LANES = 8
SLOW_POWER = 64


def share(n: int) -> int:
    """A device's share of `n` controllers, padded (see `MIN_SHARE` and `SLOW_POWER`)."""
    size = max(MIN_SHARE, -(-n // LANES) * LANES)
    if size >= SLOW_POWER and size & (size - 1) == 0:
        size += LANES
    return size


def batch_size(params) -> int:
    """The leading (batch) size shared by every leaf of `params`."""
    leaves = jax.tree_util.tree_leaves(params)
    if not leaves:
        raise ValueError("a batch of controllers is needed; got an empty pytree")
    sizes = {leaf.shape[0] if jnp.ndim(leaf) else None for leaf in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(
            "controllers must be stacked along a leading batch axis (e.g. from "
            "task.sample(n, key=...)); got leaves with leading sizes "
            f"{sorted(map(str, sizes))}"
        )
    return sizes.pop()


def _mesh() -> Mesh:
    return Mesh(np.array(jax.devices()), ("batch",))


def replicated(tree):
    """`tree` placed whole on every device. A compiled call is keyed on its inputs'
    placement as well as their shapes: controllers arrive uncommitted from `task.sample`,
    or spread over the devices by an earlier sharded call (a search's children), and without
    one canonical placement each kind would compile again."""
    sharding = NamedSharding(_mesh(), PartitionSpec())
    return jax.tree_util.tree_map(lambda a: jax.device_put(jnp.asarray(a), sharding), tree)


def padded(params, size: int):
    """The batch padded to `size` with copies of its first controller (concrete arrays
    are padded by numpy: JAX would compile a slice, a broadcast and a concatenation for
    every leaf shape, a few tenths of a second of a first call)."""
    batch = batch_size(params)
    if size <= batch:
        return params

    def pad(a):
        xp = jnp if isinstance(a, jax.core.Tracer) or _extended(a) else np
        a = a if xp is jnp else np.asarray(a)
        return xp.concatenate([a, xp.broadcast_to(a[:1], (size - batch, *a.shape[1:]))])

    return jax.tree_util.tree_map(pad, params)


def _extended(a) -> bool:
    """Whether `a` has a dtype numpy cannot hold (a typed PRNG key)."""
    return jnp.issubdtype(jnp.result_type(a), jax.dtypes.extended)


def _split(batch: int, shard: bool) -> bool:
    """Whether a batch is split over the devices (small batches, where splitting buys
    little, stay on one device)."""
    devices = len(jax.devices())
    return shard and devices > 1 and batch >= MIN_SHARE * devices


def laid_out(batch: int, shard: bool) -> int:
    """The size a batch of `batch` controllers is padded to: each device's share a whole
    number of lane groups (`share`)."""
    if not _split(batch, shard):
        return share(batch)
    devices = len(jax.devices())
    return share(-(-batch // devices)) * devices


def _sharded(fn: Callable, shard: bool, args, params):
    """`fn(args, params) -> outputs with a leading batch axis`, for a batch already padded
    as `laid_out` says, split over every device when `shard` and big enough."""
    if not _split(batch_size(params), shard):
        return fn(args, params)
    dynamic, static = eqx.partition(args, eqx.is_array)
    local = lambda d, p: fn(eqx.combine(d, static), p)
    return jax.shard_map(
        local,
        mesh=_mesh(),
        in_specs=(PartitionSpec(), PartitionSpec("batch")),
        out_specs=PartitionSpec("batch"),
        check_vma=False,
    )(dynamic, params)


@functools.cache
def _compiled(fn: Callable, shard: bool) -> Callable:
    return simulation_jit(functools.partial(_sharded, fn, shard))


def run(fn: Callable, args, params, *, chunk: int | None = None, shard: bool = True):
    """`fn(args, params)` for a batch of controllers `params` (leading batch axis), laid out
    by this module's policy; returns outputs with the leading batch axis.

    `fn` must be a module-level function (its compilation is cached by identity and by the
    shapes of its inputs). `args` reaches every controller whole. Batches run in calls of
    at most `chunk` controllers (default `CHUNK` per device), each padded to the same size
    (so all calls share one compilation), and every call pads each device's share to whole
    lane groups. `shard=False` keeps every call on one device.
    """
    batch = batch_size(params)
    size = CHUNK * (len(jax.devices()) if shard else 1) if chunk is None else chunk
    if batch <= size and chunk is None:
        size = batch
    compiled = _compiled(fn, shard)

    def call(part):
        # Padded before the call and trimmed after it, so every size with the same layout
        # (1 to 16 controllers, say) shares one compilation.
        n = batch_size(part)
        out = compiled(args, replicated(padded(part, laid_out(size, shard))))
        return jax.tree_util.tree_map(lambda a: a[:n], out)

    calls = -(-batch // size)
    if calls == 1:
        return call(params)
    full = padded(params, calls * size)
    parts = [
        call(jax.tree_util.tree_map(lambda a, k=k: a[k * size : (k + 1) * size], full))
        for k in range(calls)
    ]
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:batch], *parts)
