"""Random starts around a body state: what makes a searched controller robust (the second
paper's "enhanced motion controllers", section 3)."""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import PRNGKeyArray

from .._body.base import AbstractBody, BodyState
from .._body.figure import Figure, FigurePositions, FigureVelocities
from .._body.lattice import Lattice
from .._world import World

REDUCTIONS = ("mean", "worst")


def _check_magnitude(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
        raise ValueError(f"Robustness.{name} = {value!r}; allowed: a number >= 0")
    return float(value)


class Robustness(eqx.Module):
    """Evaluate every controller from several randomly perturbed starts, and score it by
    the mean (or the worst) of its fitness over them: a search then keeps only
    controllers insensitive to where they start (the second paper, section 3: "randomly
    perturbing the initial physical configuration ... during each iteration", which makes
    controllers that can be concatenated into composite motions).

    A perturbed start is the task's starting state with

    - each free joint angle moved by a uniform draw in `[-angles, angles]` rad (clipped to
        its range; figures only);
    - the root (a figure's root rod, a lattice as a whole) turned about its centre of mass
        by a uniform angle in `[-orientation, orientation]` rad about a random axis
        (uniform on the sphere; about the y axis for a planar figure);
    - a uniform draw in `[-velocity, velocity]` m/s added to each component of the centre
        of mass's velocity (a lattice: to every mass's);
    - then lifted or lowered so its lowest point is as high as the unperturbed state's (on
        the floor, for a start from rest): never inside the floor, never dropped.

    Angular momentum and joint rates are kept. The defaults (0.1 rad, about 6 degrees, for
    the joints and the root, 0.2 m/s) are small beside the motions of the papers'
    characters and large beside the few millimetres of a controller's usual start.

    The starts are drawn from a key that the search gives each evaluation (every
    controller of one seed's generation sees the same starts, so they compete on equal
    terms), so a search stays reproducible from its seed.

    By default every step (a generation of `serial_search` or `evolve`, a step of
    `parallel_hill_climb`) draws new starts, while a climber keeps the score it got on the
    starts it drew: one that drew easy starts can survive on that luck (in measurements, a
    robust cartwheel that scored 21.3 on its starts made 15.9 from its real one). With
    `common=True` a search draws its starts once and every evaluation faces the same
    `samples` starts (common random numbers): comparisons are then exact, and the
    controllers are robust to those starts only.

    With `nominal=True` the first of the `samples` starts is the task's own, unperturbed:
    every score then includes the controller's fitness from where it will really start,
    so a climber cannot survive on perturbed starts alone while failing from its real one
    (the other starts are the same draws as without it).

    **Fields (static):** `samples` (starts per evaluation, K), `angles`, `orientation`,
    `velocity` (magnitudes), `reduce` (`"mean"` or `"worst"`), `common` (one draw of starts
    for the whole search), `nominal` (the first start unperturbed).
    """

    samples: int = eqx.field(static=True)
    angles: float = eqx.field(static=True)
    orientation: float = eqx.field(static=True)
    velocity: float = eqx.field(static=True)
    reduce: Literal["mean", "worst"] = eqx.field(static=True)
    common: bool = eqx.field(static=True)
    nominal: bool = eqx.field(static=True)

    def __init__(
        self,
        samples: int = 4,
        angles: float = 0.1,
        orientation: float = 0.1,
        velocity: float = 0.2,
        reduce: Literal["mean", "worst"] = "mean",
        common: bool = False,
        nominal: bool = False,
    ):
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise ValueError(f"Robustness.samples = {samples!r}; allowed: an integer >= 1")
        if reduce not in REDUCTIONS:
            raise ValueError(
                f"Robustness.reduce = {reduce!r}; allowed: {', '.join(map(repr, REDUCTIONS))}"
            )
        self.samples = samples
        self.angles = _check_magnitude("angles", angles)
        self.orientation = _check_magnitude("orientation", orientation)
        self.velocity = _check_magnitude("velocity", velocity)
        self.reduce = reduce
        if not isinstance(common, bool):
            raise ValueError(f"Robustness.common = {common!r}; allowed: True or False")
        self.common = common
        if not isinstance(nominal, bool):
            raise ValueError(f"Robustness.nominal = {nominal!r}; allowed: True or False")
        self.nominal = nominal

    def starts(self, body: AbstractBody, state: BodyState, key: PRNGKeyArray) -> BodyState:
        """`samples` perturbed copies of `state` (one body's), stacked along a leading
        axis; start `k` draws from `jax.random.fold_in(key, k)` (with `nominal`, start 0
        is `state` itself)."""
        return _starts(self, body, state, key)

    def perturb(self, body: AbstractBody, state: BodyState, key: PRNGKeyArray) -> BodyState:
        """One perturbed copy of `state` (see the class)."""
        if isinstance(body, Figure):
            return self._figure(body, state, key)
        if isinstance(body, Lattice):
            return self._lattice(body, state, key)
        raise TypeError(f"Robustness perturbs figures and lattices; got a {type(body).__name__}")

    def reduced(self, fitness):
        """The score of each controller from its fitness over the starts (last axis)."""
        if self.reduce == "worst":
            return jnp.min(fitness, axis=-1)
        return jnp.mean(fitness, axis=-1)

    def _figure(self, body: Figure, state: BodyState, key) -> BodyState:
        positions, velocities = FigurePositions(*state[0]), FigureVelocities(*state[1])
        k_angles, k_turn, k_axis, k_velocity = jr.split(key, 4)
        ranges = jnp.asarray(body.ranges, dtype=positions.angles.dtype).reshape(-1, 2)
        angles = positions.angles + _uniform(k_angles, positions.angles, self.angles)
        angles = jnp.clip(angles, ranges[:, 0], ranges[:, 1])
        half = 0.5 * _uniform(k_turn, jnp.zeros(()), self.orientation)
        q = positions.orientation
        if body.planar:  # (w, y): a turn about y
            c, s = jnp.cos(half), jnp.sin(half)
            orientation = jnp.stack([c * q[0] - s * q[1], s * q[0] + c * q[1]])
        else:
            axis = jr.normal(k_axis, (3,), dtype=q.dtype)
            axis = axis / jnp.linalg.norm(axis)
            turn = jnp.concatenate([jnp.cos(half)[None], jnp.sin(half) * axis])
            orientation = _quaternion_product(turn, q)
        velocity = velocities.com_velocity + _uniform(
            k_velocity, velocities.com_velocity, self.velocity
        )
        moved = FigurePositions(positions.com, orientation, angles)
        lift = _lowest(body, positions) - _lowest(body, moved)
        up = positions.com.shape[0] - 1  # z: the last component (x, z planar; x, y, z)
        com = positions.com.at[up].add(lift)
        return BodyState(
            FigurePositions(com, orientation, angles),
            FigureVelocities(velocity, velocities.momentum, velocities.angle_rates),
        )

    def _lattice(self, body: Lattice, state: BodyState, key) -> BodyState:
        x, v = state  # (3, n)
        k_turn, k_axis, k_velocity = jr.split(key, 3)
        masses = jnp.asarray(body.masses, dtype=x.dtype)
        com = jnp.sum(x * masses, axis=1, keepdims=True) / jnp.sum(masses)
        angle = _uniform(k_turn, jnp.zeros(()), self.orientation)
        axis = jr.normal(k_axis, (3,), dtype=x.dtype)
        rotation = _rotation(axis / jnp.linalg.norm(axis), angle)
        moved = com + rotation @ (x - com)
        moved = moved.at[2].add(jnp.min(x[2]) - jnp.min(moved[2]))
        shift = _uniform(k_velocity, jnp.zeros((3, 1), dtype=x.dtype), self.velocity)
        return BodyState(moved, v + shift)


@eqx.filter_jit
def _starts(robustness: Robustness, body, state, key):
    keys = jax.vmap(lambda k: jr.fold_in(key, k))(jnp.arange(robustness.samples))
    starts = jax.vmap(lambda k: robustness.perturb(body, state, k))(keys)
    if robustness.nominal:
        starts = jax.tree_util.tree_map(
            lambda s, a: s.at[0].set(jnp.asarray(a, s.dtype)), starts, state
        )
    return starts


def _uniform(key, like, magnitude: float):
    """Uniform draws in `[-magnitude, magnitude]`, shaped like `like`."""
    like = jnp.asarray(like)
    return jr.uniform(key, like.shape, like.dtype, -magnitude, magnitude)


def _lowest(body: Figure, positions: FigurePositions):
    """The height of the figure's lowest node in this pose."""
    points = body.dynamics().observe(positions, World()).points
    return jnp.min(points[:, 2])


def _quaternion_product(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return jnp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _rotation(axis, angle):
    """The rotation matrix of `angle` about the unit `axis` (Rodrigues)."""
    k = jnp.array(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
        dtype=axis.dtype,
    )
    return jnp.eye(3, dtype=axis.dtype) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * (k @ k)


__all__ = ["Robustness"]
