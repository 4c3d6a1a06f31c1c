"""Serial search: the paper's algorithm (keep a mutant only if strictly better, reseed every R
generations), batched seeds bitwise equal to seeds run alone, and that it climbs.

Every search here evaluates batches of 3 or 6 controllers, so the whole file compiles the
simulation twice."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm


def tiny_task(stiffness=2000.0):
    # The spider for 0.2 s: the cheapest task that still moves. Stiffness is an array in the
    # lattice, so a stiffer spider reuses the same compiled simulation.
    return jm.Task(
        jm.lattices.pyramid(stiffness=stiffness),
        jm.World(),
        jm.RegimesSpace(num_regimes=2, t_per=0.5),
        jm.Objective({"forward": 1.0}),
        duration=0.2,
        dt=0.002,
    )


def on_host(tree):
    """The pytree with NumPy leaves (keys as their data), to index and compare cheaply."""
    return jax.tree_util.tree_map(
        lambda a: np.asarray(jr.key_data(a) if jnp.issubdtype(a.dtype, jax.dtypes.prng_key) else a),
        tree,
    )


def assert_same(a, b):
    """Bitwise equal pytrees (keys compared by their data)."""
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    leaves = lambda t: jax.tree_util.tree_leaves(on_host(t))
    for x, y in zip(leaves(a), leaves(b), strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)


def per_climber(tree, s, c):
    return jax.tree_util.tree_map(lambda a: a[s, c], tree)


def test_serial_search_climbs_above_the_random_start():
    task = tiny_task()
    seen = []
    result = jm.serial_search(
        task,
        key=jr.key(0),
        seeds=2,
        climbers=3,
        generations=40,
        reseed_every=10,
        callback=lambda state, parts: seen.append(
            (int(state.generation), [p.step.tolist() for p in parts])
        ),
    )
    assert [g for g, _ in seen] == list(range(41))
    assert all(steps == [[g] * 3, [g] * 3] for g, steps in seen)
    assert len(result.runs) == 2
    for run in result.runs:
        initial_best = run.history.fitness[:3].max()
        assert run.best_fitness > initial_best
        assert run.best_fitness == run.history.fitness.max()
        assert len(run.history) == 3 * 41
        assert np.bincount(run.history.step).tolist() == [3] * 41
    assert int(result.state.generation) == 40
    assert int(result.state.evaluations) == 3 * 41
    # The best over the seeds, and the seed that found it.
    winner = int(np.argmax([run.best_fitness for run in result.runs]))
    assert result.seed == winner
    assert result.best_fitness == result.runs[winner].best_fitness
    assert result.history is result.runs[winner].history
    assert_same(result.best, result.runs[winner].best)
    # The state holds the controllers whose fitness it lists (one call of the same width).
    population = jax.tree_util.tree_map(
        lambda a: a.reshape(6, *a.shape[2:]), result.state.population
    )
    np.testing.assert_array_equal(
        np.asarray(task.evaluate(population)).reshape(2, 3), np.asarray(result.state.fitness)
    )


@pytest.mark.parametrize("seeds, climbers", [(2, 3), (1, 6)])
def test_reseeding_ranks_and_copies_the_top_half_exactly_every_R_generations(seeds, climbers):
    """Stepping init / ask / tell by hand: at generations 3 and 6 (R = 3) each seed's set is
    ranked (stably) and its worse floor(C/2) are copies of its best floor(C/2), fitness
    included; at the others it is just the climbers with their better mutants kept."""
    task = tiny_task()
    search = jm.SerialSearch(climbers=climbers, reseed_every=3)
    state, initial = search.init(task, key=jr.key(1), seeds=seeds)
    # One round of initial evaluations (no enrichment), the climbers' fitness.
    np.testing.assert_array_equal(np.asarray(initial), np.asarray(state.fitness)[None])
    half = climbers // 2
    changed = 0
    for g in range(1, 8):
        mutants = search.ask(task, state)
        fitness = task.evaluate(mutants)
        new_state = search.tell(state, mutants, fitness)
        assert int(new_state.generation) == g
        mutants = on_host(mutants)
        mutants = jax.tree_util.tree_map(
            lambda a: a.reshape(seeds, climbers, *a.shape[1:]), mutants
        )
        fitness = np.asarray(fitness).reshape(seeds, climbers)
        old = np.asarray(state.fitness)
        new, population = on_host(new_state), on_host(state.population)
        kept = fitness > old
        for s in range(seeds):
            kept_fitness = np.where(kept[s], fitness[s], old[s])
            source = list(range(climbers))
            if g % 3 == 0:
                order = np.argsort(-kept_fitness, kind="stable")
                source = [int(order[c]) for c in range(climbers - half)]
                source += [int(order[c]) for c in range(half)]
                changed += source != list(range(climbers))
                # The bottom half is the top half, controllers and fitness.
                assert_same(
                    per_climber(new.population, s, slice(climbers - half, None)),
                    per_climber(new.population, s, slice(0, half)),
                )
                np.testing.assert_array_equal(
                    np.asarray(new.fitness[s, climbers - half :]), np.asarray(new.fitness[s, :half])
                )
                assert np.all(np.diff(np.asarray(new.fitness[s, : climbers - half])) <= 0)
            np.testing.assert_array_equal(np.asarray(new.fitness[s]), kept_fitness[source])
            for c, i in enumerate(source):
                parent = mutants if kept[s, i] else population
                assert_same(per_climber(new.population, s, c), per_climber(parent, s, i))
        state = new_state
    assert changed > 0  # the reseedings did rearrange some set


def test_batched_seeds_are_bitwise_the_seeds_run_alone():
    task = tiny_task()
    settings = dict(climbers=3, generations=12, reseed_every=4)
    batched = jm.serial_search(task, key=jr.key(5), seeds=2, **settings)
    for s in range(2):
        alone = jm.serial_search(task, key=jr.key(5), seed_offset=s, **settings)
        run = batched.runs[s]
        np.testing.assert_array_equal(alone.history.fitness, run.history.fitness)
        np.testing.assert_array_equal(alone.history.step, run.history.step)
        assert alone.best_fitness == run.best_fitness
        assert alone.seed == s
        assert_same(alone.best, run.best)
        assert_same(alone.state, run.state)
        assert_same(alone.state, batched.state.seed(s))
    # The seeds are different searches.
    assert not np.array_equal(batched.runs[0].history.fitness, batched.runs[1].history.fitness)


@pytest.mark.parametrize("family", ["time_bsr", "sense_bsr"])
def test_a_seeds_mutants_do_not_depend_on_the_other_seeds(family):
    """`ask` for seed s of a batch of 3 seeds draws bitwise the mutants that seed alone draws.
    With 10 climbers (the configs' number) a seed alone has climbers 8 and 9 past the first
    group of 8 vector lanes, where XLA's scalar code rounds `exp` and `log` differently; a
    1-ulp difference in a mutation is a different search on a chaotic motion (it was:
    Star-Man's time-based shuffle, seeds 0-4 batched against seed 0 alone, parted at
    evaluation 19; the time-based rules' mutants differed here)."""
    star = jm.figures.star_man()
    if family == "time_bsr":
        space = jm.TimeBSRSpace(star, num_rules=4, t_per=0.5, tau_min=0.05, tau_max=1.0)
    else:
        space = jm.SenseBSRSpace(star, num_rules=10, tau_min=0.05, tau_max=1.0)
    task = jm.Task(star, jm.World(), space, jm.Objective({"forward": 1.0}), duration=0.2)
    seeds, climbers = 3, 10
    population = task.sample(seeds * climbers, key=jr.key(0))
    motion = None
    if type(task.space).uses_motion:
        # Made-up perceived senses (20 samples of the 12), as `evaluate_sensed` records them.
        motion = jr.uniform(jr.key(1), (seeds, climbers, 20, star.num_senses))
    state = jm.SerialSearchState(
        population=jax.tree_util.tree_map(
            lambda a: a.reshape(seeds, climbers, *a.shape[1:]), population
        ),
        fitness=jnp.zeros((seeds, climbers)),
        key=jr.split(jr.key(2), seeds),
        generation=jnp.asarray(7, dtype=jnp.int32),
        evaluations=jnp.asarray(0, dtype=jnp.int32),
        motion=motion,
    )
    search = jm.SerialSearch(climbers=climbers, reseed_every=5)
    per_seed = lambda flat: jax.tree_util.tree_map(
        lambda a: a.reshape(-1, climbers, *a.shape[1:]), on_host(flat)
    )
    batched = per_seed(search.ask(task, state))
    for s in range(seeds):
        alone = per_seed(search.ask(task, state.seed(s)))
        for c in range(climbers):
            assert_same(per_climber(alone, 0, c), per_climber(batched, s, c))


def test_a_climber_only_gets_better_except_at_reseeding():
    """Per climber, fitness after a generation is the old one or its mutant's if strictly
    greater; at a reseeding the k-th best of the set never gets worse."""
    task = tiny_task()
    seen = []
    jm.serial_search(
        task,
        key=jr.key(2),
        seeds=2,
        climbers=3,
        generations=12,
        reseed_every=4,
        callback=lambda state, parts: seen.append(
            (np.asarray(state.fitness), np.stack([p.fitness for p in parts]))
        ),
    )
    replaced = 0
    for g in range(1, 13):
        before, after, mutants = seen[g - 1][0], seen[g][0], seen[g][1]
        if g % 4:
            np.testing.assert_array_equal(after, np.where(mutants > before, mutants, before))
            assert np.all(after >= before)
            replaced += np.sum(after > before)
        else:
            ranked = lambda f: -np.sort(-f, axis=1)
            assert np.all(ranked(after) >= ranked(before))
    assert replaced > 0


def test_ties_do_not_replace_and_blown_up_mutants_are_never_kept():
    task = tiny_task()
    search = jm.SerialSearch(climbers=3, reseed_every=100)
    state, _ = search.init(task, key=jr.key(3), seeds=2)
    mutants = search.ask(task, state)
    old = np.asarray(state.fitness)
    # Seed 0: a tie, a blow-up, a NaN; seed 1: a better one, a blow-up on a blown-up climber
    # and a NaN on a blown-up climber.
    dtype = old.dtype
    blown_up = np.array([old[0], [old[1, 0], -np.inf, -np.inf]], dtype=dtype)
    state = eqx.tree_at(lambda st: st.fitness, state, jnp.asarray(blown_up))
    fitness = np.array([[old[0, 0], -np.inf, np.nan], [old[1, 0] + 1.0, -np.inf, np.nan]])
    new = search.tell(state, mutants, jnp.asarray(fitness, dtype=dtype))
    expected = np.array([old[0], [old[1, 0] + 1.0, -np.inf, -np.inf]], dtype=dtype)
    np.testing.assert_array_equal(np.asarray(new.fitness), expected)
    per_seed = jax.tree_util.tree_map(lambda a: a.reshape(2, 3, *a.shape[1:]), mutants)
    assert_same(per_climber(new.population, 1, 0), per_climber(per_seed, 1, 0))
    for s, c in [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2)]:
        assert_same(per_climber(new.population, s, c), per_climber(state.population, s, c))


def test_blown_up_runs_are_recorded_and_never_replace_a_finite_climber():
    # Springs this stiff make the fixed-step simulation blow up for some controllers only.
    task = tiny_task(stiffness=2.1e5)
    states = []
    result = jm.serial_search(
        task,
        key=jr.key(0),
        seeds=2,
        climbers=3,
        generations=10,
        reseed_every=100,
        callback=lambda state, parts: states.append(np.asarray(state.fitness)),
    )
    histories = [run.history for run in result.runs]
    assert sum(h.num_nonfinite for h in histories) > 0  # the test needs blow-ups
    assert sum(len(h) - h.num_nonfinite for h in histories) > 0  # and runs that did not
    assert not any(np.any(np.isnan(h.fitness)) for h in histories)
    for before, after in itertools.pairwise(states):
        assert not np.any(np.isnan(after))
        # A climber is -inf only if it was -inf and no mutant did better.
        assert np.all(np.isfinite(after) | np.isneginf(before))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(climbers=0), r"climbers = 0; allowed: an integer >= 1"),
        (dict(climbers=2.5), r"climbers = 2.5; allowed: an integer >= 1"),
        (dict(climbers=True), r"climbers = True; allowed: an integer >= 1"),
        (dict(generations=0), r"generations = 0; allowed: an integer >= 1"),
        (dict(reseed_every=0), r"reseed_every = 0; allowed: an integer >= 1"),
        (dict(seeds=0), r"seeds = 0; allowed: an integer >= 1"),
        (dict(seeds=1.0), r"seeds = 1.0; allowed: an integer >= 1"),
        (dict(seed_offset=-1), r"seed_offset = -1; allowed: an integer >= 0"),
        (dict(archive=-1), r"archive = -1; allowed: an integer >= 0"),
    ],
)
def test_bad_settings_raise_before_anything_compiles(monkeypatch, kwargs, message):
    import jaxmotion._search.serial as serial

    def compiled(*args, **kwargs):
        raise AssertionError("the search started before checking its settings")

    monkeypatch.setattr(serial, "_sample", compiled)
    with pytest.raises(ValueError, match=message):
        jm.serial_search(tiny_task(), key=jr.key(0), **kwargs)
    if "climbers" in kwargs or "reseed_every" in kwargs:
        with pytest.raises(ValueError, match=message):
            jm.SerialSearch(**kwargs)


@pytest.mark.parametrize("size", [4, 50])  # fewer places than controllers held; more
def test_the_archive_keeps_the_fittest_controllers_ever_held(size):
    """`archive = K`: each seed's K fittest controllers it ever held as climbers (the
    initial set, every kept mutant; reseeding's copies are nothing new), best first, stably;
    unfilled places `-inf`. Followed here from the outside, step by step; the search itself
    is bitwise the one without an archive, and `fittest` reads the archive."""
    task = tiny_task()
    seeds, climbers = 2, 3
    held = [[] for _ in range(seeds)]  # per seed: (fitness, controller), in the order held

    def hold(state, controllers, fitness, kept):
        for s, c in itertools.product(range(seeds), range(climbers)):
            if kept[s, c]:
                held[s].append((float(fitness[s, c]), on_host(per_climber(controllers, s, c))))

    searches = {}
    for size_ in (0, size):
        search = jm.SerialSearch(climbers=climbers, reseed_every=7, seeds=seeds, archive=size_)
        state, _ = search.init(task, key=jr.key(3))
        if size_:
            hold(state, state.population, state.fitness, np.ones((seeds, climbers), bool))
        for _ in range(30):
            mutants = search.ask(task, state)
            fitness, extras = search.evaluate(task, state, mutants)
            if size_:
                per_seed = jax.tree_util.tree_map(
                    lambda a: a.reshape(seeds, climbers, *a.shape[1:]), mutants
                )
                f = np.asarray(fitness).reshape(seeds, climbers)
                hold(state, per_seed, f, f > np.asarray(state.fitness))
            state = search.tell(state, mutants, fitness, **extras)
        searches[size_] = state

    plain, state = searches[0], searches[size]
    assert plain.archive is None and plain.archive_fitness is None
    assert_same(plain.population, state.population)
    assert_same(plain.fitness, state.fitness)
    assert len(held[0]) > climbers  # mutants were kept: more than the first set was held
    for s in range(seeds):
        ranked = sorted(held[s], key=lambda fc: -fc[0])[:size]  # stable: first held first
        expect = [f for f, _ in ranked] + [-np.inf] * (size - len(ranked))
        np.testing.assert_array_equal(np.asarray(state.archive_fitness[s]), expect)
        for k, (_, controller) in enumerate(ranked):
            assert_same(per_climber(state.archive, s, k), controller)

    result = jm.SearchResult(best=None, best_fitness=0.0, history=None, state=state)
    chosen, fitness = jm.fittest(result, 5)
    everything = np.asarray(state.archive_fitness).reshape(-1)
    np.testing.assert_array_equal(fitness, np.sort(everything)[::-1][:5])
    top = np.unravel_index(np.argmax(everything), state.archive_fitness.shape)
    assert_same(jax.tree_util.tree_map(lambda a: a[0], chosen), per_climber(state.archive, *top))
