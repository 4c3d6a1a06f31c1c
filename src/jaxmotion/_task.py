"""`Task`: body, world, controller family, objective and simulation settings, and the one hot
function `task.evaluate`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Float, PRNGKeyArray

from ._body.base import AbstractBody
from ._control.base import AbstractController, AbstractControllerSpace
from ._objective.registry import Objective
from ._sim.compile import simulation_jit
from ._sim.simulate import SolverName, simulate, simulate_batch, time_grid
from ._sim.trajectory import Trajectory
from ._world import World


class Task(eqx.Module):
    """What to synthesise: a body in a world, a controller family to search, an objective
    to maximise and how to simulate.

    **Arguments:**

    - `body`: the character (e.g. `jaxmotion.lattices.cube()`).
    - `world`: gravity, floor, contact and friction.
    - `space`: the controller family searched (e.g. `RegimesSpace(num_regimes=4, t_per=1.0)`).
    - `objective`: the fitness, **maximised** (e.g. `Objective({"forward": 1, "upright": -10})`).
    - `duration`: simulated time per evaluation, s.
    - `dt`: physics step of the fixed-step search solver, s.
    - `save_dt`: interval between the samples the objective sees, s (default 20 ms: 50 per
        second is plenty for the objectives, and observing costs a share of every evaluation).

    **Raises:** `ValueError` for non-positive or inconsistent times, before any compilation.
    """

    body: AbstractBody
    world: World
    space: AbstractControllerSpace
    objective: Objective
    duration: float = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    save_dt: float | None = eqx.field(static=True)

    def __init__(
        self,
        body: AbstractBody,
        world: World,
        space: AbstractControllerSpace,
        objective: Objective,
        duration: float,
        dt: float = 1e-3,
        save_dt: float | None = None,
    ):
        for name, value, kind in (
            ("body", body, AbstractBody),
            ("world", world, World),
            ("space", space, AbstractControllerSpace),
            ("objective", objective, Objective),
        ):
            if not isinstance(value, kind):
                raise TypeError(
                    f"Task.{name} must be a {kind.__name__}; got {type(value).__name__}"
                )
        time_grid(duration, dt, save_dt)  # raises ValueError naming a bad time
        self.body = body
        self.world = world
        self.space = space
        self.objective = objective
        self.duration = float(duration)
        self.dt = float(dt)
        self.save_dt = None if save_dt is None else float(save_dt)

    def sample(self, num: int, *, key: PRNGKeyArray) -> AbstractController:
        """`num` random controllers of the task's family, stacked along a leading axis."""
        return jax.vmap(lambda k: self.space.sample(key=k))(jr.split(key, num))

    def evaluate(self, params: AbstractController) -> Float[Array, " batch"]:
        """Fitness (maximised) of a batch of controllers (leading batch axis on every array).

        One compiled call simulates the whole batch, sharded over every device JAX sees; it is
        compiled once per body structure, controller family and batch size, and reused by
        every later call with the same shapes. A run that blows up gets fitness `-inf` (the
        worst) rather than raising or returning NaN; count them with
        `jnp.isneginf(fitness)`.

        Results are bitwise reproducible: the same batch gives the same fitness every time,
        whatever the number of devices, and a controller's fitness depends neither on its
        place in the batch nor on the size of the batch it comes in (so a search's best
        controller replays alone to the very fitness the search recorded). Batches under 16
        are padded to 16, which is why they cost about as much as 16.
        """
        batch = _batch_size(params)
        params = _replicated(params)
        chunk = _CHUNK * len(jax.devices())
        if batch <= chunk:
            return _evaluate(self, params)
        # Large batches run as several calls of one compiled size (the last one padded):
        # memory stays bounded and each device keeps a working set that fits its cache.
        calls = -(-batch // chunk)
        padded = _padded(params, calls * chunk)
        parts = [
            _evaluate(
                self, jax.tree_util.tree_map(lambda a, k=k: a[k * chunk : (k + 1) * chunk], padded)
            )
            for k in range(calls)
        ]
        return jnp.concatenate(parts)[:batch]

    def trajectories(self, params: AbstractController) -> Trajectory:
        """The trajectories behind `evaluate`, with a leading batch axis (fast path)."""
        _batch_size(params)
        return _trajectories(self, _replicated(params))

    def simulate(
        self,
        params: AbstractController,
        *,
        solver: SolverName = "symplectic",
        dt: float | None = None,
        save_dt: float | None = None,
    ) -> Trajectory:
        """Simulate one controller (playback) with the search settings, unless `solver`,
        `dt` or `save_dt` say otherwise (`solver="tsit5"` for an adaptive check).

        With the search's own fixed-step solver the trajectory is computed exactly as
        `evaluate` computes it, so a controller replays to the very fitness the search
        recorded (contact-rich motions are chaotic: a different rounding anywhere would
        grow into a visibly different motion).
        """
        dt = self.dt if dt is None else dt
        save_dt = self.save_dt if save_dt is None else save_dt
        if solver == "symplectic":
            task = Task(
                self.body,
                self.world,
                self.space,
                self.objective,
                self.duration,
                dt=dt,
                save_dt=save_dt,
            )
            batch = _replicated(jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], params))
            return jax.tree_util.tree_map(lambda a: a[0], _trajectories(task, batch))
        return _simulate_one(self, params, solver, dt, save_dt)

    def fitness(self, trajectory: Trajectory) -> Float[Array, "..."]:
        """The objective of one trajectory, or of a batch of them (leading axis)."""
        if trajectory.com.ndim == 3:
            return jax.vmap(self.objective)(trajectory)
        return self.objective(trajectory)


@simulation_jit
def _simulate_one(task: Task, params, solver, dt, save_dt) -> Trajectory:
    return simulate(
        task.body, params, task.world, task.duration, dt=dt, save_dt=save_dt, solver=solver
    )


def _batch_size(params) -> int:
    leaves = jax.tree_util.tree_leaves(params)
    if not leaves:
        raise ValueError("Task.evaluate needs a batch of controllers; got an empty pytree")
    sizes = {leaf.shape[0] if jnp.ndim(leaf) else None for leaf in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(
            "Task.evaluate needs controllers stacked along a leading batch axis (e.g. from "
            "task.sample(n, key=...)); got leaves with leading sizes "
            f"{sorted(map(str, sizes))}"
        )
    return sizes.pop()


# Controllers simulated at once per device. `evaluate` runs larger batches as several calls
# of this size: memory stays bounded, and a device's working set (its controllers' regime
# tables and state) stays small enough for its cache. 500 measured fastest here (padded to
# 504, see `_LANES`); powers of two are avoided (see `_SLOW_POWER`).
_CHUNK = 500


def _local_fitness(task: Task, params):
    trajectories = simulate_batch(
        task.body, params, task.world, task.duration, dt=task.dt, save_dt=task.save_dt
    )
    return jax.vmap(task.objective)(trajectories)


# XLA's CPU loops work on groups of 8 float32 lanes; the controllers left over past the last
# whole group run through scalar code whose rounding differs in the last bits, which chaotic
# contact-rich motion amplifies, and batches shorter than 16 compile to different code
# again. Every device's share is therefore at least `_MIN_SHARE` and a whole number of
# `_LANES` groups: a controller's result is then bitwise the same whatever the batch it comes
# in and the number of devices (with the compiler options of `jaxmotion._sim.compile`).
#
# A share that is a power of two from `_SLOW_POWER` up gets one more group: the state's
# component arrays then sit at power-of-two strides and evict each other from the cache.
# Measured on the cube, 1 ms steps, 2 devices: 256 controllers per device 1,550 evals/s,
# 264 per device 2,410/s (so a search with batch 500 ran 35% slower than one with 520);
# 64 against 72 per device 1,610 against 1,900/s.
_MIN_SHARE = 16
_LANES = 8
_SLOW_POWER = 64


def _share(n: int) -> int:
    """A device's share of `n` controllers, padded (see `_MIN_SHARE` and `_SLOW_POWER`)."""
    share = max(_MIN_SHARE, -(-n // _LANES) * _LANES)
    if share >= _SLOW_POWER and share & (share - 1) == 0:
        share += _LANES
    return share


def _mesh() -> Mesh:
    return Mesh(np.array(jax.devices()), ("batch",))


def _replicated(params):
    """`params` placed whole on every device. The compiled evaluation is keyed on its
    inputs' placement as well as their shapes: controllers arrive uncommitted from
    `task.sample`, or spread over the devices by an earlier sharded call (a search's
    children), and without one canonical placement each kind would compile again."""
    sharding = NamedSharding(_mesh(), PartitionSpec())
    return jax.tree_util.tree_map(lambda a: jax.device_put(jnp.asarray(a), sharding), params)


def _padded(params, size: int):
    batch = _batch_size(params)
    if size <= batch:
        return params
    return jax.tree_util.tree_map(
        lambda a: jnp.concatenate([a, jnp.broadcast_to(a[:1], (size - batch, *a.shape[1:]))]),
        params,
    )


def _sharded(fn, task: Task, params):
    """Run `fn(task, params) -> (batch, ...)` with the batch split over every device (small
    batches, where splitting buys little, stay on one device)."""
    devices = jax.devices()
    batch = _batch_size(params)
    if len(devices) == 1 or batch < _MIN_SHARE * len(devices):
        params = _padded(params, _share(batch))
        return jax.tree_util.tree_map(lambda a: a[:batch], fn(task, params))
    params = _padded(params, _share(-(-batch // len(devices))) * len(devices))
    mesh = _mesh()
    dynamic, static = eqx.partition(task, eqx.is_array)
    local = lambda d, p: fn(eqx.combine(d, static), p)
    out = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(PartitionSpec(), PartitionSpec("batch")),
        out_specs=PartitionSpec("batch"),
        check_vma=False,
    )(dynamic, params)
    return jax.tree_util.tree_map(lambda a: a[:batch], out)


@simulation_jit
def _evaluate(task: Task, params) -> Float[Array, " batch"]:
    return _sharded(_local_fitness, task, params)


@simulation_jit
def _trajectories(task: Task, params) -> Trajectory:
    return _sharded(
        lambda t, p: simulate_batch(t.body, p, t.world, t.duration, dt=t.dt, save_dt=t.save_dt),
        task,
        params,
    )
