"""Checkpoint and resume: a search interrupted at any step (Ctrl-C, SIGTERM, SIGKILL) and
continued from its checkpoint finishes bitwise as the uninterrupted search; checkpoints are
written atomically and refused when truncated, of another config or of another version."""

import json
import os
import random
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from jaxmotion.experiment import (
    ConfigError,
    Interrupted,
    default_config_path,
    parse_config,
    run_experiment,
)

ROOT = Path(__file__).resolve().parents[1]

# The default config, shrunk: a 0.3-s motion, search sets of 16 (one compiled batch size).
SEARCHES = {
    "parallel_hill_climb": {"evaluations": 160, "size": 16, "batch": 16},
    "serial_search": {"climbers": 8, "runs": 2, "generations": 12, "reseed_every": 5},
    "evolve": {"generations": 6, "size": 20, "mutations": 2},
}


def tiny(algorithm: str, directory: Path, **top):
    raw = tomllib.loads(default_config_path().read_text())
    raw["simulation"]["duration"] = 0.3
    raw["search"] = {"algorithm": algorithm, **SEARCHES[algorithm]}
    raw["output"] = {"directory": str(directory), "animation": False}
    raw.update(top)
    return parse_config(raw, name=f"tiny-{algorithm.replace('_', '-')}")


def results(folder: Path) -> dict:
    """What must be bitwise equal: the best controller, its fitness, every evaluation."""
    summary = json.loads((folder / "summary.json").read_text())
    return {
        "best_controller.json": (folder / "best_controller.json").read_text(),
        "history.csv": (folder / "history.csv").read_text(),
        "best_fitness": summary["best_fitness"],
        "histories": sorted((p.name, p.read_text()) for p in folder.glob("history-run-*.csv")),
    }


def interrupt_after(monkeypatch, steps: int):
    """Ctrl-C after the driver has reported `steps` steps (the initial set is step 1)."""
    import jaxmotion._cli.results as module

    record = module._Checkpoints.__call__
    seen = []

    def interrupted(self, state, part):
        record(self, state, part)
        seen.append(1)
        if len(seen) == steps:
            raise KeyboardInterrupt

    monkeypatch.setattr(module._Checkpoints, "__call__", interrupted)


@pytest.mark.parametrize("algorithm", ["serial_search", "evolve"])
def test_resume_after_ctrl_c_is_bitwise_the_uninterrupted_run(tmp_path, monkeypatch, algorithm):
    reference = run_experiment(tiny(algorithm, tmp_path / "a"), progress=False)
    experiment = tiny(algorithm, tmp_path / "b")
    steps = random.Random(algorithm).randint(2, 5)  # a step inside the search
    with monkeypatch.context() as patch:
        interrupt_after(patch, steps)
        with pytest.raises(Interrupted) as stopped:
            run_experiment(experiment, progress=False, checkpoint_every=3600.0)
    checkpoint = stopped.value.checkpoint
    assert checkpoint is not None and checkpoint.is_file()
    assert [p.name for p in (tmp_path / "b").iterdir()] == [checkpoint.name]  # no folder
    folder = run_experiment(experiment, progress=False, resume=tmp_path / "b")
    assert results(folder) == results(reference)
    assert [p.name for p in (tmp_path / "b").iterdir()] == [folder.name]  # checkpoint gone


def test_truncated_foreign_and_other_version_checkpoints_are_refused(tmp_path, monkeypatch):
    from jaxmotion._cli.checkpoint import MAGIC

    experiment = tiny("evolve", tmp_path)
    with monkeypatch.context() as patch:
        interrupt_after(patch, 2)
        with pytest.raises(Interrupted) as stopped:
            run_experiment(experiment, progress=False, checkpoint_every=3600.0)
    path = stopped.value.checkpoint
    data = path.read_bytes()

    other_seed = tiny("evolve", tmp_path, seed=7)
    with pytest.raises(ConfigError, match=r"a checkpoint of another config \(differs in: seed\)"):
        run_experiment(other_seed, progress=False, resume=path)
    cut = tmp_path / "cut.checkpoint"
    cut.write_bytes(data[: len(data) - 100])
    with pytest.raises(ConfigError, match=r"cut.checkpoint: truncated or corrupted"):
        run_experiment(experiment, progress=False, resume=cut)
    header_end = data.index(b"\n", len(MAGIC))
    header = json.loads(data[len(MAGIC) : header_end])
    header["jaxmotion"] = "0.0.1"
    old = tmp_path / "old.checkpoint"
    old.write_bytes(MAGIC + json.dumps(header).encode() + data[header_end:])
    with pytest.raises(
        ConfigError, match=r"written by jaxmotion '0.0.1'.*allowed: a checkpoint of"
    ):
        run_experiment(experiment, progress=False, resume=old)
    (tmp_path / "x.toml").write_text("x")
    with pytest.raises(ConfigError, match=r"x.toml: not a jaxmotion checkpoint"):
        run_experiment(experiment, progress=False, resume=tmp_path / "x.toml")
    # Nothing was written by the refused runs: no folders, no partial folders.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [path.name, "cut.checkpoint", "old.checkpoint", "x.toml"]
    )


def _start(config: Path, out: Path, *options: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "jaxmotion",
            "run",
            str(config),
            "--out",
            str(out),
            "--quiet",
            "--no-animation",
            *options,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _kill_mid_search(
    process: subprocess.Popen, out: Path, how: int, rng: random.Random, within: float
):
    """Send `how` at a random moment up to `within` seconds after the process has written a
    checkpoint (a new one, or a newer version of the one there)."""
    deadline = time.monotonic() + 300
    before = {p: p.stat().st_mtime_ns for p in out.glob("*.checkpoint")}

    def written():
        return any(before.get(p) != p.stat().st_mtime_ns for p in out.glob("*.checkpoint"))

    while not written():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(rng.uniform(0.0, within))
    process.send_signal(how)
    return process.communicate(timeout=300)


CLI_SEARCHES = {
    "parallel_hill_climb": {"evaluations": 4000, "size": 16, "batch": 16},
    "serial_search": {"climbers": 8, "runs": 2, "generations": 250, "reseed_every": 20},
    "evolve": {"generations": 120, "size": 20, "mutations": 2},
}


@pytest.mark.parametrize(
    ("algorithm", "stop"),
    [
        ("parallel_hill_climb", signal.SIGINT),
        pytest.param("serial_search", signal.SIGTERM, marks=pytest.mark.slow),
        pytest.param("evolve", signal.SIGINT, marks=pytest.mark.slow),
    ],
)
def test_cli_killed_with_sigkill_then_stopped_resumes_bitwise(tmp_path, algorithm, stop):
    """A real run killed with SIGKILL at a random moment leaves its last checkpoint (and a
    partial folder, which the next run removes); resumed and stopped again with SIGINT
    (Ctrl-C) or SIGTERM, it writes a fresh checkpoint and exits 130; resumed once more it
    finishes with bitwise the uninterrupted run's best controller, fitness and history."""
    raw = tomllib.loads(default_config_path().read_text())
    raw["simulation"]["duration"] = 0.3
    raw["search"] = {"algorithm": algorithm, **CLI_SEARCHES[algorithm]}
    config = tmp_path / "tiny.toml"
    config.write_text(__import__("tomli_w").dumps(raw))
    rng = random.Random(os.getpid())

    reference = _start(config, tmp_path / "a")
    out, err = reference.communicate(timeout=300)
    assert reference.returncode == 0, err
    expected = results(Path(out.strip().splitlines()[-1]))

    b = tmp_path / "b"
    killed = _start(config, b, "--checkpoint-every", "0.05")
    _kill_mid_search(killed, b, signal.SIGKILL, rng, within=0.3)
    assert killed.returncode == -signal.SIGKILL
    (checkpoint,) = b.glob("*.checkpoint")
    assert [p for p in b.iterdir() if p.name.endswith(".partial")]  # left by the kill

    stopped = _start(config, b, "--checkpoint-every", "0.05", "--resume", str(b))
    _, err = _kill_mid_search(stopped, b, stop, rng, within=0.2)
    assert stopped.returncode == 130, err
    assert f"--resume {checkpoint}" in err
    assert sorted(p.name for p in b.iterdir()) == [checkpoint.name]  # partial folders gone

    resumed = _start(config, b, "--resume", str(checkpoint))
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    folder = Path(out.strip().splitlines()[-1])
    assert results(folder) == expected
    assert sorted(p.name for p in b.iterdir()) == [folder.name]


def stages_results(folder: Path) -> dict:
    """Every stage's `results` (a multi-stage folder)."""
    return {p.name: results(p) for p in sorted(folder.glob("stage-*"))}


@pytest.mark.parametrize("steps", [3, 13])  # in the first stage's search; in the second's
def test_a_multi_stage_run_resumes_bitwise_from_any_stage(tmp_path, monkeypatch, steps):
    """A [[stage]] run's checkpoint holds each stage begun: a finished stage is continued
    from its last state (no step left), the one in progress from where it stopped."""

    def staged(directory):
        raw = tomllib.loads(default_config_path().read_text())
        raw["simulation"]["duration"] = 0.3
        del raw["search"]
        raw["output"] = {"directory": str(directory), "animation": False}
        hill_climb = {"algorithm": "parallel_hill_climb", **SEARCHES["parallel_hill_climb"]}
        raw["stage"] = [
            {"name": "first", "search": hill_climb},  # the initial set, 10 steps: 11 reports
            {"name": "second", "search": {"algorithm": "evolve", **SEARCHES["evolve"]}},
        ]
        return parse_config(raw, name="tiny-stages")

    reference = run_experiment(staged(tmp_path / "a"), progress=False)
    experiment = staged(tmp_path / "b")
    with monkeypatch.context() as patch:
        interrupt_after(patch, steps)
        with pytest.raises(Interrupted) as stopped:
            run_experiment(experiment, progress=False, checkpoint_every=3600.0)
    assert [p.name for p in (tmp_path / "b").iterdir()] == [stopped.value.checkpoint.name]
    folder = run_experiment(experiment, progress=False, resume=stopped.value.checkpoint)
    assert stages_results(folder) == stages_results(reference)
    assert len(stages_results(folder)) == 2
    # Each stage's non-finite evaluations are counted in the run's summary.
    summary = json.loads((folder / "summary.json").read_text())
    for entry in summary["stages"]:
        history = (folder / entry["folder"] / "history.csv").read_text()
        assert entry["nonfinite_evaluations"] == history.count(",-inf,")
