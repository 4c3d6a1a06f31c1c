"""`Composite`: controllers in turn scored by a script, the transition-point search on a
real simulation, and the editor, driven headlessly through the widgets' Python API (a
slider moved re-simulates and redraws, the search button moves the sliders to its result)."""

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)
DT = 4e-3
DURATION = 0.4  # s: 100 ticks
SCRIPT_RTOL = 1e-5  # the script inside the search's program and outside it round alike


@pytest.fixture(scope="module")
def composite():
    body = jm.figures.star_man()
    space = jm.TimeBSRSpace(body, num_rules=3, t_per=0.2, tau_min=0.02, tau_max=0.2)
    controllers = {"kick": space.sample(key=jr.key(0)), "roll": space.sample(key=jr.key(1))}
    script = """
    # the kick should last 60 ticks; credit the roll's travel a little
    kick = delta_time ?= 60
    roll = 0.01 * delta_cm_x
    total = kick + roll
    """
    return jm.Composite(body, WORLD, controllers, script, DURATION, DT)


def test_evaluate_is_the_script_of_the_sequences_motion(composite):
    transitions = jnp.array([[0.1], [0.24], [0.36]])
    fitness = composite.evaluate(transitions)
    for i, t in enumerate(transitions):
        trajectory = composite.trajectory(t)
        values = composite.script.values(trajectory, t)
        np.testing.assert_allclose(fitness[i], values["total"], rtol=SCRIPT_RTOL)
        # The kick's credit depends only on its length: 1 at 60 ticks (0.24 s).
        assert (values["kick"] == 1.0) == (i == 1)
    np.testing.assert_allclose(
        composite.values(transitions[1])["total"], fitness[1], rtol=SCRIPT_RTOL
    )


def test_the_default_transitions_share_the_duration(composite):
    np.testing.assert_allclose(composite.equally_spaced(), [0.2], rtol=1e-12)


def test_the_search_finds_the_planted_transition_and_never_loses(composite):
    """The script's kick credit peaks at a transition of 60 ticks; the roll's travel is
    worth at most a few hundredths: the search from the equally spaced start (50 ticks)
    moves the transition to within a few ticks of 60 and never returns worse than its
    start."""
    result = composite.search(key=jr.key(0), num_arrays=4, rounds=3, mutations=2)
    start = composite.evaluate(composite.equally_spaced()[None])[0]
    assert result.best_fitness >= float(start)
    assert abs(float(result.best[0]) / DT - 60) <= 5
    assert result.evaluations == 4 + 3 * 2 * 4
    # The composite is the task of a protocol searcher: the driver runs the same search.
    search = jm.TransitionSearch(composite.duration, num_arrays=4, mutations=2, tick=composite.tick)
    driven = jm.drive(search, composite, key=jr.key(0), steps=3 * 2)
    np.testing.assert_array_equal(driven.history.fitness, result.history.fitness)
    np.testing.assert_array_equal(np.asarray(driven.best), np.asarray(result.best))


def test_bad_composites_are_refused():
    body = jm.figures.star_man()
    space = jm.TimeBSRSpace(body, num_rules=3, t_per=0.2)
    c = space.sample(key=jr.key(0))
    with pytest.raises(ValueError, match="non-empty mapping"):
        jm.Composite(body, WORLD, [c, c], "total = 1", 1.0, DT)
    with pytest.raises(jm.ScriptError, match="line 1"):
        jm.Composite(body, WORLD, {"a": c, "b": c}, "total = a.nope", 1.0, DT)
    with pytest.raises(ValueError, match="duration"):
        jm.Composite(body, WORLD, {"a": c}, "total = 1", -1.0, DT)
    with pytest.raises(ValueError, match=r"allowed: \(arrays, 1\)"):
        jm.Composite(body, WORLD, {"a": c, "b": c}, "total = 1", 1.0, DT).evaluate(jnp.zeros(3))


def test_a_tick_longer_than_the_control_period_is_the_scripts_unit(composite):
    """With `tick` = 5 steps, the controllers still act every step (the same motion as the
    fine composite's at a transition on both grids) while the script's `delta_time` counts
    ticks and the search's transitions fall on ticks."""
    coarse = jm.Composite(
        composite.body,
        composite.world,
        dict(zip(composite.phases, composite.controllers, strict=True)),
        "kick = delta_time ?= 12\ntotal = kick",
        DURATION,
        DT,
        tick=5 * DT,
    )
    assert coarse.tick == pytest.approx(5 * DT) and coarse.control_dt == DT
    t = jnp.array([0.24])  # 60 steps = 12 ticks
    assert float(coarse.values(t)["total"]) == 1.0
    fine, ticked = composite.trajectory(t), coarse.trajectory(t)
    np.testing.assert_array_equal(fine.points[::5], ticked.points)
    np.testing.assert_allclose(coarse.equally_spaced(), [0.2], rtol=1e-12)
    result = coarse.search(key=jr.key(0), num_arrays=4, rounds=2, mutations=2)
    ticks = np.asarray(result.best) / coarse.tick
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-6)


def test_a_tick_must_be_whole_control_periods_dividing_the_duration(composite):
    controllers = dict(zip(composite.phases, composite.controllers, strict=True))
    args = (composite.body, composite.world, controllers, "total = 1")
    with pytest.raises(ValueError, match=r"tick = 0.006 is not a whole number of control"):
        jm.Composite(*args, DURATION, DT, tick=0.006)
    with pytest.raises(ValueError, match=r"duration = 0.42 is not a whole number of ticks"):
        jm.Composite(*args, 0.42, DT, tick=0.04)
    with pytest.raises(ValueError, match=r"tick = -1; allowed: a number of seconds > 0"):
        jm.Composite(*args, DURATION, DT, tick=-1)


@pytest.fixture(scope="module")
def editor(composite):
    return jm.viz.composite_editor(
        composite, frames=3, search=dict(num_arrays=4, rounds=3, mutations=2)
    )


def test_the_editor_starts_equally_spaced_and_draws(editor):
    np.testing.assert_allclose(editor.transitions, [0.2])
    assert editor.sliders[0].description == "kick → roll"
    assert bytes(editor.picture.value).startswith(b"\x89PNG")
    assert set(editor.values) == {"kick", "roll", "total"}


def test_moving_a_slider_resimulates_and_updates_the_values(editor):
    before = np.asarray(editor.trajectory.points).copy()
    editor.sliders[0].value = 0.24  # 60 ticks: the kick's credit is 1
    assert editor.values["kick"] == pytest.approx(1.0, abs=1e-6)
    after = np.asarray(editor.trajectory.points)
    assert not np.array_equal(before, after)
    expected = editor.composite.values(np.array([0.24]))
    assert editor.values == expected


def test_the_search_button_moves_the_sliders_to_its_result(editor):
    editor.sliders[0].value = 0.1
    low = editor.values["total"]
    editor.search_button.click()
    assert editor.transitions[0] != pytest.approx(0.1)
    assert editor.values["total"] >= low
    assert abs(editor.transitions[0] / DT - 60) <= 5  # the planted optimum's neighbourhood
    assert editor.status.value.startswith("searched")


def test_animate_renders_the_motion_as_a_gif_and_a_move_clears_it(editor):
    editor.animate(fps=5)
    assert bytes(editor.movie.value).startswith(b"GIF8")
    editor.sliders[0].value = 0.2
    assert bytes(editor.movie.value) == b""
