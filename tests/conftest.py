import os
from pathlib import Path

# A persistent compilation cache for the whole test run: every process of it (the xdist
# workers; the CLI and the notebook kernels the tests start) reuses what another of its kind
# compiled (a simulation compiles in seconds; most tests compile a handful). Set before JAX
# starts; the subprocesses inherit it through the environment.
_CACHE = Path(__file__).resolve().parents[1] / ".jax_cache"
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

# The test processes compile with XLA's backend optimisation off: they compile a few hundred
# small programs and run most of them for a fraction of a second, so LLVM's optimisation
# passes were a fifth of a cold suite's time and bought nothing. XLA reads its flags once,
# at the first compilation (below); the subprocesses the tests start (the CLI, the notebook
# kernels) get the environment back as it was, and compile as a user's run does, so the
# promises that hold end to end (a search's best replays alone to the very fitness the
# search recorded) are still tested on the code users run. JAX keys its persistent cache on
# the XLA_FLAGS of the moment, restored below, so the test processes keep their programs in
# a cache of their own (`.jax_cache/tests`): there a subprocess never finds, and runs, an
# unoptimised program under its own key.
# Not here on purpose: `--xla_cpu_use_fusion_emitters=false` (XLA's older loop emitters).
# It cut a cold suite from 1013 s to 638 s on 2 cores (2026-12-07), but programs built with
# it round differently from one another where the default emitters do not: 7 bitwise tests
# failed by 1-2 ulp (a motion saved on a coarser grid, continued from a state, in a batch
# of sequences, or searched under jit), so the suite would no longer test what users run.
_USER_XLA_FLAGS = os.environ.get("XLA_FLAGS")
os.environ["XLA_FLAGS"] = f"{_USER_XLA_FLAGS or ''} --xla_backend_optimization_level=0".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update(
    "jax_compilation_cache_dir", str(Path(os.environ["JAX_COMPILATION_CACHE_DIR"]) / "tests")
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
jax.jit(lambda x: x + 1).lower(1.0).compile()  # XLA parses XLA_FLAGS here, once
if _USER_XLA_FLAGS is None:
    del os.environ["XLA_FLAGS"]
else:
    os.environ["XLA_FLAGS"] = _USER_XLA_FLAGS


@pytest.fixture
def x64():
    """Run a test in float64 (accuracy tests): build bodies and controllers inside it."""
    with jax.enable_x64(True):
        yield


# Worker crashes are re-run, not hung on: see crash_tolerant.py.
from crash_tolerant import pytest_xdist_make_scheduler  # noqa: E402, F401
