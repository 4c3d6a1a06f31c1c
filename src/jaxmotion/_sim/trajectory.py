"""What a simulation returns: the observables every body reports at saved times, and the full
state it ended in."""

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
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
    - `positions`: the body's positions state at the saved times (time leading on every
        leaf), when asked for (`simulate(..., positions=True)`, `Task.simulate(...,
        positions=True)`); otherwise `None`. For a `Figure` it is `FigurePositions` (centre
        of mass, root orientation, free joint angles): with the figure it rebuilds every
        rod's whole pose, twist included (`Figure.rod_poses`), which the endpoints in
        `points` do not; for a `Lattice` it is the masses' positions (as `points`). The
        search never records it.

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
    positions: Any = None

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


def concatenate_trajectories(trajectories: Sequence[Trajectory]) -> Trajectory:
    """One motion of several performed one after another (the stages of a multi-stage
    run): each later trajectory's times shifted by the durations of those before it, and
    its first sample dropped (it repeats the previous trajectory's last one when it started
    from that one's final state, as `jaxmotion.experiment.start_where` starts a stage).

    **Arguments:** one or more unbatched trajectories of the same body.

    **Returns:** a `Trajectory`: finite when every part is, `final` the last part's,
    `senses` and `positions` each joined when every part has them (else None).

    **Raises:** `ValueError` for no trajectories, a batched one, or parts of different
    bodies.
    """
    parts = list(trajectories)
    if not parts:
        raise ValueError("concatenate_trajectories needs at least one trajectory")
    for i, part in enumerate(parts):
        if not isinstance(part, Trajectory) or np.ndim(part.com) != 2:
            raise ValueError(
                f"concatenate_trajectories joins unbatched Trajectory objects; part {i} is "
                f"{'batched' if isinstance(part, Trajectory) else type(part).__name__}"
            )
        if np.shape(part.points)[1:] != np.shape(parts[0].points)[1:]:
            raise ValueError(
                f"concatenate_trajectories: part {i} has points of shape "
                f"{np.shape(part.points)[1:]}, part 0 {np.shape(parts[0].points)[1:]} (one body)"
            )
    ts, offset = [parts[0].ts], parts[0].ts[-1]
    for part in parts[1:]:
        ts.append(part.ts[1:] - part.ts[0] + offset)
        offset = offset + part.ts[-1] - part.ts[0]

    def join(name):
        trees = [getattr(p, name) for p in parts]
        return jax.tree_util.tree_map(
            lambda first, *rest: jnp.concatenate([first, *(leaf[1:] for leaf in rest)]), *trees
        )

    sensed = all(p.senses is not None for p in parts)
    posed = all(p.positions is not None for p in parts)
    return Trajectory(
        ts=jnp.concatenate(ts),
        points=join("points"),
        com=join("com"),
        frame=join("frame"),
        contact=join("contact"),
        finite=jnp.all(jnp.stack([jnp.asarray(p.finite) for p in parts])),
        final=parts[-1].final,
        senses=join("senses") if sensed else None,
        positions=join("positions") if posed else None,
    )
