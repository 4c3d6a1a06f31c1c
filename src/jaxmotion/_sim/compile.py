"""How the simulations are compiled: one `jit` for every function that runs a simulation, so
that they all compile to the same code (a controller's fitness is bitwise the same in a
search, in playback and in gradient refinement)."""

import functools
from collections.abc import Callable

import equinox as eqx
import jax

# XLA's CPU backend hands some fusions to the YNNPACK library: reductions, element-wise blocks and
# matrix products above a size. Its kernels tile by the array sizes, so the same controller's
# arithmetic was grouped, and rounded, differently in batches of different widths (the pyramid's
# rest lengths from 40 controllers per device on, say), and a chaotic motion amplified the last bit
# into a different motion: a search's best controller replayed alone (a batch of 16) to another
# fitness than the search recorded. Without it, the lattices score bitwise the same at every batch
# size (measured: widths 1 to 1,200, on 1 and 2 devices), at the same speed (some figures still do
# not in parts of 176-264 controllers and more: the README's "Known problem: wide parts of some
# figures"); the figures' sums over rods are written as explicit adds so that they lose nothing by
# it. (XLA's classic loop emitters, used here before, made Rex's results depend on the width too;
# they run batches of 100 figures about 15% faster and of 1,000 about 10% slower.) An XLA that no
# longer knows the option compiles with its defaults.
_PREFERRED = {"xla_cpu_experimental_ynn_fusion_type": ""}


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
