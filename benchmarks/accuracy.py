"""Which fixed step can the search use? Accuracy of `Task.evaluate`'s fitness against a
tight adaptive fifth-order reference, as a ranking (what a search needs).

    python benchmarks/accuracy.py [--controllers 256] [--dts 0.0005,0.001,0.002,...]

For `--controllers` random controllers of the cube forward task (forward + upright, 5 s), the
reference fitness comes from Tsit5 in float64 at `--rtol`/`--atol`; then for every candidate
step, the search path (semi-implicit Euler, float32, `Task.evaluate`) scores the same
controllers. Contact-rich motion is chaotic, so individual fitness values move with any
change of rounding; what matters is the ranking: the table gives Spearman's rank correlation
with the reference, the overlap of the top 10, and runs that blew up (non-finite). The chosen
step is the largest with rank correlation >= `--threshold` and no more non-finite runs than
the reference. Results go to `benchmarks/accuracy.json`.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--controllers", type=int, default=256)
    p.add_argument("--duration", type=float, default=5.0)
    p.add_argument("--dts", default="0.0005,0.001,0.0015,0.002,0.0025,0.003,0.004,0.005")
    p.add_argument("--rtol", type=float, default=1e-7)
    p.add_argument("--atol", type=float, default=1e-9)
    p.add_argument("--threshold", type=float, default=0.95)
    p.add_argument("--nudges", default="1e-9,1e-6", help="start displacements, m")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()

    import jaxmotion as jm

    jm.use_cpu_cores()
    import jax
    import jax.random as jr

    def make_task(dt):
        return jm.Task(
            jm.lattices.cube(),
            jm.World(),
            jm.RegimesSpace(4, 1.0),
            jm.Objective({"forward": 1.0, "upright": -10.0}),
            duration=args.duration,
            dt=dt,
        )

    # The controllers, drawn once in float32 and used by both paths.
    params32 = make_task(1e-3).sample(args.controllers, key=jr.key(args.seed))
    host = jax.tree_util.tree_map(np.asarray, params32)

    start = time.perf_counter()
    with jax.enable_x64(True):
        task64 = make_task(1e-3)
        params64 = jax.tree_util.tree_map(
            lambda a: jax.numpy.asarray(
                a, float if np.issubdtype(a.dtype, np.floating) else a.dtype
            ),
            host,
        )

        def adaptive(rtol, atol, nudge=0.0):
            x0, v0 = task64.body.initial_state()
            move = nudge * np.random.default_rng(args.seed).standard_normal(x0.shape)

            @jax.jit
            def fitness(p):
                trajectory = jm.simulate(
                    task64.body,
                    p,
                    task64.world,
                    task64.duration,
                    solver="tsit5",
                    rtol=rtol,
                    atol=atol,
                    dt=1e-4,
                    max_steps=400_000,
                    initial_state=(x0 + move, v0),
                )
                return task64.objective(trajectory)

            return fitness

        reference = adaptive(args.rtol, args.atol)

        def run(fn):
            chunks = []
            for lo in range(0, args.controllers, 32):
                part = jax.tree_util.tree_map(lambda a, lo=lo: a[lo : lo + 32], params64)
                chunks.append(np.asarray(jax.vmap(fn)(part)))
            return np.concatenate(chunks)

        ref = run(reference)
        ref_seconds = time.perf_counter() - start
        ref_bad = int(np.sum(~np.isfinite(ref)))
        print(
            f"reference: Tsit5 float64 rtol={args.rtol:g} atol={args.atol:g}, "
            f"{args.controllers} controllers in {ref_seconds:.0f} s, {ref_bad} non-finite"
        )
        print("the chaos floor, what the reference solver itself agrees to:")
        floor = []
        variants = [("100x looser tolerances", adaptive(args.rtol * 100, args.atol * 100))]
        variants += [
            (f"start moved by {float(m):g} m", adaptive(args.rtol, args.atol, float(m)))
            for m in args.nudges.split(",")
        ]
        for label, fn in variants:
            other = run(fn)
            ok = np.isfinite(other) & np.isfinite(ref)
            rho = spearman(other[ok], ref[ok])
            err = float(np.median(np.abs(other[ok] - ref[ok])))
            floor.append(dict(variant=label, spearman=rho, median_abs_error=err))
            print(f"  {label:28s} spearman {rho:.3f}, median |err| {err:.2g}")
    print(
        f"{'dt (ms)':>8} {'non-finite':>10} {'spearman':>9} {'top-10':>7} {'median |err|':>13} {'evals/s':>8} {'f32 vs f64':>11}"
    )
    rows = []
    top_ref = set(np.argsort(-np.where(np.isfinite(ref), ref, -np.inf))[:10])
    for dt in [float(s) for s in args.dts.split(",")]:
        task = make_task(dt)
        fitness = np.asarray(task.evaluate(params32))  # compiles
        start = time.perf_counter()
        fitness = np.asarray(task.evaluate(params32))
        seconds = time.perf_counter() - start
        ok = np.isfinite(fitness) & np.isfinite(ref)
        rho = spearman(fitness[ok], ref[ok])
        top = len(top_ref & set(np.argsort(-np.where(np.isfinite(fitness), fitness, -np.inf))[:10]))
        bad = int(np.sum(~np.isfinite(fitness)))
        err = float(np.median(np.abs(fitness[ok] - ref[ok])))
        with jax.enable_x64(True):
            fitness64 = np.asarray(make_task(dt).evaluate(params64))
        ok = np.isfinite(fitness) & np.isfinite(fitness64)
        rounding = spearman(fitness[ok], fitness64[ok])
        rows.append(
            dict(
                dt=dt,
                nonfinite=bad,
                spearman=rho,
                top10=top,
                median_abs_error=err,
                evals_per_s=args.controllers / seconds,
                float32_vs_float64_spearman=rounding,
            )
        )
        print(
            f"{dt * 1e3:8.2f} {bad:10d} {rho:9.3f} {top:5d}/10 {err:13.4f} {args.controllers / seconds:8.0f} {rounding:11.3f}",
            flush=True,
        )
    good = [r for r in rows if r["spearman"] >= args.threshold and r["nonfinite"] <= ref_bad]
    chosen = max((r["dt"] for r in good), default=None)
    print(
        f"accuracy-matched step: {chosen * 1e3:g} ms" if chosen else "no step meets the threshold"
    )
    Path(args.json).write_text(
        json.dumps(
            dict(
                settings=vars(args),
                reference_seconds=ref_seconds,
                reference_nonfinite=ref_bad,
                chaos_floor=floor,
                rows=rows,
                chosen_dt=chosen,
            ),
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
