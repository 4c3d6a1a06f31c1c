"""The solvers of the closed loop: diffrax solvers whose step is a whole number of control
periods (one save interval).

Each control period `[t_k, t_{k+1}]` starts with the control tick at `t_k` (the controller's
state updated from the time and the body's senses there), then integrates the continuous
state with the discrete state held. The solvers differ in that integration:

- `FixedStep`: semi-implicit (symplectic) Euler in `substeps` equal physics steps of `dt`: the
  search's fast path.
- `Adaptive`: an inner adaptive `diffeqsolve` (Tsit5 or Dopri5 with error control) from tick
  to tick, which never sees a switch inside a step: playback and accuracy checks.

The model (body, controller, world) arrives as diffrax's `args`, a `ClosedLoop`, with the
term `ClosedLoopTerm()` whose vector field reads it; the solvers hold only numerical settings.

A solver step covers `ticks` control periods (a save interval: diffrax's loop costs a few
microseconds a step, a fifth of a whole lattice step at 1 ms for 50 controllers, so one
diffrax step per control period would cost that much). The tick times are computed from
whole tick counts, `(n + j) control_dt`, and the physics step is a constant, so the states
computed never depend on how the periods are grouped: saving at another interval, or
continuing from a final state, computes the same states bitwise.
"""

from typing import Any, ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from .system import ClosedLoop, axpy, join, materialise, split


class ClosedLoopTerm(dfx.AbstractTerm):
    """The diffrax term of a closed loop, whose `args` is the `ClosedLoop`: `vf` is the
    rate of the continuous state with the discrete state held (what an adaptive solver
    integrates between ticks); the solvers of this module also call the system's `tick` at
    the start of each step."""

    def vf(self, t, y, args: ClosedLoop):
        positions, velocities, discrete = split(y)
        xdot, vdot = args.rates(t, positions, velocities, discrete)
        zero = jax.tree_util.tree_map(jnp.zeros_like, discrete)
        return join(xdot, vdot, zero)

    def contr(self, t0, t1, **kwargs):
        del kwargs
        return t1 - t0

    def prod(self, vf, control):
        return jax.tree_util.tree_map(lambda v: v * control, vf)


def _tick(system: ClosedLoop, t, y):
    """The control tick at `t`, starting a period: the state split for integration, the
    discrete state materialised.

    The senses are read from the state the period starts from, which the period's first
    force evaluation reads too, so XLA computes what they share once. The discrete state is
    then materialised (`materialise`): left to itself XLA fused the tick's arithmetic (a
    time-based controller's choice of regime) into the loops that use its result and
    repeated it for every entry of the actuation it selects (a quarter of a lattice's step).
    """
    body, control = y
    positions, velocities, discrete = split((body, system.tick(t, body, control)))
    return positions, velocities, materialise(discrete)


def _periods(period, ticks: int, control_dt: float, t0, y0, carry):
    """`period(t_start, t_end, y, carry) -> (y, carry)` over the `ticks` control periods from
    `t0` (a tick time), every time computed from whole tick counts, `k control_dt`."""
    n = jnp.round(t0 / control_dt)
    dt = jnp.asarray(control_dt, dtype=jnp.result_type(t0))
    if ticks == 1:
        return period(n * dt, (n + 1) * dt, y0, carry)

    def body(state, j):
        y, c = state
        return period((n + j) * dt, (n + j + 1) * dt, y, c), None

    steps = jnp.arange(ticks, dtype=jnp.result_type(t0))
    (y, carry), _ = jax.lax.scan(body, (y0, carry), steps)
    return y, carry


class FixedStep(dfx.AbstractSolver):
    """`ticks` control periods, each a tick then `substeps` semi-implicit Euler steps of
    `dt`: `v1 = v0 + dt a(t, x0, v0)`, then `x1 = x0 + dt xdot(t, x0, v1)`, for the body and
    the controller's continuous state together, with the discrete state chosen at the
    tick.

    The physics step `dt` is a constant (the diffrax times only tell the controller the time),
    so the arithmetic of a step never depends on where it falls.
    """

    ticks: int = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    term_structure: ClassVar = ClosedLoopTerm
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del t1, terms, solver_state, made_jump
        system = args

        def period(t_tick, t_next, y, carry):
            del t_next
            positions, velocities, discrete = _tick(system, t_tick, y)

            def euler(i, xv):
                x, v = xv
                t = t_tick + i * self.dt
                _, vdot = system.rates(t, x, v, discrete)
                v1 = axpy(self.dt, vdot, v)
                xdot, _ = system.rates(t, x, v1, discrete)  # the unused half is dead code
                return axpy(self.dt, xdot, x), v1

            xv = (positions, velocities)
            if self.substeps == 1:
                xv = euler(0, xv)
            else:
                xv = jax.lax.fori_loop(0, self.substeps, euler, xv)
            return join(*xv, discrete), carry

        y1, _ = _periods(period, self.ticks, self.dt * self.substeps, t0, y0, None)
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class Adaptive(dfx.AbstractSolver):
    """`ticks` control periods, each a tick then an adaptive Runge-Kutta solve with error
    control to the next tick with the discrete state held (a discrete switch never falls
    inside one of its steps).

    The solver state carries a first step size into the next period (the mean accepted
    step of this one) and counts the steps taken; when they exceed `max_steps` the period fails with
    `max_steps_reached` (and the simulation is flagged not finite).
    """

    method: dfx.AbstractAdaptiveSolver
    ticks: int = eqx.field(static=True)
    control_dt: float = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    dt0: float = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)

    term_structure: ClassVar = ClosedLoopTerm
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation

    def order(self, terms):
        return self.method.order(terms)

    def init(self, terms, t0, t1, y0, args):
        dtype = jnp.result_type(t0)
        return jnp.asarray(self.dt0, dtype=dtype), jnp.asarray(0, dtype=jnp.int32)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del t1, terms, made_jump
        system = args

        def period(t_tick, t_next, y, carry):
            dt_guess, used, result = carry
            positions, velocities, discrete = _tick(system, t_tick, y)

            def vector_field(t, xv, args):
                del args
                return system.rates(t, xv[0], xv[1], discrete)

            sol = dfx.diffeqsolve(
                dfx.ODETerm(vector_field),
                self.method,
                t0=t_tick,
                t1=t_next,
                dt0=jnp.minimum(dt_guess, t_next - t_tick),
                y0=(positions, velocities),
                saveat=dfx.SaveAt(t1=True),
                stepsize_controller=dfx.PIDController(rtol=self.rtol, atol=self.atol),
                max_steps=self.max_steps,
                throw=False,
                adjoint=dfx.DirectAdjoint(),
            )
            x1, v1 = jax.tree_util.tree_map(lambda a: a[-1], sol.ys)
            # The next period starts from the mean accepted step of this one.
            accepted = jnp.maximum(sol.stats["num_accepted_steps"], 1)
            dt_guess = (t_next - t_tick) / accepted.astype(dt_guess.dtype)
            used = used + sol.stats["num_steps"]
            result = dfx.RESULTS.where(result == dfx.RESULTS.successful, sol.result, result)
            return join(x1, v1, discrete), (dt_guess, used, result)

        dt_guess, used = solver_state
        carry = (dt_guess, used, dfx.RESULTS.successful)
        y1, (dt_guess, used, result) = _periods(period, self.ticks, self.control_dt, t0, y0, carry)
        result = dfx.RESULTS.where(used > self.max_steps, dfx.RESULTS.max_steps_reached, result)
        return y1, None, dict(y0=y0, y1=y1), (dt_guess, used), result

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def solver_for(name: str, grid, *, rtol: float, atol: float, max_steps: int) -> Any:
    """The solver of one control period for a solver name (`"symplectic"`, `"tsit5"`,
    `"dopri5"`)."""
    if name == "symplectic":
        return FixedStep(ticks=grid.save_every, substeps=grid.substeps, dt=grid.dt)
    method = dfx.Tsit5() if name == "tsit5" else dfx.Dopri5()
    return Adaptive(
        method,
        ticks=grid.save_every,
        control_dt=grid.control_dt,
        rtol=rtol,
        atol=atol,
        dt0=grid.dt,
        max_steps=max_steps,
    )
