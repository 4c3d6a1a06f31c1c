"""`python -m jaxmotion compose`: controllers found by earlier runs, concatenated, their
transitions searched; the config checked before anything runs; the results folder."""

import json
import shutil
import tomllib

import numpy as np
import pytest
import tomli_w

import jaxmotion as jm
from jaxmotion._cli.compose import _check_shared, parse_compose_config, phase_trajectories
from jaxmotion._cli.main import _compose, _export, _parser
from jaxmotion.experiment import ConfigError, controller_from_dict, parse_config, run_experiment

COMPONENT = {
    "body": {"figure": "star_man"},
    "world": {"floor_stiffness": 1.0e4, "floor_damping": 100.0, "friction_velocity": 0.1},
    "controller": {"family": "time_bsr", "num_rules": 3, "t_per": 0.2},
    "objective": {"forward": 1.0},
    "simulation": {"duration": 0.4, "dt": 0.004},
    "search": {"algorithm": "serial_search", "climbers": 2, "generations": 2},
    "output": {"animation": False},
}
EXPORT_ATOL = 1e-5  # m: the exported motion is the scored one (float32 rounding)
STAGE_ATOL = 1e-5  # m: a phase replays its stage (float32 rounding of the saved samples)
SCRIPT = """
# the kick should last 40 ticks, then the roll travels
kick = delta_time ?= 40
roll = 1.0 + delta_cm_x
total = kick * roll
"""


@pytest.fixture(scope="module")
def components(tmp_path_factory):
    """Two results folders of tiny runs (one compilation: the same shapes, two seeds)."""
    out = tmp_path_factory.mktemp("components")
    folders = []
    for seed in (0, 1):
        experiment = parse_config({**COMPONENT, "seed": seed}, name=f"part{seed}")
        folders.append(run_experiment(experiment, directory=out, progress=False))
    return folders


def compose_raw(folders, **changes):
    raw = {
        "name": "duo",
        "phase": [
            {"name": "kick", "results": str(folders[0]), "ticks": 50},
            {"name": "roll", "results": str(folders[1]), "ticks": 50},
        ],
        "script": {"text": SCRIPT},
        "search": {"arrays": 4, "rounds": 2, "mutations": 1},
    }
    raw.update(changes)
    return raw


def test_compose_writes_a_searched_composite(components, tmp_path):
    """The CLI runs the search and writes its folder: the best transitions score at least
    the start, the saved sequence holds the components' controllers at those transitions,
    the summary reports each phase's measures, and the resolved config reads back."""
    config = tmp_path / "duo.toml"
    config.write_text(tomli_w.dumps(compose_raw(components)))
    out = tmp_path / "results"
    # The CLI's own parsing and command (`main` would also set JAX's devices, which a test
    # process has started already).
    args = _parser().parse_args(["compose", str(config), "--out", str(out), "--no-animation"])
    assert args.command == "compose"
    args.quiet = True
    assert _compose(args) == 0
    (folder,) = out.iterdir()
    names = {p.name for p in folder.iterdir()}
    assert {
        "config.toml",
        "best_controller.json",
        "best_transitions.json",
        "history.csv",
        "learning_plot.png",
        "summary.json",
    } <= names
    summary = json.loads((folder / "summary.json").read_text())
    best, start = summary["best"], summary["start"]
    assert best["fitness"] >= start["fitness"]
    assert start["ticks"] == [50]
    assert summary["evaluations"] == 4 + 2 * 1 * 4
    # delta_time in the summary is the transition's tick count, the phases' sum the whole.
    ticks = [best["phases"][p]["delta_time"] for p in ("kick", "roll")]
    assert ticks == [best["ticks"][0], 100 - best["ticks"][0]]
    assert set(best["values"]) == {"kick", "roll", "total"}
    sequence = controller_from_dict(json.loads((folder / "best_controller.json").read_text()))
    assert isinstance(sequence, jm.Sequence)
    np.testing.assert_allclose(sequence.transitions, best["transitions"])
    again = parse_compose_config(tomllib.loads((folder / "config.toml").read_text()))
    assert again.config == tomllib.loads((folder / "config.toml").read_text())
    # `export` rebuilds the composite's best motion from the folder: one BVH frame per
    # tick, the motion the search scored (the fast path's samples).
    args = _parser().parse_args(["export", str(folder), "--format", "bvh"])
    assert _export(args) == 0
    motion = again.composite.trajectory(best["transitions"])
    text = (folder / "motion.bvh").read_text()
    assert f"Frames: {len(motion.ts)}" in text
    recorded = again.composite.trajectory(best["transitions"], positions=True)
    np.testing.assert_allclose(recorded.points, motion.points, atol=EXPORT_ATOL)


def test_phase_cuts_rejoin_the_motion(components):
    compose = parse_compose_config(compose_raw(components))
    trajectory = compose.composite.trajectory(np.array([0.2]))
    parts = phase_trajectories(trajectory, [0.2])
    assert [len(p.ts) for p in parts] == [51, 51]  # samples every tick; the cut shared
    np.testing.assert_array_equal(parts[0].points[-1], parts[1].points[0])
    assert float(parts[1].ts[0]) == 0.0


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(phase=[]), r"needs \[\[phase\]\] tables"),
        (
            dict(script={"text": "total = kick.nope"}),
            r"\[script\] text: line 1, column 14: unknown measure 'nope'",
        ),
        (dict(search={"arrays": 1}), r"\[search\] arrays = 1"),
        (dict(oops={"x": 1}), r"unknown section \[oops\]"),
        (
            dict(script={"text": SCRIPT, "tick": 0.006}),
            r"\[script\] tick = 0.006 is not a whole number of control periods",
        ),
        (dict(script={"text": SCRIPT, "tick": 0}), r"\[script\] tick = 0"),
    ],
)
def test_bad_compose_configs_name_what_is_wrong(components, change, match):
    with pytest.raises(ConfigError, match=match):
        parse_compose_config(compose_raw(components, **change))


def test_a_phase_needs_one_source_and_a_unique_name(components):
    raw = compose_raw(components)
    raw["phase"][1] = {"name": "roll", "ticks": 5}
    with pytest.raises(ConfigError, match="needs exactly one of results"):
        parse_compose_config(raw)
    raw["phase"][1] = {"name": "kick", "results": str(components[1]), "ticks": 5}
    with pytest.raises(ConfigError, match='name = "kick" is used twice'):
        parse_compose_config(raw)
    raw["phase"][1] = {"name": "roll", "results": "no/such/folder", "ticks": 5}
    with pytest.raises(ConfigError, match="no/such/folder"):
        parse_compose_config(raw)


def test_components_must_share_body_world_and_step():
    a = parse_config(COMPONENT)
    b = parse_config({**COMPONENT, "world": {**COMPONENT["world"], "friction": 0.5}})
    with pytest.raises(ConfigError, match=r'phase "b": its \[world\]'):
        _check_shared([("a", a, None), ("b", b, None)])


def test_a_control_period_longer_than_the_step_is_the_scripts_tick():
    """`[simulation] control_dt` sets the task's control period (the composite's tick);
    one that is not a whole number of steps names itself."""
    raw = {**COMPONENT, "simulation": {"duration": 0.4, "dt": 0.004, "control_dt": 0.02}}
    assert parse_config(raw).task.control_dt == 0.02
    bad = {**COMPONENT, "simulation": {"duration": 0.4, "dt": 0.004, "control_dt": 0.006}}
    with pytest.raises(ConfigError, match=r"\[simulation\] control_dt = 0.006"):
        parse_config(bad)


def test_a_script_tick_counts_coarser_than_the_control_period(components):
    """`[script] tick` sets the script's unit: the phases' ticks and the duration count it,
    while the components keep their control period."""
    raw = compose_raw(components, script={"text": SCRIPT, "tick": 0.02})
    raw["phase"][0]["ticks"], raw["phase"][1]["ticks"] = 12, 8
    compose = parse_compose_config(raw)
    assert compose.composite.tick == pytest.approx(0.02)
    assert compose.composite.control_dt == pytest.approx(0.004)
    assert compose.composite.duration == pytest.approx(0.4)
    np.testing.assert_allclose(compose.initial, [0.24])


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    """The results folder of a tiny two-stage run (the second starts where the first ended;
    one compilation: the stages share their shapes)."""
    raw = {**COMPONENT, "stage": [{"name": "kick"}, {"name": "roll"}]}
    experiment = parse_config(raw, name="staged")
    return run_experiment(experiment, directory=tmp_path_factory.mktemp("staged"), progress=False)


def test_phases_can_be_the_stages_of_a_multi_stage_run(staged):
    """`stage = "NAME"` takes a phase from a multi-stage run; at the stages' own boundary
    the composite replays the run: each phase's motion is its stage's."""
    from jaxmotion.experiment import load_stages, replay_stages

    raw = compose_raw([staged, staged])
    for phase, stage in zip(raw["phase"], ("kick", "roll"), strict=True):
        phase.update(stage=stage, ticks=100)  # each stage's own 0.4 s
    compose = parse_compose_config(raw)
    experiment, controllers = load_stages(staged)
    assert [e.name for _, e, _ in compose.phases] == ["kick", "roll"]
    for (_, _, mine), theirs in zip(compose.phases, controllers, strict=True):
        assert mine == theirs
    stages = replay_stages(experiment, controllers)
    boundary = float(stages[0].ts[-1])
    motion = compose.composite.trajectory(np.array([boundary]))
    parts = phase_trajectories(motion, [boundary])
    for part, stage in zip(parts, stages, strict=True):
        same = np.round(np.asarray(stage.ts) / compose.composite.tick).astype(int)
        np.testing.assert_allclose(part.com[same], stage.com, atol=STAGE_ATOL)


def test_a_phase_names_a_stage_exactly_when_its_run_has_stages(staged, components):
    raw = compose_raw([staged, components[1]])
    with pytest.raises(ConfigError, match=r"is a multi-stage run; allowed: name its stage"):
        parse_compose_config(raw)
    raw["phase"][0]["stage"] = "nope"
    with pytest.raises(ConfigError, match=r"stage = 'nope' is not a stage of .*'kick', 'roll'"):
        parse_compose_config(raw)
    raw = compose_raw(components)
    raw["phase"][0]["stage"] = "kick"
    with pytest.raises(ConfigError, match=r"stage = 'kick' is not a stage of .* no stage key"):
        parse_compose_config(raw)


def test_every_phase_is_checked_before_a_component_runs(components):
    """A bad results folder in a later phase is reported before an earlier phase's config
    is run (nothing is searched, nothing written)."""
    raw = compose_raw(components)
    raw["phase"][0] = {"name": "kick", "config": "configs/default.toml", "ticks": 50}
    raw["phase"][1]["results"] = "no/such/folder"
    ran = []
    with pytest.raises(ConfigError, match=r'\[\[phase\]\] 2 \("roll"\): results = .no/such/folder'):
        parse_compose_config(raw, run_component=ran.append)
    assert ran == []


def test_a_component_run_first_is_recorded_by_its_results_folder(components):
    """The resolved config names the folder a phase's config ran into (not the config), so
    the composite's own config.toml composes the same controllers without running them."""
    raw = compose_raw(components)
    raw["phase"][0] = {"name": "kick", "config": "configs/default.toml", "ticks": 50}
    compose = parse_compose_config(raw, run_component=lambda path: components[0])
    assert compose.config["phase"][0] == {
        "name": "kick",
        "ticks": 50,
        "results": str(components[0]),
    }
    again = parse_compose_config(compose.config)
    assert again.config == compose.config


def test_an_interrupted_transition_search_resumes_to_the_uninterrupted_result(components, tmp_path):
    """Stopped after its third mutation step, the compose run saves its transition search
    and writes no folder; resumed, it finishes with the uninterrupted run's transitions and
    history, bitwise, and removes the checkpoint. A checkpoint of another compose config, or
    of the same config after a component's results folder was rewritten, is refused before
    anything runs."""
    from jaxmotion._cli.compose import run_compose
    from jaxmotion._cli.results import Interrupted

    search = {"arrays": 4, "rounds": 3, "mutations": 2}
    roll = tmp_path / "roll"  # a component folder of this test's own, rewritten below
    shutil.copytree(components[1], roll)
    compose = parse_compose_config(compose_raw([components[0], roll], search=search), name="duo")
    whole = run_compose(compose, directory=tmp_path / "whole", animation=False)
    asked = []

    def stop():
        asked.append(1)
        return len(asked) == 3

    cut = tmp_path / "cut"
    with pytest.raises(Interrupted) as stopped:
        run_compose(compose, directory=cut, animation=False, checkpoint_every=1e9, stop=stop)
    saved = stopped.value.checkpoint
    assert [p.name for p in cut.iterdir()] == [saved.name]  # the checkpoint, no folder
    kept = tmp_path / "kept.checkpoint"
    kept.write_bytes(saved.read_bytes())
    folder = run_compose(compose, directory=cut, animation=False, resume=cut)
    assert not saved.exists()
    for name in ("best_transitions.json", "history.csv", "best_controller.json"):
        assert (folder / name).read_text() == (whole / name).read_text(), name

    other = parse_compose_config(
        compose_raw([components[0], roll], search={**search, "rounds": 4}), name="duo"
    )
    with pytest.raises(ConfigError, match="another config"):
        run_compose(other, directory=tmp_path / "other", animation=False, resume=kept)
    assert not (tmp_path / "other").exists()

    # The same config, but the roll's folder now holds another controller.
    shutil.copy(components[0] / "best_controller.json", roll / "best_controller.json")
    rewritten = parse_compose_config(compose_raw([components[0], roll], search=search), name="duo")
    with pytest.raises(ConfigError, match="differs in: component_controllers"):
        run_compose(rewritten, directory=tmp_path / "other", animation=False, resume=kept)
    assert not (tmp_path / "other").exists()
