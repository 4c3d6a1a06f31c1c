"""The searcher protocol every search follows, the one driver that runs them, and the registry
that finds them by name.

A searcher is a static settings object (an equinox Module whose fields are static) with pure
functions on a state pytree that holds everything a resume needs:

- `init(task, *, key) -> (state, initial)`: draw the first candidates, evaluate them
    (`task.evaluate`, compiled with the shape the steps reuse) and return the state and the
    initial fitness, `(rounds, runs, n)`. It is `first` (pure, jittable: the candidates and
    what `begin` needs besides their fitness), the evaluation, then `begin` (pure,
    jittable: the state), so a caller with an evaluation of its own can run a whole search
    from pure functions; the evaluation itself is outside them because `task.evaluate` is
    a compiled, parallel call of its own (serial search then makes its `enrich` rounds);
- `ask(task, state) -> candidates`: what to evaluate next (jitted, pure);
- `evaluate(task, state, candidates) -> (fitness, extras)`: the driver's one call to the
    simulator per step (the searcher chooses the random starts of a robust task, the chunking,
    and whether the motion is recorded; `extras` go to `tell`);
- `tell(state, candidates, fitness, **extras) -> state` (jitted, pure);
- `best(state) -> (controller, fitness)`.

The task is an argument rather than a field, so one searcher (one set of settings) serves every
task, and the registry can build it from a config's settings alone. Fitness is maximised; NaN
and `-inf` rank worst and never enter a searcher's population.

The driver (`drive`) owns the loop: the progress bar, the history of every evaluation, the
callback (the CLI's checkpoints) and resuming from a state and its history.
"""

import abc
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._control.base import AbstractController
from .._task import Task
from .history import History


@dataclass(frozen=True)
class SearchResult:
    """What a search returns.

    - `best`: the best controller found (unbatched).
    - `best_fitness`: its fitness (maximised).
    - `history`: the fitness of every evaluation, in order (`History`).
    - `state`: the final search state (resume or inspect it).
    """

    best: AbstractController
    best_fitness: float
    history: History
    state: eqx.Module


def fittest(result: SearchResult, k: int) -> tuple[AbstractController, np.ndarray]:
    """The `k` fittest controllers of a search's final set (stacked, best first) and their
    fitness, from its state's `population` and `fitness` (any leading axes: serial search's
    runs and climbers), or from its `archive` and `archive_fitness` when it keeps one
    (`SerialSearch(archive=K)`: the fittest controllers it held over the whole search);
    controllers whose fitness is not finite are left out. A searcher whose state keeps no
    such set (evosax's: a distribution) gives its best alone."""
    state = result.state
    population = getattr(state, "population", None)
    fitness = getattr(state, "fitness", None)
    if getattr(state, "archive", None) is not None:
        population, fitness = state.archive, state.archive_fitness
    if population is None or fitness is None:
        best = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], result.best)
        return best, np.asarray([result.best_fitness])
    lead = jnp.ndim(fitness)
    flat = np.asarray(fitness).reshape(-1)
    order = [int(i) for i in np.argsort(-flat, kind="stable") if np.isfinite(flat[i])][:k]
    index = np.asarray(order, dtype=int)
    chosen = jax.tree_util.tree_map(lambda a: a.reshape((-1, *a.shape[lead:]))[index], population)
    return chosen, flat[index]


class AbstractSearcher(eqx.Module):
    """A search, as pure `init` / `ask` / `evaluate` / `tell` functions on a state pytree (see
    the module's docstring). Subclasses are final; their settings are static fields.

    Class attributes:

    - `name`: the name the registry, configs and `compare` know it by.
    - `per_run`: the state holds several independent runs (serial search's seeds): the
        history is then one `History` per run.
    """

    name: ClassVar[str]
    per_run: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, task: Task, *, key: PRNGKeyArray) -> tuple[Any, Float[Array, "..."]]:
        """Draw and evaluate the first candidates: the state and their fitness, in the order
        evaluated (reshaped by the driver to `(rounds, runs, n)`)."""

    @abc.abstractmethod
    def first(self, task: Task, *, key: PRNGKeyArray) -> tuple[Any, Any]:
        """The first candidates to evaluate (along a leading axis) and the `carry` that
        `begin` takes besides their fitness. Pure and jittable."""

    @abc.abstractmethod
    def begin(self, task: Task, carry, candidates, fitness, **extras):
        """The state after the first candidates were evaluated (`fitness` maximised, NaN
        and `-inf` worst; `extras` as `evaluate` gives them). Pure and jittable."""

    @abc.abstractmethod
    def ask(self, task: Task, state) -> AbstractController:
        """The candidates of the next step, along a leading axis."""

    def evaluate(self, task: Task, state, candidates) -> tuple[Float[Array, " batch"], dict]:
        """Evaluate `ask`'s candidates: their fitness and the extra arguments `tell` takes.
        Default: `task.evaluate` (with the step's random starts of a robust task)."""
        return task.evaluate(candidates, key=self.start_key(task, state)), {}

    def start_key(self, task: Task, state):
        """The key of a step's random starts (`Task.robustness`), `None` without."""
        del task, state
        return None

    @abc.abstractmethod
    def tell(self, state, candidates, fitness, **extras):
        """The state after the evaluated `candidates` (`fitness` maximised; NaN and `-inf`
        rank worst)."""

    @abc.abstractmethod
    def steps_done(self, state) -> int:
        """How many steps (after `init`) the state has made."""

    def history_step(self, state) -> int:
        """The step label the history gives the evaluations of the step just told (default:
        `steps_done`; the transition search labels them with their round)."""
        return self.steps_done(state)

    @abc.abstractmethod
    def best(self, state) -> tuple[AbstractController, float]:
        """The best controller the state holds and its fitness."""

    def template(self, task: Task):
        """A state's tree structure (leaves may be placeholders), drawing and evaluating
        nothing: what reading a checkpoint needs."""
        raise NotImplementedError(f"{type(self).__name__} does not describe its state")

    def runs(self, state) -> int:
        """Independent runs the state holds (1 but for `per_run` searchers)."""
        del state
        return 1

    def check_resume(self, state, history) -> None:
        """Refuse a state and history that do not continue this search (`ValueError`)."""
        del state, history

    def result(self, state, runs: list[History]) -> SearchResult:
        """The `SearchResult` of a finished search, from its state and each run's history."""
        best, fitness = self.best(state)
        return SearchResult(best=best, best_fitness=fitness, history=runs[0], state=state)

    def step(self, task: Task, state, **tell_extras):
        """ask, evaluate, tell. Returns the new state and the step's fitness."""
        candidates = self.ask(task, state)
        fitness, extras = self.evaluate(task, state, candidates)
        return self.tell(state, candidates, fitness, **extras, **tell_extras), fitness


SEARCHERS: dict[str, type[AbstractSearcher]] = {}
"""Every searcher by name: configs (`[search] algorithm`), `compare` and the CLI read it."""


def register(cls: type[AbstractSearcher]) -> type[AbstractSearcher]:
    """Add a searcher class to `SEARCHERS` under its `name` (a class decorator)."""
    if cls.name in SEARCHERS and SEARCHERS[cls.name] is not cls:
        raise ValueError(f"a searcher named {cls.name!r} is already registered")
    SEARCHERS[cls.name] = cls
    return cls


def _histories(chunks: list[tuple[np.ndarray, np.ndarray]], runs: int) -> list[History]:
    if not chunks:
        return [History(np.zeros(0), np.zeros(0, dtype=np.int64)) for _ in range(runs)]
    fitness = np.concatenate([f for f, _ in chunks], axis=1)
    steps = np.concatenate([s for _, s in chunks])
    return [History(fitness[r], steps) for r in range(runs)]


def _recorded(fitness) -> np.ndarray:
    """Fitness as the history records it: a NaN (an evaluation that failed) as `-inf`."""
    fitness = np.asarray(fitness)
    return np.where(np.isnan(fitness), -np.inf, fitness)


def _report(searcher: AbstractSearcher, parts: list[History]):
    return tuple(parts) if searcher.per_run else parts[0]


def drive(
    searcher: AbstractSearcher,
    task: Task,
    *,
    key: PRNGKeyArray | None,
    steps: int,
    last: int | None = None,
    progress: bool = False,
    callback: Callable[[Any, Any], None] | None = None,
    before_step: Callable[[Any], Any] | None = None,
    state=None,
    history=None,
) -> SearchResult:
    """Run `searcher` on `task` until it has made `steps` steps after its `init`; fitness is
    maximised.

    **Arguments:**

    - `searcher`, `task`: what searches and what it optimises.
    - `key`: the PRNG key of `init` (not used when continuing a `state`).
    - `steps`: the steps to have made at the end, counted from `init` (a continued state
        makes only those it has left).
    - `last`: how many of the final step's candidates count (the rest are told as never
        evaluated: a budget of evaluations that is not a whole number of steps); `None`: all.
        Only for searchers whose `tell` takes `num_valid`.
    - `progress`: a tqdm progress bar (off by default: the library does not print).
    - `callback`: called after `init` and after every step with the state and that step's
        evaluations (a `History`, or one per run for `per_run` searchers).
    - `before_step`: called with the state before every step; returns the state to step
        from (evolution's hand selection).
    - `state`, `history`: continue from a state a `callback` was given and the history up to
        it (a checkpoint): with the same settings the result is bitwise the uninterrupted
        search's. (`Evolve` also continues without a history: the result then holds this
        call's evaluations only.)

    **Returns:** the searcher's `SearchResult`.
    """
    if state is None:
        state, initial = searcher.init(task, key=key)
        runs = searcher.runs(state)
        rounds = _recorded(initial)
        if rounds.ndim < 3:  # one round of evaluations
            rounds = rounds.reshape(1, runs, -1)
        fitness = np.concatenate(list(rounds), axis=1)  # (runs, rounds x n), round by round
        chunks = [(fitness, np.zeros(fitness.shape[1], dtype=np.int64))]
        if callback is not None:
            callback(state, _report(searcher, _histories(chunks, runs)))
    else:
        searcher.check_resume(state, history)
        runs = searcher.runs(state)
        if history is None:  # a searcher that continues without (evolve): this call's only
            history = History(np.zeros(0), np.zeros(0, dtype=np.int64))
        parts = list(history) if searcher.per_run else [history]
        chunks = [(np.stack([p.fitness for p in parts]), parts[0].step)]
    best = float(np.max(chunks[0][0])) if chunks[0][0].size else -np.inf
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, unit="step", desc=searcher.name.replace("_", " "))
        bar.update(min(searcher.steps_done(state), steps))
    try:
        for k in range(searcher.steps_done(state), steps):
            if before_step is not None:
                state = before_step(state)
            extra = {} if last is None or k < steps - 1 else {"num_valid": last}
            state, fitness = searcher.step(task, state, **extra)
            fitness = _recorded(fitness).reshape(runs, -1)
            if "num_valid" in extra:
                fitness = fitness[:, :last]
            label = searcher.history_step(state)
            chunk = (fitness, np.full(fitness.shape[1], label, dtype=np.int64))
            chunks.append(chunk)
            if callback is not None:
                callback(state, _report(searcher, _histories([chunk], runs)))
            if bar is not None:
                best = max(best, float(np.max(fitness)))
                bar.update(1)
                bar.set_postfix(best=f"{best:.4g}", refresh=False)
    finally:
        if bar is not None:
            bar.close()
    return searcher.result(state, _histories(chunks, runs))
