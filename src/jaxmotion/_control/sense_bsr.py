"""Sense-based banked stimulus-response (BSR) controllers of the second paper (section 2.1.2,
Figure 2) and their search space (Table 2; creep and reinitialisation with the relevance
heuristic, sections 2.1.3 and 4.2)."""

import math
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .._body.figure import Figure
from .base import AbstractController, AbstractControllerSpace, ControllerState
from .time_bsr import figure_mirror, joint_bounds, mirrored_pose, rule_response

SIDE_MIN, SIDE_MAX = 0.4, 4.0
"""Table 2's range of a hyper-rectangle's side length `2 / lambda` (log-uniform)."""
CENTRE_MIN, CENTRE_MAX = -0.5, 1.5
"""Table 2's range of a hyper-rectangle's centre coordinate `mu` (uniform)."""
LAMBDA_MIN = 2.0 / SIDE_MAX
"""The smallest allowed `lambda` (the largest side), the weight's reference."""


class BSRState(eqx.Module):
    """The discrete state of a `SenseBSR` controller (its `ControllerState.discrete`).

    - `active`: the active rule's index (with `blend > 0`: `weights`, each rule's share).
    - `filtered`: the low-pass-filtered senses the rules score (the senses themselves when
        the filter is off).
    - `t`: the time of the last tick (the filter's step is the time since).
    - `first`: true until the first tick (which keeps rule 0, as the paper's Figure 2 acts
        before it first senses).
    """

    active: Int[Array, ""] | Float[Array, " R"]
    filtered: Float[Array, " num_senses"]
    t: Float[Array, ""]
    first: Bool[Array, ""]


class SenseBSR(AbstractController):
    """A sense-based BSR controller (second paper, section 2.1.2): R stimulus-response rules,
    each a hyper-rectangle over the body's sense variables (the stimulus) and a target pose
    with a time constant (the response).

    Rule `r` is the hyper-rectangle of centre `centres[r]` (`mu`) and side lengths
    `sides[r]` (`2 / lambda`) over the senses `S` (each normalised to [0, 1]; see the
    figure's `sense_names`). At every control tick each rule scores

        W_r (1 - max_j [lambda_rj (S_j - mu_rj)]^2),   W_r = sum_j log(lambda_rj / lambda_min)

    (`lambda_min = 2 / 4`, the largest side): positive exactly inside its rectangle, and
    higher for smaller, more specific rectangles. The rule with the highest positive score
    becomes active (the lowest index on ties); if no rule scores positive, the previous rule
    stays active. Rule 0 is active over the first control period (the paper's Figure 2 sets
    `i_active = 1` and acts before it first senses). Every free joint angle then moves
    toward the active rule's `targets` with its time constant `taus`
    (`tau^2 th'' + 2 tau th' + th = th0`).

    The senses may first pass a first-order low-pass filter of time constant `filter_time`
    (the paper's section 4.2, "to remove noise and high-frequency variation"): at a tick
    `filtered += (1 - exp(-h / filter_time)) (senses - filtered)`, `h` the time since the
    last tick, starting from the senses of the starting state; `filter_time = 0` is no
    filter.

    **Mirror twins** (`mirror`, not in the paper): a walk is a half-stride and its mirror
    image. With `mirror` set (the figure's `Figure.sense_mirror`, a map of the senses to
    those of the motion's left-right mirror image), every rule also acts as its mirror
    twin: rule `R + r` scores the mirrored senses against rule `r`'s rectangle and poses
    rule `r`'s targets mirrored (angle `i` toward `sign[i] * targets[r, partner[i]]`, the
    pose map that `Figure.mirror` gives, read off the angle senses' part of the map), with
    rule `r`'s tau. The choice among the 2R scores is the one above (ties keep the lower
    index, so a rule before its twin). Where rule `r` acts in a state, its twin acts in the
    mirror image of that state, so a controller that steps with the left leg steps the same
    way with the right; the parameter count is unchanged.

    **Fields:** `centres`, `sides` `(R, num_senses)`; `targets` `(R, num_free)` (radians);
    `taus` `(R,)` (s); `filter_time` (s, static); `blend` (static) 0 for the paper's hard
    choice, or the temperature (in score units) of a soft choice for gradients (see
    `smoothed`); `mirror` (static) `None` or the sense map `(source, flip)`.

    In 2D the parameter count is `(5 N + 4) R` for `N` rods with every joint free (the
    paper's count): `2 (2 N + 2)` stimulus numbers, `N - 1` target angles and one tau per
    rule (`num_parameters`).
    """

    centres: Float[Array, "R num_senses"]
    sides: Float[Array, "R num_senses"]
    targets: Float[Array, "R num_free"]
    taus: Float[Array, " R"]
    filter_time: float = eqx.field(static=True)
    blend: float = eqx.field(static=True)
    mirror: tuple[tuple[int, ...], tuple[bool, ...]] | None = eqx.field(static=True)

    supports_batch_last: ClassVar[bool] = True
    reads_senses: ClassVar[bool] = True

    def __init__(
        self,
        centres: Float[ArrayLike, "R num_senses"],
        sides: Float[ArrayLike, "R num_senses"],
        targets: Float[ArrayLike, "R num_free"],
        taus: Float[ArrayLike, " R"],
        filter_time: float = 0.0,
        blend: float = 0.0,
        mirror=None,
    ):
        for name, value in (("filter_time", filter_time), ("blend", blend)):
            if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
                raise ValueError(f"SenseBSR.{name} = {value!r}; allowed: a number >= 0")
        if not any(isinstance(x, jax.core.Tracer) for x in (centres, sides, targets, taus)):
            _check(centres, sides, targets, taus)
        self.centres = jnp.asarray(centres, dtype=float)
        self.sides = jnp.asarray(sides, dtype=float)
        self.targets = jnp.asarray(targets, dtype=float)
        self.taus = jnp.asarray(taus, dtype=float)
        self.filter_time = float(filter_time)
        self.blend = float(blend)
        self.mirror = _sense_mirror_map(mirror, np.shape(centres)[-1], np.shape(targets)[-1])

    @property
    def num_rules(self) -> int:
        return self.taus.shape[0]

    @property
    def num_senses(self) -> int:
        return self.centres.shape[1]

    @property
    def num_choices(self) -> int:
        """The rules the choice is made among: R, or 2R with mirror twins (`R + r` is rule
        `r`'s twin)."""
        return self.num_rules * (1 if self.mirror is None else 2)

    @property
    def num_parameters(self) -> int:
        """Free parameters: `(2 num_senses + num_free + 1) R`."""
        return int(self.centres.size + self.sides.size + self.targets.size + self.taus.size)

    def prepare(self, body: Figure):
        """Each rule's `lambda` and weight `W` (per controller and rule, computed once)."""
        if not isinstance(body, Figure):
            raise TypeError(f"SenseBSR controls articulated figures; got a {type(body).__name__}")
        if self.targets.shape[-1] != body.num_free:
            raise ValueError(
                f"SenseBSR has targets for {self.targets.shape[-1]} joint angles but figure "
                f"{body.name!r} has {body.num_free} free angles"
            )
        if self.centres.shape[-1] != body.num_senses:
            raise ValueError(
                f"SenseBSR has rectangles over {self.centres.shape[-1]} senses but figure "
                f"{body.name!r} has {body.num_senses} ({', '.join(body.sense_names)})"
            )
        if self.mirror is not None and self.mirror != body.sense_mirror:
            raise ValueError(
                f"SenseBSR.mirror = {self.mirror!r} is not figure {body.name!r}'s sense map "
                f"(Figure.sense_mirror = {body.sense_mirror!r})"
            )
        lam = 2.0 / self.sides
        # W as explicit adds over the senses (elementwise over any batch: the same rounding
        # whatever the batch width).
        logs = jnp.log(lam / LAMBDA_MIN)
        weight = logs[:, 0]
        for j in range(1, logs.shape[1]):
            weight = weight + logs[:, j]
        return lam, weight

    def scores(self, senses, plan) -> Float[Array, " choices"]:
        """Every rule's score `W (1 - max_j [lambda_j (S_j - mu_j)]^2)` for the senses `S`,
        then, with `mirror`, every twin's (the rules' scores of the mirrored senses): `R` or
        `2R` scores (works on a batch-last stack too: `(choices, *batch)`)."""
        lam, weight = plan
        d = lam * (senses[None] - self.centres)
        own = weight * (1.0 - jnp.max(d * d, axis=1))
        if self.mirror is None:
            return own
        d = lam * (self.mirrored_senses(senses)[None] - self.centres)
        return jnp.concatenate([own, weight * (1.0 - jnp.max(d * d, axis=1))])

    def mirrored_senses(self, senses):
        """The senses of the mirror image of the state that reads `senses` (`mirror`'s map;
        leading axis the senses, any batch after it)."""
        source, flip = self.mirror
        picked = senses[np.asarray(source)]
        flip = np.asarray(flip).reshape((-1,) + (1,) * (jnp.ndim(senses) - 1))
        return jnp.where(flip, 1.0 - picked, picked)

    def _mirror_pose(self, target):
        return mirrored_pose(target, *_pose_map(self.mirror, self.num_senses, target.shape[0]))

    def init(self, senses, plan) -> ControllerState:
        """Rule 0 active; the filter starts at the starting state's senses."""
        del plan
        shape = jnp.shape(self.taus)[1:]  # () for one controller, (batch,) batch-last
        if self.blend > 0:
            active = jnp.zeros((self.num_choices, *shape), dtype=float).at[0].set(1.0)
        else:
            active = jnp.zeros(shape, dtype=jnp.int32)
        zero = jnp.zeros(shape, dtype=float)
        return ControllerState(BSRState(active, senses, zero, jnp.ones(shape, dtype=bool)))

    def _filtered(self, state: BSRState, t, senses):
        if self.filter_time == 0:
            return senses
        gain = 1.0 - jnp.exp(-(t - state.t) / self.filter_time)
        return state.filtered + gain * (senses - state.filtered)

    def update(self, t, state: ControllerState, senses, plan) -> ControllerState:
        """The tick: filter the senses, score the rules, keep the previous rule if none
        scores positive (or at the first tick)."""
        bsr = state.discrete
        filtered = self._filtered(bsr, t, senses)
        scores = self.scores(filtered, plan)
        time = jnp.broadcast_to(t, jnp.shape(bsr.t)).astype(bsr.t.dtype)
        done = jnp.zeros_like(bsr.first)
        if self.blend > 0:
            soft = self._soft(scores, bsr.active)
            active = jnp.where(bsr.first, bsr.active, soft)
            return ControllerState(BSRState(active, filtered, time, done))
        # The highest positive score by a chain of compares (elementwise over a batch-last
        # stack); ties keep the lower index; no positive score keeps the previous rule.
        best = scores[0]
        index = jnp.zeros(jnp.shape(best), dtype=jnp.int32)
        for r in range(1, self.num_choices):
            higher = scores[r] > best
            best = jnp.where(higher, scores[r], best)
            index = jnp.where(higher, r, index)
        active = jnp.where((best > 0) & ~bsr.first, index, bsr.active)
        return ControllerState(BSRState(active, filtered, time, done))

    def _soft(self, scores, previous):
        # Softmax of the scores at temperature `blend`, blended with the previous weights by
        # the soft "some rule scores positive" sigmoid(max score / blend): as blend -> 0,
        # the hard choice with hysteresis.
        top = jnp.max(scores, axis=0)
        weights = jnp.exp((scores - top) / self.blend)
        weights = weights / jnp.sum(weights, axis=0)
        positive = jax.nn.sigmoid(top / self.blend)
        return positive * weights + (1.0 - positive) * previous

    def actuation(self, t, state: ControllerState, plan):
        """The active rule's target pose and time constant (held until the next tick); a
        twin's are its rule's, the pose mirrored."""
        del t, plan
        active = state.discrete.active
        r_all = self.num_rules
        if self.blend > 0:
            w = active
            target = sum(w[r] * self.targets[r] for r in range(1, r_all))
            target = target + w[0] * self.targets[0]
            tau = sum(w[r] * self.taus[r] for r in range(1, r_all)) + w[0] * self.taus[0]
            if self.mirror is not None:
                # The twins' blend of the rules' poses, mirrored once (the mirror is a
                # signed permutation: exact, and linear).
                twins = sum(w[r_all + r] * self.targets[r] for r in range(r_all))
                target = target + self._mirror_pose(twins)
                tau = tau + sum(w[r_all + r] * self.taus[r] for r in range(r_all))
            return target, tau
        # A chain of selects (elementwise for a batch-last stack) rather than an index.
        rule = active if self.mirror is None else jnp.where(active >= r_all, active - r_all, active)
        target, tau = self.targets[0], self.taus[0]
        for r in range(1, r_all):
            on = rule == r
            target = jnp.where(on, self.targets[r], target)
            tau = jnp.where(on, self.taus[r], tau)
        if self.mirror is not None:
            target = jnp.where(active >= r_all, self._mirror_pose(target), target)
        return target, tau

    def perceive(self, t, state: ControllerState, senses, plan):
        """The senses the rules score at a tick at `t`: filtered, or the senses themselves
        without a filter."""
        del plan
        return self._filtered(state.discrete, t, senses)

    def active_rules(self, perceived: Float[Array, "num_samples num_senses"]):
        """The rule that the hard choice makes at each of a sequence of perceived senses
        (e.g. `Trajectory.senses`), starting from rule 0: which rules a motion activates
        (with `mirror`, `R + r` is rule `r`'s twin)."""
        plan = self.prepare_rules()

        def step(active, s):
            scores = self.scores(s, plan)
            best = jnp.argmax(scores).astype(active.dtype)
            active = jnp.where(scores[best] > 0, best, active)
            return active, active

        _, out = jax.lax.scan(step, jnp.asarray(0, dtype=jnp.int32), perceived)
        return out

    def prepare_rules(self):
        """`(lambda, W)` of every rule (what `prepare` computes, without the body check)."""
        lam = 2.0 / self.sides
        return lam, jnp.sum(jnp.log(lam / LAMBDA_MIN), axis=-1)

    def smoothed(self, width: float) -> "SenseBSR":
        """This controller with a soft rule choice at temperature `width` (score units; see
        `_soft`); `width=0` is the paper's hard switch."""
        return SenseBSR(
            self.centres, self.sides, self.targets, self.taus, self.filter_time, width, self.mirror
        )


def _sense_mirror_map(mirror, num_senses: int, num_free: int):
    """`mirror` as a `(source, flip)` pair of tuples (lists, as JSON gives them, are
    accepted), checked against the sense count."""
    if mirror is None:
        return None
    allowed = (
        f"None or (source, flip): a permutation of the {num_senses} senses and a bool for "
        "each, its own inverse (a figure's Figure.sense_mirror)"
    )
    try:
        source, flip = mirror
        source = tuple(int(i) for i in source)
        if not all(isinstance(b, bool | np.bool_) for b in flip):
            raise TypeError
        flip = tuple(bool(b) for b in flip)
    except (TypeError, ValueError):
        raise ValueError(f"SenseBSR.mirror = {mirror!r}; allowed: {allowed}") from None
    ok = (
        len(source) == num_senses
        and len(flip) == num_senses
        and sorted(source) == list(range(num_senses))
        and all(source[source[j]] == j and flip[source[j]] == flip[j] for j in range(num_senses))
    )
    off = num_senses - num_free
    if ok:
        ok = all(off <= source[j] for j in range(off, num_senses))
    if not ok:
        raise ValueError(f"SenseBSR.mirror = {mirror!r}; allowed: {allowed}")
    return source, flip


def _pose_map(mirror, num_senses: int, num_free: int):
    """The pose map `(partner, sign)` (`Figure.mirror`'s) read off the angle senses, the
    last `num_free`, of the sense map."""
    source, flip = mirror
    off = num_senses - num_free
    partner = tuple(source[off + k] - off for k in range(num_free))
    sign = tuple(-1.0 if flip[off + k] else 1.0 for k in range(num_free))
    return partner, sign


def _check(centres, sides, targets, taus) -> None:
    c = np.asarray(centres, dtype=float)
    s = np.asarray(sides, dtype=float)
    tg = np.asarray(targets, dtype=float)
    ta = np.asarray(taus, dtype=float)
    if ta.ndim != 1 or ta.size < 1:
        raise ValueError(f"SenseBSR needs taus of shape (R,), R >= 1; got shape {ta.shape}")
    r = ta.size
    if c.ndim != 2 or c.shape[0] != r or s.shape != c.shape:
        raise ValueError(
            f"SenseBSR needs centres and sides of shape (R, num_senses) with R = {r}; got "
            f"shapes {c.shape} and {s.shape}"
        )
    if tg.ndim != 2 or tg.shape[0] != r:
        raise ValueError(f"SenseBSR needs targets of shape (R, num_free), R = {r}; got {tg.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("SenseBSR.centres must be finite")
    bad = np.argwhere(~(np.isfinite(s) & (s > 0)))
    if bad.size:
        i, j = bad[0]
        raise ValueError(f"rule {i} has side {s[i, j]:g} on sense {j}; allowed: a number > 0")
    for i, v in enumerate(ta):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"rule {i} has tau {v:g}; allowed: a number > 0 (s)")
    if not np.all(np.isfinite(tg)):
        raise ValueError("SenseBSR.targets must be finite")


Relevance = Literal["corner", "contain", "none"]
_NUDGE = 0.05
"""How far inside its rectangle the chosen point of the parent's motion lies, as a share of
the half side (the point at an exact corner would score exactly 0, never positive)."""


class SenseBSRSpace(AbstractControllerSpace[SenseBSR]):
    """The family of `SenseBSR` controllers for one figure, with the second paper's sampling
    (Table 2) and mutation (sections 2.1.3 and 4.2).

    **Sampling** (Table 2): centres uniform in `[-0.5, 1.5]`, sides log-uniform in
    `[0.4, 4]`, target angles uniform in the free joints' ranges, `tau` log-uniform in
    `[tau_min, tau_max]` (the paper: `2 dt` and `T / 4`).

    **Mutation** (`perturb`) changes one rule, chosen uniformly: with probability
    `reinit_probability` it is reinitialised, otherwise it creeps (every parameter of the
    rule moves by a uniform step of at most `creep` times its range, sides and tau on a log
    scale, clipped to the range). A reinitialised rule gets a fresh response, and a fresh
    stimulus placed by the *relevance heuristic* when the parent's perceived senses along
    its motion (`motion`, `(num_samples, num_senses)`) are given:

    - `"corner"` (2D, section 2.1.3): a corner of the new rectangle lies on the parent's
        sense trajectory: at a sample `p` drawn uniformly, the rectangle extends from `p`
        toward where the trajectory goes next (the sign of the change to the next sample in
        each sense; a random side where it does not change), with `p` nudged `5%` of the
        half sides inside so that it scores positive;
    - `"contain"` (3D, section 4.2): the rectangle contains `p`, placed uniformly at random
        within it (at most `95%` of the half sides from the centre);
    - `"none"`, or no motion given: drawn from Table 2 like a new controller's.

    The default is `"corner"` for planar figures and `"contain"` for 3D ones. The paper gives
    no probability for reinitialising against creeping; the default 1/3 is its Figure 5's
    mix (as for `TimeBSRSpace`).

    **Mirror twins:** `mirror=True` draws and mutates controllers whose rules act also as
    their mirror twins (see `SenseBSR`), with the figure's `Figure.sense_mirror` map.

    **Arguments:** `figure`; `num_rules` R (the paper: 10); `tau_min`, `tau_max` (s);
    `filter_time` (s, 0: no filter); `creep`; `reinit_probability`; `relevance`; `mirror`.

    **Raises:** `ValueError` for a bad argument, or `mirror=True` for a figure without a
    mirror image (planar, or not left-right symmetric).
    """

    num_free: int = eqx.field(static=True)
    num_senses: int = eqx.field(static=True)
    ranges: tuple[tuple[float, float], ...] = eqx.field(static=True)
    num_rules: int = eqx.field(static=True)
    tau_min: float = eqx.field(static=True)
    tau_max: float = eqx.field(static=True)
    filter_time: float = eqx.field(static=True)
    creep: float = eqx.field(static=True)
    reinit_probability: float = eqx.field(static=True)
    relevance: str = eqx.field(static=True)
    mirror: tuple[tuple[int, ...], tuple[bool, ...]] | None = eqx.field(static=True)

    uses_motion: ClassVar[bool] = True

    def __init__(
        self,
        figure: Figure,
        num_rules: int = 10,
        tau_min: float = 0.02,
        tau_max: float = 0.5,
        filter_time: float = 0.0,
        creep: float = 0.1,
        reinit_probability: float = 1 / 3,
        relevance: Relevance | None = None,
        mirror: bool = False,
    ):
        if not isinstance(figure, Figure):
            raise TypeError(f"SenseBSRSpace needs a Figure; got {type(figure).__name__}")
        if isinstance(num_rules, bool) or not isinstance(num_rules, int) or num_rules < 1:
            raise ValueError(f"SenseBSRSpace.num_rules = {num_rules!r}; allowed: an integer >= 1")
        for name, v in (("tau_min", tau_min), ("tau_max", tau_max)):
            if (
                isinstance(v, bool)
                or not isinstance(v, int | float)
                or not (math.isfinite(v) and v > 0)
            ):
                raise ValueError(f"SenseBSRSpace.{name} = {v!r}; allowed: a number > 0 (s)")
        if tau_min > tau_max:
            raise ValueError(
                f"SenseBSRSpace.tau_min = {tau_min!r} > tau_max = {tau_max!r}; allowed: "
                "tau_min <= tau_max"
            )
        if (
            isinstance(filter_time, bool)
            or not isinstance(filter_time, int | float)
            or not (math.isfinite(filter_time) and filter_time >= 0)
        ):
            raise ValueError(
                f"SenseBSRSpace.filter_time = {filter_time!r}; allowed: a number >= 0 (s; 0 "
                "is no filter)"
            )
        if not (isinstance(creep, int | float) and 0 < creep <= 1):
            raise ValueError(f"SenseBSRSpace.creep = {creep!r}; allowed: 0 < creep <= 1")
        if not (isinstance(reinit_probability, int | float) and 0 <= reinit_probability <= 1):
            raise ValueError(
                f"SenseBSRSpace.reinit_probability = {reinit_probability!r}; allowed: 0..1"
            )
        if relevance is None:
            relevance = "corner" if figure.planar else "contain"
        if relevance not in ("corner", "contain", "none"):
            raise ValueError(
                f"SenseBSRSpace.relevance = {relevance!r}; allowed: 'corner', 'contain' or 'none'"
            )
        self.num_free = figure.num_free
        self.num_senses = figure.num_senses
        self.ranges = tuple((float(lo), float(hi)) for lo, hi in figure.ranges)
        self.num_rules = int(num_rules)
        self.tau_min = float(tau_min)
        self.tau_max = float(tau_max)
        self.filter_time = float(filter_time)
        self.creep = float(creep)
        self.reinit_probability = float(reinit_probability)
        self.relevance = str(relevance)
        self.mirror = figure_mirror(figure, mirror, "SenseBSRSpace", "sense_mirror")

    @property
    def family(self) -> str:
        return "sense_bsr"

    def _lo_hi(self):
        return joint_bounds(self.ranges)

    def _response(self, u_targets, u_tau):
        return rule_response(self.ranges, self.tau_min, self.tau_max, u_targets, u_tau)

    @staticmethod
    def _sides(u):
        return jnp.exp(math.log(SIDE_MIN) + (math.log(SIDE_MAX) - math.log(SIDE_MIN)) * u)

    @staticmethod
    def _centres(u):
        return CENTRE_MIN + (CENTRE_MAX - CENTRE_MIN) * u

    def sample(self, *, key: PRNGKeyArray) -> SenseBSR:
        r, f, v = self.num_rules, self.num_free, self.num_senses
        u = jr.uniform(key, (r, 2 * v + f + 1))
        targets, taus = self._response(u[:, 2 * v : 2 * v + f], u[:, -1])
        return SenseBSR(
            self._centres(u[:, :v]),
            self._sides(u[:, v : 2 * v]),
            targets,
            taus,
            filter_time=self.filter_time,
            mirror=self.mirror,
        )

    def _stimulus(self, u_centre, u_side, u_pick, u_sign, motion):
        """A reinitialised rule's rectangle: Table 2, or placed by the relevance heuristic on
        `motion`."""
        sides = self._sides(u_side)
        if motion is None or self.relevance == "none":
            return self._centres(u_centre), sides
        motion = jnp.asarray(motion)
        samples = motion.shape[0]
        # A sample of the motion (finite ones only: a run that blew up records NaN).
        ok = jnp.all(jnp.isfinite(motion), axis=-1)
        count = jnp.maximum(jnp.sum(ok), 1)
        rank = jnp.minimum(jnp.floor(u_pick * count).astype(jnp.int32), count - 1)
        index = jnp.argmax(jnp.cumsum(ok) > rank)
        point = jnp.where(jnp.isfinite(motion[index]), motion[index], 0.5)
        half = 0.5 * sides * (1.0 - _NUDGE)
        if self.relevance == "contain":
            return point + half * (2.0 * u_centre - 1.0), sides
        later = motion[jnp.minimum(index + 1, samples - 1)]
        step = jnp.where(jnp.isfinite(later), later, point) - point
        random_sign = jnp.where(u_sign < 0.5, -1.0, 1.0)
        sign = jnp.where(step > 0, 1.0, jnp.where(step < 0, -1.0, random_sign))
        return point + sign * half, sides

    def perturb(self, controller: SenseBSR, *, key: PRNGKeyArray, motion=None) -> SenseBSR:
        return self._mutate(controller, key, motion, reinit=None)

    def reinitialise(self, controller: SenseBSR, *, key: PRNGKeyArray, motion=None) -> SenseBSR:
        """Reinitialise one rule (chosen uniformly) with the relevance heuristic: the
        mutation that enriches an initial population (section 4.2)."""
        return self._mutate(controller, key, motion, reinit=True)

    def _mutate(self, controller: SenseBSR, key, motion, reinit):
        r, f, v = self.num_rules, self.num_free, self.num_senses
        u = jr.uniform(key, (4 + 4 * v + f + 1,))
        rule = jnp.minimum((u[0] * r).astype(jnp.int32), r - 1)
        if reinit is None:
            reinit = u[1] < self.reinit_probability
        u_pick = u[2]
        u_centre, u_side, u_sign = u[4 : 4 + v], u[4 + v : 4 + 2 * v], u[4 + 2 * v : 4 + 3 * v]
        u_creep = u[4 + 3 * v : 4 + 4 * v]
        u_targets, u_tau = u[4 + 4 * v : 4 + 4 * v + f], u[-1]
        # Reinitialise: fresh values.
        new_centres, new_sides = self._stimulus(u_centre, u_side, u_pick, u_sign, motion)
        new_targets, new_tau = self._response(u_targets, u_tau)
        # Creep: a step of at most `creep` of the range (sides and tau on a log scale).
        lo, hi = self._lo_hi()
        old_centres, old_sides = controller.centres[rule], controller.sides[rule]
        crept_centres = jnp.clip(
            old_centres + self.creep * (CENTRE_MAX - CENTRE_MIN) * (2.0 * u_centre - 1.0),
            CENTRE_MIN,
            CENTRE_MAX,
        )
        side_span = math.log(SIDE_MAX / SIDE_MIN)
        crept_sides = jnp.clip(
            old_sides * jnp.exp(self.creep * side_span * (2.0 * u_creep - 1.0)),
            SIDE_MIN,
            SIDE_MAX,
        )
        crept_targets = jnp.clip(
            controller.targets[rule] + self.creep * (hi - lo) * (2.0 * u_targets - 1.0), lo, hi
        )
        log_span = math.log(self.tau_max / self.tau_min)
        crept_tau = jnp.clip(
            controller.taus[rule] * jnp.exp(self.creep * log_span * (2.0 * u_tau - 1.0)),
            self.tau_min,
            self.tau_max,
        )
        pick = lambda new, old: jnp.where(reinit, new, old)
        return SenseBSR(
            controller.centres.at[rule].set(pick(new_centres, crept_centres)),
            controller.sides.at[rule].set(pick(new_sides, crept_sides)),
            controller.targets.at[rule].set(pick(new_targets, crept_targets)),
            controller.taus.at[rule].set(pick(new_tau, crept_tau)),
            filter_time=controller.filter_time,
            blend=controller.blend,
            mirror=controller.mirror,
        )

    def trainable(self, controller: SenseBSR):
        """Centres, sides, targets and time constants are refined by gradients."""
        spec = jax.tree_util.tree_map(lambda _: False, controller)
        return eqx.tree_at(
            lambda c: (c.centres, c.sides, c.targets, c.taus), spec, (True, True, True, True)
        )

    def project(self, controller: SenseBSR) -> SenseBSR:
        """Clip into the family's bounds."""
        lo, hi = self._lo_hi()
        return eqx.tree_at(
            lambda c: (c.centres, c.sides, c.targets, c.taus),
            controller,
            (
                jnp.clip(controller.centres, CENTRE_MIN, CENTRE_MAX),
                jnp.clip(controller.sides, SIDE_MIN, SIDE_MAX),
                jnp.clip(controller.targets, lo, hi),
                jnp.clip(controller.taus, self.tau_min, self.tau_max),
            ),
        )
