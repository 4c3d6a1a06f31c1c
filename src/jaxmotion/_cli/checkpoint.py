"""Checkpoints of a running search: written atomically, read back only when they match.

A checkpoint is one file, `<results directory>/<name>-<time>.checkpoint`:

1. the line `jaxmotion-checkpoint 1`;
2. one line of JSON, the header: the format, jaxmotion's, JAX's and equinox's versions, the
   resolved config, and for each search begun (a multi-stage run's stages so far) its
   algorithm, evaluations, the shape and dtype of every leaf and its bytes of the payload;
   the payload's length and SHA-256;
3. the payload: each search's state and history so far, as equinox's leaf serialisation
   (`equinox.tree_serialise_leaves`: one `numpy.save` per leaf, no pickle). PRNG keys are
   stored as their raw key data and wrapped again when read.

It is written to a temporary file in the same folder, flushed to disk and renamed over the
old one (`os.replace`), so a kill at any moment leaves the previous checkpoint or the new
one, never half of one. Reading checks the header, the length and the hash (a truncated or
corrupted file is refused) and that the config and jaxmotion's version are the run's.
"""

import hashlib
import io
import json
import os
import time
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._search.history import History
from .config import ConfigError, Experiment, make_searcher

MAGIC = b"jaxmotion-checkpoint 1\n"
FORMAT = 1
SUFFIX = ".checkpoint"


def _versions() -> dict[str, str]:
    return {
        "jaxmotion": version("jaxmotion"),
        "jax": jax.__version__,
        "equinox": version("equinox"),
    }


def _search_config(experiment) -> dict[str, Any]:
    """What a checkpoint must share with the run that resumes it: the whole resolved config
    (of an `Experiment` or a compose run's `ComposeConfig`) but `[output]` (where and what
    to write does not change the search)."""
    return json.loads(
        json.dumps({k: v for k, v in experiment.config.items() if k != "output"}, sort_keys=True)
    )


def _is_key(a) -> bool:
    return hasattr(a, "dtype") and jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key)


@dataclass
class Progress:
    """What a search has done so far, as its driver's callback reports it: the latest state
    and the `History` of each step up to it (one per seed for serial search). `latest` is set
    in one assignment after the step's history is appended, so an interrupt at any moment
    finds a consistent pair."""

    seeds: int | None = None  # serial search: one History per seed
    parts: list = field(default_factory=list)
    latest: tuple[Any, int] | None = None

    def record(self, state, part) -> None:
        self.parts.append(part)
        self.latest = (state, len(self.parts))

    def history(self, count: int):
        """The history of the first `count` steps (a tuple per seed for serial search)."""
        parts = self.parts[:count]
        if self.seeds is None:
            return History.concatenate(parts)
        return tuple(History.concatenate([p[s] for p in parts]) for s in range(self.seeds))


def _payload(state, history) -> tuple[Any, list[bool]]:
    """The pytree written: the state with its keys as raw data, and the history's arrays."""
    leaves, treedef = jax.tree_util.tree_flatten(state)
    keys = [_is_key(a) for a in leaves]
    plain = [jr.key_data(a) if k else a for a, k in zip(leaves, keys, strict=True)]
    histories = history if isinstance(history, tuple) else (history,)
    arrays = [(h.fitness, h.step) for h in histories]
    return (jax.tree_util.tree_unflatten(treedef, plain), arrays), keys


def _searches(experiment: Experiment) -> tuple[Experiment, ...]:
    """The single-search experiments a run is made of: its stages, or itself."""
    return experiment.stages or (experiment,)


def state_to_bytes(state, history) -> tuple[bytes, dict[str, Any]]:
    """One search's state and history (a `History`, or a tuple of one per run) as the
    checkpoint's bytes, and the header part that describes them (`state_from_bytes` reads
    them back)."""
    tree, keys = _payload(state, history)
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, tree)
    histories = history if isinstance(history, tuple) else (history,)
    part = {
        "evaluations": int(sum(len(h) for h in histories)),
        "leaves": [
            [list(np.shape(a)), str(np.asarray(a).dtype)] for a in jax.tree_util.tree_leaves(tree)
        ],
        "keys": [i for i, k in enumerate(keys) if k],
        "key_impl": [str(jr.key_impl(a)) for a in jax.tree_util.tree_leaves(state) if _is_key(a)],
        "bytes": len(buffer.getvalue()),
    }
    return buffer.getvalue(), part


def state_from_bytes(template, part: dict[str, Any], payload: bytes, runs: int | None):
    """The `(state, history)` that `state_to_bytes` wrote, given a state of the same
    structure (`template`: a searcher's `template(task)`) and the number of histories
    (`runs`: one per run, or `None` for a single `History`).

    **Raises:** `ValueError` when the bytes do not fit the template."""
    shapes = part["leaves"]
    histories = 1 if runs is None else runs
    state_leaves = len(shapes) - 2 * histories
    treedef = jax.tree_util.tree_structure(template)
    if treedef.num_leaves != state_leaves:
        raise ValueError(f"{len(shapes)} leaves")
    state_like = [jax.ShapeDtypeStruct(tuple(s), jnp.dtype(d)) for s, d in shapes[:state_leaves]]
    history_like = [np.empty(tuple(s), dtype=d) for s, d in shapes[state_leaves:]]
    like = (
        jax.tree_util.tree_unflatten(treedef, state_like),
        [tuple(history_like[2 * i : 2 * i + 2]) for i in range(histories)],
    )
    state, arrays = eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    leaves, treedef = jax.tree_util.tree_flatten(state)
    impls = iter(part.get("key_impl", []))
    leaves = [
        jr.wrap_key_data(a, impl=next(impls)) if i in part["keys"] else a
        for i, a in enumerate(leaves)
    ]
    state = jax.tree_util.tree_unflatten(treedef, leaves)
    history = tuple(History(f, s) for f, s in arrays)
    return state, (history if runs is not None else history[0])


def save_checkpoint(path: Path, experiment: Experiment, searches) -> None:
    """Write `searches`, a `(state, history)` pair for each search the run has begun (a
    single search: one; a multi-stage run: each stage so far, the last one in progress;
    `history` a `History`, or one per seed), to `path` atomically (a temporary file beside
    it, flushed, then `os.replace`)."""
    payload, parts = b"", []
    for (state, history), search in zip(searches, _searches(experiment), strict=False):
        data, part = state_to_bytes(state, history)
        parts.append({"algorithm": search.search["algorithm"], **part})
        payload += data
    _write(path, experiment.name, _search_config(experiment), parts, payload)


def _write(path: Path, name: str, config: dict[str, Any], parts: list, payload: bytes) -> None:
    """The checkpoint file (header, then payload), written atomically."""
    header = {
        "format": FORMAT,
        **_versions(),
        "name": name,
        "config": config,
        "saved": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "searches": parts,
        "payload_bytes": len(payload),
        "payload_sha256": hashlib.sha256(payload).hexdigest(),
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with tmp.open("wb") as f:
        f.write(MAGIC)
        f.write(json.dumps(header).encode() + b"\n")
        f.write(payload)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_header(path: Path) -> tuple[dict[str, Any], bytes]:
    """A checkpoint's header and payload, checked for completeness.

    **Raises:** `ConfigError` for a file that is not a checkpoint, or one truncated or
    corrupted."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise ConfigError(f"--resume {path}: cannot read it ({e.strerror or e})") from None
    if not data.startswith(MAGIC):
        raise ConfigError(f"--resume {path}: not a jaxmotion checkpoint")
    end = data.find(b"\n", len(MAGIC))
    try:
        header = json.loads(data[len(MAGIC) : end])
        size, digest = header["payload_bytes"], header["payload_sha256"]
    except (ValueError, KeyError, TypeError):
        raise ConfigError(f"--resume {path}: its header is damaged (truncated?)") from None
    payload = data[end + 1 :]
    if len(payload) != size or hashlib.sha256(payload).hexdigest() != digest:
        raise ConfigError(
            f"--resume {path}: truncated or corrupted ({len(payload)} of {size} payload bytes, "
            "hash mismatch); allowed: a checkpoint written whole"
        )
    return header, payload


def load_checkpoint(path: Path, experiment: Experiment) -> list[tuple[Any, Any]]:
    """The `(state, history)` of each search a checkpoint of `experiment` holds (a single
    search: one; a multi-stage run: each stage begun, in order; see `save_checkpoint`).

    **Raises:** `ConfigError` for a checkpoint that is truncated or corrupted, of another
    config, of another jaxmotion version or checkpoint format, or that does not fit the
    search's state."""
    header, payload = read_header(path)
    _check_identity(path, header, _search_config(experiment))
    try:
        out, start = [], 0
        for part, search in zip(header["searches"], _searches(experiment), strict=False):
            out.append(_restore(search, part, payload[start : start + part["bytes"]]))
            start += part["bytes"]
        if not out or len(out) > len(_searches(experiment)) or start != len(payload):
            raise ValueError(f"{len(header['searches'])} searches")
        return out
    except (KeyError, TypeError, ValueError, RuntimeError, OSError, StopIteration) as e:
        raise ConfigError(
            f"--resume {path}: its contents do not fit this config's search ({e})"
        ) from None


def _check_identity(path: Path, header: dict[str, Any], mine: dict[str, Any]) -> None:
    """Refuse a checkpoint of another format, jaxmotion version or config (`ConfigError`)."""
    if header.get("format") != FORMAT or header.get("jaxmotion") != version("jaxmotion"):
        raise ConfigError(
            f"--resume {path}: written by jaxmotion {header.get('jaxmotion')!r} (checkpoint "
            f"format {header.get('format')!r}); allowed: a checkpoint of this version "
            f"({version('jaxmotion')}, format {FORMAT})"
        )
    if header.get("config") != mine:
        theirs = header.get("config") if isinstance(header.get("config"), dict) else {}
        differ = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        raise ConfigError(
            f"--resume {path}: a checkpoint of another config (differs in: "
            f"{', '.join(differ)}); allowed: a checkpoint of this very config and options"
        )


def save_transitions_checkpoint(path: Path, compose, searches) -> None:
    """Write a compose run's transition search (`compose`: its `ComposeConfig`; `searches`:
    its one `(state, history)` so far) to `path` atomically, in the format of a run's
    checkpoint."""
    ((state, history),) = searches
    data, part = state_to_bytes(state, history)
    parts = [{"algorithm": "transition_search", **part}]
    _write(path, compose.name, _compose_identity(compose), parts, data)


def _compose_identity(compose) -> dict[str, Any]:
    """What a compose checkpoint must share with the run that resumes it: its config and
    its components' controllers (a digest of each, in order), so that a component's
    results folder rewritten between the stop and the resume is noticed even though the
    config, which names the folder, is unchanged."""
    from .results import controller_to_dict

    def digest(controller) -> str:
        text = json.dumps(controller_to_dict(controller), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    controllers = [digest(controller) for _, _, controller in compose.phases]
    return {**_search_config(compose), "component_controllers": controllers}


def load_transitions_checkpoint(path: Path, compose, searcher):
    """The `(state, history)` of a compose run's checkpoint (`searcher`: its
    `TransitionSearch`, whose `template` describes the state).

    **Raises:** `ConfigError` as `load_checkpoint` does."""
    header, payload = read_header(path)
    _check_identity(path, header, _compose_identity(compose))
    try:
        (part,) = header["searches"]
        if part["algorithm"] != "transition_search" or part["bytes"] != len(payload):
            raise ValueError(f"a {part['algorithm']} search")
        template = searcher.template(compose.composite)
        return state_from_bytes(template, part, payload, None)
    except (KeyError, TypeError, ValueError, RuntimeError, OSError) as e:
        raise ConfigError(
            f"--resume {path}: its contents do not fit this composite's search ({e})"
        ) from None


def _restore(experiment: Experiment, header: dict[str, Any], payload: bytes):
    """The state and history of one search of a checkpoint whose header checked out
    (`header`: that search's part of it)."""
    algorithm = experiment.search["algorithm"]
    if header["algorithm"] != algorithm:
        raise ValueError(f"a {header['algorithm']} search")
    searcher = make_searcher(experiment.search)[0]
    runs = experiment.search["runs"] if searcher.per_run else None
    return state_from_bytes(searcher.template(experiment.task), header, payload, runs)


def find_checkpoint(path: Path, experiment: Experiment) -> Path:
    """The checkpoint `--resume PATH` names: the file itself, or in a results directory the
    newest `<name>-<time>.checkpoint` of this experiment.

    **Raises:** `ConfigError` if there is none."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise ConfigError(f"--resume {path}: no such checkpoint file or results directory")
    if (path / "summary.json").is_file():
        raise ConfigError(
            f"--resume {path}: a complete results folder (nothing to resume); allowed: a "
            "checkpoint file or the results directory that holds one"
        )
    found = sorted(
        path.glob(f"{experiment.name}-*{SUFFIX}"), key=lambda p: p.stat().st_mtime, reverse=True
    )
    if not found:
        raise ConfigError(
            f"--resume {path}: no checkpoint of {experiment.name!r} in it "
            f"({experiment.name}-<time>{SUFFIX})"
        )
    return found[0]
