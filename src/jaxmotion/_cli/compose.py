"""`python -m jaxmotion compose`: a composite motion from controllers found earlier (the second
paper's section 3): its config, the transition-point search and its results folder."""

import itertools
import json
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import tomli_w

from .._composite import Composite
from .._objective.script import Script, ScriptError
from .._search.protocol import drive
from .._search.transitions import TransitionSearch
from .._sim.trajectory import Trajectory
from .config import (
    OUTPUT,
    TOP,
    ConfigError,
    Experiment,
    Key,
    _read_section,
    load_config,
    read_toml,
)

PHASE = {
    "name": Key(
        "string",
        None,
        lambda v: v.isidentifier(),
        "that is an identifier (the script's name of the phase)",
    ),
    "results": Key("string", None, lambda v: bool(v.strip()), "(a results folder of `run`)"),
    "config": Key("string", None, lambda v: bool(v.strip()), "(a config to run first)"),
    "stage": Key(
        "string",
        None,
        lambda v: bool(v.strip()),
        "(a stage's name, when results or config is a multi-stage run)",
    ),
    "ticks": Key("integer", None, lambda v: v >= 0, ">= 0 (the phase's first guess, in ticks)"),
}

SCRIPT = {
    "text": Key("string", None, lambda v: bool(v.strip()), "(the composite's script)"),
    "tick": Key(
        "number",
        None,
        lambda v: v > 0,
        "> 0 (s: the script's unit of time, a whole number of the components' control "
        "period; default: that period)",
    ),
}

COMPOSE_SEARCH = {
    "arrays": Key("integer", 16, lambda v: v >= 2, ">= 2 (the paper's Q = 16)"),
    "rounds": Key("integer", 16, lambda v: v >= 0, ">= 0 (the paper's G = 16)"),
    "mutations": Key("integer", 4, lambda v: v >= 1, ">= 1 (the paper's H = 4)"),
    "perturb_scale": Key(
        "number", 0.2, lambda v: v > 0, "> 0 (a perturbation's spread, share of the gap)"
    ),
    "start": Key(
        "string",
        "ticks",
        lambda v: v in ("ticks", "equal"),
        '"ticks" (the phases\' ticks) or "equal" (equally spaced)',
    ),
}

COMPOSE_SIMULATION = {
    "duration": Key("number", None, lambda v: v > 0, "> 0 (s; default: the phases' ticks)"),
}

SECTIONS = ("phase", "script", "search", "simulation", "output")

# The keys of a component's config that must agree for its controller to act on the
# composite's body: the same character, in the same world, at the same step.
SHARED = (("body", None), ("world", None), ("simulation", "dt"), ("simulation", "control_dt"))

MEASURES = ("delta_time", "delta_seconds", "delta_cm_x", "delta_cm_z", "clearance")
"""The measures the summary reports for every phase (besides the script's own values)."""


@dataclass(frozen=True)
class ComposeConfig:
    """A checked compose config: the name, seed, the resolved config, the phases (name, its
    source experiment and its best controller), the script, the search and output settings,
    and the composite they make."""

    name: str
    seed: int
    config: dict[str, Any]
    phases: tuple[tuple[str, Experiment, Any], ...]
    search: dict[str, Any]
    output: dict[str, Any]
    composite: Composite
    initial: np.ndarray


def read_compose_config(
    path: str | Path, *, run_component: Callable[[Path], Path] | None = None
) -> ComposeConfig:
    """Read and check a compose config (everything before any compilation, except that a
    phase given as a `config` is first run by `run_component(path) -> results folder`).

    Paths in it are relative to the working directory, as on the command line.

    **Raises:** `ConfigError` naming the first bad key, its value and what is allowed.
    """
    path = Path(path)
    raw = read_toml(path)
    try:
        return parse_compose_config(raw, name=path.stem, run_component=run_component)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def parse_compose_config(
    raw: Mapping[str, Any],
    *,
    name: str = "composite",
    run_component: Callable[[Path], Path] | None = None,
) -> ComposeConfig:
    """`read_compose_config` on a config already read from TOML."""
    head, phases_cfg, script_cfg, search_cfg, simulation_cfg, output_cfg = _tables(raw, name)
    ticks = [c["ticks"] for c in phases_cfg]
    # Every phase is checked before any component runs: the results folders loaded (once),
    # the configs read.
    wheres = [f'[[phase]] {i} ("{cfg["name"]}")' for i, cfg in enumerate(phases_cfg, start=1)]
    loaded = {}
    for i, (where, cfg) in enumerate(zip(wheres, phases_cfg, strict=True)):
        if "config" in cfg:
            _component_config(where, cfg)
        else:
            loaded[i] = _component(where, Path(cfg["results"]), cfg.get("stage"))
    ran: dict[Path, Path] = {}  # a multi-stage config named by several phases runs once
    phases, recorded = [], []
    for i, (where, cfg) in enumerate(zip(wheres, phases_cfg, strict=True)):
        if "config" in cfg:
            source = Path(cfg["config"]).resolve()
            if run_component is None:
                raise ConfigError(f"{where}: config = {cfg['config']!r} would need a run")
            if source not in ran:
                ran[source] = run_component(Path(cfg["config"]))
            folder = ran[source]
            loaded[i] = _component(where, folder, cfg.get("stage"))
        else:
            folder = Path(cfg["results"])
        phases.append((cfg["name"], *loaded[i]))
        # The resolved config names the folder a component config ran into, so that the
        # results folder's config.toml composes the same controllers again.
        recorded.append({k: v for k, v in cfg.items() if k != "config"} | {"results": str(folder)})
    _check_shared(phases)
    first = phases[0][1]
    dt = first.task.dt
    tick = script_cfg.get("tick", first.task.control_dt or dt)
    duration = simulation_cfg.get("duration", round(sum(ticks) * tick, 12))
    try:
        composite = Composite(
            first.task.body,
            first.task.world,
            {n: c for n, _, c in phases},
            script_cfg["text"],
            duration,
            dt,
            control_dt=first.task.control_dt,
            tick=script_cfg.get("tick"),
        )
    except ValueError as e:
        section = "[script]" if str(e).startswith("tick") else "[simulation]"
        raise ConfigError(f"{section} {e}") from None
    initial = np.cumsum(ticks)[:-1] * composite.tick
    if np.any(initial > duration * (1 + 1e-9)):
        raise ConfigError(
            f"the phases' ticks {ticks} end at {initial[-1]:.6g} s, after [simulation] "
            f"duration = {duration}; allowed: a duration at least that long"
        )
    resolved = {
        **head,
        "phase": recorded,
        "script": script_cfg,
        "search": search_cfg,
        "simulation": {"duration": duration},
        "output": output_cfg,
    }
    return ComposeConfig(
        name=head["name"],
        seed=head["seed"],
        config=resolved,
        phases=tuple(phases),
        search=search_cfg,
        output=output_cfg,
        composite=composite,
        initial=initial,
    )


def _tables(raw: Mapping[str, Any], name: str):
    """The checked tables of a compose config (no component loaded or run): the top level,
    the phases, the script (parsed against the phases' names), search, simulation and
    output."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"a compose config must be a table; got {raw!r}")
    top = {k: v for k, v in raw.items() if k not in SECTIONS}
    for k, v in top.items():
        if isinstance(v, Mapping):
            allowed = "[[phase]], [script], [search], [simulation], [output]"
            raise ConfigError(f"unknown section [{k}]; allowed: {allowed}")
    head = _read_section("the top level", top, TOP)
    head.setdefault("name", name)
    phases_raw = raw.get("phase")
    if not isinstance(phases_raw, list) or not phases_raw:
        raise ConfigError(
            "a compose config needs [[phase]] tables, one per controller in order (each "
            'with name, results = "FOLDER" or config = "CONFIG.toml", and ticks)'
        )
    phases_cfg = []
    for i, table in enumerate(phases_raw, start=1):
        where = f"[[phase]] {i}"
        cfg = _read_section(where, table, PHASE)
        for key in ("name", "ticks"):
            if key not in cfg:
                raise ConfigError(f"{where} is missing the key {key!r}")
        if ("results" in cfg) == ("config" in cfg):
            raise ConfigError(
                f'{where} ("{cfg["name"]}") needs exactly one of results = "FOLDER" (a run\'s '
                'results) or config = "CONFIG.toml" (run first)'
            )
        if cfg["name"] in [c["name"] for c in phases_cfg]:
            raise ConfigError(f'{where}: name = "{cfg["name"]}" is used twice; allowed: unique')
        phases_cfg.append(cfg)
    script_cfg = _read_section("[script]", raw.get("script", {}), SCRIPT)
    if "text" not in script_cfg:
        raise ConfigError('[script] is missing the key \'text\' (the script, text = """...""")')
    search_cfg = _read_section("[search]", raw.get("search", {}), COMPOSE_SEARCH)
    simulation_cfg = _read_section("[simulation]", raw.get("simulation", {}), COMPOSE_SIMULATION)
    output_cfg = _read_section("[output]", raw.get("output", {}), OUTPUT)
    names = tuple(c["name"] for c in phases_cfg)
    try:
        Script(script_cfg["text"], names, 1.0)
    except ScriptError as e:
        raise ConfigError(f"[script] text: {e}") from None
    return head, phases_cfg, script_cfg, search_cfg, simulation_cfg, output_cfg


def _component_config(where: str, cfg: Mapping[str, Any]):
    """The checked config a phase names, and its stage if it names one."""
    try:
        experiment = load_config(cfg["config"])
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    return _stage_of(where, experiment, cfg.get("stage"), f"config = {cfg['config']!r}")


def _stage_of(where: str, experiment, stage: str | None, source: str):
    """A phase's experiment: the run's own, or the named stage of a multi-stage run."""
    names = [s.name for s in experiment.stages]
    if stage is None:
        if names:
            raise ConfigError(
                f"{where}: {source} is a multi-stage run; allowed: name its stage with "
                f"stage = one of {', '.join(map(repr, names))}"
            )
        return experiment
    if stage not in names:
        allowed = f"one of {', '.join(map(repr, names))}" if names else "no stage key"
        raise ConfigError(
            f"{where}: stage = {stage!r} is not a stage of {source}; allowed: {allowed}"
        )
    return experiment.stages[names.index(stage)]


def _component(where: str, folder: Path, stage: str | None):
    """A phase's experiment and controller from a results folder of `run` (a single
    search, or the named stage of a multi-stage run)."""
    from .results import _read_config, load_result, load_stages

    source = f"results = {str(folder)!r}"
    try:
        experiment = _stage_of(where, _read_config(folder), stage, source)
        if stage is None:
            return load_result(folder)
        whole, controllers = load_stages(folder)
        return experiment, controllers[[s.name for s in whole.stages].index(stage)]
    except (FileNotFoundError, ValueError) as e:
        if isinstance(e, ConfigError) and str(e).startswith(where):
            raise
        raise ConfigError(f"{where}: {source}: {e}") from None


def check_compose_config(raw: Mapping[str, Any], *, name: str = "composite") -> str:
    """Check a compose config without running or loading anything that needs a run: its
    tables, its script, the component configs it names (each a valid run config, all for
    one body, world and step) and the results folders it names (present). Returns a
    one-line description.

    **Raises:** `ConfigError` naming the first bad key, its value and what is allowed.
    """
    head, phases_cfg, *_ = _tables(raw, name)
    configs = []
    for i, cfg in enumerate(phases_cfg, start=1):
        where = f'[[phase]] {i} ("{cfg["name"]}")'
        if "config" in cfg:
            configs.append((cfg["name"], _component_config(where, cfg), None))
        elif not (Path(cfg["results"]) / "config.toml").is_file():
            raise ConfigError(
                f"{where}: results = {cfg['results']!r} is not a results folder of `run` "
                "(no config.toml)"
            )
    if len(configs) > 1:
        _check_shared(configs)
    ticks = sum(c["ticks"] for c in phases_cfg)
    return f"{head['name']}: {len(phases_cfg)} phases, {ticks} ticks"


def _check_shared(phases) -> None:
    """Every component's body, world and step agree with the first's."""
    first_name, first, _ = phases[0]
    for name, experiment, _ in phases[1:]:
        for section, key in SHARED:
            mine = (
                experiment.config[section] if key is None else experiment.config[section].get(key)
            )
            theirs = first.config[section] if key is None else first.config[section].get(key)
            if mine != theirs:
                label = f"[{section}]" + ("" if key is None else f" {key}")
                raise ConfigError(
                    f'phase "{name}": its {label} = {mine!r} differs from phase '
                    f'"{first_name}"\'s {theirs!r}; allowed: controllers found for one body, '
                    "world and step"
                )


def phase_measures(composite: Composite, trajectory: Trajectory, transitions) -> dict:
    """Per phase, the measures of `MEASURES` (the script language's own)."""
    lines = [f"{p}_{m} = {p}.{m}" for p in composite.phases for m in MEASURES]
    probe = Script("\n".join([*lines, "total = 0"]), composite.phases, composite.tick)
    values = probe.values(trajectory, jnp.asarray(transitions, dtype=float))
    return {p: {m: float(values[f"{p}_{m}"]) for m in MEASURES} for p in composite.phases}


def phase_trajectories(trajectory: Trajectory, transitions) -> list[Trajectory]:
    """The composite's motion cut at the transitions (each phase from its first sample to
    its last, times from 0), for the phases' own checks."""
    ts = np.asarray(trajectory.ts)
    bounds = [0, *[int(np.argmin(np.abs(ts - t))) for t in np.asarray(transitions)], len(ts) - 1]
    parts = []
    for a, b in itertools.pairwise(bounds):
        cut = lambda x, a=a, b=b: x[a : b + 1]
        parts.append(
            Trajectory(
                ts=cut(trajectory.ts) - trajectory.ts[a],
                points=cut(trajectory.points),
                com=cut(trajectory.com),
                frame=cut(trajectory.frame),
                contact=cut(trajectory.contact),
                finite=trajectory.finite,
            )
        )
    return parts


def _report(compose: ComposeConfig, transitions) -> dict[str, Any]:
    """The composite with these transitions: its fitness, the script's values, each phase's
    measures and its component's check on it."""
    from .results import _json_number, run_check

    composite = compose.composite
    trajectory = composite.trajectory(transitions)
    values = composite.script.values(trajectory, jnp.asarray(transitions, dtype=float))
    measures = phase_measures(composite, trajectory, transitions)
    checks = {}
    for (name, experiment, _), part in zip(
        compose.phases, phase_trajectories(trajectory, transitions), strict=True
    ):
        if len(part.ts) > 1:
            verdict = run_check(experiment, part)
            checks[name] = None if verdict is None else verdict.to_dict()
        else:
            checks[name] = None
    fitness = float(composite.evaluate(jnp.asarray(transitions, dtype=float)[None])[0])
    return {
        "transitions": [float(t) for t in np.asarray(transitions)],
        "ticks": [round(float(t) / composite.tick) for t in np.asarray(transitions)],
        "fitness": _json_number(fitness),
        "values": {k: _json_number(float(v)) for k, v in values.items()},
        "phases": measures,
        "checks": checks,
    }, trajectory


def run_compose(
    compose: ComposeConfig,
    *,
    directory: str | Path | None = None,
    animation: bool | None = None,
    report: Callable[[str], None] | None = None,
    checkpoint_every: float | None = None,
    resume: str | Path | None = None,
    stop: Callable[[], bool] | None = None,
) -> Path:
    """Search the transitions of a composite and write its results folder
    `<directory>/<name>-<timestamp>/`: `config.toml` (resolved), `best_controller.json` (the
    `Sequence` at the best transitions), `best_transitions.json`, `history.csv` and
    `learning_plot.png` of the search, `motion.gif` of the best composite (unless
    `animation` is off) and `summary.json` (the start, the equally spaced default and the
    best: fitness, the script's values, each phase's measures and its component's check;
    the search's wall time). Written whole or not at all.

    **Checkpoints**, as `run_experiment`'s: with `checkpoint_every` (seconds) the transition
    search's state and history are saved to `<directory>/<name>-<time>.checkpoint` that often
    (after a mutation step) and on an interrupt (`KeyboardInterrupt`, or `stop()` true after
    a step), which then raises `Interrupted` naming the file; `resume` (the file, or the
    directory holding it) continues the search to the uninterrupted result, bitwise.

    **Raises:** `ConfigError` for a checkpoint that is truncated, of another config or
    version; `Interrupted`."""
    from ..viz import animate, learning_plot
    from .checkpoint import (
        SUFFIX,
        find_checkpoint,
        load_transitions_checkpoint,
        save_transitions_checkpoint,
    )
    from .results import (
        Interrupted,
        _Checkpoints,
        _json_number,
        controller_to_dict,
        new_folder,
        write_history_csv,
    )

    say = report or (lambda _: None)
    out_root = Path(directory if directory is not None else compose.output["directory"])
    want_animation = compose.output["animation"] if animation is None else animation
    composite, s = compose.composite, compose.search
    equal = composite.equally_spaced()
    start = compose.initial if s["start"] == "ticks" else equal
    searcher = TransitionSearch(
        composite.duration,
        num_arrays=s["arrays"],
        mutations=s["mutations"],
        tick=composite.tick,
        initial=start,
    )
    resumed, source = None, None
    if resume is not None:
        source = find_checkpoint(Path(resume), compose)
        resumed = load_transitions_checkpoint(source, compose, searcher)
    final, tmp = new_folder(out_root, compose.name)
    checkpoints = None
    if checkpoint_every is not None or resumed is not None:
        path = source if source is not None else out_root / f"{final.name}{SUFFIX}"
        resumed = None if resumed is None else [resumed]
        write = save_transitions_checkpoint
        checkpoints = _Checkpoints(path, compose, checkpoint_every, resumed, stop, write)
        checkpoints.begin()
        resumed = checkpoints.resumed

    try:
        say(f"searching transitions from {np.round(start, 6).tolist()} s")
        began = time.perf_counter()
        result = drive(
            searcher,
            composite,
            key=jr.key(compose.seed),
            steps=s["rounds"] * s["mutations"],
            callback=checkpoints,
            **({} if resumed is None else {"state": resumed[0], "history": resumed[1]}),
        )
        search_s = time.perf_counter() - began
        best = np.asarray(result.best)
        summary_best, trajectory = _report(compose, best)
        summary = {
            "name": compose.name,
            "seed": compose.seed,
            "search_time_s": search_s,
            "evaluations": int(result.evaluations),
            "best": summary_best,
            "start": _report(compose, start)[0],
            "equally_spaced": _report(compose, equal)[0],
        }
        summary["improved_on_equal_spacing"] = bool(
            result.best_fitness > float(summary["equally_spaced"]["fitness"])
        )
        saved = controller_to_dict(composite.sequence(best))
        saved.update(fitness=_json_number(result.best_fitness), config="config.toml")
        (tmp / "best_controller.json").write_text(json.dumps(saved, indent=2))
        (tmp / "best_transitions.json").write_text(
            json.dumps({k: summary_best[k] for k in ("transitions", "ticks", "fitness")}, indent=2)
        )
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        write_history_csv(tmp / "history.csv", result.history)
        fig = learning_plot(result.history, title=f"{compose.name}: transition search")
        fig.savefig(tmp / "learning_plot.png", dpi=120)
        if want_animation:
            animate(trajectory, composite.body, fps=compose.output["fps"]).save(tmp / "motion.gif")
        (tmp / "config.toml").write_text(tomli_w.dumps(compose.config))
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
    say(
        f"best fitness {result.best_fitness:.4g} (equally spaced "
        f"{summary['equally_spaced']['fitness']}), {search_s:.1f} s"
    )
    return final


__all__ = [
    "ComposeConfig",
    "check_compose_config",
    "parse_compose_config",
    "phase_measures",
    "phase_trajectories",
    "read_compose_config",
    "run_compose",
]
