"""Robust evaluation (the second paper's enhanced controllers): random starts within their
documented magnitudes, drawn reproducibly from a key, and the fitness reduced over them."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm
from jaxmotion._body.figure import FigurePositions

SEAT = 1e-5  # m: the lowest point is re-seated at its old height to float32 rounding
ANGLE = 1e-5  # rad: float32 rounding of an angle read back from a quaternion
WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)


def lowest(body, positions):
    return float(jnp.min(body.dynamics().observe(positions, jm.World()).points[:, 2]))


def one(tree, k):
    return jax.tree_util.tree_map(lambda a: a[k], tree)


@pytest.mark.parametrize("make", [jm.figures.star_man, jm.figures.cujo])
def test_figure_starts_stay_within_their_magnitudes(make):
    body = make()
    robust = jm.Robustness(samples=6, angles=0.2, orientation=0.3, velocity=0.5)
    start = body.initial_state()
    starts = robust.starts(body, start, jr.key(0))
    ranges = np.asarray(body.ranges).reshape(-1, 2)
    for k in range(robust.samples):
        s = one(starts, k)
        pos, vel = s
        moved = np.asarray(pos.angles) - np.asarray(start.positions.angles)
        assert np.all(np.abs(moved) <= robust.angles + ANGLE)
        assert np.all((pos.angles >= ranges[:, 0] - ANGLE) & (pos.angles <= ranges[:, 1] + ANGLE))
        # The root turned by at most `orientation` (w = cos(angle / 2)), as a unit quaternion.
        q = np.asarray(pos.orientation)
        assert abs(np.linalg.norm(q) - 1) < ANGLE
        assert 2 * np.arccos(min(1.0, abs(q[0]))) <= robust.orientation + ANGLE
        dv = np.asarray(vel.com_velocity) - np.asarray(start.velocities.com_velocity)
        assert np.all(np.abs(dv) <= robust.velocity + ANGLE)
        np.testing.assert_array_equal(vel.momentum, start.velocities.momentum)
        # Re-seated on the floor: the lowest point where it was at rest.
        assert abs(lowest(body, FigurePositions(*pos)) - lowest(body, start.positions)) < SEAT
    # The starts differ from each other and from the start they perturb.
    angles = np.asarray(starts.positions.angles)
    assert len({tuple(a) for a in angles}) == robust.samples
    assert not np.any(np.all(angles == np.asarray(start.positions.angles), axis=1))


def test_lattice_starts_are_rigid_turns_and_pushes():
    body = jm.lattices.cube()
    robust = jm.Robustness(samples=4, orientation=0.3, velocity=0.5)
    start = body.initial_state()
    starts = robust.starts(body, start, jr.key(1))
    x0 = np.asarray(start.positions)
    for k in range(robust.samples):
        x, v = (np.asarray(a) for a in one(starts, k))
        # Rigid: every distance between masses kept.
        d0 = np.linalg.norm(x0[:, :, None] - x0[:, None, :], axis=0)
        d = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=0)
        np.testing.assert_allclose(d, d0, atol=SEAT)
        assert abs(x[2].min() - x0[2].min()) < SEAT
        # One push for every mass, each component within the magnitude.
        np.testing.assert_allclose(v, np.repeat(v[:, :1], v.shape[1], axis=1))
        assert np.all(np.abs(v[:, 0]) <= robust.velocity)
        assert not np.allclose(x, x0)


def test_starts_are_reproducible_from_their_key():
    body = jm.figures.star_man()
    robust = jm.Robustness(samples=3)
    a = robust.starts(body, body.initial_state(), jr.key(7))
    b = robust.starts(body, body.initial_state(), jr.key(7))
    c = robust.starts(body, body.initial_state(), jr.key(8))
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.positions.angles, c.positions.angles)
    # nominal: the first start is the state itself, the others the same draws.
    nominal = jm.Robustness(samples=3, nominal=True).starts(body, body.initial_state(), jr.key(7))
    for x, y, s in zip(
        jax.tree_util.tree_leaves(nominal),
        jax.tree_util.tree_leaves(a),
        jax.tree_util.tree_leaves(body.initial_state()),
        strict=True,
    ):
        np.testing.assert_array_equal(x[0], s)
        np.testing.assert_array_equal(x[1:], y[1:])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(samples=0), "samples = 0"),
        (dict(angles=-0.1), "angles = -0.1"),
        (dict(velocity="fast"), "velocity = 'fast'"),
        (dict(reduce="median"), "reduce = 'median'; allowed: 'mean', 'worst'"),
        (dict(common="yes"), "common = 'yes'; allowed: True or False"),
        (dict(nominal=1), "nominal = 1; allowed: True or False"),
    ],
)
def test_bad_settings_are_refused_naming_them(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jm.Robustness(**kwargs)


@pytest.fixture(scope="module")
def robust_task():
    body = jm.figures.star_man()
    space = jm.TimeBSRSpace(body, num_rules=3, t_per=0.2, tau_min=0.02, tau_max=0.2)
    return jm.Task(
        body,
        WORLD,
        space,
        jm.Objective({"forward": 1.0, "final_tilt": -0.1}),
        duration=0.2,
        dt=4e-3,
        robustness=jm.Robustness(samples=3),
    )


def like(task, **changes):
    """The task with only `changes` (a start, a robustness) of its own."""
    return jm.Task(
        task.body, task.world, task.space, task.objective, task.duration, task.dt, **changes
    )


def test_robust_fitness_is_the_mean_or_worst_over_the_starts(robust_task):
    """A controller's robust fitness is the mean (or the minimum) of its fitness from each
    random start, each computed by a plain task starting there; the same key gives the
    same fitness, another key another."""
    task = robust_task
    params = task.sample(4, key=jr.key(0))
    key = jr.key(3)
    fitness = task.evaluate(params, key=key)
    np.testing.assert_array_equal(fitness, task.evaluate(params, key=key))
    assert not np.array_equal(fitness, task.evaluate(params, key=jr.key(4)))
    starts = task.random_starts(key)
    plain = [
        like(task, initial_state=one(starts, k)).evaluate(params)
        for k in range(task.robustness.samples)
    ]
    per_start = np.stack([np.asarray(p) for p in plain], axis=-1)
    np.testing.assert_allclose(fitness, per_start.mean(axis=-1), rtol=1e-6)
    worst = like(task, robustness=jm.Robustness(samples=3, reduce="worst"))
    worst = worst.evaluate(params, key=key)
    np.testing.assert_array_equal(worst, per_start.min(axis=-1))
    # One key per controller: the controllers given the shared key score as above.
    keys = jnp.stack([key, jr.key(9), key, key])
    mixed = task.evaluate(params, key=keys)
    np.testing.assert_array_equal(np.asarray(mixed)[[0, 2, 3]], np.asarray(fitness)[[0, 2, 3]])


def test_a_robust_task_needs_a_key(robust_task):
    params = robust_task.sample(2, key=jr.key(0))
    with pytest.raises(ValueError, match="needs key="):
        robust_task.evaluate(params)
    with pytest.raises(ValueError, match=r"one per controller \(2,\)"):
        robust_task.evaluate(params, key=jr.split(jr.key(0), 3))


def test_a_robust_serial_search_is_reproducible_and_improves(robust_task):
    """The search draws the starts from its key: the same key gives the same search; the
    best robust fitness never falls below the initial set's best."""
    run = lambda: jm.serial_search(
        robust_task, key=jr.key(5), climbers=4, generations=4, reseed_every=2
    )
    a, b = run(), run()
    assert a.best_fitness == b.best_fitness
    np.testing.assert_array_equal(a.history.fitness, b.history.fitness)
    assert a.best_fitness >= float(np.max(np.asarray(a.history.fitness)[:4]))


def test_a_config_asks_for_robustness_and_round_trips():
    """`[robustness]` builds the task's `Robustness` (defaults filled in, written back in the
    resolved config); a bad key or value names itself and what is allowed."""
    import tomllib

    import tomli_w

    from jaxmotion.experiment import ConfigError, parse_config

    raw = {
        "body": {"figure": "star_man"},
        "controller": {"family": "sense_bsr", "num_rules": 4},
        "objective": {"forward": 1.0},
        "simulation": {"duration": 1.0, "dt": 0.004},
        "search": {"algorithm": "serial_search"},
        "robustness": {"samples": 3, "reduce": "worst"},
    }
    e = parse_config(raw)
    assert e.task.robustness == jm.Robustness(samples=3, reduce="worst")
    assert e.config["robustness"]["angles"] == 0.1
    again = parse_config(tomllib.loads(tomli_w.dumps(e.config)))
    assert again.config == e.config and again.task.robustness == e.task.robustness
    with pytest.raises(ConfigError, match=r"\[robustness\] reduce = 'median'.*\"mean\" or"):
        parse_config({**raw, "robustness": {"reduce": "median"}})
    with pytest.raises(ConfigError, match=r"\[robustness\] common = 1"):
        parse_config({**raw, "robustness": {"common": 1}})
    assert parse_config({**raw, "robustness": {"common": True}}).task.robustness.common
    assert parse_config({**raw, "robustness": {"nominal": True}}).task.robustness.nominal
    with pytest.raises(ConfigError, match=r"\[robustness\].*'spin'"):
        parse_config({**raw, "robustness": {"spin": 0.1}})
    assert parse_config({k: v for k, v in raw.items() if k != "robustness"}).task.robustness is None


def test_a_robust_hill_climb_is_reproducible(robust_task):
    """parallel_hill_climb draws each step's starts from its key: the same key gives the
    same search."""
    run = lambda: jm.parallel_hill_climb(robust_task, key=jr.key(6), evaluations=4, size=4, batch=2)
    a, b = run(), run()
    np.testing.assert_array_equal(a.history.fitness, b.history.fitness)
    assert a.best_fitness >= float(np.max(a.history.fitness[:4]))


def test_common_starts_are_drawn_once_per_search(robust_task):
    """With `common=True` every evaluation of a search faces the starts its initial set
    drew (serial search: the enrichment rounds and every generation; hill climbing: every
    step), so climbers are compared on the same starts; by default each generation or step
    draws new ones. A common search is reproducible and never loses its initial best."""
    from jaxmotion._search.hill_climb import ParallelHillClimb, _start_key
    from jaxmotion._search.serial import _start_keys

    common = like(robust_task, robustness=jm.Robustness(samples=3, common=True))
    keys = jr.split(jr.key(0), 2)

    def drawn(task):  # (stream, index): init, an enrichment round, two generations
        calls = ((0, 0), (1, 2), (2, 0), (2, 7))
        return [np.asarray(jr.key_data(_start_keys(task, keys, 4, s, i))) for s, i in calls]

    shared, fresh = drawn(common), drawn(robust_task)
    for k in shared[1:]:
        np.testing.assert_array_equal(k, shared[0])
    np.testing.assert_array_equal(fresh[0], shared[0])  # the same first draw
    assert not any(np.array_equal(fresh[0], k) for k in fresh[1:])
    assert not np.array_equal(fresh[2], fresh[3])

    state, _ = ParallelHillClimb(size=4, batch=2).init(common, key=jr.key(1))
    for task, same in ((common, True), (robust_task, False)):
        a = np.asarray(jr.key_data(_start_key(task, state.key, state.step)))
        b = np.asarray(jr.key_data(_start_key(task, state.key, state.step + 5)))
        assert np.array_equal(a, b) == same

    run = lambda: jm.serial_search(common, key=jr.key(5), climbers=4, generations=4)
    a, b = run(), run()
    np.testing.assert_array_equal(a.history.fitness, b.history.fitness)
    assert a.best_fitness >= float(np.max(np.asarray(a.history.fitness)[:4]))
