"""What a composite's components tolerate: each transition of a searched composite moved by
a few ticks, and whether every phase still passes its component's check. The second paper
makes its controllers robust so that a composite survives imprecise transitions; this
measures it on results folders of `python -m jaxmotion compose`.

    .venv/bin/python benchmarks/composite_tolerance.py results/starman-composite-*
    .venv/bin/python benchmarks/composite_tolerance.py FOLDER... --moves=-8,-4,-2,2,4,8

For every folder, every transition in turn is moved by each of `--moves` ticks (the others
kept where the search put them; a move that leaves a phase shorter than a tick is skipped),
the composite re-simulated, and each phase checked as `compose` checks it. Prints one line a
folder and the totals (cases where all phases pass / cases); writes
`benchmarks/composite_tolerance.json` (or `--json`).
"""

import argparse
import json
from pathlib import Path

import numpy as np


def _failed(report: dict) -> list[str]:
    """The phases whose check did not pass (or could not run) in a `compose` report."""
    return [name for name, check in report["checks"].items() if not (check and check["passed"])]


def tolerance(folder: Path, moves: list[int]) -> dict:
    """The searched transitions of one compose results folder, each moved by `moves` ticks."""
    from jaxmotion._cli.compose import _report, read_compose_config

    compose = read_compose_config(folder / "config.toml")
    tick = compose.composite.tick
    duration = compose.composite.duration
    best = np.asarray(json.loads((folder / "best_transitions.json").read_text())["transitions"])
    cases = []
    for i in range(len(best)):
        for move in moves:
            moved = best.copy()
            moved[i] += move * tick
            bounds = np.concatenate([[0.0], moved, [duration]])
            if np.any(np.diff(bounds) < tick - 1e-6):
                continue
            failed = _failed(_report(compose, moved)[0])
            cases.append({"transition": i, "move": move, "passed": not failed, "failed": failed})
    return {
        "folder": str(folder),
        "seed": compose.seed,
        "searched_passes": not _failed(_report(compose, best)[0]),
        "cases": cases,
    }


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("folders", nargs="+", type=Path, help="results folders of `compose`")
    p.add_argument("--moves", default="-8,-4,-2,2,4,8", help="ticks, comma-separated")
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    import jaxmotion as jm

    jm.use_cpu_cores()
    moves = [int(m) for m in args.moves.split(",")]
    rows = []
    for folder in args.folders:
        row = tolerance(folder, moves)
        rows.append(row)
        kept = sum(c["passed"] for c in row["cases"])
        print(
            f"{folder} (seed {row['seed']}): searched composite passes "
            f"{row['searched_passes']}; moved: all phases pass in {kept} of "
            f"{len(row['cases'])}",
            flush=True,
        )
    kept = sum(c["passed"] for r in rows for c in r["cases"])
    total = sum(len(r["cases"]) for r in rows)
    print(f"\nmoves {moves} ticks: all phases pass in {kept} of {total} moved composites")
    Path(args.json).write_text(json.dumps({"moves": moves, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
