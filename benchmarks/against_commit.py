"""`Task.evaluate` of this working tree against another commit's, in one process.

    python benchmarks/against_commit.py HEAD~1                    # cube, Star-Man, Rex
    python benchmarks/against_commit.py 6437ff9 --tasks cube --batches 100,1000 --rounds 15

The other commit's `src/jaxmotion` is exported (`git archive`) into a temporary folder as the
package `jaxmotion_base` and imported beside this tree's `jaxmotion`; both evaluate the same
task (same body, controller family, objective, duration and step) at each batch size, their
calls alternating (old, new, new, old, ...) so that the machine's drifts of speed hit both
alike. On a shared machine one process's speed drifts by tens of percent over a minute; the
alternation and the ratio of medians are what make a comparison of a few percent possible.
Prints evaluations per second (median and best of `--rounds` calls each) and the ratio
new / base, and writes `benchmarks/against_commit.json`.
"""

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def export(rev: str, into: Path) -> None:
    """`rev`'s `src/jaxmotion`, as the package `jaxmotion_base` under `into`."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", rev, "src/jaxmotion"],
        capture_output=True,
        check=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    package = into / "jaxmotion_base"
    shutil.move(str(into / "src" / "jaxmotion"), str(package))
    main = package / "__main__.py"
    main.write_text(main.read_text().replace("from jaxmotion.", "from jaxmotion_base."))


def make_task(lib, name: str):
    if name in ("cube", "pyramid", "chair"):
        return lib.Task(
            getattr(lib.lattices, name)(),
            lib.World(),
            lib.RegimesSpace(4, 1.0),
            lib.Objective({"forward": 1.0, "upright": -10.0}),
            duration=5.0,
            dt=1e-3,
        )
    figure = getattr(lib.figures, name)()
    return lib.Task(
        figure,
        lib.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1),
        lib.TimeBSRSpace(figure, num_rules=4, t_per=1.0, tau_min=0.05, tau_max=1.25),
        lib.Objective({"forward": 1.0}),
        duration=5.0,
        dt=0.005,
    )


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("rev", help="the commit to compare against (e.g. HEAD~1)")
    p.add_argument("--tasks", default="cube,star_man,rex")
    p.add_argument("--batches", default="100,1000")
    p.add_argument("--rounds", type=int, default=11)
    p.add_argument("--json", default=str(HERE / "against_commit.json"))
    args = p.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        export(args.rev, Path(tmp))
        sys.path.insert(0, tmp)
        import jaxmotion as new

        new.use_cpu_cores()
        import jax.random as jr
        import jaxmotion_base as base

        rows = []
        print(f"this tree against {args.rev}: evals/s, median (best) of {args.rounds} calls")
        for name in args.tasks.split(","):
            tasks = {"base": make_task(base, name), "new": make_task(new, name)}
            for batch in [int(b) for b in args.batches.split(",")]:
                params = {k: t.sample(batch, key=jr.key(1)) for k, t in tasks.items()}
                first = {}
                for k, task in tasks.items():
                    start = time.perf_counter()
                    task.evaluate(params[k]).block_until_ready()
                    first[k] = time.perf_counter() - start
                times = {"base": [], "new": []}
                for r in range(args.rounds):
                    for k in ("base", "new") if r % 2 == 0 else ("new", "base"):
                        start = time.perf_counter()
                        tasks[k].evaluate(params[k]).block_until_ready()
                        times[k].append(time.perf_counter() - start)
                med = {k: statistics.median(v) for k, v in times.items()}
                best = {k: min(v) for k, v in times.items()}
                row = {
                    "task": name,
                    "batch": batch,
                    **{f"{k}_evals_per_s": batch / med[k] for k in med},
                    **{f"{k}_best_evals_per_s": batch / best[k] for k in best},
                    "ratio_median": med["base"] / med["new"],
                    "ratio_best": best["base"] / best["new"],
                    **{f"{k}_first_call_s": first[k] for k in first},
                }
                rows.append(row)
                print(
                    f"{name:9} B={batch:5d}: base {row['base_evals_per_s']:7.0f} "
                    f"({row['base_best_evals_per_s']:7.0f}), new {row['new_evals_per_s']:7.0f} "
                    f"({row['new_best_evals_per_s']:7.0f}); new/base {row['ratio_median']:.3f} "
                    f"({row['ratio_best']:.3f}); first call base {first['base']:.1f} s, new "
                    f"{first['new']:.1f} s",
                    flush=True,
                )
    Path(args.json).write_text(json.dumps({"rev": args.rev, "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
