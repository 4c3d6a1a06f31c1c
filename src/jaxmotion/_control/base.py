"""Controllers (small hybrid systems that sense the body and carry state) and the families
(spaces) that sample and perturb them."""

import abc
from typing import Any, ClassVar, Generic, NamedTuple, TypeVar

import equinox as eqx
import jax
from jaxtyping import Array, Float, PRNGKeyArray, PyTree

from .._body.base import AbstractBody


class ControllerState(NamedTuple):
    """What a controller carries through a simulation, part of the simulation state (so it
    is batched, split and continued with the body's).

    - `discrete`: a pytree that changes only at control ticks (`AbstractController.update`):
        the active regime or rule, low-pass-filtered senses, a sequence's phase. `None` if
        the controller has none.
    - `continuous`: `None`, or a pair `(positions, velocities)` of pytrees with rates of
        their own (`AbstractController.rates`), integrated with the body by the same solver
        (a spring net's masses).
    """

    discrete: PyTree = None
    continuous: tuple[PyTree, PyTree] | None = None


class AbstractController(eqx.Module):
    """A controller: an equinox Module whose array fields are its parameters, and a small
    hybrid system run alongside the body (the way robotics simulators run a policy).

    A simulation first calls `on_grid(control_dt)` (the control period, for a controller
    that counts ticks) and `prepare(body)` once (outside the time loop) for whatever can be
    computed ahead (the plan), and `init(senses, plan)` for the controller's state at the
    start. Time then runs in control periods of `control_dt` (by default one step of the
    search's solver), each starting with a *control tick* at its time `t_k`:

    1. `update(t_k, state, senses, plan)` returns the state for the period from the time,
        the state and the body's senses there (normalised to [0, 1]; `None` unless the class
        sets `reads_senses`);
    2. over the period the body is driven by `actuation(t, state, plan)`, and the state's
        continuous part (if any) moves with `rates(t, state, plan)`.

    The discrete part of the state is held between ticks (zero-order hold), so `actuation`
    may switch discontinuously only through it: the adaptive solvers integrate from tick to
    tick and never see a switch inside a step. Its dependence on `t` and on the continuous
    state must be smooth. (The second paper's Figure 2 acts before it first senses: a BSR
    controller keeps rule 0 through its first tick.)

    An open-loop (time-based) controller ignores the senses: what it carries from tick to
    tick is its choice (the active regime or rule), made once per controller and tick rather
    than for every entry of the actuation it selects.

    A subclass that sets `supports_batch_last = True` promises that `init`, `update`,
    `actuation`, `rates` and `perceive` also work on a batch of controllers stacked with the
    batch as the *last* axis of every array field (and of the plan, the state and the
    senses): index only leading axes and let elementwise arithmetic broadcast. The batched
    layout then calls them once for the whole batch; otherwise it `vmap`s them. In that
    layout the time `t` is shared (a scalar) or per controller (`(batch,)`: a `Sequence`
    gives each controller of a batch its own local time).
    """

    supports_batch_last: ClassVar[bool] = False
    reads_senses: ClassVar[bool] = False

    @abc.abstractmethod
    def prepare(self, body: AbstractBody) -> Any:
        """Per-simulation precomputation (a pytree), e.g. the rest lengths of every regime.
        Raises `TypeError` or `ValueError` if the controller does not fit `body`."""

    def init(self, senses: Float[Array, " num_senses"] | None, plan: Any) -> ControllerState:
        """The state at the start (t = 0, before the first tick), given the senses of the
        starting state (`None` unless `reads_senses`). Default: no state."""
        del senses, plan
        return ControllerState()

    def update(
        self,
        t: Float[Array, ""],
        state: ControllerState,
        senses: Float[Array, " num_senses"] | None,
        plan: Any,
    ) -> ControllerState:
        """The state after the control tick at time `t` (the state for the period from `t`),
        given the body's `senses` there. Default: unchanged."""
        del t, senses, plan
        return state

    @abc.abstractmethod
    def actuation(self, t: Float[Array, ""], state: ControllerState, plan: Any) -> Any:
        """What the body's dynamics take as actuation at time `t` (for lattices, a table of
        spring rest lengths; for figures, target joint angles and a time constant)."""

    def rates(
        self, t: Float[Array, ""], state: ControllerState, plan: Any
    ) -> tuple[PyTree, PyTree] | None:
        """Time derivative of `state.continuous`, shaped like it (`None` when there is no
        continuous state, the default)."""
        del t, state, plan
        return None

    def perceive(self, t: Float[Array, ""], state: ControllerState, senses: Any, plan: Any) -> Any:
        """The sense vector the controller's decisions read at a tick at `t` with these
        `senses` (default: the senses themselves; a low-pass-filtered controller returns its
        filtered senses). Searches record it along a motion (the relevance heuristic)."""
        del t, state, plan
        return senses

    def on_grid(self, control_dt: float) -> "AbstractController":
        """This controller as run with control ticks `control_dt` seconds apart. A
        simulation calls it once, before `prepare`, with its control period; a controller
        that keeps clocks of its own (a `Sequence`'s local times, counted in whole ticks)
        records the period here. Default: the controller itself."""
        del control_dt
        return self

    def smoothed(self, width: float) -> "AbstractController":
        """The same controller with its discrete switches blended (for gradients,
        `jaxmotion.refine`); `width=0` must return the controller unchanged. Controllers
        without switches return themselves."""
        del width
        return self


C = TypeVar("C", bound=AbstractController)


class AbstractControllerSpace(eqx.Module, Generic[C]):
    """A controller family: knows how to draw random controllers and how to perturb one, with
    the distributions of the paper it comes from. Both act on one controller; `vmap` them over
    `jax.random.split(key, n)` for a population.

    A family whose mutation looks at the parent's motion (the second paper's relevance
    heuristic) sets `uses_motion = True`: searches then record the senses the parent's
    controller perceived along its motion (`Task.evaluate_sensed`) and pass them to
    `perturb` as `motion`, a `(num_samples, num_senses)` array.
    """

    uses_motion: ClassVar[bool] = False

    @abc.abstractmethod
    def sample(self, *, key: PRNGKeyArray) -> C:
        """A random controller."""

    @abc.abstractmethod
    def perturb(self, controller: C, *, key: PRNGKeyArray, motion=None) -> C:
        """A perturbed copy of `controller` (`motion`: see `uses_motion`)."""

    @property
    @abc.abstractmethod
    def family(self) -> str:
        """The family's name as configs and saved controllers spell it (e.g. `"regimes"`)."""

    def trainable(self, controller: C) -> Any:
        """Which of the controller's leaves gradient refinement may change: a pytree of bools
        shaped like the controller (an `equinox` filter spec). Default: none."""
        return jax.tree_util.tree_map(lambda _: False, controller)

    def project(self, controller: C) -> C:
        """The nearest controller within the family's bounds (applied after every gradient
        step). Default: unchanged."""
        return controller
