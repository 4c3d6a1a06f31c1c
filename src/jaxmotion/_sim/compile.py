"""How the simulations are compiled: one `jit` for every function that runs a simulation, so
that they all compile to the same code (a controller's fitness is bitwise the same in a
search, in playback and in gradient refinement)."""

import functools
from collections.abc import Callable

import equinox as eqx
import jax

# XLA's CPU backend writes fused loops either with its newer "fusion emitters" (the default)
# or with its classic loop emitters. A simulation step is thousands of scalar operations
# batched over controllers; for it the classic emitters compile about a third faster and run
# as fast or faster. Measured on 2 cores (`benchmarks/figures.py`, `benchmarks/evaluate.py`):
# Rex's `Task.evaluate` compiles in 7.5 s instead of 11 s, the cube's in 3.5 s instead of
# 4.8 s. An XLA that no longer knows the option compiles with its defaults.
_PREFERRED = {"xla_cpu_use_fusion_emitters": False}


@functools.cache
def compiler_options() -> dict:
    """The preferred compiler options this XLA accepts (asked once, at the first compile:
    the backend must not start when jaxmotion is imported)."""
    try:
        jax.jit(lambda x: x + 1, compiler_options=_PREFERRED).lower(1.0).compile()
    except jax.errors.JaxRuntimeError:
        return {}
    return dict(_PREFERRED)


def simulation_jit(fn: Callable) -> Callable:
    """`eqx.filter_jit(fn)`, compiled with `compiler_options()` (`.lower(...)` as well, to
    inspect or time the compilation)."""
    jitted = None

    def get():
        nonlocal jitted
        if jitted is None:
            jitted = eqx.filter_jit(fn, compiler_options=compiler_options() or None)
        return jitted

    @functools.wraps(fn)
    def call(*args, **kwargs):
        return get()(*args, **kwargs)

    call.lower = lambda *args, **kwargs: get().lower(*args, **kwargs)
    return call
