"""The first paper's whole search, end to end: 25,000 evaluations of the cube forward task by
parallel hill climbing, timed from a fresh process (imports and compilation included).

    python benchmarks/search.py [--runs 3] [--evaluations 25000] [--batch 500] [--dt ...]

Each run is a new Python process (nothing compiled or cached in memory), so the wall time is
what a user waits for. Prints every run and the medians; writes `benchmarks/search.json`.
The paper reports 66 minutes for this search on a 1995 workstation.
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

RUN = r"""
import json, sys, time
start = time.perf_counter()
import jaxmotion as jm
jm.use_cpu_cores()
import jax.random as jr
evaluations, batch, dt, seed = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
task = jm.Task(jm.lattices.cube(), jm.World(), jm.RegimesSpace(4, 1.0),
               jm.Objective({"forward": 1.0, "upright": -10.0}), duration=5.0, dt=dt)
marks = []
setup = time.perf_counter()
result = jm.parallel_hill_climb(task, key=jr.key(seed), evaluations=evaluations, size=100,
                                batch=batch, callback=lambda s, h: marks.append(time.perf_counter()))
end = time.perf_counter()
print(json.dumps({
    "import_and_setup_s": setup - start,
    "first_two_calls_s": marks[1] - setup,
    "search_s": end - setup,
    "steady_evals_per_s": (len(result.history) - 100 - batch) / (end - marks[1]),
    "best_fitness": result.best_fitness,
    "initial_best": float(result.history.fitness[:100].max()),
    "evaluations": len(result.history),
}))
"""


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--evaluations", type=int, default=25_000)
    p.add_argument("--batch", type=int, default=500)
    p.add_argument("--dt", type=float, default=None, help="step (default: the Task default)")
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    if args.dt is None:
        import inspect

        import jaxmotion as jm

        args.dt = inspect.signature(jm.Task).parameters["dt"].default
    rows = []
    for run in range(args.runs):
        start = time.perf_counter()
        out = subprocess.run(
            [
                sys.executable,
                "-c",
                RUN,
                str(args.evaluations),
                str(args.batch),
                str(args.dt),
                str(run),
            ],
            capture_output=True,
            text=True,
            check=True,
        )
        wall = time.perf_counter() - start
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["wall_s"] = wall
        rows.append(row)
        print(
            f"run {run}: {wall:5.1f} s wall (import+setup {row['import_and_setup_s']:.1f} s, first two "
            f"calls {row['first_two_calls_s']:.1f} s, then {row['steady_evals_per_s']:.0f} evals/s); "
            f"best fitness {row['best_fitness']:.2f} (best random {row['initial_best']:.2f})",
            flush=True,
        )
    median = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(
        f"median wall time {median['wall_s']:.1f} s for {args.evaluations} evaluations "
        f"(batch {args.batch}, dt {args.dt * 1e3:g} ms); the paper: 66 minutes"
    )
    Path(args.json).write_text(
        json.dumps({"settings": vars(args), "runs": rows, "median": median}, indent=2) + "\n"
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
