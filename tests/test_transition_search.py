"""Transition-point search (fourth paper, Figure 5): its bookkeeping, its mutation and
selection rules, that it never loses its start and that it finds a planted optimum.

The objectives are NumPy functions (nothing of theirs compiles), and almost every search
has 16 arrays of 3 or 2 transitions, so the file compiles the search's steps for a handful
of shapes."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxmotion as jm
from jaxmotion._search.transitions import (
    TransitionSearch,
    TransitionSearchState,
    transition_search,
)

DURATION = 3.0  # s
Q, G, H = 16, 16, 4  # the paper's settings, the defaults


def quadratic(target):
    """Fitness -|T - T*|^2, best (0) at the planted `target`."""
    target = np.asarray(target)
    return lambda t: -np.sum((np.asarray(t, dtype=np.float64) - target) ** 2, axis=1)


class Recorder:
    """An evaluate that records every batch it is given (as NumPy) and passes it on."""

    def __init__(self, fitness):
        self.fitness = fitness
        self.calls = []

    def __call__(self, t):
        t = np.asarray(t)
        self.calls.append(t)
        return self.fitness(t)


def ascending_within(t, duration):
    return bool(np.all(np.diff(t, axis=-1) >= 0) and np.all(t >= 0) and np.all(t <= duration))


def on_grid(t, tick):
    # float32 times on a grid of ticks: within 1e-4 of a tick, counted in ticks.
    ticks = np.asarray(t, dtype=np.float64) / tick
    return bool(np.all(np.abs(ticks - np.round(ticks)) < 1e-4))


def state_of(transitions, fitness, *, key=0, mutation=0, round_=0):
    transitions = np.asarray(transitions, dtype=np.float32)
    return TransitionSearchState(
        transitions=transitions,
        fitness=np.asarray(fitness, dtype=np.float32),
        key=jr.key(key),
        round=np.asarray(round_, dtype=np.int32),
        mutation=np.asarray(mutation, dtype=np.int32),
        evaluations=np.asarray(transitions.shape[0], dtype=np.int32),
    )


# Mostly flat with noise: a plateau, a step up late in the first phase, and fresh noise on
# every evaluation (so the same array scores differently each time).
def noisy_plateau(seed):
    rng = np.random.default_rng(seed)
    return lambda t: (
        (np.asarray(t)[:, 0] > 2.0).astype(np.float64) + 0.01 * rng.normal(size=np.shape(t)[0])
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("objective", ["quadratic", "noisy_plateau"])
def test_never_worse_than_its_start(seed, objective):
    evaluate = quadratic([0.2, 2.9, 2.95]) if objective == "quadratic" else noisy_plateau(seed)
    best_after_round = []
    result = transition_search(
        evaluate,
        DURATION,
        key=jr.key(seed),
        num_transitions=3,
        rounds=4,
        callback=lambda r, state: best_after_round.append(float(np.max(state.fitness))),
    )
    start_best = result.history.fitness[:Q].max()
    assert result.best_fitness >= start_best
    # The set's best never drops, and what the search returns is the best it evaluated.
    assert np.all(np.diff(best_after_round) >= 0)
    assert result.best_fitness == best_after_round[-1] == result.history.fitness.max()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("target", [[0.3, 2.8], [0.4, 1.7, 2.2]])
def test_finds_a_planted_optimum_with_the_papers_settings(seed, target):
    result = transition_search(
        quadratic(target), DURATION, key=jr.key(seed), num_transitions=len(target)
    )
    # Within 1% of the duration (the worst of 20 seeds of each was 0.012 s).
    tolerance = 0.03  # s
    np.testing.assert_allclose(np.asarray(result.best), target, atol=tolerance)
    assert result.best_fitness > -len(target) * tolerance**2


@pytest.mark.parametrize("tick", [None, 0.01])
def test_figure5_bookkeeping(tick):
    """Q evaluations of the start, then G * H calls of Q arrays each; every array ascending
    within [0, duration], and on the tick grid when there is one."""
    evaluate = Recorder(quadratic([0.4, 1.7, 2.2]))
    result = transition_search(evaluate, DURATION, key=jr.key(3), num_transitions=3, tick=tick)
    assert len(evaluate.calls) == 1 + G * H
    assert all(c.shape == (Q, 3) for c in evaluate.calls)
    assert result.evaluations == len(result.history) == int(result.state.evaluations)
    assert result.evaluations == Q + G * H * Q == 1040
    # Step 0 is the start, step r the H * Q evaluations of round r.
    assert np.bincount(result.history.step).tolist() == [Q] + [H * Q] * G
    assert int(result.state.round) == G and int(result.state.mutation) == 0
    calls = np.stack(evaluate.calls)
    assert ascending_within(calls, DURATION)
    assert ascending_within(np.asarray(result.population), DURATION)
    if tick is not None:
        assert on_grid(calls, tick) and on_grid(result.population, tick)
        assert on_grid(result.best, tick)


def test_each_mutant_changes_one_point_and_the_history_is_its_fitness():
    evaluate = Recorder(quadratic([0.4, 1.7, 2.2]))
    transition_search(evaluate, DURATION, key=jr.key(4), num_transitions=3, rounds=2)
    # Mutation step j's parents are the set after step j - 1, which the calls do not show;
    # but the start is known: the first step's mutants differ from it in one point each.
    start, first = evaluate.calls[0], evaluate.calls[1]
    assert np.all(np.sum(first != start, axis=1) <= 1)
    assert np.sum(first != start) > Q // 2  # most mutations move their point


def test_every_round_ends_with_the_better_half_copied_over_the_worse():
    halves = []

    def check(r, state):
        if r == 0:
            return
        t, f = np.asarray(state.transitions), np.asarray(state.fitness)
        half = Q // 2
        assert np.all(np.diff(f[:half]) <= 0)  # ranked, best first
        np.testing.assert_array_equal(t[half:], t[:half])
        np.testing.assert_array_equal(f[half:], f[:half])
        halves.append(r)

    transition_search(
        quadratic([0.4, 1.7, 2.2]), DURATION, key=jr.key(5), num_transitions=3, callback=check
    )
    assert halves == list(range(1, G + 1))


@pytest.mark.parametrize("num_arrays", [4, 5])
def test_tell_keeps_strictly_better_mutants_then_ranks_and_copies(num_arrays):
    """The last step of a round: each mutant replaces its array only if strictly better
    (a tie or a NaN keeps the old one), then the set is ranked stably and the worse
    `num_arrays // 2` become copies of the better (with 5 arrays the middle one stays)."""
    search = TransitionSearch(DURATION, num_arrays=num_arrays, mutations=2)
    old = np.linspace(0.5, 2.5, 2 * num_arrays, dtype=np.float32).reshape(num_arrays, 2)
    mutants = old + np.float32(0.125)
    old_fitness = np.array([1.0, 2.0, 3.0, 4.0, 5.0][:num_arrays], dtype=np.float32)
    # better, tie, NaN, worse, better
    new_fitness = np.array([7.0, 2.0, np.nan, 1.0, 6.0][:num_arrays], dtype=np.float32)

    step = search.tell(state_of(old, old_fitness), mutants, new_fitness)
    assert int(step.mutation) == 1 and int(step.round) == 0
    kept = np.array([True, False, False, False, True][:num_arrays])
    np.testing.assert_array_equal(
        np.asarray(step.transitions), np.where(kept[:, None], mutants, old)
    )
    np.testing.assert_array_equal(
        np.asarray(step.fitness), np.where(kept, new_fitness, old_fitness)
    )

    end = search.tell(state_of(old, old_fitness, mutation=1), mutants, new_fitness)
    assert int(end.mutation) == 0 and int(end.round) == 1
    kept_t = np.where(kept[:, None], mutants, old)
    kept_f = np.where(kept, new_fitness, old_fitness)
    order = np.argsort(-kept_f, kind="stable")
    half = num_arrays // 2
    source = np.concatenate([order[: num_arrays - half], order[:half]])
    np.testing.assert_array_equal(np.asarray(end.transitions), kept_t[source])
    np.testing.assert_array_equal(np.asarray(end.fitness), kept_f[source])


def test_ties_in_the_ranking_keep_the_lower_index_first():
    search = TransitionSearch(DURATION, num_arrays=4, mutations=1)
    old = np.array([[0.5, 1.0], [1.0, 1.5], [1.5, 2.0], [2.0, 2.5]], dtype=np.float32)
    fitness = np.array([1.0, 2.0, 2.0, 0.0], dtype=np.float32)
    end = search.tell(state_of(old, fitness), old, np.full(4, -np.inf, dtype=np.float32))
    np.testing.assert_array_equal(np.asarray(end.transitions), old[[1, 2, 1, 2]])


def test_same_key_same_search_other_key_another():
    run = lambda seed: transition_search(
        noisy_plateau(0), DURATION, key=jr.key(seed), num_transitions=3, rounds=3
    )
    a, b, c = run(6), run(6), run(7)
    np.testing.assert_array_equal(a.history.fitness, b.history.fitness)
    np.testing.assert_array_equal(np.asarray(a.population), np.asarray(b.population))
    np.testing.assert_array_equal(np.asarray(a.best), np.asarray(b.best))
    assert not np.array_equal(np.asarray(a.population), np.asarray(c.population))


def test_the_driver_is_init_then_steps():
    """`transition_search` is the protocol's `init` then G * H `step`s (one `evaluate` call
    each), run by the common driver."""
    evaluate = quadratic([0.4, 1.7, 2.2])
    result = transition_search(evaluate, DURATION, key=jr.key(8), num_transitions=3, rounds=2)
    search = TransitionSearch(DURATION, num_transitions=3)
    state, _ = search.init(evaluate, key=jr.key(8))
    # init = first, the evaluation, begin; first and begin are pure (jitted whole alike).
    transitions, carry = eqx.filter_jit(search.first)(evaluate, key=jr.key(8))
    fitness = jnp.asarray(evaluate(transitions), dtype=transitions.dtype)
    begun = eqx.filter_jit(search.begin)(evaluate, carry, transitions, fitness)
    np.testing.assert_array_equal(np.asarray(begun.transitions), np.asarray(state.transitions))
    np.testing.assert_array_equal(np.asarray(begun.fitness), np.asarray(state.fitness))
    for _ in range(2 * H):
        state, _ = search.step(evaluate, state)
    assert search.steps_done(state) == 2 * H
    # ask and tell are pure: jitted whole, they give what they give eagerly.
    asked = search.ask(evaluate, state)
    np.testing.assert_array_equal(
        np.asarray(eqx.filter_jit(search.ask)(None, state)), np.asarray(asked)
    )
    fitness = jnp.asarray(evaluate(asked), dtype=asked.dtype)
    told = search.tell(state, asked, fitness)
    jitted = eqx.filter_jit(search.tell)(state, asked, fitness)
    np.testing.assert_array_equal(np.asarray(jitted.transitions), np.asarray(told.transitions))
    np.testing.assert_array_equal(np.asarray(jitted.fitness), np.asarray(told.fitness))
    np.testing.assert_array_equal(np.asarray(state.transitions), np.asarray(result.population))
    np.testing.assert_array_equal(np.asarray(state.fitness), np.asarray(result.fitness))
    driven = jm.drive(search, evaluate, key=jr.key(8), steps=2 * H)
    np.testing.assert_array_equal(driven.history.fitness, result.history.fitness)
    np.testing.assert_array_equal(driven.history.step, result.history.step)


def test_a_search_continued_from_a_round_equals_the_uninterrupted_one():
    """The state after round 2 and the history up to it continue to the very result of
    four rounds in one go (a checkpoint's contract)."""
    evaluate = quadratic([0.9, 1.1, 2.6])
    run = lambda rounds, **more: transition_search(
        evaluate, DURATION, key=jr.key(11), num_transitions=3, rounds=rounds, **more
    )
    whole, half = run(4), run(2)
    continued = run(4, state=half.state, history=half.history)
    np.testing.assert_array_equal(continued.history.fitness, whole.history.fitness)
    np.testing.assert_array_equal(continued.history.step, whole.history.step)
    np.testing.assert_array_equal(np.asarray(continued.population), np.asarray(whole.population))
    assert continued.best_fitness == whole.best_fitness
    with pytest.raises(ValueError, match="history holds"):
        run(4, state=half.state, history=whole.history)


def test_the_state_round_trips_through_the_checkpoint_format():
    """The state is a pytree the CLI's checkpoint format writes and reads back exactly,
    with the structure `template` gives without evaluating anything."""
    from jaxmotion._cli.checkpoint import state_from_bytes, state_to_bytes

    result = transition_search(noisy_plateau(2), DURATION, key=jr.key(12), initial=[0.5, 2.0])
    search = TransitionSearch(DURATION, initial=[0.5, 2.0])
    payload, part = state_to_bytes(result.state, result.history)
    state, history = state_from_bytes(search.template(never_called), part, payload, None)
    leaves = jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(result.state)
    for a, b in zip(*leaves, strict=True):
        if jnp.issubdtype(jnp.asarray(a).dtype, jax.dtypes.prng_key):
            a, b = jr.key_data(a), jr.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(history.fitness, result.history.fitness)


def test_nan_is_never_kept_and_never_best():
    # Fitness grows with T_1 but is NaN beyond 1.2 s: the search presses against the NaNs.
    def evaluate(t):
        t = np.asarray(t)
        return np.where(t[:, 0] > 1.2, np.nan, t[:, 0])

    result = transition_search(evaluate, DURATION, key=jr.key(9), num_transitions=3, rounds=4)
    assert result.history.num_nonfinite > 0  # NaNs were evaluated, recorded as -inf
    assert not np.any(np.isnan(result.history.fitness))
    assert np.all(np.isfinite(np.asarray(result.fitness)))
    assert np.isfinite(result.best_fitness) and float(result.best[0]) <= 1.2
    assert result.best_fitness > 0.75  # it climbed from the start's T_1 = 0.75


def test_a_start_that_gives_nan_is_left_behind():
    # NaN whenever T_1 < 1 s, the start included: the set starts at -inf and must climb out.
    def evaluate(t):
        t = np.asarray(t)
        return np.where(t[:, 0] < 1.0, np.nan, -((t[:, 0] - 1.5) ** 2))

    result = transition_search(evaluate, DURATION, key=jr.key(10), initial=[0.5, 2.0])
    assert np.all(result.history.fitness[:Q] == -np.inf)
    assert np.isfinite(result.best_fitness) and float(result.best[0]) >= 1.0
    assert np.all(np.isfinite(np.asarray(result.fitness)))  # -inf has been ranked out


@pytest.mark.parametrize("num_transitions", [1, 2, 4])
def test_the_default_start_is_equally_spaced(num_transitions):
    evaluate = Recorder(quadratic(np.zeros(num_transitions)))
    result = transition_search(
        evaluate, DURATION, key=jr.key(0), num_transitions=num_transitions, rounds=0
    )
    k = num_transitions + 1
    expected = np.arange(1, k) * DURATION / k
    np.testing.assert_allclose(evaluate.calls[0], np.tile(expected, (Q, 1)), rtol=1e-6)
    assert len(evaluate.calls) == 1 and result.evaluations == Q


@pytest.mark.parametrize("tick", [None, 0.25])
def test_the_users_initial_guess_is_the_start(tick):
    guess = [0.3, 0.3, 2.6]  # two transitions at once: a phase of zero length
    evaluate = Recorder(quadratic(np.zeros(3)))
    result = transition_search(
        evaluate, DURATION, key=jr.key(0), initial=guess, tick=tick, rounds=0
    )
    # With a tick of 0.25 s the guess is rounded to the nearest whole ticks.
    expected = guess if tick is None else [0.25, 0.25, 2.5]
    np.testing.assert_allclose(evaluate.calls[0], np.tile(expected, (Q, 1)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(result.best), expected, rtol=1e-6)


def test_mutation_randomises_a_third_of_the_time_and_perturbs_by_the_scale():
    """Every point starts mid-way between its neighbours, 0.75 s from each. With a
    tiny perturb_scale a perturbation stays within 5 standard deviations, and a
    randomisation rarely does (1% of the time): the share of far moves is the share of
    randomisations. Q arrays x 64 steps = 1,024 mutations."""
    scale = 1e-3
    width = 1.5  # s, hi - lo for every point
    search = TransitionSearch(DURATION, perturb_scale=scale)
    start = np.tile([0.75, 1.5, 2.25], (Q, 1))
    moves, which = [], []
    for k in range(64):
        mutants = np.asarray(
            search.ask(never_called, state_of(start, np.zeros(Q), key=k)), dtype=np.float64
        )
        changed = mutants != start
        assert np.all(changed.sum(axis=1) <= 1)
        i = np.argmax(np.abs(mutants - start), axis=1)
        which.append(i)
        moves.append((mutants - start)[np.arange(Q), i])
    moves, which = np.concatenate(moves), np.concatenate(which)
    far = np.abs(moves) > 5 * scale * width
    # Shares of 1,024 draws: a standard deviation of 0.015; tolerances of about 3.
    share_tolerance = 0.05
    assert abs(far.mean() - 1 / 3 * 0.99) < share_tolerance
    assert np.all(np.abs(np.bincount(which, minlength=3) / which.size - 1 / 3) < share_tolerance)
    # Randomised points land anywhere between the neighbours (uniform: mean at the middle,
    # and a quarter of them in each quarter of the interval).
    landed = (moves[far] + width / 2) / width
    assert np.all((landed >= 0) & (landed <= 1))
    quarters = np.bincount(np.minimum((landed * 4).astype(int), 3), minlength=4) / far.sum()
    assert np.all(np.abs(quarters - 0.25) < 0.1)  # about 340 draws: sd 0.024 per quarter
    # Perturbations: Gaussian with sd perturb_scale * (hi - lo), within 10% (sd of the
    # estimate from about 680 draws: 3%).
    np.testing.assert_allclose(np.std(moves[~far]), scale * width, rtol=0.1)


@settings(max_examples=20, deadline=None)
@given(
    duration=st.floats(0.5, 5.0),
    num_ticks=st.one_of(st.none(), st.integers(1, 400)),
    perturb_scale=st.floats(0.01, 2.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_mutants_stay_ordered_within_the_duration_and_on_the_grid(
    duration, num_ticks, perturb_scale, seed
):
    """From any ordered set (equal neighbours and points at the bounds included), every
    mutant moves at most one point and stays ascending within [0, duration], on the grid
    when there is a tick. One shape: one compilation for all examples."""
    tick = None if num_ticks is None else duration / num_ticks
    search = TransitionSearch(duration, tick=tick, perturb_scale=perturb_scale)
    rng = np.random.default_rng(seed)
    if tick is None:
        start = rng.uniform(0, duration, size=(Q, 3))
        start[rng.uniform(size=(Q, 3)) < 0.2] = 0.0
        start[rng.uniform(size=(Q, 3)) < 0.2] = duration
    else:
        start = rng.integers(0, num_ticks + 1, size=(Q, 3)) * np.float32(tick)
    start = np.sort(np.minimum(start.astype(np.float32), np.float32(duration)), axis=1)
    mutants = np.asarray(search.ask(never_called, state_of(start, np.zeros(Q), key=seed)))
    assert ascending_within(mutants, np.float32(duration))
    assert np.all(np.sum(mutants != start, axis=1) <= 1)
    if tick is not None:
        assert on_grid(mutants, tick)


def never_called(t):
    raise AssertionError("evaluate must not be called for a bad argument")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"duration": 0.0}, "duration = 0.0"),
        ({"duration": -1.0}, "duration = -1.0"),
        ({"duration": float("nan")}, "duration = nan"),
        ({"duration": "3"}, "duration = '3'"),
        ({"num_arrays": 1}, "num_arrays = 1"),
        ({"num_arrays": 0}, "num_arrays = 0"),
        ({"num_arrays": 2.0}, "num_arrays = 2.0"),
        ({"num_arrays": True}, "num_arrays = True"),
        ({"rounds": -1}, "rounds = -1"),
        ({"mutations": 0}, "mutations = 0"),
        ({"perturb_scale": 0.0}, "perturb_scale = 0.0"),
        ({"tick": 0.0}, "tick = 0.0"),
        ({"tick": -0.01}, "tick = -0.01"),
        ({"tick": 0.7}, "tick = 0.7 with duration = 3.0"),
        ({"tick": 4.0}, "tick = 4.0 with duration = 3.0"),
        ({"num_transitions": None}, "initial = None and num_transitions = None"),
        ({"num_transitions": 0}, "num_transitions = 0"),
        ({"initial": [1.0, 2.0, 3.5]}, r"initial = \[1.0, 2.0, 3.5\]"),
        ({"initial": [-0.1, 2.0]}, r"initial = \[-0.1, 2.0\]"),
        ({"initial": [2.0, 1.0]}, r"initial = \[2.0, 1.0\]"),
        ({"initial": [1.0, float("nan")]}, r"initial = \[1.0, nan\]"),
        ({"initial": [[1.0, 2.0]]}, r"initial has shape \(1, 2\)"),
        ({"initial": []}, r"initial has shape \(0,\)"),
        ({"initial": [1.0, 2.0], "num_transitions": 3}, "num_transitions = 3 but initial"),
    ],
)
def test_bad_arguments_raise_before_anything_runs(kwargs, match):
    arguments = {"duration": DURATION, "num_transitions": 2} | kwargs
    if "initial" in kwargs and "num_transitions" not in kwargs:
        del arguments["num_transitions"]
    duration = arguments.pop("duration")
    with pytest.raises(ValueError, match=match):
        transition_search(never_called, duration, key=jr.key(0), **arguments)


@pytest.mark.parametrize("shape", [(Q, 1), (), (Q - 1,)])
def test_evaluate_of_the_wrong_shape_is_named(shape):
    with pytest.raises(ValueError, match=r"expected \(16,\)"):
        transition_search(lambda t: np.zeros(shape), DURATION, key=jr.key(0), num_transitions=2)
