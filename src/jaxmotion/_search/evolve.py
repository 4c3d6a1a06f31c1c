"""Generational evolution, the third paper's search ("Spring Net Controllers for Articulated
Figures", section "Artificial Evolution"), with its hand-selection hook."""

from collections.abc import Callable, Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .._control.base import AbstractController
from .._sim import execution
from .._task import Task
from .hill_climb import (
    _check_positive_int,
    _check_resume,
    _first_member,
    _population_shape,
    _sample,
    _start_key,
    finite_fitness,
    finite_members,
)
from .history import History
from .protocol import AbstractSearcher, SearchResult, drive, register
from .serial import _select

# Controllers per part (one part per device) in one compiled call. Above about 200 per device
# (measured on the snake and the Luxo lamp, 2 devices, with spring nets and with `TimeBSR` alike:
# 160 per device bitwise equal to 8, 240 not) XLA's CPU code rounds a figure's step differently,
# and a search's best then replayed alone to another motion than the one it was scored for. The
# generations therefore run in calls of this many per device (measured on the snake: 8,956
# evaluations/s against 11,563/s in one call of 1,600).
SHARE = 160

SURVIVOR, OFFSPRING, NEW = 0, 1, 2
"""Where a member of a generation came from (`EvolveState.origin`)."""


class EvolveState(eqx.Module):
    """The whole state of a generational evolution (one pytree, so it can be checkpointed).

    - `population`: the current generation, stacked along a leading axis, best first.
    - `fitness`: their fitness, descending (`-inf` for a controller that blew up).
    - `origin`: where each came from: `SURVIVOR` (0, kept from the generation before with
        its fitness), `OFFSPRING` (1, a mutated copy of a survivor) or `NEW` (2, random);
        the first generation is all `NEW`.
    - `parent`: for offspring, the index of their parent in the generation before (as it
        was ordered when `ask` was called), for survivors their own index there; -1 for
        new nets.
    - `key`: the PRNG key; generation `g` draws from `jax.random.fold_in(key, g)`.
    - `generation`: how many generations have been made after the first.
    - `evaluations`: how many controllers have been evaluated, the first generation
        included.
    """

    population: AbstractController
    fitness: Float[Array, " size"]
    origin: Int[Array, " size"]
    parent: Int[Array, " size"]
    key: PRNGKeyArray
    generation: Int[Array, ""]
    evaluations: Int[Array, ""]


@register
class Evolve(AbstractSearcher):
    """The third paper's generational algorithm, as pure init / pin / ask / tell functions.

    A generation of `size` controllers (`size` a multiple of 5), ranked by fitness, makes
    the next one:

    1. the best `size / 5` survive, keeping their fitness (they are not evaluated again);
    2. each survivor makes 3 offspring, each a copy hit by a number of mutations drawn
        uniformly from `1..mutations` (each mutation one call of the family's `perturb`:
        for `SpringNetSpace`, the paper's four kinds in its shares);
    3. `size / 5` new random controllers are drawn.

    The `4 size / 5` offspring and new controllers are evaluated in one call of
    `task.evaluate` (`tell` merges them with the survivors and ranks the whole generation;
    ties rank survivors first); that call runs them in compiled calls of `SHARE`
    controllers per device, so that each is scored bitwise as it is when replayed alone.

    **Hand selection** (the paper's manual selection): `pin(state, indices)` moves chosen
    members to the front, so that they survive the next generation whatever their
    fitness (at most `size / 5`; the best of the rest fill the other places). Fitness is
    maximised.

    `ask` and `tell` are jitted; between them the driver calls `task.evaluate`. The first
    generation is evaluated the same way, so that every call shares one compilation.
    """

    name: ClassVar[str] = "evolve"
    size: int = eqx.field(static=True)
    mutations: int = eqx.field(static=True)

    def __init__(self, size: int = 2000, mutations: int = 3):
        size = _check_positive_int("size", size)
        if size % 5:
            raise ValueError(
                f"size = {size!r}; allowed: a multiple of 5 (a fifth survive and a fifth are new)"
            )
        self.size = size
        self.mutations = _check_positive_int("mutations", mutations)

    @property
    def survivors(self) -> int:
        """How many survive each generation (`size / 5`)."""
        return self.size // 5

    @property
    def chunk(self) -> int:
        """The controllers of one compiled call: a generation's `4 size / 5`, or `SHARE`
        per device if fewer (the first generation runs in calls of the same size)."""
        return min(self.batch, SHARE * execution.workers())

    @property
    def batch(self) -> int:
        """How many controllers each generation evaluates (`4 size / 5`)."""
        return self.size - self.survivors

    def init(self, task: Task, *, key: PRNGKeyArray) -> tuple[EvolveState, Float[Array, " size"]]:
        """Draw and evaluate the first generation. Returns the state and the fitness of the
        controllers in the order they were drawn."""
        population, next_key = self.first(task, key=key)
        starts = _start_key(task, next_key)
        fitness = task.evaluate(population, chunk=self.chunk, key=starts)
        return self.begin(task, next_key, population, fitness), fitness

    def first(self, task: Task, *, key: PRNGKeyArray) -> tuple[AbstractController, PRNGKeyArray]:
        """The `size` random controllers of the first generation and the state's key."""
        return _sample(self, task, key)

    def begin(self, task: Task, carry, candidates, fitness) -> EvolveState:
        """The first generation ranked by fitness (stably), every member new."""
        del task
        return _first(candidates, fitness, carry)

    def pin(self, state: EvolveState, indices: Sequence[int] | Int[ArrayLike, " k"]) -> EvolveState:
        """The state with the members `indices` (into `state.population`) moved to the front
        (in the given order), the rest after them by fitness: they survive the next
        generation. At most `size / 5` of them.

        **Raises:** `ValueError` for too many, repeated or out-of-range indices."""
        picked = [int(i) for i in np.asarray(indices, dtype=np.int64).reshape(-1)]
        if len(picked) > self.survivors:
            raise ValueError(
                f"pin: {len(picked)} members; allowed: at most size / 5 = {self.survivors}"
            )
        if len(set(picked)) != len(picked) or any(not 0 <= i < self.size for i in picked):
            raise ValueError(
                f"pin: indices {picked!r}; allowed: distinct indices in 0..{self.size - 1}"
            )
        rest = [i for i in range(self.size) if i not in set(picked)]
        return _reorder(state, jnp.asarray(picked + rest, dtype=jnp.int32))

    def ask(self, task: Task, state: EvolveState) -> AbstractController:
        """The `4 size / 5` controllers to evaluate next: 3 offspring of each of the first
        `size / 5` members (the survivors), then `size / 5` new random ones."""
        return _ask(self, task, state)

    def tell(
        self, state: EvolveState, children: AbstractController, fitness: Float[Array, " batch"]
    ) -> EvolveState:
        """The next generation: the survivors (with their fitness) and the evaluated
        `children`, ranked by fitness."""
        return _tell(self, state, children, fitness)

    def step(self, task: Task, state: EvolveState) -> tuple[EvolveState, Float[Array, " batch"]]:
        """ask, evaluate (one call), tell. Returns the new state and the fitness of this
        generation's `4 size / 5` evaluations."""
        return super().step(task, state)

    def evaluate(self, task: Task, state: EvolveState, candidates):
        starts = _start_key(task, state.key, state.generation)
        return task.evaluate(candidates, chunk=self.chunk, key=starts), {}

    def steps_done(self, state: EvolveState) -> int:
        return int(state.generation)

    def best(self, state: EvolveState) -> tuple[AbstractController, float]:
        return _first_member(state)

    def template(self, task: Task) -> EvolveState:
        x = jax.ShapeDtypeStruct((), jnp.float32)
        return EvolveState(_population_shape(task), x, x, x, x, x, x)

    def check_resume(self, state: EvolveState, history) -> None:
        if state.fitness.shape != (self.size,):
            raise ValueError(
                f"evolve: the state holds {state.fitness.shape[0]} controllers; allowed: size = "
                f"{self.size}"
            )
        if history is not None:
            _check_resume(state, history, (self.size,), int(state.evaluations))


@eqx.filter_jit
def _first(population, fitness, key) -> EvolveState:
    fitness = finite_fitness(population, fitness)
    order = jnp.argsort(-fitness, stable=True)
    size = fitness.shape[0]
    return EvolveState(
        population=jax.tree_util.tree_map(lambda a: a[order], population),
        fitness=fitness[order],
        origin=jnp.full((size,), NEW, dtype=jnp.int32),
        parent=jnp.full((size,), -1, dtype=jnp.int32),
        key=key,
        generation=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(size, dtype=jnp.int32),
    )


@eqx.filter_jit
def _reorder(state: EvolveState, order) -> EvolveState:
    return eqx.tree_at(
        lambda s: (s.population, s.fitness, s.origin, s.parent),
        state,
        (
            jax.tree_util.tree_map(lambda a: a[order], state.population),
            state.fitness[order],
            state.origin[order],
            state.parent[order],
        ),
    )


@eqx.filter_jit
def _ask(search: Evolve, task: Task, state: EvolveState):
    s = search.survivors
    count_key, mutate_key, new_key = jr.split(jr.fold_in(state.key, state.generation), 3)
    parents = jax.tree_util.tree_map(lambda a: jnp.repeat(a[:s], 3, axis=0), state.population)
    counts = jr.randint(count_key, (3 * s,), 1, search.mutations + 1)

    def offspring(parent, count, key):
        def one(i, child):
            mutated = task.space.perturb(child, key=jr.fold_in(key, i))
            return jax.tree_util.tree_map(lambda a, b: jnp.where(i < count, a, b), mutated, child)

        return jax.lax.fori_loop(0, search.mutations, one, parent)

    children = jax.vmap(offspring)(parents, counts, jr.split(mutate_key, 3 * s))
    new = task.sample(s, key=new_key)
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), children, new)


@eqx.filter_jit
def _tell(search: Evolve, state: EvolveState, children, fitness) -> EvolveState:
    s = search.survivors
    survivors = jax.tree_util.tree_map(lambda a: a[:s], state.population)
    # A child with a parameter that is not finite (only an extreme parent or space makes
    # one) scores -inf and is replaced by a copy of its parent (a new net: by survivor 0),
    # so that no NaN enters the population.
    fitness = finite_fitness(children, fitness)
    finite = finite_members(children)
    source = jnp.concatenate([jnp.repeat(jnp.arange(s), 3), jnp.zeros(s, dtype=jnp.int32)])
    children = jax.tree_util.tree_map(
        lambda c, p: _select(finite, c, p[source]), children, survivors
    )
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), survivors, children)
    scores = jnp.concatenate([state.fitness[:s], fitness])
    origin = jnp.concatenate(
        [
            jnp.full((s,), SURVIVOR, dtype=jnp.int32),
            jnp.full((3 * s,), OFFSPRING, dtype=jnp.int32),
            jnp.full((s,), NEW, dtype=jnp.int32),
        ]
    )
    parent = jnp.concatenate(
        [
            jnp.arange(s, dtype=jnp.int32),
            jnp.repeat(jnp.arange(s, dtype=jnp.int32), 3),
            jnp.full((s,), -1, dtype=jnp.int32),
        ]
    )
    # Stable sort on -fitness: among equal fitness the survivors (listed first) rank higher.
    order = jnp.argsort(-scores, stable=True)
    return EvolveState(
        population=jax.tree_util.tree_map(lambda a: a[order], both),
        fitness=scores[order],
        origin=origin[order],
        parent=parent[order],
        key=state.key,
        generation=state.generation + 1,
        evaluations=state.evaluations + search.batch,
    )


def evolve(
    task: Task,
    *,
    key: PRNGKeyArray,
    generations: int = 20,
    size: int = 2000,
    mutations: int = 3,
    state: EvolveState | None = None,
    select: Callable[[EvolveState], Sequence[int] | None] | None = None,
    progress: bool = False,
    callback: Callable[[EvolveState, History], None] | None = None,
    history: History | None = None,
) -> SearchResult:
    """The third paper's generational evolution on `task` (see `Evolve`); fitness is
    maximised.

    **Arguments:**

    - `task`: what to optimise.
    - `key`: the PRNG key (the same key gives the same search).
    - `generations`: how many generations this call makes, the random first one included
        (the paper's largest run: 20 generations of 2,000, which evaluates 2,000 + 19 x
        1,600 = 32,400 controllers, the survivors keeping their fitness); continuing a
        `state`, every one of them is new.
    - `size`: the population, a multiple of 5 (2,000 in the paper's largest run).
    - `mutations`: each offspring is hit by `1..mutations` mutations (uniformly).
    - `state`: continue from this state (an earlier result's `state`) instead of drawing
        a first generation; `key` is then not used.
    - `select`: the hand-selection hook: called with the state before each generation is
        made, it returns the indices (into `state.population`) of members to keep whatever
        their fitness (`Evolve.pin`), or `None`.
    - `progress`: show a tqdm progress bar (off by default: the library does not print).
    - `callback`: called after every generation with the state and that generation's
        `History` (the first generation's too).
    - `history`: with `state`, the `History` of every evaluation up to it (a checkpoint),
        put before this call's in the result: continuing an interrupted evolution with the
        generations it had left gives bitwise the uninterrupted result.

    **Returns:** a `SearchResult`; its history has every evaluation (`size` for the first
    generation, then `4 size / 5` per generation; survivors are not evaluated again), with
    `step` the generation that made it (0 for the first).
    """
    if state is None or generations != 0:  # a continued state may have none left to make
        generations = _check_positive_int("generations", generations)
    search = Evolve(size=size, mutations=mutations)
    if state is None:
        steps = generations - 1  # after the random first generation
    else:
        search.check_resume(state, history)
        steps = int(state.generation) + generations

    def pin(state: EvolveState) -> EvolveState:
        picked = select(state) if select is not None else None
        return search.pin(state, picked) if picked is not None and len(picked) else state

    return drive(
        search,
        task,
        key=key,
        steps=steps,
        progress=progress,
        callback=callback,
        before_step=pin,
        state=state,
        history=history,
    )
