"""Time-based regime controllers of the first paper (section 2.2) and their search space
(section 2.3, Table 2)."""

import functools
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .._body.lattice import Lattice
from .base import AbstractController, AbstractControllerSpace, ControllerState
from .deformations import DEFAULT_AMPLITUDES, deform


def _check_amplitudes(amplitudes, owner: str) -> tuple[float, float, float, float]:
    try:
        amps = tuple(float(a) for a in amplitudes)
    except (TypeError, ValueError):
        amps = ()
    if (
        len(amps) != 4
        or not all(math.isfinite(a) and a >= 0 for a in amps)
        or max(amps[0], amps[2]) >= 1
    ):
        raise ValueError(
            f"{owner}.amplitudes = {amplitudes!r}; allowed: four numbers (scale, shear, splay, "
            "twist) >= 0, with scale and splay < 1 so no reflex inverts the lattice"
        )
    return amps  # type: ignore[return-value]


class Regimes(AbstractController):
    """A time-based controller of C regimes (first paper, section 2.2).

    Time runs in periods of `t_per`; regime `c` owns every phase `t mod t_per` closer to
    `times[c]` than to any other regime time (ties go to the lower index), and during it the
    lattice's spring rest lengths are those of its rest shape deformed by reflex `reflexes[c]`
    (see `jaxmotion.REFLEX_NAMES` and `deform`) with coefficient `coefficients[c]`, about the
    centre of mass and along the lattice-centric axes. With `t_per >= duration` the sequence
    is not periodic. The regime is chosen at each control tick and held until the next
    (its state is the active regime's index), so a switch takes effect at the first tick at
    or after its time.

    **Fields:** `times` `(C,)` in `[0, t_per]`; `reflexes` `(C,)` integers in `0..11`;
    `coefficients` `(C,)` in `[-1, 1]`; `t_per` the period (s); `amplitudes` the
    full-strength size of the four kinds of deformation (scale, shear, splay, twist);
    `blend` (s, static) 0 for the paper's hard switch between regimes, or the width over
    which neighbouring regimes' rest lengths cross-fade (a smoothed problem for gradients,
    see `smoothed` and `jaxmotion.refine`).
    """

    times: Float[Array, " C"]
    reflexes: Int[Array, " C"]
    coefficients: Float[Array, " C"]
    t_per: Float[Array, ""]
    amplitudes: tuple[float, float, float, float] = eqx.field(static=True)
    blend: float = eqx.field(static=True)

    supports_batch_last: ClassVar[bool] = True

    def __init__(
        self,
        times: Float[ArrayLike, " C"],
        reflexes: Int[ArrayLike, " C"],
        coefficients: Float[ArrayLike, " C"],
        t_per: float | Float[ArrayLike, ""],
        amplitudes: tuple[float, float, float, float] = DEFAULT_AMPLITUDES,
        blend: float = 0.0,
    ):
        if isinstance(blend, bool) or not isinstance(blend, int | float) or not blend >= 0:
            raise ValueError(f"Regimes.blend = {blend!r}; allowed: a number >= 0 (seconds)")
        if not any(isinstance(x, jax.core.Tracer) for x in (times, reflexes, coefficients, t_per)):
            _check_regimes(times, reflexes, coefficients, t_per)
        self.times = jnp.asarray(times, dtype=float)
        self.reflexes = jnp.asarray(reflexes, dtype=jnp.int32)
        self.coefficients = jnp.asarray(coefficients, dtype=float)
        self.t_per = jnp.asarray(t_per, dtype=float)
        self.amplitudes = _check_amplitudes(amplitudes, "Regimes")
        self.blend = float(blend)

    @property
    def num_regimes(self) -> int:
        return self.times.shape[0]

    def shapes(self, lattice: Lattice) -> Float[Array, "C n 3"]:
        """The deformed rest shape of every regime, in world coordinates."""
        com = lattice.com
        local = (lattice.points - com) @ lattice.frame
        deformed = jax.vmap(lambda r, c: deform(local, r, c, self.amplitudes))(
            self.reflexes, self.coefficients
        )
        return com + deformed @ jnp.transpose(lattice.frame)

    def prepare(self, body: Lattice) -> Float[Array, "C n n"]:
        if not isinstance(body, Lattice):
            raise TypeError(f"Regimes controls mass-spring lattices; got a {type(body).__name__}")
        return jax.vmap(body.rest_length_matrix)(self.shapes(body))

    def active(self, t: Float[Array, ""]) -> Int[Array, ""]:
        """Index of the regime active at time `t` (batch-last controllers give one per
        controller)."""
        phase = jnp.mod(t, self.t_per)
        # A chain of compares rather than an argmin over the regimes, so that it is
        # elementwise for a batch-last stack of controllers too.
        best = jnp.abs(phase - self.times[0])
        index = jnp.zeros(jnp.shape(best), dtype=jnp.int32)
        for c in range(1, self.num_regimes):
            dist = jnp.abs(phase - self.times[c])
            nearer = dist < best
            best = jnp.where(nearer, dist, best)
            index = jnp.where(nearer, c, index)
        return index

    def smoothed(self, width: float) -> "Regimes":
        """This controller with its regime switches blended over about `width` seconds (see
        `blend`); `width=0` is the paper's hard switch."""
        return Regimes(
            self.times, self.reflexes, self.coefficients, self.t_per, self.amplitudes, width
        )

    def init(self, senses, plan) -> ControllerState:
        """The regime of t = 0 (the first tick chooses it again)."""
        return self.update(jnp.zeros((), dtype=float), None, senses, plan)

    def update(self, t, state, senses, plan) -> ControllerState:
        """The choice made at a tick: the active regime's index (hard switch), or the tick's
        time when `blend > 0` (the cross-fade needs every regime's distance)."""
        del state, senses, plan
        if self.blend > 0:
            return ControllerState(jnp.broadcast_to(t, jnp.shape(self.t_per)).astype(float))
        return ControllerState(self.active(t))

    def actuation(self, t, state: ControllerState, plan: Float[Array, "C n n"]):
        """The rest-length table of the regime chosen at the last tick (held until the
        next)."""
        del t
        if self.blend > 0:
            return self._blended(jnp.mod(state.discrete, self.t_per), plan)
        return _pick(plan, state.discrete)

    def _blended(self, phase, plan):
        # Regime c weighs exp(-(d_c - d_min) / blend), d_c = |phase - times[c]|: the nearest
        # regime dominates, and across a switch (where two distances cross) the tables
        # cross-fade over about `blend` seconds. As blend -> 0 this is the hard switch.
        dists = [jnp.abs(phase - self.times[c]) for c in range(self.num_regimes)]
        nearest = dists[0]
        for d in dists[1:]:
            nearest = jnp.minimum(nearest, d)
        weights = [jnp.exp(-(d - nearest) / self.blend) for d in dists]
        total = sum(weights[1:], weights[0])
        return _mix(plan, jnp.stack(weights)) / total


# The regime tables are read at every tick, so the backward pass of a gradient adds each
# tick's cotangent of the table in use into the cotangent of all the tables. JAX's own
# transposes of the reads below turn every regime's slice into a padded copy of the whole
# stack, whose arithmetic XLA repeats for each regime (on the cube the larger part of a
# backward pass); the written ones form the stack's cotangent in one broadcast product.


def _pick(plan, index):
    """`plan[index]` (plan `(C, n, n, *batch)`, index `batch`), as a chain of selects:
    under vmap an index per controller would become a gather, which is slow on CPU;
    selects stay elementwise."""
    return _pick_among(plan.shape[0], plan, index)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _pick_among(regimes: int, plan, index):
    table = plan[0]
    for c in range(1, regimes):
        table = jnp.where(index == c, plan[c], table)
    return table


def _pick_fwd(regimes, plan, index):
    return _pick_among(regimes, plan, index), index


def _pick_bwd(regimes, index, cotangent):
    which = jnp.arange(regimes).reshape((regimes,) + (1,) * index.ndim)
    return _along((which == index).astype(cotangent.dtype), cotangent), None


_pick_among.defvjp(_pick_fwd, _pick_bwd)


@jax.custom_vjp
def _mix(plan, weights):
    """`sum_c weights[c] plan[c]` (weights `(C, *batch)`, plan `(C, n, n, *batch)`)."""
    return sum((w * p for w, p in zip(weights[1:], plan[1:], strict=True)), weights[0] * plan[0])


def _mix_fwd(plan, weights):
    return _mix(plan, weights), (plan, weights)


def _mix_bwd(residuals, cotangent):
    plan, weights = residuals
    product = plan * cotangent[None]  # (C, n, n, *batch)
    # Summed over the two table axes as explicit adds: XLA's reductions over middle axes
    # of the batch-last layout are slow.
    rows = sum(product[:, :, k] for k in range(product.shape[2]))
    return _along(weights, cotangent), sum(rows[:, k] for k in range(rows.shape[1]))


_mix.defvjp(_mix_fwd, _mix_bwd)


def _along(weights, table):
    """`weights[c] * table` stacked over c: `(C, *table.shape)`. The weights `(C, *batch)`
    and the table `(n, n, *batch)` share any trailing batch axes (the batch-last layout)."""
    batch = weights.shape[1:]
    inner = table.ndim - len(batch)
    return weights.reshape(weights.shape[:1] + (1,) * inner + batch) * table[None]


def _check_regimes(times, reflexes, coefficients, t_per) -> None:
    t = np.asarray(times, dtype=float)
    r = np.asarray(reflexes)
    a = np.asarray(coefficients, dtype=float)
    tp = np.asarray(t_per, dtype=float)
    if t.ndim != 1 or t.shape != r.shape or t.shape != a.shape or t.size < 1:
        raise ValueError(
            "Regimes needs times, reflexes and coefficients of the same shape (C,), C >= 1; got "
            f"shapes {t.shape}, {r.shape}, {a.shape}"
        )
    if tp.shape != () or not np.isfinite(tp) or tp <= 0:
        raise ValueError(f"Regimes.t_per = {t_per!r}; allowed: a number > 0")
    for c in range(t.size):
        if not (np.isfinite(t[c]) and 0 <= t[c] <= tp):
            raise ValueError(f"regime {c} has time {t[c]:g}; allowed: 0 <= time <= t_per = {tp:g}")
        if r[c] != np.round(r[c]) or not 0 <= r[c] <= 11:
            raise ValueError(f"regime {c} has reflex {r[c]}; allowed: an integer 0..11")
        if not (np.isfinite(a[c]) and -1 <= a[c] <= 1):
            raise ValueError(
                f"regime {c} has coefficient {a[c]:g}; allowed: -1 <= coefficient <= 1"
            )


PERTURBATIONS: tuple[tuple[float, str], ...] = (
    (0.32, "new reflex number, one regime"),
    (0.08, "new reflex number, every regime"),
    (0.10, "new reflex coefficient, one regime"),
    (0.02, "new reflex coefficient, every regime"),
    (0.22, "adjust reflex coefficient, one regime"),
    (0.06, "adjust reflex coefficient, every regime"),
    (0.05, "new regime time, one regime"),
    (0.01, "new regime time, every regime"),
    (0.11, "adjust regime time, one regime"),
    (0.03, "adjust regime time, every regime"),
)
"""The first paper's Table 2: (probability, perturbation), in the order of the table."""

ADJUST = 0.1
""""Adjust" multiplies a value by `1 + u`, `u` uniform in [-ADJUST, ADJUST): under 10%."""

NUM_REFLEXES = 12

# Upper ends of the Table 2 probabilities on [0, 1), in float64 so that they sum to exactly 1.
_CUMULATIVE = np.cumsum([prob for prob, _ in PERTURBATIONS])
_CUMULATIVE[-1] = 1.0


def _choose(u: Float[Array, ""]) -> Int[Array, ""]:
    """The Table 2 perturbation for a uniform draw `u` in [0, 1) (inverse-CDF sampling)."""
    edges = jnp.asarray(_CUMULATIVE[:-1], dtype=u.dtype)
    return jnp.sum(u >= edges).astype(jnp.int32)


class RegimesSpace(AbstractControllerSpace[Regimes]):
    """The family of `Regimes` controllers with `num_regimes` regimes and period `t_per`, with
    the first paper's sampling and perturbation (section 2.3, Table 2).

    - **Sampling:** regime times uniform in `[0, t_per]`, reflex numbers uniform in `0..11`,
        coefficients from the arcsine distribution on `[-1, 1]` (`sin(pi (u - 1/2))`, `u`
        uniform): its density grows towards the extremes, favouring exaggerated, purposeful
        movements over twitches, as the paper asks.
    - **Perturbation:** one of the ten operators of Table 2 (`PERTURBATIONS`), chosen with the
        table's probabilities. "Pick a new value" draws from the sampling distribution above
        (it may draw the old value again, as in the paper); "adjust" multiplies the value by a
        random factor `1 + u`, `|u| < 10%`, and clips it to its range.
    """

    num_regimes: int = eqx.field(static=True)
    t_per: float = eqx.field(static=True)
    amplitudes: tuple[float, float, float, float] = eqx.field(static=True)

    def __init__(
        self,
        num_regimes: int = 4,
        t_per: float = 1.0,
        amplitudes: tuple[float, float, float, float] = DEFAULT_AMPLITUDES,
    ):
        if isinstance(num_regimes, bool) or not isinstance(num_regimes, int) or num_regimes < 1:
            raise ValueError(
                f"RegimesSpace.num_regimes = {num_regimes!r}; allowed: an integer >= 1"
            )
        try:
            tp = float(t_per)
        except (TypeError, ValueError):
            tp = float("nan")
        if not (math.isfinite(tp) and tp > 0):
            raise ValueError(f"RegimesSpace.t_per = {t_per!r}; allowed: a number > 0 (seconds)")
        self.num_regimes = num_regimes
        self.t_per = tp
        self.amplitudes = _check_amplitudes(amplitudes, "RegimesSpace")

    @property
    def family(self) -> str:
        return "regimes"

    # Every random quantity is a transform of one uniform draw: one threefry call per
    # controller rather than one per quantity, which keeps `sample` and `perturb` cheap to
    # compile (each threefry call costs XLA about half a second on CPU).
    def _times(self, u):
        return u * self.t_per

    @staticmethod
    def _reflexes(u):
        return jnp.minimum(jnp.floor(u * NUM_REFLEXES), NUM_REFLEXES - 1).astype(jnp.int32)

    @staticmethod
    def _coefficients(u):
        # The arcsine law on [-1, 1]: density 1 / (pi sqrt(1 - a^2)), favouring the extremes.
        return jnp.sin(jnp.pi * (u - 0.5))

    def sample(self, *, key: PRNGKeyArray) -> Regimes:
        u = jr.uniform(key, (3, self.num_regimes))
        return Regimes(
            times=self._times(u[0]),
            reflexes=self._reflexes(u[1]),
            coefficients=self._coefficients(u[2]),
            t_per=jnp.asarray(self.t_per, dtype=float),
            amplitudes=self.amplitudes,
        )

    def choose_perturbation(self, *, key: PRNGKeyArray) -> Int[Array, ""]:
        """Index into `PERTURBATIONS`, drawn with the probabilities of Table 2."""
        return _choose(jr.uniform(key))

    def apply_perturbation(
        self, op: Int[Array, ""], controller: Regimes, *, key: PRNGKeyArray
    ) -> Regimes:
        """Apply perturbation number `op` (an index into `PERTURBATIONS`) to `controller`."""
        return self._apply(op, controller, jr.uniform(key, (1 + 4 * self.num_regimes,)))

    def _apply(self, op, controller: Regimes, u) -> Regimes:
        c = self.num_regimes
        u_regime, u_factor, u_reflex, u_coefficient, u_time = (
            u[0],
            u[1 : 1 + c],
            u[1 + c : 1 + 2 * c],
            u[1 + 2 * c : 1 + 3 * c],
            u[1 + 3 * c : 1 + 4 * c],
        )
        one = jnp.arange(c) == jnp.minimum(jnp.floor(u_regime * c), c - 1)
        every = jnp.ones(c, dtype=bool)
        factor = 1.0 + ADJUST * (2.0 * u_factor - 1.0)
        new_reflexes = self._reflexes(u_reflex)
        new_coefficients = self._coefficients(u_coefficient)
        new_times = self._times(u_time)
        adjusted_coefficients = jnp.clip(controller.coefficients * factor, -1.0, 1.0)
        adjusted_times = jnp.clip(controller.times * factor, 0.0, self.t_per)

        def reflexes(mask):
            return lambda: (
                jnp.where(mask, new_reflexes, controller.reflexes),
                controller.coefficients,
                controller.times,
            )

        def coefficients(mask, values):
            return lambda: (
                controller.reflexes,
                jnp.where(mask, values, controller.coefficients),
                controller.times,
            )

        def times(mask, values):
            return lambda: (
                controller.reflexes,
                controller.coefficients,
                jnp.where(mask, values, controller.times),
            )

        branches = [
            reflexes(one),
            reflexes(every),
            coefficients(one, new_coefficients),
            coefficients(every, new_coefficients),
            coefficients(one, adjusted_coefficients),
            coefficients(every, adjusted_coefficients),
            times(one, new_times),
            times(every, new_times),
            times(one, adjusted_times),
            times(every, adjusted_times),
        ]
        r, a, t = jax.lax.switch(op, branches)
        return Regimes(
            times=t,
            reflexes=r,
            coefficients=a,
            t_per=controller.t_per,
            amplitudes=controller.amplitudes,
            blend=controller.blend,
        )

    def trainable(self, controller: Regimes):
        """Regime times and reflex coefficients are refined by gradients; the reflex numbers
        (discrete) and the period (fixed by the family) are not."""
        spec = jax.tree_util.tree_map(lambda _: False, controller)
        return eqx.tree_at(lambda c: (c.times, c.coefficients), spec, (True, True))

    def project(self, controller: Regimes) -> Regimes:
        """Clip times into `[0, t_per]` and coefficients into `[-1, 1]`."""
        return eqx.tree_at(
            lambda c: (c.times, c.coefficients),
            controller,
            (
                jnp.clip(controller.times, 0.0, self.t_per),
                jnp.clip(controller.coefficients, -1.0, 1.0),
            ),
        )

    def perturb(self, controller: Regimes, *, key: PRNGKeyArray, motion=None) -> Regimes:
        del motion
        u = jr.uniform(key, (2 + 4 * self.num_regimes,))
        return self._apply(_choose(u[0]), controller, u[1:])
