"""Where the time of `task.evaluate` goes: the batched physics step taken apart.

    python benchmarks/profile_step.py [--batch 500] [--duration 1.0] [--repeats 5]

On one device (one core), for one chunk of the batch (`Task` runs 500 controllers per device
and call), it times

- `evaluate`: the Task's own compiled evaluation (diffrax, observation, objective);
- `scan`: the same step in a plain `lax.scan`, no diffrax, no saving: the control tick (the
  regime chosen), materialised as the solver does, then semi-implicit Euler;
- `scan, tick not materialised`: the tick's result left to XLA's fusion, which repeats the
  regime choice in the loop over every spring-table entry (what the solver avoids);
- `scan, one rest table`: without the regime switch (every step reads one table instead of
  choosing among the C regime tables);
- `scan, no floor`: without contact and friction;
- `scan, springs only`: neither;
- `memory floor`: a step that only streams the state (x += h v; v += h g), the least any
  layout can cost;

and prints each as microseconds per controller-step and the evaluations per second it would
allow at T = 5 s, dt = 1 ms (the issue's target: 5,000/s at B = 1000 on two cores, so 2,500/s
per core). Writes `benchmarks/profile_step.json`.
"""

import argparse
import json
import statistics
import time
from pathlib import Path

import jaxmotion as jm

jm.use_cpu_cores(1)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402

from jaxmotion._body.base import BodyState  # noqa: E402
from jaxmotion._sim.compile import compiler_options  # noqa: E402
from jaxmotion._sim.system import materialise  # noqa: E402
from jaxmotion._task import _fitness  # noqa: E402


def timed(fn, args, repeats):
    jax.block_until_ready(fn(*args))  # compile
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--batch", type=int, default=500)
    p.add_argument("--duration", type=float, default=1.0)
    p.add_argument("--dt", type=float, default=1e-3)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()

    body = jm.lattices.cube()
    world = jm.World()
    task = jm.Task(
        body,
        world,
        jm.RegimesSpace(4, 1.0),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=args.duration,
        dt=args.dt,
    )
    params = task.sample(args.batch, key=jr.key(0))
    steps = round(args.duration / args.dt)
    dynamics = body.dynamics()
    plans = jnp.moveaxis(jax.vmap(lambda c: c.prepare(body))(params), 0, -1)
    ctrl = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), params)
    y0 = tuple(
        jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a[..., None], (*a.shape, args.batch)), body.initial_state()
        )
    )
    no_floor = jm.World(floor=False)

    jit = lambda fn: jax.jit(fn, compiler_options=compiler_options() or None)

    def scan(switch: str | None, w):
        @jit
        def run(y0, ctrl, plans):
            def step(carry, k):
                (x, v), control = carry
                t = k * args.dt
                if switch is None:
                    table = plans[0]
                else:
                    control = ctrl.update(t, control, None, plans)
                    if switch == "materialised":
                        control = materialise(control)
                    table = ctrl.actuation(t, control, plans)
                _, a = dynamics.rates(BodyState(x, v), table, w)
                v = v + args.dt * a
                return ((x + args.dt * v, v), control), None

            ks = jnp.arange(steps, dtype=jnp.float32)
            control = ctrl.init(None, plans)
            return jax.lax.scan(step, (y0, control), ks)[0][0]

        return run

    @jit
    def stream(y0):
        g = jnp.asarray([0.0, 0.0, -9.81])[:, None, None]

        def step(y, _):
            x, v = y
            v = v + args.dt * g
            return (x + args.dt * v, v), None

        return jax.lax.scan(step, y0, None, length=steps)[0]

    evaluate = jit(lambda p: _fitness(task, p))
    cases = {
        "evaluate": (evaluate, (params,)),
        "scan": (scan("materialised", world), (y0, ctrl, plans)),
        "scan, tick not materialised": (scan("fused", world), (y0, ctrl, plans)),
        "scan, one rest table": (scan(None, world), (y0, ctrl, plans)),
        "scan, no floor": (scan("materialised", no_floor), (y0, ctrl, plans)),
        "scan, springs only": (scan(None, no_floor), (y0, ctrl, plans)),
        "memory floor": (stream, (y0,)),
    }
    rows = []
    print(f"cube, B = {args.batch} on one core, {steps} steps of {args.dt * 1e3:g} ms")
    print(f"{'variant':<32} {'us/ctrl-step':>13} {'evals/s at 5 s':>15} {'share':>7}")
    base = None
    for name, (fn, fn_args) in cases.items():
        seconds = timed(fn, fn_args, args.repeats)
        per = seconds / (steps * args.batch) * 1e6
        rate = 1e6 / (per * round(5.0 / args.dt))
        base = base or per
        rows.append({"variant": name, "us_per_controller_step": per, "evals_per_s_at_5s": rate})
        print(f"{name:<32} {per:>13.4f} {rate:>15,.0f} {per / base:>7.0%}")
    Path(args.json).write_text(json.dumps({"settings": vars(args), "rows": rows}, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
