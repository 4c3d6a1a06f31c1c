"""The execution policy of batched simulations, in one place: how a batch of controllers is
laid out on the machine (padding to whole lane groups, one part per worker, chunking of
large batches), kept apart from what is computed. `Task.evaluate`, `Task.trajectories`,
gradient refinement and the searches all run their batches through `run`.

Every part of every batch runs through one compiled single-device program: on the CPU all
parts go to the first device, one thread each, as many at once as JAX has CPU devices
(`jaxmotion.use_cpu_cores` makes one per core). Sharding the batch over the devices instead
(`shard_map`) compiled another program, SPMD-partitioned, whose fusions rounded a sense-based
figure's motion differently from the one-device program's, and differently again past the
first 256 places of a device's share: a search's best controller replayed to another
fitness than it had been given. Threads keep the parallelism (XLA runs each small
simulation loop on the thread that calls it) with a single program, compiled once.
"""

import concurrent.futures
import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .compile import simulation_jit

# Controllers simulated at once per part. Larger batches run as several parts of this size:
# memory stays bounded, and a part's working set (its controllers' regime tables and state)
# stays small enough for its cache. 500 measured fastest here (padded to 504, see `LANES`);
# powers of two are avoided (see `SLOW_POWER`).
CHUNK = 500

# XLA's CPU loops work on groups of 8 float32 lanes; the controllers left over past the last
# whole group run through scalar code whose rounding differs in the last bits, which chaotic
# contact-rich motion amplifies, and batches shorter than 16 compile to different code
# again. Every part is therefore at least `MIN_SHARE` and a whole number of `LANES` groups:
# a controller's result is then bitwise the same whatever the batch it comes in and the
# number of workers (with the compiler options of `jaxmotion._sim.compile`), except that
# XLA rounds some figures differently in wider parts (2D figures from 176 or 264, Rex from
# 264 controllers a part: the README's "Known problem: wide parts of some figures").
#
# A part that is a power of two from `SLOW_POWER` up gets one more group: the state's
# component arrays then sit at power-of-two strides and evict each other from the cache.
# Measured on the cube, 1 ms steps, 2 devices: 256 controllers per device 1,550 evals/s,
# 264 per device 2,410/s (so a search with batch 500 ran 35% slower than one with 520);
# 64 against 72 per device 1,610 against 1,900/s.
MIN_SHARE = 16
LANES = 8
SLOW_POWER = 64


def share(n: int) -> int:
    """The size a part of `n` controllers is padded to (see `MIN_SHARE` and `SLOW_POWER`)."""
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


def workers() -> int:
    """How many parts of a batch run at once: one per device JAX sees."""
    return len(jax.devices())


def _devices(parts: int) -> list:
    """The device of each of `parts` parts: on the CPU the first device for every part (so
    one compiled program serves them all, run on as many threads); on accelerators, one
    device each, in turn."""
    devices = jax.devices()
    if devices[0].platform == "cpu":
        return [devices[0]] * parts
    return [devices[k % len(devices)] for k in range(parts)]


def placed(tree, device=None):
    """`tree`'s arrays committed to `device` (default: the first device). A compiled call is
    keyed on its inputs' placement as well as their shapes: controllers arrive uncommitted
    from `task.sample`, or committed by an earlier call, and without one canonical placement
    each kind would compile again."""
    device = jax.devices()[0] if device is None else device
    dynamic, static = eqx.partition(tree, eqx.is_array)
    if _traced(dynamic):
        return tree
    return eqx.combine(jax.device_put(dynamic, device), static)


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


def _parts(size: int, parallel: bool) -> int:
    """How many parts a call of `size` controllers is split into (small batches, where
    splitting buys little, stay whole)."""
    n = workers()
    return n if parallel and n > 1 and size >= MIN_SHARE * n else 1


@functools.cache
def _compiled(fn: Callable) -> Callable:
    return simulation_jit(fn)


@functools.cache
def _pool(threads: int) -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="jaxmotion")


def _traced(tree) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(tree))


def run(fn: Callable, args, params, *, chunk: int | None = None, parallel: bool = True):
    """`fn(args, params)` for a batch of controllers `params` (leading batch axis), laid out
    by this module's policy; returns outputs with the leading batch axis.

    `fn` must be a module-level function (its compilation is cached by identity and by the
    shapes of its inputs). `args` reaches every controller whole. The batch runs in parts
    of at most `CHUNK` controllers (`chunk` given: parts of `chunk / workers()`, so that
    calls of `chunk` controllers share one compilation), each padded by `share` to the same
    size, so that all parts share one compilation; `workers()` parts run at once.
    `parallel=False` runs the parts one after another. Under a trace (`run` inside `jit`)
    the parts run in line.
    """
    batch = batch_size(params)
    size = min(batch, CHUNK * workers()) if chunk is None else chunk
    parts = _parts(size, parallel)
    piece = -(-size // parts)  # controllers of one part
    padded_piece = share(piece)
    count = -(-batch // piece)
    full = padded(params, count * piece)
    pieces = [
        padded(
            jax.tree_util.tree_map(lambda a, k=k: a[k * piece : (k + 1) * piece], full),
            padded_piece,
        )
        for k in range(count)
    ]
    compiled = _compiled(fn)
    if _traced((args, params)):
        outs = [compiled(args, p) for p in pieces]
    else:
        devices = _devices(count)
        placed_args = {d: placed(args, d) for d in set(devices)}  # once per device
        calls = [
            functools.partial(compiled, placed_args[d], placed(p, d))
            for p, d in zip(pieces, devices, strict=True)
        ]
        threads = workers() if parallel else 1
        if threads == 1 or count == 1:
            outs = [call() for call in calls]
        else:
            # Each thread waits for its part, so that the parts really run side by side.
            outs = list(_pool(threads).map(lambda call: jax.block_until_ready(call()), calls))
        if len(placed_args) > 1:  # parts on several accelerators: one device, to be joined
            outs = [placed(out) for out in outs]
    outs = [jax.tree_util.tree_map(lambda a: a[:piece], out) for out in outs]
    if count == 1:
        return jax.tree_util.tree_map(lambda a: a[:batch], outs[0])
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:batch], *outs)
