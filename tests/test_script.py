"""The composite-motion script language on hand-built trajectories with known answers: the
grammar, the closeness operator, phase windows, batching, and the errors it reports."""

import math
import pickle
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion._objective import script as script_module
from jaxmotion._objective.registry import terms
from jaxmotion._objective.script import Script, ScriptError, closeness, script_measures

# Float32 arithmetic on values of order 1-100: relative agreement with NumPy's float64.
FLOAT32_RTOL = 1e-5
# Float32 values that should come out as 0 exactly up to rounding (m, rad, counts).
FLOAT32_ATOL = 1e-5
# Central finite differences in float64: step and agreement with the gradient.
FD_STEP = 1e-6
FD_RTOL = 1e-6

TICK = 0.01
STAR_MAN = ("cartwheel", "jump", "shuffle")
TABLE_4 = """# Star-Man: cartwheel, jump, shuffle
cartwheel = delta_cm_x * (delta_time ?= 159)
jump = clearance * (delta_time ?= 90)
shuffle = delta_cm_x * (delta_time ?= 100)
total = (1.0 + cartwheel) * (1.0 + jump) * (1.0 + shuffle)
"""


def make(ts, com, points, frame=None, finite=True):
    ts = np.asarray(ts, dtype=float)
    frame = np.broadcast_to(np.eye(3), (len(ts), 3, 3)) if frame is None else frame
    return jm.Trajectory(
        ts=jnp.asarray(ts),
        points=jnp.asarray(points),
        com=jnp.asarray(com),
        frame=jnp.asarray(frame),
        contact=jnp.asarray(np.asarray(points)[..., 2] <= 0.0),
        finite=jnp.asarray(finite),
    )


def rotation(axis, angles):
    """`(len(angles), 3, 3)` rotations by `angles` (rad) about world axis 0, 1 or 2."""
    c, s = np.cos(angles), np.sin(angles)
    i, j = [k for k in range(3) if k != axis]
    out = np.zeros((len(angles), 3, 3))
    out[:, axis, axis] = 1.0
    out[:, i, i], out[:, i, j], out[:, j, i], out[:, j, j] = c, -s, s, c
    return out


def bump(t, centre, half_width, height):
    return height * np.maximum(0.0, 1.0 - ((t - centre) / half_width) ** 2)


def star_man_motion(speed=0.8):
    """3.5 s at 100 saves per second: the centre of mass moves along x at `speed` m/s, and
    both feet leave the floor twice, to 0.8 m at t = 0.5 s and to 0.3 m at t = 1.9 s."""
    ts = np.arange(351) * TICK
    com = np.stack([speed * ts, 0.1 * ts, 0.5 + 0.0 * ts], axis=1)
    z = bump(ts, 0.5, 0.2, 0.8) + bump(ts, 1.9, 0.3, 0.3)
    feet = np.stack([speed * ts - 0.1, speed * ts + 0.1], axis=1)
    points = np.stack([feet, np.zeros_like(feet), np.stack([z, z], axis=1)], axis=-1)
    return make(ts, com, points)


def close_np(a, b):
    """The documented closeness, in NumPy float64."""
    rms = math.sqrt((a * a + b * b) / 2)
    return 2.0 ** -(((a - b) / (0.1 * rms)) ** 2)


def tiny_motion(n=3):
    ts = np.arange(n) * TICK
    com = np.zeros((n, 3))
    return make(ts, com, np.zeros((n, 1, 3)))


def constant(expression: str) -> float:
    script = Script(f"total = {expression}", ("only",), TICK)
    return float(script.values(tiny_motion(), jnp.zeros((0,)))["total"])


# --- values on hand-built motions -------------------------------------------------------------


@pytest.fixture(scope="module")
def star_man():
    """The Table 4 script and its values, jitted once for this file, with a list that gains
    an entry each time they are traced."""
    script = Script(TABLE_4, STAR_MAN, TICK)
    traces = []

    def values(motion, transitions):
        traces.append(None)
        return script.values(motion, transitions)

    return script, jax.jit(values), traces


def test_table_4_script_by_hand(star_man):
    _, values, _ = star_man
    motion = star_man_motion()
    transitions = np.array([1.5, 2.4])  # durations 150, 90 and 110 ticks
    measured = values(motion, jnp.asarray(transitions))

    x = np.asarray(motion.com)[:, 0]
    z = np.asarray(motion.points)[..., 2]
    cartwheel = (x[150] - x[0]) * close_np(150, 159)
    jump = np.max(np.min(z[150:241], axis=1)) * close_np(90, 90)
    shuffle = (x[350] - x[240]) * close_np(110, 100)
    total = (1 + cartwheel) * (1 + jump) * (1 + shuffle)
    # The arrays say what the phases are: 1.2 m, the second jump's 0.3 m (not the first's
    # 0.8 m, which lies in the cartwheel phase), 0.88 m.
    np.testing.assert_allclose(
        [x[150] - x[0], jump, x[350] - x[240]], [1.2, 0.3, 0.88], rtol=FLOAT32_RTOL
    )
    expected = {"cartwheel": cartwheel, "jump": jump, "shuffle": shuffle, "total": total}
    assert list(measured) == list(expected)
    for name, value in expected.items():
        np.testing.assert_allclose(measured[name], value, rtol=FLOAT32_RTOL, err_msg=name)


def test_phase_measures_durations_and_displacements():
    text = """
    # every phase's measures, named explicitly
    a_ticks = a.delta_time
    b_ticks = b.delta_time
    c_ticks = c.delta_time
    b_seconds = b.delta_seconds
    c_seconds = c.delta_seconds
    b_y = b.delta_cm_y
    c_z = c.delta_cm_z
    c_x = c.delta_cm_x
    a_clearance = a.clearance
    total = 0
    """
    script = Script(text.replace("\n    ", "\n"), ("a", "b", "c"), TICK)
    # 1.503 s is placed at the nearest save (1.50 s) and is 150 ticks; 3.0 s lies inside.
    values = jax.jit(script.values)
    motion = star_man_motion()
    measured = values(motion, jnp.array([1.503, 3.0]))
    expected = {
        "a_ticks": 150.0,
        "b_ticks": 150.0,
        "c_ticks": 50.0,
        "b_seconds": 3.0 - 1.503,
        "c_seconds": 0.5,
        "b_y": 0.1 * 1.5,
        "c_z": 0.0,
        "c_x": 0.8 * 0.5,
        "a_clearance": 0.8,
    }
    for name, value in expected.items():
        np.testing.assert_allclose(
            measured[name], value, rtol=FLOAT32_RTOL, atol=FLOAT32_ATOL, err_msg=name
        )
    # A transition past the end is moved to it: the last phase is empty.
    measured = values(motion, jnp.array([1.5, 9.0]))
    ends = [measured[name] for name in ("b_ticks", "c_ticks", "c_x", "c_seconds")]
    np.testing.assert_allclose(ends, [200.0, 0.0, 0.0, 0.0], atol=FLOAT32_ATOL)
    # Out of order: the middle phase lasts -100 ticks and reads one sample, its first.
    measured = values(motion, jnp.array([2.0, 1.0]))
    backwards = [measured[name] for name in ("b_ticks", "b_y", "c_ticks")]
    np.testing.assert_allclose(backwards, [-100.0, 0.0, 250.0], atol=FLOAT32_ATOL)


def test_every_phase_measure_matches_the_term_on_the_phase_alone():
    """Each registered term that a script may read, over a phase padded to the trajectory's
    length, equals the term on the phase's samples alone."""
    n, first, last = 30, 7, 19
    ts = np.arange(n) * TICK
    frame = rotation(2, 0.05 * np.arange(n) ** 1.5) @ rotation(1, 0.3 * np.arange(n))
    com = np.stack([0.4 * ts * 10, 0.05 * np.sin(ts * 30), 0.3 + 0.2 * np.sin(ts * 25)], axis=1)
    shape = np.array([[0.3, 0.2, -0.3], [-0.3, 0.2, -0.3], [0.3, -0.2, -0.3], [0.0, 0.0, 0.3]])
    points = com[:, None, :] + np.einsum("tij,nj->tni", frame, shape)
    motion = make(ts, com, points, frame)
    piece = make(
        ts[first : last + 1],
        com[first : last + 1],
        points[first : last + 1],
        frame[first : last + 1],
    )

    names = [m for m in script_measures() if not m.startswith("delta_")]
    text = "\n".join(f"m_{m} = mid.{m}" for m in names) + "\ntotal = 0"
    script = Script(text, ("before", "mid", "after"), TICK)

    @jax.jit
    def compare(motion, piece, transitions):
        values = script.values(motion, transitions)
        alone = {m: terms()[m].fn(piece, **dict(terms()[m].options)) for m in names}
        # What the excluded terms would get wrong on the padded window.
        window = script_module._phase_window(motion, first, last)
        wrong = {
            m: (terms()[m].fn(window), terms()[m].fn(piece)) for m in ("final_spin", "air_height")
        }
        return values, alone, wrong

    values, alone, wrong = compare(motion, piece, jnp.array([ts[first], ts[last]]))
    assert float(values["m_rotations"]) > 0.1  # the phase does turn: a real test of the sums
    for m in names:
        np.testing.assert_allclose(
            values[f"m_{m}"], alone[m], rtol=FLOAT32_RTOL, atol=FLOAT32_ATOL, err_msg=m
        )
    assert not np.isfinite(wrong["final_spin"][0]) and np.isfinite(wrong["final_spin"][1])
    assert float(wrong["air_height"][0]) != pytest.approx(
        float(wrong["air_height"][1]), rel=FLOAT32_RTOL
    )


@pytest.mark.parametrize("term", ["air_height", "asymmetry", "final_spin"])
def test_terms_inexact_over_a_phase_are_refused(term):
    with pytest.raises(ScriptError, match="cannot be a phase's measure") as error:
        Script(f"x = 1\ntotal = b.{term}", ("a", "b"), TICK)
    assert (error.value.line, error.value.column) == (2, 11)
    assert term not in script_measures()


# --- grammar ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "expression, value",
    [
        ("1 + 2 * 3", 7.0),
        ("(1 + 2) * 3", 9.0),
        ("8 - 3 - 2", 3.0),  # left-associative
        ("8 / 4 / 2", 1.0),
        ("2 * 3 / 4", 1.5),
        ("-2 * 3", -6.0),
        ("2 * -3", -6.0),
        ("- - 2", 2.0),
        ("-(1 + 2)", -3.0),
        ("1 - -1", 2.0),
        ("2.5e1 / 5", 5.0),
        (".5 + 1.", 1.5),
        ("1e-3 * 1000", 1.0),
        ("3E+2", 300.0),
        ("((7))", 7.0),
        ("3 ?= 1 + 2", 1.0),  # ?= binds more loosely than +
        ("(4 ?= 4) * 2 + 1", 3.0),
        ("2 * (5 ?= 5)", 2.0),
    ],
)
def test_precedence_associativity_and_numbers(expression, value):
    assert constant(expression) == pytest.approx(value, rel=FLOAT32_RTOL)


def test_comments_blank_lines_and_earlier_variables():
    text = (
        "# a comment: anything goes here $ ' ?= ((\n"
        "\n"
        "a = 2   # two\r\n"
        "   \t\n"
        "b = a * a - a # four minus two\n"
        "total = b / a + only.delta_time  # one, plus two ticks\n"
    )
    script = Script(text, ("only",), TICK)
    values = script.values(tiny_motion(), jnp.zeros((0,)))
    assert {k: float(v) for k, v in values.items()} == {"a": 2.0, "b": 2.0, "total": 3.0}


def test_static_hashable_and_round_trips():
    script = Script(TABLE_4, STAR_MAN, TICK)
    assert jax.tree_util.tree_leaves(script) == []
    again = Script(script.to_text(), script.phases, script.tick)
    assert again == script and hash(again) == hash(script)
    assert (script.text, script.phases, script.tick) == (TABLE_4, STAR_MAN, TICK)


# --- the closeness operator -----------------------------------------------------------------


def test_closeness_properties():
    rng = np.random.default_rng(0)
    equal = np.array([0.0, -3.0, 1e-4, 1.0, 159.0, 2e5])
    random_a, random_b = rng.normal(size=50) * 10, rng.normal(size=50) * 10
    gaps = np.linspace(0, 60, 61)
    # Operands differing by k tenths of their root mean square (about 100): 2 ** -k**2.
    tenths = np.array([1.0, 2.0, 3.0])
    gap = 0.1 * tenths * 100.0 / np.sqrt(1 - (0.1 * tenths) ** 2 / 4)
    # The examples the docstring gives.
    example_a, example_b = [100.0, 100.0, 159.0, 159.0], [110.5, 90.5, 144.0, 176.0]
    parts_a = [equal, random_a, 100 + 0 * gaps, 100 + 0 * gaps, 100 - gap / 2, example_a]
    parts_b = [equal, random_b, 100 + gaps, 100 - gaps, 100 + gap / 2, example_b]
    a, b = np.concatenate(parts_a), np.concatenate(parts_b)
    ab, ba = np.asarray(closeness(a, b)), np.asarray(closeness(b, a))
    np.testing.assert_array_equal(ab, ba)
    ab = np.split(ab, np.cumsum([len(part) for part in parts_a])[:-1])

    np.testing.assert_array_equal(ab[0], 1.0)
    for falling in ab[2:4]:
        assert np.all(np.diff(falling) < 0) and falling[-1] < 1e-3
    np.testing.assert_allclose(ab[4], 2.0 ** -(tenths**2), rtol=FLOAT32_RTOL)
    # About 1/2: to the 0.01 that the operands' rounding to 0.5 or 1 leaves.
    np.testing.assert_allclose(ab[5], 0.5, atol=0.01)
    assert constant("159 ?= 150") == pytest.approx(close_np(159, 150), rel=FLOAT32_RTOL)


def test_closeness_is_differentiable(x64):
    a = np.array([5.0, 100.0, 0.0, -1.0, 0.5])
    b = np.array([5.0, 95.0, 0.0, -1.05, 0.52])
    da, db = jax.jit(jax.vmap(jax.grad(closeness, argnums=(0, 1))))(a, b)
    close = jax.jit(closeness)
    assert np.all(np.isfinite(da)) and np.all(np.isfinite(db))
    assert (da[0], db[0]) == (0.0, 0.0)  # the top, at equality
    fd_a = (close(a + FD_STEP, b) - close(a - FD_STEP, b)) / (2 * FD_STEP)
    fd_b = (close(a, b + FD_STEP) - close(a, b - FD_STEP)) / (2 * FD_STEP)
    np.testing.assert_allclose(da, fd_a, rtol=FD_RTOL, atol=FD_RTOL)
    np.testing.assert_allclose(db, fd_b, rtol=FD_RTOL, atol=FD_RTOL)


# --- batching and compilation ---------------------------------------------------------------


def test_vmap_equals_a_loop_and_jit_compiles_once(star_man):
    script, values, traces = star_man
    motions = [star_man_motion(speed) for speed in (0.8, 1.0, 0.5)]
    transitions = jnp.array([[1.5, 2.4], [1.59, 2.49], [0.7, 3.1]])
    batch = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *motions)
    batched = jax.jit(jax.vmap(script))(batch, transitions)
    looped = [values(m, t)["total"] for m, t in zip(motions, transitions, strict=True)]
    np.testing.assert_allclose(batched, looped, rtol=FLOAT32_RTOL)
    assert len(set(np.asarray(looped).tolist())) == 3  # three different motions and values
    assert len(traces) == 1  # one compiled function served every transition array


def test_not_finite_scores_minus_infinity():
    script = Script("total = 1 + only.delta_cm_x", ("only",), TICK)
    motion = tiny_motion()
    assert float(script(motion, jnp.zeros((0,)))) == 1.0
    broken = jm.Trajectory(
        ts=motion.ts,
        points=motion.points,
        com=motion.com,
        frame=motion.frame,
        contact=motion.contact,
        finite=jnp.asarray(False),
    )
    assert float(script(broken, jnp.zeros((0,)))) == -math.inf
    divide = Script("total = 1 / (only.delta_time - 2)", ("only",), TICK)
    assert float(divide.values(tiny_motion(), jnp.zeros((0,)))["total"]) == math.inf
    assert float(divide(tiny_motion(), jnp.zeros((0,)))) == -math.inf


# --- errors -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, line, column, message",
    [
        ("total = 1 $ 2", 1, 11, "unexpected character '$'"),
        ("total = 1 ? 2", 1, 11, "expected '=' after '?'"),
        ("x = 1\ntotal = (x + 2", 2, 15, "expected ')' to close the '(' at column 9"),
        ("total = (1 + (2 * 3)\n", 1, 21, "expected ')' to close the '(' at column 9"),
        ("total = 1 + 2)", 1, 14, "unbalanced ')'"),
        ("total = 1 +", 1, 12, "expected a number, a name or '(' after '+'; got end of line"),
        ("total = * 2", 1, 9, "after '='; got '*'"),
        ("total = 2 * / 3", 1, 13, "after '*'; got '/'"),
        ("total = ()", 1, 10, "after '('; got ')'"),
        ("total = 1 2", 1, 11, "expected an operator"),
        ("total = 1 = 2", 1, 11, "expected an operator"),
        ("total = 1e", 1, 9, "malformed number '1e'"),
        ("total = 1.2.3", 1, 9, "malformed number"),
        ("total = 1 ?= 1 ?= 1", 1, 16, "'?=' does not chain"),
        ("total = speed", 1, 9, "unknown name 'speed'"),
        ("total = a.delta_time", 1, 9, "unknown phase 'a'"),
        (
            "total = jump.delta_tim",
            1,
            14,
            "unknown measure 'delta_tim' (did you mean 'delta_time'?)",
        ),
        ("total = jump.", 1, 14, "expected a measure's name after 'jump.'"),
        ("total = jump * 2\njump = 1", 1, 9, "the phase 'jump' has no value yet"),
        ("x = 1\ntotal = delta_cm_x", 2, 9, "the measure 'delta_cm_x' needs a phase"),
        ("fast = clearance\ntotal = fast", 1, 8, "'fast' is not a phase"),
        ("jump = jump + 1\ntotal = 1", 1, 8, "used in its own assignment"),
        ("x = 1\n\nx = 2\ntotal = x", 3, 1, "'x' is already assigned on line 1"),
        ("delta_time = 1\ntotal = 1", 1, 1, "cannot assign to 'delta_time'"),
        ("3 = total", 1, 1, "expected a name to assign"),
        ("total 3", 1, 7, "expected '=' after 'total'; got '3'"),
        ("total", 1, 6, "expected '=' after 'total'; got end of line"),
        ("x = 1\n# no total\n", 3, 1, "expected an assignment 'total = ...'"),
        ("", 1, 1, "empty script"),
        ("# only a comment", 1, 17, "empty script"),
        ("total = __import__('os')", 1, 20, 'unexpected character "\'"'),
        ("total = __import__", 1, 9, "unknown name '__import__'"),
        ("total = os.system", 1, 9, "unknown phase 'os'"),
        ("total = [1]", 1, 9, "unexpected character '['"),
        ("total = 2 ** 3", 1, 12, "after '*'; got '*'"),
        ("total = " + "(" * 60 + "1" + ")" * 60, 1, 59, "nested more than 50 deep"),
        ("total = " + "-" * 60 + "1", 1, 59, "nested more than 50 deep"),
    ],
)
def test_errors_name_line_and_column(text, line, column, message):
    with pytest.raises(ScriptError) as error:
        Script(text, STAR_MAN, TICK)
    assert (error.value.line, error.value.column) == (line, column), str(error.value)
    assert message in str(error.value)
    assert str(error.value).startswith(f"line {line}, column {column}: ")
    assert isinstance(error.value, ValueError)


def test_unknown_name_lists_what_is_allowed():
    with pytest.raises(ScriptError) as error:
        Script("cartwheel = 1\ntotal = speed", STAR_MAN, TICK)
    message = str(error.value)
    for allowed in ["cartwheel", "jump", "shuffle", "phase.measure", "delta_time", "clearance"]:
        assert allowed in message
    copy = pickle.loads(pickle.dumps(error.value))  # crosses process boundaries intact
    assert (str(copy), copy.line, copy.column) == (message, 2, 9)


@pytest.mark.parametrize(
    "phases, tick, field",
    [
        ((), TICK, "phases"),
        ("abc", TICK, "phases"),
        (("a", "a"), TICK, "distinct"),
        (("a", "b c"), TICK, "identifier"),
        (("clearance",), TICK, "measure"),
        (("total",), TICK, "measure"),
        (("a",), 0.0, "tick"),
        (("a",), math.nan, "tick"),
        (("a",), True, "tick"),
    ],
)
def test_bad_phases_and_tick(phases, tick, field):
    with pytest.raises(ValueError, match=field):
        Script("total = 1", phases, tick)


def test_transitions_of_the_wrong_shape():
    script = Script(TABLE_4, STAR_MAN, TICK)
    with pytest.raises(ValueError, match=r"needs shape \(2,\)"):
        script(star_man_motion(), jnp.array([1.5]))
    with pytest.raises(ValueError, match="unbatched"):
        batch = jax.tree_util.tree_map(lambda x: x[None], star_man_motion())
        script(batch, jnp.array([1.5, 2.4]))


def test_the_interpreter_never_evaluates_python():
    source = Path(script_module.__file__).read_text()
    assert re.search(r"\b(eval|exec|compile)\s*\(", source.replace("re.compile(", "")) is None
    assert re.search(r"^\s*(import ast|from ast )", source, re.MULTILINE) is None
