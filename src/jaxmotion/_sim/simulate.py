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

    obs, ok = _solve(
        grid,
        vector_field,
        body.initial_state() if initial_state is None else initial_state,
        (controller, plan),
        solver,
        observe=lambda positions: dynamics.observe(positions, world),
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
    )
    return _trajectory(grid, obs, ok)


def _solve(
    grid,
    vector_field,
    y0,
    args,
    solver,
    *,
    observe=None,
    rtol=None,
    atol=None,
    max_steps=100_000,
    scheduled=None,
):
    """Integrate; return `observe(positions)` at the save times (time leading on every
    leaf; default: the positions themselves) and whether the solver succeeded. Shared by the
    single and the batched paths.

    The observables are computed as each sample is saved, inside the solver's loop, where
    the state is small and stays in the cache: observing all saved samples at once
    afterwards worked on arrays of every sample of every controller, which spilled out of the
    cache and cost a sixth of a whole evaluation.

    `scheduled` (fixed step only) is a pair `(schedule, rates)` that `vector_field` is made
    of, `vector_field(t, y, args) = rates(t, y, args, schedule(t, args))`, for the solver to
    carry the schedule from step to step (see `SemiImplicitEuler`)."""
    term = dfx.ODETerm(vector_field)
    save_ts = jnp.asarray(grid.save_times, dtype=jnp.result_type(float))
    observe = (lambda x: x) if observe is None else observe
    sample = lambda t, y, args: observe(y[0])  # observables depend on positions alone
    if solver == "symplectic":
        # One diffrax step per save interval, each made of `substeps` physics steps.
        sol = dfx.diffeqsolve(
            term,
            SemiImplicitEuler(grid.substeps, *(scheduled or (None, None))),
            t0=save_ts[0],
            t1=save_ts[-1],
            dt0=None,
            y0=y0,
            args=args,
            saveat=dfx.SaveAt(t0=True, steps=True, fn=sample),
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
            saveat=dfx.SaveAt(ts=save_ts, fn=sample),
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

    # The controllers' choice at each step (`schedule`) is carried by the solver from one
    # step to the next, so it is made once per controller, not once per entry of the
    # actuation built from it (see `SemiImplicitEuler`).
    if type(controllers).supports_batch_last:
        batched_schedule = lambda t, ctrl: ctrl.schedule(t)
        batched_actuation = lambda s, ctrl, plan: ctrl.actuation_from(s, plan)
    else:
        batched_schedule = jax.vmap(
            lambda t, ctrl: ctrl.schedule(t), in_axes=(None, -1), out_axes=-1
        )
        batched_actuation = jax.vmap(
            lambda s, ctrl, plan: ctrl.actuation_from(s, plan), in_axes=-1, out_axes=-1
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

    schedule = lambda t, args: batched_schedule(t, args[0])
    rates = lambda t, y, args, s: batched_rates(y, batched_actuation(s, *args))
    vector_field = lambda t, y, args: rates(t, y, args, schedule(t, args))
    # `observe` works elementwise over trailing batch axes: each saved sample is observed for
    # the whole batch at once, the batch staying the contiguous last axis.
    obs, ok = _solve(
        grid,
        vector_field,
        y0,
        args,
        "symplectic",
        observe=lambda positions: dynamics.observe(positions, world),
        scheduled=(schedule, rates),
    )
    # (time, ..., batch) -> (batch, time, ...)
    obs = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), obs)
    return _trajectory(grid, obs, ok)


__all__ = ["SOLVERS", "TimeGrid", "simulate", "simulate_batch", "time_grid"]
