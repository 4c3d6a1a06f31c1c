"""`simulate`: one body, one controller, one world, integrated with diffrax."""

import math
from dataclasses import dataclass
from typing import Literal

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from .._body.base import AbstractBody
from .._control.base import AbstractController
from .._world import World
from .solver import SemiImplicitEuler
from .trajectory import Observation, Trajectory

SolverName = Literal["symplectic", "tsit5", "dopri5"]
SOLVERS = ("symplectic", "tsit5", "dopri5")


@dataclass(frozen=True)
class TimeGrid:
    """The steps and save times of a simulation, fixed before anything is traced: whole
    save intervals fill the duration and whole, equal steps fill each save interval."""

    duration: float
    num_saves: int
    substeps: int

    @property
    def num_steps(self) -> int:
        return self.num_saves * self.substeps

    @property
    def dt(self) -> float:
        return self.duration / self.num_steps

    @property
    def save_dt(self) -> float:
        return self.duration / self.num_saves

    @property
    def save_times(self) -> np.ndarray:
        """`num_saves + 1` times from 0 to `duration` (t = 0 is saved too)."""
        return np.linspace(0.0, self.duration, self.num_saves + 1)


def _check_seconds(name, value) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float | np.floating | np.integer)
        or not (math.isfinite(value) and value > 0)
    ):
        raise ValueError(f"{name} = {value!r}; allowed: a number of seconds > 0")


def time_grid(duration, dt, save_dt=None) -> TimeGrid:
    """Check the timing arguments and fix the save intervals and steps.

    The duration is cut into `round(duration / save_dt)` equal save intervals (`save_dt`
    defaults to 20 ms, or `dt` if that is longer), and each interval into
    `round(save_interval / dt)` equal steps; so the step actually taken can differ a little
    from `dt`. Raises `ValueError` naming the argument for anything not a positive number of
    seconds, or a `dt` or `save_dt` longer than `duration`.
    """
    _check_seconds("duration", duration)
    _check_seconds("dt", dt)
    if save_dt is None:
        save_dt = min(max(0.02, dt), duration)
    _check_seconds("save_dt", save_dt)
    for name, value in (("dt", dt), ("save_dt", save_dt)):
        if value > duration * (1 + 1e-9):
            raise ValueError(
                f"{name} = {value!r} is longer than duration = {duration!r}; "
                f"allowed: {name} <= duration"
            )
    if save_dt < dt * (1 - 1e-9):
        raise ValueError(
            f"save_dt = {save_dt!r} is shorter than dt = {dt!r}; allowed: save_dt >= dt"
        )
    num_saves = max(1, round(duration / save_dt))
    substeps = max(1, round(duration / num_saves / dt))
    return TimeGrid(float(duration), int(num_saves), int(substeps))


def _check_solver(solver) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"solver = {solver!r}; allowed: one of {', '.join(map(repr, SOLVERS))}")


def simulate(
    body: AbstractBody,
    controller: AbstractController | None,
    world: World,
    duration: float,
    *,
    dt: float = 1e-3,
    save_dt: float | None = None,
    solver: SolverName = "symplectic",
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100_000,
    initial_state=None,
) -> Trajectory:
    """Simulate `body` driven by `controller` in `world` for `duration` seconds.

    Write the call for one controller and `jax.vmap` it over a batch of controllers (or use
    `Task.evaluate`, which batches the same computation in a faster layout).

    **Arguments:**

    - `body`: a `Lattice` (or any `AbstractBody`), starting at rest in its rest pose.
    - `controller`: what actuates the body (`None`: no actuation, the body keeps its rest
        lengths).
    - `world`: gravity, floor and contact model.
    - `duration`: simulated time in seconds.
    - `dt`: step of the fixed-step solver (rounded so whole steps fill `duration`); for the
        adaptive solvers, the first step tried.
    - `save_dt`: interval between saved samples (rounded to whole steps; default 20 ms).
        The final state is always saved.
    - `solver`: `"symplectic"` (semi-implicit Euler at fixed `dt`: the fast path of the
        search) or `"tsit5"` / `"dopri5"` (adaptive fifth order with error control
        `rtol`, `atol`, as the first paper used: for playback and accuracy checks).
    - `rtol`, `atol`: tolerances of the adaptive solvers; by default `1e-5`, `1e-6` in
        float32 (tighter cannot be met in single precision) and `1e-8`, `1e-10` in float64.
    - `max_steps`: step budget of the adaptive solvers; a run that exhausts it is flagged
        `finite=False`.
    - `initial_state`: where to start instead of the rest pose at rest (e.g.
        `lattice.state(points=..., velocities=...)`).

    **Returns:** a `Trajectory` sampled at the save times; `trajectory.finite` is `False` for
    a run that blew up (it never raises for that, so it is safe inside a batch).

    **Raises:** `ValueError` for a non-positive `duration`, `dt` or `save_dt`, or an unknown
    solver, before anything is compiled.
    """
    grid = time_grid(duration, dt, save_dt)
    _check_solver(solver)
    dynamics = body.dynamics()
    plan = None if controller is None else controller.prepare(body)

    def vector_field(t, y, args):
        ctrl, plan = args
        actuation = None if ctrl is None else ctrl.actuation(t, plan)
        return dynamics.rates(y, actuation, world)

    positions, ok = _solve(
        grid,
        vector_field,
        body.initial_state() if initial_state is None else initial_state,
        (controller, plan),
        solver,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
    )
    return _trajectory(grid, _observe(dynamics, world, positions, batched=False), ok)


def _solve(grid, vector_field, y0, args, solver, *, rtol=None, atol=None, max_steps=100_000):
    """Integrate; return the positions at the save times (time leading) and whether the
    solver succeeded. Shared by the single and the batched paths."""
    term = dfx.ODETerm(vector_field)
    save_ts = jnp.asarray(grid.save_times, dtype=jnp.result_type(float))
    # Only positions are saved during the solve (a cheap copy per sample); the observables
    # are computed from them afterwards, for all samples at once.
    positions = lambda t, y, args: y[0]
    if solver == "symplectic":
        # One diffrax step per save interval, each made of `substeps` physics steps.
        sol = dfx.diffeqsolve(
            term,
            SemiImplicitEuler(substeps=grid.substeps),
            t0=save_ts[0],
            t1=save_ts[-1],
            dt0=None,
            y0=y0,
            args=args,
            saveat=dfx.SaveAt(t0=True, steps=True, fn=positions),
            stepsize_controller=dfx.StepTo(save_ts),
            max_steps=grid.num_saves,
            throw=False,
        )
    else:
        method = dfx.Tsit5() if solver == "tsit5" else dfx.Dopri5()
        double = jnp.result_type(float) == jnp.float64
        rtol = (1e-8 if double else 1e-5) if rtol is None else rtol
        atol = (1e-10 if double else 1e-6) if atol is None else atol
        sol = dfx.diffeqsolve(
            term,
            method,
            t0=save_ts[0],
            t1=save_ts[-1],
            dt0=grid.dt,
            y0=y0,
            args=args,
            saveat=dfx.SaveAt(ts=save_ts, fn=positions),
            stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps,
            throw=False,
        )
    return sol.ys, sol.result == dfx.RESULTS.successful


def _trajectory(grid, obs: Observation, ok) -> Trajectory:
    """Assemble a Trajectory from observations with leading axes (..., time)."""
    lead = obs.com.shape[:-2]
    finite = ok
    for a in (obs.points, obs.com, obs.frame):
        finite = finite & jnp.all(jnp.isfinite(a).reshape(*lead, -1), axis=-1)
    ts = jnp.broadcast_to(jnp.asarray(grid.save_times, obs.com.dtype), (*lead, grid.num_saves + 1))
    return Trajectory(
        ts=ts, points=obs.points, com=obs.com, frame=obs.frame, contact=obs.contact, finite=finite
    )


def simulate_batch(
    body: AbstractBody,
    controllers: AbstractController,
    world: World,
    duration: float,
    *,
    dt: float = 1e-3,
    save_dt: float | None = None,
) -> Trajectory:
    """`jax.vmap(simulate)` over `controllers` (leading batch axis), computed in the fast
    batch-last layout: the single-controller step is vmapped with the batch as the last
    (contiguous) axis of every array, so XLA runs each step as a few vectorised loops over the
    batch, and diffrax integrates the whole batch as one system (fixed step only). Returns
    the same trajectories as the plain `vmap`, with a leading batch axis.
    """
    grid = time_grid(duration, dt, save_dt)
    dynamics = body.dynamics()
    plans = jax.vmap(lambda c: c.prepare(body))(controllers)
    to_last = lambda tree: jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), tree)
    args = (to_last(controllers), to_last(plans))
    batch = jax.tree_util.tree_leaves(controllers)[0].shape[0]
    y0 = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a[..., None], (*a.shape, batch)), body.initial_state()
    )

    if type(controllers).supports_batch_last:
        batched_actuation = lambda t, ctrl, plan: ctrl.actuation(t, plan)
    else:
        batched_actuation = jax.vmap(
            lambda t, ctrl, plan: ctrl.actuation(t, plan), in_axes=(None, -1, -1), out_axes=-1
        )
    if type(dynamics).supports_batch_last:
        batched_rates = lambda y, act: dynamics.rates(y, act, world)
    else:
        batched_rates = jax.vmap(
            lambda y, act: dynamics.rates(y, act, world), in_axes=-1, out_axes=-1
        )

    # diffrax traces the vector field several times (structure checks, the loop body twice,
    # and the semi-implicit step calls it twice). Under `jax.jit(inline=True)` every call
    # with the same shapes reuses one trace, inlined where it is called (the computation
    # is unchanged; tracing a figure's step takes a large share of its compile time).
    batched_rates = jax.jit(batched_rates, inline=True)

    def vector_field(t, y, args):
        ctrl, plan = args
        return batched_rates(y, batched_actuation(t, ctrl, plan))

    positions, ok = _solve(grid, vector_field, y0, args, "symplectic")
    return _trajectory(grid, _observe(dynamics, world, positions, batched=True), ok)


def _observe(dynamics, world, positions, *, batched: bool) -> Observation:
    """Observables of saved positions, all samples at once.

    `positions` has leaves `(time, *shape)` (single) or `(time, *shape, batch)` (batched).
    The time (and batch) axes are moved to the back, where `observe` treats them elementwise
    (the batch stays the contiguous axis, as in the simulation), and the fields come back
    as `(time, ...)` or `(batch, time, ...)`.
    """
    if batched:
        trailing = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -2), positions)
    else:
        trailing = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), positions)
    obs = dynamics.observe(trailing, world)
    k = 2 if batched else 1

    def lead(a):
        a = jnp.moveaxis(a, tuple(range(a.ndim - k, a.ndim)), tuple(range(k)))
        return jnp.swapaxes(a, 0, 1) if batched else a

    return jax.tree_util.tree_map(lead, obs)


__all__ = ["SOLVERS", "TimeGrid", "simulate", "simulate_batch", "time_grid"]
