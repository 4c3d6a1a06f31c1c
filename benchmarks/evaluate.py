"""Throughput of `Task.evaluate`, the hot function, against baselines measured in the same run.

    python benchmarks/evaluate.py                       # everything (several minutes)
    python benchmarks/evaluate.py --lattices cube --batches 100,1000 --dts 0.001

For each lattice (cube, pyramid, chair), batch size (1, 100, 1000, 10000) and step (1 ms,
the peers' setting, and the accuracy-matched step), one evaluation is one 5 s simulation of a
4-regime controller scored by forward + upright. Columns (evaluations per second, medians of
`--repeats` timed calls after a first, compiling call):

- `evaluate`: `Task.evaluate`, the batch split over one CPU device per core.
- `vmap`: `jax.jit(jax.vmap(...))` of the single-controller `simulate` plus the objective:
  what a user gets by vmapping the documented single-controller function.
- `numpy`: the same model in vectorised NumPy (`benchmarks/numpy_model.py`), float32.
- `perf-lab`: perf-lab's best JAX layout (`dense_bl_ms`, sharded the same way) for the cube
  at 1 ms, if `../shared/perf-lab` is there: a simpler model (one kind of reflex, no
  observation or objective), the reference the project measured before this code existed.

Also measured: the compile time of `evaluate`, its peak memory at B = 10,000 (a fresh
process, its `VmHWM`), and diffrax's overhead against a `lax.scan` of the same step
(`--no-perf-lab`, `--no-memory`, `--no-overhead` and the other `--no-*` options leave parts
out: `benchmarks/peers.py` times `evaluate` alone). Results go to `benchmarks/evaluate.json`
for comparison across commits.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def timed(fn, args, repeats, budget=2.0):
    """First call (compiles) and the median of later calls, in seconds."""
    start = time.perf_counter()
    out = fn(*args)
    _block(out)
    first = time.perf_counter() - start
    times = []
    while len(times) < repeats or (sum(times) < budget and len(times) < 4 * repeats):
        start = time.perf_counter()
        _block(fn(*args))
        times.append(time.perf_counter() - start)
    return first, statistics.median(times), out


def _block(x):
    import jax

    jax.block_until_ready(x)


def make_task(name, dt):
    import jaxmotion as jm

    builders = {
        "cube": jm.lattices.cube,
        "pyramid": jm.lattices.pyramid,
        "chair": jm.lattices.chair,
    }
    return jm.Task(
        builders[name](),
        jm.World(),
        jm.RegimesSpace(4, 1.0),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=5.0,
        dt=dt,
    )


PEAK = r"""
import resource, sys, json
import jaxmotion as jm
jm.use_cpu_cores()
import jax.random as jr
sys.path.insert(0, sys.argv[3])
from evaluate import make_task
task = make_task(sys.argv[1], float(sys.argv[2]))
params = task.sample(10_000, key=jr.key(0))
task.evaluate(params).block_until_ready()
task.evaluate(params).block_until_ready()
try:  # this process's own high-water mark (ru_maxrss would include the parent's, from fork)
    status = open("/proc/self/status").read()
    peak_kb = int(status.split("VmHWM:")[1].split()[0])
except (OSError, IndexError):
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"peak_mb": peak_kb / 1024}))
"""


def perf_lab_rate(path: Path, batch: int, repeats: int) -> float | None:
    """perf-lab's `dense_bl_ms` at dt = 1 ms, sharded over the devices like `evaluate`."""
    if not (path / "jax_model.py").exists():
        return None
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, PartitionSpec

    sys.path.insert(0, str(path))
    import common
    import jax_model

    sim = jax_model.make_dense_bl_sim(1e-3, manual_sum=True)
    args = jax_model.ctrl_arrays(common.make_controllers(batch, seed=3), jnp.float32)
    devices = jax.devices()
    if len(devices) > 1 and batch % len(devices) == 0:
        mesh = Mesh(np.array(devices), ("b",))
        spec = PartitionSpec("b")
        fn = jax.jit(
            jax.shard_map(sim, mesh=mesh, in_specs=(spec,) * 4, out_specs=spec, check_vma=False)
        )
    else:
        fn = jax.jit(sim)
    _, seconds, _ = timed(fn, args, repeats)
    return batch / seconds


def diffrax_overhead(batch: int, dt: float, repeats: int) -> dict:
    """`simulate_batch`'s diffrax solve against a `lax.scan` of the same solver step (the
    save interval's control periods) and the same saving, without diffrax's loop."""
    import jax
    import jax.numpy as jnp
    import jax.random as jr

    from jaxmotion._sim.simulate import _batched_start, _integrate, _to_last, time_grid
    from jaxmotion._sim.solver import solver_for
    from jaxmotion._sim.system import ClosedLoop

    task = make_task("cube", dt)
    params = task.sample(batch, key=jr.key(0))
    grid = time_grid(task.duration, task.dt, task.save_dt)

    def setup(params):
        plans = jax.vmap(lambda c: c.prepare(task.body))(params)
        system = ClosedLoop(
            task.body.dynamics(),
            _to_last(params),
            _to_last(plans),
            task.world,
            grid.control_dt,
            batched=True,
        )
        t0, y0 = _batched_start(system, task.body, None, batch)
        return system.with_start(y0[1]), t0, y0

    @jax.jit
    def with_diffrax(params):
        system, t0, y0 = setup(params)
        _, samples, _, _ = _integrate(system, y0, t0, grid, "symplectic")
        return samples[0].com

    @jax.jit
    def with_scan(params):
        system, t0, y0 = setup(params)
        solver = solver_for("symplectic", grid, rtol=0.0, atol=0.0, max_steps=0)
        save_dt = jnp.asarray(grid.save_dt, dtype=float)

        def interval(y, k):
            t = k * save_dt
            y, *_ = solver.step(None, t, t + save_dt, y, system, None, False)
            return y, system.sample(t + save_dt, y)[0].com

        _, saved = jax.lax.scan(interval, y0, jnp.arange(grid.num_saves, dtype=float))
        return jnp.concatenate([system.sample(t0, y0)[0].com[None], saved])

    out = {}
    for _ in range(2):  # interleaved, twice, against drift of the machine's speed
        for name, fn in (("scan", with_scan), ("diffrax", with_diffrax)):
            _, seconds, _ = timed(fn, (params,), repeats)
            out.setdefault(name, []).append(seconds)
    scan, dfx = min(out["scan"]), min(out["diffrax"])
    return {"batch": batch, "dt": dt, "scan_s": scan, "diffrax_s": dfx, "ratio": dfx / scan}


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--lattices", default="cube,pyramid,chair")
    p.add_argument("--batches", default="1,100,1000,10000")
    p.add_argument("--dts", default=None, help="steps, s (default: 0.001 and the Task default)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-numpy", action="store_true")
    p.add_argument("--no-vmap", action="store_true")
    p.add_argument("--no-memory", action="store_true")
    p.add_argument("--perf-lab", default=str(HERE.parent.parent / "shared" / "perf-lab"))
    p.add_argument("--no-perf-lab", action="store_true")
    p.add_argument("--no-overhead", action="store_true", help="skip diffrax vs lax.scan")
    p.add_argument("--json", default=str(HERE / "evaluate.json"))
    args = p.parse_args()

    import jaxmotion as jm

    jm.use_cpu_cores()
    import inspect

    import jax
    import jax.random as jr
    import numpy as np
    import numpy_model

    default_dt = inspect.signature(jm.Task).parameters["dt"].default
    dts = [float(s) for s in args.dts.split(",")] if args.dts else sorted({1e-3, default_dt})
    rows = []
    print(
        f"{len(jax.devices())} CPU devices; evaluations per second (median of >= {args.repeats} calls)"
    )
    header = f"{'lattice':8} {'dt ms':>5} {'B':>6} {'evaluate':>9} {'compile s':>9} {'vmap':>7} {'x vmap':>7} {'numpy':>7} {'x numpy':>8} {'perf-lab':>9} {'x perf-lab':>10}"
    print(header)
    for name in args.lattices.split(","):
        for dt in dts:
            task = make_task(name, dt)
            plain = jax.jit(
                jax.vmap(
                    lambda c, task=task: task.objective(
                        jm.simulate(
                            task.body,
                            c,
                            task.world,
                            task.duration,
                            dt=task.dt,
                            save_dt=task.save_dt,
                        )
                    )
                )
            )
            for batch in [int(b) for b in args.batches.split(",")]:
                params = task.sample(batch, key=jr.key(0))
                first, seconds, fitness = timed(task.evaluate, (params,), args.repeats)
                row = dict(
                    lattice=name,
                    dt=dt,
                    batch=batch,
                    evaluate=batch / seconds,
                    compile_s=first - seconds,
                    nonfinite=int(np.sum(~np.isfinite(np.asarray(fitness)))),
                )
                if not args.no_vmap and batch <= 1000:
                    _, s, _ = timed(plain, (params,), max(2, args.repeats // 2))
                    row["vmap"] = batch / s
                if not args.no_numpy and batch <= 1000:
                    model = numpy_model.prepare(task, params, dtype=np.float32)
                    start = time.perf_counter()
                    numpy_model.simulate(model)
                    row["numpy"] = batch / (time.perf_counter() - start)
                if not args.no_perf_lab and name == "cube" and dt == 1e-3 and batch in (100, 1000):
                    rate = perf_lab_rate(Path(args.perf_lab), batch, args.repeats)
                    if rate:
                        row["perf_lab"] = rate
                for key in ("vmap", "numpy", "perf_lab"):
                    if key in row:
                        row[f"x_{key}"] = row["evaluate"] / row[key]
                rows.append(row)
                cell = lambda k, fmt, row=row: format(row[k], fmt) if k in row else "-"
                print(
                    f"{name:8} {dt * 1e3:5.2g} {batch:6d} {row['evaluate']:9.0f} {row['compile_s']:9.1f} "
                    f"{cell('vmap', '7.0f'):>7} {cell('x_vmap', '7.2f'):>7} {cell('numpy', '7.0f'):>7} "
                    f"{cell('x_numpy', '8.1f'):>8} {cell('perf_lab', '9.0f'):>9} {cell('x_perf_lab', '10.2f'):>10}",
                    flush=True,
                )
    result = {"rows": rows}
    if "cube" in args.lattices and not args.no_overhead:
        overhead = [diffrax_overhead(b, 1e-3, args.repeats) for b in (1, 100, 1000)]
        for o in overhead:
            print(
                f"diffrax vs lax.scan, cube B={o['batch']:5d}: {o['diffrax_s'] * 1e3:8.1f} ms vs "
                f"{o['scan_s'] * 1e3:8.1f} ms, ratio {o['ratio']:.3f}"
            )
        result["diffrax_overhead"] = overhead
    if not args.no_memory:
        memory = []
        for name in args.lattices.split(","):
            out = subprocess.run(
                [sys.executable, "-c", PEAK, name, str(default_dt), str(HERE)],
                capture_output=True,
                text=True,
                check=True,
            )
            peak = json.loads(out.stdout.strip().splitlines()[-1])["peak_mb"]
            memory.append({"lattice": name, "batch": 10_000, "peak_mb": peak})
            print(f"peak memory of a fresh process evaluating {name} at B=10000: {peak:.0f} MB")
        result["memory"] = memory
    result["meta"] = {
        "devices": len(jax.devices()),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "repeats": args.repeats,
    }
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
