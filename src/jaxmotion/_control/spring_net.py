"""Spring-net controllers of the third paper (van de Panne's student project, "Spring Net
Controllers for Articulated Figures") and their family: sampling and the paper's four kinds
of mutation.

**The model** (the paper's equations did not survive in its text; this is the model its
words describe, stated here):

- `n` point masses `m_i` on a line (the net's axis) at positions `x_i`, starting at rest at
  the initial positions `x_i(0)`;
- a spring between *every pair* of masses (the paper's `k_ij`, "indices of point masses
  connected by the spring", with no topology given: all pairs is the general net, and a
  chain is the case with the other constants near zero), of *zero rest length*: the force
  on mass `i` from the spring to `j` is `k_ij (x_j - x_i)`. The paper says the masses move
  "as long as the initial positions are not all identical and the spring constants are not
  all zero", which is exactly the zero-rest-length law (springs with rest lengths could sit
  at rest with distinct positions);
- no damping by default (the paper's nets oscillate for ever; `damping` adds a drag
  `-damping * v_i` for a user who wants the net to settle).

So `m_i x_i'' = sum_j k_ij (x_j - x_i) - damping m_i x_i'`: a linear system whose motion is a
sum of its normal modes. Without damping its energy `sum_i m_i v_i^2 / 2 + sum_{i<j} k_ij
(x_i - x_j)^2 / 2` is conserved, and its mass-weighted centre stays where it started.

The net's positions and velocities are the controller's continuous state, integrated in the
same solve as the body (`AbstractController.rates`): the semi-implicit Euler of the search
(which keeps the energy within a bounded band) or the adaptive solvers.

**Outputs.** Joint `j` (of the figure's free angles, in order) reads mass `outputs[j]`
(default mass `j`): its target angle is the affine map of the position `[-1, 1]` onto the
joint's range `[lo, hi]`, clipped, `th0 = (lo + hi) / 2 + (hi - lo) / 2 * clip(x, -1, 1)`,
and the joint follows the law `tau^2 th'' + 2 tau th' + (th - th0) = 0`. The paper applied
torques from the net's outputs through a general dynamics simulator: a figure built with
`max_torque` does so too (each joint applies the torque the law asks for, clipped, and the
figure moves under it; `configs/snake_travel.toml` and `configs/luxo_travel.toml`); without
it the joints are the second paper's kinematic ones, of unlimited torque.
"""

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .._body.figure import Figure
from .base import AbstractController, AbstractControllerSpace, ControllerState

MUTATION_KINDS = ("all_springs", "one_spring", "one_mass", "one_position")
"""The paper's four kinds of mutation, in the order of `MUTATION_PROBABILITIES`."""
MUTATION_PROBABILITIES = (0.2, 0.6, 0.1, 0.1)
"""How often each kind of mutation is chosen (the paper: 2/10, 6/10, 1/10, 1/10)."""


def spring_pairs(num_masses: int) -> tuple[tuple[int, int], ...]:
    """The springs of a net of `num_masses` masses: every pair `(i, j)`, `i < j`, in
    lexicographic order (the order of `SpringNet.stiffness`)."""
    return tuple((i, j) for i in range(num_masses) for j in range(i + 1, num_masses))


class SpringNet(AbstractController):
    """A spring-net controller (third paper): `n` point masses on a line joined by
    zero-rest-length springs between every pair, oscillating from rest at their initial
    positions; chosen masses' positions are the figure's target joint angles (see the
    module's docstring for the model and the output map).

    **Fields:** `masses` `(n,)` kg; `stiffness` `(n (n - 1) / 2,)` spring constants (N/m)
    of the pairs `spring_pairs(n)`; `positions` `(n,)` the initial positions (dimensionless:
    `[-1, 1]` spans each output joint's range); `tau` the joints' time constant (s);
    `ranges` (static) the free joints' ranges `((lo, hi), ...)`, radians; `outputs`
    (static) which mass each free joint reads; `damping` (static) the drag rate, 1/s
    (default 0: none).

    The state is `ControllerState(None, (x, v))`: the masses' positions and velocities.
    """

    masses: Float[Array, " num_masses"]
    stiffness: Float[Array, " num_springs"]
    positions: Float[Array, " num_masses"]
    tau: Float[Array, ""]
    ranges: tuple[tuple[float, float], ...] = eqx.field(static=True)
    outputs: tuple[int, ...] = eqx.field(static=True)
    damping: float = eqx.field(static=True)

    supports_batch_last: ClassVar[bool] = True

    def __init__(
        self,
        masses: Float[ArrayLike, " num_masses"],
        stiffness: Float[ArrayLike, " num_springs"],
        positions: Float[ArrayLike, " num_masses"],
        tau: float | Float[ArrayLike, ""],
        ranges,
        outputs=None,
        damping: float = 0.0,
    ):
        ranges = tuple((float(lo), float(hi)) for lo, hi in ranges)
        n = int(np.shape(masses)[0]) if np.ndim(masses) >= 1 else 0
        outputs = tuple(range(len(ranges))) if outputs is None else tuple(int(o) for o in outputs)
        if not any(isinstance(x, jax.core.Tracer) for x in (masses, stiffness, positions, tau)):
            _check(masses, stiffness, positions, tau, ranges, outputs, damping)
        elif len(outputs) != len(ranges) or any(not 0 <= o < n for o in outputs):
            raise ValueError(
                f"SpringNet.outputs = {outputs!r}; allowed: one mass index in 0..{n - 1} per "
                f"joint range ({len(ranges)})"
            )
        self.masses = jnp.asarray(masses, dtype=float)
        self.stiffness = jnp.asarray(stiffness, dtype=float)
        self.positions = jnp.asarray(positions, dtype=float)
        self.tau = jnp.asarray(tau, dtype=float)
        self.ranges = ranges
        self.outputs = outputs
        self.damping = float(damping)

    @property
    def num_masses(self) -> int:
        return self.masses.shape[0]

    @property
    def pairs(self) -> tuple[tuple[int, int], ...]:
        return spring_pairs(self.num_masses)

    def prepare(self, body: Figure) -> None:
        if not isinstance(body, Figure):
            raise TypeError(f"SpringNet controls articulated figures; got a {type(body).__name__}")
        if len(self.outputs) != body.num_free:
            raise ValueError(
                f"SpringNet drives {len(self.outputs)} joint angles but figure {body.name!r} "
                f"has {body.num_free} free angles"
            )
        figure_ranges = tuple((float(lo), float(hi)) for lo, hi in body.ranges)
        if not np.allclose(self.ranges, figure_ranges):
            raise ValueError(
                f"SpringNet.ranges = {self.ranges!r} are not figure {body.name!r}'s joint "
                f"ranges {figure_ranges!r}"
            )
        return None

    def init(self, senses, plan) -> ControllerState:
        """The masses at their initial positions, at rest."""
        del senses, plan
        return ControllerState(None, (self.positions, jnp.zeros_like(self.positions)))

    def accelerations(self, x, v):
        """The masses' accelerations at positions `x` and velocities `v` (`(n, *batch)`):
        the springs' forces over the masses, minus the drag."""
        n = self.num_masses
        force = [jnp.zeros_like(x[0]) for _ in range(n)]
        # Explicit adds over the springs (elementwise over any batch: the same rounding
        # whatever the batch width).
        for p, (i, j) in enumerate(self.pairs):
            f = self.stiffness[p] * (x[j] - x[i])
            force[i] = force[i] + f
            force[j] = force[j] - f
        acc = jnp.stack([force[i] / self.masses[i] for i in range(n)])
        if self.damping:
            acc = acc - self.damping * v
        return acc

    def rates(self, t, state: ControllerState, plan):
        """`(x', v') = (v, a(x, v))`."""
        del t, plan
        x, v = state.continuous
        return v, self.accelerations(x, v)

    def outputs_to_targets(self, x) -> Float[Array, "num_free ..."]:
        """The target joint angles for net positions `x` (`(n, *batch)`): each output mass's
        position mapped affinely from `[-1, 1]` onto its joint's range, clipped."""
        targets = []
        for (lo, hi), o in zip(self.ranges, self.outputs, strict=True):
            mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            targets.append(mid + half * jnp.clip(x[o], -1.0, 1.0))
        return jnp.stack(targets)

    def actuation(self, t, state: ControllerState, plan):
        """The output masses' positions as target angles, and the time constant."""
        del t, plan
        x, _ = state.continuous
        return self.outputs_to_targets(x), self.tau

    def energy(self, x, v) -> Float[Array, "..."]:
        """The net's energy at positions `x` and velocities `v` (`(n, *batch)`): kinetic
        `sum m v^2 / 2` plus the springs' `sum k (x_i - x_j)^2 / 2`; conserved without
        damping."""
        masses = jnp.reshape(self.masses, self.masses.shape + (1,) * (v.ndim - self.masses.ndim))
        kinetic = 0.5 * jnp.sum(masses * v * v, axis=0)
        potential = 0.0
        for p, (i, j) in enumerate(self.pairs):
            potential = potential + 0.5 * self.stiffness[p] * (x[i] - x[j]) ** 2
        return kinetic + potential

    def oscillate(self, duration: float, dt: float) -> tuple[np.ndarray, Float[Array, "steps n"]]:
        """The net alone over `duration` s, in steps of `dt` by the search's semi-implicit
        Euler (`v1 = v0 + dt a(x0, v0)`, `x1 = x0 + dt v1`). A closed-loop net reads no
        senses, so this is its motion in any simulation with that step (for plots: the
        masses beside the figure). Returns the times `(steps + 1,)` and the positions
        `(steps + 1, n)`; the velocities at the end are `oscillate_state(...)`'s."""
        ts, (xs, _) = self.oscillate_state(duration, dt)
        return ts, xs

    def oscillate_state(self, duration: float, dt: float):
        """`oscillate`, with the velocities: times `(steps + 1,)` and `(positions,
        velocities)`, each `(steps + 1, n)`."""
        steps = round(duration / dt)
        if steps < 1 or not math.isclose(steps * dt, duration, rel_tol=1e-9):
            raise ValueError(
                f"oscillate: duration = {duration!r} is not a whole number (>= 1) of steps "
                f"dt = {dt!r}"
            )
        xs, vs = _oscillate(self, steps, float(dt))
        return np.arange(steps + 1) * dt, (xs, vs)


@eqx.filter_jit
def _oscillate(net: SpringNet, steps: int, dt: float):
    def step(xv, _):
        x, v = xv
        v1 = v + dt * net.accelerations(x, v)
        x1 = x + dt * v1
        return (x1, v1), (x1, v1)

    start = (net.positions, jnp.zeros_like(net.positions))
    _, (xs, vs) = jax.lax.scan(step, start, None, length=steps)
    return (
        jnp.concatenate([start[0][None], xs]),
        jnp.concatenate([start[1][None], vs]),
    )


def _check(masses, stiffness, positions, tau, ranges, outputs, damping) -> None:
    m = np.asarray(masses, dtype=float)
    k = np.asarray(stiffness, dtype=float)
    x = np.asarray(positions, dtype=float)
    if m.ndim != 1 or m.size < 2:
        raise ValueError(f"SpringNet.masses has shape {m.shape}; allowed: (n,) with n >= 2")
    n = m.size
    if k.shape != (n * (n - 1) // 2,):
        raise ValueError(
            f"SpringNet.stiffness has shape {k.shape}; allowed: ({n * (n - 1) // 2},), one per "
            f"pair of the {n} masses (spring_pairs)"
        )
    if x.shape != (n,):
        raise ValueError(f"SpringNet.positions has shape {x.shape}; allowed: ({n},)")
    if not np.all(np.isfinite(m)) or np.any(m <= 0):
        raise ValueError(f"SpringNet.masses = {m.tolist()}; allowed: numbers > 0 (kg)")
    if not np.all(np.isfinite(k)) or np.any(k < 0):
        raise ValueError(f"SpringNet.stiffness = {k.tolist()}; allowed: numbers >= 0 (N/m)")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"SpringNet.positions = {x.tolist()}; allowed: finite numbers")
    t = np.asarray(tau, dtype=float)
    if t.shape != () or not np.isfinite(t) or t <= 0:
        raise ValueError(f"SpringNet.tau = {tau!r}; allowed: a number > 0 (s)")
    for j, (lo, hi) in enumerate(ranges):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"SpringNet.ranges[{j}] = {(lo, hi)!r}; allowed: lo <= hi, finite")
    if len(outputs) != len(ranges) or any(not 0 <= o < n for o in outputs):
        raise ValueError(
            f"SpringNet.outputs = {outputs!r}; allowed: one mass index in 0..{n - 1} per joint "
            f"range ({len(ranges)})"
        )
    if not (math.isfinite(damping) and damping >= 0):
        raise ValueError(f"SpringNet.damping = {damping!r}; allowed: a number >= 0 (1/s)")


def _number(owner: str, name: str, value, allowed: str, ok) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not ok(value):
        raise ValueError(f"{owner}.{name} = {value!r}; allowed: {allowed}")
    return float(value)


class SpringNetSpace(AbstractControllerSpace[SpringNet]):
    """The family of `SpringNet` controllers for one figure: random nets and the paper's
    mutations.

    **Sampling** (the paper gives no distributions; these are ours): every mass log-uniform
    in `[mass_min, mass_max]` (0.5..2 kg), every spring constant log-uniform in
    `[stiffness_min, stiffness_max]` (1..50 N/m: with four masses of 0.5..2 kg the net's
    modes then lie between about 0.2 and 3 Hz, the rates of a gait over a few seconds),
    every initial position uniform in `[-1, 1]` (the span the output map reads), velocities
    zero.

    **Mutation** (`perturb`: one mutation; the paper's kinds and shares,
    `MUTATION_PROBABILITIES`): with probability 2/10 every spring constant is perturbed,
    6/10 one spring constant (chosen uniformly), 1/10 one mass, 1/10 one initial position.
    A spring constant or a mass is multiplied by `exp(scale * N(0, 1))` (a step on the log
    scale its sampling uses) and clipped to its bounds; a position moves by `scale *
    N(0, 1)` and is clipped to `[-1, 1]`. `mutate(controller, kind, key=...)` applies one
    mutation of a given kind.

    **Arguments:** `figure`; `num_masses` n (default 4; at least the figure's free angles,
    each of which reads its own mass: angle `j` reads mass `j`); `tau` the joints' time
    constant (s, default 0.1: with kinematic joints, whose torque is unlimited, a shorter
    time constant lets the limbs whip; the torque-limited creatures of the configs use
    0.03); `mass_min`, `mass_max`, `stiffness_min`, `stiffness_max`; `scale` the mutation's
    step (default 0.3); `damping` (1/s, default 0).

    **Raises:** `TypeError` for a body that is not a `Figure`; `ValueError`, naming the
    argument, for a bad one.
    """

    num_masses: int = eqx.field(static=True)
    ranges: tuple[tuple[float, float], ...] = eqx.field(static=True)
    tau: float = eqx.field(static=True)
    mass_min: float = eqx.field(static=True)
    mass_max: float = eqx.field(static=True)
    stiffness_min: float = eqx.field(static=True)
    stiffness_max: float = eqx.field(static=True)
    scale: float = eqx.field(static=True)
    damping: float = eqx.field(static=True)

    def __init__(
        self,
        figure: Figure,
        num_masses: int = 4,
        tau: float = 0.1,
        mass_min: float = 0.5,
        mass_max: float = 2.0,
        stiffness_min: float = 1.0,
        stiffness_max: float = 50.0,
        scale: float = 0.3,
        damping: float = 0.0,
    ):
        if not isinstance(figure, Figure):
            raise TypeError(f"SpringNetSpace needs a Figure; got {type(figure).__name__}")
        owner = "SpringNetSpace"
        if (
            isinstance(num_masses, bool)
            or not isinstance(num_masses, int)
            or num_masses < max(2, figure.num_free)
        ):
            raise ValueError(
                f"{owner}.num_masses = {num_masses!r}; allowed: an integer >= "
                f"{max(2, figure.num_free)} (at least 2, and one mass per free angle of "
                f"figure {figure.name!r})"
            )
        positive = lambda v: math.isfinite(v) and v > 0
        self.tau = _number(owner, "tau", tau, "a number > 0 (s)", positive)
        self.mass_min = _number(owner, "mass_min", mass_min, "a number > 0 (kg)", positive)
        self.mass_max = _number(owner, "mass_max", mass_max, "a number > 0 (kg)", positive)
        self.stiffness_min = _number(
            owner, "stiffness_min", stiffness_min, "a number > 0 (N/m)", positive
        )
        self.stiffness_max = _number(
            owner, "stiffness_max", stiffness_max, "a number > 0 (N/m)", positive
        )
        for lo, hi in (("mass_min", "mass_max"), ("stiffness_min", "stiffness_max")):
            if getattr(self, lo) > getattr(self, hi):
                raise ValueError(
                    f"{owner}.{lo} = {getattr(self, lo)!r} > {hi} = {getattr(self, hi)!r}; "
                    f"allowed: {lo} <= {hi}"
                )
        self.scale = _number(owner, "scale", scale, "a number > 0", positive)
        self.damping = _number(
            owner, "damping", damping, "a number >= 0 (1/s)", lambda v: math.isfinite(v) and v >= 0
        )
        self.num_masses = int(num_masses)
        self.ranges = tuple((float(lo), float(hi)) for lo, hi in figure.ranges)

    @property
    def family(self) -> str:
        return "spring_net"

    @property
    def num_springs(self) -> int:
        return self.num_masses * (self.num_masses - 1) // 2

    def _net(self, masses, stiffness, positions) -> SpringNet:
        return SpringNet(masses, stiffness, positions, self.tau, self.ranges, damping=self.damping)

    def sample(self, *, key: PRNGKeyArray) -> SpringNet:
        n, p = self.num_masses, self.num_springs
        u = jr.uniform(key, (n + p + n,))
        masses = _log_uniform(u[:n], self.mass_min, self.mass_max)
        stiffness = _log_uniform(u[n : n + p], self.stiffness_min, self.stiffness_max)
        positions = 2.0 * u[n + p :] - 1.0
        return self._net(masses, stiffness, positions)

    def mutation_kind(self, *, key: PRNGKeyArray) -> Int[Array, ""]:
        """A kind of mutation (an index into `MUTATION_KINDS`), drawn with the paper's
        shares `MUTATION_PROBABILITIES`."""
        return jr.choice(key, len(MUTATION_KINDS), p=jnp.asarray(MUTATION_PROBABILITIES))

    def mutate(self, controller: SpringNet, kind, *, key: PRNGKeyArray) -> SpringNet:
        """`controller` hit by one mutation of kind `kind` (an index into
        `MUTATION_KINDS`, possibly traced)."""
        n, p = self.num_masses, self.num_springs
        spring_key, mass_key, step_key = jr.split(key, 3)
        step = self.scale * jr.normal(step_key, (p,))
        pick_spring = jr.randint(spring_key, (), 0, p)
        pick_mass = jr.randint(mass_key, (), 0, n)
        k_lo, k_hi = self.stiffness_min, self.stiffness_max
        k = controller.stiffness
        all_k = jnp.clip(k * jnp.exp(step), k_lo, k_hi)
        one_k = k.at[pick_spring].set(jnp.clip(k[pick_spring] * jnp.exp(step[0]), k_lo, k_hi))
        m = controller.masses
        one_m = m.at[pick_mass].set(
            jnp.clip(m[pick_mass] * jnp.exp(step[0]), self.mass_min, self.mass_max)
        )
        x = controller.positions
        one_x = x.at[pick_mass].set(jnp.clip(x[pick_mass] + step[0], -1.0, 1.0))
        stiffness = jnp.where(kind == 0, all_k, jnp.where(kind == 1, one_k, k))
        masses = jnp.where(kind == 2, one_m, m)
        positions = jnp.where(kind == 3, one_x, x)
        return SpringNet(
            masses,
            stiffness,
            positions,
            controller.tau,
            controller.ranges,
            controller.outputs,
            controller.damping,
        )

    def perturb(self, controller: SpringNet, *, key: PRNGKeyArray, motion=None) -> SpringNet:
        """One mutation, its kind drawn with the paper's shares."""
        del motion
        kind_key, mutate_key = jr.split(key)
        return self.mutate(controller, self.mutation_kind(key=kind_key), key=mutate_key)

    def trainable(self, controller: SpringNet):
        """Masses, spring constants and initial positions are refined by gradients; the
        time constant (fixed by the family) is not."""
        spec = jax.tree_util.tree_map(lambda _: False, controller)
        return eqx.tree_at(lambda c: (c.masses, c.stiffness, c.positions), spec, (True, True, True))

    def project(self, controller: SpringNet) -> SpringNet:
        """Clip into the family's bounds."""
        return eqx.tree_at(
            lambda c: (c.masses, c.stiffness, c.positions),
            controller,
            (
                jnp.clip(controller.masses, self.mass_min, self.mass_max),
                jnp.clip(controller.stiffness, self.stiffness_min, self.stiffness_max),
                jnp.clip(controller.positions, -1.0, 1.0),
            ),
        )


def _log_uniform(u, lo: float, hi: float):
    return jnp.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)
