"""Transition-point search, the second paper's search for composite motions (Figure 5): when
to switch from each controller of a sequence to the next.

A composite motion runs `K` controllers one after another over `duration` seconds, switching
at the `K - 1` transition times `0 <= T_1 <= ... <= T_{K-1} <= duration`. A set of
transition arrays climbs: every array mutates one of its points at a time and keeps the
mutant if it is better, and after every round the worse half is replaced by the better half.
The caller's `evaluate` turns a batch of arrays into fitness (typically a jitted, batched
simulation of the composite motion scored by its script); this module never traces it.
"""

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .hill_climb import _check_count, _check_positive_int
from .history import History
from .protocol import AbstractSearcher, SearchResult, drive
from .serial import _reseeded

# The fraction of mutations that randomise the chosen point (Figure 5: "randomize 1/3 of the
# time, perturb 2/3 of the time").
RANDOMISE_SHARE = 1 / 3

Evaluate = Callable[[Float[Array, "arrays transitions"]], Float[ArrayLike, " arrays"]]


def _evaluator(task) -> Evaluate:
    """The function that scores transition arrays: the task's `evaluate` (a `Composite`'s),
    or the task itself when it is a plain function."""
    evaluate = getattr(task, "evaluate", None)
    if callable(evaluate):
        return evaluate
    if callable(task):
        return task
    raise TypeError(
        f"the task of a transition search is {type(task).__name__}; allowed: a `Composite` "
        "(anything with `evaluate(transitions)`) or a function of the transition arrays"
    )


class TransitionSearchState(eqx.Module):
    """The whole state of a transition-point search (one pytree, so it can be checkpointed
    and resumed).

    - `transitions`: the set of transition arrays, `(arrays, transitions)`, each ascending
        within `[0, duration]` (seconds). After every round it lists the ranked better half,
        best first, followed by its copies in the same order.
    - `fitness`: their fitness, `(arrays,)`; `-inf` for an evaluation that gave NaN or
        `-inf`.
    - `key`: the PRNG key of the whole search; mutation step `j` of round `r` (both counted
        from 0) draws from `fold_in(fold_in(key, r), j)`.
    - `round`: how many rounds have been completed.
    - `mutation`: how many mutation steps of the current round have been made (`0` to
        `mutations - 1`; back to 0 when a round ends).
    - `evaluations`: how many arrays have been evaluated, the starting set included.
    """

    transitions: Float[Array, "arrays transitions"]
    fitness: Float[Array, " arrays"]
    key: PRNGKeyArray
    round: Int[Array, ""]
    mutation: Int[Array, ""]
    evaluations: Int[Array, ""]


def _check_positive_number(name: str, value, unit: str) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ValueError(f"{name} = {value!r}; allowed: a finite number > 0{unit}")
    return float(value)


# Ticks may miss a whole number by this much, relative to their count: `3.0 / 0.01` is
# 299.99999999999994 in float64.
_TICK_TOLERANCE = 1e-6


class TransitionSearch(AbstractSearcher):
    """Transition-point search (second paper, Figure 5), a searcher of the common protocol
    (`AbstractSearcher`: `init` / `ask` / `evaluate` / `tell`, run by `drive`) whose
    candidates are transition arrays rather than controllers, and whose task is a `Composite`
    (or anything with `evaluate(transitions)`, or that function itself). It is not in
    `SEARCHERS`, the registry of controller searches that configs' `[search] algorithm`
    names: the `compose` command runs it.

    The set holds `num_arrays` transition arrays (the paper's Q = 16). A round makes
    `mutations` (the paper's H = 4) mutation steps; in each, every array mutates one point
    (below), all `num_arrays` mutants are evaluated in one call, and each replaces its array
    only if its fitness is strictly greater (ties keep the old array; NaN counts as `-inf`
    and is never kept). As the arrays do not interact within a round, this is Figure 5's
    "for each array, H times" with the arrays taken side by side. After the last step of a
    round the set is ranked by fitness (stably: ties keep the lower index first) and the
    worse `num_arrays // 2` are replaced by copies of the better `num_arrays // 2`, fitness
    included (no re-evaluation); with an odd `num_arrays` the middle array stays as it is.
    Fitness is maximised, and the best fitness of the set never decreases.

    **Mutation.** Each array draws one of its points, `T_i`, uniformly. It may move between
    its neighbours, `lo = T_{i-1}` (0 for the first) and `hi = T_{i+1}` (`duration` for the
    last), so the phases keep their order (a phase may shrink to zero length, never below).
    With probability 1/3 it is randomised, drawn uniformly from `[lo, hi]`; otherwise it is
    perturbed, `T_i + perturb_scale * (hi - lo) * N(0, 1)`, clipped into `[lo, hi]`. With a
    `tick`, the new point is then rounded to the nearest whole number of ticks (still within
    `[lo, hi]`, which are on the grid too), so arrays that switch within the same control
    period, and so simulate alike, are the same array. A perturbation much smaller than a
    tick rounds back to where it was; randomisation still moves the point.

    `ask` and `tell` are jitted; between them the driver calls the task's `evaluate`, which
    is not traced here. `duration`, `tick` and `perturb_scale` reach the compiled steps as
    arrays, so searches that differ only in them share their compilations. A step is one
    mutation step (one call of `evaluate`); the history labels a step's evaluations with its
    round, `1` to `rounds`, and the starting set with 0.

    **Arguments:**

    - `duration`: the length of the composite motion (s), `> 0`.
    - `num_arrays`: transition arrays in the set (the paper's Q = 16), `>= 2`.
    - `mutations`: mutation steps per array per round (the paper's H = 4), `>= 1`.
    - `tick`: if given, the simulator's control period (s): every transition lies on a
        whole number of ticks. `duration` must be a whole number of ticks.
    - `perturb_scale`: the standard deviation of a perturbation, as a fraction of the
        interval between the point's neighbours. The default 0.2 keeps perturbations
        local (95% move the point by less than 0.4 of that interval), leaving long jumps to
        randomisation; on a smooth objective the defaults find an optimum to within about
        1% of the duration.
    - `initial`: the array every member of the set starts from (the user's guess):
        ascending times within `[0, duration]`; or
    - `num_transitions`: start from that many transitions equally spaced over the duration.
        With neither, `init` starts from the task's `equally_spaced()` (a `Composite`'s).

    **Raises:** `ValueError` for a setting out of range, before anything compiles.
    """

    duration: float = eqx.field(static=True)
    num_arrays: int = eqx.field(static=True)
    mutations: int = eqx.field(static=True)
    tick: float | None = eqx.field(static=True)
    perturb_scale: float = eqx.field(static=True)
    initial: tuple[float, ...] | None = eqx.field(static=True)

    name: ClassVar[str] = "transition_search"

    def __init__(
        self,
        duration: float,
        *,
        num_arrays: int = 16,
        mutations: int = 4,
        tick: float | None = None,
        perturb_scale: float = 0.2,
        initial: ArrayLike | None = None,
        num_transitions: int | None = None,
    ):
        self.duration = _check_positive_number("duration", duration, " (s)")
        self.num_arrays = _check_positive_int("num_arrays", num_arrays)
        if self.num_arrays < 2:
            raise ValueError(
                f"num_arrays = {num_arrays!r}; allowed: an integer >= 2 (the worse half is "
                "replaced by the better half)"
            )
        self.mutations = _check_positive_int("mutations", mutations)
        if tick is not None:
            tick = _check_positive_number("tick", tick, " (s), or None")
            ticks = self.duration / tick
            if tick > self.duration or abs(ticks - round(ticks)) > _TICK_TOLERANCE * ticks:
                raise ValueError(
                    f"tick = {tick!r} with duration = {self.duration!r} ({ticks:.6g} ticks); "
                    "allowed: a tick that divides the duration into a whole number of ticks"
                )
        self.tick = tick
        self.perturb_scale = _check_positive_number("perturb_scale", perturb_scale, "")
        if initial is None and num_transitions is None:
            self.initial = None
        else:
            start = self.start(initial=initial, num_transitions=num_transitions)
            self.initial = tuple(float(t) for t in start)

    def start(
        self,
        *,
        initial: ArrayLike | None = None,
        num_transitions: int | None = None,
    ) -> np.ndarray:
        """The array every member of the set starts from, checked (no compilation): the
        user's guess `initial` if given, else `num_transitions` points equally spaced over
        the duration, `T_k = k * duration / K` with `K = num_transitions + 1` phases.

        **Returns:** the `(transitions,)` starting array (float64, not yet on the tick grid:
        `init` rounds it there).

        **Raises:** `ValueError` if neither is given, if they disagree on the number of
        transitions, or if `initial` is not a non-empty 1-D array of finite, ascending
        times within `[0, duration]`.
        """
        if num_transitions is not None:
            num_transitions = _check_positive_int("num_transitions", num_transitions)
        if initial is None:
            if num_transitions is None:
                raise ValueError(
                    "initial = None and num_transitions = None; allowed: give the initial "
                    "transition times or how many transitions there are"
                )
            k = np.arange(1, num_transitions + 1)
            return k * self.duration / (num_transitions + 1)
        start = np.asarray(initial, dtype=np.float64)
        if start.ndim != 1 or start.shape[0] == 0:
            raise ValueError(
                f"initial has shape {start.shape}; allowed: (transitions,) with at least one "
                "transition"
            )
        if num_transitions is not None and num_transitions != start.shape[0]:
            raise ValueError(
                f"num_transitions = {num_transitions} but initial has {start.shape[0]} "
                "transitions; allowed: the same number (or give only one of them)"
            )
        if not (
            np.all(np.isfinite(start))
            and np.all(start >= 0)
            and np.all(start <= self.duration)
            and np.all(np.diff(start) >= 0)
        ):
            raise ValueError(
                f"initial = {start.tolist()}; allowed: ascending times (equal neighbours "
                f"allowed) within [0, duration = {self.duration}] (s)"
            )
        return start

    def init(
        self, task, *, key: PRNGKeyArray
    ) -> tuple[TransitionSearchState, Float[Array, " arrays"]]:
        """Make `num_arrays` identical copies of the starting array (`initial`, or the task's
        `equally_spaced()`; rounded to the tick grid if there is one) and evaluate them in
        one call of the task's `evaluate`.

        **Returns:** the state and the fitness of the starting set (NaN as `-inf`).
        """
        evaluate = _evaluator(task)
        transitions, key = self.first(task, key=key)
        fitness = _evaluated(evaluate, transitions, self.num_arrays)
        return self.begin(task, key, transitions, fitness), fitness

    def first(self, task, *, key: PRNGKeyArray) -> tuple[Float[Array, "arrays transitions"], Any]:
        """`num_arrays` copies of the starting array (on the tick grid), and the key."""
        dtype = jnp.result_type(float)
        duration, tick, _ = self._settings(dtype)
        start = jnp.asarray(self._start(task), dtype=dtype)
        return _population(start, self.num_arrays, duration, tick), key

    def begin(self, task, carry, candidates, fitness) -> TransitionSearchState:
        """The set with its fitness (NaN as `-inf`), at round 0."""
        del task
        fitness = jnp.asarray(fitness, dtype=candidates.dtype)
        return TransitionSearchState(
            transitions=candidates,
            fitness=jnp.where(jnp.isnan(fitness), -jnp.inf, fitness),
            key=carry,
            round=jnp.asarray(0, dtype=jnp.int32),
            mutation=jnp.asarray(0, dtype=jnp.int32),
            evaluations=jnp.asarray(self.num_arrays, dtype=jnp.int32),
        )

    def ask(self, task, state: TransitionSearchState) -> Float[Array, "arrays transitions"]:
        """This mutation step's mutant of every array, `(arrays, transitions)`, ready for
        `evaluate` (the task is not read)."""
        del task
        self._check_state(state)
        return _ask(state, *self._settings(state.transitions.dtype))

    def evaluate(self, task, state, candidates) -> tuple[Float[Array, " arrays"], dict]:
        """The task's fitness of the mutants (one call; NaN as `-inf`)."""
        del state
        return _evaluated(_evaluator(task), candidates, self.num_arrays), {}

    def tell(
        self,
        state: TransitionSearchState,
        candidates: Float[Array, "arrays transitions"],
        fitness: Float[ArrayLike, " arrays"],
    ) -> TransitionSearchState:
        """Replace every array whose mutant (`candidates`) has strictly greater fitness (NaN
        never does); after the round's last mutation step, rank the set and replace its worse
        half by its better half."""
        self._check_state(state)
        if jnp.shape(candidates) != state.transitions.shape:
            raise ValueError(
                f"mutants have shape {jnp.shape(candidates)}; expected "
                f"{state.transitions.shape} (arrays, transitions), as `ask` gives them"
            )
        if jnp.shape(fitness) != state.fitness.shape:
            raise ValueError(
                f"fitness has shape {jnp.shape(fitness)}; expected {state.fitness.shape}: "
                "one fitness per transition array"
            )
        return _tell(
            state,
            candidates,
            jnp.asarray(fitness, dtype=state.fitness.dtype),
            jnp.asarray(self.mutations, dtype=jnp.int32),
        )

    def steps_done(self, state: TransitionSearchState) -> int:
        """Mutation steps made: `round * mutations + mutation`."""
        return int(state.round) * self.mutations + int(state.mutation)

    def history_step(self, state: TransitionSearchState) -> int:
        """The round the step just told belongs to (1 for the first round's steps)."""
        return int(state.round) + (int(state.mutation) > 0)

    def best(self, state: TransitionSearchState) -> tuple[Float[Array, " transitions"], float]:
        """The best array of the set (the first on ties: the set is ranked after a round)
        and its fitness."""
        fitness = np.asarray(state.fitness)
        best = int(np.argmax(fitness))
        return state.transitions[best], float(fitness[best])

    def template(self, task) -> TransitionSearchState:
        """The state's structure and shapes (`begin` of zeros), evaluating nothing."""
        dtype = jnp.result_type(float)
        transitions = jnp.zeros((self.num_arrays, len(self._start(task))), dtype)
        return self.begin(task, jr.key(0), transitions, jnp.zeros(self.num_arrays, dtype))

    def check_resume(self, state: TransitionSearchState, history) -> None:
        self._check_state(state)
        if history is not None and history.fitness.shape[0] != int(state.evaluations):
            raise ValueError(
                f"the history holds {history.fitness.shape[0]} evaluations but the state "
                f"{int(state.evaluations)}; allowed: the history recorded with this state"
            )

    def result(self, state: TransitionSearchState, runs: list[History]):
        best, fitness = self.best(state)
        return TransitionSearchResult(
            best=best,
            best_fitness=fitness,
            history=runs[0],
            state=state,
            population=state.transitions,
            fitness=state.fitness,
            evaluations=int(state.evaluations),
        )

    def _start(self, task) -> np.ndarray:
        if self.initial is not None:
            return np.asarray(self.initial)
        equally_spaced = getattr(task, "equally_spaced", None)
        if equally_spaced is None:
            raise ValueError(
                "initial = None and num_transitions = None, and the task has no "
                "`equally_spaced()`; allowed: give the initial transition times or how many "
                "transitions there are"
            )
        return self.start(initial=equally_spaced())

    def _settings(self, dtype):
        # No tick is a tick of 0, so that both kinds of search share one compilation.
        return (
            jnp.asarray(self.duration, dtype=dtype),
            jnp.asarray(0.0 if self.tick is None else self.tick, dtype=dtype),
            jnp.asarray(self.perturb_scale, dtype=dtype),
        )

    def _check_state(self, state: TransitionSearchState):
        if state.fitness.shape != (self.num_arrays,):
            raise ValueError(
                f"the state holds {state.fitness.shape[0]} transition arrays; this search "
                f"has num_arrays = {self.num_arrays}"
            )


def _evaluated(evaluate: Evaluate, transitions, num_arrays: int) -> Float[Array, " arrays"]:
    """`evaluate(transitions)`, checked to give one fitness per array, in the transitions'
    dtype, NaN as `-inf` (a NaN would compare false against everything)."""
    fitness = np.asarray(evaluate(transitions))
    if fitness.shape != (num_arrays,):
        raise ValueError(
            f"evaluate returned fitness of shape {fitness.shape} for transition arrays of "
            f"shape {tuple(transitions.shape)}; expected ({num_arrays},): one fitness per "
            "transition array"
        )
    fitness = fitness.astype(transitions.dtype)
    return jnp.asarray(np.where(np.isnan(fitness), -np.inf, fitness))


def _snapped(times, lo, hi, tick):
    """`times` rounded to the nearest whole number of ticks (unchanged if `tick` is 0), then
    clipped into `[lo, hi]`. With `lo` and `hi` on the grid the clip only removes rounding
    error of the last bit."""
    whole = jnp.round(times / jnp.where(tick > 0, tick, 1)) * tick
    return jnp.clip(jnp.where(tick > 0, whole, times), lo, hi)


@eqx.filter_jit
def _population(start, num_arrays: int, duration, tick):
    return jnp.tile(_snapped(start, 0, duration, tick), (num_arrays, 1))


def _mutated(transitions, key, duration, tick, scale):
    """One array with one point, drawn uniformly, randomised or perturbed between its
    neighbours (see `TransitionSearch`)."""
    pick_key, kind_key, uniform_key, normal_key = jr.split(key, 4)
    dtype = transitions.dtype
    i = jr.randint(pick_key, (), 0, transitions.shape[0])
    bounds = jnp.concatenate([jnp.zeros(1, dtype), transitions, duration[None]])
    lo, hi = bounds[i], bounds[i + 2]
    randomised = jr.uniform(uniform_key, (), dtype, lo, hi)
    perturbed = transitions[i] + scale * (hi - lo) * jr.normal(normal_key, (), dtype)
    moved = jnp.where(jr.bernoulli(kind_key, RANDOMISE_SHARE), randomised, perturbed)
    return transitions.at[i].set(_snapped(moved, lo, hi, tick))


@eqx.filter_jit
def _ask(state: TransitionSearchState, duration, tick, scale):
    step_key = jr.fold_in(jr.fold_in(state.key, state.round), state.mutation)
    keys = jr.split(step_key, state.transitions.shape[0])
    return jax.vmap(lambda t, k: _mutated(t, k, duration, tick, scale))(state.transitions, keys)


@eqx.filter_jit
def _tell(state: TransitionSearchState, mutants, fitness, mutations):
    num_arrays = state.fitness.shape[0]
    # Strictly greater: ties keep the incumbent, and NaN (which compares false) or -inf is
    # never kept.
    better = fitness > state.fitness
    transitions = jnp.where(better[:, None], mutants, state.transitions)
    fitness = jnp.where(better, fitness, state.fitness)
    mutation = state.mutation + 1
    round_ends = mutation == mutations
    transitions, fitness = jax.lax.cond(
        round_ends,
        lambda t, f: _reseeded(t, f, num_arrays // 2),
        lambda t, f: (t, f),
        transitions,
        fitness,
    )
    return TransitionSearchState(
        transitions=transitions,
        fitness=fitness,
        key=state.key,
        round=state.round + round_ends.astype(state.round.dtype),
        mutation=jnp.where(round_ends, 0, mutation),
        evaluations=state.evaluations + num_arrays,
    )


@dataclass(frozen=True)
class TransitionSearchResult(SearchResult):
    """What `transition_search` (and `drive` with a `TransitionSearch`) returns: a
    `SearchResult` whose candidates are transition arrays.

    - `best`: the best transition array found, `(transitions,)` (s), ascending within
        `[0, duration]` (the first of the set on ties).
    - `best_fitness`: its fitness (maximised; never below the start's).
    - `history`: the fitness of every evaluation, in order (`History`): step 0 holds the
        starting set, step `r` the `mutations * num_arrays` evaluations of round `r`.
    - `state`: the final `TransitionSearchState` (resume or inspect it).
    - `population`: the final set of transition arrays, `(arrays, transitions)`.
    - `fitness`: their fitness, `(arrays,)`.
    - `evaluations`: how many arrays were evaluated, `num_arrays * (1 + rounds *
        mutations)`.
    """

    population: Float[Array, "arrays transitions"] = None
    fitness: Float[Array, " arrays"] = None
    evaluations: int = 0


def transition_search(
    evaluate: Evaluate,
    duration: float,
    *,
    key: PRNGKeyArray,
    num_transitions: int | None = None,
    initial: ArrayLike | None = None,
    num_arrays: int = 16,
    rounds: int = 16,
    mutations: int = 4,
    tick: float | None = None,
    perturb_scale: float = 0.2,
    callback: Callable[[int, TransitionSearchState], None] | None = None,
    state: TransitionSearchState | None = None,
    history: History | None = None,
) -> TransitionSearchResult:
    """Transition-point search (second paper, Figure 5): when to switch between the
    controllers of a composite motion; fitness is maximised.

    Start from `num_arrays` copies of the user's guess (`initial`) or of equally spaced
    transitions; then for `rounds` rounds, mutate every array `mutations` times, keeping
    each mutant that is strictly better, and replace the worse half of the set by the better
    half (see `TransitionSearch` for the mutation and the ranking). The paper's settings
    (the defaults) evaluate 16 + 16 * 16 * 4 = 1,040 arrays.

    **Arguments:**

    - `evaluate`: a Python callable taking a `(num_arrays, transitions)` array of
        transition times (s) and returning their `(num_arrays,)` fitness; NaN counts as
        `-inf`. It is called once per mutation step with the whole set, `1 + rounds *
        mutations` times in all, from Python (it is not traced here: jit it yourself).
    - `duration`: the length of the composite motion (s).
    - `key`: the PRNG key (the same key gives the same search).
    - `num_transitions`: how many transitions (`K - 1` for `K` controllers), if `initial`
        is not given; the start is then `T_k = k * duration / K`.
    - `initial`: the user's guess, `(transitions,)`: ascending times within
        `[0, duration]`.
    - `num_arrays`: transition arrays in the set (the paper's Q = 16).
    - `rounds`: rounds (the paper's G = 16); 0 evaluates the start only.
    - `mutations`: mutation steps per array per round (the paper's H = 4).
    - `tick`: if given, the control period (s): every transition, the start's included,
        is rounded to a whole number of ticks. It must divide `duration`.
    - `perturb_scale`: the standard deviation of a perturbation as a fraction of the
        interval between the point's neighbours.
    - `callback`: called as `callback(0, state)` once the start is evaluated and
        `callback(r, state)` after round `r` (its ranking and replacement included).
    - `state`, `history`: continue from a state a `callback` was given after a round and
        the result's history up to it (`result.history` of a search with fewer rounds, or a
        saved pair): with the same settings the result is bitwise the uninterrupted one's.

    **Returns:** a `TransitionSearchResult`.

    **Raises:** `ValueError` for an argument out of range (before anything compiles), or
    when `evaluate` returns fitness of another shape than `(num_arrays,)`.
    """
    rounds = _check_count("rounds", rounds)
    search = TransitionSearch(
        duration,
        num_arrays=num_arrays,
        mutations=mutations,
        tick=tick,
        perturb_scale=perturb_scale,
        initial=initial,
        num_transitions=num_transitions,
    )
    if search.initial is None:
        search.start()  # raises: neither `initial` nor `num_transitions` was given
    _evaluator(evaluate)

    def report(state, part):
        del part
        if callback is not None and int(state.mutation) == 0:
            callback(int(state.round), state)

    return drive(
        search,
        evaluate,
        key=key,
        steps=rounds * search.mutations,
        callback=report,
        state=state,
        history=history,
    )
