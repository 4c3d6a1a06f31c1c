"""`[search] accurate_candidates`: the final set's fittest (serial search's archive)
replayed accurately (float64, Dopri5, tight tolerances) and the best chosen by the lower of
its two fitnesses."""

import math

import jax
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion._cli.config import make_searcher
from jaxmotion._cli.results import accurate_fitness, pick_accurate
from jaxmotion.experiment import ConfigError, parse_config

# The float32 task's constants (lattice geometry) stay float32 when its arrays are widened:
# against a task built in float64 from the start, the accurate fitness agrees to about
# float32's resolution.
GEOMETRY_TOLERANCE = 1e-5


def _task():
    return jm.Task(
        jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 0.25),
        jm.Objective({"forward": 1.0, "max_height": 0.5}),
        duration=0.4,
    )


def _float64_task():
    with jax.enable_x64(True):
        return _task()


def test_the_best_is_chosen_by_the_lower_of_its_two_fitnesses():
    task = _task()
    result = jm.parallel_hill_climb(task, key=jr.key(0), evaluations=48, size=16, batch=16)
    picked, measured = pick_accurate(task, result, 3)
    fitness = np.asarray(result.state.fitness)
    top = np.argsort(-fitness, kind="stable")[:3]
    rows = []
    for i in top:
        one = jax.tree_util.tree_map(lambda a, i=i: a[i], result.state.population)
        rows.append((float(fitness[i]), accurate_fitness(task, one), one))
    scores = [min(f, a) for f, a, _ in rows]
    chosen = int(np.argmax(scores))
    assert measured["candidates"] == 3 and measured["chosen_rank"] == chosen
    assert picked.best_fitness == rows[chosen][0]
    assert measured["accurate_fitness"] == rows[chosen][1]
    assert measured["search_best_fitness"] == result.best_fitness
    for a, b in zip(jax.tree.leaves(picked.best), jax.tree.leaves(rows[chosen][2]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # With a check, the chosen motion's accurate replay is checked, not replayed again.
    seen = []

    def check(trajectory):
        seen.append(float(_float64_task().objective(trajectory)))
        return jm.checks.CheckResult("probe", True, {"fitness": seen[-1]}, {"ran": True})

    again, measured_checked = pick_accurate(task, result, 3, check)
    assert again.best_fitness == picked.best_fitness
    assert seen == [measured["accurate_fitness"]]  # one call, on the chosen motion
    assert measured_checked["check"]["figures"] == {"fitness": seen[0]}
    assert "check" not in measured
    # The accurate fitness is a float64 adaptive replay: a task built in float64 agrees.
    with jax.enable_x64(True):
        task64 = _task()
        one = jax.tree_util.tree_map(
            lambda a: np.asarray(a, np.float64) if np.issubdtype(a.dtype, np.floating) else a,
            rows[0][2],
        )
        trajectory = task64.simulate(one, solver="dopri5", rtol=1e-8, atol=1e-10)
        reference = float(task64.objective(trajectory))
    assert math.isclose(rows[0][1], reference, rel_tol=GEOMETRY_TOLERANCE, abs_tol=1e-7)


def test_the_fittest_of_any_searchers_final_set():
    """Serial search keeps climbers per run: the fittest are chosen over all of them, and
    an accurate pick reads them as it reads hill climbing's set; a searcher without a final
    set (evosax: a distribution) offers its best alone."""
    import dataclasses

    task = _task()
    searcher = jm.SEARCHERS["serial_search"](climbers=3, reseed_every=200, enrich=0, seeds=2)
    result = jm.drive(searcher, task, key=jr.key(1), steps=2)
    fitness = np.asarray(result.state.fitness)
    assert fitness.shape == (2, 3)
    chosen, values = jm.fittest(result, 4)
    np.testing.assert_array_equal(values, np.sort(fitness.reshape(-1))[::-1][:4])
    np.testing.assert_array_equal(np.asarray(task.evaluate(chosen)), values)
    assert values[0] == result.best_fitness
    picked, measured = pick_accurate(task, result, 2)
    assert measured["candidates"] == 2
    assert picked.best_fitness == values[measured["chosen_rank"]]
    bare = dataclasses.replace(result, state=None)
    alone, value = jm.fittest(bare, 4)
    assert value.tolist() == [result.best_fitness]
    for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(result.best), strict=True):
        np.testing.assert_array_equal(np.asarray(a)[0], np.asarray(b))


def test_the_config_key():
    raw = {
        "simulation": {"duration": 1.0},
        "objective": {"forward": 1.0},
        "search": {"accurate_candidates": 10},
    }
    assert parse_config(raw).search["accurate_candidates"] == 10
    for algorithm in ("serial_search", "evolve"):
        raw["search"]["algorithm"] = algorithm
        assert parse_config(raw).search["accurate_candidates"] == 10
    # Serial search's few final climbers are alike: it keeps an archive of the fittest
    # controllers it held (`SerialSearch(archive=K)`), as many as the replay chooses among.
    raw["search"]["algorithm"] = "serial_search"
    assert make_searcher(parse_config(raw).search)[0].archive == 10
    del raw["search"]["algorithm"]
    raw["search"]["accurate_candidates"] = -1
    with pytest.raises(
        ConfigError, match=r"\[search\] accurate_candidates = -1; allowed: an integer >= 0"
    ):
        parse_config(raw)
