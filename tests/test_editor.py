"""The composite editor, driven headlessly through the widgets' Python API: a slider moved
re-simulates and redraws, the search button moves the sliders to its result."""

import ipywidgets  # noqa: F401  (the `editor` extra; the test extra installs it)
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)
DT = 4e-3


@pytest.fixture(scope="module")
def editor():
    body = jm.figures.star_man()
    space = jm.TimeBSRSpace(body, num_rules=3, t_per=0.2, tau_min=0.02, tau_max=0.2)
    composite = jm.Composite(
        body,
        WORLD,
        {"kick": space.sample(key=jr.key(0)), "roll": space.sample(key=jr.key(1))},
        "kick = delta_time ?= 60\nroll = 0.01 * delta_cm_x\ntotal = kick + roll",
        0.4,
        DT,
    )
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
