"""Configs and the CLI for articulated figures: `figure = ...` bodies, the `time_bsr` family and
`serial_search`, checked before anything compiles; a figure run writes the usual results
folder and replays to the fitness the search recorded."""

import argparse
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

import jaxmotion as jm
from jaxmotion.experiment import (
    ConfigError,
    load_config,
    load_result,
    parse_config,
    read_history_csv,
    run_experiment,
)

ROOT = Path(__file__).resolve().parents[1]
FIGURE_CONFIGS = ("starman_shuffle", "starman_cartwheel", "beryl_tumble", "cujo_bound")


def figure_config(**sections):
    raw = {
        "body": {"figure": "star_man"},
        "objective": {"forward": 1.0},
        "simulation": {"duration": 1.0, "dt": 0.004},
        "search": {"algorithm": "serial_search"},
    }
    for name, value in sections.items():
        raw[name] = {**raw.get(name, {}), **value}
    return raw


def test_a_figure_config_builds_figure_time_bsr_and_serial_search():
    e = parse_config(figure_config(), name="demo")
    assert isinstance(e.task.body, jm.Figure) and e.task.body.name == "star_man"
    assert isinstance(e.task.space, jm.TimeBSRSpace)
    # The paper's Table 2 defaults: tau from 2 dt to T / 4.
    assert e.config["controller"]["tau_min"] == 2 * 0.004
    assert e.config["controller"]["tau_max"] == 1.0 / 4
    assert e.config["search"] == {
        "algorithm": "serial_search",
        "climbers": 10,
        "generations": 4000,
        "reseed_every": 200,
        "enrich": 0,
        "runs": 1,
        "accurate_candidates": 0,
    }


@pytest.mark.parametrize("name", FIGURE_CONFIGS)
def test_shipped_figure_configs_use_figures_and_serial_search(name):
    e = load_config(ROOT / "configs" / f"{name}.toml")
    assert isinstance(e.task.body, jm.Figure)
    assert e.search["algorithm"] == "serial_search"


def test_a_config_asks_for_mirrored_gaits():
    e = parse_config(figure_config(body={"figure": "rex"}, controller={"mirror": True}))
    assert e.task.space.mirror == jm.figures.rex().mirror
    assert parse_config(figure_config()).config["controller"]["mirror"] is False
    # Sense-based rules with mirror twins.
    sense = {"family": "sense_bsr", "mirror": True}
    e = parse_config(figure_config(body={"figure": "bob"}, controller=sense))
    assert e.task.space.mirror == jm.figures.bob().sense_mirror
    with pytest.raises(ConfigError, match=r"\[controller\] .*figure 'star_man' is planar"):
        parse_config(figure_config(controller=sense))


def test_beryl_tumble_is_not_periodic():
    e = load_config(ROOT / "configs" / "beryl_tumble.toml")
    assert e.task.space.t_per >= e.task.duration


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (figure_config(body={"figure": "dog"}), r"\[body\] figure = 'dog'; allowed: one of"),
        (
            figure_config(body={"lattice": "cube"}),
            r"\[body\] names both a lattice and a figure",
        ),
        (
            figure_config(controller={"family": "regimes"}),
            r"family = 'regimes' does not control an articulated figure",
        ),
        (
            {
                "objective": {"forward": 1.0},
                "simulation": {"duration": 1.0},
                "controller": {"family": "time_bsr"},
            },
            r"family = 'time_bsr' does not control a mass-spring lattice",
        ),
        (
            figure_config(controller={"num_rules": 0}),
            r"\[controller\] num_rules = 0; allowed: an integer >= 1",
        ),
        (
            figure_config(controller={"tau_min": 0.5, "tau_max": 0.1}),
            r"tau_min = 0.5 > tau_max = 0.1",
        ),
        (
            figure_config(controller={"num_regimes": 4}),
            r"\[controller\] has an unknown key 'num_regimes'; allowed: family, num_rules",
        ),
        (
            figure_config(search={"climbers": 0}),
            r"\[search\] climbers = 0; allowed: an integer >= 1",
        ),
        (
            figure_config(search={"batch": 10}),
            r"\[search\] has an unknown key 'batch'; allowed: algorithm, climbers",
        ),
        (figure_config(check={"motion": "hopscotch"}), r"\[check\] motion = 'hopscotch'; allowed"),
        (
            figure_config(controller={"mirror": "yes"}),
            r"\[controller\] mirror = 'yes'; allowed: true or false",
        ),
        (
            figure_config(controller={"mirror": True}),
            r"\[controller\] .*figure 'star_man' is planar.*allowed: mirror = False",
        ),
        (
            figure_config(body={"figure": "star_man", "max_torque": -1.0}),
            r"\[body\] max_torque = -1.0; allowed: a number >= 0 \(N m",
        ),
        (
            figure_config(body={"figure": "bob", "max_torque": 5.0}),
            r"\[body\] max_torque = 5.0 for figure = 'bob', a 3D figure; allowed: only for "
            r"the planar figures \(star_man, beryl_biped, snake, luxo\)",
        ),
    ],
)
def test_bad_figure_configs_name_the_key_the_value_and_what_is_allowed(raw, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(raw)


def _cli(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "jaxmotion", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_cli_rejects_batch_for_serial_search_before_compiling():
    out = _cli("run", ROOT / "configs" / "starman_shuffle.toml", "--batch", "5", timeout=120)
    assert out.returncode == 2
    assert "--batch applies to parallel_hill_climb" in out.stderr


def test_a_figure_run_writes_its_results_with_batched_runs_and_replays_exactly(tmp_path):
    from jaxmotion._cli.main import _load
    from jaxmotion._cli.results import fitness_of

    args = argparse.Namespace(seed=None, evaluations=30, batch=None, runs=2)
    # The config's accurate pick off: the best is then the fittest run's (tested for the
    # accurate pick in test_accurate.py and test_paper000.py).
    raw = tomllib.loads((ROOT / "configs" / "starman_shuffle.toml").read_text())
    raw["search"]["accurate_candidates"] = 0
    config = tmp_path / "starman_shuffle.toml"
    config.write_text(tomli_w.dumps(raw))
    experiment = _load(config, args)  # as the CLI does
    directory = tmp_path / "results"
    folder = run_experiment(experiment, directory=directory, progress=False)
    assert (folder / "motion.gif").stat().st_size > 0
    summary = json.loads((folder / "summary.json").read_text())
    # 3 generations of 10 climbers (30 evaluations) after the initial 10, for each of 2 runs.
    assert summary["evaluations"] == 2 * 10 * 4
    assert [r["run"] for r in summary["runs"]] == [0, 1]
    # Each run's history (the best run's is history.csv too) and their learning curves.
    runs = [read_history_csv(folder / f"history-run-{i}.csv") for i in (0, 1)]
    assert all(len(h) == 10 * 4 for h in runs)
    best_run = int(np.argmax([r["best_fitness"] for r in summary["runs"]]))
    np.testing.assert_array_equal(
        runs[best_run].fitness, read_history_csv(folder / "history.csv").fitness
    )
    assert (folder / "learning_curves.png").stat().st_size > 0
    assert summary["best_fitness"] == max(r["best_fitness"] for r in summary["runs"])
    assert all(r["check"]["name"] == "shuffle" for r in summary["runs"])
    loaded, controller = load_result(folder)
    assert isinstance(controller, jm.TimeBSR)
    # The saved controller (through JSON) replays to exactly the fitness the search recorded.
    assert fitness_of(loaded.task, controller) == summary["best_fitness"]
