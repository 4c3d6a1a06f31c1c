"""`python -m jaxmotion sweep`: many independent searches (configs x seeds x override sets)
as Ray tasks, on a local Ray started on demand or on an existing cluster (`--address`).

Each task is the CLI's own `run`, in a subprocess of its Ray worker:
`python -m jaxmotion run CONFIG --seed S --set KEY=VALUE ... --cpu-devices N --quiet`, so
its results folder is exactly the one `run` writes (same code path, same compiled
programs), and a subprocess is the one place where JAX can be given the task's cores
(`--cpu-devices N`: N CPU devices, set before JAX starts in that process, whatever a
reused Ray worker had started before). A crash inside XLA, a SIGKILL or an out-of-memory
kill takes down that subprocess only; the task reports it, and the sweep retries it once.

The `--set` parser lives here too; `run` uses it for its own `--set`.
"""

import argparse
import copy
import csv
import io
import itertools
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tarfile
import tempfile
import time
import tomllib
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import ConfigError

INSTALL = "pip install 'jaxmotion[cluster]'"
"""How to get Ray, which `sweep` needs (the `cluster` extra)."""

MAX_TASKS = 10_000  # configs x seeds x override sets in one sweep
MAX_SEED = 2**32 - 1

# ------------------------------------------------------------------------------- --set

_KEY = re.compile(r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$")
_BARE_WORD = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-/]*$")
SET_EXAMPLE = "KEY=VALUE with a dotted key and a TOML value, e.g. search.evaluations=2000"


@dataclass(frozen=True)
class Setting:
    """One `--set KEY=VALUE`: the key's path (`("search", "evaluations")`), its value (as
    TOML reads it) and the text given."""

    path: tuple[str, ...]
    value: Any
    text: str

    @property
    def key(self) -> str:
        return ".".join(self.path)


def parse_set(text: str) -> Setting:
    """One `--set KEY=VALUE`. The value is read as TOML (`2000`, `0.5`, `true`, `"name"`,
    `[1, 2]`); a bare word that is not TOML (`cartwheel-fast`) is taken as a string.

    **Raises:** `ConfigError` naming the option and what is allowed."""
    key, eq, value = text.partition("=")
    key, value = key.strip(), value.strip()
    if not eq:
        raise ConfigError(f"--set {text!r} has no '='; allowed: {SET_EXAMPLE}")
    if not _KEY.match(key):
        raise ConfigError(
            f"--set {text!r}: the key {key!r} is not a dotted name; allowed: names of "
            "letters, digits, _ and - joined by dots, e.g. search.evaluations"
        )
    if not value:
        raise ConfigError(f"--set {text!r} has no value; allowed: {SET_EXAMPLE}")
    try:
        parsed = tomllib.loads(f"value = {value}")["value"]
    except tomllib.TOMLDecodeError:
        if not _BARE_WORD.match(value):
            raise ConfigError(
                f"--set {text!r}: {value!r} is not a TOML value; allowed: a number (2000, "
                '0.5), true or false, a "string" (or a bare word), an array [1, 2]'
            ) from None
        parsed = value
    return Setting(tuple(key.split(".")), parsed, f"{key}={value}")


def override_sets(texts: list[str] | None, *, grid: bool) -> list[tuple[Setting, ...]]:
    """The override sets `--set` options give: one set of every key's value, or, with
    `grid` (a sweep), one set per combination when a key is given several values (`--set
    search.size=50 --set search.size=100` crosses both sizes with every other choice).

    **Raises:** `ConfigError` for a bad `--set`, a key given twice with one value, or (not
    `grid`) a key given twice."""
    by_key: dict[str, list[Setting]] = {}
    for text in texts or ():
        s = parse_set(text)
        given = by_key.setdefault(s.key, [])
        if any(g.value == s.value and type(g.value) is type(s.value) for g in given):
            raise ConfigError(f"--set {s.text!r} is given twice; allowed: each value once")
        if given and not grid:
            raise ConfigError(
                f"--set {s.key} is given {len(given) + 1} times; allowed: once (a sweep "
                "crosses several values of a key; run takes one)"
            )
        by_key[s.key] = [*given, s]
    keys = list(by_key)
    for a, b in itertools.combinations(keys, 2):
        pa, pb = by_key[a][0].path, by_key[b][0].path
        if pa[: len(pb)] == pb or pb[: len(pa)] == pa:
            raise ConfigError(
                f"--set {a} and --set {b}: one is inside the other; allowed: separate keys"
            )
    return [tuple(combo) for combo in itertools.product(*(by_key[k] for k in keys))]


def apply_sets(raw: dict[str, Any], settings: tuple[Setting, ...]) -> dict[str, Any]:
    """A config's table (as read from TOML) with `settings` applied (a copy): each key's
    tables are made if missing; the config's checks then judge the values.

    **Raises:** `ConfigError` for a key that goes through a value or an array of tables
    (`[[stage]]`), or that would replace a whole table."""
    raw = copy.deepcopy(raw)
    for s in settings:
        table = raw
        for depth, part in enumerate(s.path[:-1], start=1):
            inner = table.setdefault(part, {})
            if not isinstance(inner, dict):
                what = (
                    "an array of tables; --set reaches tables and their keys only (a "
                    "stage's [search] is merged over the top-level one, which --set can set)"
                    if isinstance(inner, list) and inner and isinstance(inner[0], dict)
                    else f"the value {inner!r}, not a table"
                )
                raise ConfigError(f"--set {s.text!r}: {'.'.join(s.path[:depth])} is {what}")
            table = inner
        if isinstance(table.get(s.path[-1]), dict):
            raise ConfigError(
                f"--set {s.text!r}: {s.key} is a table; allowed: one of its keys, e.g. "
                f"{s.key}.{next(iter(table[s.path[-1]]), 'KEY')}=VALUE"
            )
        table[s.path[-1]] = s.value
    return raw


# ------------------------------------------------------------------------------- seeds


def parse_seeds(text: str) -> tuple[int, ...]:
    """`--seeds`: integers and inclusive ranges joined by commas (`0-9`, `0,3,5`, `0-4,10`).

    **Raises:** `ConfigError` naming the option and what is allowed."""
    allowed = (
        f"integers from 0 to {MAX_SEED} and ranges, joined by commas, e.g. 0-9 or 0,3,5 "
        "(each seed once)"
    )
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if match is None:
            raise ConfigError(
                f"--seeds {text!r}: {part!r} is not a seed or a range; allowed: {allowed}"
            )
        lo = int(match.group(1))
        hi = int(match.group(2)) if match.group(2) is not None else lo
        if hi < lo:
            raise ConfigError(
                f"--seeds {text!r}: the range {part!r} runs backwards; allowed: {allowed}"
            )
        if hi > MAX_SEED:
            raise ConfigError(f"--seeds {text!r}: {hi} is too large; allowed: {allowed}")
        if hi - lo >= MAX_TASKS:
            raise ConfigError(f"--seeds {text!r}: more than {MAX_TASKS} seeds; allowed: {allowed}")
        for seed in range(lo, hi + 1):
            if seed in seeds:
                raise ConfigError(
                    f"--seeds {text!r}: seed {seed} is given twice; allowed: {allowed}"
                )
            seeds.append(seed)
    return tuple(seeds)


# ------------------------------------------------------------------------------- the tasks


@dataclass(frozen=True)
class Task:
    """One search of the sweep: a config file, a seed and an override set."""

    config: Path
    seed: int
    settings: tuple[Setting, ...]
    label: str  # its folder in the sweep's folder

    def run_options(self, cpus: int) -> list[str]:
        """The options of `python -m jaxmotion run CONFIG` that run it (`cpus`: the CPU
        devices JAX makes, one per core Ray gives the task)."""
        sets = [f"--set={s.text}" for s in self.settings]
        return ["--seed", str(self.seed), *sets, "--cpu-devices", str(cpus)]

    @property
    def overrides(self) -> str:
        return " ".join(s.text for s in self.settings)


# What each task's subprocess runs: the CLI, after asking the kernel to send it SIGTERM when
# its Ray worker dies (a cancelled sweep: `run` then saves its checkpoint and stops), rather
# than leave it running as an orphan. Linux only; elsewhere the CLI alone.
_CHILD = """\
import os, signal, sys
if sys.platform.startswith("linux"):
    import ctypes
    parent = int(os.environ.pop("JAXMOTION_SWEEP_PARENT"))
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        sys.exit(143)
from jaxmotion._cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def run_task(spec: dict[str, Any]) -> dict[str, Any]:
    """One sweep task, in a Ray worker: the CLI's `run` in a subprocess; returns what became
    of it. On the driver's node the results folder is moved into the sweep's folder here;
    on another node it comes back as a tar archive (no shared file system needed).

    The task's working folder (`.<label>.task/` in the sweep's folder, on the driver's
    node) keeps a killed run's checkpoint, and the retry resumes from it."""
    import ray

    local = ray.get_runtime_context().get_node_id() == spec["driver_node"]
    sweep = Path(spec["sweep"])
    work = (
        sweep / f".{spec['label']}.task"
        if local
        else Path(tempfile.mkdtemp(prefix=f"jaxmotion-{spec['label']}-"))
    )
    out = work / "out"
    out.mkdir(parents=True, exist_ok=True)
    config = work / spec["file"]
    config.write_text(spec["text"])
    argv = ["run", str(config), *spec["options"], "--out", str(out), "--quiet"]
    if any(out.glob("*.checkpoint")):
        argv += ["--resume", str(out)]
    env = {**os.environ, "JAXMOTION_SWEEP_PARENT": str(os.getpid())}
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, *argv],
        capture_output=True,
        text=True,
        env=env,
        cwd=work,
        check=False,
    )
    result: dict[str, Any] = {
        "label": spec["label"],
        "attempt": spec["attempt"],
        "returncode": done.returncode,
        "wall_time_s": round(time.perf_counter() - started, 3),
        "node": socket.gethostname(),
        "resumed": "--resume" in argv,
        "stderr": done.stderr[-3000:],
    }
    lines = done.stdout.strip().splitlines()
    folder = Path(lines[-1]) if done.returncode == 0 and lines else None
    if folder is None or not (folder / "summary.json").is_file():
        result["work"] = str(work) if local else f"{socket.gethostname()}:{work}"
        return result
    if local:
        os.replace(folder, sweep / spec["label"])
        result["folder"] = spec["label"]
    else:
        result["archive"] = pack(folder, spec["label"])
    shutil.rmtree(work, ignore_errors=True)
    return result


def pack(folder: Path, name: str) -> bytes:
    """A results folder as a gzipped tar archive whose one folder is `name` (how a search
    that ran on another node sends its folder back)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(folder, arcname=name)
    return buffer.getvalue()


def unpack(archive: bytes, into: Path) -> None:
    """Unpack an archive made by `pack` into the folder `into`."""
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r:gz") as tar:
        # The "data" filter (no links out, no devices) where Python has it (3.11.4+).
        safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
        tar.extractall(into, **safe)


def _failure(result: dict[str, Any]) -> str:
    """What became of a failed attempt, in a few words."""
    if "error" in result:
        return result["error"]
    code = result["returncode"]
    if code < 0:
        try:
            what = f"killed by {signal.Signals(-code).name}"
        except ValueError:
            what = f"killed by signal {-code}"
    elif code == 0:
        what = "finished without a results folder"
    else:
        what = f"exit status {code}"
    tail = [line for line in result.get("stderr", "").strip().splitlines() if line.strip()]
    return f"{what} after {result['wall_time_s']:.1f} s" + (f": {tail[-1]}" if tail else "")


# ------------------------------------------------------------------------------- the driver


def _plan(args) -> list[Task]:
    """The sweep's tasks, every config checked with every override set before Ray starts or
    anything compiles. Seed-major order: each config's first seed runs before its second,
    so that the later ones find its compiled programs in the persistent cache. Without
    `--seeds`, each config runs with its own seed."""
    from .main import _load

    settings = override_sets(args.set, grid=True)
    seeds = parse_seeds(args.seeds) if args.seeds is not None else None
    configs = [Path(c) for c in args.config]
    count = len(configs) * len(settings) * (len(seeds) if seeds is not None else 1)
    if count > MAX_TASKS:
        raise ConfigError(
            f"{count} searches (configs x seeds x override sets); allowed: at most "
            f"{MAX_TASKS} in one sweep"
        )
    own_seed = {}  # (config, override set's index) -> its seed (--set seed=S sets it)
    for path in configs:
        for k, sets in enumerate(settings, start=1):
            keep = argparse.Namespace(
                seed=None, evaluations=None, batch=None, runs=None, set=[s.text for s in sets]
            )
            own_seed[path, k] = _load(path, keep).seed
    stems = [c.stem for c in configs]
    tasks = []
    for seed_index in range(len(seeds) if seeds is not None else 1):
        for i, path in enumerate(configs):
            # Two configs of one name (in different folders) get their place as a prefix.
            stem = stems[i] if stems.count(stems[i]) == 1 else f"{i + 1}-{stems[i]}"
            for k, sets in enumerate(settings, start=1):
                seed = seeds[seed_index] if seeds is not None else own_seed[path, k]
                label = f"{stem}-seed{seed}" + (f"-set{k}" if len(settings) > 1 else "")
                tasks.append(Task(path, seed, sets, label))
    return tasks


def _new_sweep_folder(out_root: Path) -> Path:
    """`<out_root>/sweep-<time>[-n]/`, made (the results folders' naming and checks)."""
    from .results import new_folder

    final, tmp = new_folder(out_root, "sweep")
    os.replace(tmp, final)
    return final


def _start_ray(args):
    try:
        import ray
    except ImportError:
        raise ConfigError(f"sweep runs its searches on Ray; install it with: {INSTALL}") from None
    if args.address is None:
        cpus = args.local_cpus or os.cpu_count() or 1
        if args.cpus_per_task > cpus:
            raise ConfigError(
                f"--cpus-per-task = {args.cpus_per_task}; allowed: at most the local Ray's "
                f"{cpus} CPUs (--local-cpus)"
            )
        # address="local": always a Ray of our own, even where RAY_ADDRESS names a cluster.
        # Its workers at the sweep's own priority: Ray starts them with niceness 15 (to keep
        # its services responsive), and each task's search, their child, inherits it: on a
        # machine doing anything else the searches got a few percent of a core (a sweep of
        # two 9 s searches took 209 s beside two busy processes).
        with warnings.catch_warnings():
            # JAX warns at every fork once it has started (the configs were checked); Ray's
            # processes are forked and exec'd at once, which is safe.
            warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
            ray.init(
                address="local",
                num_cpus=cpus,
                include_dashboard=False,
                log_to_driver=False,
                logging_level="ERROR",
                _system_config={"worker_niceness": 0},
            )
        return ray, f"a local Ray ({cpus} CPUs)"
    _check_reachable(args.address)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
            ray.init(address=args.address, log_to_driver=False, logging_level="WARNING")
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise ConfigError(f"--address {args.address!r}: cannot connect to Ray ({e})") from None
    largest = max((n["Resources"].get("CPU", 0) for n in ray.nodes() if n.get("Alive")), default=0)
    if args.cpus_per_task > largest:
        ray.shutdown()
        raise ConfigError(
            f"--cpus-per-task = {args.cpus_per_task}; allowed: at most the {largest:g} CPUs "
            f"of the cluster's largest node"
        )
    return ray, f"the Ray cluster at {args.address}"


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fail fast on a `--address` where nothing listens (Ray itself keeps trying for
    minutes). `auto` and `local` are left to Ray.

    **Raises:** `ConfigError` naming the address and what is allowed."""
    allowed = (
        "allowed: HOST:PORT of a running Ray cluster's head (`ray start --head` prints it), "
        "ray://HOST:PORT (Ray Client), or auto (the cluster this machine belongs to)"
    )
    if address in ("auto", "local"):
        return
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--address {address!r}; {allowed}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise ConfigError(
            f"--address {address!r}: nothing answers at {host}:{port} ({e.strerror or e}); "
            f"{allowed}"
        ) from None


def run_sweep(args) -> int:
    """`python -m jaxmotion sweep`: plan and check every task, start (or join) Ray, run them,
    retry a failed one once, and write the summary as results arrive. Returns the exit
    status (1 if a task failed twice)."""
    if args.local_cpus is not None and args.address is not None:
        raise ConfigError(
            "--local-cpus sizes the local Ray; with --address the cluster's own is used"
        )
    tasks = _plan(args)
    say = (
        (lambda _: None) if args.quiet else (lambda line: print(f"sweep: {line}", file=sys.stderr))
    )
    ray, where = _start_ray(args)
    try:
        sweep = _new_sweep_folder(Path(args.out if args.out is not None else "results"))
    except BaseException:
        ray.shutdown()
        raise
    flags = ["--no-animation"] if args.no_animation else []
    flags += ["--checkpoint-every", str(args.checkpoint_every)]
    rows = {t.label: _row(t, "pending") for t in tasks}
    started = time.perf_counter()
    header = {
        "where": where,
        "cpus_per_task": args.cpus_per_task,
        "configs": len(args.config),
        "seeds": len({t.seed for t in tasks}),
        "sets": len(override_sets(args.set, grid=True)),
    }
    say(f"{len(tasks)} searches on {where}, {args.cpus_per_task} CPU(s) each -> {sweep}")
    previous = signal.signal(signal.SIGTERM, _terminate)
    remote = ray.remote(num_cpus=args.cpus_per_task, max_retries=0)(run_task)
    driver_node = ray.get_runtime_context().get_node_id()

    def submit(task: Task, attempt: int):
        spec = {
            "label": task.label,
            "attempt": attempt,
            "sweep": str(sweep.resolve()),
            "driver_node": driver_node,
            "file": task.config.name,
            "text": task.config.read_text(),
            "options": [*task.run_options(args.cpus_per_task), *flags],
        }
        rows[task.label]["attempts"] = attempt
        return remote.remote(spec)

    pending = {submit(t, 1): t for t in tasks}
    failed = 0
    try:
        while pending:
            [ref], _ = ray.wait(list(pending), num_returns=1)
            task = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as e:  # the worker died, the node was lost, ...
                lines = str(e).strip().splitlines()
                result = {
                    "label": task.label,
                    "error": f"{type(e).__name__}: {lines[0] if lines else ''}",
                }
                result["attempt"] = rows[task.label]["attempts"]
            row = rows[task.label]
            sent = ""
            if "archive" in result:
                unpack(result.pop("archive"), sweep)
                result["folder"] = task.label
                sent = f" (sent back from {result['node']})"
            if "folder" in result:
                _finished(row, sweep / result["folder"], result)
                say(f"[{_count(rows)}/{len(tasks)}] {task.label}: {_verdict(row)}{sent}")
            else:
                why = _failure(result)
                row["failures"].append(f"attempt {result['attempt']}: {why}")
                if result["attempt"] == 1:
                    row["status"] = "retrying"
                    say(f"{task.label}: attempt 1 {why}; retrying it once")
                    pending[submit(task, 2)] = task
                else:
                    failed += 1
                    row["status"] = "failed"
                    row["wall_time_s"] = result.get("wall_time_s")
                    if "work" in result:
                        row["failures"].append(f"its working folder: {result['work']}")
                    say(f"[{_count(rows)}/{len(tasks)}] {task.label}: failed twice ({why})")
            _write_tables(sweep, rows, header, time.perf_counter() - started)
    except KeyboardInterrupt:
        for ref, task in pending.items():
            ray.cancel(ref, force=True)
            rows[task.label]["status"] = "interrupted"
            out = sweep / f".{task.label}.task" / "out"
            if any(out.glob("*.checkpoint")):  # run on this machine, and saved
                argv = ["run", str(task.config), *task.run_options(args.cpus_per_task)]
                command = shlex.join(["python", "-m", "jaxmotion", *argv, "--resume", str(out)])
                rows[task.label]["failures"].append(f"interrupted; continue it with: {command}")
        _write_tables(sweep, rows, header, time.perf_counter() - started)
        print(
            f"sweep interrupted; the finished searches and the table so far are in {sweep}",
            file=sys.stderr,
        )
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
        ray.shutdown()
    _plot(sweep, rows)
    if not args.quiet:
        print((sweep / "sweep.md").read_text(), file=sys.stderr)
    print(sweep)
    return 1 if failed else 0


def _terminate(signum, frame):
    del signum, frame
    raise KeyboardInterrupt


def _row(task: Task, status: str) -> dict[str, Any]:
    return {
        "config": str(task.config),
        "seed": task.seed,
        "overrides": task.overrides,
        "best_fitness": None,
        "check": None,
        "wall_time_s": None,
        "attempts": 0,
        "status": status,
        "folder": None,
        "failures": [],
        "curve": None,
    }


def _count(rows) -> int:
    return sum(r["status"] in ("ok", "failed") for r in rows.values())


def _finished(row: dict[str, Any], folder: Path, result: dict[str, Any]) -> None:
    """Fill a row from a finished task's results folder (a run's or a multi-stage run's)."""
    from .results import read_history_csv

    summary = json.loads((folder / "summary.json").read_text())
    row["status"] = "ok"
    row["folder"] = folder.name
    row["wall_time_s"] = result["wall_time_s"]
    if result.get("resumed"):
        row["failures"].append(f"attempt {result['attempt']} resumed from the checkpoint")
    if "stages" in summary:
        stages = summary["stages"]
        row["best_fitness"] = " / ".join(_number(s["best_fitness"]) for s in stages)
        checks = (
            [summary["check"]]
            if summary.get("check")
            else [s["check"] for s in stages if s["check"]]
        )
        curves = [read_history_csv(folder / s["folder"] / "history.csv").fitness for s in stages]
        row["curve"] = np.concatenate(curves)
    else:
        row["best_fitness"] = _number(summary["best_fitness"])
        checks = [summary["check"]] if summary.get("check") else []
        row["curve"] = read_history_csv(folder / "history.csv").fitness
    if checks:
        row["check"] = "pass" if all(c["passed"] for c in checks) else "FAIL"


def _number(value) -> str:
    """A fitness as summary.json holds it (a number, or "-inf", "nan") for the table: exact
    (`repr`), so the table can be compared with a run's summary."""
    return repr(float(value)) if isinstance(value, int | float) else str(value)


def _verdict(row: dict[str, Any]) -> str:
    check = "" if row["check"] is None else f", check {row['check']}"
    retried = f", attempt {row['attempts']}" if row["attempts"] > 1 else ""
    return f"best fitness {row['best_fitness']}{check}, {row['wall_time_s']:.1f} s{retried}"


COLUMNS = (
    "config",
    "seed",
    "overrides",
    "best_fitness",
    "check",
    "wall_time_s",
    "attempts",
    "status",
    "folder",
    "failures",
)


def _write_tables(sweep: Path, rows: dict[str, dict], header: dict, seconds: float) -> None:
    """sweep.csv and sweep.md, rewritten (atomically) as each task ends: what has finished
    is on disk even if the driver is killed."""
    table = list(rows.values())

    def cell(row, column):
        value = row[column]
        if column == "failures":
            return "; ".join(value)
        if column == "wall_time_s" and value is not None:
            return f"{value:.1f}"
        return "" if value is None else str(value)

    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(COLUMNS)
    for row in table:
        writer.writerow([cell(row, c) for c in COLUMNS])
    _atomic_write(sweep / "sweep.csv", text.getvalue())
    done = sum(r["status"] == "ok" for r in table)
    failed = sum(r["status"] == "failed" for r in table)
    lines = [
        f"# Sweep: {_n(len(table), 'search', 'searches')} ({_n(header['configs'], 'config')} "
        f"x {_n(header['seeds'], 'seed')} x {_n(header['sets'], 'override set')})",
        "",
        f"On {header['where']}, {_n(header['cpus_per_task'], 'CPU')} per search; "
        f"{done} finished, {failed} failed, {len(table) - done - failed} not finished; "
        f"wall time {seconds:.1f} s. Each search is `python -m jaxmotion run CONFIG --seed "
        f"SEED [--set OVERRIDE ...] --cpu-devices {header['cpus_per_task']}`.",
        "",
        "| config | seed | overrides | best fitness | check | wall time (s) | attempts | folder |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in table:
        folder = row["folder"] or row["status"]
        cells = [cell(row, c) or "-" for c in COLUMNS[:7]] + [folder]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    notes = [
        f"- {row['folder'] or row['config']} (seed {row['seed']}): " + "; ".join(row["failures"])
        for row in table
        if row["failures"]
    ]
    if notes:
        lines += ["", "## Failures and retries", "", *notes]
    _atomic_write(sweep / "sweep.md", "\n".join(lines) + "\n")


def _n(count: int, word: str, plural: str | None = None) -> str:
    return f"{count} {word if count == 1 else plural or word + 's'}"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _plot(sweep: Path, rows: dict[str, dict]) -> None:
    """sweep.png: every finished search's learning curve (best fitness so far)."""
    from ..viz import learning_curves

    done = [(label, r["curve"]) for label, r in rows.items() if r["curve"] is not None]
    if not done:
        return
    fig = learning_curves(
        [curve for _, curve in done],
        labels=[label for label, _ in done],
        title=f"sweep: {len(done)} searches",
    )
    if len(done) > 12:
        fig.axes[0].get_legend().remove()
    fig.savefig(sweep / "sweep.png", dpi=120)


__all__ = ["INSTALL", "apply_sets", "override_sets", "parse_seeds", "parse_set", "run_sweep"]
