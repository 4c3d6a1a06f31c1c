"""Multi-stage (seriatim) experiments: `[[stage]]` configs checked before anything compiles,
with every error naming the stage and the key; each stage's search starting exactly where
the previous stage's best motion ended; the results folder written whole or not at all."""

import argparse
import dataclasses
import json
import tomllib

import jax.numpy as jnp
import numpy as np
import pytest
import tomli_w

import jaxmotion as jm
from jaxmotion._cli.main import _load
from jaxmotion.experiment import (
    ConfigError,
    concatenate_trajectories,
    load_stages,
    parse_config,
    replay_stages,
    run_experiment,
    start_where,
)


def staged(*stages, **top):
    """A multi-stage config of Star-Man (planar, quick to compile) with these stage tables
    over shared top-level tables (`top` replaces or adds top-level entries)."""
    raw = {
        "name": "staged",
        "body": {"figure": "star_man"},
        "controller": {"family": "time_bsr", "num_rules": 2, "t_per": 0.25},
        "objective": {"forward": 1.0},
        "simulation": {"duration": 0.5, "dt": 0.005},
        "search": {"algorithm": "serial_search", "climbers": 4, "generations": 3},
        "stage": list(stages) or [{"name": "walk"}, {"name": "turn"}],
    }
    raw.update(top)
    return raw


WALK, TURN = {"name": "walk"}, {"name": "turn"}


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (
            staged(
                WALK,
                {"name": "turn", "search": {"algorithm": "parallel_hill_climb", "evaluations": -5}},
                search={},
            ),
            r'^\[\[stage\]\] 2 \("turn"\): \[search\] evaluations = -5; allowed: an integer >= 1'
            r", at most 1000000000$",
        ),
        (
            staged(WALK, {"name": "turn", "search": {"generations": 0}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[search\] generations = 0; allowed: an integer >= 1',
        ),
        (
            staged(WALK, {"name": "turn", "objective": {"forwrd": 1.0}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[objective\] objective term \'forwrd\': unknown term',
        ),
        (
            staged(WALK, {"name": "turn", "controller": {"family": "sense_bsr"}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[controller\] has an unknown key \'t_per\'',
        ),
        (
            staged(WALK, {"name": "turn", "simulation": {"duration": -1.0}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[simulation\] duration = -1.0; allowed: a number > 0',
        ),
        (
            staged({"objective": {"forward": 1.0}}),
            r"^\[\[stage\]\] 1 is missing the key 'name' \(a string that is an identifier",
        ),
        (
            staged({"name": "9lives"}),
            r'^\[\[stage\]\] 1 \("9lives"\) name = \'9lives\'; allowed: a string that is an '
            r"identifier",
        ),
        (
            staged(WALK, TURN, {"name": "walk"}),
            r'^\[\[stage\]\] 3 \("walk"\) name = \'walk\' is already stage 1\'s',
        ),
        (
            staged(WALK, {"name": "turn", "world": {"gravity": 1.0}}),
            r'^\[\[stage\]\] 2 \("turn"\) has an unknown key \'world\'; allowed: name, '
            r"controller, objective, simulation, search, robustness, check "
            r"\(\[body\], \[world\] and \[output\] are shared: top level only\)",
        ),
        (
            {
                k: v
                for k, v in staged(WALK, {"name": "turn", "objective": {"heading": 1.0}}).items()
                if k != "objective"
            },
            r'^\[\[stage\]\] 1 \("walk"\): no \[objective\] at the top level or in '
            r"\[stage.objective\]",
        ),
        (
            staged(WALK, {"name": "turn", "check": {"motion": "walk_turn_walk"}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[check\] motion = "walk_turn_walk" checks a '
            r"sequence of 3 stages",
        ),
        (
            staged(WALK, {"name": "turn", "check": {"motion": "hopp"}}),
            r'^\[\[stage\]\] 2 \("turn"\): \[check\] motion = \'hopp\'; allowed: a string',
        ),
        (
            staged(WALK, TURN, check={"motion": "walk_turn_walk"}),
            r'^\[check\] motion = "walk_turn_walk" checks a sequence of 3 stages; this config '
            r"has 2 \[\[stage\]\] tables",
        ),
        (
            staged(
                WALK,
                TURN,
                {"name": "again"},
                body={"lattice": "cube"},
                controller={"num_regimes": 2},
                check={"motion": "walk_turn_walk"},
            ),
            r'^\[check\] motion = "walk_turn_walk" needs a body with feet .*\'cube\' has none',
        ),
        # Shared tables are checked once, naming no stage.
        (staged(world={"gravity": -1.0}), r"^\[world\] gravity = -1.0; allowed: a number >= 0"),
        (staged(stage=[]), r"^stage = \[\]; allowed: one or more \[\[stage\]\] tables"),
        (staged(stage={"name": "walk"}), r"^stage = \{'name': 'walk'\}; allowed: one or more"),
    ],
)
def test_bad_stage_configs_name_the_stage_and_the_key(raw, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(raw)


def test_a_single_stage_in_a_multi_stage_config_is_a_single_stage_config():
    # Each stage's merged tables are the config a single search would have: same checks,
    # same resolved tables, same task.
    raw = staged(WALK, {"name": "turn", "objective": {"heading": 1.0}})
    single = {k: v for k, v in raw.items() if k != "stage"} | {"name": "walk"}
    experiment, alone = parse_config(raw), parse_config(single)
    walk = experiment.stages[0]
    assert walk.name == "walk" and walk.config == alone.config
    assert walk.search == alone.search and walk.task.duration == alone.task.duration
    assert alone.stages == () and experiment.task is walk.task


def test_stage_tables_merge_over_the_top_level_and_the_resolved_config_round_trips():
    raw = staged(
        {"name": "walk", "objective": {"fallen": -5.0}, "check": {"motion": "shuffle"}},
        {
            "name": "turn",
            "objective": {"forward": 0.0, "heading": {"weight": 1.0, "absolute": True}},
            "controller": {"t_per": 0.5},
            "search": {"generations": 7},
        },
        seed=41,
        check={"motion": "cartwheel"},
    )
    experiment = parse_config(raw)
    walk, turn = experiment.stages
    assert walk.task.objective.to_dict() == {"forward": 1.0, "fallen": -5.0}
    assert turn.task.objective.to_dict() == {
        "forward": 0.0,
        "heading": {"weight": 1.0, "absolute": True},
    }
    assert (walk.task.space.t_per, turn.task.space.t_per) == (0.25, 0.5)
    assert (walk.search["generations"], turn.search["generations"]) == (3, 7)
    assert turn.search["climbers"] == 4  # from the top level
    # Stage i (from 0) searches with seed + i; the top-level [check] is the sequence's, a
    # stage's own [check] its own.
    assert (experiment.seed, walk.seed, turn.seed) == (41, 41, 42)
    assert (experiment.check, walk.check, turn.check) == ("cartwheel", "shuffle", None)
    # Resolved: shared body, world, output and check at the top level, each stage in full.
    config = experiment.config
    assert set(config) == {"name", "seed", "body", "world", "output", "check", "stage"}
    assert config["stage"][1]["controller"]["t_per"] == 0.5
    assert config["stage"][1]["search"]["climbers"] == 4
    again = parse_config(tomllib.loads(tomli_w.dumps(config)))
    assert again.config == config
    assert [s.config for s in again.stages] == [s.config for s in experiment.stages]


def test_cli_overrides_reach_every_stage(tmp_path):
    path = tmp_path / "staged.toml"
    path.write_text(tomli_w.dumps(staged(WALK, {"name": "turn", "search": {"climbers": 8}})))
    args = argparse.Namespace(seed=5, evaluations=40, batch=None, runs=None)
    experiment = _load(path, args)
    # 40 evaluations: 10 generations of 4 climbers, 5 of 8.
    assert [s.search["generations"] for s in experiment.stages] == [10, 5]
    assert [s.seed for s in experiment.stages] == [5, 6]
    runs = _load(path, argparse.Namespace(seed=None, evaluations=None, batch=None, runs=2))
    assert [s.search["runs"] for s in runs.stages] == [2, 2]


def samples(ts, offset=0.0):
    """A finite trajectory of 2 points whose observables count the samples from `offset`."""
    n = len(ts)
    values = offset + np.arange(n, dtype=np.float32)
    return jm.Trajectory(
        ts=jnp.asarray(ts, dtype=jnp.float32),
        points=jnp.asarray(np.broadcast_to(values[:, None, None], (n, 2, 3))),
        com=jnp.asarray(np.broadcast_to(values[:, None], (n, 3))),
        frame=jnp.asarray(np.broadcast_to(np.eye(3, dtype=np.float32), (n, 3, 3))),
        contact=jnp.asarray(np.zeros((n, 2), bool)),
        finite=jnp.asarray(True),
    )


def test_concatenated_trajectories_shift_time_and_drop_the_repeated_sample():
    first = samples([0.0, 0.5, 1.0])
    second = samples([0.0, 0.25, 0.5], offset=2.0)  # starts at first's last sample
    third = samples([0.0, 1.0], offset=4.0)
    whole = concatenate_trajectories([first, second, third])
    np.testing.assert_array_equal(whole.ts, [0.0, 0.5, 1.0, 1.25, 1.5, 2.5])
    np.testing.assert_array_equal(whole.com[:, 0], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    assert whole.points.shape == (6, 2, 3) and bool(whole.finite)
    broken = samples([0.0, 1.0], offset=4.0)
    broken = jm.Trajectory(
        ts=broken.ts,
        points=broken.points,
        com=broken.com,
        frame=broken.frame,
        contact=broken.contact,
        finite=jnp.asarray(False),
    )
    assert not bool(concatenate_trajectories([first, broken]).finite)
    with pytest.raises(ValueError, match="at least one"):
        concatenate_trajectories([])
    other_body = jm.Trajectory(
        ts=third.ts,
        points=jnp.zeros((2, 3, 3)),
        com=third.com,
        frame=third.frame,
        contact=jnp.zeros((2, 3), bool),
        finite=third.finite,
    )
    with pytest.raises(ValueError, match=r"part 1 has points of shape \(3, 3\)"):
        concatenate_trajectories([first, other_body])


def test_a_two_stage_run_starts_each_stage_where_the_last_ended(tmp_path):
    # Star-Man for 0.5 s, 4 climbers x 3 generations per stage (two independent runs in the
    # second), no GIFs: the test's time is compiling, once for both stages (same objective,
    # and 4 or 8 controllers share a layout).
    raw = staged(
        WALK,
        {"name": "turn", "check": {"motion": "shuffle"}, "search": {"runs": 2}},
        output={"directory": str(tmp_path / "results"), "animation": False},
        check={"motion": "shuffle"},
    )
    experiment = parse_config(raw)
    lines = []
    folder = run_experiment(experiment, progress=False, report=lines.append)
    assert [p.name for p in (tmp_path / "results").iterdir()] == [folder.name]  # no leftovers
    assert sorted(p.name for p in folder.iterdir()) == [
        "config.toml",
        "stage-1-walk",
        "stage-2-turn",
        "summary.json",
    ]
    files = ["best_controller.json", "history.csv", "learning_plot.png", "summary.json"]
    assert sorted(p.name for p in (folder / "stage-1-walk").iterdir()) == files
    runs = ["history-run-0.csv", "history-run-1.csv", "learning_curves.png"]
    assert sorted(p.name for p in (folder / "stage-2-turn").iterdir()) == sorted(files + runs)
    summary = json.loads((folder / "summary.json").read_text())
    assert [s["name"] for s in summary["stages"]] == ["walk", "turn"]
    assert [s["seed"] for s in summary["stages"]] == [0, 1]
    assert summary["evaluations"] == 3 * 4 * (3 + 1)
    assert summary["stages"][0]["check"] is None
    assert summary["stages"][1]["check"]["name"] == "shuffle"
    assert summary["check"]["name"] == "shuffle"  # the whole sequence, end to end
    assert len(lines) == 4 and "starting where walk ended" in lines[2]
    stage_summary = json.loads((folder / "stage-2-turn" / "summary.json").read_text())
    assert stage_summary["stage"] == 2 and stage_summary["starts_after"] == "walk"
    assert stage_summary["best_fitness"] == summary["stages"][1]["best_fitness"]
    # The stage kept its better run (and its motion: the replays below).
    run_best = [r["best_fitness"] for r in stage_summary["runs"]]
    assert len(run_best) == 2 and stage_summary["best_fitness"] == max(run_best)

    loaded, controllers = load_stages(folder)
    assert loaded.config == experiment.config
    first, second = replay_stages(loaded, controllers)
    # Stage 2 starts exactly (bitwise) where stage 1's best motion ended.
    for name in ("points", "com", "frame"):
        np.testing.assert_array_equal(getattr(second, name)[0], getattr(first, name)[-1])
    # Each stage's best, reloaded from JSON and replayed from that start, scores exactly
    # what its search recorded.
    started = start_where(loaded.stages[1], first).task
    assert float(started.fitness(second)) == summary["stages"][1]["best_fitness"]
    for entry in summary["stages"]:
        assert entry["replay_fitness"] == entry["best_fitness"]
    whole = concatenate_trajectories([first, second])
    assert len(whole.ts) == len(first.ts) + len(second.ts) - 1
    assert float(whole.ts[-1]) == pytest.approx(1.0, rel=1e-6)  # two stages of 0.5 s
    assert bool(np.all(np.diff(np.asarray(whole.ts)) > 0))


def test_an_interrupted_multi_stage_run_leaves_nothing_behind(tmp_path, monkeypatch):
    import jaxmotion._cli.results as results

    experiment = parse_config(
        staged(output={"directory": str(tmp_path / "results"), "animation": False})
    )
    searches = []
    search = results.drive

    def interrupted_second(*args, **kwargs):
        searches.append(1)
        if len(searches) == 2:
            raise KeyboardInterrupt
        return search(*args, **kwargs)

    monkeypatch.setattr(results, "drive", interrupted_second)
    with pytest.raises(KeyboardInterrupt):
        run_experiment(experiment, progress=False)
    assert len(searches) == 2 and list((tmp_path / "results").iterdir()) == []


def test_cli_checks_a_multi_stage_config_and_names_the_stage_of_an_error(tmp_path):
    import subprocess
    import sys

    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text(tomli_w.dumps(staged()))
    bad.write_text(tomli_w.dumps(staged(WALK, {"name": "turn", "search": {"climbers": 0}})))
    out = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "check", str(good)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    # Two stages of 4 climbers x (3 + 1) generations.
    assert out.returncode == 0 and "ok (staged: 2 stages, 32 evaluations)" in out.stdout
    out = subprocess.run(
        [sys.executable, "-m", "jaxmotion", "run", str(bad), "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and not (tmp_path / "r").exists()
    assert '[[stage]] 2 ("turn"): [search] climbers = 0; allowed: an integer >= 1' in out.stderr


def test_a_stage_started_elsewhere_keeps_everything_but_its_start():
    """`start_where` changes a stage's task only in its initial state: its robustness (a
    robust stage searched from where the previous ended is still robust), objective, space
    and steps are the stage's own."""
    raw = staged(WALK, {"name": "turn", "robustness": {"samples": 2, "velocity": 0.3}})
    experiment = parse_config(raw)
    stage = experiment.stages[1]
    started = start_where(stage, stage.task.body.initial_state()).task
    assert started.robustness == jm.Robustness(samples=2, velocity=0.3)
    for field in dataclasses.fields(started):
        if field.name != "initial_state":
            assert getattr(started, field.name) is getattr(stage.task, field.name), field.name
