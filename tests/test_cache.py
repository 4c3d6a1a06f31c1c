"""The warm start: the CLI keeps compiled programs in a persistent cache folder, and a
second run of the same config loads them, with the same result."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxmotion._cli import cache

ROOT = Path(__file__).resolve().parents[1]


def _run(tmp_path, name, env, *extra):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxmotion",
            "run",
            str(ROOT / "configs" / "default.toml"),
            "--evaluations",
            "200",
            "--batch",
            "100",
            "--no-animation",
            "--quiet",
            "--out",
            str(tmp_path / name),
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert out.returncode == 0, out.stderr
    (folder,) = (tmp_path / name).iterdir()
    return json.loads((folder / "summary.json").read_text())


def _entries(folder: Path) -> set[str]:
    return {p.name for p in folder.rglob("*") if p.is_file()}


def test_a_second_run_loads_the_first_runs_programs(tmp_path):
    """The first run fills the cache; the second (a fresh process, same config) finds every
    program there (it stores nothing new) and finds the same best fitness, bitwise.

    Every program is stored (threshold 0 s): with the CLI's 0.5 s threshold a program that
    compiles in 0.4 s in the first run and 0.6 s in a busier second one would be stored only
    then, which says nothing about loading."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    folder = tmp_path / "cache"
    env[cache.CACHE_ENV] = str(folder)
    env[cache.MIN_COMPILE_TIME_ENV] = "0"
    first = _run(tmp_path, "first", env)
    stored = _entries(folder)
    assert stored, "the first run stored no compiled program"
    second = _run(tmp_path, "second", env)
    assert _entries(folder) == stored
    assert second["best_fitness"] == first["best_fitness"]


def test_the_flag_turns_the_cache_off(monkeypatch, capsys):
    """`--no-compilation-cache` (on every command) skips the cache; without it the CLI turns
    it on before anything compiles."""
    import jaxmotion._devices
    from jaxmotion._cli.main import main

    calls = []
    monkeypatch.setattr(jaxmotion._devices, "use_cpu_cores", lambda: 1)
    monkeypatch.setattr(cache, "use_compilation_cache", lambda: calls.append(1))
    config = str(ROOT / "configs" / "default.toml")
    assert main(["check", config, "--no-compilation-cache"]) == 0
    assert calls == []
    assert main(["check", config]) == 0
    assert calls == [1]
    capsys.readouterr()


def test_the_cache_folder_follows_the_environment(tmp_path, monkeypatch):
    import jax

    before = (
        jax.config.jax_compilation_cache_dir,
        jax.config.jax_persistent_cache_min_compile_time_secs,
    )
    try:
        monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
        monkeypatch.delenv(cache.CACHE_ENV, raising=False)
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        assert cache.default_cache_dir() == tmp_path / "xdg" / "jaxmotion" / "jax"
        assert cache.use_compilation_cache() == tmp_path / "xdg" / "jaxmotion" / "jax"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "xdg" / "jaxmotion" / "jax")
        for off in ("off", "", "0"):
            monkeypatch.setenv(cache.CACHE_ENV, off)
            assert cache.use_compilation_cache() is None
        monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "mine"))
        assert cache.use_compilation_cache() == tmp_path / "mine"
        monkeypatch.delenv(cache.CACHE_ENV)
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jax's"))
        assert cache.use_compilation_cache() == tmp_path / "jax's"  # JAX's own setting kept
        (tmp_path / "file").write_text("x")
        with pytest.raises(ValueError, match=r"is a file; allowed: a folder"):
            cache.use_compilation_cache(tmp_path / "file")
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])
