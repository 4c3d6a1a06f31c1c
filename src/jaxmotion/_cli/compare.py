"""`python -m jaxmotion compare`: stochastic search alone against stochastic search followed
by gradient refinement, or any two searchers of the registry against each other, on equal
numbers of simulations, over several seeds."""

import datetime as _dt
import json
import math
import shutil
import statistics
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

from .._search.protocol import AbstractSearcher, SearchResult, drive, fittest
from .._search.refine import Smoothing, gradient_cost, refine
from .config import SEARCHES, ConfigError, Experiment, search_evaluations

STRATEGIES = ("plain", "anneal", "final")


@dataclass(frozen=True)
class CompareSettings:
    """How the budget is split: `fraction` of the search's simulations after its initial
    set go to the config's searcher, the rest to `refine` on its best `top_k` controllers
    with Adam at `learning_rate`, by each of `strategies`:

    - `"plain"`: gradients of the problem smoothed by `smoothing`, through the whole motion.
    - `"anneal"`: the smoothing annealed to none over the steps (`Smoothing.annealed()`).
    - `"final"`: gradients through the last `final_phase` seconds only (`refine`'s
        `final_phase`), smoothed by `smoothing`.

    A gradient step costs what `jaxmotion.gradient_cost` measures for its strategy
    (`gradient_cost`, if given, for all), plus one simulation for its true evaluation, per
    controller."""

    seeds: tuple[int, ...] = (0, 1, 2)
    fraction: float = 0.5
    top_k: int = 10
    learning_rate: float = 0.01
    smoothing: Smoothing = field(
        default_factory=lambda: Smoothing(regime_width=0.05, friction_velocity=0.1)
    )
    gradient_cost: float | None = None
    strategies: tuple[str, ...] = ("plain",)
    final_phase: float = 1.0

    def __post_init__(self):
        if not 0 < self.fraction < 1:
            raise ValueError(f"compare fraction = {self.fraction!r}; allowed: 0 < fraction < 1")
        if self.top_k < 1:
            raise ValueError(f"compare top_k = {self.top_k!r}; allowed: an integer >= 1")
        if not self.learning_rate > 0:
            raise ValueError(f"compare learning_rate = {self.learning_rate!r}; allowed: > 0")
        if not self.seeds:
            raise ValueError("compare seeds: allowed: at least one seed")
        unknown = [x for x in self.strategies if x not in STRATEGIES]
        if unknown or not self.strategies or len(set(self.strategies)) < len(self.strategies):
            raise ValueError(
                f"compare strategies = {','.join(self.strategies)!r}; allowed: distinct names "
                f"among {', '.join(STRATEGIES)}"
            )
        if not (isinstance(self.final_phase, int | float) and self.final_phase > 0):
            raise ValueError(f"compare final_phase = {self.final_phase!r}; allowed: seconds > 0")

    def refine_options(self, strategy: str) -> dict:
        """`refine`'s keyword arguments for a strategy."""
        if strategy == "anneal":
            return dict(smoothing=self.smoothing.annealed())
        if strategy == "final":
            return dict(smoothing=self.smoothing, final_phase=self.final_phase)
        return dict(smoothing=self.smoothing)

    def label(self, strategy: str) -> str:
        """A strategy's method name in the table."""
        if strategy == "plain":
            return "search+refine"
        if strategy == "final":
            return f"search+refine final {self.final_phase:g}s"
        return f"search+refine {strategy}"


def _curve(history_fitness: np.ndarray, costs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best fitness so far against simulations spent."""
    return np.cumsum(costs), np.maximum.accumulate(history_fitness)


def _budget(experiment: Experiment, settings: CompareSettings) -> tuple[int, int]:
    """The simulations of each method, and the search's share of them when it is followed
    by refinement (its initial set, then `fraction` of the rest)."""
    budget = search_evaluations(experiment.search)
    initial = SEARCHES[experiment.search["algorithm"]].initial(experiment.search)
    return budget, initial + max(1, round(settings.fraction * (budget - initial)))


def compare_one(
    experiment: Experiment, seed: int, settings: CompareSettings, costs: dict[str, float]
):
    """Search alone and search + refine by each strategy for one seed; returns the curve
    and best of the search alone, per strategy its curve, best and gradient steps, and the
    best of the search on its share (where refinement starts)."""
    import optax

    task = experiment.task
    budget, share = _budget(experiment, settings)
    alone, _ = run_searcher(experiment, experiment.search, budget, seed)
    a = _curve(alone.history.fitness, np.ones(len(alone.history)))

    first, used = run_searcher(experiment, experiment.search, share, seed)
    start, _ = fittest(first, settings.top_k)
    k = jax.tree_util.tree_leaves(start)[0].shape[0]
    refined = {}
    for strategy in settings.strategies:
        per_step = k * (costs[strategy] + 1)  # a gradient and a true evaluation each
        steps = int((budget - used) // per_step)
        _, result = refine(
            task,
            start,
            optax.adam(settings.learning_rate),
            steps,
            **settings.refine_options(strategy),
        )
        # The refinement's history holds k true evaluations per step (step 0: the
        # starting point, already paid for by the search); each later step costs per_step.
        rows = result.history.fitness.reshape(steps + 1, k)[1:].max(axis=1)
        fitness = np.concatenate([first.history.fitness, rows])
        spent = np.concatenate([np.ones(len(first.history)), np.full(steps, per_step)])
        b = _curve(fitness, spent)
        refined[strategy] = (b, float(b[1][-1]), steps)
    return a, float(a[1][-1]), refined, float(first.best_fitness)


def run_compare(
    experiment: Experiment,
    settings: CompareSettings,
    *,
    directory: str | Path | None = None,
    progress=None,
) -> Path:
    """Run the comparison and write its folder (atomically, like `run_experiment`):
    `compare.csv` (per seed and method, the best fitness), `compare.md` (the table),
    `compare.png` (best fitness against simulations spent) and `summary.json`."""
    task = experiment.task
    budget, share = _budget(experiment, settings)
    budgeted(experiment.search, share)  # refuse a share that does not fit before anything
    if "final" in settings.strategies and not settings.final_phase <= task.duration:
        raise ConfigError(
            f"compare final_phase = {settings.final_phase:g} s; allowed: at most the "
            f"duration {task.duration:g} s"
        )
    k = settings.top_k
    probe = task.sample(k, key=jr.key(12345))  # a batch of the refined size, to time
    measured = {}
    for strategy in settings.strategies:
        # Annealing's stages cost at most its first stage, the plain smoothed problem: it
        # is charged that.
        timed = "plain" if strategy == "anneal" else strategy
        if settings.gradient_cost is not None:
            measured[timed] = settings.gradient_cost
        elif timed not in measured:
            options = settings.refine_options(timed)
            measured[timed] = gradient_cost(
                task, probe, options["smoothing"], options.get("final_phase")
            )
    costs = {s: math.ceil(measured["plain" if s == "anneal" else s]) for s in settings.strategies}
    results = []
    for seed in settings.seeds:
        if progress is not None:
            progress(f"seed {seed}")
        results.append((seed, *compare_one(experiment, seed, settings, costs)))

    a_best = [r[2] for r in results]
    starts = [r[4] for r in results]
    lines = ["seed,method,best_fitness,simulations,gradient_steps"]
    for seed, a, fa, refined, _ in results:
        lines.append(f"{seed},search,{fa!r},{int(a[0][-1])},0")
        for strategy, (b, fb, steps) in refined.items():
            lines.append(f"{seed},{settings.label(strategy)},{fb!r},{int(b[0][-1])},{steps}")
    table = [
        f"{experiment.name}: best fitness over seeds {list(settings.seeds)} (equal budgets; "
        f"search on {settings.fraction:.0%} of the simulations after its initial set, then "
        f"refine its top {k}; a gradient step counts as {k} x (cost + 1) simulations, with "
        + ", ".join(f"{s} cost {c}" for s, c in costs.items())
        + ")",
        "",
        "| method | median | min | max |",
        "|---|---|---|---|",
        _row("stochastic search", a_best),
        _row(f"search on its share ({settings.fraction:.0%}): refinement's start", starts),
    ]
    per_strategy = {}
    for strategy in settings.strategies:
        best = [r[3][strategy][1] for r in results]
        diffs = [fb - fa for fa, fb in zip(a_best, best, strict=True)]
        table.append(_row(settings.label(strategy), best))
        table.append(_row(f"difference ({strategy} - search)", diffs))
        per_strategy[strategy] = {
            "best": best,
            "improved_on_start": sum(b > a for a, b in zip(starts, best, strict=True)),
            "gradient_steps": [r[3][strategy][2] for r in results],
            "gradient_cost_simulations": costs[strategy],
            "median_difference": statistics.median(diffs),
            "wins": sum(d > 0 for d in diffs),
        }
    first = settings.strategies[0]
    summary = {
        "name": experiment.name,
        "seeds": list(settings.seeds),
        "budget": budget,
        "fraction": settings.fraction,
        "top_k": k,
        "learning_rate": settings.learning_rate,
        "smoothing": {
            "regime_width": settings.smoothing.regime_width,
            "friction_velocity": settings.smoothing.friction_velocity,
        },
        "final_phase": settings.final_phase,
        "search_best": a_best,
        "start_best": starts,
        "strategies": per_strategy,
        # The first strategy's figures under the names earlier versions wrote.
        "gradient_cost_simulations": costs[first],
        "refine_best": per_strategy[first]["best"],
        "median_difference": per_strategy[first]["median_difference"],
        "refine_wins": per_strategy[first]["wins"],
    }
    curves = {"stochastic search": [r[1] for r in results]}
    for strategy in settings.strategies:
        curves[settings.label(strategy)] = [r[3][strategy][0] for r in results]
    title = f"{experiment.name}: stochastic search vs search + gradients"
    return _write(experiment, directory, lines, table, curves, title, summary)


def _row(name: str, values, *cells) -> str:
    """A table row: the name, any other cells, then the median, min and max of `values`."""
    middle = "".join(f" {c} |" for c in cells)
    return (
        f"| {name} |{middle} {statistics.median(values):.4g} | {min(values):.4g} | "
        f"{max(values):.4g} |"
    )


def _write(
    experiment: Experiment,
    directory: str | Path | None,
    lines: list[str],
    table: list[str],
    curves: dict[str, list[tuple[np.ndarray, np.ndarray]]],
    title: str,
    summary: dict,
) -> Path:
    """Write a comparison's folder atomically (a hidden temporary folder moved into place):
    `compare.csv` (`lines`), `compare.md` (`table`), `compare.png` (each method's curves of
    best fitness against simulations, one per seed) and `summary.json`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_root = Path(directory if directory is not None else experiment.output["directory"])
    out_root.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    final = out_root / f"{experiment.name}-compare-{stamp}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=out_root))
    try:
        (tmp / "compare.csv").write_text("\n".join(lines) + "\n")
        (tmp / "compare.md").write_text("\n".join(table) + "\n")
        fig, ax = plt.subplots(figsize=(7, 4))
        for i, (label, runs) in enumerate(curves.items()):
            for n, (sims, best) in enumerate(runs):
                ax.step(
                    sims,
                    best,
                    where="post",
                    color=f"C{i}",
                    alpha=0.7,
                    label=label if n == 0 else None,
                )
        ax.set_xlabel("simulations spent")
        ax.set_ylabel("best fitness so far")
        ax.set_title(title)
        ax.legend()
        fig.tight_layout()
        fig.savefig(tmp / "compare.png", dpi=110)
        plt.close(fig)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        shutil.move(str(tmp), str(final))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def budgeted(search: dict, budget: int) -> tuple[AbstractSearcher, int, int | None, int]:
    """The searcher of a checked [search] section with its steps set so that it makes at most
    `budget` simulations, initial set included: exactly `budget` for the searchers that can
    end within a step (hill climbing, evosax), else the most whole generations that fit.
    Returns the searcher, its steps, the evaluations that count of its last step, and the
    simulations it will make.

    **Raises:** `ConfigError` if even its initial set does not fit."""
    config = SEARCHES[search["algorithm"]]
    searcher = config.make(search)
    initial, per_step = config.initial(search), config.per_step(search)
    partial = hasattr(searcher, "plan")  # it can end within a step: exactly on the budget
    if budget - initial < (1 if partial else per_step):
        raise ConfigError(
            f"compare: a budget of {budget} simulations leaves no step after the "
            f"{search['algorithm']} initial set of {initial}; allowed: a larger budget"
        )
    if partial:
        steps, last = searcher.plan(budget - initial)
        return searcher, steps, last, budget
    steps = (budget - initial) // per_step  # the most whole steps that fit
    return searcher, steps, None, initial + steps * per_step


def run_searcher(
    experiment: Experiment, search: dict, budget: int, seed: int
) -> tuple[SearchResult, int]:
    """One search of `experiment`'s task by the searcher `search` describes, on at most
    `budget` simulations, from `jax.random.key(seed)`. Returns the result and its
    simulations."""
    searcher, steps, last, used = budgeted(search, budget)
    result = drive(searcher, experiment.task, key=jr.key(seed), steps=steps, last=last)
    return result, used


def search_label(search: dict) -> str:
    """A searcher's name in a table: the algorithm, and the strategy for evosax."""
    if search["algorithm"] == "evosax":
        return f"evosax {search['strategy']}"
    return search["algorithm"]


def run_compare_searchers(
    experiment: Experiment,
    other: dict,
    seeds: tuple[int, ...],
    *,
    directory: str | Path | None = None,
    progress=None,
) -> Path:
    """Run `experiment`'s searcher against the searcher of the checked [search] section
    `other`, both on `experiment`'s task and budget (its [search] section's simulations),
    over `seeds`; write the folder (atomically): `compare.csv` (per seed and searcher, the
    best fitness and the simulations made), `compare.md` (the table), `compare.png` (best
    fitness against simulations) and `summary.json`."""
    budget = search_evaluations(experiment.search)
    searches = (experiment.search, other)
    labels = [search_label(s) for s in searches]
    if labels[0] == labels[1]:
        labels = [f"{labels[0]} (config)", f"{labels[1]} (against)"]
    for s in searches:
        budgeted(s, budget)  # refuse a budget that does not fit before anything runs
    runs = []
    for seed in seeds:
        row = []
        for label, s in zip(labels, searches, strict=True):
            if progress is not None:
                progress(f"seed {seed}: {label}")
            row.append(run_searcher(experiment, s, budget, seed))
        runs.append(row)

    lines = ["seed,searcher,best_fitness,simulations"]
    for seed, row in zip(seeds, runs, strict=True):
        for label, (result, used) in zip(labels, row, strict=True):
            lines.append(f"{seed},{label},{result.best_fitness!r},{used}")
    bests = [[row[i][0].best_fitness for row in runs] for i in range(2)]
    diffs = [b - a for a, b in zip(*bests, strict=True)]
    used = [runs[0][i][1] for i in range(2)]
    table = [
        f"{experiment.name}: best fitness over seeds {list(seeds)} (equal budgets: at most "
        f"{budget} simulations each)",
        "",
        "| searcher | simulations | median | min | max |",
        "|---|---|---|---|---|",
        _row(labels[0], bests[0], used[0]),
        _row(labels[1], bests[1], used[1]),
        _row("difference (b - a)", diffs, ""),
    ]
    summary = {
        "name": experiment.name,
        "seeds": list(seeds),
        "budget": budget,
        "searchers": labels,
        "search": [dict(s) for s in searches],
        "simulations": used,
        "best": bests,
        "median_difference": statistics.median(diffs),
        "b_wins": sum(d > 0 for d in diffs),
    }
    curves = {
        label: [
            (np.arange(1, len(row[i][0].history) + 1), row[i][0].history.best_so_far)
            for row in runs
        ]
        for i, label in enumerate(labels)
    }
    title = f"{experiment.name}: {labels[0]} vs {labels[1]}"
    return _write(experiment, directory, lines, table, curves, title, summary)


__all__ = ["CompareSettings", "run_compare", "run_compare_searchers"]
