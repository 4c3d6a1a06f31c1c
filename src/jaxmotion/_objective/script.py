"""The composite-motion script language (the second paper's section 3, Table 4): the animator
scores a motion made of several controllers run one after another, phase by phase.

A composite motion runs `K` controllers in turn; phase `k` runs from transition time
`T_{k-1}` to `T_k`, the first from the trajectory's first saved time and the last to its last
saved time. A script names what each phase should achieve and combines the credits into one
fitness, `total`; the paper's Star-Man script reads

    # Star-Man: cartwheel, jump, shuffle
    cartwheel = delta_cm_x * (delta_time ?= 159)
    jump = clearance * (delta_time ?= 90)
    shuffle = delta_cm_x * (delta_time ?= 100)
    total = (1.0 + cartwheel) * (1.0 + jump) * (1.0 + shuffle)

with the phases `("cartwheel", "jump", "shuffle")`.

## Grammar

A script is lines; `#` starts a comment that runs to the end of the line, and blank lines are
allowed. Every other line is one statement, `name = expression`, and each name is assigned
once, before it is used; the script must assign `total`, its value.

    statement  := NAME "=" closeness
    closeness  := sum [ "?=" sum ]                 (non-associative: a ?= b ?= c is an error)
    sum        := product { ("+" | "-") product }  (left-associative)
    product    := unary { ("*" | "/") unary }      (left-associative)
    unary      := "-" unary | primary
    primary    := NUMBER | NAME | NAME "." NAME | "(" closeness ")"

`?=` binds more loosely than `+` and `-`: `delta_time ?= 150 + 9` compares with 159. Numbers
are decimal (`3`, `0.5`, `.5`, `1e-3`, `2.5E+2`); names are ASCII identifiers. A name in an
expression is one of:

- a variable assigned on an earlier line;
- `phase.measure`: a measure (below) of the named phase, usable anywhere;
- a bare `measure`, only in an assignment to a phase's own name: in `jump = clearance`, the
  jump phase's clearance (as the paper writes it).

## The closeness operator `a ?= b`

    a ?= b = 2 ** -((a - b) / (0.1 * rms)) ** 2,    rms = sqrt((a**2 + b**2) / 2 + 1e-12)

A Gaussian in the difference relative to the operands' root mean square: exactly 1 when they
are equal, 1/2 when they differ by a tenth of their root mean square (`100 ?= 110.5` and
`100 ?= 90.5` are about 1/2, and a phase of 144 or 176 ticks scores about 1/2 on
`delta_time ?= 159`), 1/16 at two tenths, 1/512 at three tenths, and falling to 0 as
they differ more. It is symmetric in its operands and smooth everywhere (the 1e-12, in the
operands' squared units, keeps it defined at `0 ?= 0`, which gives 1). Being relative, it
judges 175 against 159 as it judges 1.75 against 1.59, whatever the units; against 0 it
gives about 0 for anything much further than 1e-6 from 0.

## Measures

Each measure reads one phase. The phase's samples are the saved samples with times in
`[T_{k-1}, T_k]`, both ends included: each transition is placed at the saved sample nearest
to it (exact when samples are saved every tick and transitions lie on the tick grid; a
transition outside the trajectory's time span is moved to its nearer end). Transitions are
expected in increasing order: a phase whose end comes before its start lasts a negative
number of ticks and reads the one sample at its start.

- `delta_time`: the phase's duration in simulator ticks, `round(T_k / tick) -
  round(T_{k-1} / tick)` (the paper's Δtime; a whole number, piecewise constant in the
  transitions).
- `delta_seconds`: the phase's duration in seconds, `T_k - T_{k-1}` (smooth in the
  transitions; `delta_time * tick` when they lie on the tick grid).
- `delta_cm_x`, `delta_cm_y`, `delta_cm_z`: the centre of mass's displacement over the phase
  along world x, y, z (m): its value at the phase's last sample minus at its first.
- every registered objective term (`jaxmotion.objective_terms()`: `clearance`, `forward`,
  `max_height`, `rotations`, `upright`, `final_tilt`, ...), with its default options, computed
  on the phase as if the phase were the whole trajectory: "the start" is the phase's first
  sample, "the end" its last (`max_height` is above the height at the phase's start, and
  `forward` is along the heading at the phase's start). Units are the term's own.

Transitions are traced (one compiled function serves every transition array), so a phase
cannot be sliced to its own length: it is read from a sub-trajectory as long as the whole one,
its samples followed by copies of its last sample (time included). On it these kinds of terms
are exact: a last-minus-first difference (`forward`, `distance`, `max_height`), a maximum,
minimum, any or all over samples (`clearance`, `tilt`, `upright`, `grounded`), a value at the
last sample (`final_tilt`, `fallen`), a sum weighted by time increments (`contact_time`,
`flight_time`), and a sum over consecutive pairs of samples that is zero for a repeated
sample (`rotations`, `heading`, `hops`, `steps`, `contact_distance`). The angle summed by
`rotation` (`axis = "any"`) gains 1e-10 rad for each repeated sample, below float32's
resolution. Terms that would come out wrong are excluded, and naming one raises
`ScriptError` saying why:

- `air_height`, `asymmetry`: means over saved samples, which the repeated samples would bias
  toward the phase's last sample;
- `final_spin`: divides the last rotation by the last time increment, which is zero on the
  repeated samples.

A term registered later (`jaxmotion.register_term`) is assumed to read a trajectory in one of
the exact ways above.
"""

import difflib
import math
import re
import string
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple, NoReturn

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._sim.trajectory import Trajectory
from . import terms as _builtin_terms  # noqa: F401  (registers the built-in terms)
from .registry import terms as registered_terms

CLOSENESS_WIDTH = 0.1
"""`a ?= b` is 1/2 when `a` and `b` differ by this share of their root mean square."""

_CLOSENESS_FLOOR = 1e-6
"""Added (squared) to the root mean square so that `0 ?= 0` is defined (it is 1)."""

_PHASE_MEASURES = {
    "delta_time": "the phase's duration in simulator ticks",
    "delta_seconds": "the phase's duration (s)",
    "delta_cm_x": "the centre of mass's displacement along world x over the phase (m)",
    "delta_cm_y": "the centre of mass's displacement along world y over the phase (m)",
    "delta_cm_z": "the centre of mass's displacement along world z over the phase (m)",
}

_INEXACT_TERMS = {
    "air_height": (
        "it is a mean over saved samples, which the copies of the phase's last sample that "
        "pad a phase to a fixed length would bias"
    ),
    "asymmetry": (
        "it is a mean over saved samples, which the copies of the phase's last sample that "
        "pad a phase to a fixed length would bias"
    ),
    "final_spin": (
        "it divides by the last time increment, which is zero on the copies of the phase's "
        "last sample that pad a phase to a fixed length"
    ),
}


def script_measures() -> dict[str, str]:
    """The measures a script can read of a phase, by name, each with a one-line summary:
    the durations and centre-of-mass displacements, then every registered objective term
    except those that a phase cannot compute exactly (see this module's docstring)."""
    out = dict(_PHASE_MEASURES)
    for name, term in registered_terms().items():
        if name not in out and name not in _INEXACT_TERMS:
            out[name] = term.summary
    return out


def closeness(a: Float[Array, "*shape"], b: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
    """The script's `a ?= b`: 1 when `a == b`, 1/2 when they differ by a tenth of their root
    mean square, falling smoothly to 0 as they differ more (a Gaussian in the relative
    difference; see the module docstring). Symmetric, differentiable, elementwise.

    **Arguments:** `a`, `b`: arrays of broadcastable shapes.

    **Returns:** the closeness, in [0, 1] (1 only at equality, up to rounding).
    """
    a = jnp.asarray(a, dtype=float)
    b = jnp.asarray(b, dtype=float)
    mean_square = 0.5 * (a * a + b * b) + _CLOSENESS_FLOOR**2
    relative = (a - b) ** 2 / (CLOSENESS_WIDTH**2 * mean_square)
    return jnp.exp2(-relative)


class ScriptError(ValueError):
    """A composite-motion script that does not parse or names what it cannot use; `line` and
    `column` (1-based) locate the problem in the script's text."""

    def __init__(self, message: str, line: int, column: int):
        super().__init__(f"line {line}, column {column}: {message}")
        self.message = message
        self.line = line
        self.column = column

    def __reduce__(self):
        return type(self), (self.message, self.line, self.column)


# ---------------------------------------------------------------------------------------------
# Parsing. The tree is nested tuples (hashable, so a Script is a static object):
#   ("number", value) | ("variable", name) | ("measure", phase_index, measure)
#   | ("negate", x) | ("binary", op, x, y) | ("closeness", x, y)


class _Token(NamedTuple):
    kind: str  # "number", "name", "operator" or "end" (of the line)
    text: str
    line: int
    column: int


_NUMBER = re.compile(r"(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_WORD = frozenset(string.ascii_letters + string.digits + "_.")  # cannot follow a number
_OPERATORS = ("?=", "+", "-", "*", "/", "(", ")", "=", ".")
_MAX_DEPTH = 50  # nested parentheses and minuses (deeper would overflow Python's stack)
_ALLOWED = "names, numbers, + - * / ( ) = ?= . and # comments"


def _describe(token: _Token) -> str:
    return "end of line" if token.kind == "end" else repr(token.text)


def _tokenize(code: str, line: int) -> list[_Token]:
    """The tokens of one line (its comment already cut off), ending with an "end" token."""
    tokens, i = [], 0
    while i < len(code):
        char = code[i]
        if char in " \t\r\f\v":
            i += 1
            continue
        number = _NUMBER.match(code, i)
        if number:
            end = rest = number.end()
            while rest < len(code) and code[rest] in _WORD:
                rest += 1
            if rest > end:
                raise ScriptError(
                    f"malformed number {code[i:rest]!r}; expected digits with an "
                    "optional decimal point and exponent (like 2, 0.5 or 1e-3)",
                    line,
                    i + 1,
                )
            tokens.append(_Token("number", number.group(), line, i + 1))
            i = end
            continue
        name = _NAME.match(code, i)
        if name:
            tokens.append(_Token("name", name.group(), line, i + 1))
            i = name.end()
            continue
        operator = next((op for op in _OPERATORS if code.startswith(op, i)), None)
        if operator is None:
            if char == "?":
                message = "expected '=' after '?' (the closeness operator is '?=')"
            else:
                message = f"unexpected character {char!r}; allowed: {_ALLOWED}"
            raise ScriptError(message, line, i + 1)
        tokens.append(_Token("operator", operator, line, i + 1))
        i += len(operator)
    tokens.append(_Token("end", "", line, len(code.rstrip()) + 1))
    return tokens


class _LineParser:
    """Recursive descent over one statement's tokens; names resolve against what the lines
    before it assigned."""

    def __init__(self, tokens, target, assigned, phases, measures):
        self.tokens = tokens
        self.position = 0
        self.target = target  # the name this statement assigns
        self.assigned = assigned  # name -> line, of the statements before this one
        self.phases = phases
        self.measures = measures
        self.uses: list[tuple[int, str]] = []  # (phase index, measure) pairs read
        self.depth = 0  # open parentheses and unary minuses: recursion, which is bounded

    def peek(self) -> _Token:
        return self.tokens[self.position]

    def take(self) -> _Token:
        token = self.tokens[self.position]
        self.position += 1
        return token

    def after(self) -> str:
        return repr(self.tokens[self.position - 1].text)

    def fail(self, message: str, token: _Token) -> NoReturn:
        raise ScriptError(message, token.line, token.column)

    def is_operator(self, *texts: str) -> bool:
        token = self.peek()
        return token.kind == "operator" and token.text in texts

    def closeness(self):
        left = self.sum()
        if not self.is_operator("?="):
            return left
        self.take()
        right = self.sum()
        if self.is_operator("?="):
            self.fail(
                "'?=' does not chain: expected an operator (+ - * /), ')' or the end of the "
                f"line after {self.after()}; got '?=' (parenthesise, e.g. (a ?= b) ?= c)",
                self.peek(),
            )
        return ("closeness", left, right)

    def sum(self):
        tree = self.product()
        while self.is_operator("+", "-"):
            op = self.take().text
            tree = ("binary", op, tree, self.product())
        return tree

    def product(self):
        tree = self.unary()
        while self.is_operator("*", "/"):
            op = self.take().text
            tree = ("binary", op, tree, self.unary())
        return tree

    def nest(self, token: _Token):
        self.depth += 1
        if self.depth > _MAX_DEPTH:
            self.fail(f"expression nested more than {_MAX_DEPTH} deep; expected less", token)

    def unary(self):
        if self.is_operator("-"):
            self.nest(self.take())
            tree = ("negate", self.unary())
            self.depth -= 1
            return tree
        return self.primary()

    def primary(self):
        token = self.peek()
        if token.kind == "number":
            self.take()
            value = float(token.text)
            if not math.isfinite(value):
                self.fail(f"number {token.text} is too large; expected a finite number", token)
            return ("number", value)
        if token.kind == "name":
            self.take()
            return self.name(token)
        if token.kind == "operator" and token.text == "(":
            self.nest(self.take())
            tree = self.closeness()
            if not self.is_operator(")"):
                self.fail(
                    f"expected ')' to close the '(' at column {token.column} after "
                    f"{self.after()}; got {_describe(self.peek())}",
                    self.peek(),
                )
            self.take()
            self.depth -= 1
            return tree
        self.fail(
            f"expected a number, a name or '(' after {self.after()}; got {_describe(token)}",
            token,
        )

    def measure(self, phase: int, token: _Token):
        name = token.text
        if name in _INEXACT_TERMS:
            self.fail(
                f"the term {name!r} cannot be a phase's measure: {_INEXACT_TERMS[name]}", token
            )
        if name not in self.measures:
            self.fail(
                f"unknown measure {name!r}{_suggest(name, self.measures)}; measures: "
                f"{', '.join(self.measures)}",
                token,
            )
        self.uses.append((phase, name))
        return ("measure", phase, name)

    def name(self, token: _Token):
        name = token.text
        if self.is_operator("."):
            self.take()
            if name not in self.phases:
                self.fail(
                    f"unknown phase {name!r} before '.'{_suggest(name, self.phases)}; phases: "
                    f"{', '.join(self.phases)}",
                    token,
                )
            measure = self.peek()
            if measure.kind != "name":
                self.fail(
                    f"expected a measure's name after '{name}.'; got {_describe(measure)}",
                    measure,
                )
            self.take()
            return self.measure(self.phases.index(name), measure)
        if name in self.assigned:
            return ("variable", name)
        if name in self.measures or name in _INEXACT_TERMS:
            if self.target in self.phases:
                return self.measure(self.phases.index(self.target), token)
            self.fail(
                f"the measure {name!r} needs a phase: write phase.{name} (phases: "
                f"{', '.join(self.phases)}); a bare measure reads the phase only in an "
                f"assignment to that phase's name, and {self.target!r} is not a phase",
                token,
            )
        if name == self.target:
            self.fail(f"{name!r} is used in its own assignment before it has a value", token)
        if name in self.phases:
            self.fail(
                f"unknown name {name!r}: the phase {name!r} has no value yet (assign it on an "
                f"earlier line), and its measures are written {name}.measure",
                token,
            )
        variables = ", ".join(self.assigned) or "none yet"
        self.fail(
            f"unknown name {name!r}{_suggest(name, [*self.assigned, *self.measures])}; allowed: "
            f"variables assigned on earlier lines ({variables}), phase.measure for the phases "
            f"{', '.join(self.phases)}, and, in an assignment to a phase's name, a bare "
            f"measure: {', '.join(self.measures)}",
            token,
        )


def _suggest(name: str, candidates) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _parse(text: str, phases: tuple[str, ...], measures: Mapping[str, str]):
    """The statements `(name, tree, line)` of a script and the `(phase, measure)` pairs they
    read; raises `ScriptError` at the first problem."""
    statements, assigned, uses = [], {}, []
    lines = text.split("\n")
    for number, raw in enumerate(lines, start=1):
        tokens = _tokenize(raw.split("#", 1)[0], number)
        if tokens[0].kind == "end":
            continue
        first = tokens[0]
        if first.kind != "name":
            raise ScriptError(
                "expected a name to assign at the start of a statement (name = expression); "
                f"got {_describe(first)}",
                number,
                first.column,
            )
        target = first.text
        if tokens[1].kind != "operator" or tokens[1].text != "=":
            raise ScriptError(
                f"expected '=' after {target!r}; got {_describe(tokens[1])}",
                number,
                tokens[1].column,
            )
        if target in measures or target in _INEXACT_TERMS:
            raise ScriptError(
                f"cannot assign to {target!r}: it is a measure; choose another name",
                number,
                first.column,
            )
        if target in assigned:
            raise ScriptError(
                f"{target!r} is already assigned on line {assigned[target]}; each name is "
                "assigned once",
                number,
                first.column,
            )
        parser = _LineParser(tokens, target, assigned, phases, measures)
        parser.position = 2
        tree = parser.closeness()
        rest = parser.peek()
        if rest.kind != "end":
            if rest.kind == "operator" and rest.text == ")":
                message = "unbalanced ')': no '(' before it to close"
            else:
                message = (
                    "expected an operator (+ - * / ?=) or the end of the line after "
                    f"{parser.after()}; got {_describe(rest)}"
                )
            raise ScriptError(message, number, rest.column)
        statements.append((target, tree, number))
        assigned[target] = number
        uses.extend(use for use in parser.uses if use not in uses)
    end_line, end_column = len(lines), len(lines[-1]) + 1
    if not statements:
        raise ScriptError(
            "empty script: expected statements (name = expression) ending with 'total = ...'",
            end_line,
            end_column,
        )
    if "total" not in assigned:
        raise ScriptError(
            "expected an assignment 'total = ...' (the script's value); got none",
            end_line,
            end_column,
        )
    return tuple(statements), tuple(uses)


# ---------------------------------------------------------------------------------------------
# Evaluation.


def _evaluate(tree, variables: Mapping[str, Array], measures: Mapping[tuple[int, str], Array]):
    kind = tree[0]
    if kind == "number":
        return jnp.asarray(tree[1], dtype=float)
    if kind == "variable":
        return variables[tree[1]]
    if kind == "measure":
        return measures[tree[1], tree[2]]
    if kind == "negate":
        return -_evaluate(tree[1], variables, measures)
    if kind == "closeness":
        return closeness(
            _evaluate(tree[1], variables, measures), _evaluate(tree[2], variables, measures)
        )
    _, op, x, y = tree
    x, y = _evaluate(x, variables, measures), _evaluate(y, variables, measures)
    return {"+": jnp.add, "-": jnp.subtract, "*": jnp.multiply, "/": jnp.divide}[op](x, y)


def _phase_window(trajectory: Trajectory, start, end) -> Trajectory:
    """The samples `start..end` (inclusive) of `trajectory`, followed by copies of sample `end`
    up to the trajectory's own length (a fixed shape for traced bounds)."""
    num_saves = trajectory.ts.shape[0]
    take = jnp.minimum(start + jnp.arange(num_saves), end)
    senses = None if trajectory.senses is None else trajectory.senses[take]
    return Trajectory(
        ts=trajectory.ts[take],
        points=trajectory.points[take],
        com=trajectory.com[take],
        frame=trajectory.frame[take],
        contact=trajectory.contact[take],
        finite=trajectory.finite,
        senses=senses,
    )


class Script(eqx.Module):
    """A composite-motion script (the second paper's Table 4): the fitness of a motion made
    of several controllers run one after another, written phase by phase. See this module's
    docstring for the grammar, the closeness operator `?=` and the measures.

        script = Script(
            "cartwheel = delta_cm_x * (delta_time ?= 159)\\n"
            "jump = clearance * (delta_time ?= 90)\\n"
            "shuffle = delta_cm_x * (delta_time ?= 100)\\n"
            "total = (1.0 + cartwheel) * (1.0 + jump) * (1.0 + shuffle)\\n",
            phases=("cartwheel", "jump", "shuffle"),
            tick=0.01,
        )
        fitness = script(trajectory, jnp.array([1.59, 2.49]))

    The text is parsed and checked when the script is made, so a mistake is reported before
    anything compiles. A script holds only static fields: it is hashable and sits in jitted
    code as a constant. Calling it is a JAX function of one (unbatched) trajectory and the
    transition times, which are traced: one compiled function serves every transition
    array; `jax.vmap` over both scores a batch.

    **Arguments:**

    - `text`: the script.
    - `phases`: the phases' names in order, one per controller (identifiers, distinct, none
        of them a measure's name or `total`).
    - `tick`: the simulator tick (the control period), s: the unit of `delta_time`.

    **Raises:** `ScriptError` (a `ValueError`, with the `line` and `column` of the problem)
    for a script that does not parse or names what it cannot use; `ValueError` for bad
    `phases` or `tick`.
    """

    text: str = eqx.field(static=True)
    phases: tuple[str, ...] = eqx.field(static=True)
    tick: float = eqx.field(static=True)
    _statements: tuple[tuple[str, Any, int], ...] = eqx.field(static=True)
    _uses: tuple[tuple[int, str], ...] = eqx.field(static=True)

    def __init__(self, text: str, phases: Sequence[str], tick: float):
        if not isinstance(text, str):
            raise ValueError(f"Script text must be a string; got {type(text).__name__}")
        measures = script_measures()
        if isinstance(phases, str) or not isinstance(phases, Sequence) or not phases:
            raise ValueError(
                f"Script phases = {phases!r}; allowed: a non-empty sequence of phase names, "
                "one per controller"
            )
        phases = tuple(phases)
        for phase in phases:
            if not isinstance(phase, str) or _NAME.fullmatch(phase) is None:
                raise ValueError(f"Script phase name {phase!r}; allowed: an ASCII identifier")
            if phase in measures or phase in _INEXACT_TERMS or phase == "total":
                raise ValueError(
                    f"Script phase name {phase!r} is a measure's name or 'total'; allowed: "
                    "any other identifier"
                )
        if len(set(phases)) != len(phases):
            raise ValueError(f"Script phases = {phases!r}; allowed: distinct names")
        if (
            isinstance(tick, bool)
            or not isinstance(tick, int | float)
            or not math.isfinite(tick)
            or tick <= 0
        ):
            raise ValueError(f"Script tick = {tick!r}; allowed: a positive number of seconds")
        self._statements, self._uses = _parse(text, phases, measures)
        self.text = text
        self.phases = phases
        self.tick = float(tick)

    def to_text(self) -> str:
        """The script's text: `Script(script.to_text(), script.phases, script.tick)` makes
        an equal script."""
        return self.text

    def values(
        self, trajectory: Trajectory, transitions: Float[Array, " num_transitions"]
    ) -> dict[str, Float[Array, ""]]:
        """Every assigned variable's value, by name in the order of the script, `total`
        included (as computed: `-inf` for a diverged run is `__call__`'s).

        **Arguments:**

        - `trajectory`: one unbatched `Trajectory` of the whole composite motion.
        - `transitions`: `(len(phases) - 1,)` the times (s, on the trajectory's clock) at
            which each phase after the first begins, in order.

        **Returns:** a dict of scalars.
        """
        measures = self._measures(trajectory, transitions)
        variables: dict[str, Array] = {}
        for name, tree, _ in self._statements:
            variables[name] = _evaluate(tree, variables, measures)
        return variables

    def __call__(
        self, trajectory: Trajectory, transitions: Float[Array, " num_transitions"]
    ) -> Float[Array, ""]:
        """The script's `total`: the fitness (maximised) of the composite motion; `-inf` when
        the run was not finite or the total is not (arguments as for `values`)."""
        total = self.values(trajectory, transitions)["total"]
        return jnp.where(trajectory.finite & jnp.isfinite(total), total, -jnp.inf)

    def _measures(self, trajectory, transitions) -> dict[tuple[int, str], Array]:
        if not isinstance(trajectory, Trajectory) or jnp.ndim(trajectory.com) != 2:
            raise ValueError(
                "a Script scores one unbatched Trajectory (jax.vmap it for a batch); got "
                f"{type(trajectory).__name__} with com of shape "
                f"{jnp.shape(getattr(trajectory, 'com', ()))}"
            )
        transitions = jnp.asarray(transitions, dtype=float)
        expected = (len(self.phases) - 1,)
        if transitions.shape != expected:
            raise ValueError(
                f"transitions of shape {transitions.shape}; a script of {len(self.phases)} "
                f"phases ({', '.join(self.phases)}) needs shape {expected}: the time each "
                "phase after the first begins"
            )
        if not self._uses:
            return {}
        ts = trajectory.ts
        first, last = ts[0], ts[-1]
        cuts = jnp.clip(transitions, first, last)
        nearest = jnp.argmin(jnp.abs(ts[None, :] - cuts[:, None]), axis=1)
        starts = jnp.concatenate([jnp.zeros((1,), nearest.dtype), nearest])
        ends = jnp.concatenate([nearest, jnp.full((1,), ts.shape[0] - 1, nearest.dtype)])
        ends = jnp.maximum(ends, starts)  # transitions out of order: a one-sample phase
        bounds = jnp.concatenate([first[None], cuts, last[None]])
        ticks = jnp.round(bounds / self.tick)
        windows = {
            phase: _phase_window(trajectory, starts[phase], ends[phase])
            for phase in sorted({p for p, name in self._uses if name not in _PHASE_MEASURES})
        }

        def measure(phase: int, name: str) -> Array:
            start, end = starts[phase], ends[phase]
            if name == "delta_time":
                return ticks[phase + 1] - ticks[phase]
            if name == "delta_seconds":
                return bounds[phase + 1] - bounds[phase]
            if name.startswith("delta_cm_"):
                axis = "xyz".index(name[-1])
                return trajectory.com[end, axis] - trajectory.com[start, axis]
            term = registered_terms()[name]
            return jnp.asarray(term.fn(windows[phase], **dict(term.options)), dtype=float)

        return {(phase, name): measure(phase, name) for phase, name in self._uses}
