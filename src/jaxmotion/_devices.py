"""Using every CPU core: the one helper applications call before JAX starts."""

import os


def use_cpu_cores(count: int | None = None) -> int:
    """Make JAX expose one CPU device per core, so `Task.evaluate` splits its batch into as
    many parts and runs them side by side, one thread each (XLA runs each small simulation
    loop on the thread that calls it; two parts on two cores nearly double throughput, see
    `perf-lab`). Every part runs through the same compiled program, so a controller's
    fitness is bitwise the same whatever the count.

    Call it first thing in a notebook or script, before anything else uses JAX (the CLI does).
    It changes JAX's global configuration, which is the application's call: the library never
    does it on its own. Returns the number of CPU devices requested.

    **Raises:** `RuntimeError` if JAX has already started with a different device count.
    """
    import jax

    n = int(count) if count is not None else (os.cpu_count() or 1)
    if n < 1:
        raise ValueError(f"count = {count!r}; allowed: an integer >= 1")
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError as e:  # the backend already started
        have = len(jax.devices("cpu"))
        if have != n:
            raise RuntimeError(
                f"JAX already started with {have} CPU device(s); call "
                "jaxmotion.use_cpu_cores() before anything else uses JAX"
            ) from e
    return n
