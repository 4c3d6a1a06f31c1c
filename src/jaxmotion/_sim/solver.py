"""The fixed-step solver of the search path: semi-implicit (symplectic) Euler on diffrax."""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax


class SemiImplicitEuler(dfx.AbstractSolver):
    """Semi-implicit (symplectic) Euler for a state `(positions, velocities)`:
    `v1 = v0 + h a(t0, x0, v0)`, then `x1 = x0 + h xdot(t0, x0, v1)`.

    diffrax's own `SemiImplicitEuler` computes accelerations from positions alone; our forces
    also depend on velocities (spring and contact damping, friction), so this solver takes one
    term whose vector field returns `(xdot, vdot)` of the whole state. First order, symplectic
    for separable conservative systems (energy stays bounded instead of drifting), one force
    evaluation per step. Fixed steps only.

    Each diffrax step is `substeps` Euler steps of `h / substeps` in a loop: the search path
    takes one diffrax step per saved sample, so diffrax's bookkeeping (step control, saving)
    runs once per sample rather than once per physics step.

    With `schedule` and `rates` (functions `(t, args) -> s` and `(t, y, args, s) -> (xdot,
    vdot)` whose composition `rates(t, y, args, schedule(t, args))` is the term's vector
    field), the solver calls `rates` and carries `s`, computed at the end of the previous
    Euler step, into the next: a value the loop carries is kept in memory, where a value
    computed inside the step would be fused into, and recomputed by, every loop over the
    state that uses it (the controllers' choice of regime, in every loop over springs).
    """

    substeps: int = eqx.field(default=1, static=True)
    schedule: Callable | None = eqx.field(default=None, static=True)
    rates: Callable | None = eqx.field(default=None, static=True)

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        h = (t1 - t0) / self.substeps
        if self.rates is None:
            schedule = lambda t: None
            rates = lambda t, y, s: terms.vf(t, y, args)
        else:
            schedule = lambda t: self.schedule(t, args)
            rates = lambda t, y, s: self.rates(t, y, args, s)

        def euler(i, carry):
            (x0, v0), s = carry
            t = t0 + i * h
            _, vdot = rates(t, (x0, v0), s)
            v1 = _axpy(h, vdot, v0)
            xdot, _ = rates(t, (x0, v1), s)  # the unused half is dead code under jit
            return (_axpy(h, xdot, x0), v1), schedule(t0 + (i + 1) * h)

        carry = (y0, schedule(t0))
        if self.substeps == 1:
            y1, _ = euler(0, carry)
        else:
            y1, _ = jax.lax.fori_loop(0, self.substeps, euler, carry)
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _axpy(h, dx, x):
    return jax.tree_util.tree_map(lambda a, b: b + h * a, dx, x)
