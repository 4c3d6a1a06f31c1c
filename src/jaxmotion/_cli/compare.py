"""`python -m jaxmotion compare`: stochastic search alone against stochastic search followed
by gradient refinement, on equal numbers of simulations, over several seeds."""

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

from .._search.hill_climb import parallel_hill_climb
from .._search.refine import Smoothing, gradient_cost, refine
from .config import Experiment


@dataclass(frozen=True)
class CompareSettings:
    """How the budget is split: `fraction` of the search's evaluations go to the stochastic
    search, the rest to `refine` on its best `top_k` controllers with Adam at
    `learning_rate`, on the problem smoothed by `smoothing`. A gradient step costs
    `gradient_cost` simulations per controller (measured with `jaxmotion.gradient_cost` when
    None), plus one for its true evaluation when the problem is smoothed."""

    seeds: tuple[int, ...] = (0, 1, 2)
    fraction: float = 0.5
    top_k: int = 10
    learning_rate: float = 0.01
    smoothing: Smoothing = field(
        default_factory=lambda: Smoothing(regime_width=0.05, friction_velocity=0.1)
    )
    gradient_cost: float | None = None

    def __post_init__(self):
        if not 0 < self.fraction < 1:
            raise ValueError(f"compare fraction = {self.fraction!r}; allowed: 0 < fraction < 1")
        if self.top_k < 1:
            raise ValueError(f"compare top_k = {self.top_k!r}; allowed: an integer >= 1")
        if not self.learning_rate > 0:
            raise ValueError(f"compare learning_rate = {self.learning_rate!r}; allowed: > 0")
        if not self.seeds:
            raise ValueError("compare seeds: allowed: at least one seed")


def _curve(history_fitness: np.ndarray, costs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best fitness so far against simulations spent."""
    return np.cumsum(costs), np.maximum.accumulate(history_fitness)


def compare_one(experiment: Experiment, seed: int, settings: CompareSettings, cost: float):
    """Both methods for one seed; returns (a's curve, b's curve, a's best, b's best, b's
    number of gradient steps)."""
    import optax

    task = experiment.task
    s = experiment.search
    key = jr.key(seed)
    size, batch, budget = s["size"], s["batch"], s["evaluations"]
    alone = parallel_hill_climb(task, key=key, evaluations=budget, size=size, batch=batch)
    a = _curve(alone.history.fitness, np.ones(len(alone.history)))

    searched = max(1, round(settings.fraction * budget))
    first = parallel_hill_climb(task, key=key, evaluations=searched, size=size, batch=batch)
    k = min(settings.top_k, size)
    start = jax.tree_util.tree_map(lambda x: x[:k], first.state.population)
    per_step = k * (cost + 1)  # a gradient and a true evaluation per controller and step
    steps = int((budget - searched) // per_step)
    _, refined = refine(
        task,
        start,
        optax.adam(settings.learning_rate),
        steps,
        smoothing=settings.smoothing,
    )
    # The refinement's history holds k true evaluations per step (step 0: the starting
    # point, already paid for by the search); each later step costs per_step simulations.
    rows = refined.history.fitness.reshape(steps + 1, k)[1:].max(axis=1)
    fitness = np.concatenate([first.history.fitness, rows])
    costs = np.concatenate([np.ones(len(first.history)), np.full(steps, per_step)])
    b = _curve(fitness, costs)
    return a, b, float(a[1][-1]), float(b[1][-1]), steps


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task = experiment.task
    k = min(settings.top_k, experiment.search["size"])
    probe = task.sample(k, key=jr.key(12345))  # a batch of the refined size, to time
    measured = settings.gradient_cost
    if measured is None:
        measured = gradient_cost(task, probe, settings.smoothing)
    cost = math.ceil(measured)
    results = []
    for seed in settings.seeds:
        if progress is not None:
            progress(f"seed {seed}")
        results.append((seed, *compare_one(experiment, seed, settings, cost)))

    out_root = Path(directory if directory is not None else experiment.output["directory"])
    out_root.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    final = out_root / f"{experiment.name}-compare-{stamp}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=out_root))
    try:
        a_best = [r[3] for r in results]
        b_best = [r[4] for r in results]
        lines = ["seed,method,best_fitness,simulations,gradient_steps"]
        for seed, a, b, fa, fb, steps in results:
            lines.append(f"{seed},search,{fa!r},{int(a[0][-1])},0")
            lines.append(f"{seed},search+refine,{fb!r},{int(b[0][-1])},{steps}")
        (tmp / "compare.csv").write_text("\n".join(lines) + "\n")
        diffs = [fb - fa for fa, fb in zip(a_best, b_best, strict=True)]

        def row(name, values):
            return (
                f"| {name} | {statistics.median(values):.4g} | {min(values):.4g} | "
                f"{max(values):.4g} |"
            )

        table = "\n".join(
            [
                f"{experiment.name}: best fitness over seeds {list(settings.seeds)} "
                f"(equal budgets; a gradient step of {k} controllers counts as {k} x "
                f"({cost} + 1) simulations)",
                "",
                "| method | median | min | max |",
                "|---|---|---|---|",
                row("stochastic search", a_best),
                row(
                    f"search ({settings.fraction:.0%}) + refine top {k}",
                    b_best,
                ),
                row("difference (b - a)", diffs),
            ]
        )
        (tmp / "compare.md").write_text(table + "\n")
        fig, ax = plt.subplots(figsize=(7, 4))
        for label, idx, colour in (("stochastic search", 1, "C0"), ("search + refine", 2, "C1")):
            for n, r in enumerate(results):
                sims, best = r[idx]
                ax.step(
                    sims,
                    best,
                    where="post",
                    color=colour,
                    alpha=0.7,
                    label=label if n == 0 else None,
                )
        ax.set_xlabel("simulations spent")
        ax.set_ylabel("best fitness so far")
        ax.set_title(f"{experiment.name}: stochastic search vs search + gradients")
        ax.legend()
        fig.tight_layout()
        fig.savefig(tmp / "compare.png", dpi=110)
        plt.close(fig)
        summary = {
            "name": experiment.name,
            "seeds": list(settings.seeds),
            "budget": experiment.search["evaluations"],
            "fraction": settings.fraction,
            "top_k": k,
            "learning_rate": settings.learning_rate,
            "smoothing": {
                "regime_width": settings.smoothing.regime_width,
                "friction_velocity": settings.smoothing.friction_velocity,
            },
            "gradient_cost_simulations": cost,
            "search_best": a_best,
            "refine_best": b_best,
            "median_difference": statistics.median(diffs),
            "refine_wins": sum(d > 0 for d in diffs),
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        shutil.move(str(tmp), str(final))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


__all__ = ["CompareSettings", "run_compare"]
