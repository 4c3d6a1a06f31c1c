"""`Task(second_dt=...)`: every controller is also simulated at a second, shorter step and
scored by the lower fitness, so a search keeps motions that do not depend on the step."""

import dataclasses

import jax
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion._cli.results import fitness_of
from jaxmotion.experiment import ConfigError, parse_config

DURATION = 0.4  # s: long enough for the two steps' motions to differ


def _task(**kwargs):
    return jm.Task(
        jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 0.25),
        jm.Objective({"forward": 1.0, "max_height": 0.5}),
        duration=DURATION,
        **kwargs,
    )


def test_the_fitness_is_the_lower_of_the_two_steps():
    task = _task(dt=1e-3, second_dt=5e-4)
    params = task.sample(16, key=jr.key(0))
    both = np.asarray(task.evaluate(params))
    first = np.asarray(_task(dt=1e-3).evaluate(params))
    second = np.asarray(_task(dt=5e-4, control_dt=1e-3).evaluate(params))
    np.testing.assert_array_equal(both, np.minimum(first, second))
    # The two steps do give different motions, and each side of the minimum is taken.
    assert np.any(first < second) and np.any(second < first)
    # A search's best replays to what the search recorded (the CLI's summary).
    one = jax.tree_util.tree_map(lambda a: a[3], params)
    assert fitness_of(task, one) == both[3]
    fitness, senses = task.evaluate_sensed(params)
    np.testing.assert_array_equal(np.asarray(fitness), both)
    _, senses_first = _task(dt=1e-3).evaluate_sensed(params)
    np.testing.assert_array_equal(np.asarray(senses), np.asarray(senses_first))


def test_a_replay_and_a_started_task_keep_their_settings():
    task = _task(dt=1e-3, second_dt=5e-4)
    # simulate() replays at the search's own step (the motion the animator sees).
    one = jax.tree_util.tree_map(lambda a: a[0], task.sample(1, key=jr.key(3)))
    replay = task.simulate(one)
    alone = _task(dt=1e-3).simulate(one)
    np.testing.assert_array_equal(np.asarray(replay.points), np.asarray(alone.points))
    assert dataclasses.replace(task, initial_state=None).second_dt == 5e-4


@pytest.mark.parametrize(
    "second_dt, message",
    [
        (1e-3, "second_dt = 0.001 is not shorter than dt = 0.001"),
        (3e-4, "second_dt = 0.0003 does not fit the control period 0.001"),
        (-1e-4, "second_dt = -0.0001; allowed: a number of seconds > 0"),
        (True, "second_dt = True; allowed: a number of seconds > 0"),
    ],
)
def test_bad_second_steps_are_refused(second_dt, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.")):
        _task(dt=1e-3, second_dt=second_dt)


def test_the_config_key():
    raw = {
        "simulation": {"duration": 1.0, "dt": 1e-3, "second_dt": 5e-4},
        "objective": {"forward": 1.0},
    }
    assert parse_config(raw).task.second_dt == 5e-4
    raw["simulation"]["second_dt"] = 4e-4
    with pytest.raises(ConfigError, match=r"\[simulation\] second_dt = 0\.0004 does not fit"):
        parse_config(raw)
