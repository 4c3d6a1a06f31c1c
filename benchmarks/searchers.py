"""The papers' searches against evosax's CMA-ES and OpenAI-ES on equal simulation budgets.

    python benchmarks/searchers.py [--budget 3000] [--seeds 5] [--population 32]
        [--configs configs/default.toml configs/starman_cartwheel.toml ...]

For each config: its own search (the paper's: hill climbing for the cube, serial search for
Star-Man), CMA-ES and OpenAI-ES, each on `--budget` simulations (random initial sets
included; `jaxmotion._cli.compare.budgeted`), from seeds 0..N-1. Reports per searcher the
median, min and max best fitness over the seeds, how many bests pass the config's motion
check (each best replayed with the search's own settings, as `run` does) and the wall time
(compilation included). Prints a Markdown table and writes `benchmarks/searchers.json`.

Needs the evosax extra: `pip install 'jaxmotion[evosax]'`.
"""

import argparse
import json
import statistics
import time
from pathlib import Path

CONFIGS = (
    "configs/default.toml",  # paper 000: the cube's regimes, parallel hill climbing
    "configs/starman_cartwheel.toml",  # paper 004: Star-Man's time-based rules, serial search
    "configs/starman_sense_shuffle.toml",  # paper 004: sense-based rules, serial search
)


def strategies(population: int) -> dict[str, dict]:
    """The evosax searchers compared, as [search] tables (the adapter's defaults otherwise)."""
    common = {"algorithm": "evosax", "population": population, "size": 100}
    return {
        "CMA-ES": {**common, "strategy": "CMA_ES"},
        "OpenAI-ES": {**common, "strategy": "Open_ES"},
    }


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--configs", nargs="+", default=list(CONFIGS))
    p.add_argument("--budget", type=int, default=3000, help="simulations per search")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--population", type=int, default=32, help="evosax population")
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()

    import jaxmotion as jm

    jm.use_cpu_cores()
    import tomllib

    from jaxmotion._cli.compare import run_searcher, search_label
    from jaxmotion.experiment import parse_config, run_check

    rows = []
    for path in args.configs:
        with open(path, "rb") as f:
            raw = tomllib.load(f)
        experiment = parse_config(raw, name=Path(path).stem)
        searches = {f"paper: {search_label(experiment.search)}": experiment.search}
        for label, table in strategies(args.population).items():
            searches[label] = parse_config({**raw, "search": table}).search
        for label, search in searches.items():
            start = time.perf_counter()
            bests, passed, used = [], 0, 0
            for seed in range(args.seeds):
                result, used = run_searcher(experiment, search, args.budget, seed)
                bests.append(result.best_fitness)
                verdict = run_check(experiment, experiment.task.simulate(result.best))
                passed += bool(verdict is not None and verdict.passed)
            row = {
                "config": path,
                "searcher": label,
                "simulations": used,
                "best": bests,
                "median": statistics.median(bests),
                "check": None if experiment.check is None else experiment.check,
                "passed": None if experiment.check is None else passed,
                "wall_s": time.perf_counter() - start,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)

    print()
    print(
        f"| config | searcher | simulations | median best | min | max | check passed "
        f"({args.seeds} seeds) | wall (s) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        check = "-" if r["check"] is None else f"{r['passed']} / {args.seeds} ({r['check']})"
        print(
            f"| {Path(r['config']).stem} | {r['searcher']} | {r['simulations']} | "
            f"{r['median']:.4g} | {min(r['best']):.4g} | {max(r['best']):.4g} | {check} | "
            f"{r['wall_s']:.0f} |"
        )
    Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
