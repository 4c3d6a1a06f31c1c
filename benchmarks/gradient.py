"""What a gradient through the simulation costs: time (in simulations) and peak memory.

    python benchmarks/gradient.py [--batches 10,100,1000] [--duration 5.0]
        [--before PATH/TO/OTHER/CHECKOUT/src]

For the cube forward task (T = 5 s at the search step, dt = 1 ms, smoothed as `compare`
smooths it) and each batch size, in a fresh process: the wall time of one
`jaxmotion.fitness_and_gradient` call against `task.evaluate` on the same batch (both
compiled first, medians of 3 calls; the ratio is what `compare` charges a gradient step),
the compile time of the gradient, and the process's peak memory (`VmHWM`). With `--before`,
every case runs a second time on the jaxmotion package under that path (e.g. a worktree of
an earlier commit: `git worktree add /tmp/before <commit>`), in the same sitting. Writes
`benchmarks/gradient.json`.
"""

import argparse
import json
import os
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


def _run(batch: int, duration: float, src: str | None) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = src  # ahead of the installed package
    out = subprocess.run(
        [sys.executable, "-c", RUN, str(batch), str(duration)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--batches", default="10,100,1000")
    p.add_argument("--duration", type=float, default=5.0)
    p.add_argument("--before", metavar="SRC", help="another checkout's src folder to compare")
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    rows = []
    print(f"cube, T = {args.duration:g} s, dt = 1 ms, 2 CPU devices")
    print(
        f"{'code':>6} {'B':>5} {'gradient s':>11} {'evaluate s':>11} {'ratio':>7} "
        f"{'compile s':>10} {'peak MB':>8}"
    )
    versions = [("this", None)] + ([("before", args.before)] if args.before else [])
    for batch in [int(b) for b in args.batches.split(",")]:
        for name, src in versions:
            row = {"code": name, **_run(batch, args.duration, src)}
            rows.append(row)
            print(
                f"{name:>6} {batch:>5} {row['gradient_s']:>11.2f} {row['evaluate_s']:>11.3f} "
                f"{row['ratio']:>7.1f} {row['gradient_compile_s']:>10.1f} "
                f"{row['peak_mb']:>8.0f}",
                flush=True,
            )
    Path(args.json).write_text(json.dumps({"settings": vars(args), "rows": rows}, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
