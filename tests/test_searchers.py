"""The searcher protocol: one contract every registered searcher passes, on a synthetic task
with a planted optimum (no simulation, so the whole file compiles little), and the evosax
adapter on real controller spaces."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import tomli_w
from jaxtyping import Array, Float, Int

import jaxmotion as jm
from jaxmotion._cli.checkpoint import state_from_bytes, state_to_bytes
from jaxmotion._control.base import AbstractController, AbstractControllerSpace
from jaxmotion._search.evosax import minimised
from jaxmotion.experiment import ConfigError, load_config, parse_config, run_experiment

TARGET = jnp.array([0.3, -0.5, 0.2, 0.7])  # the planted optimum, inside the bounds [-1, 1]


class Point(AbstractController):
    """A synthetic controller: a point in [-1, 1]^4 and a discrete label that fitness
    ignores (as a regime's reflex number, held fixed by the evosax adapter)."""

    x: Float[Array, " 4"]
    label: Int[Array, ""]

    def prepare(self, body):
        del body

    def actuation(self, t, state, plan):
        del t, state, plan


class PointSpace(AbstractControllerSpace[Point]):
    def sample(self, *, key):
        x_key, label_key = jr.split(key)
        return Point(
            jr.uniform(x_key, (4,), minval=-1.0, maxval=1.0), jr.randint(label_key, (), 0, 4)
        )

    def perturb(self, controller, *, key, motion=None):
        del motion
        step = 0.1 * jr.normal(key, (4,))
        return Point(jnp.clip(controller.x + step, -1.0, 1.0), controller.label)

    @property
    def family(self):
        return "point"

    def trainable(self, controller):
        return Point(True, False)

    def project(self, controller):
        return Point(jnp.clip(controller.x, -1.0, 1.0), controller.label)


class Planted(eqx.Module):
    """A task without a simulator: fitness is minus the squared distance to `TARGET`; with
    `storm`, every third candidate (by its first coordinate's last bits) scores NaN and
    every seventh `-inf`, as blown-up simulations do."""

    space: PointSpace
    storm: bool = eqx.field(static=True, default=False)
    robustness: None = eqx.field(static=True, default=None)

    def sample(self, n, *, key):
        return jax.vmap(lambda k: self.space.sample(key=k))(jr.split(key, n))

    def evaluate(self, params, *, chunk=None, key=None):
        del chunk, key
        return _score(self, params)


@eqx.filter_jit
def _score(task: Planted, params):
    fitness = -jnp.sum((params.x - TARGET) ** 2, axis=1)
    if task.storm:
        bits = jax.lax.bitcast_convert_type(params.x[:, 0], jnp.int32)
        fitness = jnp.where(bits % 3 == 0, jnp.nan, fitness)
        fitness = jnp.where(bits % 7 == 0, -jnp.inf, fitness)
    return fitness


# Every registered searcher, with settings for about 600 evaluations of the synthetic task.
SETTINGS = {
    "parallel_hill_climb": (dict(size=20, batch=20), 30),
    "serial_search": (dict(climbers=10, reseed_every=10, seeds=2, archive=15), 30),
    "evolve": (dict(size=20, mutations=2), 30),
    "evosax": (dict(strategy="CMA_ES", population=16, size=16), 30),
    "evosax_open_es": (dict(strategy="Open_ES", population=16, size=16, learning_rate=0.1), 30),
}
# The planted optimum is approached: the best squared distance at the end is at most this
# share of the best of the random start (a random point in [-1, 1]^4 is ~1.3 away on average).
APPROACH = 0.1


def finite_leaves(state) -> bool:
    """Whether no floating leaf of `state` holds a NaN (every searcher's invariant)."""
    return all(
        not np.any(np.isnan(np.asarray(a)))
        for a in jax.tree_util.tree_leaves(state)
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.inexact)
    )


def test_every_registered_searcher_is_in_the_contract():
    assert set(jm.SEARCHERS) <= {name.split("_open")[0] for name in SETTINGS}


def _searcher(name):
    settings, steps = SETTINGS[name]
    return jm.SEARCHERS[name.split("_open")[0]](**settings), steps


def _same(a, b) -> bool:
    """Bitwise equal pytrees (keys compared by their data)."""
    data = lambda t: jax.tree_util.tree_map(
        lambda x: jr.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x, t
    )
    la, ta = jax.tree_util.tree_flatten(data(a))
    lb, tb = jax.tree_util.tree_flatten(data(b))
    same = lambda x, y: np.array_equal(
        np.asarray(x), np.asarray(y), equal_nan=np.issubdtype(np.asarray(x).dtype, np.inexact)
    )  # a NaN placeholder (evosax's unset best) equals itself
    return ta == tb and all(same(x, y) for x, y in zip(la, lb, strict=True))


@pytest.fixture(scope="module", params=sorted(SETTINGS))
def run(request):
    """One search per searcher on the planted task, and one on its stormy version."""
    searcher, steps = _searcher(request.param)
    task = Planted(PointSpace())
    result = jm.drive(searcher, task, key=jr.key(0), steps=steps)
    stormy = jm.drive(searcher, Planted(PointSpace(), storm=True), key=jr.key(0), steps=steps)
    return request.param, searcher, task, result, stormy


def test_the_planted_optimum_is_approached(run):
    name, _, _, result, _ = run
    history = result.history
    start = -float(np.max(history.fitness[history.step == 0]))
    end = -result.best_fitness
    assert end <= APPROACH * start, (name, start, end)
    assert result.best_fitness == pytest.approx(float(np.max(history.fitness)), abs=0)
    assert float(np.max(history.fitness)) == -float(jnp.sum((result.best.x - TARGET) ** 2))


def test_non_finite_fitness_never_enters_the_population(run):
    name, _, _, _, stormy = run
    history = stormy.history
    assert np.sum(np.isnan(history.fitness)) == 0, name  # a NaN is recorded as -inf
    assert history.num_nonfinite > 0, name  # the storm reached the search
    assert finite_leaves(stormy.state), name
    assert np.isfinite(stormy.best_fitness), name
    assert stormy.best_fitness == float(np.max(history.fitness)), name
    for field in ("fitness", "best_fitness"):
        if hasattr(stormy.state, field):
            assert not np.any(np.isnan(np.asarray(getattr(stormy.state, field)))), name


def test_the_same_key_gives_the_same_run(run):
    name, searcher, task, result, _ = run
    again = jm.drive(searcher, task, key=jr.key(0), steps=SETTINGS[name][1])
    np.testing.assert_array_equal(again.history.fitness, result.history.fitness)
    assert _same(again.state, result.state), name
    other = jm.drive(searcher, task, key=jr.key(1), steps=2)
    assert not np.array_equal(other.history.fitness, result.history.fitness[: len(other.history)])


def test_ask_and_tell_are_pure_and_jittable(run):
    name, searcher, task, result, _ = run
    state = result.state
    asked = searcher.ask(task, state)
    if name == "serial_search":
        # Compiled at the top level with the simulations' compiler options (`simulation_jit`:
        # bitwise equal lanes), which JAX accepts only on an outermost jit.
        from jaxmotion._search.serial import _ask

        assert _same(_ask.lower(task, state).compile()(task, state), asked)
    else:
        assert _same(eqx.filter_jit(searcher.ask)(task, state), asked), name
    assert _same(searcher.ask(task, state), asked), name  # nothing changed by asking
    fitness, extras = searcher.evaluate(task, state, asked)
    told = searcher.tell(state, asked, fitness, **extras)
    jitted = eqx.filter_jit(lambda s, c, f: searcher.tell(s, c, f, **extras))(state, asked, fitness)
    assert _same(jitted, told), name
    assert searcher.steps_done(told) == searcher.steps_done(state) + 1


def test_init_is_first_then_the_evaluation_then_begin_both_pure(run):
    """`init` = `first` (the candidates and a carry), the first evaluation, then `begin`;
    `first` and `begin` are pure and give, jitted whole, what they give eagerly."""
    name, searcher, task, _, _ = run
    state, initial = searcher.init(task, key=jr.key(0))
    candidates, carry = searcher.first(task, key=jr.key(0))
    if name == "serial_search":
        # Compiled at the top level with the simulations' compiler options, as its `ask`.
        from jaxmotion._search.serial import _sample

        seeds = jnp.arange(searcher.seeds) + searcher.seed_offset
        compiled = _sample.lower(task, jr.key(0), seeds, searcher.climbers).compile()
        again = compiled(task, jr.key(0), seeds, searcher.climbers)
    else:
        again = eqx.filter_jit(lambda t, k: searcher.first(t, key=k))(task, jr.key(0))
    assert _same(again, (candidates, carry)), name
    fitness, extras = task.evaluate(candidates), {}
    if name == "serial_search":
        extras = {"motion": None}
    begun = searcher.begin(task, carry, candidates, fitness, **extras)
    jitted = eqx.filter_jit(lambda t, c, x, f: searcher.begin(t, c, x, f, **extras))
    assert _same(jitted(task, carry, candidates, fitness), begun), name
    assert _same(begun, state), name
    np.testing.assert_array_equal(np.asarray(initial).reshape(-1), np.asarray(fitness))


def test_the_state_round_trips_through_the_checkpoint_format_and_resumes_bitwise(run):
    name, searcher, task, result, _ = run
    steps = SETTINGS[name][1]
    seen = []
    jm.drive(searcher, task, key=jr.key(0), steps=steps, callback=lambda s, h: seen.append((s, h)))
    state, _ = seen[steps // 2]
    history = _history_up_to(searcher, seen[: steps // 2 + 1])
    data, part = state_to_bytes(state, history)
    runs = searcher.runs(state) if searcher.per_run else None
    back, history_back = state_from_bytes(searcher.template(task), part, data, runs)
    assert _same(back, state), name
    resumed = jm.drive(searcher, task, key=None, steps=steps, state=back, history=history_back)
    np.testing.assert_array_equal(resumed.history.fitness, result.history.fitness)
    assert _same(resumed.state, result.state), name


def _history_up_to(searcher, seen):
    parts = [h for _, h in seen]
    if searcher.per_run:
        return tuple(jm.History.concatenate([p[r] for p in parts]) for r in range(len(parts[0])))
    return jm.History.concatenate(parts)


# ------------------------------------------------------------------- evosax on real spaces

DEFAULT = "configs/default.toml"  # paper 000's cube with 4 regimes (integer reflex numbers)
FIGURE = "configs/starman_cartwheel.toml"  # paper 004's Star-Man, time-based rules


def _member(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


def _evosax_state(config, strategy="CMA_ES"):
    """An evosax searcher's state on a real config's task, started from a random set with
    made-up fitness (nothing is simulated)."""
    from jaxmotion._search.evosax import _start

    task = load_config(config).task
    searcher = jm.Evosax(strategy=strategy, population=8, size=12, std_init=3.0)
    population = task.sample(12, key=jr.key(3))
    state = _start(searcher, task, population, jnp.arange(12.0), jr.key(4))
    return task, searcher, state


@pytest.mark.parametrize("config", [DEFAULT, FIGURE])
def test_the_cma_es_adapter_round_trips_parameters_exactly_and_respects_bounds(config):
    task, searcher, state = _evosax_state(config)
    # The template is the best of the random set (fitness 11: the last drawn).
    drawn = jax.tree_util.tree_map(lambda a: a[11], task.sample(12, key=jr.key(3)))
    assert _same(state.template, task.space.project(drawn))
    # Controllers with the template's fixed parts: controller -> vector -> controller exactly.
    others = task.sample(5, key=jr.key(5))
    spec = task.space.trainable(state.template)
    for i in range(5):
        other = _member(others, i)
        mixed = eqx.combine(eqx.filter(other, spec), eqx.filter(state.template, spec, inverse=True))
        vector = searcher.to_vector(task, state, mixed)
        assert _same(searcher.from_vector(task, state, vector), mixed)
        # and vector -> controller -> vector.
        np.testing.assert_array_equal(
            np.asarray(searcher.to_vector(task, state, searcher.from_vector(task, state, vector))),
            np.asarray(vector),
        )
    # A generation drawn with a large step size (std_init 3 spreads) lies within the bounds,
    # its fixed parts the template's.
    asked = searcher.ask(task, state)
    projected = jax.vmap(task.space.project)(asked)
    assert _same(projected, asked)
    fixed = eqx.filter(asked, spec, inverse=True)
    template = eqx.filter(state.template, spec, inverse=True)
    for i in range(searcher.population):
        assert _same(_member(fixed, i), template)
    raw = state.pending  # the strategy's vectors, before projection
    if config == DEFAULT:
        assert bool(jnp.all((asked.times >= 0) & (asked.times <= task.space.t_per)))
        assert bool(jnp.all(jnp.abs(asked.coefficients) <= 1.0))
        outside = jnp.any(jnp.abs(raw * state.scale) > 1.0)
        assert bool(outside)  # the step size put some candidates outside, projected back


def test_evosax_is_told_the_negated_fitness_with_non_finite_ranked_worst():
    fitness = jnp.array([1.0, jnp.nan, -2.0, -jnp.inf, 3.0])
    told = minimised(fitness, jnp.ones(5, dtype=bool))
    np.testing.assert_array_equal(np.asarray(told), [-1.0, 3.0, 2.0, 3.0, -3.0])
    told = minimised(fitness, jnp.arange(5) < 4)  # the last does not count
    np.testing.assert_array_equal(np.asarray(told), [-1.0, 3.0, 2.0, 3.0, 3.0])
    np.testing.assert_array_equal(
        np.asarray(minimised(jnp.full(3, jnp.nan), jnp.ones(3, dtype=bool))), [1.0, 1.0, 1.0]
    )


def _raw(search):
    return {
        "body": {"lattice": "cube"},
        "objective": {"forward": 1.0},
        "simulation": {"duration": 0.5},
        "search": search,
    }


@pytest.mark.parametrize(
    "search, message",
    [
        ({"algorithm": "evosax", "strategy": "CMA"}, r"strategy = 'CMA'; allowed: .*\"CMA_ES\""),
        (
            {"algorithm": "evosax", "strategy": "Open_ES", "population": 31},
            r"population = 31; allowed: an even number for Open_ES",
        ),
        ({"algorithm": "evosax", "population": 1}, r"population = 1; allowed: an integer >= 2"),
        ({"algorithm": "evosax", "std_init": 0.0}, r"std_init = 0.0; allowed: a number > 0"),
        (
            {"algorithm": "evosax", "evaluations": 10},
            r"unknown key 'evaluations'; allowed: algorithm, strategy",
        ),
        (
            {"algorithm": "annealing"},
            r"allowed: a string \"parallel_hill_climb\", .* or \"evosax\"",
        ),
    ],
)
def test_bad_evosax_settings_are_named_before_anything_compiles(search, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(_raw(search))


def test_a_missing_evosax_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "evosax", None)
    monkeypatch.setitem(sys.modules, "evosax.algorithms", None)
    with pytest.raises(ConfigError, match=r"pip install 'jaxmotion\[evosax\]'"):
        parse_config(_raw({"algorithm": "evosax"}))
    with pytest.raises(ImportError, match=r"pip install 'jaxmotion\[evosax\]'"):
        jm.Evosax()


def test_an_evosax_config_runs_and_its_checkpoint_resumes_bitwise(tmp_path):
    """The config layer builds the searcher from the registry; the CLI's checkpoint of an
    evosax search reads back into the same state."""
    from jaxmotion._cli.checkpoint import load_checkpoint, save_checkpoint
    from jaxmotion._cli.config import make_searcher, search_evaluations

    raw = _raw(
        {"algorithm": "evosax", "strategy": "CMA_ES", "population": 8, "size": 8, "generations": 2}
    )
    experiment = parse_config(raw, name="evo")
    searcher, steps, last = make_searcher(experiment.search)
    assert (type(searcher), steps, last) == (jm.Evosax, 2, None)
    assert search_evaluations(experiment.search) == 8 + 2 * 8
    seen = []
    result = jm.drive(
        searcher,
        experiment.task,
        key=jr.key(0),
        steps=steps,
        callback=lambda s, h: seen.append((s, h)),
    )
    assert len(result.history) == 24
    path = tmp_path / "evo.checkpoint"
    save_checkpoint(
        path, experiment, [(seen[1][0], jm.History.concatenate([h for _, h in seen[:2]]))]
    )
    ((state, history),) = load_checkpoint(path, experiment)
    assert _same(state, seen[1][0]) and len(history) == 16
    resumed = jm.drive(
        searcher, experiment.task, key=None, steps=steps, state=state, history=history
    )
    np.testing.assert_array_equal(resumed.history.fitness, result.history.fitness)
    # `run` drives the same searcher from the registry and writes its folder.
    folder = run_experiment(
        experiment, directory=tmp_path / "results", progress=False, animation=False
    )
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["best_fitness"] == result.best_fitness
    assert summary["evaluations"] == 24


def test_compare_budgets_any_two_searchers_equally():
    from jaxmotion._cli.compare import budgeted

    hill = parse_config(_raw({"size": 10, "batch": 4, "evaluations": 90})).search
    evo = parse_config(_raw({"algorithm": "evosax", "population": 8, "size": 12})).search
    serial = parse_config(_raw({"algorithm": "serial_search", "climbers": 5, "runs": 2})).search
    evolve = parse_config(_raw({"algorithm": "evolve", "size": 10})).search
    # 100 simulations: hill climbing and evosax exactly (a partial last step), the
    # generational ones the most whole generations that fit.
    assert budgeted(hill, 100)[1:] == (23, 2, 100)  # 10 + 22 x 4 + 2
    assert budgeted(evo, 100)[1:] == (11, 8, 100)  # 12 + 11 x 8
    assert budgeted(serial, 100)[1:] == (9, None, 100)  # 10 + 9 x 10
    assert budgeted(evolve, 100)[1:] == (11, None, 98)  # 10 + 11 x 8
    with pytest.raises(ConfigError, match="a budget of 10 simulations leaves no step"):
        budgeted(evo, 10)


def test_compare_runs_two_searchers_on_equal_budgets(tmp_path):
    """`compare CONFIG --against TOML`: the config's hill climbing against CMA-ES on the same
    task and budget, the table and the folder written (in this process: the task is the one
    of the evosax config test above, so nothing new compiles)."""
    import argparse
    import csv

    from jaxmotion._cli.main import _compare_searchers

    config, against = tmp_path / "cube.toml", tmp_path / "cma.toml"
    raw = _raw({"size": 8, "batch": 8, "evaluations": 24})
    config.write_text(tomli_w.dumps(raw))
    against.write_text(
        '[search]\nalgorithm = "evosax"\nstrategy = "CMA_ES"\npopulation = 8\nsize = 8\n'
    )
    experiment = parse_config(raw, name="cube")
    args = argparse.Namespace(
        config=str(config), against=str(against), out=str(tmp_path / "out"), quiet=True
    )
    assert _compare_searchers(args, experiment, (0, 1)) == 0
    (folder,) = (tmp_path / "out").iterdir()
    rows = list(csv.DictReader((folder / "compare.csv").open()))
    assert [(r["seed"], r["searcher"], r["simulations"]) for r in rows] == [
        ("0", "parallel_hill_climb", "32"),
        ("0", "evosax CMA_ES", "32"),
        ("1", "parallel_hill_climb", "32"),
        ("1", "evosax CMA_ES", "32"),
    ]
    # Each is the search its [search] table runs on its own, from the seed's key.
    alone = jm.parallel_hill_climb(experiment.task, key=jr.key(1), evaluations=24, size=8, batch=8)
    assert float(rows[2]["best_fitness"]) == alone.best_fitness
    cma = jm.drive(jm.Evosax(population=8, size=8), experiment.task, key=jr.key(0), steps=3)
    assert float(rows[1]["best_fitness"]) == cma.best_fitness and len(cma.history) == 32
    assert "| evosax CMA_ES | 32 |" in (folder / "compare.md").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text('[search]\nalgorithm = "evosax"\nstrategy = "CMA"\n')
    args.against = str(bad)
    with pytest.raises(ConfigError, match=r"--against .*bad.toml: \[search\] strategy = 'CMA'"):
        _compare_searchers(args, experiment, (0,))
