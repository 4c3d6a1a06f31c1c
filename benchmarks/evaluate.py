"""Throughput of `Task.evaluate` (evaluations per second) against the plain `jax.vmap` of the
single-controller simulation, measured in the same run.

    python benchmarks/evaluate.py [--batches 1,100,1000] [--lattices cube] [--repeats 5]

One evaluation is one simulation of `--duration` seconds (default 5 s) at `--dt` (default
1 ms) of a 4-regime controller, scored by forward + upright. Prints a table of medians and
writes every figure to `benchmarks/evaluate.json` (or `--json PATH`) for comparison across
commits. The batch is sharded over one CPU device per core, as the CLI does.
"""

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import jaxmotion as jm


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--batches", default="1,100,1000")
    p.add_argument("--lattices", default="cube")
    p.add_argument("--duration", type=float, default=5.0)
    p.add_argument("--dt", type=float, default=1e-3)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-baseline", action="store_true", help="skip the plain vmap baseline")
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    jm.use_cpu_cores()

    import jax
    import jax.random as jr

    builders = {
        "cube": jm.lattices.cube,
        "pyramid": jm.lattices.pyramid,
        "chair": jm.lattices.chair,
    }
    rows = []
    for name in args.lattices.split(","):
        task = jm.Task(
            builders[name](),
            jm.World(),
            jm.RegimesSpace(4, 1.0),
            jm.Objective({"forward": 1.0, "upright": -10.0}),
            duration=args.duration,
            dt=args.dt,
        )
        plain = jax.jit(
            jax.vmap(
                lambda c, task=task: task.objective(
                    jm.simulate(task.body, c, task.world, task.duration, dt=task.dt)
                )
            )
        )
        for batch in [int(b) for b in args.batches.split(",")]:
            params = task.sample(batch, key=jr.key(0))
            row = {"lattice": name, "batch": batch}
            for label, fn in [("evaluate", task.evaluate)] + (
                [] if args.no_baseline else [("plain_vmap", plain)]
            ):
                start = time.perf_counter()
                fn(params).block_until_ready()
                compile_s = time.perf_counter() - start
                times = []
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    fn(params).block_until_ready()
                    times.append(time.perf_counter() - start)
                row[f"{label}_evals_per_s"] = [batch / t for t in times]
                row[f"{label}_median"] = batch / statistics.median(times)
                row[f"{label}_first_call_s"] = compile_s
            if not args.no_baseline:
                row["ratio_to_plain_vmap"] = row["evaluate_median"] / row["plain_vmap_median"]
            rows.append(row)
            base = (
                ""
                if args.no_baseline
                else (
                    f"  plain vmap {row['plain_vmap_median']:8.0f}/s"
                    f"  ratio {row['ratio_to_plain_vmap']:5.2f}"
                )
            )
            print(
                f"{name:8s} B={batch:6d}  evaluate {row['evaluate_median']:8.0f} evals/s "
                f"(first call {row['evaluate_first_call_s']:.1f} s){base}",
                flush=True,
            )
    meta = {
        "devices": len(jax.devices()),
        "jax": jax.__version__,
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "duration": args.duration,
        "dt": args.dt,
        "repeats": args.repeats,
    }
    Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
