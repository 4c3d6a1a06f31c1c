"""The interface every body implements, so `simulate`, the controllers and the objectives never
care which body moves."""

import abc
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
from jaxtyping import Array, Float, PyTree

from .._sim.trajectory import Observation
from .._world import World


class BodyState(NamedTuple):
    """The state of a body: a pair `(positions, velocities)` of pytrees, so that one
    semi-implicit (symplectic) solver serves every body (velocities are advanced with the
    forces at the old state, then positions with the new velocities).

    Each body names what its pair holds: a `Lattice`'s `positions` and `velocities` are
    `(3, num_masses)` arrays; a `Figure`'s are `FigurePositions(com, orientation, angles)` and
    `FigureVelocities(com_velocity, momentum, angle_rates)`. Make one with the body's own
    `state(...)`; a batch of states carries the batch as a leading axis of every leaf.
    """

    positions: PyTree[Float[Array, "..."]]
    velocities: PyTree[Float[Array, "..."]]


class AbstractDynamics(eqx.Module):
    """A body prepared for simulation: whatever per-step arithmetic needs, precomputed once
    per simulation (e.g. dense spring tables), with the equations of motion and the senses.

    `rates`, `senses` and `observe` are written for one body. A subclass that sets
    `supports_batch_last = True` promises that they also accept states with extra trailing
    (batch) axes, with the actuation batched the same way, and return results with the same
    trailing axes: the batched layout then calls them directly on the whole batch (the batch
    as the contiguous last axis is what makes XLA's CPU loops vectorise). Otherwise the
    batched layout `vmap`s them.
    """

    supports_batch_last: ClassVar[bool] = False

    @abc.abstractmethod
    def rates(self, state: BodyState, actuation: Any, world: World) -> BodyState:
        """Time derivative `(d positions/dt, d velocities/dt)` of `state` under `actuation`
        (what the controller commands; `None` for no actuation) in `world`."""

    @abc.abstractmethod
    def senses(self, state: BodyState, world: World, control_dt: float) -> Float[Array, "..."]:
        """The sense variables of `state`, each normalised to [0, 1] (and clipped there), as
        one `(num_senses, *batch)` array in the order of the body's `sense_names`.
        `control_dt` is the control period (the collision impulse of a contact point is its
        force times this period)."""

    @abc.abstractmethod
    def observe(self, positions: PyTree, world: World) -> Observation:
        """The observables (points, centre of mass, frame, contact) at the given positions
        (the first half of the state: observables never depend on velocities).

        `positions` may carry any number of trailing batch axes (saved times, controllers);
        each field of the returned `Observation` then has those axes trailing too (e.g.
        `com` is `(3, *batch)`, `points` `(num_points, 3, *batch)`). Write it elementwise
        over them.
        """


class AbstractBody(eqx.Module):
    """A physical body: the model (masses and springs, or rods and joints), kept apart from
    its evolving state (a `BodyState`, which `simulate` owns).

    Every body offers the same interface: `initial_state()` and `state(**named parts)` make
    states, `dynamics()` prepares it for simulation, `body_length` and `total_mass` are
    Python floats, `num_points` counts the points `Observation.points` holds, and
    `sense_names` lists its sense variables (paper 004, Table 1 and section 4.2).
    """

    @abc.abstractmethod
    def initial_state(self) -> BodyState:
        """The state at t = 0: the rest pose, at rest."""

    @abc.abstractmethod
    def state(self, **parts) -> BodyState:
        """A state made from named parts (each body documents its own); parts not given
        are those of the rest pose, at rest."""

    @abc.abstractmethod
    def dynamics(self) -> AbstractDynamics:
        """This body prepared for simulation (called once per simulation, outside the time
        loop)."""

    @property
    @abc.abstractmethod
    def num_points(self) -> int:
        """How many points `Observation.points` holds for this body."""

    @property
    @abc.abstractmethod
    def body_length(self) -> float:
        """Size of the rest pose along the body's forward axis, m (the unit of "body
        lengths")."""

    @property
    @abc.abstractmethod
    def total_mass(self) -> float:
        """Total mass, kg."""

    @property
    @abc.abstractmethod
    def sense_names(self) -> tuple[str, ...]:
        """The name of each sense variable, in the order `senses` returns them."""

    @property
    def num_senses(self) -> int:
        """How many sense variables the body has."""
        return len(self.sense_names)
