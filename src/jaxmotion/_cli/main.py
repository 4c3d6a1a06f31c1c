"""`python -m jaxmotion`: run experiments from TOML configs."""

import argparse
import contextlib
import json
import math
import signal
import sys
import threading
from pathlib import Path

DESCRIPTION = """\
jaxmotion: automatic motion synthesis for animated characters.

  python -m jaxmotion                      run the default experiment (a cube learns to travel
                                           forward; about a minute on 2 cores)
  python -m jaxmotion run CONFIG.toml      run a configured experiment (see configs/)
  python -m jaxmotion check CONFIG.toml    check a config without running it
  python -m jaxmotion replay RESULTS_DIR   re-simulate a run's best controller and report it
  python -m jaxmotion export RESULTS_DIR --format bvh|usd [--out PATH]
                                           re-simulate a run's best motion and write it for
                                           Blender, Maya or a game engine (BVH: figures)
  python -m jaxmotion compare CONFIG.toml  stochastic search vs search + gradient refinement
                                           on equal budgets, over several seeds
  python -m jaxmotion compose CONFIG.toml  a composite motion: controllers found earlier, in
                                           turn, their transitions searched (see configs/)
  python -m jaxmotion gallery RESULTS... [--out PAGE.html]
                                           one self-contained HTML page of results folders
                                           (or folders of them): motions, learning plots,
                                           checks and key figures, sortable and filterable
  python -m jaxmotion sweep CONFIG... --seeds 0-9 [--set KEY=VALUE ...] [--address ADDR]
                                           independent runs (configs x seeds x override
                                           sets) as Ray tasks, on a local Ray or a cluster;
                                           a table (sweep.md, sweep.csv) and sweep.png

A run writes a results folder: config.toml (resolved), best_controller.json, history.csv (one
row per evaluation), learning_plot.png, motion.gif and summary.json. Fitness is maximised.
A config with [[stage]] tables runs one search per stage, each starting where the previous
stage's best motion ended; its folder holds a subfolder per stage (stage-1-NAME/, ...), the
whole sequence's motion.gif and a summary.json of every stage.
A run saves a checkpoint every --checkpoint-every seconds and on Ctrl-C or SIGTERM;
`run CONFIG.toml --resume CHECKPOINT` continues it to the very result of an uninterrupted run.
"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m jaxmotion",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command")

    def run_options(q):
        q.add_argument(
            "--out", metavar="DIR", help="results directory (default: [output] directory)"
        )
        q.add_argument("--seed", type=int, help="override the config's seed")
        q.add_argument("--evaluations", type=int, help="override [search] evaluations")
        q.add_argument("--batch", type=int, help="override [search] batch")
        q.add_argument(
            "--runs",
            type=int,
            help="override [search] runs (serial_search: independent runs batched together)",
        )
        q.add_argument("--no-animation", action="store_true", help="do not write motion.gif")
        q.add_argument("--quiet", action="store_true", help="no progress bar or summary")
        q.add_argument(
            "--set",
            action="append",
            metavar="KEY=VALUE",
            help="override a config key, e.g. --set search.evaluations=2000 (a TOML value; "
            "repeat for several keys)",
        )
        checkpoint_options(q)

    def checkpoint_options(q):
        q.add_argument(
            "--checkpoint-every",
            type=float,
            default=30.0,
            metavar="SECONDS",
            help="save the search's state to <out>/<name>-<time>.checkpoint this often and "
            "on Ctrl-C or SIGTERM (default 30)",
        )
        q.add_argument(
            "--resume",
            metavar="CHECKPOINT",
            help="continue an interrupted search of the same config from its checkpoint (the "
            "file, or the results directory holding it); finishes as the uninterrupted run",
        )

    run = sub.add_parser(
        "run",
        help="run a configured experiment",
        description="Run the experiment a TOML config describes.",
    )
    run.add_argument("config", help="path to a TOML config, e.g. configs/default.toml")
    run_options(run)
    check = sub.add_parser("check", help="check a config without running it")
    check.add_argument("config")
    replay = sub.add_parser("replay", help="re-simulate the best controller of a results folder")
    replay.add_argument("results", help="a results folder written by `run`")
    replay.add_argument(
        "--solver",
        default="symplectic",
        choices=["symplectic", "tsit5", "dopri5"],
        help="solver for the replay (default: the search's fixed-step solver)",
    )
    replay.add_argument("--gif", metavar="PATH", help="also write the motion as a GIF here")
    export = sub.add_parser(
        "export",
        help="write a results folder's best motion for animation tools (BVH, USD)",
        description="Re-simulate the best controller of a results folder (every stage of a "
        "multi-stage run, joined) with the search's own settings and write the motion as a "
        "file for animation tools: BVH (figures only; Y-up, metres, one frame per saved "
        "sample) or USD (any body; z-up, metres; needs usd-core); see the README's Export "
        "section.",
    )
    export.add_argument("results", help="a results folder written by `run`")
    export.add_argument(
        "--format", required=True, help="the file format: bvh or usd", metavar="FORMAT"
    )
    export.add_argument(
        "--out",
        metavar="PATH",
        help="the file to write (default: RESULTS/motion.bvh or RESULTS/motion.usd)",
    )
    compare = sub.add_parser(
        "compare",
        help="search vs search + gradient refinement, or two searchers, equal budgets",
        description="Run a config's search alone and search + refine (gradient ascent on "
        "its best controllers) on equal numbers of simulations, over several seeds; with "
        "--against, the config's searcher against another one instead; write a table "
        "(compare.md, compare.csv), a plot (compare.png) and summary.json.",
    )
    compare.add_argument("config")
    compare.add_argument(
        "--against",
        metavar="TOML",
        help="a TOML file whose [search] table is the second searcher (e.g. algorithm = "
        '"evosax", strategy = "CMA_ES"), run on CONFIG\'s task and budget',
    )
    compare.add_argument("--seeds", default="0,1,2", help="comma-separated (default 0,1,2)")
    compare.add_argument(
        "--fraction", type=float, default=0.5, help="share of the budget for the search"
    )
    compare.add_argument("--top-k", type=int, default=10, help="controllers refined")
    compare.add_argument("--learning-rate", type=float, default=0.01, help="Adam's step")
    compare.add_argument(
        "--gradient-cost",
        type=float,
        help="simulations one gradient step costs per controller (default: measured)",
    )
    compare.add_argument(
        "--strategies",
        default="plain",
        help="refinement strategies, comma-separated among plain (smoothed gradients of the "
        "whole motion), anneal (smoothing annealed to none), final (gradients through the "
        "last --final-phase seconds only); default plain",
    )
    compare.add_argument(
        "--final-phase",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="the final strategy's phase, s (default 1.0)",
    )
    compare.add_argument("--out", metavar="DIR", help="results directory")
    compare.add_argument("--evaluations", type=int, help="override [search] evaluations")
    compare.add_argument("--batch", type=int, help="override [search] batch")
    compare.add_argument("--quiet", action="store_true")
    compose = sub.add_parser(
        "compose",
        help="a composite motion: controllers in turn, transitions searched",
        description="Concatenate controllers found earlier (results folders, or configs run "
        "first) into a composite motion scored by the config's script, and search the "
        "transition points (the second paper's Figure 5). Writes a results folder: "
        "config.toml, best_controller.json (the sequence), best_transitions.json, history.csv, "
        "learning_plot.png, motion.gif and summary.json.",
    )
    compose.add_argument("config", help="a compose config, e.g. configs/starman_composite.toml")
    compose.add_argument("--out", metavar="DIR", help="results directory")
    compose.add_argument(
        "--seed", type=int, help="override the config's seed (and the seed of components run first)"
    )
    compose.add_argument("--no-animation", action="store_true", help="do not write motion.gif")
    compose.add_argument("--quiet", action="store_true", help="no progress or summary")
    checkpoint_options(compose)
    gallery = sub.add_parser(
        "gallery",
        help="one HTML page of results folders: motions, learning plots, checks, figures",
        description="Write one self-contained HTML page (images embedded, no network) with, "
        "for every results folder given (a run, a multi-stage run, a compose; or a folder "
        "holding results folders, e.g. a sweep), its motion.gif, learning plot, check "
        "verdict and key figures, under a sortable, filterable table. Nothing is simulated.",
    )
    gallery.add_argument(
        "results", nargs="+", help="results folders, or folders holding results folders"
    )
    gallery.add_argument(
        "--out",
        dest="page",
        metavar="PAGE.html",
        default="gallery.html",
        help="the page to write (default: gallery.html in the working directory)",
    )
    sweep = sub.add_parser(
        "sweep",
        help="independent runs (configs x seeds x override sets) as Ray tasks",
        description="Run every config with every seed and override set as independent "
        "searches, each a Ray task that runs `python -m jaxmotion run` and writes its results "
        "folder into the sweep's folder; on a local Ray started for the sweep, or on a "
        "cluster with --address. A task that fails or is killed is retried once. Writes "
        "sweep.md and sweep.csv (best fitness, check, wall time per search) and sweep.png "
        "(the learning curves). Needs Ray: pip install 'jaxmotion[cluster]'.",
    )
    sweep.add_argument("config", nargs="+", help="TOML configs, e.g. configs/default.toml")
    sweep.add_argument(
        "--seeds", help="seeds and ranges, e.g. 0-9 or 0,3,5 (default: each config's seed)"
    )
    sweep.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a config key in every search, e.g. --set search.evaluations=2000 (a "
        "TOML value); a key given several values is crossed with the rest",
    )
    sweep.add_argument(
        "--address",
        help="an existing Ray cluster (e.g. ray://head:10001, or auto); default: a local Ray "
        "started for the sweep",
    )
    sweep.add_argument(
        "--out", metavar="DIR", help="where the sweep's folder goes (default: results)"
    )
    sweep.add_argument(
        "--cpus-per-task",
        type=_cpu_count,
        default=1,
        metavar="N",
        help="CPUs Ray gives each search; JAX in it makes one device per CPU (default 1)",
    )
    sweep.add_argument(
        "--local-cpus",
        type=_cpu_count,
        metavar="N",
        help="CPUs of the local Ray (default: every core); not with --address",
    )
    sweep.add_argument("--no-animation", action="store_true", help="no motion.gif per search")
    sweep.add_argument("--quiet", action="store_true", help="no progress lines or table")
    sweep.add_argument(
        "--checkpoint-every",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="each search's checkpoint interval; a killed search's retry resumes from it",
    )
    run_options(p)  # `python -m jaxmotion [options]` runs the default experiment
    for q in (p, *sub.choices.values()):
        q.add_argument(
            "--no-compilation-cache",
            action="store_true",
            help="do not keep compiled programs in the persistent cache (default: kept in "
            "$JAXMOTION_COMPILATION_CACHE, else ~/.cache/jaxmotion/jax, so the next run "
            "starts warm; see the README's Performance section)",
        )
    for q in (p, *sub.choices.values()):
        q.add_argument(
            "--cpu-devices",
            type=_cpu_count,
            metavar="N",
            help="CPU devices JAX makes (default: one per core); a sweep gives each of its "
            "runs --cpus-per-task",
        )
    return p


def _cpu_count(text: str) -> int:
    """A count of CPUs (`--cpu-devices`, `--cpus-per-task`, `--local-cpus`)."""
    n = int(text) if text.strip().isdigit() else 0
    if not 1 <= n <= 4096:
        raise argparse.ArgumentTypeError(f"{text!r}; allowed: an integer from 1 to 4096")
    return n


def _compose_check(path: Path) -> str | None:
    """`check` of a compose config (one with [[phase]] tables); None for any other."""
    import tomllib

    from .compose import check_compose_config
    from .config import ConfigError

    try:
        with path.open("rb") as f:
            raw = tomllib.load(f)
    except (FileNotFoundError, tomllib.TOMLDecodeError):
        return None  # `_load` reports it
    if not isinstance(raw, dict) or "phase" not in raw:
        return None
    try:
        return check_compose_config(raw, name=path.stem)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def _compose(args) -> int:
    from .compose import read_compose_config, run_compose
    from .results import run_experiment

    say = (lambda _: None) if args.quiet else (lambda line: print(line, file=sys.stderr))

    def run_component(path: Path) -> Path:
        # With --seed, the components are searched with that seed too (a composite's
        # independent runs are independent all the way down).
        say(f"running {path} first" + ("" if args.seed is None else f" (seed {args.seed})"))
        keep = argparse.Namespace(seed=args.seed, evaluations=None, batch=None, runs=None)
        folder = run_experiment(
            _load(path, keep), directory=args.out, progress=not args.quiet, animation=False
        )
        say(f"  -> {folder}")
        return folder

    compose = read_compose_config(args.config, run_component=run_component)
    if args.seed is not None:
        from dataclasses import replace

        compose = replace(compose, seed=args.seed, config={**compose.config, "seed": args.seed})
    with _stop_on_signals() as stop:
        folder = run_compose(
            compose,
            directory=args.out,
            animation=False if args.no_animation else None,
            report=say,
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
            stop=stop,
        )
    if not args.quiet:
        summary = json.loads((folder / "summary.json").read_text())
        print(json.dumps({k: summary[k] for k in ("best", "equally_spaced")}, indent=2))
    print(folder)
    return 0


def _overrides(raw: dict, args) -> dict:
    raw = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    if args.seed is not None:
        raw["seed"] = args.seed
    search = raw.setdefault("search", {})
    stages = raw.get("stage")
    if not isinstance(stages, list):
        _override_search(search, args, "")
        return raw
    # A multi-stage config: the override applies to every stage's search (its own table
    # merged over the top-level one), which then spells out its merged table.
    if not any(getattr(args, k, None) is not None for k in ("evaluations", "batch", "runs")):
        return raw
    raw["stage"] = stages = [dict(s) if isinstance(s, dict) else s for s in stages]
    for i, stage in enumerate(stages, start=1):
        if not isinstance(stage, dict):
            continue  # parse_config reports it
        own = stage.get("search", {})
        if not isinstance(search, dict) or not isinstance(own, dict):
            continue
        merged = {**search, **own}
        name = stage.get("name")
        _override_search(merged, args, f"[[stage]] {i}" + (f' ("{name}")' if name else "") + ": ")
        stage["search"] = merged
    return raw


def _override_search(search, args, where: str) -> None:
    """Apply --evaluations, --batch and --runs to one [search] table (`where`: which)."""
    from .config import ConfigError

    serial = isinstance(search, dict) and search.get("algorithm") == "serial_search"
    evolution = isinstance(search, dict) and search.get("algorithm") == "evolve"
    if evolution:
        _override_evolve(search, args, where)
        return
    if args.evaluations is not None:
        if serial:
            # Serial search counts generations: each evaluates every climber once.
            climbers = search.get("climbers", 10)
            if not isinstance(climbers, int) or isinstance(climbers, bool) or climbers < 1:
                raise ConfigError(
                    f"{where}[search] climbers = {climbers!r}; allowed: an integer >= 1"
                )
            if args.evaluations < 1:
                raise ConfigError(f"--evaluations = {args.evaluations}; allowed: >= 1")
            search["generations"] = max(1, -(-args.evaluations // climbers))
        elif isinstance(search, dict):
            search["evaluations"] = args.evaluations
    if args.batch is not None:
        if serial:
            raise ConfigError(
                f"{where}--batch applies to parallel_hill_climb; serial_search evaluates all "
                "its climbers (and runs) in one batch"
            )
        if isinstance(search, dict):
            search["batch"] = args.batch
    if getattr(args, "runs", None) is not None:
        if not serial:
            raise ConfigError(f'{where}--runs applies to [search] algorithm = "serial_search"')
        search["runs"] = args.runs


def _override_evolve(search: dict, args, where: str) -> None:
    """--evaluations for [search] algorithm = "evolve": the generations that evaluate at
    least that many (the first evaluates `size`, each later one `4 size / 5`)."""
    from .config import ConfigError

    if args.batch is not None:
        raise ConfigError(
            f"{where}--batch applies to parallel_hill_climb; evolve evaluates each generation "
            "in one call"
        )
    if getattr(args, "runs", None) is not None:
        raise ConfigError(f'{where}--runs applies to [search] algorithm = "serial_search"')
    if args.evaluations is None:
        return
    size = search.get("size", 2000)
    if not isinstance(size, int) or isinstance(size, bool) or size < 5 or size % 5:
        raise ConfigError(
            f"{where}[search] size = {size!r}; allowed: an integer >= 5, a multiple of 5"
        )
    if args.evaluations < 1:
        raise ConfigError(f"--evaluations = {args.evaluations}; allowed: >= 1")
    later = max(0, args.evaluations - size)
    search["generations"] = 1 + -(-later // (size * 4 // 5))


def _load(path: Path, args):
    from .config import ConfigError, parse_config, read_toml

    raw = read_toml(path)
    if getattr(args, "set", None):
        from .sweep import apply_sets, override_sets

        [settings] = override_sets(args.set, grid=False)
        raw = apply_sets(raw, settings)
    try:
        return parse_config(_overrides(raw, args), name=path.stem)
    except ConfigError as e:
        given = " ".join(getattr(args, "set", None) or ())
        raise ConfigError(f"{path}: {e}" + (f" (with --set {given})" if given else "")) from None


@contextlib.contextmanager
def _stop_on_signals():
    """Ctrl-C and SIGTERM (a scheduler's stop) ask the search to stop after its current
    step, with a checkpoint; a second one stops at once. (A KeyboardInterrupt raised wherever
    the signal lands can be swallowed, e.g. inside a garbage-collection callback.) Yields
    the `stop()` question the search asks after every step."""
    stop = threading.Event()
    handled = (signal.SIGINT, signal.SIGTERM)
    previous = {}

    def request(signum, frame):
        del frame
        stop.set()
        signal.signal(signum, _terminate)

    if threading.current_thread() is threading.main_thread():
        previous = {s: signal.signal(s, request) for s in handled}
    try:
        yield stop.is_set
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _run(path: Path, args) -> int:
    experiment = _load(path, args)
    from .config import search_plan
    from .results import run_experiment

    say = None if args.quiet else (lambda line: print(line, file=sys.stderr))
    if say is not None:
        if experiment.stages:
            names = ", ".join(s.name for s in experiment.stages)
            plan = f"{len(experiment.stages)} stages ({names}), one search each"
        else:
            plan = search_plan(experiment.search)
        say(f"jaxmotion: {experiment.name}: {plan}, seed {experiment.seed}")
    with _stop_on_signals() as stop:
        folder = run_experiment(
            experiment,
            directory=args.out,
            progress=not args.quiet,
            animation=False if args.no_animation else None,
            report=say,
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
            stop=stop,
        )
    if experiment.stages:
        if say is not None:
            summary = json.loads((folder / "summary.json").read_text())
            say(
                f"{len(summary['stages'])} stages, {summary['evaluations']} evaluations in "
                f"{summary['wall_time_s']:.1f} s"
            )
            if summary.get("check"):
                say(_check_lines(summary["check"]))
        print(folder)
        return 0
    if not args.quiet:
        summary = json.loads((folder / "summary.json").read_text())
        speed = summary.get("steady_evals_per_s")
        speed = (
            f"{speed:.0f} evals/s after compiling"
            if speed
            else f"{summary['evals_per_s']:.0f} evals/s"
        )
        terms = ", ".join(f"{k} {_short(v)}" for k, v in summary["terms"].items())
        print(
            f"best fitness {_short(summary['best_fitness'])} after {summary['evaluations']} "
            f"evaluations in {summary['search_time_s']:.1f} s ({speed}); terms: {terms}",
            file=sys.stderr,
        )
        if summary.get("nonfinite_evaluations"):
            print(
                f"{summary['nonfinite_evaluations']} of {summary['evaluations']} evaluations "
                "blew up (non-finite; scored -inf)",
                file=sys.stderr,
            )
        accurate = summary.get("accurate")
        if accurate and accurate.get("candidates"):
            print(
                f"accurate replay (float64 Dopri5) of the {accurate['candidates']} fittest: "
                f"chose #{accurate['chosen_rank'] + 1}, fitness {_short(accurate['fitness'])} "
                f"(accurately {_short(accurate['accurate_fitness'])}; the fittest's: "
                f"{_short(accurate['search_best_fitness'])}, accurately "
                f"{_short(accurate['search_best_accurate_fitness'])})"
                + (
                    f"; its check under accurate replay: "
                    f"{'passed' if accurate['check']['passed'] else 'failed'}"
                    if accurate.get("check")
                    else ""
                ),
                file=sys.stderr,
            )
        if summary.get("check"):
            print(_check_lines(summary["check"]), file=sys.stderr)
        if summary.get("runs"):
            checked = [r for r in summary["runs"] if r["check"] is not None]
            fits = ", ".join(_short(r["best_fitness"]) for r in summary["runs"])
            line = f"{len(summary['runs'])} independent runs, best fitness: {fits}"
            if checked:
                passed = sum(r["check"]["passed"] for r in checked)
                line += f"; {passed} of {len(checked)} pass the check"
            print(line, file=sys.stderr)
    print(folder)
    return 0


def _short(value) -> str:
    """A fitness or term as the summary holds it: a number, or "-inf", "inf", "nan" for one
    that is not finite."""
    return f"{value:.4g}" if isinstance(value, int | float) else str(value)


def _check_lines(check: dict) -> str:
    """A check's verdict and its criteria, one a line."""
    lines = [f"  {'pass' if ok else 'FAIL'}  {text}" for text, ok in check["criteria"].items()]
    verdict = "passed" if check["passed"] else "failed"
    return f"{check['name']} check {verdict}:\n" + "\n".join(lines)


def _replay_stages(args) -> int:
    from .results import (
        concatenate_trajectories,
        fitness_of,
        load_stages,
        replay_stages,
        run_check,
        run_sequence_check,
        start_where,
    )

    experiment, controllers = load_stages(args.results)
    trajectories = replay_stages(experiment, controllers, solver=args.solver)
    stages = []
    for number, (stage, controller, trajectory) in enumerate(
        zip(experiment.stages, controllers, trajectories, strict=True), start=1
    ):
        task = stage.task
        if args.solver == "symplectic":
            previous = trajectories[number - 2] if number > 1 else task.body.initial_state()
            fitness = fitness_of(start_where(stage, previous).task, controller)
        else:
            fitness = float(task.objective(trajectory))
        entry = {
            "stage": number,
            "name": stage.name,
            "fitness": fitness,
            "terms": {k: float(v) for k, v in task.objective.values(trajectory).items()},
            "finite": bool(trajectory.finite),
        }
        check = run_check(stage, trajectory)
        if check is not None:
            entry["check"] = check.to_dict()
        stages.append(entry)
    report = {"stages": stages, "solver": args.solver}
    check = run_sequence_check(experiment, trajectories)
    if check is not None:
        report["check"] = check.to_dict()
    print(json.dumps(report, indent=2))
    if args.gif:
        from ..viz import animate

        whole = concatenate_trajectories(trajectories)
        animate(whole, experiment.task.body, fps=experiment.output["fps"]).save(args.gif)
        print(args.gif)
    return 0


def _replay(args) -> int:
    from .results import load_result, results_config

    if "stage" in results_config(args.results):
        return _replay_stages(args)
    experiment, controller = load_result(args.results)
    task = experiment.task
    trajectory = task.simulate(controller, solver=args.solver)
    values = {k: float(v) for k, v in task.objective.values(trajectory).items()}
    if args.solver == "symplectic":
        from .results import fitness_of

        fitness = fitness_of(task, controller)  # exactly as the search computed it
    else:
        fitness = float(task.objective(trajectory))
    from .results import run_check

    report = {
        "fitness": fitness,
        "terms": values,
        "finite": bool(trajectory.finite),
        "solver": args.solver,
    }
    check = run_check(experiment, trajectory)
    if check is not None:
        report["check"] = check.to_dict()
    print(json.dumps(report, indent=2))
    if args.gif:
        from ..viz import animate

        animate(trajectory, task.body, fps=experiment.output["fps"]).save(args.gif)
        print(args.gif)
    return 0


def _export(args) -> int:
    from .config import EXPORT_FORMATS, ConfigError
    from .results import (
        EXPORT_FILES,
        concatenate_trajectories,
        load_result,
        load_stages,
        replay_stages,
        results_config,
    )

    if args.format not in EXPORT_FORMATS:
        raise ConfigError(
            f"--format = {args.format!r}; allowed: one of "
            + ", ".join(repr(f) for f in EXPORT_FORMATS)
        )
    folder = Path(args.results)
    raw = results_config(folder)
    compose = None
    if "phase" in raw:  # a composite's folder (`compose`): its phases' shared body
        from .compose import parse_compose_config

        compose = parse_compose_config(raw)
        body = compose.phases[0][1].config["body"]
    else:
        body = raw.get("body", {})
    if args.format == "bvh" and not (isinstance(body, dict) and "figure" in body):
        kind = body.get("lattice", "cube") if isinstance(body, dict) else body
        raise ConfigError(
            f"{folder}: --format bvh exports articulated figures; this run's [body] is a "
            f"lattice ({kind!r}), which has no skeleton"
        )
    out = Path(args.out) if args.out is not None else folder / EXPORT_FILES[args.format]
    if args.format == "usd" and out.suffix not in (".usd", ".usda", ".usdc"):
        raise ConfigError(f"--out = {args.out!r}; allowed: a USD file (.usd, .usda or .usdc)")
    if not out.parent.is_dir():
        raise ConfigError(f"--out = {args.out!r}: the folder {str(out.parent)!r} does not exist")
    if compose is not None:
        best = json.loads((folder / "best_transitions.json").read_text())["transitions"]
        trajectory = compose.composite.trajectory(best, positions=True)
        figure = compose.composite.body
    elif "stage" in raw:
        experiment, controllers = load_stages(folder)
        trajectory = concatenate_trajectories(
            replay_stages(experiment, controllers, positions=True)
        )
        figure = experiment.task.body
    else:
        experiment, controller = load_result(folder)
        trajectory = experiment.task.simulate(controller, positions=True)
        figure = experiment.task.body
    from .. import export

    try:
        getattr(export, args.format)(trajectory, figure, out)
    except (ValueError, ImportError) as e:
        raise ConfigError(f"{folder}: {e}") from None
    print(out)
    return 0


def _gallery(args) -> int:
    from .gallery import write_gallery

    page, count = write_gallery(args.results, args.page)
    print(f"{page} ({count} result{'s' if count != 1 else ''})")
    return 0


def _compare(args) -> int:
    from .compare import CompareSettings, run_compare
    from .config import ConfigError

    try:
        seeds = tuple(int(x) for x in args.seeds.split(","))
    except ValueError:
        raise ConfigError(
            f"--seeds = {args.seeds!r}; allowed: comma-separated integers, e.g. 0,1,2"
        ) from None
    if len(seeds) > 1000 or not all(0 <= s < 2**32 for s in seeds):
        raise ConfigError(
            f"--seeds = {args.seeds!r}; allowed: at most 1000 integers, each from 0 to 2**32 - 1"
        )
    experiment = _load(
        Path(args.config),
        argparse.Namespace(seed=None, evaluations=args.evaluations, batch=args.batch),
    )
    if experiment.stages:
        raise ConfigError(
            f"{args.config}: compare runs one search; this config has "
            f"{len(experiment.stages)} [[stage]] tables"
        )
    if args.against is not None:
        return _compare_searchers(args, experiment, seeds)
    try:
        settings = CompareSettings(
            seeds=seeds,
            fraction=args.fraction,
            top_k=args.top_k,
            learning_rate=args.learning_rate,
            gradient_cost=args.gradient_cost,
            strategies=tuple(x.strip() for x in args.strategies.split(",")),
            final_phase=args.final_phase,
        )
    except ValueError as e:
        raise ConfigError(str(e)) from None
    say = None if args.quiet else (lambda msg: print(f"compare: {msg}", file=sys.stderr))
    folder = run_compare(experiment, settings, directory=args.out, progress=say)
    if not args.quiet:
        print((folder / "compare.md").read_text(), file=sys.stderr)
    print(folder)
    return 0


def _compare_searchers(args, experiment, seeds) -> int:
    """`compare CONFIG --against TOML`: CONFIG's searcher against TOML's [search] one."""
    from .compare import run_compare_searchers
    from .config import ConfigError, parse_config, read_toml

    other = read_toml(Path(args.against))
    if set(other) - {"search"} or not isinstance(other.get("search"), dict):
        raise ConfigError(
            f"--against {args.against}: has {sorted(other) or 'nothing'}; allowed: a TOML file "
            "with only a [search] table"
        )
    raw = read_toml(Path(args.config))
    raw["search"] = other["search"]
    try:
        search = parse_config(raw, name=experiment.name).search
    except ConfigError as e:
        raise ConfigError(f"--against {args.against}: {e}") from None
    say = None if args.quiet else (lambda msg: print(f"compare: {msg}", file=sys.stderr))
    folder = run_compare_searchers(experiment, search, seeds, directory=args.out, progress=say)
    if not args.quiet:
        print((folder / "compare.md").read_text(), file=sys.stderr)
    print(folder)
    return 0


def _check_options(args) -> None:
    """The numeric and path options, checked before anything is loaded or compiled.

    **Raises:** `ConfigError` naming the option, its value and what is allowed."""
    from .config import MAX_BATCH, MAX_EVALUATIONS, ConfigError

    bounds = {
        "seed": (0, 2**32 - 1),
        "evaluations": (1, MAX_EVALUATIONS),
        "batch": (1, MAX_BATCH),
        "runs": (1, MAX_BATCH),
        "top_k": (1, MAX_BATCH),
    }
    for name, (lo, hi) in bounds.items():
        value = getattr(args, name, None)
        if value is not None and not lo <= value <= hi:
            option = "--" + name.replace("_", "-")
            raise ConfigError(f"{option} = {value}; allowed: an integer from {lo} to {hi}")
    for name in ("learning_rate", "gradient_cost"):
        value = getattr(args, name, None)
        if value is not None and not (math.isfinite(value) and 0 < value <= 1e30):
            option = "--" + name.replace("_", "-")
            raise ConfigError(f"{option} = {value}; allowed: a number > 0 (finite, <= 1e30)")
    fraction = getattr(args, "fraction", None)
    if fraction is not None and not 0 < fraction < 1:
        raise ConfigError(f"--fraction = {fraction}; allowed: a number with 0 < fraction < 1")
    every = getattr(args, "checkpoint_every", None)
    if every is not None and not (math.isfinite(every) and every > 0):
        raise ConfigError(
            f"--checkpoint-every = {every}; allowed: a number of seconds > 0 (finite)"
        )
    for name in ("out", "gif"):
        value = getattr(args, name, None)
        if value is None:
            continue
        option = "--" + name
        if not value.strip() or "\x00" in value:
            raise ConfigError(f"{option} = {value!r}; allowed: a path (not empty)")
        path = Path(value)
        exporting = getattr(args, "command", None) == "export"
        if name == "out" and not exporting and path.exists() and not path.is_dir():
            raise ConfigError(
                f"{option} = {value!r} is a file; allowed: a folder (existing or not)"
            )
        if name == "out" and getattr(args, "command", None) == "export" and path.is_dir():
            raise ConfigError(
                f"{option} = {value!r} is a folder; allowed: a file path (e.g. motion.bvh)"
            )
        if name == "gif" and path.is_dir():
            raise ConfigError(f"{option} = {value!r} is a folder; allowed: a file path")


def _terminate(signum, frame):
    del signum, frame
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # One CPU device per core, before anything starts JAX (the application's call).
    from .._devices import use_cpu_cores

    use_cpu_cores() if args.cpu_devices is None else use_cpu_cores(args.cpu_devices)
    from .cache import use_compilation_cache
    from .config import ConfigError, default_config_path, search_evaluations

    if not args.no_compilation_cache:
        try:
            use_compilation_cache()
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2

    try:
        _check_options(args)
        if args.command is None:
            return _run(default_config_path(), args)
        if args.command == "run":
            return _run(Path(args.config), args)
        if args.command == "check":
            composite = _compose_check(Path(args.config))
            if composite is not None:
                print(f"{args.config}: ok ({composite})")
                return 0
            experiment = _load(
                Path(args.config), argparse.Namespace(seed=None, evaluations=None, batch=None)
            )
            parts = experiment.stages or (experiment,)
            total = sum(search_evaluations(s.search) for s in parts)
            stages = f"{len(parts)} stages, " if experiment.stages else ""
            print(f"{args.config}: ok ({experiment.name}: {stages}{total} evaluations)")
            return 0
        if args.command == "compare":
            return _compare(args)
        if args.command == "compose":
            return _compose(args)
        if args.command == "export":
            return _export(args)
        if args.command == "gallery":
            return _gallery(args)
        if args.command == "sweep":
            from .sweep import run_sweep

            return run_sweep(args)
        return _replay(args)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        saved = getattr(e, "checkpoint", None)
        print("interrupted; no results were written", file=sys.stderr)
        if saved is not None:
            config = getattr(args, "config", None) or default_config_path()
            print(
                f"the search so far is saved in {saved}; continue it with:\n"
                f"  python -m jaxmotion {args.command} {config} --resume {saved}",
                file=sys.stderr,
            )
        return 130


if __name__ == "__main__":
    sys.exit(main())

__all__ = ["main"]
