"""Running an experiment and writing (and reading back) its results folder."""

import csv
import dataclasses
import datetime as _dt
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import tomli_w

from .._control.base import AbstractController
from .._control.regimes import Regimes
from .._control.sense_bsr import SenseBSR
from .._control.time_bsr import TimeBSR
from .._search.hill_climb import SearchResult, parallel_hill_climb
from .._search.history import History
from .._search.serial import serial_search
from .config import ConfigError, Experiment, parse_config

CONTROLLER_FAMILIES: dict[str, type[AbstractController]] = {
    "regimes": Regimes,
    "time_bsr": TimeBSR,
    "sense_bsr": SenseBSR,
}
FORMAT_VERSION = 1


def controller_to_dict(controller: AbstractController, family: str) -> dict[str, Any]:
    """A JSON-ready description of one controller: its family and every field's value."""
    params: dict[str, Any] = {}
    for f in dataclasses.fields(controller):
        value = getattr(controller, f.name)
        if isinstance(value, tuple):
            params[f.name] = list(value)
        else:
            params[f.name] = np.asarray(value).tolist()
    return {"family": family, "params": params}


def controller_from_dict(data: dict[str, Any]) -> AbstractController:
    """Rebuild a controller saved by `controller_to_dict` (checking its values).

    **Raises:** `ValueError` naming an unknown family or a bad parameter.
    """
    family = data.get("family")
    if family not in CONTROLLER_FAMILIES:
        known = ", ".join(map(repr, CONTROLLER_FAMILIES))
        raise ValueError(f"controller family = {family!r}; allowed: {known}")
    cls = CONTROLLER_FAMILIES[family]
    params = dict(data.get("params", {}))
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(params) - set(names))
    if unknown:
        raise ValueError(
            f"{family} controller has unknown parameters {unknown}; allowed: {', '.join(names)}"
        )
    if "amplitudes" in params:
        params["amplitudes"] = tuple(params["amplitudes"])
    return cls(**params)


def _json_number(x: float) -> float | str:
    return float(x) if math.isfinite(x) else ("-inf" if x < 0 else "inf" if x > 0 else "nan")


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def write_history_csv(path: Path, history: History) -> None:
    """One row per evaluation: its number, the search step, its fitness, the best so far."""
    best = history.best_so_far
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["evaluation", "step", "fitness", "best_so_far"])
        for i in range(len(history)):
            w.writerow(
                [i + 1, int(history.step[i]), repr(float(history.fitness[i])), repr(float(best[i]))]
            )


def read_history_csv(path: str | Path) -> History:
    """Read a history written by `write_history_csv`."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    return History(
        np.array([float(r["fitness"]) for r in rows]), np.array([int(r["step"]) for r in rows])
    )


def _run_search(experiment: Experiment, progress: bool) -> tuple[SearchResult, dict[str, float]]:
    """Run the search; also time it: the first two calls compile (the initial set and the
    first step), later steps show the steady throughput."""
    s = experiment.search
    marks: list[tuple[float, int]] = []
    start = time.perf_counter()

    def clock(state, part):
        del state
        marks.append((time.perf_counter(), len(part)))

    if s["algorithm"] == "serial_search":
        result = serial_search(
            experiment.task,
            key=jr.key(experiment.seed),
            seeds=s["runs"],
            climbers=s["climbers"],
            generations=s["generations"],
            reseed_every=s["reseed_every"],
            enrich=s["enrich"],
            progress=progress,
            # One History per run: the step's evaluations are all of theirs together.
            callback=lambda state, parts: clock(state, range(sum(len(p) for p in parts))),
        )
    else:
        result = parallel_hill_climb(
            experiment.task,
            key=jr.key(experiment.seed),
            evaluations=s["evaluations"],
            size=s["size"],
            batch=s["batch"],
            progress=progress,
            callback=clock,
        )
    end = time.perf_counter()
    timing = {
        "search_time_s": end - start,
        "first_steps_s": marks[min(1, len(marks) - 1)][0] - start,
    }
    if len(marks) > 2:
        steady = sum(n for _, n in marks[2:])
        timing["steady_evals_per_s"] = steady / (marks[-1][0] - marks[1][0])
    return result, timing


def run_experiment(
    experiment: Experiment,
    *,
    directory: str | Path | None = None,
    progress: bool = True,
    animation: bool | None = None,
) -> Path:
    """Run an experiment's search and write its results folder; return the folder.

    The folder `<directory>/<name>-<timestamp>/` holds `config.toml` (resolved),
    `best_controller.json`, `history.csv` (one row per evaluation), `learning_plot.png`,
    `motion.gif` (unless `animation` is off) and `summary.json`. It is assembled in a hidden
    temporary folder and renamed into place only when complete, so a failed or interrupted
    run leaves nothing half-written behind.
    """
    from ..viz import animate, learning_plot

    out_root = Path(directory if directory is not None else experiment.output["directory"])
    want_animation = experiment.output["animation"] if animation is None else animation
    out_root.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    final = out_root / f"{experiment.name}-{stamp}"
    n = 1
    while final.exists():
        n += 1
        final = out_root / f"{experiment.name}-{stamp}-{n}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=out_root))
    try:
        started = time.perf_counter()
        result, timing = _run_search(experiment, progress)
        search_seconds = timing["search_time_s"]
        task = experiment.task
        best = result.best
        runs = getattr(result, "runs", (result,))
        evaluations = sum(len(r.history) for r in runs)
        # Every run's best replayed with the search's own settings, so its terms are what the
        # search scored; the overall best is the best run's (serial search's `runs`).
        replays = [task.simulate(r.best) for r in runs]
        trajectory = replays[int(np.argmax([r.best_fitness for r in runs]))]
        values = {k: float(v) for k, v in task.objective.values(trajectory).items()}
        check = run_check(experiment, trajectory)
        replay_fitness = fitness_of(task, best)
        per_run = None
        if len(runs) > 1:
            # Independent runs: each one's best, replayed and checked.
            per_run = []
            for i, (r, replay) in enumerate(zip(runs, replays, strict=True)):
                verdict = run_check(experiment, replay)
                per_run.append(
                    {
                        "run": i,
                        "best_fitness": _json_number(r.best_fitness),
                        "terms": {
                            k: _json_number(float(v))
                            for k, v in task.objective.values(replay).items()
                        },
                        "check": None if verdict is None else verdict.to_dict(),
                    }
                )

        (tmp / "config.toml").write_text(tomli_w.dumps(experiment.config))
        saved = controller_to_dict(best, task.space.family)
        saved.update(
            fitness=_json_number(result.best_fitness),
            format=FORMAT_VERSION,
            config="config.toml",
        )
        _write_json(tmp / "best_controller.json", saved)
        write_history_csv(tmp / "history.csv", result.history)
        fig = learning_plot(result.history, title=f"{experiment.name}: learning plot")
        fig.savefig(tmp / "learning_plot.png", dpi=120)
        if want_animation:
            animate(trajectory, task.body, fps=experiment.output["fps"]).save(tmp / "motion.gif")
        summary = {
            "name": experiment.name,
            "seed": experiment.seed,
            "best_fitness": _json_number(result.best_fitness),
            "replay_fitness": _json_number(replay_fitness),
            "terms": {k: _json_number(v) for k, v in values.items()},
            "evaluations": evaluations,
            "nonfinite_evaluations": sum(r.history.num_nonfinite for r in runs),
            "wall_time_s": round(time.perf_counter() - started, 3),
            "search_time_s": round(search_seconds, 3),
            "evals_per_s": round(evaluations / search_seconds, 1),
            "compile_and_first_steps_s": round(timing["first_steps_s"], 3),
            "steady_evals_per_s": round(timing.get("steady_evals_per_s", float("nan")), 1)
            if "steady_evals_per_s" in timing
            else None,
            "check": None if check is None else check.to_dict(),
            "runs": per_run,
            "devices": len(jax.devices()),
            "float": str(jnp.result_type(float)),
            "jax": jax.__version__,
        }
        _write_json(tmp / "summary.json", summary)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def fitness_of(task, controller) -> float:
    """A controller's fitness computed exactly as the search computed it: by `task.evaluate`
    (the objective compiled together with the simulation; summing a term's samples in another
    compiled function may round its last bit differently)."""
    one = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], controller)
    return float(task.evaluate(one)[0])


def run_check(experiment: Experiment, trajectory):
    """The experiment's motion check on a trajectory of its task (None if it has none)."""
    if experiment.check is None:
        return None
    import inspect

    from .._checks import CHECKS

    check = CHECKS[experiment.check]
    task = experiment.task
    available = {"body_length": float(task.body.body_length)}
    if hasattr(task.space, "t_per"):
        available["period"] = task.space.t_per
    if getattr(task.body, "feet", ()):
        available["feet"] = task.body.feet
    wanted = inspect.signature(check).parameters
    return check(trajectory, **{k: v for k, v in available.items() if k in wanted})


def load_result(folder: str | Path) -> tuple[Experiment, AbstractController]:
    """Load a results folder: its experiment (from `config.toml`) and best controller.

    **Raises:** `FileNotFoundError` if the folder lacks those files; `ConfigError` or
    `ValueError` if they do not check out.
    """
    import tomllib

    folder = Path(folder)
    with (folder / "config.toml").open("rb") as f:
        raw = tomllib.load(f)
    try:
        experiment = parse_config(raw, name=raw.get("name", folder.name))
    except ConfigError as e:
        raise ConfigError(f"{folder / 'config.toml'}: {e}") from None
    data = json.loads((folder / "best_controller.json").read_text())
    return experiment, controller_from_dict(data)
