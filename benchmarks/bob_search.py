"""Bob's sense-based search at the second paper's Figure 7 scale, end to end: the serial
search of `configs/bob_walk.toml` (100 climbers x 1,000 generations, R = 10 rules over
Bob's 40 senses, three rounds of enrichment: 100,000 evaluations of 1,000 steps), timed
from a fresh process (imports and compilation included).

    python benchmarks/bob_search.py [--runs 3] [--generations 1000]

Each run is a new Python process with its own seed (nothing compiled or cached in memory:
the persistent compilation cache is switched off), so the wall time is what a user waits
for. Prints every run and the medians; writes `benchmarks/bob_search.json`. Target: <= 3
minutes on 2 cores. The paper's figure for scale: about 3 evaluations per second for Rex
(0.3 s each on a DEC 3000/400), so this search would have taken it about 9 hours.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "bob_walk.toml"

RUN = r"""
import json, sys, time
start = time.perf_counter()
import jax.random as jr
import jaxmotion as jm
from jaxmotion.experiment import load_config
jm.use_cpu_cores()
config, generations, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
experiment = load_config(config)
s = experiment.search
marks = []
setup = time.perf_counter()
result = jm.serial_search(
    experiment.task, key=jr.key(seed), climbers=s["climbers"], generations=generations,
    reseed_every=s["reseed_every"], enrich=s["enrich"],
    callback=lambda state, parts: marks.append(time.perf_counter()),
)
end = time.perf_counter()
print(json.dumps({
    "import_and_setup_s": setup - start,
    "first_two_calls_s": marks[1] - setup,
    "search_s": end - setup,
    "steady_evals_per_s": s["climbers"] * (len(marks) - 2) / (end - marks[1]),
    "evaluations": len(result.history),
    "best_fitness": result.best_fitness,
}))
"""


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--generations", type=int, default=1000)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    rows = []
    for run in range(args.runs):
        start = time.perf_counter()
        cmd = [sys.executable, "-c", RUN, str(CONFIG), str(args.generations), str(run)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["wall_s"] = time.perf_counter() - start
        rows.append(row)
        print(
            f"run {run}: {row['wall_s']:5.1f} s wall for {row['evaluations']} evaluations "
            f"(import+setup {row['import_and_setup_s']:.1f} s, first two calls "
            f"{row['first_two_calls_s']:.1f} s, then {row['steady_evals_per_s']:.0f} evals/s); "
            f"best fitness {row['best_fitness']:.3f}",
            flush=True,
        )
    median = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(
        f"median wall time {median['wall_s']:.1f} s for {median['evaluations']:.0f} "
        f"evaluations (target <= 180 s on 2 cores)"
    )
    Path(args.json).write_text(
        json.dumps({"settings": vars(args), "runs": rows, "median": median}, indent=2) + "\n"
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
