"""Every shipped config's best controller, replayed by every solver.

Runs each config's search (its own seed and budget; `--runs N` for N independent runs of a
serial search), then replays each run's best with the search's fixed-step solver and with
the adaptive solvers (Tsit5, Dopri5, default tolerances), and prints, per run, the fitness
each gives, whether the motion stayed finite and the check's verdict. The adaptive replays
are a different discretisation of a chaotic motion: their fitness differs from the search's,
but it must be finite.

    .venv/bin/python benchmarks/replay.py                      # every config in configs/
    .venv/bin/python benchmarks/replay.py configs/spider_leap.toml --runs 5
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jaxmotion as jm

jm.use_cpu_cores()

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402

from jaxmotion._cli.results import _run_search, fitness_of  # noqa: E402
from jaxmotion.experiment import load_config, run_check  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SOLVERS = ("symplectic", "tsit5", "dopri5")


def replay(path: Path, runs: int) -> list[dict]:
    experiment = load_config(path)
    if experiment.search["algorithm"] == "serial_search":
        experiment.search["runs"] = runs
    started = time.perf_counter()
    result, _ = _run_search(experiment, progress=False)
    search_s = time.perf_counter() - started
    task = experiment.task
    rows = []
    for i, r in enumerate(getattr(result, "runs", (result,))):
        row = {"config": path.stem, "run": i, "search_s": round(search_s, 1)}
        row["recorded"] = float(r.best_fitness)
        for solver in SOLVERS:
            trajectory = task.simulate(r.best, solver=solver)
            if solver == "symplectic":
                fitness = fitness_of(task, r.best)
            else:
                fitness = float(task.objective(trajectory))
            check = run_check(experiment, trajectory)
            row[solver] = {
                "fitness": round(fitness, 4),
                "finite": bool(trajectory.finite),
                "check": None if check is None else bool(check.passed),
            }
        rows.append(row)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("configs", nargs="*", type=Path)
    parser.add_argument("--runs", type=int, default=1, help="runs of each serial search")
    args = parser.parse_args()
    configs = args.configs or sorted((ROOT / "configs").glob("*.toml"))
    print(f"float: {jnp.result_type(float)}; key: {jr.key(0).dtype}", flush=True)
    bad = 0
    rows = []
    for path in configs:
        for row in replay(path, args.runs):
            rows.append(row)
            cells = "  ".join(
                f"{s} {row[s]['fitness']:9.4f} {'finite' if row[s]['finite'] else 'NOT FINITE'}"
                f" check={row[s]['check']}"
                for s in SOLVERS
            )
            print(f"{row['config']:24s} run {row['run']}  recorded {row['recorded']:9.4f}  {cells}")
            sys.stdout.flush()
            bad += sum(not row[s]["finite"] for s in SOLVERS)
    out = Path(__file__).with_suffix(".json")
    out.write_text(json.dumps(rows, indent=1))
    print(f"{bad} non-finite replays; written {out.name}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
