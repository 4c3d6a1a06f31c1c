"""The interface every body implements, so `simulate` and the objectives never care which
body moves."""

import abc
from typing import Any, ClassVar

import equinox as eqx
from jaxtyping import Array, Float, PyTree

from .._sim.trajectory import Observation
from .._world import World

State = PyTree[Float[Array, "..."]]


class AbstractDynamics(eqx.Module):
    """A body prepared for simulation: whatever per-step arithmetic needs, precomputed once
    per simulation (e.g. dense spring tables), with the equations of motion.

    The state is a pair `(positions, velocities)` of pytrees, so that one semi-implicit
    (symplectic) solver serves every body: velocities are advanced with the forces at the
    old state, then positions with the new velocities.

    `rates` is written for one body. A subclass that sets `supports_batch_last = True`
    promises that `rates` also accepts states with extra trailing (batch) axes, with the
    actuation batched the same way, and returns rates shaped like the state: the fast
    batched path then calls it directly on the whole batch (the batch as the contiguous last
    axis is what makes XLA's CPU loops vectorise). Otherwise the fast path `vmap`s it.
    """

    supports_batch_last: ClassVar[bool] = False

    @abc.abstractmethod
    def rates(
        self, state: tuple[State, State], actuation: Any, world: World
    ) -> tuple[State, State]:
        """Time derivative `(d positions/dt, d velocities/dt)` of `state` under `actuation`
        (what the controller commands; `None` for no actuation) in `world`."""

    @abc.abstractmethod
    def observe(self, positions: State, world: World) -> Observation:
        """The observables (points, centre of mass, frame, contact) at the given positions
        (the first half of the state: observables never depend on velocities).

        `positions` may carry any number of trailing batch axes (saved times, controllers);
        each field of the returned `Observation` then has those axes trailing too (e.g.
        `com` is `(3, *batch)`, `points` `(num_points, 3, *batch)`). Write it elementwise
        over them.
        """


class AbstractBody(eqx.Module):
    """A physical body: the model (masses and springs, or rods and joints), kept apart from
    its evolving state (which `simulate` owns)."""

    @abc.abstractmethod
    def initial_state(self) -> tuple[State, State]:
        """The state `(positions, velocities)` at t = 0: the rest pose, at rest."""

    @abc.abstractmethod
    def dynamics(self) -> AbstractDynamics:
        """This body prepared for simulation (called once per simulation, outside the time
        loop)."""

    @property
    @abc.abstractmethod
    def num_points(self) -> int:
        """How many points `Observation.points` holds for this body."""
