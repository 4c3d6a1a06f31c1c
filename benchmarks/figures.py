"""Throughput of `Task.evaluate` for articulated figures (the second paper's characters).

A 1,000-step evaluation (T = 5 s at dt = 5 ms) of Star-Man, Cujo and Rex with random
time-based BSR controllers (R = 4), and of Star-Man and Bob with random sense-based ones
(R = 10, the paper's, over Star-Man's 12 senses and Bob's 40), at B = 1, 100 and 1000, on every CPU core (one JAX device per
core), each in a fresh process so its compile time is its own.

    python benchmarks/figures.py            # the table, and benchmarks/figures.json
    python benchmarks/figures.py --quick    # B = 1 and 100, one timed call

For scale, the paper's own figure: 3.3/s for Rex (0.3 s per evaluation on a DEC 3000/400).
Other engines' figures belong beside ours only when measured on the same machine in the same
sitting (`../shared/perf-lab/peers/`), so none is quoted here.
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

CASES = (
    ("star_man", "time_bsr"),
    ("star_man", "sense_bsr"),
    ("cujo", "time_bsr"),
    ("rex", "time_bsr"),
    ("bob", "sense_bsr"),
)
PAPER_REX = 3.3  # evaluations/s, paper 004 (0.3 s per evaluation on a DEC 3000/400)
DT, DURATION = 0.005, 5.0


def child(name: str, family: str, batches: list[int], repeats: int) -> dict:
    import jax
    import jax.random as jr

    import jaxmotion as jm

    jm.use_cpu_cores()
    fig = getattr(jm.figures, name)()
    if family == "sense_bsr":
        space = jm.SenseBSRSpace(fig, num_rules=10, tau_min=0.05, tau_max=DURATION / 4)
    else:
        space = jm.TimeBSRSpace(fig, num_rules=4, t_per=1.0, tau_min=0.05, tau_max=DURATION / 4)
    task = jm.Task(
        fig,
        jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1),
        space,
        jm.Objective({"forward": 1.0}),
        duration=DURATION,
        dt=DT,
    )
    out = {
        "figure": name,
        "family": family,
        "devices": len(jax.devices()),
        "steps": round(DURATION / DT),
        "B": {},
    }
    for b in batches:
        first = task.sample(b, key=jr.key(0))
        start = time.perf_counter()
        task.evaluate(first).block_until_ready()
        first_call = time.perf_counter() - start
        times = []
        for k in range(repeats):
            params = task.sample(b, key=jr.key(k + 1))
            start = time.perf_counter()
            fitness = task.evaluate(params).block_until_ready()
            times.append(time.perf_counter() - start)
        steady = statistics.median(times)
        out["B"][b] = {
            "evals_per_s": b / steady,
            "seconds_per_call": steady,
            "compile_s": max(0.0, first_call - steady),
            "finite_share": float((fitness > -float("inf")).mean()),
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="B = 1, 100 and one timed call")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    batches = [1, 100] if args.quick else [1, 100, 1000]
    repeats = 1 if args.quick else 3
    if args.child:
        name, family = args.child.split(":")
        print(json.dumps(child(name, family, batches, repeats)))
        return
    results = []
    for name, family in CASES:
        cmd = [sys.executable, __file__, "--child", f"{name}:{family}"]
        cmd += ["--quick"] if args.quick else []
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(
        f"Task.evaluate, {round(DURATION / DT)} steps (T = {DURATION} s, dt = {DT} s), "
        f"{results[0]['devices']} devices; evals/s (median of {repeats}), compile s"
    )
    print(f"{'figure':21s}" + "".join(f"{'B = ' + str(b):>16s}" for b in batches))
    for r in results:
        cells = "".join(
            f"{r['B'][str(b)]['evals_per_s']:9.0f} ({r['B'][str(b)]['compile_s']:4.1f} s)"
            for b in batches
        )
        print(f"{r['figure'] + ' ' + r['family']:21s}{cells}")
    star = {r["family"]: r for r in results if r["figure"] == "star_man"}
    for b in batches:
        ratio = (
            star["sense_bsr"]["B"][str(b)]["evals_per_s"]
            / star["time_bsr"]["B"][str(b)]["evals_per_s"]
        )
        compile_s = star["sense_bsr"]["B"][str(b)]["compile_s"]
        print(
            f"Star-Man sense_bsr / time_bsr at B = {b}: {ratio:.2f} (target >= 0.5); "
            f"compile {compile_s:.1f} s (target <= 5 s)"
        )
    bob = next(r for r in results if r["figure"] == "bob")
    top = bob["B"][str(batches[-1])]
    worst = max(cell["compile_s"] for cell in bob["B"].values())
    print(
        f"Bob sense_bsr at B = {batches[-1]}: {top['evals_per_s']:.0f} evals/s (target >= 1,500 "
        f"at B = 1000); compile, slowest batch size: {worst:.1f} s (target <= 10 s)"
    )
    rex = next(r for r in results if r["figure"] == "rex")
    worst = max(cell["compile_s"] for cell in rex["B"].values())
    print(f"Rex compile, slowest batch size: {worst:.1f} s (target <= 10 s)")
    top = rex["B"][str(batches[-1])]
    print(
        f"Rex at B = {batches[-1]}: {top['evals_per_s']:.0f} evals/s "
        f"({top['evals_per_s'] / PAPER_REX:.0f}x the paper's {PAPER_REX}/s)"
    )
    out = Path(__file__).with_suffix(".json")
    out.write_text(json.dumps({"results": results, "paper_rex": PAPER_REX}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
