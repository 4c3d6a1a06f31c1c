"""The warm start: `python -m jaxmotion run CONFIG` from a fresh process with an empty
persistent compilation cache (the first run) against the same command once the cache holds
that run's programs (the second run).

    python benchmarks/warm_start.py [--config configs/default.toml] [--repeats 3]
                                    [--evaluations N]

Cold and warm runs alternate (cold, warm, cold, warm, ...), each cold run with a new empty
cache folder that its warm run then reuses, so both kinds see the same machine load. Prints
every run and the medians of the wall time and of the CPU time (user + system): the CPU
time is the steadier figure on a machine that runs other work beside it.
"""

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(config: str, evaluations: int | None, cache: Path, out: Path) -> tuple[float, float]:
    """The run's wall time and CPU time (user + system, all its threads), in seconds."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["JAXMOTION_COMPILATION_CACHE"] = str(cache)
    command = [sys.executable, "-m", "jaxmotion", "run", config, "--quiet", "--no-animation"]
    command += ["--out", str(out)]
    if evaluations is not None:
        command += ["--evaluations", str(evaluations)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, env=env, cwd=ROOT, capture_output=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return wall, cpu


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--config", default="configs/default.toml")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--evaluations", type=int, help="override [search] evaluations")
    args = p.parse_args()
    cold, warm = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            cache = Path(tmp) / f"cache{i}"
            cold.append(_run(args.config, args.evaluations, cache, Path(tmp) / f"c{i}"))
            warm.append(_run(args.config, args.evaluations, cache, Path(tmp) / f"w{i}"))
            print(
                f"repeat {i}: first run {cold[-1][0]:.1f} s wall ({cold[-1][1]:.1f} s CPU), "
                f"second run {warm[-1][0]:.1f} s wall ({warm[-1][1]:.1f} s CPU)"
            )
    for k, kind in enumerate(("wall", "CPU")):
        c = statistics.median(x[k] for x in cold)
        w = statistics.median(x[k] for x in warm)
        print(
            f"{args.config}, {args.repeats} repeats, {kind} time: first run median {c:.1f} s, "
            f"second run median {w:.1f} s: {c - w:.1f} s saved ({100 * (c - w) / c:.0f}%)"
        )


if __name__ == "__main__":
    main()
