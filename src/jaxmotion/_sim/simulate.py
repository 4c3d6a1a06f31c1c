"""`simulate`: a body driven by a controller in a world, integrated with diffrax, from the rest
pose or from any state; and its batched layout."""

import math
from dataclasses import dataclass
from typing import Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._body.base import AbstractBody, BodyState
from .._control.base import AbstractController
from .._world import World
from .solver import ClosedLoopTerm, solver_for
from .system import ClosedLoop
from .trajectory import SimulationState, Trajectory, all_finite

SolverName = Literal["symplectic", "tsit5", "dopri5"]
SOLVERS = ("symplectic", "tsit5", "dopri5")

DEFAULT_SAVE_DT = 0.02  # s: 50 samples per second, plenty for the objectives and for GIFs
_WHOLE = 1e-6  # relative tolerance of "a whole number of" (rounding of decimal inputs)


@dataclass(frozen=True)
class TimeGrid:
    """The control ticks, physics steps and saved samples of a simulation, fixed before
    anything is traced: whole control periods fill the duration, whole physics steps fill a
    control period and whole control periods fill a save interval.

    - `num_ticks`: control periods (each one step of the solver's loop).
    - `substeps`: physics steps per control period (fixed-step solver).
    - `save_every`: control periods per saved sample.
    - `control_dt`: the control period, s.
    """

    num_ticks: int
    substeps: int
    save_every: int
    control_dt: float

    @property
    def dt(self) -> float:
        """The physics step of the fixed-step solver, s."""
        return self.control_dt / self.substeps

    @property
    def duration(self) -> float:
        return self.num_ticks * self.control_dt

    @property
    def save_dt(self) -> float:
        return self.save_every * self.control_dt

    @property
    def num_saves(self) -> int:
        """Save intervals (the samples are one more: the start is saved too)."""
        return self.num_ticks // self.save_every

    @property
    def num_steps(self) -> int:
        return self.num_ticks * self.substeps

    @property
    def save_times(self) -> np.ndarray:
        """`num_saves + 1` times from 0 to `duration` (t = 0 is saved too)."""
        return np.arange(self.num_saves + 1) * self.save_dt


def _check_seconds(name, value) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float | np.floating | np.integer)
        or not (math.isfinite(value) and value > 0)
    ):
        raise ValueError(f"{name} = {value!r}; allowed: a number of seconds > 0")


def _whole(name, value, unit_name, unit) -> int:
    """`value / unit` when it is a whole number (>= 1), else a `ValueError`."""
    count = round(value / unit)
    if count < 1 or abs(value - count * unit) > _WHOLE * max(value, unit):
        below = max(1, math.floor(value / unit)) * unit
        above = max(1, math.ceil(value / unit)) * unit
        raise ValueError(
            f"{name} = {value!r} is not a whole number of {unit_name} = {unit!r}; allowed: "
            f"a multiple of {unit_name}, e.g. {below:.10g} or {above:.10g}"
        )
    return count


def time_grid(duration, dt, save_dt=None, control_dt=None) -> TimeGrid:
    """Check the timing arguments and fix the control ticks, steps and samples.

    - `control_dt` (default `dt`) must be a whole number of steps `dt`;
    - `duration` a whole number of control periods;
    - `save_dt` a whole number of control periods that divides the duration (default: the
        longest such interval up to 20 ms).

    Nothing is rounded away silently: the samples saved never change the steps taken.
    Raises `ValueError` naming the argument for anything not a positive number of seconds,
    an interval longer than `duration`, or one that is not a whole number of the shorter one
    (suggesting the nearest that are).
    """
    _check_seconds("duration", duration)
    _check_seconds("dt", dt)
    control_dt = dt if control_dt is None else control_dt
    _check_seconds("control_dt", control_dt)
    if save_dt is not None:
        _check_seconds("save_dt", save_dt)
    for name, value in (("dt", dt), ("control_dt", control_dt), ("save_dt", save_dt)):
        if value is not None and value > duration * (1 + _WHOLE):
            raise ValueError(
                f"{name} = {value!r} is longer than duration = {duration!r}; "
                f"allowed: {name} <= duration"
            )
    if control_dt < dt * (1 - _WHOLE):
        raise ValueError(
            f"control_dt = {control_dt!r} is shorter than dt = {dt!r}; allowed: control_dt >= dt"
        )
    substeps = _whole("control_dt", control_dt, "dt", dt)
    control_dt = float(substeps * dt) if control_dt == dt else float(control_dt)
    num_ticks = _whole("duration", duration, "control_dt" if substeps > 1 else "dt", control_dt)
    if save_dt is None:
        most = max(1, math.floor(DEFAULT_SAVE_DT / control_dt * (1 + _WHOLE)))
        save_every = max(k for k in range(1, most + 1) if num_ticks % k == 0)
    else:
        if save_dt < control_dt * (1 - _WHOLE):
            which = "control_dt" if substeps > 1 else "dt"
            raise ValueError(
                f"save_dt = {save_dt!r} is shorter than {which} = {control_dt!r}; allowed: "
                f"save_dt >= {which}"
            )
        save_every = _whole("save_dt", save_dt, "control_dt" if substeps > 1 else "dt", control_dt)
        if num_ticks % save_every:
            raise ValueError(
                f"duration = {duration!r} is not a whole number of save_dt = {save_dt!r}; "
                f"allowed: a save_dt that divides the duration"
            )
    return TimeGrid(int(num_ticks), int(substeps), int(save_every), float(control_dt))


def _check_solver(solver) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"solver = {solver!r}; allowed: one of {', '.join(map(repr, SOLVERS))}")


def _tolerances(rtol, atol):
    double = jnp.result_type(float) == jnp.float64
    rtol = (1e-8 if double else 1e-5) if rtol is None else rtol
    atol = (1e-10 if double else 1e-6) if atol is None else atol
    return rtol, atol


class _Ticks(dfx.StepTo):
    """`diffrax.StepTo` without its run-time checks: steps to the given times, which the
    caller builds increasing from `t0` to `t1` (whole tick counts). StepTo checks them in the
    compiled program with host callbacks (`equinox.error_if`), and JAX does not write a
    program with host callbacks to its persistent compilation cache: every process compiled
    every simulation again."""

    def wrap(self, direction):
        return type(self)(ts=self.ts * direction)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        del terms, t0, t1, y0, dt0, args, func, error_order
        return self.ts[1], 2


def _integrate(
    system: ClosedLoop,
    y0,
    t0,
    grid: TimeGrid,
    solver: str,
    *,
    rtol=None,
    atol=None,
    max_steps: int = 100_000,
):
    """Integrate the closed loop from `y0 = (body, controller)` at time `t0` over the grid:
    one solver step per save interval (`save_every` control periods), a sample after each.
    Shared by one controller and a batch (the system's layout).

    Returns `(ts, samples, final, ok)`: the saved times, the samples (`system.sample` at
    each, time leading), the final `(body, controller)` and whether the solver succeeded.

    The tick times are `(n0 + k) control_dt` with `n0 = round(t0 / control_dt)`, computed
    the same way whatever the start, so a continued simulation sees the very times (and
    computes the very states) the uninterrupted one did.
    """
    rtol, atol = _tolerances(rtol, atol)
    ticks = _save_ticks(t0, grid)  # a sample at each
    saveat = dfx.SaveAt(
        subs=[dfx.SubSaveAt(t0=True, steps=True, fn=system.sample), dfx.SubSaveAt(t1=True)]
    )
    sol = dfx.diffeqsolve(
        ClosedLoopTerm(),
        solver_for(solver, grid, rtol=rtol, atol=atol, max_steps=max_steps),
        t0=ticks[0],
        t1=ticks[-1],
        dt0=None,
        y0=y0,
        args=system,
        saveat=saveat,
        stepsize_controller=_Ticks(ticks),
        max_steps=grid.num_saves,
        # Reverse mode (gradient refinement) keeps every saved state: the backward pass then
        # recomputes one save interval at a time.
        adjoint=dfx.RecursiveCheckpointAdjoint(checkpoints=grid.num_saves),
        throw=False,
    )
    samples, final = sol.ys
    final = jax.tree_util.tree_map(lambda a: a[-1], final)
    return sol.ts[0], samples, final, sol.result == dfx.RESULTS.successful


def _integrate_segments(system: ClosedLoop, y0, t0, grid: TimeGrid, held: int = 0):
    """The fixed-step path for reverse-mode differentiation: `_integrate` with the symplectic
    solver, written as a `lax.scan` over the save intervals whose body (one interval: the
    solver's very step, then the sample) is checkpointed.

    The forward pass of a gradient then keeps one state per save interval and nothing of
    the steps inside it, and the backward pass recomputes one interval at a time, keeping
    that interval's per-step residuals only while it is transposed: one forward pass, one
    recomputation and one transposition in all, with memory bounded by the interval count
    times the state plus one interval's residuals. (diffrax's `RecursiveCheckpointAdjoint`
    computes the same gradient through its checkpointed while loop, whose bookkeeping grew
    with the number of checkpoints: at T = 5 s a backward pass cost hundreds of forward
    passes.)

    The first `held` save intervals are held constant for differentiation (their samples
    and the state they end in are `stop_gradient`ed, and they are integrated outside the
    differentiated loop): the gradient of what follows, from where the motion really is.

    Same returns as `_integrate` (the solver cannot fail here, so `ok` is `True`); the same
    states up to rounding (XLA fuses the differentiated program differently).
    """
    ticks = _save_ticks(t0, grid)
    solver = solver_for("symplectic", grid, rtol=0.0, atol=0.0, max_steps=0)
    term = ClosedLoopTerm()

    def interval(y, times):
        start, end = times
        y1 = solver.step(term, start, end, y, system, None, False)[0]
        return y1, system.sample(end, y1)

    def scan(y, first, last):
        return jax.lax.scan(
            jax.checkpoint(interval, prevent_cse=False),
            y,
            (ticks[first:last], ticks[first + 1 : last + 1]),
        )

    parts = [jax.tree_util.tree_map(lambda a: a[None], system.sample(ticks[0], y0))]
    y = y0
    if held:
        y, early = jax.lax.stop_gradient(scan(y, 0, held))
        parts.append(early)
    final, late = scan(y, held, grid.num_saves)
    parts.append(late)
    samples = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *parts)
    if held:
        samples = jax.tree_util.tree_map(
            lambda a: a.at[0].set(jax.lax.stop_gradient(a[0])), samples
        )
    return jnp.asarray(ticks), samples, final, jnp.asarray(True)


def _save_ticks(t0, grid: TimeGrid):
    """The tick times of the samples from `t0`: `(n0 + k save_every) control_dt`, `n0 =
    round(t0 / control_dt)`, in the time's dtype.

    Whole tick counts in integers, each time a single rounding `k * control_dt` (XLA would
    reassociate float products of constants, `(k * save_every) * dt` -> `k * (save_every
    dt)`, and label the same instant differently for different save intervals). A start
    time known before tracing (a Python or NumPy number: every start from rest) gives the
    times in NumPy, so that they reach the compiler as constants and what diffrax computes
    from them folds away (its threshold `t1` minus 100 ULPs, a chain of 100 `nextafter`,
    was a fifth of a figure's optimised program); a traced start (a continuation) computes
    them in the program. Both round each product once in IEEE arithmetic: the same times.
    """
    concrete = isinstance(t0, int | float | np.number | np.ndarray)
    xp = np if concrete else jnp
    dtype = np.dtype(jnp.result_type(float))
    n0 = xp.round(xp.asarray(t0, dtype=dtype) / dtype.type(grid.control_dt)).astype(np.int32)
    steps = n0 + grid.save_every * xp.arange(grid.num_saves + 1, dtype=np.int32)
    return steps.astype(dtype) * xp.asarray(grid.control_dt, dtype=dtype)


def _trajectory(ts, samples, final: SimulationState, finite) -> Trajectory:
    """A Trajectory from the samples `(observations, senses, positions)` and the final
    state."""
    obs, senses, positions = samples
    return Trajectory(
        ts=ts,
        points=obs.points,
        com=obs.com,
        frame=obs.frame,
        contact=obs.contact,
        finite=finite,
        final=final,
        senses=senses,
        positions=positions,
    )


def _start(system: ClosedLoop, body: AbstractBody, initial_state):
    """`(t0, (body state, controller state))` for one controller."""
    if isinstance(initial_state, SimulationState):
        return initial_state.t, (BodyState(*initial_state.body), initial_state.controller)
    body_state = body.initial_state() if initial_state is None else BodyState(*initial_state)
    return 0.0, (body_state, system.start(body_state))


def _prepare(body: AbstractBody, controller: AbstractController | None):
    return None if controller is None else controller.prepare(body)


def _on_grid(controller: AbstractController | None, grid: TimeGrid):
    return None if controller is None else controller.on_grid(grid.control_dt)


def simulate(
    body: AbstractBody,
    controller: AbstractController | None,
    world: World,
    duration: float,
    *,
    dt: float = 1e-3,
    save_dt: float | None = None,
    control_dt: float | None = None,
    solver: SolverName = "symplectic",
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100_000,
    initial_state=None,
    senses: bool = False,
    positions: bool = False,
) -> Trajectory:
    """Simulate `body` driven by `controller` in `world` for `duration` seconds.

    The controller runs closed loop: at every control tick (every `control_dt`) it updates
    its state from the time and the body's senses, and its actuation is held until the next
    tick (see `AbstractController`). Write the call for one controller and `jax.vmap` it
    over a batch (or use `Task.evaluate`, which runs the same functions in a faster batched
    layout).

    **Arguments:**

    - `body`: a `Lattice`, a `Figure` (or any `AbstractBody`).
    - `controller`: what actuates the body (`None`: no actuation).
    - `world`: gravity, floor and contact model.
    - `duration`: simulated time in seconds (a whole number of control periods).
    - `dt`: step of the fixed-step solver; for the adaptive solvers, the first step tried.
    - `save_dt`: interval between saved samples, a whole number of control periods that
        divides the duration (default: the longest such interval up to 20 ms). Saving
        never changes the states computed.
    - `control_dt`: the control period, a whole number of steps `dt` (default `dt`).
    - `solver`: `"symplectic"` (semi-implicit Euler at fixed `dt`: the fast path of the
        search) or `"tsit5"` / `"dopri5"` (adaptive fifth order with error control
        `rtol`, `atol`, as the first paper used, integrating from tick to tick: for
        playback and accuracy checks).
    - `rtol`, `atol`: tolerances of the adaptive solvers; by default `1e-5`, `1e-6` in
        float32 and `1e-8`, `1e-10` in float64.
    - `max_steps`: step budget of the adaptive solvers over the whole simulation; a run that
        exhausts it is flagged `finite=False`.
    - `initial_state`: where to start instead of the rest pose at rest: a body state (e.g.
        `lattice.state(points=...)`, or `trajectory.final.body` to start this controller
        where another motion ended, at time 0), or a `SimulationState`
        (`trajectory.final`) to continue a simulation of the same controller from its end:
        on the fixed-step path `[0, T1]` then `[T1, T]` computes bitwise what `[0, T]`
        does.
    - `senses`: also save the senses the controller perceives (`Trajectory.senses`).
    - `positions`: also save the body's positions state (`Trajectory.positions`: what
        rebuilds a figure's every rod, twist included, for export).

    **Returns:** a `Trajectory` sampled at the save times, with the final state; its
    `finite` is `False` for a run that blew up (it never raises for that, so it is safe
    inside a batch).

    **Raises:** `ValueError` for a non-positive or inconsistent `duration`, `dt`,
    `control_dt` or `save_dt`, or an unknown solver, before anything is compiled.
    """
    grid = time_grid(duration, dt, save_dt, control_dt)
    _check_solver(solver)
    controller = _on_grid(controller, grid)
    plan = _prepare(body, controller)
    system = ClosedLoop(
        body.dynamics(),
        controller,
        plan,
        world,
        grid.control_dt,
        record_senses=senses,
        record_positions=positions,
    )
    t0, y0 = _start(system, body, initial_state)
    system = system.with_start(y0[1])
    ts, samples, (body_state, control), ok = _integrate(
        system, y0, t0, grid, solver, rtol=rtol, atol=atol, max_steps=max_steps
    )
    final = SimulationState(ts[-1], body_state, system.restore(control))
    obs = samples[0]
    finite = ok & all_finite(obs.points, obs.com, obs.frame, final.body, final.controller)
    return _trajectory(ts, samples, final, finite)


def _to_last(tree):
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), tree)


def _to_first(tree):
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), tree)


def _batched_start(system: ClosedLoop, body: AbstractBody, initial_state, batch: int):
    """`(t0, y0)` for a batch, `y0` in the batch-last layout."""
    broadcast = lambda tree: jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (batch, *jnp.shape(a))), tree
    )
    if isinstance(initial_state, SimulationState):
        t = jnp.asarray(initial_state.t)
        if t.ndim:
            # One grid serves the batch, so its states must share their time.
            t = eqx.error_if(t, jnp.any(t != t[0]), "a batch of states must share their time")
            t = t[0]
        body_state = BodyState(*initial_state.body)
        control = initial_state.controller
        if _is_single(body, body_state):
            body_state, control = broadcast(body_state), broadcast(control)
        return t, _to_last((body_state, control))
    body_state = body.initial_state() if initial_state is None else BodyState(*initial_state)
    if _is_single(body, body_state):
        body_state = broadcast(body_state)
    body_state = _to_last(body_state)
    return 0.0, (body_state, system.start(body_state))


def _is_single(body: AbstractBody, state) -> bool:
    """Whether a body state is one body's (rather than a batch with a leading axis)."""
    reference = jax.tree_util.tree_leaves(body.initial_state())
    given = jax.tree_util.tree_leaves(state)
    return [jnp.shape(a) for a in given] == [jnp.shape(a) for a in reference]


def simulate_batch(
    body: AbstractBody,
    controllers: AbstractController | None,
    world: World,
    duration: float,
    *,
    dt: float = 1e-3,
    save_dt: float | None = None,
    control_dt: float | None = None,
    solver: SolverName = "symplectic",
    initial_state=None,
    batch: int | None = None,
    record_senses: bool = False,
    record_positions: bool = False,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100_000,
    reverse_mode: bool = False,
    gradient_from: float | None = None,
) -> Trajectory:
    """`jax.vmap(simulate)` over `controllers` (leading batch axis), computed in the
    batch-last layout: the same per-step functions, called on whole batches with the batch
    as the last (contiguous) axis of every array, so XLA runs each step as a few vectorised
    loops over the batch, and diffrax integrates the whole batch as one system. Returns the
    same trajectories as the plain `vmap`, with a leading batch axis.

    `initial_state` is shared (one body state, or one `SimulationState`) or per controller
    (a leading batch axis). `controllers=None` simulates `batch` unactuated bodies.
    `record_senses` also saves the senses each controller perceives (`Trajectory.senses`),
    `record_positions` each body's positions state (`Trajectory.positions`).
    `reverse_mode=True` (the symplectic solver only) integrates in the layout built for
    `jax.grad` (`_integrate_segments`): the same states up to rounding, a backward pass of a
    few forward passes' cost. With it, `gradient_from` (seconds from the start, a whole
    number of save intervals) holds everything before that time constant for
    differentiation: gradients see only what the controllers do from then on.
    """
    grid = time_grid(duration, dt, save_dt, control_dt)
    _check_solver(solver)
    if controllers is not None:
        controllers = _on_grid(controllers, grid)
        batch = jax.tree_util.tree_leaves(controllers)[0].shape[0]
        plans = jax.vmap(lambda c: _prepare(body, c))(controllers)
    else:
        plans = None
    system = ClosedLoop(
        body.dynamics(),
        None if controllers is None else _to_last(controllers),
        _to_last(plans),
        world,
        grid.control_dt,
        batched=True,
        record_senses=record_senses,
        record_positions=record_positions,
    )
    t0, y0 = _batched_start(system, body, initial_state, batch)
    system = system.with_start(y0[1])
    if reverse_mode:
        if solver != "symplectic":
            raise ValueError(f"reverse_mode=True needs solver='symplectic'; got {solver!r}")
        held = 0 if gradient_from is None else _held_saves(gradient_from, grid)
        ts, samples, final, ok = _integrate_segments(system, y0, t0, grid, held)
    else:
        ts, samples, final, ok = _integrate(
            system, y0, t0, grid, solver, rtol=rtol, atol=atol, max_steps=max_steps
        )
    # (time, ..., batch) -> (batch, time, ...); final (..., batch) -> (batch, ...)
    obs, senses, positions = _to_first(samples)
    body_state, control = _to_first((final[0], system.restore(final[1])))
    finite = ok & _per_batch_finite((obs.points, obs.com, obs.frame, body_state, control))
    ts = jnp.broadcast_to(ts, (batch, ts.shape[0]))
    final = SimulationState(ts[:, -1], body_state, control)
    return _trajectory(ts, (obs, senses, positions), final, finite)


def _held_saves(gradient_from, grid: TimeGrid) -> int:
    """The save intervals before `gradient_from` seconds (a whole number of them, fewer than
    all)."""
    if not (isinstance(gradient_from, int | float) and 0 <= gradient_from < grid.duration):
        raise ValueError(
            f"gradient_from = {gradient_from!r}; allowed: seconds >= 0 and < the duration "
            f"{grid.duration:g}"
        )
    held = round(gradient_from / grid.save_dt)
    if abs(held * grid.save_dt - gradient_from) > _WHOLE * max(grid.duration, grid.save_dt):
        raise ValueError(
            f"gradient_from = {gradient_from!r} is not a whole number of save intervals "
            f"({grid.save_dt:g} s); allowed: a multiple of save_dt"
        )
    return int(held)


def _per_batch_finite(tree):
    """Per batch element (leading axis), whether every floating leaf is finite."""
    ok = None
    for leaf in jax.tree_util.tree_leaves(tree):
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            continue
        good = jnp.all(jnp.isfinite(leaf).reshape(leaf.shape[0], -1), axis=1)
        ok = good if ok is None else ok & good
    return ok


__all__ = ["SOLVERS", "TimeGrid", "simulate", "simulate_batch", "time_grid"]
