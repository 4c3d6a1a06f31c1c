"""Parallel hill climbing, the first paper's search (Figure 4)."""

import math
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._control.base import AbstractController
from .._task import Task
from .history import History
from .protocol import AbstractSearcher, SearchResult, drive, register


class HillClimbState(eqx.Module):
    """The whole state of a parallel hill climb (one pytree, so it can be checkpointed).

    - `population`: the search set, controllers stacked along a leading axis, best first.
    - `fitness`: their fitness, descending.
    - `key`: the PRNG key of the next step.
    - `step`: how many steps have been taken.
    - `evaluations`: how many controllers have been evaluated, the initial set included.
    """

    population: AbstractController
    fitness: Float[Array, " size"]
    key: PRNGKeyArray
    step: Int[Array, ""]
    evaluations: Int[Array, ""]


def _check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{name} = {value!r}; allowed: an integer >= 1")
    return int(value)


def _check_count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise ValueError(f"{name} = {value!r}; allowed: an integer >= 0")
    return int(value)


@register
class ParallelHillClimb(AbstractSearcher):
    """Parallel hill climbing (first paper, Figure 4), as pure init / ask / tell functions.

    The search set holds `size` controllers ranked by fitness. Each step draws `batch` members
    uniformly (with replacement), perturbs each (the family's `perturb`, Table 2 for
    `Regimes`), evaluates the perturbed copies in one call, inserts them by rank and drops the
    lowest-ranked, so the set keeps its size. Ties rank the older controller first. With
    `batch=1` this is exactly the paper's algorithm; a larger batch draws all its members
    from the set as it was before the step. Fitness is maximised.

    `ask` and `tell` are jitted; between them the driver calls `task.evaluate`, so the
    simulation compiles once per batch size and is shared by every search with that shape
    (the initial set is evaluated in batches of the same size). `step` composes the three.
    """

    name: ClassVar[str] = "parallel_hill_climb"
    size: int = eqx.field(static=True)
    batch: int = eqx.field(static=True)

    def __init__(self, size: int = 100, batch: int = 1):
        self.size = _check_positive_int("size", size)
        self.batch = _check_positive_int("batch", batch)

    def init(
        self, task: Task, *, key: PRNGKeyArray
    ) -> tuple[HillClimbState, Float[Array, " size"]]:
        """Draw and evaluate the initial search set. Returns the state and the fitness of
        the initial controllers in the order they were drawn."""
        population, next_key = self.first(task, key=key)
        # In calls of the search's batch size, so that the steps reuse this compilation.
        starts = _start_key(task, next_key)
        fitness = task.evaluate(population, chunk=self.batch, key=starts)
        return self.begin(task, next_key, population, fitness), fitness

    def first(self, task: Task, *, key: PRNGKeyArray) -> tuple[AbstractController, PRNGKeyArray]:
        """The `size` random controllers of the initial set and the state's key."""
        return _sample(self, task, key)

    def begin(self, task: Task, carry, candidates, fitness) -> HillClimbState:
        """The initial set ranked by fitness (stably)."""
        del task
        return _rank(candidates, fitness, carry)

    def ask(self, task: Task, state: HillClimbState) -> AbstractController:
        """The `batch` perturbed copies of randomly drawn members to evaluate next."""
        return _ask(self, task, state)

    def tell(
        self,
        state: HillClimbState,
        children: AbstractController,
        fitness: Float[Array, " batch"],
        num_valid: int | Int[Array, ""] | None = None,
    ) -> HillClimbState:
        """Insert evaluated children by rank and drop the lowest-ranked. Only the first
        `num_valid` children (default all) are inserted: the rest are discarded (used to end
        a search on an exact evaluation count without a new compilation)."""
        if num_valid is None:
            num_valid = self.batch
        return _tell(self, state, children, fitness, jnp.asarray(num_valid, dtype=jnp.int32))

    def step(
        self, task: Task, state: HillClimbState, num_valid: int | Int[Array, ""] | None = None
    ) -> tuple[HillClimbState, Float[Array, " batch"]]:
        """ask, evaluate, tell. Returns the new state and the fitness of this step's `batch`
        evaluations."""
        return super().step(task, state, num_valid=num_valid)

    def start_key(self, task: Task, state: HillClimbState):
        return _start_key(task, state.key, state.step)

    def steps_done(self, state: HillClimbState) -> int:
        return int(state.step)

    def best(self, state: HillClimbState) -> tuple[AbstractController, float]:
        return _first_member(state)

    def check_resume(self, state: HillClimbState, history) -> None:
        _check_resume(state, history, (self.size,), int(state.evaluations))

    def template(self, task: Task) -> HillClimbState:
        x = jax.ShapeDtypeStruct((), jnp.float32)
        return HillClimbState(_population_shape(task), x, x, x, x)

    def plan(self, evaluations: int) -> tuple[int, int]:
        """The steps that make `evaluations` evaluations after the initial set, and how many
        of the last step's count."""
        evaluations = _check_positive_int("evaluations", evaluations)
        steps = math.ceil(evaluations / self.batch)
        return steps, evaluations - (steps - 1) * self.batch


# The random starts of a task with robustness (`Task.robustness`) draw from
# `fold_in(fold_in(key, _STARTS), step)`, apart from the steps' picks and perturbations.
_STARTS = 2**31 - 1


def _start_key(task: Task, key, step=None):
    """The key of the random starts of the initial set (`step` None) or of a step (shared
    by its evaluations; with `Robustness.common`, the initial set's at every step), `None`
    without robustness. `key` is the state's."""
    if task.robustness is None:
        return None
    if step is None or task.robustness.common:
        return jr.fold_in(key, _STARTS)
    return _fold(key, step)


@eqx.filter_jit
def _fold(key, step):
    return jr.fold_in(jr.fold_in(key, _STARTS), step)


@eqx.filter_jit
def _sample(search: ParallelHillClimb, task: Task, key):
    sample_key, next_key = jr.split(key)
    return task.sample(search.size, key=sample_key), next_key


def finite_members(population) -> jax.Array:
    """Whether every parameter of each controller of `population` (leading axis) is
    finite."""
    leaves = jax.tree_util.tree_leaves(population)
    ok = jnp.ones(leaves[0].shape[0], dtype=bool)
    for a in leaves:
        if jnp.issubdtype(a.dtype, jnp.inexact):
            ok &= jnp.all(jnp.isfinite(a.reshape(a.shape[0], -1)), axis=1)
    return ok


def finite_fitness(population, fitness) -> jax.Array:
    """`fitness` with `-inf` (the worst) for every NaN and for every controller of
    `population` (leading axis) with a parameter that is not finite: such a controller can
    never displace a finite one, and no NaN enters a search's state or history."""
    return jnp.where(~jnp.isnan(fitness) & finite_members(population), fitness, -jnp.inf)


@eqx.filter_jit
def _rank(population, fitness, key) -> HillClimbState:
    fitness = finite_fitness(population, fitness)
    order = jnp.argsort(-fitness, stable=True)
    return HillClimbState(
        population=jax.tree_util.tree_map(lambda a: a[order], population),
        fitness=fitness[order],
        key=key,
        step=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(fitness.shape[0], dtype=jnp.int32),
    )


@eqx.filter_jit
def _ask(search: ParallelHillClimb, task: Task, state: HillClimbState):
    pick_key, perturb_key = jr.split(jr.fold_in(state.key, state.step))
    picks = jr.randint(pick_key, (search.batch,), 0, search.size)
    parents = jax.tree_util.tree_map(lambda a: a[picks], state.population)
    return jax.vmap(lambda p, k: task.space.perturb(p, key=k))(
        parents, jr.split(perturb_key, search.batch)
    )


@eqx.filter_jit
def _tell(search: ParallelHillClimb, state: HillClimbState, children, fitness, num_valid):
    valid = jnp.arange(search.batch) < num_valid
    fitness = finite_fitness(children, fitness)
    ranked = jnp.concatenate([state.fitness, jnp.where(valid, fitness, -jnp.inf)])
    # Stable sort on -fitness: among equal fitness the incumbents (listed first) rank higher.
    keep = jnp.argsort(-ranked, stable=True)[: search.size]
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), state.population, children)
    return HillClimbState(
        population=jax.tree_util.tree_map(lambda a: a[keep], both),
        fitness=ranked[keep],
        key=state.key,
        step=state.step + 1,
        evaluations=state.evaluations + num_valid,
    )


def parallel_hill_climb(
    task: Task,
    *,
    key: PRNGKeyArray,
    evaluations: int = 25_000,
    size: int = 100,
    batch: int = 1,
    progress: bool = False,
    callback: Callable[[HillClimbState, History], None] | None = None,
    state: HillClimbState | None = None,
    history: History | None = None,
) -> SearchResult:
    """Parallel hill climbing (first paper, Figure 4) on `task`; fitness is maximised.

    **Arguments:**

    - `task`: what to optimise.
    - `key`: the PRNG key (the same key gives the same search).
    - `evaluations`: how many perturbed controllers to evaluate (the paper's 25,000
        iterations), after the `size` random controllers of the initial set.
    - `size`: the search set (100 in the paper).
    - `batch`: members perturbed and evaluated per step, in one call. `batch=1` is exactly
        the paper's algorithm; larger batches use the machine far better.
    - `progress`: show a tqdm progress bar (off by default: the library does not print).
    - `callback`: called after every step with the state and that step's `History`.
    - `state`, `history`: continue an interrupted search from a state its `callback` was
        given and the `History` of every evaluation up to it (a checkpoint); with the same
        settings the result is bitwise the uninterrupted search's. `key` is then not used.

    **Returns:** a `SearchResult`; its history has `size + evaluations` entries.
    """
    search = ParallelHillClimb(size=size, batch=batch)
    steps, last = search.plan(evaluations)
    return drive(
        search,
        task,
        key=key,
        steps=steps,
        last=last,
        progress=progress,
        callback=callback,
        state=state,
        history=history,
    )


def _check_resume(state, history, shape: tuple[int, ...], evaluations: int) -> None:
    """A state and history to continue from: the search's shape, one entry of history per
    evaluation the state counts."""
    if history is None:
        raise ValueError("continuing from a state needs the history up to it (history=...)")
    if tuple(state.fitness.shape) != shape:
        raise ValueError(
            f"the state holds fitness of shape {tuple(state.fitness.shape)}; allowed: {shape} "
            "(the search's settings)"
        )
    if len(history) != evaluations:
        raise ValueError(
            f"the history has {len(history)} evaluations and the state counts {evaluations}; "
            "allowed: the history up to that state"
        )


def _population_shape(task: Task):
    """The shapes and dtypes of a population of `task` (one member), drawing nothing."""
    return eqx.filter_eval_shape(lambda: task.sample(1, key=jr.key(0)))


def _first_member(state) -> tuple[AbstractController, float]:
    """The first member of a state that keeps its population ranked, best first
    (`population`, `fitness`), and its fitness."""
    return jax.tree_util.tree_map(lambda a: a[0], state.population), float(state.fitness[0])
