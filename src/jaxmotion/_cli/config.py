"""Experiment configs (TOML): the schema, its checks, and building the objects it names.

Everything here runs before JAX compiles anything, so a bad config fails fast with a message
naming the key, the value and what is allowed.
"""

import inspect
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import figures, lattices
from .._control.regimes import RegimesSpace
from .._control.sense_bsr import SenseBSRSpace
from .._control.spring_net import SpringNetSpace
from .._control.time_bsr import TimeBSRSpace
from .._objective.registry import Objective
from .._search.evosax import INSTALL as EVOSAX_INSTALL
from .._search.evosax import STRATEGIES as EVOSAX_STRATEGIES
from .._search.evosax import require_evosax
from .._search.protocol import SEARCHERS, AbstractSearcher
from .._sim.robust import Robustness
from .._sim.simulate import time_grid
from .._task import Task
from .._world import World


class ConfigError(ValueError):
    """A config that cannot be run; the message names the key, the value and what is
    allowed."""


_REQUIRED = object()

FLOAT32_MAX = 3.4028234663852886e38
"""The largest float32: the simulations run in float32, so a number beyond it would become
infinite inside the first compiled call."""

# Upper bounds on the sizes a config may ask for, checked before anything compiles: far
# beyond any shipped config, and far below what overflows XLA's static shapes (a search set
# of 2**62 aborted the process inside XLA, leaving a partial results folder behind).
MAX_BATCH = 10_000  # controllers in a search set or one call (batch, climbers x runs)
MAX_EVALUATIONS = 1_000_000_000
MAX_GENERATIONS = 100_000_000
MAX_RULES = 1_000  # regimes, rules of a BSR controller
MAX_MASSES = 200  # a spring net's masses (n (n - 1) / 2 springs)
MAX_STEPS = 10_000_000  # fixed steps of one simulation (e.g. 10,000 s at dt = 1 ms)
MAX_SAVES = 100_000  # saved samples of one simulation (what the objectives see)
MAX_SAVED = 10_000_000  # saved samples of one call: controllers in it x samples of each
MAX_SAMPLES = 1_000  # random starts per evaluation (robustness), mutations per offspring


def read_toml(path: Path) -> dict[str, Any]:
    """A config file's table. **Raises:** `ConfigError` for a missing file or bad TOML."""
    try:
        with Path(path).open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None


@dataclass(frozen=True)
class Key:
    """One config key: its type, default and a check returning what is allowed (or None)."""

    kind: str  # "number", "integer", "bool", "string", "numbers", "strings"
    default: Any = _REQUIRED
    check: Callable[[Any], bool] | None = None
    allowed: str = ""
    length: int | None = None


def _positive(v):
    return v > 0


def _nonnegative(v):
    return v >= 0


def _describe(kind: str, allowed: str, length: int | None) -> str:
    base = {
        "number": "a number",
        "integer": "an integer",
        "bool": "true or false",
        "string": "a string",
        "numbers": f"a list of {length} numbers" if length else "a list of numbers",
        "strings": "a list of strings",
    }[kind]
    return f"{base} {allowed}".strip()


def _check_value(where: str, name: str, spec: Key, value: Any) -> Any:
    what = _describe(spec.kind, spec.allowed, spec.length)

    def fail():
        return ConfigError(f"{where} {name} = {value!r}; allowed: {what}")

    if spec.kind == "number":
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise fail()
        if abs(value) > FLOAT32_MAX:
            raise _too_large(where, name, value, what)
        value = float(value)
    elif spec.kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail()
    elif spec.kind == "bool":
        if not isinstance(value, bool):
            raise fail()
    elif spec.kind == "string":
        if not isinstance(value, str):
            raise fail()
    elif spec.kind == "numbers":
        if not isinstance(value, list) or any(
            isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
            for v in value
        ):
            raise fail()
        if spec.length is not None and len(value) != spec.length:
            raise fail()
        if any(abs(v) > FLOAT32_MAX for v in value):
            raise _too_large(where, name, value, what)
        value = [float(v) for v in value]
    elif spec.kind == "strings":
        if not isinstance(value, list) or any(not isinstance(v, str) for v in value):
            raise fail()
        value = list(value)
    if spec.check is not None and not spec.check(value):
        raise fail()
    return value


def _too_large(where: str, name: str, value: Any, what: str) -> "ConfigError":
    return ConfigError(
        f"{where} {name} = {value!r}; allowed: {what}, of magnitude at most "
        f"{FLOAT32_MAX:.4g} (the simulations run in float32)"
    )


def _check_objective_numbers(table: Mapping[str, Any]) -> None:
    """Every weight and numeric option of an [objective] table within float32 (the
    `Objective` itself checks the terms, options and types)."""
    for label, value in table.items():
        entries = value.items() if isinstance(value, Mapping) else [(None, value)]
        for option, v in entries:
            if isinstance(v, bool) or not isinstance(v, int | float):
                continue
            if not math.isfinite(v) or abs(v) > FLOAT32_MAX:
                name = label if option is None else f"{label}.{option}"
                raise ConfigError(
                    f"[objective] {name} = {v!r}; allowed: a finite number of magnitude at "
                    f"most {FLOAT32_MAX:.4g} (the simulations run in float32)"
                )


def _read_section(where: str, table: Any, schema: Mapping[str, Key]) -> dict[str, Any]:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table of keys; got {table!r}")
    out: dict[str, Any] = {}
    for name, value in table.items():
        if name not in schema:
            allowed = ", ".join(schema) or "(no keys)"
            raise ConfigError(f"{where} has an unknown key {name!r}; allowed: {allowed}")
        out[name] = _check_value(where, name, schema[name], value)
    for name, spec in schema.items():
        if name not in out:
            if spec.default is _REQUIRED:
                raise ConfigError(
                    f"{where} is missing the key {name!r} "
                    f"({_describe(spec.kind, spec.allowed, spec.length)})"
                )
            if spec.default is not None:
                out[name] = spec.default
    return out


# ----------------------------------------------------------------------------------- bodies

FAMILY_KEYS = ("lattice", "figure")

LATTICE_BUILDERS: dict[str, Callable] = {
    "cube": lattices.cube,
    "pyramid": lattices.pyramid,
    "chair": lattices.chair,
}


def _builder_schema(builder: Callable) -> dict[str, Key]:
    schema = {}
    for p in inspect.signature(builder).parameters.values():
        schema[p.name] = Key("number", float(p.default), _positive, "> 0")
    return schema


FIGURE_BUILDERS: dict[str, Callable] = {
    "star_man": figures.star_man,
    "beryl_biped": figures.beryl_biped,
    "cujo": figures.cujo,
    "rex": figures.rex,
    "bob": figures.bob,
    "snake": figures.snake,
    "luxo": figures.luxo,
}


def _takes_torque(builder: Callable) -> bool:
    """Whether a figure builder can limit its joints' torque (the planar figures)."""
    return "max_torque" in inspect.signature(builder).parameters


def _body_schema(table: Mapping) -> tuple[dict[str, Key], Callable, str]:
    """The [body] schema: `lattice = NAME` (and the builder's sizes) or `figure = NAME`."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"[body] must be a table of keys; got {table!r}")
    if "figure" in table:
        if "lattice" in table:
            raise ConfigError(
                "[body] names both a lattice and a figure; allowed: one of `lattice = ...` "
                "or `figure = ...`"
            )
        kind = table["figure"]
        if not isinstance(kind, str) or kind not in FIGURE_BUILDERS:
            raise ConfigError(
                f"[body] figure = {kind!r}; allowed: one of {', '.join(map(repr, FIGURE_BUILDERS))}"
            )
        builder = FIGURE_BUILDERS[kind]
        if "max_torque" in table and not _takes_torque(builder):
            planar = ", ".join(name for name, b in FIGURE_BUILDERS.items() if _takes_torque(b))
            raise ConfigError(
                f"[body] max_torque = {table['max_torque']!r} for figure = {kind!r}, a 3D "
                f"figure; allowed: only for the planar figures ({planar}): torque-limited "
                "joints are implemented for planar figures"
            )
        schema = {"figure": Key("string", _REQUIRED)}
        if _takes_torque(builder):
            schema["max_torque"] = Key(
                "number", None, _nonnegative, ">= 0 (N m: the joints' strength; unset: kinematic)"
            )
        return schema, builder, "figure"
    kind = table.get("lattice", "cube")
    if not isinstance(kind, str) or kind not in LATTICE_BUILDERS:
        raise ConfigError(
            f"[body] lattice = {kind!r}; allowed: one of {', '.join(map(repr, LATTICE_BUILDERS))}"
        )
    builder = LATTICE_BUILDERS[kind]
    schema = {"lattice": Key("string", "cube")}
    schema.update(_builder_schema(builder))
    return schema, builder, "lattice"


# ---------------------------------------------------------------------------- the sections

WORLD = {
    "gravity": Key("number", 9.81, _nonnegative, ">= 0 (m/s^2)"),
    "floor": Key("bool", True),
    "floor_stiffness": Key("number", 2.0e4, _positive, "> 0 (N/m)"),
    "floor_damping": Key("number", 200.0, _nonnegative, ">= 0 (N s/m)"),
    "friction": Key("number", 0.8, _nonnegative, ">= 0"),
    "friction_preferred": Key("number", None, _nonnegative, ">= 0"),
    "friction_direction": Key(
        "numbers", None, lambda v: math.hypot(*v) > 0, "(dx, dy), not both zero", length=2
    ),
    "friction_velocity": Key("number", 0.05, _positive, "> 0 (m/s)"),
}

CONTROLLER = {
    "family": Key("string", "regimes", lambda v: v == "regimes", '"regimes" (for a lattice)'),
    "num_regimes": Key("integer", 4, lambda v: 1 <= v <= MAX_RULES, f">= 1, at most {MAX_RULES}"),
    "t_per": Key("number", 1.0, _positive, "> 0 (s)"),
    "amplitudes": Key(
        "numbers",
        [0.3, 0.3, 0.3, 0.5],
        lambda v: min(v) >= 0 and v[0] < 1 and v[2] < 1,
        "(scale, shear, splay, twist) >= 0, scale and splay < 1",
        length=4,
    ),
}

TIME_BSR = {
    "family": Key("string", "time_bsr", lambda v: v == "time_bsr", '"time_bsr" (for a figure)'),
    "num_rules": Key("integer", 4, lambda v: 1 <= v <= MAX_RULES, f">= 1, at most {MAX_RULES}"),
    "t_per": Key("number", 1.0, _positive, "> 0 (s)"),
    "tau_min": Key("number", None, _positive, "> 0 (s; default 2 dt, the second paper's)"),
    "tau_max": Key("number", None, _positive, "> 0 (s; default duration / 4)"),
    "creep": Key("number", 0.1, lambda v: 0 < v <= 1, "in (0, 1]"),
    "reinit_probability": Key("number", 1 / 3, lambda v: 0 <= v <= 1, "in [0, 1]"),
    "mirror": Key("bool", False),
}

SENSE_BSR = {
    "family": Key("string", "sense_bsr", lambda v: v == "sense_bsr", '"sense_bsr" (for a figure)'),
    "num_rules": Key(
        "integer",
        10,
        lambda v: 1 <= v <= MAX_RULES,
        f">= 1, at most {MAX_RULES} (the second paper: 10)",
    ),
    "tau_min": TIME_BSR["tau_min"],
    "tau_max": TIME_BSR["tau_max"],
    "filter_time": Key("number", 0.0, _nonnegative, ">= 0 (s; 0: no low-pass filter)"),
    "creep": TIME_BSR["creep"],
    "reinit_probability": TIME_BSR["reinit_probability"],
    "relevance": Key(
        "string",
        None,
        lambda v: v in ("corner", "contain", "none"),
        '"corner" (2D default), "contain" (3D default) or "none"',
    ),
    "mirror": Key("bool", False),
}

SPRING_NET = {
    "family": Key(
        "string", "spring_net", lambda v: v == "spring_net", '"spring_net" (for a figure)'
    ),
    "num_masses": Key(
        "integer",
        4,
        lambda v: 2 <= v <= MAX_MASSES,
        f">= 2 and >= the figure's free joint angles, at most {MAX_MASSES}",
    ),
    "tau": Key("number", 0.1, _positive, "> 0 (s; the joints' time constant)"),
    "mass_min": Key("number", 0.5, _positive, "> 0 (kg)"),
    "mass_max": Key("number", 2.0, _positive, "> 0 (kg)"),
    "stiffness_min": Key("number", 1.0, _positive, "> 0 (N/m)"),
    "stiffness_max": Key("number", 50.0, _positive, "> 0 (N/m)"),
    "scale": Key("number", 0.3, _positive, "> 0 (the mutations' step)"),
    "damping": Key("number", 0.0, _nonnegative, ">= 0 (1/s)"),
}

# The controller families of each kind of body, the default first.
FAMILIES = {
    "lattice": {"regimes": CONTROLLER},
    "figure": {"time_bsr": TIME_BSR, "sense_bsr": SENSE_BSR, "spring_net": SPRING_NET},
}


def _controller_schema(table: Any, body_kind: str) -> dict[str, Key]:
    families = FAMILIES[body_kind]
    default = next(iter(families))
    given = table.get("family", default) if isinstance(table, Mapping) else default
    if not isinstance(given, str):
        raise ConfigError(
            f"[controller] family = {given!r}; allowed: a string, one of "
            f"{', '.join(repr(f) for f in families)}"
        )
    if given not in families:
        known = {f for kinds in FAMILIES.values() for f in kinds}
        what = "an articulated figure" if body_kind == "figure" else "a mass-spring lattice"
        allowed = " or ".join(repr(f) for f in families)
        if given in known:
            raise ConfigError(
                f"[controller] family = {given!r} does not control {what}; allowed: "
                f"family = {allowed} for the [body] given"
            )
        raise ConfigError(f"[controller] family = {given!r}; allowed: {allowed} for {what}")
    return families[given]


SIMULATION = {
    "duration": Key("number", _REQUIRED, _positive, "> 0 (s)"),
    "dt": Key("number", 1e-3, _positive, "> 0 (s)"),
    "save_dt": Key("number", 0.02, _positive, "> 0 (s)"),
    "control_dt": Key(
        "number", None, _positive, "> 0 (s; the control period, a whole number of dt; default dt)"
    ),
    "second_dt": Key(
        "number",
        None,
        _positive,
        "> 0 (s; a shorter step that divides the control period: each controller is also "
        "simulated with it and scored by the lower fitness)",
    ),
}

SEARCHER_NAMES = tuple(SEARCHERS)

SEARCH = {
    "algorithm": Key(
        "string",
        "parallel_hill_climb",
        lambda v: v in SEARCHES,
        " or ".join([", ".join(f'"{n}"' for n in SEARCHER_NAMES[:-1]), f'"{SEARCHER_NAMES[-1]}"']),
    ),
    "evaluations": Key(
        "integer", 25_000, lambda v: 1 <= v <= MAX_EVALUATIONS, f">= 1, at most {MAX_EVALUATIONS}"
    ),
    "size": Key("integer", 100, lambda v: 1 <= v <= MAX_BATCH, f">= 1, at most {MAX_BATCH}"),
    "batch": Key("integer", 1, lambda v: 1 <= v <= MAX_BATCH, f">= 1, at most {MAX_BATCH}"),
    "accurate_candidates": Key(
        "integer",
        0,
        lambda v: 0 <= v <= MAX_BATCH,
        f">= 0, at most {MAX_BATCH} (the final set's fittest, serial search's fittest held, "
        "replayed accurately to choose the best; 0: off)",
    ),
}

SERIAL_SEARCH = {
    "algorithm": SEARCH["algorithm"],
    "climbers": Key(
        "integer",
        10,
        lambda v: 1 <= v <= MAX_BATCH,
        f">= 1, at most {MAX_BATCH} (the second paper: C = 10)",
    ),
    "generations": Key(
        "integer",
        4000,
        lambda v: 1 <= v <= MAX_GENERATIONS,
        f">= 1, at most {MAX_GENERATIONS} (G = 4,000)",
    ),
    "reseed_every": Key(
        "integer",
        200,
        lambda v: 1 <= v <= MAX_GENERATIONS,
        f">= 1, at most {MAX_GENERATIONS} (R = 200)",
    ),
    "enrich": Key(
        "integer",
        0,
        lambda v: 0 <= v <= MAX_SAMPLES,
        f">= 0, at most {MAX_SAMPLES} (rounds of relevance-heuristic reinitialisation of the first "
        "set; sense_bsr)",
    ),
    "runs": Key(
        "integer",
        1,
        lambda v: 1 <= v <= MAX_BATCH,
        f">= 1, at most {MAX_BATCH} (independent runs batched together; best kept)",
    ),
    "accurate_candidates": SEARCH["accurate_candidates"],
}

EVOLVE = {
    "algorithm": SEARCH["algorithm"],
    "generations": Key(
        "integer",
        20,
        lambda v: 1 <= v <= MAX_GENERATIONS,
        f">= 1, at most {MAX_GENERATIONS} (the first, random, one included; the paper: 20)",
    ),
    "size": Key(
        "integer",
        2000,
        lambda v: 5 <= v <= MAX_BATCH and v % 5 == 0,
        f">= 5, a multiple of 5, at most {MAX_BATCH} (the population; the paper: 2,000)",
    ),
    "mutations": Key(
        "integer",
        3,
        lambda v: 1 <= v <= MAX_SAMPLES,
        f">= 1, at most {MAX_SAMPLES} (each offspring gets 1..mutations)",
    ),
    "accurate_candidates": SEARCH["accurate_candidates"],
}

EVOSAX = {
    "algorithm": SEARCH["algorithm"],
    "strategy": Key(
        "string",
        "CMA_ES",
        lambda v: v in EVOSAX_STRATEGIES,
        "(an evosax strategy): " + ", ".join(f'"{n}"' for n in EVOSAX_STRATEGIES),
    ),
    "population": Key(
        "integer",
        32,
        lambda v: 2 <= v <= MAX_BATCH,
        f">= 2, at most {MAX_BATCH} (candidates per generation; even for Open_ES and PGPE)",
    ),
    "generations": Key(
        "integer",
        100,
        lambda v: 1 <= v <= MAX_GENERATIONS,
        f">= 1, at most {MAX_GENERATIONS} (after the random set)",
    ),
    "size": Key(
        "integer",
        100,
        lambda v: 1 <= v <= MAX_BATCH,
        f">= 1, at most {MAX_BATCH} (random controllers first; the best is the template)",
    ),
    "std_init": Key("number", 0.5, _positive, "> 0 (in units of each parameter's spread)"),
    "learning_rate": Key(
        "number", 0.05, _positive, "> 0 (Adam's, for Open_ES, SNES, xNES, PGPE, SimpleES)"
    ),
    "accurate_candidates": SEARCH["accurate_candidates"],
}


@dataclass(frozen=True)
class SearchConfig:
    """What the config layer knows of a registered searcher (`jaxmotion.SEARCHERS`): its
    [search] keys and how they make the searcher and its budget. A new searcher is
    registered (`jaxmotion.register_searcher`) and gets one entry in `SEARCHES`.

    - `keys`: the [search] schema (`algorithm` included).
    - `make`: the searcher of a checked section.
    - `steps`: the steps it makes after its `init`, and how many of the last one's
        evaluations count (`None`: all).
    - `initial`, `per_step`: the evaluations of its `init` and of one step.
    - `width`: the controllers of one evaluation call, and the keys that make it (errors).
    - `describe`: the section in words (the plan the CLI prints).
    """

    keys: dict[str, Key]
    make: Callable[[Mapping[str, Any]], AbstractSearcher]
    steps: Callable[[Mapping[str, Any]], tuple[int, int | None]]
    initial: Callable[[Mapping[str, Any]], int]
    per_step: Callable[[Mapping[str, Any]], int]
    width: Callable[[Mapping[str, Any]], tuple[int, str]]
    describe: Callable[[Mapping[str, Any]], str]


def _hill_climb(s: Mapping[str, Any]) -> AbstractSearcher:
    return SEARCHERS["parallel_hill_climb"](size=s["size"], batch=s["batch"])


def _serial(s: Mapping[str, Any]) -> AbstractSearcher:
    # An accurate choice among many (`accurate_candidates`) draws from the archive of the
    # fittest controllers held: the final climbers are few and alike (SerialSearch).
    return SEARCHERS["serial_search"](
        climbers=s["climbers"],
        reseed_every=s["reseed_every"],
        enrich=s["enrich"],
        seeds=s["runs"],
        archive=s["accurate_candidates"],
    )


def _evosax(s: Mapping[str, Any]) -> AbstractSearcher:
    return SEARCHERS["evosax"](
        strategy=s["strategy"],
        population=s["population"],
        size=s["size"],
        std_init=s["std_init"],
        learning_rate=s["learning_rate"],
    )


SEARCHES: dict[str, SearchConfig] = {
    "parallel_hill_climb": SearchConfig(
        keys=SEARCH,
        make=_hill_climb,
        steps=lambda s: _hill_climb(s).plan(s["evaluations"]),
        initial=lambda s: s["size"],
        per_step=lambda s: s["batch"],
        width=lambda s: (s["batch"], f"batch = {s['batch']}"),
        describe=lambda s: (
            f"{s['evaluations']} evaluations, search set {s['size']}, batch {s['batch']}"
        ),
    ),
    "serial_search": SearchConfig(
        keys=SERIAL_SEARCH,
        make=_serial,
        steps=lambda s: (s["generations"], None),
        initial=lambda s: s["runs"] * s["climbers"] * (1 + s["enrich"]),
        per_step=lambda s: s["runs"] * s["climbers"],
        width=lambda s: (
            s["runs"] * s["climbers"],
            f"runs = {s['runs']} x climbers = {s['climbers']}",
        ),
        describe=lambda s: (
            f"serial search, {s['climbers']} climbers x {s['generations']} generations x "
            f"{s['runs']} runs, reseeding every {s['reseed_every']}"
        ),
    ),
    "evolve": SearchConfig(
        keys=EVOLVE,
        make=lambda s: SEARCHERS["evolve"](size=s["size"], mutations=s["mutations"]),
        # Its generations count the random first one (`init`).
        steps=lambda s: (s["generations"] - 1, None),
        initial=lambda s: s["size"],
        # Survivors keep their fitness: each later generation evaluates 4/5 of the size.
        per_step=lambda s: s["size"] * 4 // 5,
        width=lambda s: (s["size"] * 4 // 5, f"4/5 of size = {s['size']}"),
        describe=lambda s: (
            f"evolution, {s['generations']} generations of {s['size']} "
            f"({search_evaluations(s)} evaluations), up to {s['mutations']} mutations per "
            "offspring"
        ),
    ),
    "evosax": SearchConfig(
        keys=EVOSAX,
        make=_evosax,
        steps=lambda s: (s["generations"], None),
        initial=lambda s: s["size"],
        per_step=lambda s: s["population"],
        width=lambda s: (s["population"], f"population = {s['population']}"),
        describe=lambda s: (
            f"evosax {s['strategy']}, {s['size']} random controllers then {s['generations']} "
            f"generations of {s['population']} ({search_evaluations(s)} evaluations), "
            f"std_init {s['std_init']}"
        ),
    ),
}
"""The [search] sections of every registered searcher, by its name."""
assert set(SEARCHES) == set(SEARCHERS), "every registered searcher needs its [search] keys"

ROBUSTNESS = {
    "samples": Key(
        "integer",
        4,
        lambda v: 1 <= v <= MAX_SAMPLES,
        f">= 1, at most {MAX_SAMPLES} (random starts per evaluation)",
    ),
    "angles": Key("number", 0.1, _nonnegative, ">= 0 (rad, each free joint angle)"),
    "orientation": Key("number", 0.1, _nonnegative, ">= 0 (rad, the root's turn)"),
    "velocity": Key("number", 0.2, _nonnegative, ">= 0 (m/s, each component)"),
    "reduce": Key("string", "mean", lambda v: v in ("mean", "worst"), '"mean" or "worst"'),
    "common": Key("bool", False),
    "nominal": Key("bool", False),
}


def _check_searcher(search: Mapping[str, Any]) -> None:
    """The searcher's own checks (e.g. an even population for Open_ES) and its optional
    dependency, as a `ConfigError` before anything compiles."""
    if search["algorithm"] == "evosax":
        try:
            require_evosax()
        except ImportError:
            raise ConfigError(
                '[search] algorithm = "evosax" needs the evosax package; install it with: '
                f"{EVOSAX_INSTALL}"
            ) from None
    try:
        make_searcher(search)
    except ValueError as e:
        raise ConfigError(f"[search] {e}") from None


def _search_schema(table: Any) -> dict[str, Key]:
    algorithm = (
        table.get("algorithm", "parallel_hill_climb")
        if isinstance(table, Mapping)
        else "parallel_hill_climb"
    )
    config = SEARCHES.get(algorithm) if isinstance(algorithm, str) else None
    return SEARCH if config is None else config.keys


def make_searcher(search: Mapping[str, Any]) -> tuple[AbstractSearcher, int, int | None]:
    """The searcher a checked [search] section describes (from the registry), the steps it
    makes after its `init`, and how many of the last step's evaluations count (`None`: all):
    what `jaxmotion.drive` takes."""
    config = SEARCHES[search["algorithm"]]
    return (config.make(search), *config.steps(search))


def search_evaluations(search: Mapping[str, Any]) -> int:
    """How many simulations a checked [search] section asks for (initial sets included)."""
    config = SEARCHES[search["algorithm"]]
    steps, last = config.steps(search)
    if steps == 0:
        return config.initial(search)
    per_step = config.per_step(search)
    return config.initial(search) + (steps - 1) * per_step + (per_step if last is None else last)


def search_plan(search: Mapping[str, Any]) -> str:
    """A checked [search] section in words, e.g. "serial search, 10 climbers x 1000
    generations x 1 runs, reseeding every 200"."""
    return SEARCHES[search["algorithm"]].describe(search)


EXPORT_FORMATS = ("bvh", "usd")  # what `[output] export` and `python -m jaxmotion export` write

OUTPUT = {
    "directory": Key(
        "string",
        "results",
        lambda v: bool(v.strip()) and "\x00" not in v,
        "(a path: not empty, no NUL character)",
    ),
    "animation": Key("bool", True),
    "fps": Key("integer", 25, lambda v: 1 <= v <= 100, "from 1 to 100"),
    # Files for the animators' tools written into the results folder (optional: a config
    # without it resolves as before).
    "export": Key(
        "strings",
        None,
        lambda v: all(f in EXPORT_FORMATS for f in v) and len(set(v)) == len(v),
        "each one of " + ", ".join(f'"{f}"' for f in EXPORT_FORMATS) + " (no repeats)",
    ),
}


def _check_export(output_cfg: Mapping[str, Any], body_kind: str, body_cfg: Mapping) -> None:
    """`[output] export` against the body: BVH needs a figure's skeleton."""
    formats = output_cfg.get("export") or []
    if "bvh" in formats and body_kind != "figure":
        raise ConfigError(
            f"[output] export = {formats!r}: BVH exports articulated figures; this config's "
            f"[body] is a lattice ({body_cfg.get(body_kind, body_kind)!r}); allowed: no "
            '"bvh" for a lattice'
        )


CHECK = {
    "motion": Key(
        "string",
        _REQUIRED,
        lambda v: (
            v
            in (
                "leap",
                "somersault",
                "pirouette",
                "shuffle",
                "cartwheel",
                "bound",
                "jump",
                "walk",
                "walk_turn_walk",
                "hop",
                "roll",
                "hop_or_roll",
            )
        ),
        '"leap", "somersault", "pirouette", "shuffle", "cartwheel", "bound", "jump", "walk", '
        '"hop", "roll", "hop_or_roll" or "walk_turn_walk" (a sequence of [[stage]]s)',
    ),
}

# Checks of a whole sequence of stages (they take the stages' trajectories in order) and
# how many stages each needs.
SEQUENCE_CHECKS = {"walk_turn_walk": 3}
# Checks that need the body's feet.
FOOT_CHECKS = ("walk", "walk_turn_walk")

TOP = {
    "name": Key(
        "string",
        None,
        lambda v: (
            0 < len(v) <= 100
            and v.isascii()
            and not v.startswith(".")
            and all(c.isalnum() or c in "-_." for c in v)
        ),
        "of 1 to 100 ASCII letters, digits, '-', '_' or '.', not starting with '.'",
    ),
    "seed": Key("integer", 0, lambda v: 0 <= v < 2**32, "from 0 to 2**32 - 1"),
}

SECTIONS = (
    "body",
    "world",
    "controller",
    "objective",
    "simulation",
    "search",
    "robustness",
    "output",
    "check",
)


@dataclass(frozen=True)
class Experiment:
    """A checked experiment config and the objects it describes.

    - `name`, `seed`: the run's label and the seed of its one PRNG key.
    - `config`: the resolved config (every key, defaults filled in), as written to results.
    - `task`: the `Task` to search (a multi-stage experiment: the first stage's).
    - `search`: the search settings (`algorithm`, `evaluations`, `size`, `batch`; a
        multi-stage experiment: the first stage's).
    - `output`: where and what to write (`directory`, `animation`, `fps`).
    - `check`: the motion check to run on the best controller (`jaxmotion.checks`), or None;
        a multi-stage experiment: the check of the whole sequence.
    - `stages`: a multi-stage experiment's stages, in order (empty for a single search).

    Each stage is itself a complete single-stage `Experiment` (its `name` is the stage's,
    its `config` a single-stage config of its own tables merged over the top level's), so
    the one search driver, check runner and results writer of a single search serve every
    stage unchanged. Only its start differs, and that is known only once the previous
    stage has run: each stage's `task` starts from the body's rest pose, and
    `run_experiment` starts stage k from the final body state of stage k-1's best motion.
    The stages' seeds are the experiment's `seed + i` for the i-th stage counting from 0
    (modulo 2**32): the first stage searches with the experiment's own seed.
    """

    name: str
    seed: int
    config: dict[str, Any]
    task: Task
    search: dict[str, Any] = field(default_factory=dict)
    output: dict[str, Any] = field(default_factory=dict)
    check: str | None = None
    stages: tuple["Experiment", ...] = ()


def parse_config(raw: Mapping[str, Any], *, name: str = "experiment") -> Experiment:
    """Check a config (as read from TOML) and build its `Experiment`.

    A config with an array of `[[stage]]` tables describes several searches solved one
    after another (`Experiment.stages`; see `STAGE`).

    **Raises:** `ConfigError` (a `ValueError`) naming the first bad key, its value and what is
    allowed.
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"a config must be a table; got {raw!r}")
    if "phase" in raw:
        raise ConfigError(
            "this is a composite-motion config ([[phase]] tables): run it with "
            "`python -m jaxmotion compose CONFIG.toml`"
        )
    if "stage" in raw:
        return _parse_stages(raw, name)
    return _parse_single(raw, name)


def _top_level(raw: Mapping[str, Any], name: str) -> dict[str, Any]:
    """The checked top-level keys (`name`, `seed`)."""
    top = {k: v for k, v in raw.items() if k not in SECTIONS and k != "stage"}
    for k, v in top.items():
        if isinstance(v, Mapping) and k not in TOP:
            raise ConfigError(
                f"unknown section [{k}]; allowed: {', '.join(f'[{s}]' for s in SECTIONS)}"
                + (", [[stage]]" if "stage" in raw else "")
            )
    head = _read_section("the top level", top, TOP)
    head.setdefault("name", name)
    return head


def _check_needs(check_cfg: Mapping[str, Any], body, body_cfg: Mapping[str, Any]) -> None:
    motion = check_cfg["motion"]
    if motion in FOOT_CHECKS and len(getattr(body, "feet", ())) < 2:
        raise ConfigError(
            f'[check] motion = "{motion}" needs a body with feet (a left and a right one); '
            f"{body_cfg.get('figure', body_cfg.get('lattice', 'this body'))!r} has none"
        )


def _check_steps(simulation: Mapping[str, Any]) -> None:
    """At most `MAX_STEPS` fixed steps and `MAX_SAVES` saved samples per simulation."""
    duration, dt = simulation["duration"], simulation["dt"]
    if duration / dt > MAX_STEPS:
        raise ConfigError(
            f"[simulation] duration = {duration!r} at dt = {dt!r} is {duration / dt:.4g} steps; "
            f"allowed: at most {MAX_STEPS} steps per simulation (a longer dt or duration "
            "shorter)"
        )
    save_dt = simulation["save_dt"]
    if duration / save_dt > MAX_SAVES:
        raise ConfigError(
            f"[simulation] duration = {duration!r} at save_dt = {save_dt!r} is "
            f"{duration / save_dt:.4g} saved samples; allowed: at most {MAX_SAVES} per "
            "simulation (a longer save_dt)"
        )


def _check_width(search: Mapping[str, Any], simulation: Mapping[str, Any]) -> None:
    """At most `MAX_BATCH` controllers and `MAX_SAVED` saved samples in one evaluation call
    (its trajectories are held in memory at once)."""
    width, what = SEARCHES[search["algorithm"]].width(search)
    if width > MAX_BATCH:
        raise ConfigError(
            f"[search] {what} = {width} controllers in one call; allowed: at most {MAX_BATCH}"
        )
    samples = round(simulation["duration"] / simulation["save_dt"]) + 1
    if width * samples > MAX_SAVED:
        raise ConfigError(
            f"[search] {what} = {width} controllers in one call, each saving {samples} samples "
            f"([simulation] duration / save_dt + 1): {width * samples:.4g}; allowed: at most "
            f"{MAX_SAVED:.4g} samples in one call (a smaller batch or a longer save_dt)"
        )


def _parse_single(raw: Mapping[str, Any], name: str) -> Experiment:
    head = _top_level(raw, name)
    resolved: dict[str, Any] = dict(head)

    body_table = raw.get("body", {})
    body_schema, builder, body_kind = _body_schema(body_table)
    body_cfg = _read_section("[body]", body_table, body_schema)
    world_cfg = _read_section("[world]", raw.get("world", {}), WORLD)
    controller_table = raw.get("controller", {})
    controller_cfg = _read_section(
        "[controller]", controller_table, _controller_schema(controller_table, body_kind)
    )
    if "objective" not in raw:
        raise ConfigError("the config has no [objective] section (e.g. forward = 1.0)")
    objective_raw = raw["objective"]
    if not isinstance(objective_raw, Mapping) or not objective_raw:
        raise ConfigError(f"[objective] must be a non-empty table of terms; got {objective_raw!r}")
    _check_objective_numbers(objective_raw)
    if "simulation" not in raw:
        raise ConfigError("the config has no [simulation] section (duration = ... is required)")
    simulation_cfg = _read_section("[simulation]", raw["simulation"], SIMULATION)
    _check_steps(simulation_cfg)
    search_table = raw.get("search", {})
    search_cfg = _read_section("[search]", search_table, _search_schema(search_table))
    _check_width(search_cfg, simulation_cfg)
    _check_searcher(search_cfg)
    output_cfg = _read_section("[output]", raw.get("output", {}), OUTPUT)
    _check_export(output_cfg, body_kind, body_cfg)
    robust_cfg = None
    if "robustness" in raw:
        robust_cfg = _read_section("[robustness]", raw["robustness"], ROBUSTNESS)
    check_cfg = _read_section("[check]", raw["check"], CHECK) if "check" in raw else None
    if check_cfg is not None and check_cfg["motion"] in SEQUENCE_CHECKS:
        motion = check_cfg["motion"]
        raise ConfigError(
            f'[check] motion = "{motion}" checks a sequence of '
            f"{SEQUENCE_CHECKS[motion]} stages; allowed: only as the top-level [check] of a "
            "config with that many [[stage]] tables"
        )

    def build(section: str, make: Callable[[], Any]):
        try:
            return make()
        except (ValueError, TypeError, OverflowError) as e:
            raise ConfigError(f"[{section}] {e}") from None

    body = build(
        "body", lambda: builder(**{k: v for k, v in body_cfg.items() if k not in FAMILY_KEYS})
    )
    world = build(
        "world",
        lambda: World(
            **{k: (tuple(v) if k == "friction_direction" else v) for k, v in world_cfg.items()}
        ),
    )
    if body_kind == "figure" and controller_cfg["family"] == "spring_net":
        settings = {k: v for k, v in controller_cfg.items() if k != "family"}
        space = build("controller", lambda: SpringNetSpace(body, **settings))
    elif body_kind == "figure":
        controller_cfg.setdefault("tau_min", 2 * simulation_cfg["dt"])
        controller_cfg.setdefault("tau_max", simulation_cfg["duration"] / 4)
        if controller_cfg["family"] == "sense_bsr":
            controller_cfg.setdefault("relevance", "corner" if body.planar else "contain")
        family = SenseBSRSpace if controller_cfg["family"] == "sense_bsr" else TimeBSRSpace
        # Every key but the family is an argument of the family's space, by name.
        settings = {k: v for k, v in controller_cfg.items() if k != "family"}
        space = build("controller", lambda: family(body, **settings))
    else:
        space = build(
            "controller",
            lambda: RegimesSpace(
                num_regimes=controller_cfg["num_regimes"],
                t_per=controller_cfg["t_per"],
                amplitudes=tuple(controller_cfg["amplitudes"]),
            ),
        )
    if search_cfg.get("enrich", 0) and not hasattr(space, "reinitialise"):
        raise ConfigError(
            f"[search] enrich = {search_cfg['enrich']} needs a controller family with the "
            f"relevance heuristic; allowed: enrich = 0 for family = {space.family!r}, or "
            'family = "sense_bsr"'
        )
    objective = build("objective", lambda: Objective(dict(objective_raw)))
    build(
        "simulation",
        lambda: time_grid(
            simulation_cfg["duration"],
            simulation_cfg["dt"],
            simulation_cfg["save_dt"],
            simulation_cfg.get("control_dt"),
        ),
    )
    task = build(
        "simulation",
        lambda: Task(
            body,
            world,
            space,
            objective,
            duration=simulation_cfg["duration"],
            dt=simulation_cfg["dt"],
            save_dt=simulation_cfg["save_dt"],
            control_dt=simulation_cfg.get("control_dt"),
            robustness=None if robust_cfg is None else Robustness(**robust_cfg),
            second_dt=simulation_cfg.get("second_dt"),
        ),
    )
    resolved.update(
        body=body_cfg,
        world=world_cfg,
        controller=controller_cfg,
        objective=objective.to_dict(),
        simulation=simulation_cfg,
        search=search_cfg,
        output=output_cfg,
    )
    if robust_cfg is not None:
        resolved["robustness"] = robust_cfg
    if check_cfg is not None:
        resolved["check"] = check_cfg
        _check_needs(check_cfg, body, body_cfg)
    return Experiment(
        name=head["name"],
        seed=head["seed"],
        config=resolved,
        task=task,
        search=search_cfg,
        output=output_cfg,
        check=None if check_cfg is None else check_cfg["motion"],
    )


# ------------------------------------------------------------------------------- stages

STAGE_SECTIONS = ("controller", "objective", "simulation", "search", "robustness", "check")
"""The tables a `[[stage]]` may hold; all but `check` are merged key by key over the
top-level table of the same name."""

STAGE = {
    "name": Key(
        "string",
        _REQUIRED,
        lambda v: v.isascii() and v.isidentifier(),
        "that is an identifier (letters, digits and '_', not starting with a digit)",
    ),
}


def _parse_stages(raw: Mapping[str, Any], name: str) -> Experiment:
    """A multi-stage config: `[[stage]]` tables, each a search that starts where the
    previous stage's best motion ended.

    Each stage has a `name` (an identifier, unique) and may hold `[stage.controller]`,
    `[stage.objective]`, `[stage.simulation]` and `[stage.search]` tables, each merged key by
    key over the top-level table of the same name (shared settings are written once, at
    the top level; a top-level table is optional when every stage has its own). Each
    stage's merged tables go through exactly the checks of a single-stage config, and every
    error names the stage. `[body]`, `[world]` and `[output]` are shared (top level only). A
    stage's `[stage.check]` checks that stage's motion; the top-level `[check]` checks the
    whole sequence: a sequence check (`walk_turn_walk`) on the stages' trajectories in
    order, any other check on the stages' motions joined end to end. A stage's `runs`
    (serial search) are independent searches of that stage from the same start, batched;
    the stage keeps the best run's motion, and the next stage starts where it ended.
    Independent runs of the whole sequence are runs with several seeds.

    The resolved config keeps `[body]`, `[world]`, `[output]` and `[check]` at the top level
    and spells out every stage's merged tables in full, so it parses to itself.
    """
    head = _top_level(raw, name)
    stages_raw = raw["stage"]
    if (
        not isinstance(stages_raw, list)
        or not stages_raw
        or not all(isinstance(s, Mapping) for s in stages_raw)
    ):
        raise ConfigError(
            f"stage = {stages_raw!r}; allowed: one or more [[stage]] tables (an array of "
            "tables, each with a name)"
        )
    # The shared sections first, so their errors name no stage.
    body_table = raw.get("body", {})
    body_schema, _, body_kind = _body_schema(body_table)
    body_cfg = _read_section("[body]", body_table, body_schema)
    world_cfg = _read_section("[world]", raw.get("world", {}), WORLD)
    output_cfg = _read_section("[output]", raw.get("output", {}), OUTPUT)
    _check_export(output_cfg, body_kind, body_cfg)
    check_cfg = _read_section("[check]", raw["check"], CHECK) if "check" in raw else None

    names: list[str] = []
    stages: list[Experiment] = []
    for i, table in enumerate(stages_raw, start=1):
        where = f"[[stage]] {i}"
        if "name" in table and isinstance(table["name"], str):
            where += f' ("{table["name"]}")'
        unknown = [k for k in table if k != "name" and k not in STAGE_SECTIONS]
        if unknown:
            raise ConfigError(
                f"{where} has an unknown key {unknown[0]!r}; allowed: name, "
                f"{', '.join(STAGE_SECTIONS)} ([body], [world] and [output] are shared: top "
                "level only)"
            )
        stage_name = _read_section(
            where, {"name": table.get("name")} if "name" in table else {}, STAGE
        )["name"]
        if stage_name in names:
            raise ConfigError(
                f"{where} name = {stage_name!r} is already stage {names.index(stage_name) + 1}'s;"
                " allowed: a name no other stage has"
            )
        names.append(stage_name)
        merged: dict[str, Any] = {
            "name": stage_name,
            "seed": (head["seed"] + i - 1) % 2**32,
            "body": body_table,
            "output": raw.get("output", {}),
        }
        if "world" in raw:
            merged["world"] = raw["world"]
        for section in STAGE_SECTIONS:
            shared, own = raw.get(section), table.get(section)
            if section == "check":  # the top-level [check] is the whole sequence's
                shared = None
            if isinstance(shared, Mapping) and isinstance(own, Mapping):
                merged[section] = {**shared, **own}
            elif own is not None:
                merged[section] = own
            elif shared is not None:
                merged[section] = shared
        for section, example in (
            ("objective", "e.g. forward = 1.0"),
            ("simulation", "duration = ... is required"),
        ):
            if section not in merged:
                raise ConfigError(
                    f"{where}: no [{section}] at the top level or in [stage.{section}] ({example})"
                )
        try:
            stage = _parse_single(merged, stage_name)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None
        stages.append(stage)

    resolved: dict[str, Any] = dict(head)
    resolved.update(body=body_cfg, world=world_cfg, output=output_cfg)
    if check_cfg is not None:
        motion = check_cfg["motion"]
        needed = SEQUENCE_CHECKS.get(motion)
        if needed is not None and needed != len(stages):
            raise ConfigError(
                f'[check] motion = "{motion}" checks a sequence of {needed} stages; this '
                f"config has {len(stages)} [[stage]] table{'s' if len(stages) != 1 else ''}"
            )
        _check_needs(check_cfg, stages[0].task.body, body_cfg)
        resolved["check"] = check_cfg
    resolved["stage"] = [
        {"name": s.name, **{k: s.config[k] for k in STAGE_SECTIONS if k in s.config}}
        for s in stages
    ]
    first = stages[0]
    return Experiment(
        name=head["name"],
        seed=head["seed"],
        config=resolved,
        task=first.task,
        search=first.search,
        output=output_cfg,
        check=None if check_cfg is None else check_cfg["motion"],
        stages=tuple(stages),
    )


def load_config(path: str | Path) -> Experiment:
    """Read and check a TOML experiment config. The run's name defaults to the file's stem.

    **Raises:** `ConfigError` naming the file and the first bad key, its value and what is
    allowed; `FileNotFoundError` if there is no such file.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    try:
        return parse_config(raw, name=path.stem)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def default_config_path() -> Path:
    """The config `python -m jaxmotion` runs (a copy ships as `configs/default.toml`)."""
    return Path(__file__).with_name("default.toml")
