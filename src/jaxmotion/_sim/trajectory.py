"""What a simulation returns: the observables every body reports at saved times, and the full
state it ended in."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree


class Observation(eqx.Module):
    """The observables of one body at one instant. Every body reports the same ones, so
    objectives never care which body moved.

    - `points`: `(num_points, 3)` world positions of the masses (lattices) or rod endpoints.
    - `com`: `(3,)` centre of mass.
    - `frame`: `(3, 3)` body orientation; its columns are the body's forward, left and up axes
        in world coordinates (at rest they are the body's own `frame`).
    - `contact`: `(num_points,)` whether each point touches the floor (is below z = 0, where the
        penalty contact acts).
    """

    points: Float[Array, "num_points 3"]
    com: Float[Array, "3"]
    frame: Float[Array, "3 3"]
    contact: Bool[Array, " num_points"]


class SimulationState(eqx.Module):
    """The full state of a simulation at one instant: enough to continue it exactly.

    - `t`: the time, s (on the control grid: a whole number of control periods).
    - `body`: the body's `BodyState` (`(positions, velocities)`, named by the body).
    - `controller`: the controller's `ControllerState` (`(discrete, continuous)`), as it is
        before the control tick at `t`.

    `Trajectory.final` holds the state a simulation ended in; `simulate(...,
    initial_state=trajectory.final)` (or `Task.simulate`) continues the same controller from
    it. To start *another* controller where a motion ended (seriatim searches, composite
    motions), pass only the body's state, `trajectory.final.body`: the new controller then
    starts from its own initial state at its own time 0.

    Under `vmap` (or from a batched call) every leaf gains a leading batch axis.
    """

    t: Float[Array, ""]
    body: Any
    controller: Any

    def __init__(self, t, body, controller):
        self.t = jnp.asarray(t, dtype=float)
        self.body = body
        self.controller = controller


class Trajectory(eqx.Module):
    """A simulated motion, sampled at `ts`. Leading axis of every field but `finite` and
    `final` is time.

    - `ts`: `(num_saves,)` saved times, from the start to the end of the simulation.
    - `points`, `com`, `frame`, `contact`: the `Observation` fields stacked over `ts`.
    - `finite`: whether the run stayed finite (no NaN or infinity anywhere, and the solver
        succeeded). A run that blew up is data, not an exception; objectives score it worst.
    - `final`: the `SimulationState` at the end (continue from it).
    - `senses`: `(num_saves, num_senses)` the senses the controller perceived at the saved
        times (`AbstractController.perceive`), when asked for (`Task.evaluate_sensed`,
        `Task.trajectories(..., senses=True)`); otherwise `None`.

    Under `vmap` every field gains a leading batch axis.
    """

    ts: Float[Array, " num_saves"]
    points: Float[Array, "num_saves num_points 3"]
    com: Float[Array, "num_saves 3"]
    frame: Float[Array, "num_saves 3 3"]
    contact: Bool[Array, "num_saves num_points"]
    finite: Bool[Array, ""]
    final: SimulationState | None = None
    senses: Float[Array, "num_saves num_senses"] | None = None

    @property
    def forward(self) -> Float[Array, "num_saves 3"]:
        """The body's forward axis over time (first column of `frame`)."""
        return self.frame[..., :, 0]

    @property
    def left(self) -> Float[Array, "num_saves 3"]:
        """The body's left axis over time (second column of `frame`)."""
        return self.frame[..., :, 1]

    @property
    def up(self) -> Float[Array, "num_saves 3"]:
        """The body's up axis over time (third column of `frame`)."""
        return self.frame[..., :, 2]


def all_finite(*trees: PyTree) -> Bool[Array, ""]:
    """True when every floating-point leaf of the given pytrees is finite."""
    ok = jnp.asarray(True)
    for leaf in jax.tree_util.tree_leaves(trees):
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            ok = ok & jnp.all(jnp.isfinite(leaf))
    return ok
