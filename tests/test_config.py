"""Experiment configs: checked before anything compiles, with messages naming the key, the
value and what is allowed; results folders written whole or not at all."""

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion.experiment import (
    ConfigError,
    check_compose_config,
    controller_from_dict,
    controller_to_dict,
    default_config_path,
    load_config,
    load_result,
    parse_config,
    run_experiment,
)

ROOT = Path(__file__).resolve().parents[1]


def minimal(**sections):
    raw = {"objective": {"forward": 1.0}, "simulation": {"duration": 1.0}}
    for name, value in sections.items():
        raw[name] = value
    return raw


def test_shipped_default_is_the_one_the_cli_runs():
    assert (ROOT / "configs" / "default.toml").read_text() == default_config_path().read_text()


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_config_checks_out(path):
    raw = tomllib.loads(path.read_text())
    if "phase" in raw:
        # A composite-motion config: its tables, script and component configs check out
        # (running it runs its components first).
        assert check_compose_config(raw, name=path.stem).startswith(raw["name"])
        with pytest.raises(ConfigError, match="python -m jaxmotion compose"):
            load_config(path)
        return
    experiment = load_config(path)
    assert experiment.name == path.stem or experiment.name
    # The resolved config is itself a valid config that resolves to the same thing.
    again = parse_config(tomllib.loads(__import__("tomli_w").dumps(experiment.config)))
    assert again.config == experiment.config


def test_defaults_fill_in_and_build_the_task():
    e = parse_config(minimal(), name="demo")
    assert e.name == "demo" and e.seed == 0
    assert isinstance(e.task.body, jm.Lattice) and e.task.body.name == "cube"
    assert e.config["world"]["gravity"] == 9.81
    assert e.config["search"]["evaluations"] == 25_000
    assert e.task.duration == 1.0


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (
            minimal(world={"gravty": 9.0}),
            r"\[world\] has an unknown key 'gravty'; allowed: gravity, floor",
        ),
        (minimal(world={"gravity": "high"}), r"\[world\] gravity = 'high'; allowed: a number >= 0"),
        (minimal(world={"gravity": -9.81}), r"\[world\] gravity = -9.81; allowed: a number >= 0"),
        (minimal(world={"floor": 1}), r"\[world\] floor = 1; allowed: true or false"),
        (
            minimal(world={"friction_direction": [1.0]}),
            r"friction_direction = \[1.0\]; allowed: a list of 2 numbers",
        ),
        (
            minimal(simulation={"duration": -1.0}),
            r"\[simulation\] duration = -1.0; allowed: a number > 0",
        ),
        (minimal(simulation={"dt": 0.01}), r"missing the key 'duration'"),
        (
            minimal(simulation={"duration": 1.0, "dt": 2.0}),
            r"\[simulation\] dt = 2.0 is longer than duration",
        ),
        (minimal(search={"batch": 0}), r"\[search\] batch = 0; allowed: an integer >= 1"),
        (minimal(search={"evaluations": 1.5}), r"evaluations = 1.5; allowed: an integer >= 1"),
        (
            minimal(search={"algorithm": "annealing"}),
            r"algorithm = 'annealing'; allowed: a string \"parallel_hill_climb\"",
        ),
        (
            minimal(body={"lattice": "sphere"}),
            r"\[body\] lattice = 'sphere'; allowed: one of 'cube', 'pyramid', 'chair'",
        ),
        (
            minimal(body={"lattice": "cube", "height": 2.0}),
            r"\[body\] has an unknown key 'height'; allowed: lattice, size, mass",
        ),
        (minimal(body={"size": 0.0}), r"\[body\] size = 0.0; allowed: a number > 0"),
        (minimal(controller={"num_regimes": 0}), r"num_regimes = 0; allowed: an integer >= 1"),
        (
            minimal(controller={"amplitudes": [1.5, 0.3, 0.3, 0.5]}),
            r"amplitudes = \[1.5, 0.3, 0.3, 0.5\]",
        ),
        (
            minimal(objective={"forwrd": 1.0}),
            r"\[objective\] objective term 'forwrd': unknown term",
        ),
        (minimal(objective={}), r"\[objective\] must be a non-empty table"),
        (minimal(output={"fps": 0}), r"\[output\] fps = 0; allowed: an integer from 1 to 100"),
        (dict(minimal(), seed=-3), r"seed = -3; allowed: an integer from 0"),
        (dict(minimal(), wrold={"gravity": 1.0}), r"unknown section \[wrold\]"),
        (dict(minimal(), durations=3), r"unknown key 'durations'; allowed: name, seed"),
        ({"objective": {"forward": 1.0}}, r"no \[simulation\] section"),
        (
            minimal(check={"motion": "walk"}),
            r"\[check\] motion = \"walk\" needs a body with feet .*'cube' has none",
        ),
    ],
)
def test_bad_configs_name_the_key_the_value_and_what_is_allowed(raw, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(raw)


def test_load_config_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text('[simulation]\nduration = "long"\n[objective]\nforward = 1.0\n')
    with pytest.raises(ConfigError, match=r"broken.toml: \[simulation\] duration = 'long'"):
        load_config(path)
    path.write_text("[simulation\n")
    with pytest.raises(ConfigError, match=r"broken.toml: not valid TOML"):
        load_config(path)


def test_controller_json_round_trip_and_checks():
    c = jm.Regimes(times=[0.1, 0.6], reflexes=[3, 11], coefficients=[-1.0, 0.25], t_per=0.8)
    data = json.loads(json.dumps(controller_to_dict(c, "regimes")))
    back = controller_from_dict(data)
    for field in ("times", "reflexes", "coefficients", "t_per"):
        np.testing.assert_array_equal(
            np.asarray(getattr(back, field)), np.asarray(getattr(c, field))
        )
    data["params"]["reflexes"] = [3, 12]
    with pytest.raises(ValueError, match="regime 1 has reflex 12"):
        controller_from_dict(data)
    with pytest.raises(ValueError, match="family = 'bsr'"):
        controller_from_dict({"family": "bsr", "params": {}})


def small_experiment(tmp_path, **search):
    raw = minimal(
        simulation={"duration": 0.5},
        search={"evaluations": 40, "size": 10, "batch": 20, **search},
        output={"directory": str(tmp_path / "results"), "fps": 10},
    )
    return parse_config(raw, name="tiny")


def test_run_writes_the_whole_results_folder_and_it_loads_back(tmp_path):
    experiment = small_experiment(tmp_path)
    folder = run_experiment(experiment, progress=False)
    assert sorted(p.name for p in folder.iterdir()) == [
        "best_controller.json",
        "config.toml",
        "history.csv",
        "learning_plot.png",
        "motion.gif",
        "summary.json",
    ]
    assert [p.name for p in folder.parent.iterdir()] == [folder.name]  # no leftovers
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["evaluations"] == 50 and summary["seed"] == 0
    rows = (folder / "history.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 50
    loaded, controller = load_result(folder)
    assert loaded.config == experiment.config
    replay = float(loaded.task.fitness(loaded.task.simulate(controller)))
    # The saved controller (through JSON) replays to exactly the fitness the search saw.
    assert replay == summary["best_fitness"] == summary["replay_fitness"]


def test_failed_or_interrupted_runs_leave_nothing_behind(tmp_path, monkeypatch):
    import jaxmotion._cli.results as results

    experiment = small_experiment(tmp_path)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(results, "parallel_hill_climb", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_experiment(experiment, progress=False)
    assert list((tmp_path / "results").iterdir()) == []


def test_cli_fails_fast_on_a_bad_config(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[simulation]\nduration = -5.0\n[objective]\nforward = 1.0\n")
    out = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "run", str(path), "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2
    assert "[simulation] duration = -5.0; allowed: a number > 0" in out.stderr
    assert not (tmp_path / "r").exists()


def test_cli_help_documents_both_ways_to_run():
    out = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert "python -m jaxmotion run CONFIG.toml" in out.stdout
    assert "run the default experiment" in out.stdout


def test_cli_runs_a_config_end_to_end_and_replays_it(tmp_path):
    # The default experiment over 1 s, its GIF at 5 frames per second (the test's time goes
    # to compiling and to drawing frames).
    config = tmp_path / "short.toml"
    text = (ROOT / "configs" / "default.toml").read_text()
    config.write_text(
        text.replace("duration = 5.0", "duration = 1.0").replace("fps = 25", "fps = 5")
    )
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxmotion",
            "run",
            str(config),
            "--evaluations",
            "100",
            "--batch",
            "50",
            "--out",
            str(tmp_path),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    folder = Path(out.stdout.strip().splitlines()[-1])
    assert (folder / "motion.gif").stat().st_size > 0
    assert len((folder / "history.csv").read_text().strip().splitlines()) == 1 + 200
    replay = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "replay", str(folder)],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    report = json.loads(replay.stdout[replay.stdout.index("{") :])
    summary = json.loads((folder / "summary.json").read_text())
    assert report["fitness"] == summary["best_fitness"]
