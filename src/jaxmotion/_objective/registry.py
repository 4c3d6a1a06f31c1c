"""The objective registry: named terms, each a function of a Trajectory, and `Objective`,
their weighted sum."""

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._sim.trajectory import Trajectory

TermFn = Callable[..., Float[Array, ""]]


@dataclass(frozen=True)
class Term:
    """A registered objective term: `fn(trajectory, **options) -> scalar`."""

    name: str
    fn: TermFn
    options: Mapping[str, Any]
    summary: str


_REGISTRY: dict[str, Term] = {}


def register_term(name: str, fn: TermFn | None = None):
    """Register an objective term under `name` (usable as a decorator).

    A term is a function `fn(trajectory, **options) -> scalar` of one (unbatched) `Trajectory`;
    its keyword arguments with defaults are its options, and the first line of its docstring
    is its summary. Registering a name twice is an error.
    """

    def add(f: TermFn) -> TermFn:
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"term name {name!r} must be a Python identifier")
        if name in _REGISTRY:
            raise ValueError(f"an objective term named {name!r} is already registered")
        params = list(inspect.signature(f).parameters.values())[1:]
        options = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
        summary = (inspect.getdoc(f) or "").split("\n")[0]
        _REGISTRY[name] = Term(name, f, MappingProxyType(options), summary)
        return f

    return add if fn is None else add(fn)


def terms() -> Mapping[str, Term]:
    """Every registered term, by name (read-only)."""
    return MappingProxyType(_REGISTRY)


def _spec_error(label, message):
    return ValueError(f"objective term {label!r}: {message}")


def _check_option(label: str, term: Term, key: str, value: Any) -> Any:
    default = term.options[key]
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise _spec_error(label, f"option {key} = {value!r}; allowed: true or false")
    elif isinstance(default, int | float):
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise _spec_error(label, f"option {key} = {value!r}; allowed: a number")
        if isinstance(default, int) and not isinstance(default, bool) and value != int(value):
            raise _spec_error(label, f"option {key} = {value!r}; allowed: a whole number")
        value = type(default)(value)
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise _spec_error(label, f"option {key} = {value!r}; allowed: a string")
    return value


class Objective(eqx.Module):
    """A weighted sum of registered terms; the fitness of a motion. **Fitness is maximised**:
    give rewarded terms positive weights and penalties negative ones.

    `Objective({"forward": 1.0, "upright": -10.0})` rewards forward travel and penalises
    falling over. A value may also be a table with the weight and the term's options, and the
    key may be any label if the table names its term, so one term can appear twice:

        Objective({
            "forward": 1.0,
            "upright": {"weight": -10.0, "max_degrees": 30},
            "roll": {"term": "rotation", "axis": "forward", "weight": -0.5},
        })

    Calling it on a `Trajectory` gives the fitness; a trajectory that is not finite (the run
    blew up) scores `-inf`, the worst fitness, as does any non-finite total. See
    `jaxmotion.objective_terms()` for the terms and their options.

    **Raises:** `ValueError` naming the label for an unknown term, an unknown option or an
    option or weight of the wrong type, listing what is allowed.
    """

    spec: tuple[tuple[str, str, float, tuple[tuple[str, Any], ...]], ...] = eqx.field(static=True)

    def __init__(self, weights: Mapping[str, float | Mapping[str, Any]]):
        if not isinstance(weights, Mapping) or not weights:
            raise ValueError(
                f"Objective needs a non-empty mapping of term names to weights; got {weights!r}"
            )
        spec = []
        for label, value in weights.items():
            if isinstance(value, Mapping):
                entry = dict(value)
                name = entry.pop("term", label)
                if "weight" not in entry:
                    raise _spec_error(label, "a table must give its weight (weight = ...)")
                weight = entry.pop("weight")
                given = entry
            else:
                name, weight, given = label, value, {}
            if name not in _REGISTRY:
                known = ", ".join(sorted(_REGISTRY))
                raise _spec_error(label, f"unknown term {name!r}; allowed: {known}")
            if (
                isinstance(weight, bool)
                or not isinstance(weight, int | float)
                or not math.isfinite(weight)
            ):
                raise _spec_error(label, f"weight = {weight!r}; allowed: a finite number")
            term = _REGISTRY[name]
            options = dict(term.options)
            for key, v in given.items():
                if key not in term.options:
                    allowed = ", ".join(["term", "weight", *term.options]) or "term, weight"
                    raise _spec_error(label, f"unknown option {key!r}; allowed: {allowed}")
                options[key] = _check_option(label, term, key, v)
            spec.append((str(label), name, float(weight), tuple(sorted(options.items()))))
        self.spec = tuple(spec)

    @property
    def weights(self) -> dict[str, float]:
        return {label: weight for label, _, weight, _ in self.spec}

    def values(self, trajectory: Trajectory) -> dict[str, Float[Array, ""]]:
        """Each term's raw (unweighted) value, by label."""
        return {
            label: jnp.asarray(_REGISTRY[name].fn(trajectory, **dict(options)), dtype=float)
            for label, name, _, options in self.spec
        }

    def __call__(self, trajectory: Trajectory) -> Float[Array, ""]:
        values = self.values(trajectory)
        total = sum(weight * values[label] for label, _, weight, _ in self.spec)
        ok = trajectory.finite & jnp.isfinite(total)
        return jnp.where(ok, total, -jnp.inf)

    def to_dict(self) -> dict[str, Any]:
        """The spec as a plain mapping (what a config file holds); round-trips."""
        out: dict[str, Any] = {}
        for label, name, weight, options in self.spec:
            defaults = _REGISTRY[name].options
            changed = {k: v for k, v in options if defaults.get(k) != v}
            if name == label and not changed:
                out[label] = weight
            else:
                entry: dict[str, Any] = {"weight": weight}
                if name != label:
                    entry["term"] = name
                entry.update(changed)
                out[label] = entry
        return out
