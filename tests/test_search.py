"""Parallel hill climbing: the paper's algorithm, its bookkeeping, and that it works."""

import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm


def forward_task(duration=2.0):
    return jm.Task(
        jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 0.5),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=duration,
    )


def test_hill_climbing_raises_the_best_fitness_well_above_random():
    task = forward_task()
    result = jm.parallel_hill_climb(task, key=jr.key(0), evaluations=2000, batch=50)
    initial_best = result.history.fitness[:100].max()
    assert len(result.history) == 2100
    assert result.best_fitness == result.history.fitness.max()
    # "Well above" (thresholds that keys 0, 1 and 2 all meet): at least 0.5 m and 25% more
    # forward travel in 2 s than the best of the 100 random controllers, and the whole search
    # set has climbed: its median now beats that best random controller.
    assert result.best_fitness > initial_best + 0.5
    assert result.best_fitness > 1.25 * initial_best
    assert np.median(np.asarray(result.state.fitness)) > initial_best
    # The best controller really does that when replayed alone.
    replay = float(task.fitness(task.simulate(result.best)))
    assert replay == result.best_fitness


def test_batch_one_is_the_papers_algorithm():
    """Each step perturbs one member, inserts the copy by rank and drops the lowest: the set
    keeps its size and stays sorted, and it changes only if the copy beats the worst."""
    task = forward_task(duration=0.5)
    search = jm.ParallelHillClimb(size=10, batch=1)
    state, initial = search.init(task, key=jr.key(1))
    np.testing.assert_array_equal(np.asarray(state.fitness), np.sort(np.asarray(initial))[::-1])
    for _ in range(15):
        before = np.asarray(state.fitness)
        state, fitness = search.step(task, state)
        after = np.asarray(state.fitness)
        child = float(fitness[0])
        expected = np.sort(np.append(before, child))[::-1][:10]
        np.testing.assert_array_equal(after, expected)
        assert np.all(np.diff(after) <= 0)
    assert int(state.step) == 15 and int(state.evaluations) == 25
    # The population really holds the controllers whose fitness it lists.
    np.testing.assert_allclose(
        np.asarray(task.evaluate(state.population)), np.asarray(state.fitness), atol=1e-5
    )


def test_search_is_reproducible_and_counts_every_evaluation():
    task = forward_task(duration=0.5)
    run = lambda seed: jm.parallel_hill_climb(
        task, key=jr.key(seed), evaluations=130, size=20, batch=50
    )
    a, b, c = run(3), run(3), run(4)
    np.testing.assert_array_equal(a.history.fitness, b.history.fitness)
    assert a.best_fitness == b.best_fitness
    assert not np.array_equal(a.history.fitness, c.history.fitness)
    # 20 initial + 130 perturbed, in steps of 50, 50 and 30 (the last batch is trimmed).
    assert len(a.history) == 150
    assert np.bincount(a.history.step).tolist() == [20, 50, 50, 30]
    assert int(a.state.evaluations) == 150
    best = np.maximum.accumulate(a.history.fitness)
    np.testing.assert_array_equal(a.history.best_so_far, best)
    assert a.best_fitness == best[-1]


def test_blown_up_evaluations_are_counted_and_never_kept():
    task = jm.Task(
        jm.lattices.cube(stiffness=5e6),
        jm.World(),
        jm.RegimesSpace(4, 0.5),
        jm.Objective({"forward": 1.0}),
        duration=0.5,
        dt=5e-3,
    )
    result = jm.parallel_hill_climb(task, key=jr.key(0), evaluations=20, size=10, batch=10)
    assert result.history.num_nonfinite == 30
    assert not np.any(np.isnan(result.history.fitness))


def test_callback_sees_every_step_and_bad_settings_raise():
    task = forward_task(duration=0.5)
    seen = []
    jm.parallel_hill_climb(
        task,
        key=jr.key(0),
        evaluations=40,
        size=10,
        batch=20,
        callback=lambda state, part: seen.append((int(state.step), len(part))),
    )
    assert seen == [(0, 10), (1, 20), (2, 20)]
    for kwargs, message in [
        (dict(evaluations=0), r"evaluations = 0; allowed: an integer >= 1"),
        (dict(batch=0), r"batch = 0; allowed: an integer >= 1"),
        (dict(size=2.5), r"size = 2.5; allowed: an integer >= 1"),
    ]:
        with pytest.raises(ValueError, match=message):
            jm.parallel_hill_climb(task, key=jr.key(0), **kwargs)


def test_history_round_trip(tmp_path):
    from jaxmotion._cli.results import write_history_csv
    from jaxmotion.experiment import read_history_csv

    h = jm.History(np.array([1.0, -np.inf, 3.5, 2.0]), np.array([0, 0, 1, 1]))
    write_history_csv(tmp_path / "h.csv", h)
    back = read_history_csv(tmp_path / "h.csv")
    np.testing.assert_array_equal(back.fitness, h.fitness)
    np.testing.assert_array_equal(back.step, h.step)
    assert h.num_nonfinite == 1
