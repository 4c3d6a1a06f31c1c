"""jaxmotion's cube evaluation against other frameworks' kernels of the same model, interleaved.

    python benchmarks/peers.py --peers-python .peers/bin/python            # 2 rounds
    python benchmarks/peers.py --peers-python .peers/bin/python --rounds 3 --impls numba_simd64

The peers are perf-lab's `peers/bench_peers.py` (`../shared/perf-lab` beside this checkout,
or `--perf-lab`): the cube lattice (8 masses, 28 springs, floor, anisotropic tanh friction,
a 4-regime controller) hand-written in Numba (`numba_simd64`: 64 controllers as SIMD lanes
per thread, the fastest) and Taichi (`taichi_kernel`), float32, dt = 1 ms, T = 5 s, timed as
the median of 5 calls after a compiling one, on 2 threads. They need Numba, Taichi and SciPy,
which jaxmotion does not depend on: give a Python that has them, e.g.

    python -m venv .peers && .peers/bin/pip install numba taichi scipy

Each round runs, each in a fresh process, jaxmotion's `benchmarks/evaluate.py --lattices cube
--batches 100,1000 --dts 0.001` (`Task.evaluate`, every device, the objective and the saving
included, as in a search) and then the peers' script (`--nocheck`), so the machine's drifts of
speed over a sitting hit both alike. The peers' script runs on a copy of perf-lab in a temporary
folder (it appends to a results file beside itself). Prints evaluations per second, each
implementation's range over the rounds, and jaxmotion's ratio to each peer per round; writes
`benchmarks/peers.json`. Figures count only within one sitting on one machine.
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
OURS = "jaxmotion Task.evaluate"
BENCH_LINE = re.compile(r"^bench (\S+)\s+B=\s*(\d+) evals/s\s+([0-9.]+)")


def ours(batches: list[int], repeats: int) -> dict[int, float]:
    """Evaluations per second of `Task.evaluate` on the cube at dt = 1 ms, from a fresh
    process running `benchmarks/evaluate.py`."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "evaluate.json"
        cmd = [
            sys.executable,
            str(HERE / "evaluate.py"),
            "--lattices=cube",
            f"--batches={','.join(map(str, batches))}",
            "--dts=0.001",
            f"--repeats={repeats}",
            "--no-numpy",
            "--no-vmap",
            "--no-memory",
            "--no-perf-lab",
            "--no-overhead",
            f"--json={out}",
        ]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            tail = "\n".join((done.stdout + done.stderr).splitlines()[-15:])
            raise SystemExit(f"evaluate.py failed (exit code {done.returncode}):\n{tail}")
        rows = json.loads(out.read_text())["rows"]
    return {row["batch"]: row["evaluate"] for row in rows}


def peers(python: str, perf_lab: Path, impls: list[str]) -> dict[str, dict[int, float]]:
    """Evaluations per second of each peer at each batch size (the script's own B = 100
    and 1000), from its own run."""
    with tempfile.TemporaryDirectory() as tmp:
        lab = Path(tmp) / "perf-lab"
        shutil.copytree(perf_lab, lab, ignore=shutil.ignore_patterns("*.jsonl", "__pycache__"))
        cmd = [python, str(lab / "peers" / "bench_peers.py"), *impls, "--nocheck"]
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=lab / "peers")
    rates: dict[str, dict[int, float]] = {}
    for line in done.stdout.splitlines():
        match = BENCH_LINE.match(line)
        if match:
            rates.setdefault(match[1], {})[int(match[2])] = float(match[3])
    missing = [impl for impl in impls if impl not in rates]
    if done.returncode != 0 or missing:
        tail = "\n".join((done.stdout + done.stderr).splitlines()[-15:])
        raise SystemExit(
            f"the peers' script failed (exit code {done.returncode}; no figures for "
            f"{', '.join(missing) or 'none missing'}):\n{tail}\n"
            f"Does {python} have numba, taichi and scipy? See this script's docstring."
        )
    return rates


def span(values: list[float]) -> str:
    low, high = min(values), max(values)
    return f"{low:,.0f}" if round(low) == round(high) else f"{low:,.0f}-{high:,.0f}"


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--peers-python",
        default=sys.executable,
        help="a Python with numba, taichi and scipy (default: this one)",
    )
    p.add_argument("--perf-lab", default=str(HERE.parent.parent / "shared" / "perf-lab"))
    p.add_argument("--impls", default="numba_simd64,taichi_kernel")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5, help="timed calls of ours per batch")
    p.add_argument("--json", default=str(HERE / "peers.json"))
    args = p.parse_args()
    perf_lab = Path(args.perf_lab)
    if not (perf_lab / "peers" / "bench_peers.py").is_file():
        raise SystemExit(f"--perf-lab {perf_lab}: no peers/bench_peers.py there")
    if args.rounds < 1:
        raise SystemExit(f"--rounds {args.rounds}; allowed: a whole number >= 1")
    impls = [s for s in args.impls.split(",") if s]
    batches = [100, 1000]  # the peers' script's own batch sizes

    rounds = []
    for k in range(args.rounds):
        row = {OURS: ours(batches, args.repeats)}
        row.update(peers(args.peers_python, perf_lab, impls))
        for name in [OURS, *impls]:
            rates = ", ".join(f"B={b}: {row[name][b]:,.0f}" for b in batches)
            print(f"round {k + 1}: {name} {rates}")
        rounds.append(row)

    print(f"\nEvaluations per second of the cube at dt = 1 ms, float32, {os.cpu_count()} cores, ")
    print(f"ranges over {args.rounds} interleaved rounds:\n")
    print("| | " + " | ".join(f"B = {b:,}" for b in batches) + " |")
    print("|---|" + "---|" * len(batches))
    for name in [*impls, OURS]:
        cells = [span([r[name][b] for r in rounds]) for b in batches]
        print(f"| {name} | " + " | ".join(cells) + " |")
    for impl in impls:
        cells = [", ".join(f"{r[OURS][b] / r[impl][b]:.2f}" for r in rounds) for b in batches]
        print(f"| ratio jaxmotion / {impl}, each round | " + " | ".join(cells) + " |")
    Path(args.json).write_text(
        json.dumps(
            {
                "batches": batches,
                "rounds": [
                    {name: {str(b): v for b, v in r.items()} for name, r in row.items()}
                    for row in rounds
                ],
                "cpus": os.cpu_count(),
            },
            indent=2,
        )
        + "\n"
    )
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
