"""Do the motions the search finds survive accurate physics? Each config is searched from
seeds 0-4 (the CLI, in a fresh process, its own budget), then the best controller is
replayed in float64 by an adaptive solver at tight tolerances (Dopri5, rtol 1e-8, atol
1e-10 by default): the table gives, per run, the fitness the search recorded, the fitness of
the accurate replay, the share kept, and the check's verdict on each.

    .venv/bin/python benchmarks/accurate_replay.py                   # the paper-000 configs
    .venv/bin/python benchmarks/accurate_replay.py configs/spider_leap.toml --seeds 0-2
    .venv/bin/python benchmarks/accurate_replay.py --merge '[simulation]
    integrator_check = 0.5'                                           # a config option on

`--merge` is TOML merged into every config before it runs (a table's keys are set one by
one), so the same script measures a search option before and after. Writes
`benchmarks/accurate_replay.json` (or `--json`).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parents[1]
PAPER_000 = ("configs/spider_leap.toml", "configs/poodle_somersault.toml")
PAPER_000 += ("configs/table_pirouette.toml",)


def _merged(config: Path, merge: dict) -> dict:
    data = tomllib.loads(config.read_text())

    def into(base: dict, extra: dict) -> None:
        for key, value in extra.items():
            if isinstance(value, dict) and isinstance(base.get(key), dict):
                into(base[key], value)
            else:
                base[key] = value

    into(data, merge)
    return data


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def _search(config: Path, seed: int, out: Path) -> Path:
    command = [sys.executable, "-m", "jaxmotion", "run", str(config), "--seed", str(seed)]
    command += ["--no-animation", "--quiet", "--out", str(out)]
    subprocess.run(command, check=True, cwd=ROOT, capture_output=True, env=dict(os.environ))
    (folder,) = [p for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")]
    return folder


def _accurate(folder: Path, solver: str, rtol: float, atol: float) -> dict:
    import jax

    from jaxmotion.experiment import load_result, run_check

    with jax.enable_x64(True):
        experiment, controller = load_result(folder)
        controller = jax.tree_util.tree_map(
            lambda a: a.astype(float) if hasattr(a, "dtype") and a.dtype.kind == "f" else a,
            controller,
        )
        task = experiment.task
        trajectory = task.simulate(controller, solver=solver, rtol=rtol, atol=atol)
        fitness = float(task.objective(trajectory))
        check = run_check(experiment, trajectory)
    return {
        "fitness": fitness,
        "finite": bool(trajectory.finite),
        "check": None if check is None else bool(check.passed),
    }


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("configs", nargs="*", default=list(PAPER_000))
    p.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 0,2,3")
    p.add_argument("--merge", default="", help="TOML merged into every config")
    p.add_argument("--solver", default="dopri5", choices=["dopri5", "tsit5"])
    p.add_argument("--rtol", type=float, default=1e-8)
    p.add_argument("--atol", type=float, default=1e-10)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()
    import jaxmotion as jm

    jm.use_cpu_cores()
    merge = tomllib.loads(args.merge)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for config in args.configs:
            path = Path(tmp) / Path(config).name
            path.write_text(tomli_w.dumps(_merged(ROOT / config, merge)))
            for seed in _seeds(args.seeds):
                started = time.perf_counter()
                folder = _search(path, seed, Path(tmp) / f"{path.stem}-{seed}")
                search_s = time.perf_counter() - started
                summary = json.loads((folder / "summary.json").read_text())
                started = time.perf_counter()
                accurate = _accurate(folder, args.solver, args.rtol, args.atol)
                row = {
                    "config": config,
                    "seed": seed,
                    "search_s": search_s,
                    "replay_s": time.perf_counter() - started,
                    "fitness": summary["best_fitness"],
                    "check": (summary.get("check") or {}).get("passed"),
                    "accurate_fitness": accurate["fitness"],
                    "accurate_finite": accurate["finite"],
                    "accurate_check": accurate["check"],
                }
                row["kept"] = row["accurate_fitness"] / row["fitness"] if row["fitness"] else None
                rows.append(row)
                kept = "-" if row["kept"] is None else f"{100 * row['kept']:.0f}%"
                print(
                    f"{config} seed {seed}: fitness {row['fitness']:.4g} -> accurate "
                    f"{row['accurate_fitness']:.4g} ({kept} kept); check "
                    f"{row['check']} -> {row['accurate_check']} "
                    f"(search {search_s:.0f} s, replay {row['replay_s']:.0f} s)",
                    flush=True,
                )
    print(
        f"\nmerged: {args.merge!r}; replay: {args.solver} float64 rtol {args.rtol:g} "
        f"atol {args.atol:g}"
    )
    print("| config | runs | median kept | check passes (search) | check passes (accurate) |")
    print("|---|---|---|---|---|")
    for config in args.configs:
        mine = [r for r in rows if r["config"] == config]
        kept = [r["kept"] for r in mine if r["kept"] is not None]
        median = f"{100 * statistics.median(kept):.0f}%" if kept else "-"
        search = sum(bool(r["check"]) for r in mine)
        accurate = sum(bool(r["accurate_check"]) for r in mine)
        print(f"| {config} | {len(mine)} | {median} | {search} | {accurate} |")
    Path(args.json).write_text(json.dumps({"merge": args.merge, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
