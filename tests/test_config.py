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
    # A saved controller that does not fit its config (a regime dropped), or is not JSON,
    # is refused naming the file, before anything compiles.
    saved = folder / "best_controller.json"
    data = json.loads(saved.read_text())
    for name in ("times", "reflexes", "coefficients"):
        data["params"][name] = data["params"][name][:-1]
    saved.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=r"best_controller.json: the controller does not fit"):
        load_result(folder)
    saved.write_text('{"family": "regimes", "params": {')
    with pytest.raises(ConfigError, match=r"best_controller.json: not valid JSON"):
        load_result(folder)


def test_failed_or_interrupted_runs_leave_nothing_behind(tmp_path, monkeypatch):
    import jaxmotion._cli.results as results

    experiment = small_experiment(tmp_path)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(results, "drive", interrupted)
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


# ------------------------------------------------------------------------- hostile input

FLOAT32_OVERFLOW = r"allowed: .*magnitude at most 3.403e\+38"


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        # Values that overflow float32 (the reproduction: the search ran, then the
        # summary failed on a fitness that was not finite).
        (
            minimal(objective={"forward": 1e300}),
            r"\[objective\] forward = 1e\+300; " + FLOAT32_OVERFLOW,
        ),
        (
            minimal(objective={"upright": {"weight": -1e39}}),
            r"\[objective\] upright.weight = -1e\+39; " + FLOAT32_OVERFLOW,
        ),
        (minimal(world={"friction": 1e300}), r"\[world\] friction = 1e\+300; " + FLOAT32_OVERFLOW),
        (minimal(world={"gravity": 1e300}), r"\[world\] gravity = 1e\+300; " + FLOAT32_OVERFLOW),
        (
            minimal(world={"friction_direction": [1e300, 0.0]}),
            r"friction_direction = \[1e\+300, 0.0\]; " + FLOAT32_OVERFLOW,
        ),
        # Sizes beyond what XLA's static shapes hold (the SIGABRT inside XLA).
        (
            minimal(controller={"num_regimes": 4611686018427387904}),
            r"\[controller\] num_regimes = 4611686018427387904; allowed: an integer >= 1, at "
            r"most 1000",
        ),
        (
            minimal(search={"size": 4611686018427387904}),
            r"\[search\] size = 4611686018427387904; allowed: an integer >= 1, at most 10000",
        ),
        (
            minimal(search={"batch": 2**62}),
            r"\[search\] batch = 4611686018427387904; allowed: an integer >= 1, at most 10000",
        ),
        (
            minimal(search={"algorithm": "serial_search", "climbers": 1000, "runs": 1000}),
            r"\[search\] runs = 1000 x climbers = 1000 = 1000000 controllers in one call; "
            r"allowed: at most 10000",
        ),
        (
            minimal(
                simulation={"duration": 100.0, "save_dt": 0.01},
                search={"batch": 2000},
            ),
            r"\[search\] batch = 2000 = 2000 controllers in one call, each saving 10001 "
            r"samples .*: 2e\+07; allowed: at most 1e\+07 samples in one call",
        ),
        (
            minimal(simulation={"duration": 5.0, "dt": 1e-12}),
            r"\[simulation\] duration = 5.0 at dt = 1e-12 is 5e\+12 steps; allowed: at most "
            r"10000000 steps",
        ),
        (
            minimal(simulation={"duration": 1000.0, "dt": 1e-4, "save_dt": 1e-4}),
            r"\[simulation\] duration = 1000.0 at save_dt = 0.0001 is 1e\+07 saved samples; "
            r"allowed: at most 100000",
        ),
        (minimal(body=3), r"\[body\] must be a table of keys; got 3"),
        (minimal(body={"lattice": ["cube"]}), r"\[body\] lattice = \['cube'\]; allowed: one of"),
        (minimal(search=[1, 2]), r"\[search\] must be a table of keys"),
        (dict(minimal(), name="../up"), r"name = '../up'; allowed: a string of 1 to 100 ASCII"),
        (minimal(output={"directory": "a\x00b"}), r"\[output\] directory = 'a\\x00b'; allowed"),
        (
            minimal(objective={"x": {"term": ["forward"], "weight": 1.0}}),
            r"\[objective\] .*unhashable type: 'list'",
        ),
    ],
)
def test_hostile_values_are_refused_before_compiling(raw, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(raw)


# What a new user might write in place of a value: every key of the default config gets each.
HOSTILE = [0, -1, 1e300, -1e300, 2**62, 1.5, float("nan"), float("inf"), "x", "", True, [], {}]


def _mutations(raw):
    """(label, mutated config) for every value of every section replaced by each hostile
    value, every key removed, every section replaced by a value and an unknown key added."""
    for section, table in raw.items():
        if not isinstance(table, dict):
            for value in HOSTILE:
                yield f"{section}={value!r}", {**raw, section: value}
            continue
        for value in (3, "x", [1]):
            yield f"[{section}]={value!r}", {**raw, section: value}
        yield f"[{section}] extra", {**raw, section: {**table, "extra": 1}}
        for key in table:
            rest = {k: v for k, v in table.items() if k != key}
            yield f"[{section}] -{key}", {**raw, section: rest}
            for value in HOSTILE:
                yield f"[{section}] {key}={value!r}", {**raw, section: {**table, key: value}}


def test_a_corpus_of_mutated_default_configs_fails_cleanly_or_parses_to_bounded_sizes():
    """Every mutation of the default config either raises `ConfigError` (never another
    exception) or parses to a config whose values are finite, within float32 and whose
    sizes are within the bounds checked before compiling."""
    import math

    from jaxmotion._cli.config import FLOAT32_MAX, MAX_BATCH, MAX_RULES, MAX_STEPS

    raw = tomllib.loads(default_config_path().read_text())
    outcomes = {"refused": 0, "parsed": 0}
    for label, mutated in _mutations(raw):
        try:
            experiment = parse_config(mutated, name="mutant")
        except ConfigError as e:
            assert str(e), label
            outcomes["refused"] += 1
            continue
        outcomes["parsed"] += 1
        config = experiment.config
        numbers = [
            v
            for table in config.values()
            if isinstance(table, dict)
            for v in table.values()
            if isinstance(v, int | float) and not isinstance(v, bool)
        ]
        assert all(math.isfinite(v) and abs(v) <= FLOAT32_MAX for v in numbers), label
        assert config["controller"]["num_regimes"] <= MAX_RULES, label
        assert config["search"]["size"] <= MAX_BATCH >= config["search"]["batch"], label
        steps = config["simulation"]["duration"] / config["simulation"]["dt"]
        assert steps <= MAX_STEPS, label
    # The corpus exercises both outcomes (a mutation such as `batch = 1` is a valid config).
    assert outcomes["refused"] > 200 and outcomes["parsed"] > 10, outcomes


def test_stale_partial_folders_of_dead_runs_are_cleaned_and_live_ones_kept(tmp_path):
    """A run killed before it could clean up (SIGKILL, an abort inside XLA) leaves its
    temporary folder; the next run in the same directory removes it, but never the
    temporary folder of a run still going."""
    import os

    from jaxmotion._cli.results import new_folder

    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    dead_pid = int(dead.stdout)  # that process has exited
    stale = tmp_path / f".run-20260101-000000.pid{dead_pid}.abc_12.partial"
    older = tmp_path / ".run-20260101-000000.xyz.partial"  # the naming before process ids
    live = tmp_path / f".run-20260101-000000.pid{os.getpid()}.def.partial"
    kept = tmp_path / "run-20260101-000000"  # a complete results folder
    for folder in (stale, older, live, kept):
        folder.mkdir()
        (folder / "history.csv").write_text("evaluation\n")
    # A checkpoint killed while being written (its temporary file), and a whole one.
    (tmp_path / f".run-20260101-000000.checkpoint.{dead_pid}.tmp").write_bytes(b"half")
    (tmp_path / "run-20260101-000000.checkpoint").write_bytes(b"whole")
    final, tmp = new_folder(tmp_path, "next")
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {live.name, kept.name, tmp.name, "run-20260101-000000.checkpoint"}
    assert tmp.name.startswith(f".{final.name}.pid{os.getpid()}.")


def test_results_directory_that_is_a_file_is_refused(tmp_path):
    from jaxmotion._cli.results import new_folder

    blocker = tmp_path / "results"
    blocker.write_text("not a folder")
    with pytest.raises(
        ConfigError, match=r"results directory .*deeper' cannot be created \(Not a directory\)"
    ):
        new_folder(blocker / "deeper", "x")


def saved_regimes(**params):
    """A saved two-regime controller with these parameters changed."""
    base = {"times": [0.1, 0.6], "reflexes": [0, 1], "coefficients": [0.1, 0.2], "t_per": 1.0}
    return {"family": "regimes", "params": {**base, **params}}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ([1, 2], r"a saved controller must be a table"),
        ({"family": ["regimes"]}, r"controller family = \['regimes'\]; allowed"),
        ({"family": "regimes", "params": 3}, r"regimes controller's params = 3; allowed"),
        (
            saved_regimes(times=[0.1, 1e300]),
            r"regimes controller's times = \[0.1, 1e\+300\]; allowed: finite numbers",
        ),
        (
            saved_regimes(times=[0.1, "x"]),
            r"regimes controller's times = \[0.1, 'x'\]; allowed",
        ),
        (
            saved_regimes(times=[[0.1], [0.2, 0.3]]),
            r"regimes controller's times = \[\[0.1\], \[0.2, 0.3\]\]; allowed: .*rectangular",
        ),
        ({"family": "regimes", "params": {"times": [0.1]}}, r"regimes controller: .*missing"),
    ],
)
def test_hostile_saved_controllers_are_refused_naming_the_parameter(data, message):
    with pytest.raises(ValueError, match=message):
        controller_from_dict(data)


def _cli(monkeypatch, capsys, *argv):
    """`python -m jaxmotion ARGV` in this process (its devices are already set up):
    the exit code and stderr."""
    import jaxmotion._devices
    from jaxmotion._cli.main import main

    monkeypatch.setattr(jaxmotion._devices, "use_cpu_cores", lambda: 1)
    code = main(list(argv))
    return code, capsys.readouterr().err


def test_cli_refuses_bad_options_and_folders_with_exit_code_2(tmp_path, monkeypatch, capsys):
    config = str(ROOT / "configs" / "default.toml")
    (tmp_path / "file").write_text("x")
    out = str(tmp_path / "out")
    cases = [
        (("run", config, "--seed", "-1", "--out", out), "--seed = -1; allowed: an integer from 0"),
        (("run", config, "--evaluations", "0", "--out", out), "--evaluations = 0; allowed"),
        (("run", config, "--batch", str(2**62), "--out", out), "--batch = 4611686018427387904"),
        (("run", config, "--out", str(tmp_path / "file")), "--out = '" + str(tmp_path / "file")),
        (("compare", config, "--seeds", "0,-1", "--out", out), "--seeds = '0,-1'; allowed"),
        (("compare", config, "--learning-rate", "inf", "--out", out), "--learning-rate = inf"),
        (("compare", config, "--fraction", "1.5", "--out", out), "--fraction = 1.5; allowed"),
        (("run", config, "--checkpoint-every", "nan", "--out", out), "--checkpoint-every = nan"),
        (("run", config, "--resume", str(tmp_path / "none"), "--out", out), "no such checkpoint"),
        (("replay", str(tmp_path)), "not a results folder (no config.toml"),
        (("replay", str(tmp_path / "nothing")), "not a results folder (no such folder)"),
    ]
    for argv, message in cases:
        code, err = _cli(monkeypatch, capsys, *argv)
        assert code == 2 and message in err, (argv, err)
    assert not (tmp_path / "out").exists()


def test_a_run_whose_best_is_not_finite_finishes_cleanly(tmp_path, monkeypatch, capsys):
    """`gravity = 1e30` is a float32 number, but every simulation blows up: the run still
    writes its whole folder, reports the count of non-finite evaluations and exits 0."""
    text = (ROOT / "configs" / "default.toml").read_text()
    for old, new in (
        ("gravity = 9.81", "gravity = 1e30"),
        ("duration = 5.0", "duration = 0.2"),
        ("evaluations = 10000", "evaluations = 16"),
        ("size = 100", "size = 16"),
        ("batch = 100", "batch = 16"),
    ):
        text = text.replace(old, new)
    path = tmp_path / "heavy.toml"
    path.write_text(text)
    code, err = _cli(
        monkeypatch, capsys, "run", str(path), "--out", str(tmp_path / "r"), "--no-animation"
    )
    assert code == 0, err
    assert "best fitness -inf after 32 evaluations" in err
    assert "32 of 32 evaluations blew up" in err
    (folder,) = (tmp_path / "r").iterdir()
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["best_fitness"] == "-inf" and summary["nonfinite_evaluations"] == 32
    assert len((folder / "history.csv").read_text().splitlines()) == 1 + 32
