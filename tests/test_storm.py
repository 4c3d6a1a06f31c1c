"""NaN storms: random and extreme controllers on bodies at the edge of stability, through
`Task.evaluate` and every searcher. A blown-up run is data (fitness `-inf`, counted), never a
NaN in a fitness, a history or a population, and the search carries on."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

STORM = 10_000  # random controllers per body
CHUNK = 16  # every evaluation below runs in calls of 16, so each body compiles once


def _cube():
    # Springs stiff enough that dt = 5 ms is at the edge of stability (measured: 62% of
    # random controllers blow up at 2e4 N/m, 1% at 1.5e4, 99% at 2.5e4), and the largest
    # reflex amplitudes the space allows (scale and splay just below 1).
    return jm.Task(
        jm.lattices.cube(stiffness=2e4),
        jm.World(),
        jm.RegimesSpace(4, 0.2, amplitudes=(0.99, 3.0, 0.99, 6.0)),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=0.2,
        dt=5e-3,
    )


def _star_man():
    # The shortest time constant there is (one step), a floor stiff enough for a coarse step
    # to be at the edge of stability (measured: half of random controllers blow up).
    return jm.Task(
        jm.figures.star_man(),
        jm.World(floor_stiffness=1e8, floor_damping=10.0),
        jm.TimeBSRSpace(jm.figures.star_man(), num_rules=4, t_per=0.2, tau_min=0.01, tau_max=0.02),
        jm.Objective({"forward": 1.0}),
        duration=0.2,
        dt=0.01,
    )


TASKS = {"cube": _cube, "star_man": _star_man}


@pytest.fixture(scope="module", params=sorted(TASKS))
def task(request):
    return TASKS[request.param]()


def _finite_params(population) -> bool:
    return all(
        bool(jnp.all(jnp.isfinite(a)))
        for a in jax.tree_util.tree_leaves(population)
        if jnp.issubdtype(a.dtype, jnp.inexact)
    )


def test_a_storm_of_random_and_extreme_controllers_scores_no_nan(task):
    controllers = task.sample(STORM, key=jr.key(0))
    # Extreme ones among them: every float parameter at +inf, NaN or 1e30 in a few members.
    poisoned = {0: jnp.inf, 1: jnp.nan, 2: 1e30}
    for index, value in poisoned.items():
        controllers = jax.tree_util.tree_map(
            lambda a, i=index, v=value: (
                a.at[i].set(v) if jnp.issubdtype(a.dtype, jnp.inexact) else a
            ),
            controllers,
        )
    fitness = np.asarray(task.evaluate(controllers, chunk=CHUNK))
    assert fitness.shape == (STORM,)
    assert not np.any(np.isnan(fitness))
    assert np.all(np.isfinite(fitness) | np.isneginf(fitness))  # never +inf
    blown = int(np.sum(np.isneginf(fitness)))
    # A real storm: runs blow up, and others do not (the measure can fail both ways).
    assert 0 < blown < STORM, blown
    assert np.all(np.isneginf(fitness[[0, 1]]))  # infinite and NaN parameters


def test_every_searcher_keeps_nan_out_and_counts_what_blew_up(task):
    runs = {
        "parallel_hill_climb": jm.parallel_hill_climb(
            task, key=jr.key(1), evaluations=64, size=CHUNK, batch=CHUNK
        ),
        "serial_search": jm.serial_search(
            task, key=jr.key(2), climbers=CHUNK, generations=4, reseed_every=2
        ),
        "evolve": jm.evolve(task, key=jr.key(3), generations=3, size=20, mutations=3),
    }
    for name, result in runs.items():
        history = result.history
        assert not np.any(np.isnan(history.fitness)), name
        assert history.num_nonfinite == int(np.sum(np.isneginf(history.fitness))), name
        assert history.num_nonfinite > 0, name  # the storm reached the search
        state = result.state
        assert not np.any(np.isnan(np.asarray(state.fitness))), name
        assert _finite_params(state.population), name
        # The search carried on: its best is a finite motion, found after the first step.
        assert np.isfinite(result.best_fitness), name


def test_tell_refuses_nan_fitness_and_non_finite_children():
    """Fitness from outside `evaluate` (an ask/tell user's own) may be NaN, and a child may
    have parameters that are not finite: neither enters the search set."""
    task = _cube()
    search = jm.ParallelHillClimb(size=4, batch=4)
    population = task.sample(4, key=jr.key(4))
    state = jm.HillClimbState(
        population=population,
        fitness=jnp.array([3.0, 2.0, 1.0, 0.0]),
        key=jr.key(5),
        step=jnp.asarray(0, dtype=jnp.int32),
        evaluations=jnp.asarray(4, dtype=jnp.int32),
    )
    children = jax.tree_util.tree_map(
        lambda a: a.at[1].set(jnp.nan) if jnp.issubdtype(a.dtype, jnp.inexact) else a,
        task.sample(4, key=jr.key(6)),
    )
    after = search.tell(state, children, jnp.array([jnp.nan, 10.0, -1.0, 0.5]))
    # Child 0 (NaN fitness) and child 1 (NaN parameters, fitness 10) are out; child 3 (0.5)
    # replaces the incumbent at 0.0; child 2 (-1.0) is not kept.
    np.testing.assert_array_equal(np.asarray(after.fitness), [3.0, 2.0, 1.0, 0.5])
    assert _finite_params(after.population)


def test_evolve_replaces_a_child_with_non_finite_parameters_by_its_parent():
    task = _cube()
    search = jm.Evolve(size=5, mutations=1)
    state, _ = search.init(task, key=jr.key(7))
    children = search.ask(task, state)  # 3 offspring of member 0, then 1 new
    children = jax.tree_util.tree_map(
        lambda a: a.at[2].set(jnp.inf) if jnp.issubdtype(a.dtype, jnp.inexact) else a, children
    )
    after = search.tell(state, children, jnp.array([1.0, 2.0, 5.0, 3.0]))
    assert _finite_params(after.population)
    # The child with infinite parameters (told fitness 5.0) is scored -inf, ranked last.
    fitness = np.asarray(after.fitness)
    assert fitness[-1] == -np.inf and 5.0 not in fitness
    assert sorted(fitness[:-1].tolist()) == sorted([1.0, 2.0, 3.0, float(state.fitness[0])])
