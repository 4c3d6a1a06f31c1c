"""The third paper's generational evolution (`Evolve`, `evolve`): the generation operator's
proportions, the mutation kinds within a generation, survivors keeping their fitness, pinned
members surviving, improvement, and reproducibility from the key."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from scipy import stats

import jaxmotion as jm

# Chi-square tests: reject only what is very unlikely at the fixed keys.
P_VALUE = 1e-3
SIZE = 20  # 4 survivors, 12 offspring, 4 new: one evaluation call of 16
GENERATIONS = 4


@pytest.fixture(scope="module")
def task():
    """The snake travelling for 0.5 s: one compilation serves the whole module."""
    snake = jm.figures.snake()
    return jm.Task(
        snake,
        jm.World(),
        jm.SpringNetSpace(snake),
        jm.Objective({"distance": 1.0}),
        duration=0.5,
        dt=0.005,
    )


@pytest.fixture(scope="module")
def result(task):
    return jm.evolve(task, key=jr.key(0), generations=GENERATIONS, size=SIZE)


def fake_state(task, size, key):
    """A ranked generation with made-up fitness (no simulation): what `ask` reads."""
    population = task.sample(size, key=key)
    fitness = -jnp.arange(size, dtype=float)
    return jm.EvolveState(
        population=population,
        fitness=fitness,
        origin=jnp.full((size,), 2, dtype=jnp.int32),
        parent=jnp.full((size,), -1, dtype=jnp.int32),
        key=jr.key(11),
        generation=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(size, dtype=jnp.int32),
    )


def leaves(tree, i):
    return [np.asarray(a[i]) for a in jax.tree_util.tree_leaves(tree)]


def same(tree_a, i, tree_b, j) -> bool:
    return all(
        np.array_equal(a, b) for a, b in zip(leaves(tree_a, i), leaves(tree_b, j), strict=True)
    )


def test_a_generation_is_survivors_offspring_and_new_in_the_papers_proportions(task):
    """From a generation of 1,000: 200 survive, each makes 3 offspring, 200 are new; with
    one mutation per offspring, the kinds of mutation (read off each offspring against its
    parent) follow the paper's shares (chi-square at a fixed key)."""
    from test_spring_net import classify

    size = 1000
    search = jm.Evolve(size=size, mutations=1)
    state = fake_state(task, size, jr.key(5))
    children = search.ask(task, state)
    assert jax.tree_util.tree_leaves(children)[0].shape[0] == 800
    kinds = []
    for c in range(600):
        parent = jax.tree_util.tree_map(lambda a, c=c: a[c // 3], state.population)
        child = jax.tree_util.tree_map(lambda a, c=c: a[c], children)
        kinds.append(classify(parent, child))
    counts = np.bincount(kinds, minlength=4)
    assert stats.chisquare(counts, 600 * np.asarray(jm.MUTATION_PROBABILITIES)).pvalue > P_VALUE
    # The new nets are random draws: none shares its masses with a survivor.
    survivors = np.asarray(state.population.masses[:200])
    new = np.asarray(children.masses[600:])
    assert not np.any((new[:, None, :] == survivors[None, :, :]).all(axis=-1))
    # The origins after `tell`, whatever the fitness: 200 / 600 / 200.
    told = search.tell(state, children, jnp.zeros(800))
    np.testing.assert_array_equal(np.bincount(np.asarray(told.origin)), [200, 600, 200])
    assert int(told.evaluations) == size + 800


def test_offspring_get_one_to_max_mutations(task):
    """Each offspring is hit by 1..mutations mutations, all counts drawn (uniformly)."""
    space = task.space
    size = 500
    search = jm.Evolve(size=size, mutations=3)
    # Survivors in the middle of every bound, so every mutation shows in the child.
    n, p = space.num_masses, space.num_springs
    middle = jm.SpringNet(np.ones(n), np.full(p, 7.0), np.zeros(n), space.tau, space.ranges)
    state = fake_state(task, size, jr.key(2))
    population = jax.tree_util.tree_map(
        lambda a, m: jnp.broadcast_to(m, a.shape), state.population, middle
    )
    state = jm.EvolveState(
        population,
        state.fitness,
        state.origin,
        state.parent,
        state.key,
        state.generation,
        state.evaluations,
    )
    children = search.ask(task, state)
    changed = [
        sum(
            int(np.sum(np.asarray(getattr(children, f)[c]) != np.asarray(getattr(middle, f))))
            for f in ("masses", "positions")
        )
        + int(np.any(np.asarray(children.stiffness[c]) != 7.0))
        for c in range(300)
    ]
    assert min(changed) >= 1
    assert max(changed) >= 2  # some offspring were hit more than once


def test_survivors_keep_their_fitness_and_the_best_never_gets_worse(result):
    """Survivors are not evaluated again: each generation evaluates 4 size / 5 controllers,
    and every survivor carries the fitness it was first given. The best fitness never
    decreases and has improved on the first generation's."""
    history = result.history
    assert len(history) == SIZE + (GENERATIONS - 1) * (SIZE * 4 // 5)
    state = result.state
    survivors = np.asarray(state.origin) == 0
    assert survivors.sum() == SIZE // 5
    evaluated = set(np.asarray(history.fitness).tolist())
    assert all(float(f) in evaluated for f in np.asarray(state.fitness)[survivors])
    best = [history.fitness[history.step <= g].max() for g in range(GENERATIONS)]
    assert np.all(np.diff(best) >= 0)
    assert best[-1] > best[0]
    assert result.best_fitness == pytest.approx(best[-1], rel=0, abs=0)


def test_the_best_replays_alone_to_its_recorded_fitness(task, result):
    one = jax.tree_util.tree_map(lambda a: a[None], result.best)
    assert float(task.evaluate(one)[0]) == result.best_fitness


def test_pinned_members_survive(task, result):
    """Hand selection: the worst members, pinned, survive the next generation (as
    survivors, with their fitness), ahead of better ones."""
    search = jm.Evolve(size=SIZE)
    state = result.state
    picked = [SIZE - 1, SIZE - 3]
    pinned = search.pin(state, picked)
    assert same(pinned.population, 0, state.population, SIZE - 1)
    after, _ = search.step(task, pinned)
    for i in picked:
        found = [j for j in range(SIZE) if same(after.population, j, state.population, i)]
        assert found, f"pinned member {i} did not survive"
        assert int(after.origin[found[0]]) == 0
        assert float(after.fitness[found[0]]) == float(state.fitness[i])
    with pytest.raises(ValueError, match="at most size / 5 = 4"):
        search.pin(state, list(range(5)))
    with pytest.raises(ValueError, match="distinct indices"):
        search.pin(state, [1, 1])


def test_the_select_hook_pins_and_the_search_is_reproducible(task, result):
    """`evolve(select=...)` pins what the hook returns before each generation; the same key
    gives the same search."""
    again = jm.evolve(task, key=jr.key(0), generations=GENERATIONS, size=SIZE)
    np.testing.assert_array_equal(again.history.fitness, result.history.fitness)
    seen = []

    def select(state):
        seen.append(int(state.generation))
        return [SIZE - 1]

    worst = result.state
    more = jm.evolve(task, key=jr.key(1), generations=1, size=SIZE, state=worst, select=select)
    assert seen == [GENERATIONS - 1]
    assert any(same(more.state.population, j, worst.population, SIZE - 1) for j in range(SIZE))
    assert len(more.history) == SIZE * 4 // 5


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="size = 12; allowed: a multiple of 5"):
        jm.Evolve(size=12)
    with pytest.raises(ValueError, match="mutations = 0"):
        jm.Evolve(size=10, mutations=0)
