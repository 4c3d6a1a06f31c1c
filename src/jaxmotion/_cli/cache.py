"""A warm start: JAX's persistent compilation cache in a user cache folder.

A search compiles a handful of programs (the batched simulation, the search step, the
objective) in 5-30 s; the cache keeps them on disk, keyed by the program, the JAX and XLA
versions, the flags and the devices, so the next run of the same config (or any config that
builds the same programs) loads them instead. The CLI turns it on; in a notebook or script it
is the application's call, like `use_cpu_cores`: the library changes no global configuration
on its own.
"""

import os
from pathlib import Path

#: Environment variable naming the cache folder; `off` (or an empty value) turns it off.
CACHE_ENV = "JAXMOTION_COMPILATION_CACHE"
#: JAX's own threshold (seconds of compilation below which a program is not stored).
MIN_COMPILE_TIME_ENV = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"


def default_cache_dir() -> Path:
    """The user cache folder for compiled programs: `$XDG_CACHE_HOME/jaxmotion/jax`, or
    `~/.cache/jaxmotion/jax` when `XDG_CACHE_HOME` is unset."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxmotion" / "jax"


def use_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Keep JAX's compiled programs in a persistent cache folder, so later processes (the
    next run, a notebook's kernel after a restart) start warm.

    **Arguments:** `directory`: the folder (created by JAX on first use). Default: the
    `JAXMOTION_COMPILATION_CACHE` environment variable when it is set (`off` or empty turns
    the cache off), else JAX's own `JAX_COMPILATION_CACHE_DIR` when that is set (left as JAX
    read it), else `default_cache_dir()`.

    Programs that compile in under 0.5 s are not stored (loading them would not pay), unless
    JAX's own `JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS` is set, which is then left as JAX
    read it. Call it before anything compiles: JAX opens its cache once, at the first
    compilation.

    **Returns:** the cache folder in use, or None when it is turned off.
    """
    import jax

    if directory is None:
        chosen = os.environ.get(CACHE_ENV)
        if chosen is not None:
            if chosen.strip().lower() in ("", "off", "0", "false", "no"):
                return None
            directory = chosen
        elif os.environ.get("JAX_COMPILATION_CACHE_DIR"):
            return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
        else:
            directory = default_cache_dir()
    path = Path(directory).expanduser()
    if path.exists() and not path.is_dir():
        raise ValueError(
            f"compilation cache = {str(path)!r} is a file; allowed: a folder (or 'off' in "
            f"{CACHE_ENV})"
        )
    jax.config.update("jax_compilation_cache_dir", str(path))
    if MIN_COMPILE_TIME_ENV not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path
