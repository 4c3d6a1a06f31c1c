"""Time-based banked stimulus-response (BSR) controllers of the second paper (sections 2.3 and
4.1) and their search space (Table 2; creep and reinitialisation, section 2.1.3)."""

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._body.figure import Figure
from .base import AbstractController, AbstractControllerSpace, ControllerState


class TimeBSR(AbstractController):
    """A time-based BSR controller: R rules, each owning a segment of every period `t_per`.

    Time runs in periods of `t_per`; the split points cut each period into R consecutive
    segments, and during segment `r` rule `r` is active: every free joint angle of the figure
    moves toward the rule's target pose `targets[r]` with the rule's time constant `taus[r]`
    (`tau^2 th'' + 2 tau th' + (th - th0) = 0`). With `t_per >= duration` the script runs
    once (not periodic: the second paper's Beryl tumble). The rule is chosen at each control
    tick and held until the next (its state is the active rule's index).

    **Mirrored gaits** (`mirror`, not in the paper): a walk is the same half-stride twice,
    the second time with left and right swapped. With `mirror` set (the figure's
    `Figure.mirror` map, `(partner, sign)`), the rules share the first half of each period,
    `[0, t_per / 2)` (the splits lie in `[0, t_per / 2]`), and over the second half the same
    rules act again with their target poses mirrored: angle `i` moves toward
    `sign[i] * targets[r, partner[i]]`. The search then looks only among gaits whose
    two halves are mirror images, which keeps a walk on course.

    **Fields:** `splits` `(R - 1,)` the segment boundaries in `[0, t_per]` (with `mirror`,
    `[0, t_per / 2]`), ascending (rule 0 owns `[0, splits[0])`, rule r `[splits[r - 1],
    splits[r])`, the last rule up to the end of the period or half period); `targets` `(R,
    num_free)` target joint angles (radians); `taus` `(R,)` time constants (s); `t_per` the
    period (s); `mirror` (static) `None` or the mirror map.
    """

    splits: Float[Array, " R-1"]
    targets: Float[Array, "R num_free"]
    taus: Float[Array, " R"]
    t_per: Float[Array, ""]
    mirror: tuple[tuple[int, ...], tuple[float, ...]] | None = eqx.field(static=True)

    supports_batch_last: ClassVar[bool] = True

    def __init__(
        self,
        splits: Float[ArrayLike, " R-1"],
        targets: Float[ArrayLike, "R num_free"],
        taus: Float[ArrayLike, " R"],
        t_per: float | Float[ArrayLike, ""],
        mirror=None,
    ):
        mirror = _mirror_map(mirror, np.shape(targets)[-1])
        if not any(isinstance(x, jax.core.Tracer) for x in (splits, targets, taus, t_per)):
            _check(splits, targets, taus, t_per, mirror is not None)
        self.splits = jnp.asarray(splits, dtype=float)
        self.targets = jnp.asarray(targets, dtype=float)
        self.taus = jnp.asarray(taus, dtype=float)
        self.t_per = jnp.asarray(t_per, dtype=float)
        self.mirror = mirror

    @property
    def num_rules(self) -> int:
        return self.taus.shape[0]

    def prepare(self, body: Figure) -> None:
        if not isinstance(body, Figure):
            raise TypeError(f"TimeBSR controls articulated figures; got a {type(body).__name__}")
        if self.targets.shape[-1] != body.num_free:
            raise ValueError(
                f"TimeBSR has targets for {self.targets.shape[-1]} joint angles but figure "
                f"{body.name!r} has {body.num_free} free angles"
            )
        if self.mirror is not None and self.mirror != body.mirror:
            raise ValueError(
                f"TimeBSR.mirror = {self.mirror!r} is not figure {body.name!r}'s mirror map "
                f"(Figure.mirror = {body.mirror!r})"
            )
        return None

    def active(self, t: Float[Array, ""]):
        """Index of the rule active at time `t` (with `mirror`, plus R over the second half
        of the period, where the rules act mirrored)."""
        phase = jnp.mod(t, self.t_per)
        second = None
        if self.mirror is not None:
            half = 0.5 * self.t_per
            second = phase >= half
            phase = jnp.where(second, phase - half, phase)
        index = jnp.zeros(jnp.shape(phase), dtype=jnp.int32)
        for r in range(self.num_rules - 1):
            index = index + (phase >= self.splits[r]).astype(jnp.int32)
        if second is not None:
            index = index + self.num_rules * second.astype(jnp.int32)
        return index

    def init(self, senses, plan) -> ControllerState:
        """The rule of t = 0 (the first tick chooses it again)."""
        return self.update(jnp.zeros((), dtype=float), None, senses, plan)

    def update(self, t, state, senses, plan) -> ControllerState:
        """The rule whose segment holds the tick's time."""
        del state, senses, plan
        return ControllerState(self.active(t))

    def actuation(self, t, state: ControllerState, plan):
        """The active rule's target pose and time constant (held until the next tick)."""
        del t, plan
        # A chain of selects (elementwise under vmap) rather than an index (a gather).
        index = state.discrete
        rule = index if self.mirror is None else jnp.mod(index, self.num_rules)
        target, tau = self.targets[0], self.taus[0]
        for r in range(1, self.num_rules):
            on = rule == r
            target = jnp.where(on, self.targets[r], target)
            tau = jnp.where(on, self.taus[r], tau)
        if self.mirror is not None:
            mirrored = mirrored_pose(target, *self.mirror)
            target = jnp.where(index >= self.num_rules, mirrored, target)
        return target, tau


def mirrored_pose(target, partner, sign):
    """The mirror image of the pose `target` (free angles, leading axis; any batch after
    it) under the map `(partner, sign)` (`Figure.mirror`): angle `i` is
    `sign[i] * target[partner[i]]`."""
    return jnp.stack([s * target[p] for p, s in zip(partner, sign, strict=True)])


def figure_mirror(figure: Figure, mirror: bool, owner: str, attribute: str):
    """The figure's map `Figure.<attribute>` (`mirror` or `sense_mirror`) if `mirror` is
    true, else `None`; a `ValueError` naming `owner` for a non-bool or a figure without a
    mirror image."""
    if not isinstance(mirror, bool):
        raise ValueError(f"{owner}.mirror = {mirror!r}; allowed: True or False")
    if not mirror:
        return None
    value = getattr(figure, attribute)
    if value is None:
        why = "is planar" if figure.planar else "is not left-right symmetric"
        raise ValueError(
            f"{owner}.mirror = True but figure {figure.name!r} {why}, so it has no mirror "
            f"image (Figure.{attribute} is None); allowed: mirror = False"
        )
    return value


def _mirror_map(mirror, num_free: int):
    """`mirror` as a `(partner, sign)` pair of tuples (lists, as JSON gives them, are
    accepted), checked against `num_free` angles; `None` stays `None`."""
    if mirror is None:
        return None
    try:
        partner, sign = mirror
        partner = tuple(int(p) for p in partner)
        sign = tuple(float(s) for s in sign)
    except (TypeError, ValueError):
        raise ValueError(
            f"TimeBSR.mirror = {mirror!r}; allowed: None or (partner, sign), a figure's "
            "Figure.mirror"
        ) from None
    if (
        len(partner) != num_free
        or len(sign) != num_free
        or sorted(partner) != list(range(num_free))
        or any(s not in (-1.0, 1.0) for s in sign)
    ):
        raise ValueError(
            f"TimeBSR.mirror = {mirror!r}; allowed: a permutation of the {num_free} free "
            "angles and a sign of +-1 for each (a figure's Figure.mirror)"
        )
    return partner, sign


def _check(splits, targets, taus, t_per, mirrored: bool = False) -> None:
    sp = np.asarray(splits, dtype=float)
    tg = np.asarray(targets, dtype=float)
    ta = np.asarray(taus, dtype=float)
    tp = np.asarray(t_per, dtype=float)
    if ta.ndim != 1 or ta.size < 1 or tg.ndim != 2 or tg.shape[0] != ta.size:
        raise ValueError(
            "TimeBSR needs taus (R,) and targets (R, num_free) with R >= 1; got shapes "
            f"{ta.shape} and {tg.shape}"
        )
    if sp.shape != (ta.size - 1,):
        raise ValueError(f"TimeBSR needs R - 1 = {ta.size - 1} splits; got shape {sp.shape}")
    if tp.shape != () or not np.isfinite(tp) or tp <= 0:
        raise ValueError(f"TimeBSR.t_per = {t_per!r}; allowed: a number > 0 (s)")
    span, name = (tp / 2, "t_per / 2") if mirrored else (tp, "t_per")
    for r, v in enumerate(sp):
        if not (np.isfinite(v) and 0 <= v <= span):
            raise ValueError(f"split {r} is {v:g}; allowed: 0 <= split <= {name} = {span:g}")
    if np.any(np.diff(sp) < 0):
        raise ValueError(f"TimeBSR.splits = {sp.tolist()}; allowed: ascending")
    for r, v in enumerate(ta):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"rule {r} has tau {v:g}; allowed: a number > 0 (s)")
    if not np.all(np.isfinite(tg)):
        raise ValueError("TimeBSR.targets must be finite")


def joint_bounds(ranges):
    """The joint ranges `((lo, hi), ...)` as two arrays `(lo, hi)`."""
    r = np.array(ranges, dtype=float).reshape(-1, 2)
    return jnp.asarray(r[:, 0]), jnp.asarray(r[:, 1])


def rule_response(ranges, tau_min, tau_max, u_targets, u_tau):
    """A BSR rule's response from uniform draws (the second paper's Table 2): target angles
    uniform in their ranges, `tau` log-uniform in `[tau_min, tau_max]`."""
    lo, hi = joint_bounds(ranges)
    log_lo, log_hi = math.log(tau_min), math.log(tau_max)
    return lo + (hi - lo) * u_targets, jnp.exp(log_lo + (log_hi - log_lo) * u_tau)


class TimeBSRSpace(AbstractControllerSpace[TimeBSR]):
    """The family of `TimeBSR` controllers for one figure, with the second paper's sampling
    (Table 2) and mutation (section 2.1.3).

    **Sampling:** split points uniform in `[0, t_per]` (sorted); each rule's targets uniform in
    the free joints' ranges; each `tau` log-uniform in `[tau_min, tau_max]` (the paper: `2 dt`
    and `T / 4`).

    **Mutation** (`perturb`) changes one rule, chosen uniformly: with probability
    `reinit_probability` it is reinitialised from scratch (new targets, tau and start time),
    otherwise it creeps: every one of its parameters moves by a uniform step of at most
    `creep` times its range (tau on a log scale), clipped to the range. A rule's start time is
    the split before its segment (rule 0 always starts the period); a rule whose start moves
    past another's changes places with it, so rules 1..R-1 stay in the order of their starts
    and no other rule's start or response changes. The paper gives no
    probability for the two; the default 1/3 reinitialise, 2/3 creep is its Figure 5's mix.

    **Mirrored gaits:** `mirror=True` draws and mutates mirrored controllers (see
    `TimeBSR`): the split points lie in `[0, t_per / 2]` and every controller carries the
    figure's `Figure.mirror` map.

    **Arguments:** `figure`; `num_rules` R (the paper: 4); `t_per` (s); `tau_min`, `tau_max`
    (s); `creep`, `reinit_probability`; `mirror`.

    **Raises:** `ValueError` for a bad argument, or `mirror=True` for a figure without a
    mirror image (planar, or not left-right symmetric).
    """

    num_free: int = eqx.field(static=True)
    ranges: tuple[tuple[float, float], ...] = eqx.field(static=True)
    num_rules: int = eqx.field(static=True)
    t_per: float = eqx.field(static=True)
    tau_min: float = eqx.field(static=True)
    tau_max: float = eqx.field(static=True)
    creep: float = eqx.field(static=True)
    reinit_probability: float = eqx.field(static=True)
    mirror: tuple[tuple[int, ...], tuple[float, ...]] | None = eqx.field(static=True)

    def __init__(
        self,
        figure: Figure,
        num_rules: int = 4,
        t_per: float = 1.0,
        tau_min: float = 0.02,
        tau_max: float = 0.5,
        creep: float = 0.1,
        reinit_probability: float = 1 / 3,
        mirror: bool = False,
    ):
        if not isinstance(figure, Figure):
            raise TypeError(f"TimeBSRSpace needs a Figure; got {type(figure).__name__}")
        if isinstance(num_rules, bool) or not isinstance(num_rules, int) or num_rules < 1:
            raise ValueError(f"TimeBSRSpace.num_rules = {num_rules!r}; allowed: an integer >= 1")
        for name, v in (("t_per", t_per), ("tau_min", tau_min), ("tau_max", tau_max)):
            if (
                isinstance(v, bool)
                or not isinstance(v, int | float)
                or not (math.isfinite(v) and v > 0)
            ):
                raise ValueError(f"TimeBSRSpace.{name} = {v!r}; allowed: a number > 0 (s)")
        if tau_min > tau_max:
            raise ValueError(
                f"TimeBSRSpace.tau_min = {tau_min!r} > tau_max = {tau_max!r}; allowed: "
                "tau_min <= tau_max"
            )
        if not (isinstance(creep, int | float) and 0 < creep <= 1):
            raise ValueError(f"TimeBSRSpace.creep = {creep!r}; allowed: 0 < creep <= 1")
        if not (isinstance(reinit_probability, int | float) and 0 <= reinit_probability <= 1):
            raise ValueError(
                f"TimeBSRSpace.reinit_probability = {reinit_probability!r}; allowed: 0..1"
            )
        self.num_free = figure.num_free
        self.ranges = tuple((float(lo), float(hi)) for lo, hi in figure.ranges)
        self.num_rules = int(num_rules)
        self.t_per = float(t_per)
        self.tau_min = float(tau_min)
        self.tau_max = float(tau_max)
        self.creep = float(creep)
        self.reinit_probability = float(reinit_probability)
        self.mirror = figure_mirror(figure, mirror, "TimeBSRSpace", "mirror")

    @property
    def family(self) -> str:
        return "time_bsr"

    @property
    def span(self) -> float:
        """The stretch of each period the rules share: `t_per`, or `t_per / 2` mirrored."""
        return self.t_per / 2 if self.mirror is not None else self.t_per

    def _lo_hi(self):
        return joint_bounds(self.ranges)

    def _rule(self, u_targets, u_tau):
        return rule_response(self.ranges, self.tau_min, self.tau_max, u_targets, u_tau)

    def sample(self, *, key: PRNGKeyArray) -> TimeBSR:
        r, f = self.num_rules, self.num_free
        u = jr.uniform(key, (r - 1 + r * f + r,))
        splits = jnp.sort(u[: r - 1] * self.span)
        targets, taus = self._rule(u[r - 1 : r - 1 + r * f].reshape(r, f), u[r - 1 + r * f :])
        return TimeBSR(splits, targets, taus, self.t_per, self.mirror)

    def perturb(self, controller: TimeBSR, *, key: PRNGKeyArray, motion=None) -> TimeBSR:
        del motion
        r, f = self.num_rules, self.num_free
        u = jr.uniform(key, (3 + f + 1,))
        rule = jnp.minimum((u[0] * r).astype(jnp.int32), r - 1)
        reinit = u[1] < self.reinit_probability
        u_start, u_targets, u_tau = u[2], u[3 : 3 + f], u[3 + f]
        lo, hi = self._lo_hi()
        # Reinitialise: fresh values. Creep: a step of at most `creep` of the range.
        new_targets, new_tau = self._rule(u_targets, u_tau)
        old_targets = controller.targets[rule]
        old_tau = controller.taus[rule]
        step = 2.0 * u_targets - 1.0
        crept_targets = jnp.clip(old_targets + self.creep * (hi - lo) * step, lo, hi)
        log_span = math.log(self.tau_max) - math.log(self.tau_min)
        crept_tau = jnp.clip(
            old_tau * jnp.exp(self.creep * log_span * (2.0 * u_tau - 1.0)),
            self.tau_min,
            self.tau_max,
        )
        targets = controller.targets.at[rule].set(jnp.where(reinit, new_targets, crept_targets))
        taus = controller.taus.at[rule].set(jnp.where(reinit, new_tau, crept_tau))
        splits = controller.splits
        if r > 1:
            # Rule `rule` starts at split `rule - 1` (rule 0 always starts the period).
            index = jnp.maximum(rule - 1, 0)
            old = splits[index]
            moved = jnp.where(
                reinit,
                u_start * self.span,
                jnp.clip(old + self.creep * self.span * (2.0 * u_start - 1.0), 0.0, self.span),
            )
            starts = jnp.where(rule > 0, splits.at[index].set(moved), splits)
            # Rules 1..R-1 are kept in the order of their starts and keep their own start:
            # sorting the splits alone would hand a start that moved past a neighbour's to
            # that neighbour, changing two rules.
            order = jnp.argsort(starts, stable=True)
            splits = starts[order]
            targets = targets.at[1:].set(targets[1:][order])
            taus = taus.at[1:].set(taus[1:][order])
        return TimeBSR(splits, targets, taus, controller.t_per, self.mirror)

    def trainable(self, controller: TimeBSR):
        """Split points, targets and time constants are refined by gradients; the period
        (fixed by the family) is not."""
        spec = jax.tree_util.tree_map(lambda _: False, controller)
        return eqx.tree_at(lambda c: (c.splits, c.targets, c.taus), spec, (True, True, True))

    def project(self, controller: TimeBSR) -> TimeBSR:
        """Clip into the family's bounds (splits kept ascending)."""
        lo, hi = self._lo_hi()
        return eqx.tree_at(
            lambda c: (c.splits, c.targets, c.taus),
            controller,
            (
                jnp.sort(jnp.clip(controller.splits, 0.0, self.span)),
                jnp.clip(controller.targets, lo, hi),
                jnp.clip(controller.taus, self.tau_min, self.tau_max),
            ),
        )
