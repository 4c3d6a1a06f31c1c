"""Running an experiment and writing (and reading back) its results folder."""

import csv
import dataclasses
import datetime as _dt
import json
import math
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import tomli_w

from .._body.base import BodyState
from .._control.base import AbstractController
from .._control.regimes import Regimes
from .._control.sense_bsr import SenseBSR
from .._control.sequence import Sequence as Composite
from .._control.spring_net import SpringNet
from .._control.time_bsr import TimeBSR
from .._search.history import History
from .._search.protocol import SEARCHERS, SearchResult, drive, fittest
from .._sim.trajectory import Trajectory, concatenate_trajectories
from .._task import Task
from .checkpoint import SUFFIX, Progress, find_checkpoint, load_checkpoint, save_checkpoint
from .config import (
    FLOAT32_MAX,
    SEQUENCE_CHECKS,
    ConfigError,
    Experiment,
    make_searcher,
    parse_config,
    read_toml,
    search_plan,
)

CONTROLLER_FAMILIES: dict[str, type[AbstractController]] = {
    "regimes": Regimes,
    "time_bsr": TimeBSR,
    "sense_bsr": SenseBSR,
    "spring_net": SpringNet,
    "sequence": Composite,
}
FORMAT_VERSION = 1


def _family_of(controller: AbstractController) -> str:
    for name, cls in CONTROLLER_FAMILIES.items():
        if type(controller) is cls:
            return name
    known = ", ".join(cls.__name__ for cls in CONTROLLER_FAMILIES.values())
    raise ValueError(f"cannot save a {type(controller).__name__} controller; savable: {known}")


def controller_to_dict(controller: AbstractController, family: str | None = None) -> dict[str, Any]:
    """A JSON-ready description of one controller: its family (by default, the one its
    class is saved as) and every field's value. A `Sequence` holds its controllers' own
    descriptions, in order, and its transitions (its control period is the simulation's,
    set when it runs)."""
    family = _family_of(controller) if family is None else family
    if isinstance(controller, Composite):
        return {
            "family": family,
            "params": {
                "controllers": [controller_to_dict(c) for c in controller.controllers],
                "transitions": np.asarray(controller.transitions).tolist(),
            },
        }
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

    Every value is checked before anything compiles: a number must be finite and within
    float32 (the simulations' precision), a list of them rectangular, and the family's own
    constructor checks the rest (ranges, shapes).

    **Raises:** `ValueError` naming an unknown family, a missing, unknown or bad parameter.
    """
    if not isinstance(data, dict):
        raise ValueError(
            f"a saved controller must be a table {{'family': ..., 'params': ...}}; got "
            f"{type(data).__name__}"
        )
    family = data.get("family")
    if not isinstance(family, str) or family not in CONTROLLER_FAMILIES:
        known = ", ".join(map(repr, CONTROLLER_FAMILIES))
        raise ValueError(f"controller family = {family!r}; allowed: {known}")
    cls = CONTROLLER_FAMILIES[family]
    params = data.get("params", {})
    if not isinstance(params, dict):
        raise ValueError(f"{family} controller's params = {params!r}; allowed: a table")
    params = dict(params)
    names = (
        ["controllers", "transitions"]
        if cls is Composite
        else [f.name for f in dataclasses.fields(cls)]
    )
    unknown = sorted(set(params) - set(names))
    if unknown:
        raise ValueError(
            f"{family} controller has unknown parameters {unknown}; allowed: {', '.join(names)}"
        )
    if cls is Composite:
        children = params.get("controllers")
        if not isinstance(children, list) or not all(isinstance(c, dict) for c in children):
            raise ValueError(
                f"sequence controller's controllers = {children!r}; allowed: a list of saved "
                "controllers ({'family': ..., 'params': ...})"
            )
        return Composite([controller_from_dict(c) for c in children], params.get("transitions"))
    missing = [
        f.name
        for f in dataclasses.fields(cls)
        if f.name not in params
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    for name, value in params.items():
        _check_saved_value(family, name, value)
    if "amplitudes" in params:
        params["amplitudes"] = tuple(params["amplitudes"])
    try:
        return cls(**params)
    except (TypeError, ValueError, OverflowError, IndexError) as e:
        more = f" (missing: {', '.join(missing)})" if missing else ""
        raise ValueError(f"{family} controller: {e}{more}") from None


def _check_saved_value(family: str, name: str, value: Any) -> None:
    """A saved parameter: a number, or a rectangular nest of lists of numbers, each finite
    and within float32."""
    bad = ValueError(
        f"{family} controller's {name} = {_brief(value)}; allowed: finite numbers (or lists "
        f"of them, rectangular) of magnitude at most {FLOAT32_MAX:.4g}"
    )
    if value is None or isinstance(value, bool):
        return  # a setting (e.g. no mirror), checked by the family's constructor
    if isinstance(value, str):
        raise bad
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise bad from None
    if not np.all(np.isfinite(array)) or np.any(np.abs(array) > FLOAT32_MAX):
        raise bad


def _brief(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


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


class Interrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or SIGTERM; `checkpoint` is where its search was saved (None
    if it had not started searching)."""

    def __init__(self, checkpoint: Path | None):
        super().__init__()
        self.checkpoint = checkpoint


class _Checkpoints:
    """The CLI's side of checkpointing: the driver's callback records each step of the
    search in progress (`Progress`), and the searches so far (a multi-stage run's finished
    stages, then the one in progress) are saved to `path` every `every` seconds and on
    demand (an interrupt). `resumed`: the `(state, history)` of each search a checkpoint
    holds; `begin` hands the next one to its search. `write(path, experiment, searches)`
    writes the file (`save_checkpoint`; a compose run's transition search passes its own
    writer and its `ComposeConfig` as `experiment`)."""

    def __init__(
        self,
        path: Path,
        experiment: Experiment,
        every: float | None,
        resumed: list | None = None,
        stop: Callable[[], bool] | None = None,
        write: Callable[[Path, Any, list], None] = save_checkpoint,
    ):
        self.path, self.experiment, self.every, self.stop = path, experiment, every, stop
        self.write = write
        self.pending = list(resumed or [])
        self.done: list[tuple[Any, Any]] = []
        self.progress: Progress | None = None
        self.resumed = None
        self.last = time.monotonic()
        self.saved = False

    def begin(self, seeds: int | None = None) -> None:
        """Start recording the next search (`seeds`: its number of per-run histories, None
        for one; `_seeds(experiment)`); `resumed` is then its state and history from the
        checkpoint, if it holds them."""
        if self.progress is not None and self.progress.latest is not None:
            state, count = self.progress.latest
            self.done.append((state, self.progress.history(count)))
        self.progress = Progress(seeds=seeds)
        self.resumed = self.pending.pop(0) if self.pending else None
        if self.resumed is not None:
            self.progress.record(*self.resumed)

    def __call__(self, state, part) -> None:
        assert self.progress is not None
        self.progress.record(state, part)
        if self.stop is not None and self.stop():
            raise KeyboardInterrupt  # between two steps: `run_experiment` saves and stops
        if self.every is not None and time.monotonic() - self.last >= self.every:
            self.save()

    def save(self) -> None:
        searches = list(self.done)
        if self.progress is not None and self.progress.latest is not None:
            state, count = self.progress.latest
            searches.append((state, self.progress.history(count)))
        if not searches:
            return
        self.write(self.path, self.experiment, searches)
        self.last = time.monotonic()
        self.saved = True


def _seeds(search: Experiment) -> int | None:
    """How many histories a single search's checkpoint records: one per run for a per-run
    searcher (serial search), else None (one)."""
    return search.search["runs"] if SEARCHERS[search.search["algorithm"]].per_run else None


def _run_search(
    experiment: Experiment, progress: bool, checkpoints: "_Checkpoints | None" = None
) -> tuple[SearchResult, dict[str, float]]:
    """Run the search (continuing `checkpoints.resumed`, a checkpoint's state and history,
    if any, and recording every step in `checkpoints`); also time it: the first two calls
    compile (the initial set and the first step), later steps show the steady
    throughput."""
    s = experiment.search
    marks: list[tuple[float, int]] = []
    start = time.perf_counter()
    resumed = None if checkpoints is None else checkpoints.resumed
    carry_on = {} if resumed is None else {"state": resumed[0], "history": resumed[1]}

    def clock(state, part):
        # One History, or one per run (serial search): the step's evaluations are all of theirs.
        parts = part if isinstance(part, tuple) else (part,)
        marks.append((time.perf_counter(), sum(len(p) for p in parts)))
        if checkpoints is not None:
            checkpoints(state, part)

    searcher, steps, last = make_searcher(s)
    result = drive(
        searcher,
        experiment.task,
        key=jr.key(experiment.seed),
        steps=steps,
        last=last,
        progress=progress,
        callback=clock,
        **carry_on,
    )
    end = time.perf_counter()
    timing = {
        "search_time_s": end - start,
        "first_steps_s": (marks[min(1, len(marks) - 1)][0] if marks else end) - start,
    }
    if len(marks) > 2:
        steady = sum(n for _, n in marks[2:])
        timing["steady_evals_per_s"] = steady / (marks[-1][0] - marks[1][0])
    candidates = s.get("accurate_candidates", 0)
    if candidates:
        started = time.perf_counter()
        check = lambda trajectory: run_check(experiment, trajectory)
        result, timing["accurate"] = pick_accurate(experiment.task, result, candidates, check)
        timing["accurate"]["seconds"] = round(time.perf_counter() - started, 3)
    return result, timing


ACCURATE = {"solver": "dopri5", "rtol": 1e-8, "atol": 1e-10}
"""The accurate replay `[search] accurate_candidates` scores by: float64, Dopri5, tight
tolerances (`benchmarks/accurate_replay.py` measures found motions the same way)."""


def _float64(tree):
    return jax.tree_util.tree_map(
        lambda a: (
            jnp.asarray(a, jnp.float64)
            if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating)
            else a
        ),
        tree,
    )


def accurate_fitness(task: Task, controller: AbstractController) -> float:
    """The fitness of one controller's motion replayed accurately (`ACCURATE`: float64,
    Dopri5 at rtol 1e-8, atol 1e-10), from the task's own start; `-inf` if it blows up."""
    with jax.enable_x64(True):
        return _accurate(_float64(task), controller)[0]


def accurate_check(experiment: Experiment, controller: AbstractController):
    """The experiment's check (`run_check`) on a controller's motion replayed accurately
    (`ACCURATE`), from the task's own start."""
    with jax.enable_x64(True):
        return run_check(experiment, _accurate_replay(_float64(experiment.task), controller))


def _accurate_replay(task64: Task, controller: AbstractController):
    """A controller's motion replayed accurately on a task already in float64 (inside
    `jax.enable_x64`)."""
    return task64.simulate(_float64(controller), **ACCURATE)


def _accurate(task64: Task, controller: AbstractController):
    """`accurate_fitness` of a task already in float64 (inside `jax.enable_x64`), and the
    trajectory it scored."""
    trajectory = _accurate_replay(task64, controller)
    fitness = float(task64.objective(trajectory))
    ok = math.isfinite(fitness) and bool(trajectory.finite)
    return (fitness if ok else -math.inf), trajectory


def pick_accurate(
    task: Task, result: SearchResult, k: int, check=None
) -> tuple[SearchResult, dict]:
    """Choose the best controller among the `k` fittest of the search's final set
    (`jaxmotion.fittest`: hill climbing's set, serial search's archive of the fittest it held,
    evolution's population; evosax's best alone) by their accurate replay
    (`accurate_fitness`): the one whose lower fitness of the two (the search's, the
    accurate replay's) is highest, so that the motion an animator re-simulates with an
    accurate integrator is the motion the search found (a fixed step can reward an artefact
    of itself). Returns the result with that controller as its best (its fitness the
    search's) and what was measured; with `check` (a function of a trajectory returning a
    `CheckResult` or `None`), also the check of the chosen motion's accurate replay
    (`check`, as `accurate_check` gives it, without replaying it again)."""
    candidates, fitness = fittest(result, k)
    if not len(fitness):
        return result, {"candidates": 0}
    rows, chosen, kept = [], None, None
    with jax.enable_x64(True):
        task64 = _float64(task)  # once: the conversion is not free
        for i in range(len(fitness)):
            value, trajectory = _accurate(task64, _row(candidates, i))
            rows.append((i, float(fitness[i]), value))
            if chosen is None or min(rows[-1][1:]) > min(chosen[1:]):
                chosen, kept = rows[-1], trajectory  # ties: the first, fittest by the search
        verdict = None if check is None else check(kept)
    measured = {
        "candidates": len(rows),
        "chosen_rank": chosen[0],
        "fitness": chosen[1],
        "accurate_fitness": _json_number(chosen[2]),
        "search_best_fitness": _json_number(result.best_fitness),
        "search_best_accurate_fitness": _json_number(rows[0][2]),
    }
    if verdict is not None:
        measured["check"] = verdict.to_dict()
    best = _row(candidates, chosen[0])
    return dataclasses.replace(result, best=best, best_fitness=chosen[1]), measured


def _row(stacked, i: int):
    return jax.tree_util.tree_map(lambda a: a[i], stacked)


_PARTIAL = re.compile(r"^\..+\.pid(\d+)\.[^.]+\.partial$")
_HALF_CHECKPOINT = re.compile(r"^\..+\.checkpoint\.(\d+)\.tmp$")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def clean_partial_folders(out_root: Path) -> list[Path]:
    """Remove the temporary folders (`.<name>-<time>.pid<PID>.<random>.partial/`) and
    half-written checkpoints (`.<name>-<time>.checkpoint.<PID>.tmp`) that runs killed before
    they could clean up (SIGKILL, a crash inside XLA) left in `out_root`: those whose
    process is gone, and folders of the older naming without a process id. A running
    process's are kept. Returns the paths removed."""
    removed = []
    if not out_root.is_dir():
        return removed
    for path in out_root.iterdir():
        half = _HALF_CHECKPOINT.match(path.name)
        if half is not None:
            # A checkpoint being written when its process was killed (`save_checkpoint`).
            if not _alive(int(half.group(1))):
                path.unlink(missing_ok=True)
                removed.append(path)
            continue
        if not (path.name.startswith(".") and path.name.endswith(".partial")):
            continue
        match = _PARTIAL.match(path.name)
        if match is not None and _alive(int(match.group(1))):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def new_folder(out_root: Path, name: str) -> tuple[Path, Path]:
    """A results folder's final path `<out_root>/<name>-<timestamp>[-n]/` (not yet there)
    and the hidden temporary folder beside it to assemble it in (rename it into place when
    complete, remove it otherwise: nothing half-written is left behind). The temporary
    folder's name holds this process's id, so that a later run removes it if this process
    is killed before it can (`clean_partial_folders`, called here first).

    **Raises:** `ConfigError` if `out_root` cannot be made a folder."""
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(
            f"results directory {str(out_root)!r} cannot be created ({e.strerror or e}); "
            "allowed: a folder you can write to"
        ) from None
    clean_partial_folders(out_root)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    final = out_root / f"{name}-{stamp}"
    n = 1
    while final.exists():
        n += 1
        final = out_root / f"{name}-{stamp}-{n}"
    try:
        tmp = Path(
            tempfile.mkdtemp(
                prefix=f".{final.name}.pid{os.getpid()}.", suffix=".partial", dir=out_root
            )
        )
    except OSError as e:
        raise ConfigError(
            f"results directory {str(out_root)!r} is not writable ({e.strerror or e})"
        ) from None
    return final, tmp


def run_experiment(
    experiment: Experiment,
    *,
    directory: str | Path | None = None,
    progress: bool = True,
    animation: bool | None = None,
    report: Callable[[str], None] | None = None,
    checkpoint_every: float | None = None,
    resume: str | Path | None = None,
    stop: Callable[[], bool] | None = None,
) -> Path:
    """Run an experiment's search and write its results folder; return the folder.

    The folder `<directory>/<name>-<timestamp>/` holds `config.toml` (resolved),
    `best_controller.json`, `history.csv` (one row per evaluation), `learning_plot.png`,
    `motion.gif` (unless `animation` is off) and `summary.json`. It is assembled in a hidden
    temporary folder and renamed into place only when complete, so a failed or interrupted
    run leaves nothing half-written behind.

    A multi-stage experiment (`Experiment.stages`) runs one search per stage (its `runs`
    independent runs batched, the best run's motion kept), in order, stage k starting
    from the final body state of stage k-1's best motion (`start_where`; its controller
    starts from its own initial state at its own time 0), with the stage's own seed (the
    experiment's seed + i for the i-th stage from 0). The folder then holds `config.toml`
    (resolved), one subfolder per stage (`stage-1-<name>/`, ...) with what a
    single search's folder holds but the config, `summary.json` (every stage's best
    fitness, terms, check and wall time, and the check of the whole sequence) and
    `motion.gif` of the whole sequence (`concatenate_trajectories`). `report` is called with
    a short line as each stage starts and ends (the CLI prints them).

    **Checkpoints**: with `checkpoint_every` (seconds), the search's whole state and history
    so far (a multi-stage run: every stage's so far) are saved to
    `<directory>/<name>-<time>.checkpoint` that often and when the run is interrupted
    (`KeyboardInterrupt`: Ctrl-C, or SIGTERM as the CLI maps it), which then raises
    `Interrupted` naming the file. `resume` (that file, or the directory holding it)
    continues such a run: the result is bitwise the uninterrupted run's (best controllers,
    fitness, histories), and the checkpoint is removed once the folder is complete.
    `stop`, asked after every step of a checkpointed search, stops it there as an
    interrupt does (the CLI's signal handlers set it). See `jaxmotion._cli.checkpoint` for
    the format.

    **Raises:** `ConfigError` for a checkpoint that is truncated, of another config or
    version; `Interrupted`.
    """
    out_root = Path(directory if directory is not None else experiment.output["directory"])
    want_animation = experiment.output["animation"] if animation is None else animation
    resumed, source = None, None
    if resume is not None:
        source = find_checkpoint(Path(resume), experiment)
        resumed = load_checkpoint(source, experiment)
    final, tmp = new_folder(out_root, experiment.name)
    checkpoints = None
    if checkpoint_every is not None or resumed is not None:
        path = source if source is not None else out_root / f"{final.name}{SUFFIX}"
        checkpoints = _Checkpoints(path, experiment, checkpoint_every, resumed, stop)
    try:
        if experiment.stages:
            _run_stages(experiment, tmp, progress, want_animation, report, checkpoints)
        else:
            started = time.perf_counter()
            if checkpoints is not None:
                checkpoints.begin(_seeds(experiment))
            _search_and_write(experiment, tmp, progress, want_animation, started, checkpoints)
            (tmp / "config.toml").write_text(tomli_w.dumps(experiment.config))
        os.replace(tmp, final)
    except KeyboardInterrupt:
        shutil.rmtree(tmp, ignore_errors=True)
        if checkpoints is None:
            raise
        checkpoints.save()
        raise Interrupted(checkpoints.path if checkpoints.saved else None) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if checkpoints is not None:
        checkpoints.path.unlink(missing_ok=True)
    return final


def _search_and_write(
    experiment: Experiment,
    folder: Path,
    progress: bool,
    want_animation: bool,
    started: float,
    checkpoints: _Checkpoints | None = None,
    *,
    stage: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], Trajectory]:
    """Search one (single-stage) experiment and write what its results folder holds but the
    config: `best_controller.json`, `history.csv`, `learning_plot.png`, `motion.gif` and
    `summary.json` (`stage`: a stage's place in its sequence, added to both JSON files).
    Returns the summary and the best motion."""
    from ..viz import animate, learning_curves, learning_plot

    result, timing = _run_search(experiment, progress, checkpoints)
    search_seconds = timing["search_time_s"]
    task = experiment.task
    best = result.best
    runs = getattr(result, "runs", (result,))
    evaluations = sum(len(r.history) for r in runs)
    # Every run's best replayed with the search's own settings, so its terms are what the
    # search scored; the overall best is the best run's (serial search's `runs`).
    exports = experiment.output.get("export") or []
    replays = [task.simulate(r.best, positions=bool(exports)) for r in runs]
    trajectory = replays[int(np.argmax([r.best_fitness for r in runs]))]
    values = {k: float(v) for k, v in task.objective.values(trajectory).items()}
    check = run_check(experiment, trajectory)
    accurate = timing.get("accurate")
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
                        k: _json_number(float(v)) for k, v in task.objective.values(replay).items()
                    },
                    "check": None if verdict is None else verdict.to_dict(),
                }
            )

    saved = controller_to_dict(best, task.space.family)
    saved.update(
        fitness=_json_number(result.best_fitness),
        format=FORMAT_VERSION,
        config="config.toml" if stage is None else "../config.toml",
    )
    if stage is not None:
        saved["stage"] = stage["stage"]
    _write_json(folder / "best_controller.json", saved)
    write_history_csv(folder / "history.csv", result.history)
    fig = learning_plot(result.history, title=f"{experiment.name}: learning plot")
    fig.savefig(folder / "learning_plot.png", dpi=120)
    if len(runs) > 1:
        # Independent runs: each one's history and their learning curves (Figure 8).
        for i, r in enumerate(runs):
            write_history_csv(folder / f"history-run-{i}.csv", r.history)
        title = f"{experiment.name}: {len(runs)} independent runs"
        fig = learning_curves([r.history for r in runs], title=title)
        fig.savefig(folder / "learning_curves.png", dpi=120)
    if want_animation:
        animate(trajectory, task.body, fps=experiment.output["fps"]).save(folder / "motion.gif")
    write_exports(exports, trajectory, task.body, folder)
    summary = {
        "name": experiment.name,
        "seed": experiment.seed,
        **(stage or {}),
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
        "accurate": accurate,
        "devices": len(jax.devices()),
        "float": str(jnp.result_type(float)),
        "jax": jax.__version__,
    }
    _write_json(folder / "summary.json", summary)
    return summary, trajectory


def stage_folder(number: int, name: str) -> str:
    """The subfolder of a multi-stage results folder holding stage `number` (from 1)."""
    return f"stage-{number}-{name}"


def start_where(stage: Experiment, previous: Trajectory | BodyState | None) -> Experiment:
    """`stage` with its task starting from the final body state of `previous` (or from a
    given body state; None: from the body's rest pose, as configured). Only the body's
    state carries over: the stage's controllers start from their own initial state at their
    own time 0, so the stage's first saved sample is `previous`'s last one."""
    if previous is None:
        return stage
    if isinstance(previous, Trajectory):
        if previous.final is None:
            raise ValueError(
                "start_where needs a trajectory with its final state (Trajectory.final)"
            )
        previous = previous.final.body
    # A copy of the values alone (bitwise): a state that comes out of a compiled call stays
    # committed to its device, and a task holding it would compile its simulations again.
    previous = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)), previous)
    # Every other setting of the task is kept (robustness, second_dt, ...).
    started = dataclasses.replace(stage.task, initial_state=previous)
    return dataclasses.replace(stage, task=started)


def _chained(stage: Experiment, before: Sequence[Trajectory]) -> Experiment:
    """`stage` starting where the last of the stages `before` it ended, or (the first
    stage) from the rest pose, given explicitly: every stage's task then has the same
    layout, so stages of the same objective share their compiled simulations."""
    return start_where(stage, before[-1] if before else stage.task.body.initial_state())


def _run_stages(
    experiment: Experiment,
    folder: Path,
    progress: bool,
    want_animation: bool,
    report: Callable[[str], None] | None,
    checkpoints: _Checkpoints | None = None,
) -> None:
    """A multi-stage experiment's searches, one after another (see `run_experiment`; a
    stage that a checkpoint holds as finished is continued from its last state, so its
    search makes no step and its results are written as they were)."""
    from ..viz import animate

    say = report or (lambda line: None)
    started = time.perf_counter()
    count = len(experiment.stages)
    trajectories: list[Trajectory] = []
    summaries: list[dict[str, Any]] = []
    previous_name = None
    for number, stage in enumerate(experiment.stages, start=1):
        stage = _chained(stage, trajectories)
        label = f"stage {number}/{count} {stage.name}"
        start = "" if previous_name is None else f", starting where {previous_name} ended"
        say(f"{label}: {search_plan(stage.search)}, seed {stage.seed}{start}")
        sub = folder / stage_folder(number, stage.name)
        sub.mkdir()
        if checkpoints is not None:
            checkpoints.begin(_seeds(stage))
        summary, trajectory = _search_and_write(
            stage,
            sub,
            progress,
            want_animation,
            time.perf_counter(),
            checkpoints,
            stage={"stage": number, "starts_after": previous_name},
        )
        check = summary["check"]
        verdict = (
            ""
            if check is None
            else f"; {check['name']} check " + ("passed" if check["passed"] else "failed")
        )
        terms = ", ".join(f"{k} {_short(v)}" for k, v in summary["terms"].items())
        say(
            f"{label}: best fitness {_short(summary['best_fitness'])} ({terms}) after "
            f"{summary['evaluations']} evaluations in {summary['wall_time_s']:.1f} s{verdict}"
            + (
                f"; {summary['nonfinite_evaluations']} blew up (non-finite)"
                if summary["nonfinite_evaluations"]
                else ""
            )
        )
        trajectories.append(trajectory)
        previous_name = stage.name
        summaries.append(
            {
                "stage": number,
                "name": stage.name,
                "folder": sub.name,
                "seed": stage.seed,
                **{
                    k: summary[k]
                    for k in (
                        "best_fitness",
                        "replay_fitness",
                        "terms",
                        "check",
                        "evaluations",
                        "nonfinite_evaluations",
                        "wall_time_s",
                        "search_time_s",
                    )
                },
            }
        )
    check = run_sequence_check(experiment, trajectories)
    exports = experiment.output.get("export") or []
    if exports:
        write_exports(exports, concatenate_trajectories(trajectories), experiment.task.body, folder)
    if want_animation:
        whole = concatenate_trajectories(trajectories)
        animate(whole, experiment.task.body, fps=experiment.output["fps"]).save(
            folder / "motion.gif"
        )
    (folder / "config.toml").write_text(tomli_w.dumps(experiment.config))
    _write_json(
        folder / "summary.json",
        {
            "name": experiment.name,
            "seed": experiment.seed,
            "stages": summaries,
            "check": None if check is None else check.to_dict(),
            "evaluations": sum(s["evaluations"] for s in summaries),
            "duration_s": float(sum(s.task.duration for s in experiment.stages)),
            "wall_time_s": round(time.perf_counter() - started, 3),
            "devices": len(jax.devices()),
            "float": str(jnp.result_type(float)),
            "jax": jax.__version__,
        },
    )


def _short(value: float | str) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def replay_stages(
    experiment: Experiment,
    controllers: Sequence[AbstractController],
    *,
    solver: str = "symplectic",
    positions: bool = False,
) -> list[Trajectory]:
    """Re-simulate a multi-stage experiment's stages with these controllers, one per stage,
    each starting where the previous one's motion ended (`start_where`). With the search's
    own solver every stage replays bitwise as the run computed it. `positions`: keep each
    trajectory's positions (`Trajectory.positions`, for `jaxmotion.export`).

    **Raises:** `ValueError` if the number of controllers is not the number of stages.
    """
    if len(controllers) != len(experiment.stages):
        raise ValueError(
            f"replay_stages needs one controller per stage ({len(experiment.stages)}); got "
            f"{len(controllers)}"
        )
    trajectories: list[Trajectory] = []
    for stage, controller in zip(experiment.stages, controllers, strict=True):
        stage = _chained(stage, trajectories)
        trajectories.append(stage.task.simulate(controller, solver=solver, positions=positions))
    return trajectories


EXPORT_FILES = {
    "bvh": "motion.bvh",
    "usd": "motion.usd",
}  # the file each export format writes in a results folder


def write_exports(formats: Sequence[str], trajectory: Trajectory, body, folder: Path) -> None:
    """Write the motion in each of `formats` (`[output] export`) into a results folder
    (`EXPORT_FILES` names the files). The trajectory must hold its positions."""
    from .. import export

    for name in formats:
        getattr(export, name)(trajectory, body, folder / EXPORT_FILES[name])


def fitness_of(task, controller) -> float:
    """A controller's fitness computed exactly as the search computed it: by `task.evaluate`
    (the objective compiled together with the simulation; summing a term's samples in another
    compiled function may round its last bit differently). For a task with robustness, the
    fitness from the task's own start, unperturbed (the search scored random starts); for a
    task with `second_dt`, the lower of the fitnesses at its two steps, as the search scored."""
    one = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], controller)
    if task.robustness is not None:
        task = dataclasses.replace(task, robustness=None)
    return float(task.evaluate(one)[0])


def _check_arguments(experiment: Experiment, check) -> dict[str, Any]:
    """What a check function takes of the experiment's task: `body_length`, `period`,
    `feet`."""
    import inspect

    task = experiment.task
    available = {"body_length": float(task.body.body_length)}
    if hasattr(task.space, "t_per"):
        available["period"] = task.space.t_per
    if getattr(task.body, "feet", ()):
        available["feet"] = task.body.feet
    wanted = inspect.signature(check).parameters
    return {k: v for k, v in available.items() if k in wanted}


def run_check(experiment: Experiment, trajectory):
    """The experiment's motion check on a trajectory of its task (None if it has none)."""
    if experiment.check is None:
        return None
    from .._checks import CHECKS

    check = CHECKS[experiment.check]
    return check(trajectory, **_check_arguments(experiment, check))


def run_sequence_check(experiment: Experiment, trajectories: Sequence[Trajectory]):
    """A multi-stage experiment's check of the whole sequence (None if it has none): a
    sequence check (`walk_turn_walk`) on the stages' trajectories in order, any other check
    on them joined end to end (`concatenate_trajectories`)."""
    if experiment.check is None:
        return None
    if experiment.check in SEQUENCE_CHECKS:
        from .._checks import CHECKS

        check = CHECKS[experiment.check]
        return check(list(trajectories), **_check_arguments(experiment, check))
    return run_check(experiment, concatenate_trajectories(trajectories))


def results_config(folder: str | Path) -> dict[str, Any]:
    """The TOML table of a results folder's `config.toml`.

    **Raises:** `ConfigError` if `folder` is not a folder or holds no readable
    `config.toml` (it is then not a results folder)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: not a results folder (no such folder)")
    if not (folder / "config.toml").is_file():
        raise ConfigError(
            f"{folder}: not a results folder (no config.toml; a results folder holds "
            "config.toml, best_controller.json, history.csv and summary.json)"
        )
    return read_toml(folder / "config.toml")


def _read_config(folder: Path) -> Experiment:
    raw = results_config(folder)
    name = raw.get("name")
    try:
        return parse_config(raw, name=name if isinstance(name, str) else folder.name)
    except ConfigError as e:
        raise ConfigError(f"{folder / 'config.toml'}: {e}") from None


def read_controller(path: Path, task: Task | None = None) -> AbstractController:
    """A controller saved as JSON (`controller_to_dict`), checked value by value and, given
    the task it was found for, against the shapes of that task's controllers.

    **Raises:** `ConfigError` naming the file for a missing file, bad JSON or a bad
    controller."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(
            f"{path}: no such file (not a results folder of a complete run)"
        ) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid JSON: {e}") from None
    try:
        controller = controller_from_dict(data)
    except ValueError as e:
        raise ConfigError(f"{path}: {e}") from None
    if task is not None and not isinstance(controller, Composite):
        expected = jax.eval_shape(lambda: task.space.sample(key=jr.key(0)))
        shapes = lambda tree: [jnp.shape(a) for a in jax.tree_util.tree_leaves(tree)]
        if type(controller) is not type(expected) or shapes(controller) != shapes(expected):
            raise ConfigError(
                f"{path}: the controller does not fit its config's [controller] and [body]: "
                f"{type(controller).__name__} with parameter shapes {shapes(controller)}; "
                f"allowed: {type(expected).__name__} with {shapes(expected)}"
            )
    return controller


def load_result(folder: str | Path) -> tuple[Experiment, AbstractController]:
    """Load a results folder: its experiment (from `config.toml`) and best controller.

    **Raises:** `ConfigError` (a `ValueError`) if the folder lacks those files, if they do
    not check out (the controller is checked value by value and against the config's
    shapes), or if the folder holds a multi-stage run (load that with `load_stages`).
    """
    folder = Path(folder)
    experiment = _read_config(folder)
    if experiment.stages:
        raise ConfigError(
            f"{folder} holds a multi-stage run ({len(experiment.stages)} stages); load it "
            "with load_stages"
        )
    return experiment, read_controller(folder / "best_controller.json", experiment.task)


def load_stages(folder: str | Path) -> tuple[Experiment, tuple[AbstractController, ...]]:
    """Load a multi-stage results folder: its experiment (from `config.toml`) and each
    stage's best controller, in order (replay them with `replay_stages`).

    **Raises:** `ConfigError` (a `ValueError`) if the folder lacks those files, if they do
    not check out, or if the folder holds a single search (load that with `load_result`).
    """
    folder = Path(folder)
    experiment = _read_config(folder)
    if not experiment.stages:
        raise ConfigError(f"{folder} holds a single search, no stages; load it with load_result")
    controllers = []
    for number, stage in enumerate(experiment.stages, start=1):
        path = folder / stage_folder(number, stage.name) / "best_controller.json"
        controllers.append(read_controller(path, stage.task))
    return experiment, tuple(controllers)
