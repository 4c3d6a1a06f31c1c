"""The third paper's largest evolution, end to end: 20 generations of 2,000 spring nets for the
snake, as `configs/snake_travel.toml` sets it up (T = 5 s; torque-limited joints at a 1 ms
physics step, 5 ms control period; the paper's 40,000 simulations, of which evolve runs
32,400: survivors keep their fitness), timed from a fresh process (imports and compilation
included).

    python benchmarks/spring_nets.py [--runs 3] [--figure snake] [--generations 20] [--size 2000]

Each run is a new Python process (nothing compiled or cached in memory; the persistent
compilation cache is switched off), so the wall time is what a user waits for. Prints every
run and the medians; writes `benchmarks/spring_nets.json`.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

RUN = r"""
import json, sys, time
start = time.perf_counter()
import jaxmotion as jm
jm.use_cpu_cores()
import jax.random as jr
from jaxmotion.experiment import load_config
config, generations, size, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
task = load_config(config).task
figure = task.body
marks = []
setup = time.perf_counter()
result = jm.evolve(task, key=jr.key(seed), generations=generations, size=size,
                   callback=lambda s, h: marks.append((time.perf_counter(), len(h))))
end = time.perf_counter()
steady = sum(n for _, n in marks[2:])
print(json.dumps({
    "import_and_setup_s": setup - start,
    "first_two_generations_s": marks[min(1, len(marks) - 1)][0] - setup,
    "search_s": end - setup,
    "steady_evals_per_s": steady / (end - marks[1][0]) if len(marks) > 2 else None,
    "best_fitness": result.best_fitness,
    "best_body_lengths": result.best_fitness / figure.body_length,
    "evaluations": len(result.history),
}))
"""


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--figure", default="snake", choices=("snake", "luxo"))
    p.add_argument("--generations", type=int, default=20)
    p.add_argument("--size", type=int, default=2000)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    rows = []
    for run in range(args.runs):
        start = time.perf_counter()
        out = subprocess.run(
            [
                sys.executable,
                "-c",
                RUN,
                str(ROOT / "configs" / f"{args.figure}_travel.toml"),
                str(args.generations),
                str(args.size),
                str(run),
            ],
            capture_output=True,
            text=True,
            check=True,
            env=env,
        )
        wall = time.perf_counter() - start
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["wall_s"] = wall
        rows.append(row)
        print(
            f"run {run}: {wall:5.1f} s wall (import+setup {row['import_and_setup_s']:.1f} s, "
            f"search {row['search_s']:.1f} s of which the first two generations "
            f"{row['first_two_generations_s']:.1f} s, then {row['steady_evals_per_s']:.0f} "
            f"evals/s); {row['evaluations']} evaluations, best "
            f"{row['best_body_lengths']:.1f} body lengths",
            flush=True,
        )
    median = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(
        f"median wall time {median['wall_s']:.1f} s (search {median['search_s']:.1f} s) for "
        f"{args.generations} generations of {args.size} ({args.figure}, configs/{args.figure}_travel.toml)"
    )
    Path(args.json).write_text(
        json.dumps({"settings": vars(args), "runs": rows, "median": median}, indent=2) + "\n"
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
