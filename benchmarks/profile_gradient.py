"""Where the time of a gradient goes: the compiled program's loops and kernels, per step.

    python benchmarks/profile_gradient.py [--batch 1000] [--duration 0.5] [--top 15]

`benchmarks/gradient.py` says what a gradient costs in simulations; this says where, for the
same task (the cube forward task smoothed as `compare` smooths it, dt = 1 ms, 2 CPU
devices). It compiles `jaxmotion.fitness_and_gradient` with XLA's per-kernel trace events
switched on (`--xla_cpu_enable_xprof_traceme`), runs it once under `jax.profiler`, and
attributes every kernel to the innermost loop it ran in. XLA's dump of the optimised
program names each loop's role from the JAX operation it came from:

- `forward`: the forward pass's loop over a save interval's steps;
- `recompute`: the backward pass recomputing an interval (the checkpoint) and keeping what
    the transposed step reads;
- `transposed`: the backward pass proper, one step transposed per iteration;
- `per interval`: what runs once per save interval (samples, the objective's terms).

It prints each loop's time per step (microseconds, per device), then the `--top` most
expensive kernels of the transposed step with their shapes and the operations they fuse.
A short duration keeps the trace whole (the profiler drops events past about a million).
Every kernel's trace event costs time of its own (about a microsecond), which distorts the
short kernels of small batches: profile at B = 500 per device or more.
Writes `benchmarks/profile_gradient.json`.
"""

import argparse
import collections
import glob
import gzip
import json
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

if __name__ == "__main__":
    # Before JAX starts: per-kernel trace events and a dump of the optimised program (only
    # when run: importing this file for its parsers changes nothing).
    _DUMP = tempfile.mkdtemp(prefix="jaxmotion-hlo-")
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_cpu_enable_xprof_traceme=true --xla_dump_to={_DUMP}"
        + " --xla_dump_hlo_as_text --xla_dump_hlo_pass_re=NONE"
    )
    os.environ["JAX_ENABLE_COMPILATION_CACHE"] = "false"  # a cached program is not dumped

import jax
import jax.random as jr

import jaxmotion as jm
from jaxmotion._sim.simulate import time_grid

_INSTRUCTION = re.compile(r"\s+(?:ROOT )?%([\w.\-]+) = (\S+) ([\w\-]+)\(")
_WHILE = re.compile(r"\s+(?:ROOT )?%([\w.\-]+) = \(.*\) while\(")


def _computations(text: str) -> dict[str, list[str]]:
    comps, current = {}, None
    for line in text.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head and not line.startswith(" "):
            current = head.group(1)
            comps[current] = []
        elif current and line.startswith("  "):
            comps[current].append(line)
    return comps


def _role(line: str, steps: int, intervals: int) -> str:
    """A while loop's role, from the JAX operation it came from and its trip count (`steps`
    for a save interval's loop over its steps, `intervals` for the loop over intervals)."""
    source = re.search(r'op_name="([^"]*)"', line)
    source = source.group(1) if source else ""
    trips = re.search(r'"n":"(\d+)"', line)
    trips = int(trips.group(1)) if trips else 0
    backward = "transpose(" in source
    if trips == intervals and source.count("/while") == 1:
        return "per interval, " + ("backward" if backward else "forward")
    if backward:
        role = "recompute" if "rematted_computation" in source else "transposed"
    else:
        role = "forward"
    return role + (" steps" if trips == steps else f", inner loop of {trips}")


def _program(text: str, steps: int, intervals: int):
    """The gradient's optimised program (XLA's text dump): each while loop's role, by name
    (`_role`), and each kernel's shape and the operations it fuses."""
    comps = _computations(text)
    roles, kernels = {}, {}
    for lines in comps.values():
        for line in lines:
            loop = _WHILE.match(line)
            if loop:
                roles[loop.group(1)] = _role(line, steps, intervals)
                continue
            found = _INSTRUCTION.match(line)
            if not found or found.group(3) not in ("fusion", "dot", "copy"):
                continue
            name, shape, _ = found.groups()
            called = re.search(r"calls=%([\w.\-]+)", line)
            ops = collections.Counter()
            for inner_line in comps.get(called.group(1), []) if called else []:
                inner_op = _INSTRUCTION.match(inner_line)
                if inner_op and inner_op.group(3) not in ("parameter", "bitcast", "broadcast"):
                    ops[inner_op.group(3)] += 1
            kernels[name] = (shape.split("{")[0], dict(ops.most_common(6)))
    return roles, kernels


def _attribute(events, roles: dict, kernels) -> tuple[dict, dict]:
    """Sum a trace's complete events (`ph == "X"`) by loop and kernel: each loop's own time
    by role (its duration less that of the loops run inside it), and each kernel's time by
    the role of the innermost loop it ran in (kernels outside every loop are left out).
    Events nest by time within a thread."""
    loops = collections.defaultdict(float)
    per_kernel = collections.defaultdict(lambda: collections.defaultdict(float))
    by_thread = collections.defaultdict(list)
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            by_thread[(e["pid"], e["tid"])].append(e)

    def close(stack, until):
        """Close the open loops that ended by `until`."""
        while stack and stack[-1][0] <= until:
            _, role, duration, nested = stack.pop()
            loops[role] += duration - nested
            if stack:
                stack[-1][3] += duration

    for thread in by_thread.values():
        thread.sort(key=lambda e: (e["ts"], -e["dur"]))
        stack: list = []  # open loops: [end, role, duration, nested loops' duration]
        for e in thread:
            close(stack, e["ts"])
            if e["name"] in roles:
                stack.append([e["ts"] + e["dur"], roles[e["name"]], e["dur"], 0.0])
            elif e["name"] in kernels and stack:
                per_kernel[stack[-1][1]][e["name"]] += e["dur"]
        close(stack, float("inf"))
    return dict(loops), {role: dict(k) for role, k in per_kernel.items()}


def main() -> None:
    jm.use_cpu_cores()
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--batch", type=int, default=1000)
    p.add_argument("--duration", type=float, default=0.5)
    p.add_argument("--top", type=int, default=15)
    p.add_argument("--json", default=str(Path(__file__).with_suffix(".json")))
    args = p.parse_args()

    task = jm.Task(
        jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 1.0),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=args.duration,
    )
    params = task.sample(args.batch, key=jr.key(0))
    smoothing = jm.Smoothing(regime_width=0.05, friction_velocity=0.1)
    run = lambda: jm.fitness_and_gradient(task, params, smoothing=smoothing)
    grid = time_grid(task.duration, task.dt, task.save_dt, task.control_dt)
    trace = tempfile.mkdtemp(prefix="jaxmotion-trace-")
    try:
        jax.block_until_ready(run())  # compile
        jax.profiler.start_trace(trace, create_perfetto_trace=True)
        jax.block_until_ready(run())
        jax.profiler.stop_trace()
        dumped = glob.glob(f"{_DUMP}/*jit__sharded*cpu_after_optimizations.txt")
        text = Path(max(dumped, key=os.path.getsize)).read_text()  # the gradient's program
        roles, kernels = _program(text, grid.save_every, grid.num_saves)
        found = glob.glob(f"{trace}/**/*.trace.json.gz", recursive=True)
        events = json.load(gzip.open(found[0]))
    finally:  # the dump and the trace are large and of no use afterwards
        shutil.rmtree(_DUMP, ignore_errors=True)
        shutil.rmtree(trace, ignore_errors=True)
    loops, per_kernel = _attribute(events["traceEvents"], roles, kernels)
    steps = round(args.duration / task.dt) * jax.device_count()  # per device, summed
    print(
        f"cube, B = {args.batch}, T = {args.duration:g} s, dt = 1 ms, "
        f"{jax.device_count()} devices: microseconds per step and device"
    )
    for role, total in sorted(loops.items(), key=lambda kv: -kv[1]):
        print(f"  {role:<28} {total / steps:8.1f}")
    rows = []
    if "transposed steps" in per_kernel:
        print(f"\nthe {args.top} most expensive kernels of the transposed step:")
        ranked = sorted(per_kernel["transposed steps"].items(), key=lambda kv: -kv[1])
        for name, total in ranked[: args.top]:
            shape, ops = kernels[name]
            rows.append({"kernel": name, "shape": shape, "us": total / steps, "ops": ops})
            print(f"  {total / steps:7.1f}  {shape:<22} {name:<34} {ops}")
    Path(args.json).write_text(
        json.dumps(
            {
                "settings": vars(args),
                "loops_us": {k: v / steps for k, v in loops.items()},
                "transposed": rows,
            },
            indent=2,
        )
    )
    print(f"wrote {args.json}", file=sys.stderr)


if __name__ == "__main__":
    main()
