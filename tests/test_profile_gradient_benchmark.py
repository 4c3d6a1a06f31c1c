"""`benchmarks/profile_gradient.py`: naming the loops of a dumped program and summing a trace
by loop and kernel, on a small program and trace written out here (the script itself
compiles a gradient under the profiler: minutes, not a unit test)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_gradient


def _loop(name, source, trips):
    """A while loop as XLA's text dump writes it (one line): the JAX operation it came
    from and its trip count."""
    return (
        f"  %{name} = (s32[], f32[3,8,56]{{2,1,0}}) while(%t), condition=%c, body=%b, "
        f'metadata={{op_name="jit(_sharded)/shard_map/{source}" stack_frame_id=1}}, '
        f'backend_config={{"known_trip_count":{{"n":"{trips}"}}}}'
    )


STEP = "/while/body/closed_call/checkpoint"
# XLA's text dump, cut down to what the parser reads: loops and the fusions they call.
PROGRAM = "\n".join(
    [
        "%fused_springs (p0: f32[8,8,56]) -> f32[8,8,56] {",
        "  %p0 = f32[8,8,56]{2,1,0} parameter(0)",
        "  %sq = f32[8,8,56]{2,1,0} sqrt(%p0)",
        "  ROOT %m = f32[8,8,56]{2,1,0} multiply(%sq, %sq)",
        "}",
        "",
        "%step_body (s: (s32[], f32[3,8,56])) -> (s32[], f32[3,8,56]) {",
        "  %springs = f32[8,8,56]{2,1,0} fusion(%x), kind=kLoop, calls=%fused_springs",
        "}",
        "",
        "ENTRY %main (a: f32[3,8,56]) -> f32[3,8,56] {",
        _loop("while.1", "jvp()/while", 25),
        _loop("while.2", "jvp()/while/body/closed_call/while", 20),
        _loop("while.3", f"transpose(jvp()){STEP}/rematted_computation/while", 20),
        _loop("while.4", f"transpose(jvp()){STEP}/while", 20),
        _loop("while.5", f"transpose(jvp()){STEP}/while", 6),
        _loop("while.6", "transpose(jvp())/while", 25),
        "}",
    ]
)


def test_loops_are_named_by_their_origin_and_trip_count():
    roles, kernels = profile_gradient._program(PROGRAM, steps=20, intervals=25)
    assert roles == {
        "while.1": "per interval, forward",
        "while.2": "forward steps",
        "while.3": "recompute steps",
        "while.4": "transposed steps",
        "while.5": "transposed, inner loop of 6",
        "while.6": "per interval, backward",
    }
    # A fusion: its shape and the operations it fuses (parameters left out).
    assert kernels["springs"] == ("f32[8,8,56]", {"sqrt": 1, "multiply": 1})


def _event(name, ts, dur, tid=1):
    return {"ph": "X", "name": name, "ts": ts, "dur": dur, "pid": 1, "tid": tid}


def test_time_is_summed_by_innermost_loop():
    roles = {"while.outer": "per interval, backward", "while.inner": "transposed steps"}
    kernels = {"a", "b", "c"}
    events = [
        _event("while.outer", 0, 100),
        _event("while.inner", 10, 30),  # two runs of the inner loop inside the outer one
        _event("a", 12, 5),
        _event("b", 20, 10),
        _event("while.inner", 50, 20),
        _event("a", 55, 4),
        _event("c", 80, 6),  # in the outer loop only
        _event("c", 200, 50),  # outside every loop: not counted
        _event("while.inner", 0, 40, tid=2),  # another thread: its own nesting
        _event("b", 5, 7, tid=2),
        {"ph": "i", "name": "a", "ts": 13, "pid": 1, "tid": 1},  # an instant event
    ]
    loops, per_kernel = profile_gradient._attribute(events, roles, kernels)
    # Each loop's own time: the outer loop less the inner loop's runs inside it.
    assert loops == pytest.approx({"per interval, backward": 50.0, "transposed steps": 90.0})
    assert per_kernel == {
        "transposed steps": pytest.approx({"a": 9.0, "b": 17.0}),
        "per interval, backward": pytest.approx({"c": 6.0}),
    }
