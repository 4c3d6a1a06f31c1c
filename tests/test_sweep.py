"""`python -m jaxmotion sweep`: searches as Ray tasks, each the CLI's `run`.

One sweep on a local Ray with 2 workers (2 configs x 1 seed, tiny budgets), one of whose
runs is SIGKILLed mid-run; its folders are compared with plain `run`s of the same config,
seed and overrides. Bad --seeds and --set fail before Ray starts."""

import argparse
import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from jaxmotion._cli.sweep import apply_sets, override_sets, pack, parse_seeds, unpack

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = [ROOT / "configs" / "default.toml", ROOT / "configs" / "spider_leap.toml"]
# Tiny budgets: 120 evaluations of 1 s motions (most of a task is starting Python and JAX,
# and the first compilation of each body).
SETS = ["search.evaluations=100", "search.size=20", "search.batch=20", "simulation.duration=1.0"]
SETS += ["search.accurate_candidates=0"]  # the spider's accurate pick is tested elsewhere
SEEDS = (0,)  # the slow two-node test runs two seeds of one config
VICTIM = "spider_leap-seed0"  # the task whose first attempt is killed
CHECKPOINT_EVERY_S = 0.2  # so that the victim has a checkpoint to resume from
SWEEP_TIMEOUT_S = 600  # a hung sweep fails the test instead of hanging CI


def _kill_when_running(proc: subprocess.Popen, root: Path) -> int | None:
    """SIGKILL the first attempt of VICTIM's `run` process once it is searching and has
    saved a checkpoint (its `*.checkpoint` file exists); the process is found by its hidden
    results folder, `.NAME-TIME.pidPID.*.partial`. Returns the pid killed (None if the
    sweep ended first)."""
    work = f"sweep-*/.{VICTIM}.task/out"
    while proc.poll() is None:
        if any(root.glob(f"{work}/*.checkpoint")):
            for partial in root.glob(f"{work}/.*.partial"):
                pid = int(re.search(r"\.pid(\d+)\.", partial.name).group(1))
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue  # it finished between the glob and the kill
                return pid
        time.sleep(0.005)
    return None


def _plain_runs(tmp_path: Path, configs=CONFIGS, seeds=SEEDS) -> dict[str, Path]:
    """The same searches by `run` (`python -m jaxmotion run CONFIG --seed S --set ...
    --cpu-devices 1`, the CLI's `main` called as `python -m jaxmotion` calls it, in one
    process so that Python and JAX start once); their folders by the sweep's labels."""
    calls, labels = [], []
    for config in configs:
        for seed in seeds:
            out = tmp_path / "plain" / f"{config.stem}-{seed}"
            sets = [f"--set={s}" for s in SETS]
            flags = ["--cpu-devices", "1", "--no-animation", "--quiet", "--out", str(out)]
            calls.append(["run", str(config), "--seed", str(seed), *sets, *flags])
            labels.append(f"{config.stem}-seed{seed}")
    script = (
        "import json, sys\nfrom jaxmotion._cli.main import main\n"
        "for argv in json.loads(sys.argv[1]):\n    assert main(argv) == 0\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, json.dumps(calls)],
        capture_output=True,
        text=True,
        timeout=SWEEP_TIMEOUT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    folders = [Path(line) for line in done.stdout.split()]
    return dict(zip(labels, folders, strict=True))


def test_sweep_equals_runs_and_retries_a_killed_task(tmp_path):
    root = tmp_path / "sweeps"
    command = [sys.executable, "-m", "jaxmotion", "sweep", *map(str, CONFIGS)]
    command += ["--seeds", ",".join(map(str, SEEDS)), *(f"--set={s}" for s in SETS)]
    command += ["--no-animation"]
    command += ["--local-cpus", "2", "--cpus-per-task", "1", "--out", str(root)]
    command += ["--checkpoint-every", str(CHECKPOINT_EVERY_S)]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        killed = _kill_when_running(proc, root)
        out, err = proc.communicate(timeout=SWEEP_TIMEOUT_S)
    finally:
        proc.kill()
    assert killed is not None, f"the sweep ended before {VICTIM} could be killed:\n{err}"
    assert proc.returncode == 0, err
    sweep = Path(out.split()[-1])

    rows = {row["folder"]: row for row in csv.DictReader((sweep / "sweep.csv").open())}
    labels = [f"{c.stem}-seed{s}" for s in SEEDS for c in CONFIGS]
    assert list(rows) == labels  # every search, in order
    for label, row in rows.items():
        assert row["status"] == "ok", row
        assert row["attempts"] == ("2" if label == VICTIM else "1"), row
        assert row["overrides"] == " ".join(SETS)
    # The killed attempt is reported, in the table and on stderr, and its retry resumed
    # from its checkpoint (to the very result of an uninterrupted run, checked below).
    failures = rows[VICTIM]["failures"]
    assert failures.startswith("attempt 1: killed by SIGKILL"), failures
    assert failures.endswith("; attempt 2 resumed from the checkpoint"), failures
    assert f"{VICTIM}: attempt 1 killed by SIGKILL" in err
    assert "## Failures and retries" in (sweep / "sweep.md").read_text()
    assert (sweep / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Nothing half-written: only the finished folders and the tables (the killed attempt's
    # working folder went with its retry).
    assert sorted(p.name for p in sweep.iterdir()) == sorted(
        [*labels, "sweep.csv", "sweep.md", "sweep.png"]
    )

    # Each folder is the plain run's: the same files, the same resolved config, the same
    # fitness for every evaluation, the same best fitness (exactly: the same program).
    plain = _plain_runs(tmp_path)
    seeds = {f"{c.stem}-seed{s}": s for s in SEEDS for c in CONFIGS}
    for label in labels:
        ours, theirs = sweep / label, plain[label]
        assert sorted(p.name for p in ours.iterdir()) == sorted(p.name for p in theirs.iterdir())
        assert (ours / "config.toml").read_text() == (theirs / "config.toml").read_text()
        resolved = tomllib.loads((ours / "config.toml").read_text())  # --set took effect
        assert (resolved["seed"], resolved["search"]["evaluations"]) == (seeds[label], 100)
        assert (resolved["search"]["batch"], resolved["simulation"]["duration"]) == (20, 1.0)
        assert (ours / "history.csv").read_text() == (theirs / "history.csv").read_text()
        best = json.loads((theirs / "summary.json").read_text())["best_fitness"]
        assert json.loads((ours / "summary.json").read_text())["best_fitness"] == best
        assert float(rows[label]["best_fitness"]) == best


def _main(argv, capsys) -> tuple[int, str]:
    from jaxmotion._cli.main import main

    code = main([*argv, "--cpu-devices", "1", "--no-compilation-cache"])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--seeds", "5-2"], "--seeds '5-2': the range '5-2' runs backwards; allowed: integers"),
        (["--seeds", "0,x"], "--seeds '0,x': 'x' is not a seed or a range"),
        (["--seeds", "0-3,2"], "--seeds '0-3,2': seed 2 is given twice"),
        (["--seeds", "4294967296"], "--seeds '4294967296': 4294967296 is too large"),
        (["--set", "search.evaluations"], "--set 'search.evaluations' has no '='; allowed: KEY="),
        (["--set", "search.evaluations=2k"], "'2k' is not a TOML value; allowed: a number"),
        (["--set", "search..size=3"], "the key 'search..size' is not a dotted name"),
        (["--set", "search=3"], "search is a table; allowed: one of its keys"),
        (["--set", "seed.x=3"], "seed is the value 0, not a table"),
        (
            ["--set", "search.evaluationz=10"],
            "[search] has an unknown key 'evaluationz'; allowed: algorithm, evaluations",
        ),
        (
            ["--set", "search.evaluations=-5"],
            "[search] evaluations = -5; allowed: an integer",
        ),
        (["--set", "seed=1", "--set", "seed=1"], "--set 'seed=1' is given twice"),
        (["--address", "headnode"], "--address 'headnode'; allowed: HOST:PORT of a running"),
        # Port 1 on this machine: refused at once (Ray itself would keep trying for minutes).
        (["--address", "127.0.0.1:1"], "--address '127.0.0.1:1': nothing answers at"),
        (["--address", "127.0.0.1:1", "--local-cpus", "2"], "--local-cpus sizes the local Ray"),
    ],
)
def test_bad_options_are_named_before_ray_starts(option, message, capsys, tmp_path):
    code, err = _main(["sweep", str(CONFIGS[0]), *option, "--out", str(tmp_path)], capsys)
    assert code == 2
    assert message in err
    assert not any(tmp_path.iterdir())  # nothing started, nothing written


def test_run_takes_set_once_per_key(capsys, tmp_path):
    argv = ["run", str(CONFIGS[0]), "--set", "seed=1", "--set", "seed=2", "--out", str(tmp_path)]
    code, err = _main(argv, capsys)
    assert code == 2
    assert "--set seed is given 2 times; allowed: once" in err


def test_set_values_are_toml_and_repeated_keys_are_crossed():
    sets = override_sets(
        ["search.size=50", "name=fast-cube", "search.size=100", 'output.directory="r s"'],
        grid=True,
    )
    assert [[(s.key, s.value) for s in combo] for combo in sets] == [
        [("search.size", 50), ("name", "fast-cube"), ("output.directory", "r s")],
        [("search.size", 100), ("name", "fast-cube"), ("output.directory", "r s")],
    ]
    raw = {"search": {"size": 10, "batch": 5}, "seed": 0}
    applied = apply_sets(raw, sets[1])
    assert applied == {
        "search": {"size": 100, "batch": 5},
        "seed": 0,
        "name": "fast-cube",
        "output": {"directory": "r s"},
    }
    assert raw == {"search": {"size": 10, "batch": 5}, "seed": 0}  # the config is not changed
    assert parse_seeds("0-2, 7,9-10") == (0, 1, 2, 7, 9, 10)


def test_a_folder_sent_back_from_another_node_arrives_whole(tmp_path):
    """A search on another node sends its results folder back as an archive (no shared file
    system): every file, a multi-stage run's subfolders too, byte for byte."""
    folder = tmp_path / "cube-forward-20261204-120000"
    (folder / "stage-1-walk").mkdir(parents=True)
    files = {
        "summary.json": b'{"best_fitness": 1.5}\n',
        "history.csv": b"evaluation,step,fitness,best_so_far\n1,0,1.5,1.5\n",
        "stage-1-walk/learning_plot.png": bytes(range(256)) * 40,
    }
    for name, data in files.items():
        (folder / name).write_bytes(data)
    into = tmp_path / "sweep"
    into.mkdir()
    unpack(pack(folder, "default-seed3"), into)
    arrived = {
        str(p.relative_to(into / "default-seed3")): p.read_bytes()
        for p in (into / "default-seed3").rglob("*")
        if p.is_file()
    }
    assert arrived == files
    assert [p.name for p in into.iterdir()] == ["default-seed3"]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # Ray's processes, started here
def test_sweep_on_a_two_node_cluster(tmp_path):
    """`--address`: a sweep on an existing cluster (two Ray nodes of one CPU each on this
    machine, `ray.cluster_utils.Cluster`); the search that runs on the node the driver is
    not attached to sends its folder back, and every folder equals the plain run's.
    `python -m pytest -n0 -m slow tests/test_sweep.py` (about a minute)."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        command = [sys.executable, "-m", "jaxmotion", "sweep", str(CONFIGS[0]), "--seeds", "0-1"]
        command += [*(f"--set={s}" for s in SETS), "--no-animation"]
        command += ["--address", cluster.address, "--out", str(tmp_path / "sweeps")]
        done = subprocess.run(
            command, capture_output=True, text=True, timeout=SWEEP_TIMEOUT_S, check=False
        )
    finally:
        cluster.shutdown()
    assert done.returncode == 0, done.stderr
    assert "sent back from" in done.stderr
    sweep = Path(done.stdout.split()[-1])
    for label, theirs in _plain_runs(tmp_path, CONFIGS[:1], (0, 1)).items():
        ours = sweep / label
        assert (ours / "history.csv").read_text() == (theirs / "history.csv").read_text()
        best = json.loads((theirs / "summary.json").read_text())["best_fitness"]
        assert json.loads((ours / "summary.json").read_text())["best_fitness"] == best


def test_without_ray_sweep_names_the_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as if not installed
    code, err = _main(["sweep", str(CONFIGS[0]), "--out", str(tmp_path)], capsys)
    assert code == 2
    assert (
        "sweep runs its searches on Ray; install it with: pip install 'jaxmotion[cluster]'" in err
    )
    assert not any(tmp_path.iterdir())


def test_plan_is_seed_major_and_a_set_seed_is_the_seed():
    from jaxmotion._cli.sweep import _plan

    def plan(seeds, sets):
        args = argparse.Namespace(config=[str(c) for c in CONFIGS], seeds=seeds, set=sets)
        return [(t.label, t.seed, t.overrides) for t in _plan(args)]

    assert plan("3,1", ["search.size=50"]) == [
        ("default-seed3", 3, "search.size=50"),
        ("spider_leap-seed3", 3, "search.size=50"),
        ("default-seed1", 1, "search.size=50"),
        ("spider_leap-seed1", 1, "search.size=50"),
    ]
    assert plan(None, ["seed=4", "seed=7"]) == [
        ("default-seed4-set1", 4, "seed=4"),
        ("default-seed7-set2", 7, "seed=7"),
        ("spider_leap-seed4-set1", 4, "seed=4"),
        ("spider_leap-seed7-set2", 7, "seed=7"),
    ]


NICENESS = """\
import argparse, os
from jaxmotion._cli.sweep import _start_ray
ray, _ = _start_ray(argparse.Namespace(address=None, local_cpus=1, cpus_per_task=1))
task = ray.remote(num_cpus=1)(lambda: os.nice(0))
print(os.nice(0), ray.get(task.remote()))
"""


def test_a_local_rays_tasks_run_at_the_sweeps_own_priority():
    # Ray starts its workers with niceness 15 and a task's search (their child) inherits
    # it: beside any other work the sweep's searches then crawled
    # (test_sweep_equals_runs_and_retries_a_killed_task took 267 s in a loaded suite against
    # 64 s alone).
    done = subprocess.run(
        [sys.executable, "-c", NICENESS], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-3000:]
    driver, task = map(int, done.stdout.split())
    assert task == driver
