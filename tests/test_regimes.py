"""The regimes controller and its search space (first paper, section 2.2, Table 2)."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from scipy import stats

import jaxmotion as jm
from jaxmotion._control.regimes import ADJUST

CUBE = jm.lattices.cube()
LOCAL = CUBE.points - CUBE.com  # the cube's frame is the identity


def deform(reflex, coefficient):
    return np.asarray(jm.deform(LOCAL, jnp.asarray(reflex), jnp.asarray(coefficient)))


def test_reflex_names():
    assert jm.REFLEX_NAMES[0] == "scale-forward"
    assert jm.REFLEX_NAMES[5] == "shear-up"
    assert jm.REFLEX_NAMES[11] == "twist-up"
    assert len(set(jm.REFLEX_NAMES)) == 12


@pytest.mark.parametrize("reflex", range(12))
def test_coefficient_zero_is_the_identity(reflex):
    np.testing.assert_array_equal(deform(reflex, 0.0), np.asarray(LOCAL))


def test_the_twelve_reflexes_give_twelve_different_rest_shapes():
    tables = [np.asarray(CUBE.rest_length_matrix(CUBE.com + deform(r, 1.0))) for r in range(12)]
    for a, b in itertools.combinations(range(12), 2):
        assert np.abs(tables[a] - tables[b]).max() > 1e-2, (jm.REFLEX_NAMES[a], jm.REFLEX_NAMES[b])
    rest = np.asarray(CUBE.rest_length_matrix())
    assert all(np.abs(t - rest).max() > 1e-2 for t in tables)


def test_each_deformation_does_what_its_name_says():
    a_scale, a_shear, a_splay, a_twist = jm.Regimes([0.0], [0], [0.0], 1.0).amplitudes
    top = LOCAL[:, 2] > 0
    # scale-up: the height grows by (1 + A), nothing else changes.
    d = deform(2, 1.0)
    np.testing.assert_allclose(d[:, 2], (1 + a_scale) * LOCAL[:, 2], rtol=1e-6)
    np.testing.assert_allclose(d[:, :2], LOCAL[:, :2])
    # shear-forward: layers slide forward in proportion to height (leaning forwards).
    d = deform(3, 1.0)
    np.testing.assert_allclose(d[:, 0] - LOCAL[:, 0], a_shear * LOCAL[:, 2], rtol=1e-6)
    assert d[top, 0].mean() > d[~top, 0].mean()
    # splay-up: the top cross-section widens, the bottom one narrows.
    d = deform(8, 1.0)
    width = lambda pts: np.ptp(pts[:, 1])
    assert width(d[top]) == pytest.approx((1 + a_splay) * 1.0, rel=1e-6)
    assert width(d[~top]) == pytest.approx((1 - a_splay) * 1.0, rel=1e-6)
    # twist-up: the top face turns by +A, the bottom by -A, about the up axis.
    d = deform(11, 1.0)
    angle = lambda pts: np.arctan2(pts[:, 1], pts[:, 0])
    turn = (angle(d) - angle(np.asarray(LOCAL)) + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(turn[top], a_twist, rtol=1e-5)
    np.testing.assert_allclose(turn[~top], -a_twist, rtol=1e-5)
    np.testing.assert_allclose(d[:, 2], LOCAL[:, 2])


def test_deformations_happen_in_the_lattice_frame():
    """A lattice whose frame is turned 90 degrees about z scales along its own forward axis."""
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # forward = +y
    lattice = jm.lattices.from_points(np.asarray(CUBE.points), np.asarray(CUBE.springs), frame=turn)
    shapes = jm.Regimes([0.0], [0], [1.0], 1.0).shapes(lattice)[0]
    extent = np.ptp(np.asarray(shapes), axis=0)
    np.testing.assert_allclose(extent, [1.0, 1.3, 1.0], rtol=1e-6)


def test_active_regime_is_the_nearest_time_modulo_the_period():
    c = jm.Regimes(
        times=[0.1, 0.5, 0.8], reflexes=[0, 1, 2], coefficients=[0.5, -0.5, 1.0], t_per=1.0
    )
    cases = {0.0: 0, 0.29: 0, 0.31: 1, 0.64: 1, 0.66: 2, 0.99: 2, 1.05: 0, 2.4: 1, 3.7: 2}
    plan = c.prepare(CUBE)
    for t, regime in cases.items():
        assert int(c.active(jnp.asarray(t))) == regime, t
        np.testing.assert_array_equal(
            np.asarray(acting(c, jnp.asarray(t), plan)), np.asarray(plan[regime])
        )


def acting(c, t, plan):
    """The actuation held after a control tick at `t` (one controller, or a batch-last
    stack)."""
    return c.actuation(t, c.update(t, c.init(None, plan), None, plan), plan)


@pytest.mark.parametrize("blend", [0.0, 0.05])
def test_a_tick_on_a_batch_last_stack_acts_as_each_controller_alone(blend):
    """The batched layout calls `update` (the regime chosen once per controller and tick) and
    `actuation` (the table) on a stack of controllers with the batch as the last axis of
    every array: bitwise what each controller gives alone (ties between equally near regimes
    go to the lower index in both)."""
    space = jm.RegimesSpace(num_regimes=4, t_per=1.0)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(3), 12))
    controllers = eqx.tree_at(lambda c: c.times, controllers, controllers.times.at[0, 1].set(0.5))
    controllers = eqx.tree_at(lambda c: c.times, controllers, controllers.times.at[0, 2].set(0.5))
    controllers = jax.vmap(lambda c: c.smoothed(blend))(controllers)
    plans = jax.vmap(lambda c: c.prepare(CUBE))(controllers)
    last = lambda tree: jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), tree)
    stacked, stacked_plans = last(controllers), last(plans)
    for t in [0.0, 0.3, 0.5, 0.77, 1.5, 4.99]:
        t = jnp.asarray(t)
        expected = jax.vmap(lambda c, p, t=t: acting(c, t, p))(controllers, plans)
        initial = last(jax.vmap(lambda c, p: c.init(None, p))(controllers, plans))
        ticked = stacked.update(t, initial, None, stacked_plans)
        batched = stacked.actuation(t, ticked, stacked_plans)
        np.testing.assert_array_equal(
            np.asarray(jnp.moveaxis(batched, -1, 0)), np.asarray(expected)
        )
        if blend == 0.0:
            # The regime chosen at the tick is what `active` says.
            np.testing.assert_array_equal(
                np.asarray(ticked.discrete),
                np.asarray(jax.vmap(lambda c, t=t: c.active(t))(controllers)),
            )
    if blend == 0.0:
        # Regime times 0.5 and 0.5 tie at t = 0.5: the lower index wins.
        assert int(jax.tree_util.tree_map(lambda a: a[0], controllers).active(0.5)) == 1


def test_a_controller_without_state_runs_on_the_default_protocol():
    """A controller that only defines `prepare` and `actuation` carries no state: `init`
    gives an empty `ControllerState` and a tick leaves it unchanged."""

    class Ramp(jm.AbstractController):
        rate: float = 2.0

        def prepare(self, body):
            return None

        def actuation(self, t, state, plan):
            return self.rate * t

    ramp = Ramp()
    state = ramp.init(None, None)
    assert state == jm.ControllerState(None, None)
    assert ramp.update(0.25, state, None, None) == state
    assert ramp.actuation(0.25, state, None) == 0.5
    assert not Ramp.reads_senses and ramp.rates(0.25, state, None) is None


def test_aperiodic_controller_never_wraps():
    c = jm.Regimes(times=[0.5, 4.0], reflexes=[0, 1], coefficients=[1.0, -1.0], t_per=5.0)
    assert [int(c.active(jnp.asarray(t))) for t in (0.0, 2.2, 2.3, 4.9)] == [0, 0, 1, 1]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(times=[0.5, 1.5]), r"regime 1 has time 1.5; allowed: 0 <= time <= t_per = 1"),
        (dict(reflexes=[0, 12]), r"regime 1 has reflex 12; allowed: an integer 0..11"),
        (dict(coefficients=[0.0, -1.5]), r"regime 1 has coefficient -1.5"),
        (dict(t_per=0.0), r"Regimes.t_per = 0.0; allowed: a number > 0"),
        (dict(times=[0.5]), r"same shape"),
    ],
)
def test_bad_regimes_raise(kwargs, message):
    args = dict(times=[0.5, 0.7], reflexes=[0, 1], coefficients=[0.0, 1.0], t_per=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        jm.Regimes(**args)


def test_bad_space_raises():
    with pytest.raises(ValueError, match=r"num_regimes = 0; allowed: an integer >= 1"):
        jm.RegimesSpace(0)
    with pytest.raises(ValueError, match=r"t_per = -1; allowed: a number > 0"):
        jm.RegimesSpace(4, -1)
    with pytest.raises(ValueError, match=r"amplitudes"):
        jm.RegimesSpace(4, 1.0, amplitudes=(1.2, 0.3, 0.3, 0.5))


def sample_many(space, n, seed=0):
    return jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(seed), n))


def test_sampling_follows_the_paper():
    """Times uniform on [0, t_per], reflex numbers uniform on 0..11, coefficients from the
    arcsine distribution on [-1, 1] (more mass near the extremes than uniform)."""
    space = jm.RegimesSpace(num_regimes=4, t_per=2.0)
    s = sample_many(space, 5000)
    times = np.asarray(s.times).ravel()
    assert times.min() >= 0 and times.max() <= 2.0
    assert stats.kstest(times / 2.0, "uniform").pvalue > 1e-3
    counts = np.bincount(np.asarray(s.reflexes).ravel(), minlength=12)
    assert stats.chisquare(counts).pvalue > 1e-3
    coefficients = np.asarray(s.coefficients).ravel()
    assert stats.kstest((coefficients + 1) / 2, stats.arcsine.cdf).pvalue > 1e-3
    # Favouring the extremes: P(|a| > 0.9) is about 0.29 against 0.1 for a uniform draw.
    assert np.mean(np.abs(coefficients) > 0.9) > 0.25
    np.testing.assert_array_equal(np.asarray(s.t_per), 2.0)


def test_perturbation_frequencies_match_table_2():
    """Chi-square test of the operator chosen over 20,000 perturbations (fixed key)."""
    space = jm.RegimesSpace()
    keys = jr.split(jr.key(42), 20_000)
    ops = np.asarray(jax.vmap(lambda k: space.choose_perturbation(key=k))(keys))
    observed = np.bincount(ops, minlength=10)
    expected = np.array([p for p, _ in jm.PERTURBATIONS]) * len(ops)
    assert sum(p for p, _ in jm.PERTURBATIONS) == pytest.approx(1.0)
    assert stats.chisquare(observed, expected).pvalue > 1e-3


def changed(a, b):
    return np.asarray(a) != np.asarray(b)


@pytest.mark.parametrize("op", range(10))
def test_each_perturbation_changes_what_it_says(op):
    space = jm.RegimesSpace(num_regimes=6, t_per=1.0)
    parents = sample_many(space, 400, seed=1)
    keys = jr.split(jr.key(op), 400)
    children = jax.vmap(lambda p, k: space.apply_perturbation(jnp.asarray(op), p, key=k))(
        parents, keys
    )
    name = jm.PERTURBATIONS[op][1]
    field = {
        "reflex number": "reflexes",
        "reflex coefficient": "coefficients",
        "regime time": "times",
    }[next(k for k in ("reflex number", "reflex coefficient", "regime time") if k in name)]
    for other in {"reflexes", "coefficients", "times"} - {field}:
        np.testing.assert_array_equal(
            np.asarray(getattr(children, other)), np.asarray(getattr(parents, other))
        )
    diff = changed(getattr(children, field), getattr(parents, field))
    per_controller = diff.sum(axis=1)
    if "one regime" in name:
        assert per_controller.max() == 1
    else:
        assert per_controller.max() == 6
    old = np.asarray(getattr(parents, field), dtype=float)
    new = np.asarray(getattr(children, field), dtype=float)
    if name.startswith("adjust"):
        low, high = (-1.0, 1.0) if field == "coefficients" else (0.0, 1.0)
        ratio = np.where(old != 0, new / np.where(old != 0, old, 1), 1.0)
        clipped = (new == low) | (new == high)
        assert np.all((np.abs(ratio - 1) <= ADJUST + 1e-6) | clipped)
        assert np.abs(ratio - 1).max() > 0.05  # it does adjust, by up to 10%
    if field == "reflexes":
        assert new.min() >= 0 and new.max() <= 11
    if field == "coefficients":
        assert np.abs(new).max() <= 1.0
    if field == "times":
        assert new.min() >= 0 and new.max() <= 1.0


def test_perturb_is_deterministic_given_the_key():
    space = jm.RegimesSpace()
    parent = space.sample(key=jr.key(0))
    a = space.perturb(parent, key=jr.key(5))
    b = space.perturb(parent, key=jr.key(5))
    for f in ("times", "reflexes", "coefficients"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
