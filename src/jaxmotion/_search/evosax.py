"""evosax's evolution strategies (CMA-ES, OpenAI-ES, SNES, ...) as searchers on a `Task`.

The strategies search a vector of real numbers; a controller family is a pytree with discrete
parts (a regime's reflex number) and bounds. The adapter:

- draws and evaluates `size` random controllers, like the papers' searches; the best of them
  is the *template*: its discrete parts (and every part the family does not mark trainable)
  are held fixed for the whole search, and its trainable parameters are the strategy's
  initial mean;
- flattens the parameters the family marks trainable (`space.trainable`: the continuous
  ones) into the strategy's vector, each coordinate divided by a power of two near its
  spread over the random set (so one unit of `std_init` is about one spread of that
  parameter whatever its units, and the map is exact both ways);
- restores bounds on the way back by the family's `project` (clipping; a `TimeBSR`'s splits
  sorted);
- tells the strategy the negated fitness (evosax minimises, jaxmotion maximises), with NaN and
  `-inf` (a blown-up motion) ranked worst: replaced by one more than the worst finite value of
  the generation, so no non-finite number reaches the strategy's state.

evosax is an optional dependency: `pip install 'jaxmotion[evosax]'`.
"""

import inspect
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._control.base import AbstractController
from .._task import Task
from .hill_climb import (
    _check_positive_int,
    _sample,
    _start_key,
    finite_fitness,
)
from .protocol import AbstractSearcher, register

STRATEGIES = (
    "CMA_ES",
    "Sep_CMA_ES",
    "Open_ES",
    "SNES",
    "xNES",
    "PGPE",
    "SimpleES",
    "MA_ES",
    "LM_MA_ES",
)
"""The evosax strategies offered (distribution-based ones that need no learned weights or
extra arguments)."""

INSTALL = "pip install 'jaxmotion[evosax]'"


def require_evosax():
    """The `evosax.algorithms` module. **Raises:** `ImportError` naming the extra to install."""
    try:
        import evosax.algorithms as algorithms
    except ImportError as e:
        raise ImportError(
            f"the evosax searcher needs the evosax package ({e}); install it with: {INSTALL}"
        ) from None
    return algorithms


class EvosaxState(eqx.Module):
    """The whole state of an evosax search (one pytree, so it can be checkpointed).

    - `template`: the controller whose fixed (non-trainable, discrete) parts every candidate
        shares: the best of the random set.
    - `scale`: the power of two each coordinate of the strategy's vector is measured in.
    - `strategy`: the strategy's own state (evosax's dataclass; a pytree of arrays), as it
        is after asking for the next generation.
    - `pending`: the next generation's vectors, `(population, dims)`, asked when the state
        was made (`tell` asks for the next at once: CMA-ES decomposes its covariance when
        asked, once per generation).
    - `best`, `best_fitness`: the best controller evaluated so far and its fitness (`-inf`
        while none is finite).
    - `key`: the PRNG key; step `k` draws from `fold_in(key, k)`.
    - `step`: steps made after the random set.
    - `evaluations`: controllers evaluated, the random set included.
    """

    template: AbstractController
    scale: Float[Array, " dims"]
    strategy: Any
    pending: Float[Array, "population dims"]
    best: AbstractController
    best_fitness: Float[Array, ""]
    key: PRNGKeyArray
    step: Int[Array, ""]
    evaluations: Int[Array, ""]


def _check_number(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise ValueError(f"{name} = {value!r}; allowed: a finite number > 0")
    if value <= 0:
        raise ValueError(f"{name} = {value!r}; allowed: a finite number > 0")
    return float(value)


@register
class Evosax(AbstractSearcher):
    """An evosax strategy as a searcher (see the module's docstring); fitness is maximised.

    **Arguments:**

    - `strategy`: the evosax strategy's name, one of `STRATEGIES` (e.g. `"CMA_ES"`,
        `"Open_ES"`).
    - `population`: candidates per generation (evosax's `population_size`; even for
        `Open_ES` and `PGPE`, which sample in mirrored pairs).
    - `size`: random controllers drawn and evaluated first (the template is their best).
    - `std_init`: the initial step size, in units of each parameter's spread (`scale`).
    - `learning_rate`: Adam's learning rate, for the strategies that move their mean with an
        optimizer (`Open_ES`, `SNES`, `xNES`, `PGPE`, `SimpleES`); ignored by the others.

    **Raises:** `ValueError` for a bad setting, `ImportError` (naming the extra) without
    evosax, both before anything compiles.
    """

    name: ClassVar[str] = "evosax"
    strategy: str = eqx.field(static=True)
    population: int = eqx.field(static=True)
    size: int = eqx.field(static=True)
    std_init: float = eqx.field(static=True)
    learning_rate: float = eqx.field(static=True)

    def __init__(
        self,
        strategy: str = "CMA_ES",
        population: int = 32,
        size: int = 100,
        std_init: float = 0.5,
        learning_rate: float = 0.05,
    ):
        if strategy not in STRATEGIES:
            raise ValueError(
                f"strategy = {strategy!r}; allowed: one of {', '.join(map(repr, STRATEGIES))}"
            )
        self.strategy = strategy
        self.population = _check_positive_int("population", population)
        if self.population < 2:
            raise ValueError(f"population = {population!r}; allowed: an integer >= 2")
        if strategy in ("Open_ES", "PGPE") and self.population % 2:
            raise ValueError(
                f"population = {population!r}; allowed: an even number for {strategy} "
                "(it samples mirrored pairs)"
            )
        self.size = _check_positive_int("size", size)
        self.std_init = _check_number("std_init", std_init)
        self.learning_rate = _check_number("learning_rate", learning_rate)
        require_evosax()

    # -- the strategy ------------------------------------------------------------------------

    def _es(self, dims: int):
        """The evosax strategy object for vectors of `dims` numbers, and its params."""
        import optax

        cls = getattr(require_evosax(), self.strategy)
        takes = inspect.signature(cls.__init__).parameters
        kwargs: dict[str, Any] = {}
        if "optimizer" in takes:
            kwargs["optimizer"] = optax.adam(self.learning_rate)
        if "std_schedule" in takes:
            kwargs["std_schedule"] = optax.constant_schedule(self.std_init)
        es = cls(population_size=self.population, solution=jnp.zeros(dims), **kwargs)
        params = es.default_params
        if hasattr(params, "std_init"):
            params = params.replace(std_init=jnp.asarray(self.std_init, dtype=jnp.float32))
        return es, params

    # -- the protocol ------------------------------------------------------------------------

    def init(self, task: Task, *, key: PRNGKeyArray) -> tuple[EvosaxState, Float[Array, " size"]]:
        """Draw and evaluate the random set (in calls of `population`, the steps' width);
        returns the state and their fitness in the order drawn."""
        population, next_key = self.first(task, key=key)
        fitness = task.evaluate(population, chunk=self.population, key=_start_key(task, next_key))
        return self.begin(task, next_key, population, fitness), fitness

    def first(self, task: Task, *, key: PRNGKeyArray) -> tuple[AbstractController, PRNGKeyArray]:
        """The `size` random controllers of the random set and the state's key."""
        return _sample(self, task, key)

    def begin(self, task: Task, carry, candidates, fitness) -> EvosaxState:
        """The strategy started at the best of the random set (its discrete parts held from
        it, the scale of each parameter from the set's spread)."""
        return _start(self, task, candidates, fitness, carry)

    def ask(self, task: Task, state: EvosaxState) -> AbstractController:
        """The generation's `population` candidates (the strategy's vectors as controllers,
        within the family's bounds)."""
        return _ask(self, task, state)

    def start_key(self, task: Task, state: EvosaxState):
        return _start_key(task, state.key, state.step)

    def tell(
        self,
        state: EvosaxState,
        candidates: AbstractController,
        fitness: Float[Array, " population"],
        num_valid: int | None = None,
    ) -> EvosaxState:
        """Update the strategy with the generation's fitness (only the first `num_valid`
        candidates count, the rest ranked worst) and keep the best controller so far."""
        num_valid = self.population if num_valid is None else num_valid
        return _tell(self, state, candidates, fitness, jnp.asarray(num_valid, dtype=jnp.int32))

    def steps_done(self, state: EvosaxState) -> int:
        return int(state.step)

    def best(self, state: EvosaxState) -> tuple[AbstractController, float]:
        return state.best, float(state.best_fitness)

    def check_resume(self, state: EvosaxState, history) -> None:
        if history is None:
            raise ValueError("continuing from a state needs the history up to it (history=...)")
        if len(history) != int(state.evaluations):
            raise ValueError(
                f"the history has {len(history)} evaluations and the state counts "
                f"{int(state.evaluations)}; allowed: the history up to that state"
            )

    def template(self, task: Task) -> EvosaxState:
        population = eqx.filter_eval_shape(lambda: task.sample(self.size, key=jr.key(0)))
        fitness = jax.ShapeDtypeStruct((self.size,), jnp.float32)
        return eqx.filter_eval_shape(
            lambda p, f: _start(self, task, p, f, jr.key(0)), population, fitness
        )

    def plan(self, evaluations: int) -> tuple[int, int]:
        """The steps that make `evaluations` evaluations after the random set, and how many of
        the last step's count."""
        evaluations = _check_positive_int("evaluations", evaluations)
        steps = -(-evaluations // self.population)
        return steps, evaluations - (steps - 1) * self.population

    # -- the vector ----------------------------------------------------------------------------

    def to_vector(self, task: Task, state: EvosaxState, controller: AbstractController):
        """The strategy's vector of one controller (its trainable parameters over `scale`)."""
        return _flatten(task, controller) / state.scale

    def from_vector(self, task: Task, state: EvosaxState, vector) -> AbstractController:
        """The controller of one strategy vector: the template with its trainable parameters
        replaced, projected into the family's bounds."""
        return _unflatten(task, state.template, vector * state.scale)


def _selected(task: Task, controller):
    """The controller's leaves the family marks trainable (floating point), in order."""
    spec = task.space.trainable(controller)
    leaves = jax.tree_util.tree_leaves(controller)
    marks = jax.tree_util.tree_leaves(spec)
    return [
        (i, a)
        for i, (a, m) in enumerate(zip(leaves, marks, strict=True))
        if m and jnp.issubdtype(jnp.asarray(a).dtype, jnp.inexact)
    ]


def _flatten(task: Task, controller) -> jax.Array:
    return jnp.concatenate([jnp.ravel(a) for _, a in _selected(task, controller)])


def _unflatten(task: Task, template, vector) -> AbstractController:
    leaves, treedef = jax.tree_util.tree_flatten(template)
    start = 0
    for i, a in _selected(task, template):
        n = int(np.prod(jnp.shape(a), dtype=np.int64))
        leaves[i] = vector[start : start + n].reshape(jnp.shape(a)).astype(jnp.asarray(a).dtype)
        start += n
    return task.space.project(jax.tree_util.tree_unflatten(treedef, leaves))


def _pick(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


@eqx.filter_jit
def _start(search: Evosax, task: Task, population, fitness, key) -> EvosaxState:
    fitness = finite_fitness(population, fitness)
    best = jnp.argmax(fitness)  # the first on ties (all -inf: the first drawn)
    template = task.space.project(_pick(population, best))
    vectors = jax.vmap(lambda c: _flatten(task, c))(population)
    spread = jnp.std(jnp.where(jnp.isfinite(vectors), vectors, 0.0), axis=0)
    ok = jnp.isfinite(spread) & (spread > 0)
    scale = jnp.where(ok, jnp.exp2(jnp.round(jnp.log2(jnp.where(ok, spread, 1.0)))), 1.0)
    es, params = search._es(scale.shape[0])
    init_key, run_key = jr.split(key)
    strategy = es.init(init_key, _flatten(task, template) / scale, params)
    pending, strategy = es.ask(_keys(run_key, 0)[0], strategy, params)
    return EvosaxState(
        template=template,
        scale=scale,
        strategy=strategy,
        pending=pending,
        best=template,
        best_fitness=fitness[best],
        key=run_key,
        step=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(fitness.shape[0], dtype=jnp.int32),
    )


def _keys(key, step):
    """The keys of step `step`: the ask's (made when the step before was told) and the
    tell's."""
    return jr.split(jr.fold_in(key, step))


@eqx.filter_jit
def _ask(search: Evosax, task: Task, state: EvosaxState):
    del search
    return jax.vmap(lambda v: _unflatten(task, state.template, v * state.scale))(state.pending)


def minimised(fitness, valid) -> jax.Array:
    """What evosax is told for jaxmotion's `fitness` (maximised): its negation, every NaN,
    `-inf` or invalid entry replaced by one more than the worst finite value (0 if none)."""
    bad = ~jnp.isfinite(fitness) | ~valid
    loss = jnp.where(bad, 0.0, -fitness)
    worst = jnp.max(jnp.where(bad, -jnp.inf, loss))
    worst = jnp.where(jnp.isfinite(worst), worst, 0.0)
    return jnp.where(bad, worst + 1.0, loss)


@eqx.filter_jit
def _tell(search: Evosax, state: EvosaxState, candidates, fitness, num_valid) -> EvosaxState:
    es, params = search._es(state.scale.shape[0])
    valid = jnp.arange(search.population) < num_valid
    fitness = jnp.where(valid, finite_fitness(candidates, fitness), -jnp.inf)
    told = minimised(fitness, valid)
    strategy, _ = es.tell(
        _keys(state.key, state.step)[1], state.pending, told, state.strategy, params
    )
    pending, strategy = es.ask(_keys(state.key, state.step + 1)[0], strategy, params)
    i = jnp.argmax(fitness)
    better = fitness[i] > state.best_fitness  # strictly: ties keep the incumbent
    best = jax.tree_util.tree_map(
        lambda new, old: jnp.where(better, new, old), _pick(candidates, i), state.best
    )
    return EvosaxState(
        template=state.template,
        scale=state.scale,
        strategy=strategy,
        pending=pending,
        best=best,
        best_fitness=jnp.where(better, fitness[i], state.best_fitness),
        key=state.key,
        step=state.step + 1,
        evaluations=state.evaluations + num_valid,
    )
