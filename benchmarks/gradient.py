"""What a gradient through the simulation costs: time (in simulations) and peak memory.

    python benchmarks/gradient.py [--batches 10,100] [--duration 5.0]

For the cube forward task (T = 5 s at the search step, dt = 1 ms, smoothed as `compare`
smooths it) and each batch size, in a fresh process: the wall time of one
`jaxmotion.fitness_and_gradient` call against `task.evaluate` on the same batch (both
compiled first; the ratio is what `compare` charges a gradient step), the compile time of
the gradient, and the process's peak memory (`VmHWM`). Writes `benchmarks/gradient.json`.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

RUN = r"""
import json, sys, time
import jaxmotion as jm
jm.use_cpu_cores()
import jax, jax.random as jr
batch, duration = int(sys.argv[1]), float(sys.argv[2])
task = jm.Task(jm.lattices.cube(), jm.World(), jm.RegimesSpace(4, 1.0),
               jm.Objective({"forward": 1.0, "upright": -10.0}), duration=duration)
params = task.sample(batch, key=jr.key(0))
smoothing = jm.Smoothing(regime_width=0.05, friction_velocity=0.1)
start = time.perf_counter()
jax.block_until_ready(jm.fitness_and_gradient(task, params, smoothing=smoothing))
compile_s = time.perf_counter() - start
def timed(fn, repeats=3):
    runs = []
    for _ in range(repeats):
        t = time.perf_counter(); jax.block_until_ready(fn()); runs.append(time.perf_counter() - t)
    return sorted(runs)[len(runs) // 2]
grad_s = timed(lambda: jm.fitness_and_gradient(task, params, smoothing=smoothing))
task.evaluate(params).block_until_ready()
eval_s = timed(lambda: task.evaluate(params))
peak_kb = int(open("/proc/self/status").read().split("VmHWM:")[1].split()[0])
print(json.dumps({"batch": batch, "gradient_s": grad_s, "evaluate_s": eval_s,
                  "ratio": grad_s / eval_s, "gradient_compile_s": compile_s,
                  "peak_mb": peak_kb / 1024}))
"""


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--batches", default="10,100")
    p.add_argument("--duration", type=float, default=5.0)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    rows = []
    print(f"cube, T = {args.duration:g} s, dt = 1 ms, 2 CPU devices")
    print(
        f"{'B':>5} {'gradient s':>11} {'evaluate s':>11} {'ratio':>7} {'compile s':>10} {'peak MB':>8}"
    )
    for batch in [int(b) for b in args.batches.split(",")]:
        out = subprocess.run(
            [sys.executable, "-c", RUN, str(batch), str(args.duration)],
            capture_output=True,
            text=True,
            check=True,
        )
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"{batch:>5} {row['gradient_s']:>11.2f} {row['evaluate_s']:>11.3f} "
            f"{row['ratio']:>7.0f} {row['gradient_compile_s']:>10.1f} {row['peak_mb']:>8.0f}"
        )
    Path(args.json).write_text(json.dumps({"settings": vars(args), "rows": rows}, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
