"""Controllers and the families (spaces) that sample and perturb them."""

import abc
from typing import Any, ClassVar, Generic, TypeVar

import equinox as eqx
import jax
from jaxtyping import Array, Float, PRNGKeyArray

from .._body.base import AbstractBody


class AbstractController(eqx.Module):
    """A controller: an equinox Module whose array fields are its parameters.

    A simulation first calls `prepare(body)` once (outside the time loop) for whatever can
    be computed ahead, then `actuation(t, plan)` at every step; what it returns is what the
    body's dynamics take as actuation (for lattices, a table of spring rest lengths).

    A controller whose actuation is a cheap choice made from the time alone (which regime or
    rule is active) followed by work on the plan can say so by overriding `schedule` and
    `actuation_from`: the batched fast path then makes the choice once per controller and
    step and carries it into the step, instead of XLA repeating it for every entry of the
    actuation it selects (for a lattice, every spring of every regime table).

    A subclass that sets `supports_batch_last = True` promises that `actuation` also works on
    a batch of controllers stacked with the batch as the *last* axis of every array field
    (and of the plan): index only leading axes and let elementwise arithmetic broadcast. The
    fast batched path then calls it once for the whole batch; otherwise it is `vmap`ped.
    """

    supports_batch_last: ClassVar[bool] = False

    @abc.abstractmethod
    def prepare(self, body: AbstractBody) -> Any:
        """Per-simulation precomputation (a pytree), e.g. the rest lengths of every regime."""

    @abc.abstractmethod
    def actuation(self, t: Float[Array, ""], plan: Any) -> Any:
        """The actuation at time `t`."""

    def schedule(self, t: Float[Array, ""]) -> Any:
        """The choice `actuation` makes from the time `t` alone (e.g. the active regime's
        index): small per controller, computed once per step. Default: `t` itself."""
        return t

    def actuation_from(self, schedule: Any, plan: Any) -> Any:
        """The actuation for `schedule(t)`: `actuation_from(schedule(t), plan)` equals
        `actuation(t, plan)`. Default: `actuation(schedule, plan)` (with the default
        `schedule`, the time)."""
        return self.actuation(schedule, plan)

    def smoothed(self, width: float) -> "AbstractController":
        """The same controller with its discrete switches blended over `width` seconds, for
        gradients (`jaxmotion.refine`); `width=0` must return the controller unchanged.
        Controllers without switches return themselves."""
        del width
        return self


C = TypeVar("C", bound=AbstractController)


class AbstractControllerSpace(eqx.Module, Generic[C]):
    """A controller family: knows how to draw random controllers and how to perturb one, with
    the distributions of the paper it comes from. Both act on one controller; `vmap` them over
    `jax.random.split(key, n)` for a population."""

    @abc.abstractmethod
    def sample(self, *, key: PRNGKeyArray) -> C:
        """A random controller."""

    @abc.abstractmethod
    def perturb(self, controller: C, *, key: PRNGKeyArray) -> C:
        """A perturbed copy of `controller`."""

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
