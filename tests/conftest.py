import os
from pathlib import Path

# One persistent compilation cache for the whole test run: every process of it (the xdist
# workers, the CLI and the notebook kernels the tests start) reuses what another compiled
# (a simulation compiles in seconds; most tests compile a handful). Set before JAX starts;
# the subprocesses inherit it through the environment.
_CACHE = Path(__file__).resolve().parents[1] / ".jax_cache"
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


@pytest.fixture
def x64():
    """Run a test in float64 (accuracy tests): build bodies and controllers inside it."""
    with jax.enable_x64(True):
        yield
