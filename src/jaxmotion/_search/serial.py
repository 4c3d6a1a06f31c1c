"""Serial search, the second paper's search (Figure 3): climbers that mutate and keep the
mutant if it is better, with the worse half reseeded from the better half every few
generations."""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._control.base import AbstractController
from .._sim.compile import simulation_jit
from .._sim.execution import batch_size, padded, share
from .._task import Task
from .hill_climb import (
    _STARTS,
    _check_count,
    _check_positive_int,
    _check_resume,
    _population_shape,
    finite_fitness,
)
from .history import History
from .protocol import AbstractSearcher, SearchResult, drive, register


class SerialSearchState(eqx.Module):
    """The whole state of a serial search over one or more independent seeds (one pytree, so
    it can be checkpointed).

    - `population`: the climbers, stacked along leading axes `(seeds, climbers)`.
    - `fitness`: their fitness, `(seeds, climbers)`; `-inf` for a controller that blew up.
    - `key`: one PRNG key per seed, `(seeds,)`; generation `g` of seed `s` draws from
        `jax.random.fold_in(key[s], g)`.
    - `generation`: how many generations have been made.
    - `evaluations`: how many controllers each seed has evaluated, the initial set included.
    - `motion`: for a family whose mutation looks at the parent's motion (`uses_motion`),
        the senses each climber perceived along its motion, `(seeds, climbers, samples,
        senses)`; otherwise `None`.
    - `archive`, `archive_fitness`: with `SerialSearch(archive=K)`, each seed's `K` fittest
        controllers it has held as climbers (the initial set, enrichment rounds, kept
        mutants; reseeding makes copies, nothing new), best first (stably: on ties the one
        held first), `(seeds, K)`; an unfilled place has fitness `-inf`. Otherwise `None`.

    Seed `s` of a batched state, `state.seed(s)`, is bitwise the state of that seed run
    alone.
    """

    population: AbstractController
    fitness: Float[Array, "seeds climbers"]
    key: PRNGKeyArray
    generation: Int[Array, ""]
    evaluations: Int[Array, ""]
    motion: Float[Array, "seeds climbers samples senses"] | None = None
    archive: AbstractController | None = None
    archive_fitness: Float[Array, "seeds archive"] | None = None

    @property
    def num_seeds(self) -> int:
        """How many independent runs the state holds."""
        return self.fitness.shape[0]

    def seed(self, s: int) -> "SerialSearchState":
        """The state of seed number `s` of this batch (the `s`-th along the leading axis),
        with a seeds axis of length 1: the state a run of that seed alone would have."""
        per_seed = lambda st: (
            st.population,
            st.fitness,
            st.key,
            st.motion,
            st.archive,
            st.archive_fitness,
        )
        return eqx.tree_at(
            per_seed,
            self,
            jax.tree_util.tree_map(lambda a: a[s : s + 1], per_seed(self)),
            is_leaf=lambda x: x is None,
        )


@register
class SerialSearch(AbstractSearcher):
    """Serial search (second paper, Figure 3), as pure init / ask / tell functions.

    Each of `climbers` controllers is mutated once per generation (the family's `perturb`),
    and the mutant replaces it only if its fitness is strictly greater, so a climber's
    fitness never decreases and a blown-up mutant (`-inf`) is never kept. After every
    `reseed_every`-th generation the set is ranked by fitness (stably: ties keep the lower
    index first) and the worse `climbers // 2` are replaced by copies of the best
    `climbers // 2`, fitness included (no re-evaluation): the state then lists the ranked
    set, best first, followed by the copies in the same order. Fitness is maximised.

    Several independent runs (seeds) are searched at once: their climbers form one batch of
    `seeds * climbers` controllers, seed-major, which `ask` returns and `tell` takes, so each
    generation is one `task.evaluate` call. The initial set is evaluated in one call of the
    same width, so the simulation compiles once. Seed `s` is driven by
    `jax.random.fold_in(key, s)` alone, and evaluation is independent of the batch, so a
    seed gives bitwise the same search whether run alone or among others.

    A family whose mutation looks at the parent's motion (`space.uses_motion`, the second
    paper's relevance heuristic) gets it: every evaluation also records the senses each
    controller perceived at the saved times (`Task.evaluate_sensed`), the state keeps them
    with each climber, and `ask` hands each climber's to its mutation. `enrich` rounds of the
    heuristic reinitialisation (`space.reinitialise`) then enrich the initial set, each round
    evaluated and kept whatever its fitness (section 4.2: "applying three rounds of this
    mutation operation to the first set ... enriching the initial population").

    `ask` and `tell` are jitted; `step` composes ask, `task.evaluate` and tell.

    With `archive = K` the state also keeps each seed's `K` fittest controllers ever held as
    climbers (`SerialSearchState.archive`), which `jaxmotion.fittest` then reads instead of
    the final climbers: the choice set of an accurate replay (`[search]
    accurate_candidates`). The climbers of a chaotic motion (a cartwheel) are ten fits to
    one step's rounding; the motions held on the way there are many more, and some of them
    survive an accurate integrator. The search itself is unchanged, bitwise.

    **Arguments:**

    - `climbers`: controllers per seed (the paper's C = 10).
    - `reseed_every`: generations between reseedings (the paper's R = 200).
    - `enrich`: rounds of relevance-heuristic reinitialisation of the initial set (0: none).
    - `seeds`, `seed_offset`: the independent runs `init` draws by default (seeds
        `seed_offset, ..., seed_offset + seeds - 1`).
    - `archive`: how many of the fittest controllers held to keep per seed (0: none).
    """

    name: ClassVar[str] = "serial_search"
    per_run: ClassVar[bool] = True
    climbers: int = eqx.field(static=True)
    reseed_every: int = eqx.field(static=True)
    enrich: int = eqx.field(static=True)
    seeds: int = eqx.field(static=True)
    seed_offset: int = eqx.field(static=True)
    archive: int = eqx.field(static=True)

    def __init__(
        self,
        climbers: int = 10,
        reseed_every: int = 200,
        enrich: int = 0,
        seeds: int = 1,
        seed_offset: int = 0,
        archive: int = 0,
    ):
        self.climbers = _check_positive_int("climbers", climbers)
        self.reseed_every = _check_positive_int("reseed_every", reseed_every)
        self.enrich = _check_count("enrich", enrich)
        self.seeds = _check_positive_int("seeds", seeds)
        self.seed_offset = _check_count("seed_offset", seed_offset)
        self.archive = _check_count("archive", archive)

    def init(
        self,
        task: Task,
        *,
        key: PRNGKeyArray,
        seeds: int | None = None,
        seed_offset: int | None = None,
    ) -> tuple[SerialSearchState, Float[Array, "rounds seeds climbers"]]:
        """Draw and evaluate the initial climbers of seeds `seed_offset, ...,
        seed_offset + seeds - 1` (and enrich them, `enrich` rounds); seed `s` draws from
        `jax.random.fold_in(key, s)`. `seeds`, `seed_offset`: default the searcher's.

        **Returns:** the state and the fitness of every initial evaluation,
        `(1 + enrich, seeds, climbers)`: the random set, then each enrichment round.
        """
        seeds = _check_positive_int("seeds", self.seeds if seeds is None else seeds)
        seed_offset = _check_count(
            "seed_offset", self.seed_offset if seed_offset is None else seed_offset
        )
        if self.enrich and not hasattr(task.space, "reinitialise"):
            raise ValueError(
                f"enrich = {self.enrich}: the {task.space.family!r} family has no relevance "
                "heuristic to enrich with (allowed: enrich = 0)"
            )
        population, keys = _sample(task, key, jnp.arange(seeds) + seed_offset, self.climbers)
        starts = _start_keys(task, keys, self.climbers, 0, 0)
        fitness, motion = _evaluate(task, population, starts)
        state = self.begin(task, keys, population, fitness, motion=motion)
        rounds = [state.fitness]
        for k in range(self.enrich):
            candidates = _enriched(task, state, k)
            starts = _start_keys(task, keys, self.climbers, 1, k)
            fitness, motion = _evaluate(task, candidates, starts)
            state = _replace(state, candidates, fitness, motion)
            rounds.append(state.fitness)
        return state, jnp.stack(rounds)

    def first(self, task: Task, *, key: PRNGKeyArray) -> tuple[AbstractController, Any]:
        """The random climbers of every seed (seed-major along one axis) and each seed's
        key."""
        seeds = jnp.arange(self.seeds) + self.seed_offset
        return _sample(task, key, seeds, self.climbers)

    def begin(self, task: Task, carry, candidates, fitness, motion=None) -> SerialSearchState:
        """The climbers of each seed with their fitness (and their motion, for a family
        whose mutation uses it); the `enrich` rounds come after, in `init`."""
        del task
        return _start(candidates, fitness, carry, motion, self.archive)

    def ask(self, task: Task, state: SerialSearchState) -> AbstractController:
        """This generation's mutant of every climber: `seeds * climbers` controllers along
        one leading axis, seed-major (ready for `task.evaluate`)."""
        return _ask(task, state)

    def tell(
        self,
        state: SerialSearchState,
        mutants: AbstractController,
        fitness: Float[Array, " batch"],
        motion: Float[Array, "batch samples senses"] | None = None,
    ) -> SerialSearchState:
        """Replace every climber whose mutant has strictly greater fitness (NaN and `-inf`
        never do), then reseed if this generation is a multiple of `reseed_every`.
        `mutants` and `fitness` are seed-major along one axis of `seeds * climbers`, as `ask`
        and `task.evaluate` give them; `fitness` may also come shaped `(seeds, climbers)`.
        `motion`: the mutants' perceived senses (`Task.evaluate_sensed`), for a state that
        keeps them."""
        if (motion is None) != (state.motion is None):
            raise ValueError(
                "tell needs the mutants' motion exactly when the state keeps motions "
                "(the family's uses_motion)"
            )
        return _tell(
            state, mutants, fitness, motion, jnp.asarray(self.reseed_every, dtype=jnp.int32)
        )

    def step(
        self, task: Task, state: SerialSearchState
    ) -> tuple[SerialSearchState, Float[Array, "seeds climbers"]]:
        """ask, evaluate, tell. Returns the new state and the fitness of this generation's
        mutants, `(seeds, climbers)`."""
        new, fitness = super().step(task, state)
        return new, fitness.reshape(state.fitness.shape)

    def evaluate(self, task: Task, state: SerialSearchState, candidates):
        """The mutants' fitness, and their motion for a family whose mutation uses it."""
        starts = _start_keys(task, state.key, state.fitness.shape[1], 2, state.generation)
        fitness, motion = _evaluate(task, candidates, starts)
        return fitness, {"motion": motion}

    def steps_done(self, state: SerialSearchState) -> int:
        return int(state.generation)

    def runs(self, state: SerialSearchState) -> int:
        return state.num_seeds

    def best(self, state: SerialSearchState) -> tuple[AbstractController, float]:
        bests, best_fitness, _ = _split(state)
        winner = int(np.argmax(np.asarray(best_fitness)))
        return bests[winner], float(best_fitness[winner])

    def template(self, task: Task) -> SerialSearchState:
        x = jax.ShapeDtypeStruct((), jnp.float32)
        motion = x if type(task.space).uses_motion else None
        population = _population_shape(task)
        archive = (population, x) if self.archive else (None, None)
        return SerialSearchState(population, x, x, x, x, motion, *archive)

    def check_resume(self, state: SerialSearchState, history) -> None:
        _rounds(state, history, state.num_seeds, self.climbers)

    def result(self, state: SerialSearchState, runs: list[History]) -> "SerialSearchResult":
        bests, best_fitness, states = _split(state)
        results = [
            SearchResult(
                best=bests[i],
                best_fitness=float(best_fitness[i]),
                history=runs[i],
                state=states[i],
            )
            for i in range(len(runs))
        ]
        winner = int(np.argmax([r.best_fitness for r in results]))
        return SerialSearchResult(
            best=results[winner].best,
            best_fitness=results[winner].best_fitness,
            history=results[winner].history,
            state=state,
            seed=self.seed_offset + winner,
            runs=tuple(results),
        )


def _evaluate(task: Task, population, starts=None):
    """Fitness, and the perceived senses when the family's mutation uses the motion
    (`starts`: the keys of the random starts of a task with robustness)."""
    if type(task.space).uses_motion:
        return task.evaluate_sensed(population, key=starts)
    return task.evaluate(population, key=starts), None


# Random starts (`Task.robustness`) draw from a stream of each seed's key apart from its
# mutations: stream 0 the initial set, 1 the enrichment rounds, 2 the generations.


def _start_keys(task: Task, keys, climbers: int, stream: int, index):
    """The key of the random starts of every controller of one evaluation (seed-major),
    `None` without robustness: all the climbers of seed `s` share
    `fold_in(fold_in(fold_in(keys[s], _STARTS), stream), index)`, so they compete from the
    same starts, and a seed draws them alike alone or among others."""
    if task.robustness is None:
        return None
    if task.robustness.common:  # the initial set's starts, for every evaluation
        stream, index = 0, 0
    return _seed_keys(keys, climbers, stream, jnp.asarray(index, dtype=jnp.int32))


@eqx.filter_jit
def _seed_keys(keys, climbers: int, stream: int, index):
    one = lambda k: jr.fold_in(jr.fold_in(jr.fold_in(k, _STARTS), stream), index)
    return jnp.repeat(jax.vmap(one)(keys), climbers)


def _flat(tree):
    return jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), tree)


def _per_seed(tree, seeds: int):
    return jax.tree_util.tree_map(lambda a: a.reshape(seeds, -1, *a.shape[1:]), tree)


# The jitted steps take the climbers from the state's shape and `reseed_every` as an array,
# so searches that differ only in `reseed_every` share their compilations.


def _lanes(fn: Callable, *trees):
    """`vmap(fn)` over the leading axis of `trees` (one entry per climber of every seed), the
    axis padded to whole lane groups as `task.evaluate` pads its batch (see
    `jaxmotion._sim.execution.share`) and compiled with the simulations' options. XLA's CPU
    loops run whole groups of 8 lanes through vector code and the rest through scalar code
    that rounds `exp` and `log` differently in the last bit; without the padding, climber 8
    of a seed run alone (10 climbers) drew another mutation than the same climber batched
    with other seeds, and a chaotic motion made that another search."""
    n = batch_size(trees)
    out = jax.vmap(fn)(*padded(trees, share(n)))
    return jax.tree_util.tree_map(lambda a: a[:n], out)


def _climber_keys(keys, climbers: int, fold):
    """Every climber's key, seed-major along one axis: seed `s` splits `fold(keys[s])`."""
    return _flat(jax.vmap(lambda k: jr.split(fold(k), climbers))(keys))


@simulation_jit
def _sample(task: Task, key, seeds, climbers: int):
    # Seed s's climbers are `task.sample(climbers, key=sample_key)` of seed s.
    pairs = jax.vmap(lambda s: jr.split(jr.fold_in(key, s)))(seeds)
    sample_keys, run_keys = pairs[:, 0], pairs[:, 1]
    keys = _climber_keys(sample_keys, climbers, lambda k: k)
    return _lanes(lambda k: task.space.sample(key=k), keys), run_keys


@eqx.filter_jit
def _start(population, fitness, keys, motion, archive: int) -> SerialSearchState:
    seeds = keys.shape[0]
    fitness = fitness.reshape(seeds, -1)
    population = _per_seed(population, seeds)
    # A NaN must never enter the set: it would compare false against everything.
    fitness = finite_fitness(_flat(population), fitness.reshape(-1)).reshape(seeds, -1)
    kept, kept_fitness = None, None
    if archive:
        empty = jax.tree_util.tree_map(
            lambda a: jnp.zeros((seeds, archive, *a.shape[2:]), a.dtype), population
        )
        unfilled = jnp.full((seeds, archive), -jnp.inf, fitness.dtype)
        kept, kept_fitness = _archived(empty, unfilled, population, fitness)
    return SerialSearchState(
        population=population,
        fitness=fitness,
        key=keys,
        generation=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(fitness.shape[1], dtype=jnp.int32),
        motion=None if motion is None else _per_seed(motion, seeds),
        archive=kept,
        archive_fitness=kept_fitness,
    )


def _archived(archive, archive_fitness, new, new_fitness):
    """Each seed's archive `(seeds, K)` merged with controllers `new` `(seeds, n)` (a new
    fitness of `-inf` adds nothing): the `K` fittest of both, best first, stably (on ties
    the archive's before the new, each in its order)."""
    size = archive_fitness.shape[1]
    fitness = jnp.concatenate([archive_fitness, new_fitness], axis=1)
    order = jnp.argsort(-fitness, axis=1, stable=True)[:, :size]

    def pick(a, b):
        both = jnp.concatenate([a, b], axis=1)
        return jnp.take_along_axis(both, order.reshape(order.shape + (1,) * (a.ndim - 2)), 1)

    return jax.tree_util.tree_map(pick, archive, new), jnp.take_along_axis(fitness, order, 1)


def _archive_kept(state: SerialSearchState, candidates, fitness, new):
    """`state`'s archive with the climbers `candidates` `(seeds, climbers)` where `new` holds
    (the rest already in it, or not kept), or `(None, None)` without an archive."""
    if state.archive is None:
        return None, None
    added = jnp.where(new, fitness, -jnp.inf)
    return _archived(state.archive, state.archive_fitness, candidates, added)


@simulation_jit
def _enriched(task: Task, state: SerialSearchState, round_: int):
    """Every climber with one rule reinitialised by the relevance heuristic. Round `k` of
    seed `s` draws from `fold_in(fold_in(key[s], 0), k)` (generation `g` draws from
    `fold_in(key[s], g + 1)`)."""
    keys = _climber_keys(
        state.key, state.fitness.shape[1], lambda k: jr.fold_in(jr.fold_in(k, 0), round_)
    )
    return _lanes(
        lambda p, k, m: task.space.reinitialise(p, key=k, motion=m),
        _flat(state.population),
        keys,
        _flat(state.motion),
    )


@eqx.filter_jit
def _replace(state: SerialSearchState, candidates, fitness, motion) -> SerialSearchState:
    """Every climber replaced by its candidate, whatever the fitness (enrichment)."""
    seeds, climbers = state.fitness.shape
    fitness = finite_fitness(candidates, fitness.reshape(-1)).reshape(seeds, climbers)
    population = _per_seed(candidates, seeds)
    archive, archive_fitness = _archive_kept(state, population, fitness, True)
    return SerialSearchState(
        population=population,
        fitness=fitness,
        key=state.key,
        generation=state.generation,
        evaluations=state.evaluations + climbers,
        motion=None if motion is None else _per_seed(motion, seeds),
        archive=archive,
        archive_fitness=archive_fitness,
    )


@simulation_jit
def _ask(task: Task, state: SerialSearchState):
    keys = _climber_keys(
        state.key, state.fitness.shape[1], lambda k: jr.fold_in(k, state.generation + 1)
    )
    return _lanes(
        lambda p, k, m: task.space.perturb(p, key=k, motion=m),
        _flat(state.population),
        keys,
        _flat(state.motion),
    )


def _select(mask, new, old):
    """Per climber (leading axes `mask.shape`), `new` where `mask` holds, else `old`."""
    return jnp.where(mask.reshape(mask.shape + (1,) * (new.ndim - mask.ndim)), new, old)


def _reseeded(population, fitness, half: int):
    """One seed's climbers (and whatever is kept with them) ranked (stably, best first), the
    worse `half` replaced by copies of the best `half`."""
    size = fitness.shape[0]
    order = jnp.argsort(-fitness, stable=True)
    rank = jnp.arange(size)
    source = order[jnp.where(rank < size - half, rank, rank - (size - half))]
    return jax.tree_util.tree_map(lambda a: a[source], population), fitness[source]


@eqx.filter_jit
def _tell(state: SerialSearchState, mutants, fitness, motion, reseed_every):
    seeds, climbers = state.fitness.shape
    fitness = finite_fitness(mutants, fitness.reshape(-1)).reshape(state.fitness.shape)
    mutants = _per_seed(mutants, seeds)
    motion = None if motion is None else _per_seed(motion, seeds)
    # Strictly greater: ties keep the incumbent, and NaN or -inf is never kept.
    better = fitness > state.fitness
    # Each climber with its motion (if kept), selected and reseeded together.
    kept = jax.tree_util.tree_map(
        lambda new, old: _select(better, new, old),
        (mutants, motion),
        (state.population, state.motion),
    )
    archive, archive_fitness = _archive_kept(state, mutants, fitness, better)
    fitness = jnp.where(better, fitness, state.fitness)
    generation = state.generation + 1
    reseed = generation % reseed_every == 0
    kept, fitness = jax.lax.cond(
        reseed,
        lambda p, f: jax.vmap(lambda p1, f1: _reseeded(p1, f1, climbers // 2))(p, f),
        lambda p, f: (p, f),
        kept,
        fitness,
    )
    population, motion = kept
    return SerialSearchState(
        population=population,
        fitness=fitness,
        key=state.key,
        generation=generation,
        evaluations=state.evaluations + climbers,
        motion=motion,
        archive=archive,
        archive_fitness=archive_fitness,
    )


@eqx.filter_jit
def _split(state: SerialSearchState):
    """Every seed's best climber (the first on ties) and its fitness, and every seed's
    state, in one compiled call (indexing seed by seed would compile one slice per seed)."""
    seeds = state.num_seeds
    index = jnp.argmax(state.fitness, axis=1)
    bests = tuple(
        jax.tree_util.tree_map(lambda a, s=s: a[s, index[s]], state.population)
        for s in range(seeds)
    )
    best_fitness = state.fitness[jnp.arange(seeds), index]
    return bests, best_fitness, tuple(state.seed(s) for s in range(seeds))


def _rounds(state: SerialSearchState, history, seeds: int, climbers: int):
    """The driver's evaluation rounds, `(seeds, climbers)` each, and their steps, from every
    seed's `History` up to `state` (continuing a search)."""
    if history is None or len(history) != seeds:
        raise ValueError(
            f"continuing from a state needs one History per seed ({seeds}); got "
            f"{None if history is None else len(history)}"
        )
    _check_resume(state, history[0], (seeds, climbers), int(state.evaluations))
    table = np.stack([h.fitness for h in history]).reshape(seeds, -1, climbers)
    return list(table.transpose(1, 0, 2)), list(history[0].step[::climbers])


@dataclass(frozen=True)
class SerialSearchResult(SearchResult):
    """What `serial_search` returns: a `SearchResult` for the best seed, and one per seed.

    - `best`: the best controller over all seeds (unbatched), the lowest seed on ties.
    - `best_fitness`: its fitness (maximised).
    - `history`: the `History` of the seed that found it.
    - `state`: the final `SerialSearchState` of all seeds (resume or inspect it).
    - `seed`: which seed found `best` (its number, `seed_offset` included).
    - `runs`: one `SearchResult` per seed, in order: that seed's best controller, its
        fitness, its `History`, and its state (`state.seed(i)`, bitwise the state of the
        same seed run alone).

    With `seeds=1` the top-level fields are that seed's.
    """

    seed: int
    runs: tuple[SearchResult, ...]


def serial_search(
    task: Task,
    *,
    key: PRNGKeyArray,
    seeds: int = 1,
    seed_offset: int = 0,
    climbers: int = 10,
    generations: int = 4000,
    reseed_every: int = 200,
    enrich: int = 0,
    archive: int = 0,
    progress: bool = False,
    callback: Callable[[SerialSearchState, tuple[History, ...]], None] | None = None,
    state: SerialSearchState | None = None,
    history: tuple[History, ...] | None = None,
) -> SerialSearchResult:
    """Serial search (second paper, Figure 3) on `task`; fitness is maximised.

    Start from `climbers` random controllers; every generation mutate each one and keep the
    mutant if it is strictly better; every `reseed_every` generations replace the worse half
    by copies of the better half (see `SerialSearch`). The paper's settings (the defaults)
    make 10 + 40,000 simulations per seed.

    Independent seeds run together, every generation evaluated in one call of
    `seeds * climbers` controllers. Seed `s` draws from `jax.random.fold_in(key, s)` only,
    so seed `s` of a batched run is bitwise the run
    `serial_search(task, key=key, seed_offset=s)`.

    **Arguments:**

    - `task`: what to optimise.
    - `key`: the PRNG key (the same key gives the same search).
    - `seeds`: independent runs, searched together.
    - `seed_offset`: the number of the first seed: the run searches seeds
        `seed_offset, ..., seed_offset + seeds - 1`.
    - `climbers`: controllers per seed (the paper's C = 10).
    - `generations`: generations (the paper's G = 4000); each evaluates one mutant per
        climber.
    - `reseed_every`: generations between reseedings (the paper's R = 200).
    - `enrich`: rounds of relevance-heuristic reinitialisation of the initial set (the
        paper's Bob: 3; see `SerialSearch`).
    - `archive`: keep each seed's `archive` fittest controllers ever held as climbers
        (`SerialSearchState.archive`; what `jaxmotion.fittest` reads; 0: none).
    - `progress`: show a tqdm progress bar (off by default: the library does not print).
    - `callback`: called after the initial evaluations and after every generation with the
        state and those evaluations, one `History` per seed.
    - `state`, `history`: continue an interrupted search from a state its `callback` was
        given and every seed's `History` up to it (a checkpoint); with the same settings the
        result is bitwise the uninterrupted search's. `key` is then not used.

    **Returns:** a `SerialSearchResult`; every seed's history has
    `climbers * (1 + enrich + generations)` entries: step 0 holds the initial climbers
    and each enrichment round, step `g` generation `g`.

    **Raises:** `ValueError` for a setting that is not a positive integer (`seed_offset`: a
    non-negative one), before anything compiles.
    """
    generations = _check_positive_int("generations", generations)
    search = SerialSearch(
        climbers=climbers,
        reseed_every=reseed_every,
        enrich=enrich,
        seeds=seeds,
        seed_offset=seed_offset,
        archive=archive,
    )
    if state is not None:
        _rounds(state, history, search.seeds, search.climbers)
    return drive(
        search,
        task,
        key=key,
        steps=generations,
        progress=progress,
        callback=callback,
        state=state,
        history=history,
    )
