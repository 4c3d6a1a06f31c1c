"""The first paper's three motions as configs: each runs from the command line and writes a
complete results folder whose summary carries its check's verdict (small budgets here); with
the paper's full budget the default seed passes its check (`-m slow`, not in CI)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from jaxmotion._cli.results import accurate_check
from jaxmotion.experiment import load_result

ROOT = Path(__file__).resolve().parents[1]

# Config -> the check its summary must report, and the figures that check measures.
MOTIONS = {
    "spider_leap": (
        "leap",
        {"forward_body_lengths", "max_tilt_degrees", "airborne_periods"},
    ),
    "poodle_somersault": (
        "somersault",
        {"backward_turns", "forward_m", "final_tilt_degrees", "on_floor_at_end"},
    ),
    "table_pirouette": (
        "pirouette",
        {"turns", "max_tilt_degrees", "displacement_body_lengths", "on_floor_at_end"},
    ),
}

# One float64 adaptive replay (rtol 1e-8) computed by two processes with different XLA
# options: the step sizes it adapts differ in the last bits, the figures by about its rtol.
ACCURATE_REPLAY_AGREEMENT = 1e-6

FILES = {
    "config.toml",
    "best_controller.json",
    "history.csv",
    "learning_plot.png",
    "motion.gif",
    "summary.json",
}


def run(config: str, out: Path, *extra: str) -> Path:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxmotion",
            "run",
            str(ROOT / "configs" / f"{config}.toml"),
            "--out",
            str(out),
            "--quiet",
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return Path(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(
    "config",
    # The spider's run covers the CLI's path; the poodle's and the table's are more of it
    # (their configs run, through the API, in the paper000_motions notebook): `-m slow`.
    [c if c == "spider_leap" else pytest.param(c, marks=pytest.mark.slow) for c in MOTIONS],
)
def test_each_motion_config_runs_and_writes_everything(config, tmp_path):
    # One writes its GIF (drawing 10 s of frames is a large share of a run's time).
    animated = config == "spider_leap"
    extra = () if animated else ("--no-animation",)
    # Batches of the config's 100, as the notebook runs them: the CLI and the notebook kernel
    # compile the same programs, and whichever runs second finds them in the tests' cache.
    # The config's accurate pick (100 float64 replays) cut to 2: the same path, in seconds.
    folder = run(
        config, tmp_path, "--evaluations", "100", "--set", "search.accurate_candidates=2", *extra
    )
    files = FILES if animated else FILES - {"motion.gif"}
    assert {p.name for p in folder.iterdir()} == files
    assert all((folder / name).stat().st_size > 0 for name in files)
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["evaluations"] == 100 + 100  # the search set of 100, then the budget
    history = (folder / "history.csv").read_text().strip().splitlines()
    assert len(history) == 1 + summary["evaluations"]
    name, figures = MOTIONS[config]
    check = summary["check"]
    assert check["name"] == name
    assert figures <= set(check["figures"])
    assert isinstance(check["passed"], bool)
    assert check["passed"] == all(check["criteria"].values())
    assert summary["replay_fitness"] == summary["best_fitness"]
    accurate = summary["accurate"]
    assert accurate["candidates"] == 2 and accurate["fitness"] == summary["best_fitness"]
    assert summary["best_fitness"] <= accurate["search_best_fitness"]
    # The chosen motion's check under the accurate replay, as this process computes it.
    experiment, controller = load_result(folder)
    again = accurate_check(experiment, controller).to_dict()
    assert (accurate["check"]["name"], accurate["check"]["passed"]) == (name, again["passed"])
    assert accurate["check"]["criteria"] == again["criteria"]
    for key, value in again["figures"].items():
        assert math.isclose(
            accurate["check"]["figures"][key], value, rel_tol=ACCURATE_REPLAY_AGREEMENT
        )


@pytest.mark.slow
@pytest.mark.parametrize("config", list(MOTIONS))
def test_with_the_papers_budget_the_default_seed_does_the_motion(config, tmp_path):
    folder = run(config, tmp_path, "--no-animation")
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["evaluations"] == 100 + 25_000
    assert summary["check"]["passed"], summary["check"]
