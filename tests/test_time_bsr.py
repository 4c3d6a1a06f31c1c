"""The time-based BSR controller and its search space (second paper, sections 2.1.3, 2.3 and
4.1, Table 2): sampling distributions, the rule schedule, mutation, validation, bounds, and a
figure driven by it."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from scipy import stats

import jaxmotion as jm

# Significance level of every distribution test (fixed keys: a test either passes or fails
# every time; ALPHA only says how unlikely a failure of a correct implementation would be).
ALPHA = 1e-3
# float32 slack when comparing a step with its bound (relative to the bound).
SLACK = 1e-4

REX = jm.figures.rex()  # 10 free angles, ranges symmetric and one-sided ([-40, 0], [0, 40])
T_PER, TAU_MIN, TAU_MAX, CREEP = 2.0, 0.01, 0.5, 0.1
LOG_SPAN = math.log(TAU_MAX / TAU_MIN)
LO, HI = REX.ranges[:, 0], REX.ranges[:, 1]
# The bounds as the float32 controller holds them (rounding can put them just outside LO, HI).
LO32, HI32 = LO.astype(np.float32), HI.astype(np.float32)


def space(**kwargs):
    args = dict(num_rules=4, t_per=T_PER, tau_min=TAU_MIN, tau_max=TAU_MAX, creep=CREEP)
    args.update(kwargs)
    return jm.TimeBSRSpace(REX, **args)


SPACE = space()


N = 2000  # controllers per distribution test (one compilation per family and size)


@eqx.filter_jit
def _sample(space, keys):
    return jax.vmap(lambda k: space.sample(key=k))(keys)


@eqx.filter_jit
def _perturb(space, parents, keys):
    return jax.vmap(lambda p, k: space.perturb(p, key=k))(parents, keys)


def sample_many(space, n=N, seed=0):
    return _sample(space, jr.split(jr.key(seed), n))


def perturb_many(space, parents, seed):
    return _perturb(space, parents, jr.split(jr.key(seed), parents.taus.shape[0]))


def as_numpy(c):
    return (
        np.asarray(c.splits, dtype=float),
        np.asarray(c.targets, dtype=float),
        np.asarray(c.taus, dtype=float),
    )


# ------------------------------------------------------------------ sampling (Table 2)


def test_sampling_follows_table_2():
    """Splits sorted uniforms on [0, t_per]; targets uniform in each free joint's range; tau
    log-uniform in [tau_min, tau_max]."""
    n, r, f = 2 * N, SPACE.num_rules, REX.num_free
    c = sample_many(SPACE, n)
    splits, targets, taus = as_numpy(c)
    assert splits.shape == (n, r - 1)
    assert targets.shape == (n, r, f)
    assert taus.shape == (n, r)
    np.testing.assert_array_equal(np.asarray(c.t_per), T_PER)
    assert np.all(np.diff(splits, axis=1) >= 0)
    assert splits.min() >= 0 and splits.max() <= T_PER
    # Pooled, the splits are uniform; the k-th of R - 1 sorted uniforms is Beta(k+1, R-1-k).
    assert stats.kstest(splits.ravel() / T_PER, "uniform").pvalue > ALPHA
    for k in range(r - 1):
        beta = stats.beta(k + 1, r - 1 - k)
        assert stats.kstest(splits[:, k] / T_PER, beta.cdf).pvalue > ALPHA, k
    for j in range(f):
        u = (targets[:, :, j] - LO[j]) / (HI[j] - LO[j])
        assert targets[:, :, j].min() >= LO32[j] and targets[:, :, j].max() <= HI32[j], j
        assert stats.kstest(u.ravel(), "uniform").pvalue > ALPHA, j
    assert taus.min() >= TAU_MIN * (1 - SLACK) and taus.max() <= TAU_MAX * (1 + SLACK)
    log_u = np.log(taus / TAU_MIN) / LOG_SPAN
    assert stats.kstest(log_u.ravel(), "uniform").pvalue > ALPHA
    # Log-uniform, not uniform: the median is the geometric mean of the bounds.
    assert np.median(taus) == pytest.approx(math.sqrt(TAU_MIN * TAU_MAX), rel=0.05)


def test_one_rule_has_no_splits():
    c = jm.TimeBSRSpace(jm.figures.star_man(), num_rules=1).sample(key=jr.key(3))
    assert c.splits.shape == (0,) and c.targets.shape == (1, 4) and c.taus.shape == (1,)


# ------------------------------------------------------------------ the schedule (section 2.3)


def acting(c, t, plan=None):
    """The actuation held after a control tick at `t` (works on a batch-last stack too)."""
    state = c.update(t, c.init(None, plan), None, plan)
    return c.actuation(t, state, plan)


# Dyadic splits and period: phases of t and t + k t_per are computed exactly in float32.
SCHEDULE = jm.TimeBSR(
    splits=[0.25, 0.5, 0.875],
    targets=[[0.1, 0.2], [-0.3, 0.4], [0.5, -0.6], [0.7, 0.8]],
    taus=[0.05, 0.1, 0.2, 0.4],
    t_per=1.0,
)


def test_active_rule_owns_its_segment_of_every_period():
    """Rule r is active exactly on [splits[r-1], splits[r]) of each period."""
    cases = {0.0: 0, 0.2499: 0, 0.25: 1, 0.4999: 1, 0.5: 2, 0.8749: 2, 0.875: 3, 0.9999: 3}
    for period in range(4):
        for phase, rule in cases.items():
            t = jnp.asarray(period + phase)
            assert int(SCHEDULE.active(t)) == rule, (period, phase)
            target, tau = acting(SCHEDULE, t)
            np.testing.assert_array_equal(np.asarray(target), np.asarray(SCHEDULE.targets[rule]))
            assert float(tau) == float(SCHEDULE.taus[rule])


def test_active_and_actuation_agree_with_a_reference_on_random_times():
    rng = np.random.default_rng(0)
    c = jm.TimeBSR(
        np.sort(rng.uniform(0.0, 0.7, 4)),
        rng.uniform(-1, 1, (5, 3)),
        rng.uniform(0.02, 0.5, 5),
        0.7,
    )
    splits, targets, taus = as_numpy(c)
    ts = rng.uniform(0.0, 5 * 0.7, 3000).astype(np.float32)
    phase = np.mod(ts.astype(float), 0.7)
    # Away from the boundaries, where float32 rounding of the phase could tip the rule.
    away = np.min(np.abs(phase[:, None] - np.concatenate([splits, [0.0, 0.7]])), axis=1) > 1e-4
    ts, phase = ts[away], phase[away]
    expected = np.searchsorted(splits, phase, side="right")
    active = np.asarray(jax.vmap(c.active)(jnp.asarray(ts)))
    np.testing.assert_array_equal(active, expected)
    target, tau = jax.vmap(lambda t: acting(c, t))(jnp.asarray(ts))
    np.testing.assert_array_equal(np.asarray(target), targets[expected])
    np.testing.assert_array_equal(np.asarray(tau), taus[expected])
    # Periodic: one period later the same rule acts.
    later = np.asarray(jax.vmap(c.active)(jnp.asarray(ts + np.float32(0.7))))
    assert np.mean(later == active) > 0.99  # float32 phases within ~1e-7 of a split may tip


def test_empty_segments_are_never_active():
    c = jm.TimeBSR([0.0, 0.5, 0.5, 1.0], np.arange(5.0)[:, None], [0.1] * 5, t_per=1.0)
    rules = {int(c.active(jnp.asarray(t))) for t in np.linspace(0, 3, 301)}
    assert rules == {1, 3}


def test_a_script_at_least_as_long_as_the_motion_runs_once():
    """t_per >= duration: each rule acts on one stretch and the script never returns to an
    earlier rule; with t_per < duration it does."""
    duration = 2.0
    ts = jnp.linspace(0.0, duration, 2001)[:-1]
    once = jm.TimeBSR([0.3, 1.1, 1.9], np.zeros((4, 1)), [0.1] * 4, t_per=duration)
    rules = np.asarray(jax.vmap(once.active)(ts))
    assert np.all(np.diff(rules) >= 0) and set(rules.tolist()) == {0, 1, 2, 3}
    repeated = jm.TimeBSR([0.15, 0.55, 0.95], np.zeros((4, 1)), [0.1] * 4, t_per=duration / 2)
    rules = np.asarray(jax.vmap(repeated.active)(ts))
    assert np.sum(np.diff(rules) < 0) == 1  # one wrap, at t = t_per


def test_one_rule_is_always_active():
    c = jm.TimeBSR(np.zeros(0), [[0.3, -0.2]], [0.05], t_per=1.0)
    ts = jnp.linspace(0.0, 3.0, 31)
    np.testing.assert_array_equal(np.asarray(jax.vmap(c.active)(ts)), 0)
    target, tau = jax.vmap(lambda t: acting(c, t))(ts)
    np.testing.assert_allclose(np.asarray(target), np.broadcast_to([0.3, -0.2], (31, 2)))
    np.testing.assert_allclose(np.asarray(tau), 0.05)


def test_batch_last_actuation_equals_vmap():
    """`supports_batch_last`: one tick and actuation on controllers stacked along the last axis
    give what `vmap` gives."""
    batch = jax.tree_util.tree_map(lambda a: a[:8], sample_many(SPACE, seed=11))
    last = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), batch)
    for t in (0.0, 0.37, 1.3, 2.9):
        t = jnp.asarray(t)
        target, tau = acting(last, t)
        v_target, v_tau = jax.vmap(lambda c, t=t: acting(c, t))(batch)
        np.testing.assert_array_equal(np.moveaxis(np.asarray(target), -1, 0), v_target)
        np.testing.assert_array_equal(np.asarray(tau), v_tau)


# ------------------------------------------------------------------ mutation (section 2.1.3)


def rule_table(c, i):
    """Controller `i` of a batch as a list of rules `(start, targets, tau)` (rule 0 starts
    the period): the schedule itself, whatever the order the rules are stored in."""
    splits, targets, taus = (np.asarray(x)[i] for x in (c.splits, c.targets, c.taus))
    starts = np.concatenate([[0.0], splits])
    return [
        (float(starts[r]), tuple(targets[r].tolist()), float(taus[r])) for r in range(len(taus))
    ]


def changed_rule(parents, children, i):
    """The one rule of controller `i` that the mutation changed: (its index in the parent,
    the parent's rule, the child's rule). Fails if not exactly one rule changed."""
    old, new = rule_table(parents, i), rule_table(children, i)
    gone = [r for r, rule in enumerate(old) if rule not in new]
    came = [rule for rule in new if rule not in old]
    assert len(gone) == 1 and len(came) == 1, (i, old, new)
    return gone[0], old[gone[0]], came[0]


def assert_within_bounds(c, space):
    splits, targets, taus = as_numpy(c)
    assert np.all(np.diff(splits, axis=-1) >= 0)
    assert splits.min() >= 0 and splits.max() <= space.t_per
    assert np.all(targets >= LO32) and np.all(targets <= HI32)
    assert taus.min() >= space.tau_min * (1 - SLACK)
    assert taus.max() <= space.tau_max * (1 + SLACK)


def test_perturb_changes_one_rule_uniformly_chosen():
    """Exactly one rule changes: all its targets and its tau, and its start only if it is not
    rule 0; the rule is chosen uniformly (chi-square)."""
    parents = sample_many(SPACE, seed=1)
    children = perturb_many(SPACE, parents, seed=2)
    assert_within_bounds(children, SPACE)
    np.testing.assert_array_equal(np.asarray(children.t_per), T_PER)
    counts = np.zeros(SPACE.num_rules, dtype=int)
    moved = 0
    for i in range(N):
        index, (start, targets, tau), (new_start, new_targets, new_tau) = changed_rule(
            parents, children, i
        )
        counts[index] += 1
        assert np.all(np.asarray(new_targets) != np.asarray(targets)), i
        assert new_tau != tau, i
        if index == 0:
            assert new_start == 0.0  # rule 0 always starts the period
        moved += new_start != start
    assert stats.chisquare(counts).pvalue > ALPHA
    assert moved > 0.5 * N  # the start of rules 1..R-1 (3 in 4 mutations) moves
    again = perturb_many(SPACE, parents, seed=2)  # the same keys: the same children
    for x, y in zip(as_numpy(again), as_numpy(children), strict=True):
        np.testing.assert_array_equal(x, y)


def steps(parents, children):
    """Per mutation: the changed rule's index, its target steps in units of `creep` times the
    range, its tau step in units of `creep` times the log range, its start step in units of
    `creep` times the period, and the new rule (start, targets, tau)."""
    out = []
    for i in range(parents.taus.shape[0]):
        index, (start, targets, tau), (new_start, new_targets, new_tau) = changed_rule(
            parents, children, i
        )
        out.append(
            (
                index,
                np.subtract(new_targets, targets) / (CREEP * (HI - LO)),
                math.log(new_tau / tau) / (CREEP * LOG_SPAN),
                (new_start - start) / (CREEP * T_PER),
                (new_start, new_targets, new_tau),
            )
        )
    return out


def beyond_creep(step) -> bool:
    """Whether some parameter moved further than a creep can (so: a reinitialisation)."""
    _, targets, tau, start, _ = step
    return bool(max(np.abs(targets).max(), abs(tau), abs(start)) > 1 + SLACK)


def test_fraction_of_reinitialisations():
    """Binomial test of the reinitialisations among N mutations with the default probability
    1/3. A mutation is recognised as a reinitialisation when some parameter moved further
    than a creep can: a reinitialised rule of Rex (10 targets and tau) stays within creep
    reach in every parameter with probability about 0.19^11 < 1e-7."""
    assert SPACE.reinit_probability == pytest.approx(1 / 3)
    parents = sample_many(SPACE, seed=3)
    reinits = sum(beyond_creep(x) for x in steps(parents, perturb_many(SPACE, parents, seed=4)))
    assert stats.binomtest(reinits, N, SPACE.reinit_probability).pvalue > ALPHA


def test_creep_steps_are_at_most_creep_times_the_range():
    """reinit_probability = 0: every parameter of the changed rule moves by at most `creep`
    of its range (tau on a log scale, the start by `creep` of the period), in both directions,
    and the steps do reach close to that bound."""
    s = space(reinit_probability=0.0)
    parents = sample_many(SPACE, seed=5)
    out = steps(parents, perturb_many(s, parents, seed=6))
    assert not any(beyond_creep(x) for x in out)
    target_steps = np.array([x[1] for x in out])
    tau_steps = np.array([x[2] for x in out])
    start_steps = np.array([x[3] for x in out if x[0] > 0])
    for step in (target_steps, tau_steps, start_steps):
        assert np.abs(step).max() > 0.95
        assert step.min() < 0 < step.max()


def test_reinitialised_rules_are_drawn_afresh():
    """reinit_probability = 1: the new rule's targets, tau and start follow the sampling
    distributions (KS), whatever the old rule was."""
    s = space(reinit_probability=1.0)
    parents = sample_many(SPACE, seed=8)
    out = steps(parents, perturb_many(s, parents, seed=9))
    assert all(beyond_creep(x) for x in out)
    new = [x[4] for x in out]
    targets = (np.array([t for _, t, _ in new]) - LO) / (HI - LO)
    log_taus = np.log(np.array([tau for _, _, tau in new]) / TAU_MIN) / LOG_SPAN
    starts = np.array([x[4][0] for x in out if x[0] > 0]) / T_PER
    assert stats.kstest(targets.ravel(), "uniform").pvalue > ALPHA
    assert stats.kstest(log_taus, "uniform").pvalue > ALPHA
    assert stats.kstest(starts, "uniform").pvalue > ALPHA


def test_repeated_perturbation_stays_within_bounds():
    """Parents pinned to the bounds, then 20 mutations each: targets, taus and splits never
    leave their ranges and splits stay sorted."""
    parents = sample_many(SPACE, seed=10)
    rng = np.random.default_rng(0)
    edge = rng.integers(0, 3, parents.targets.shape)  # 0: keep, 1: lo, 2: hi
    targets = np.where(edge == 1, LO, np.where(edge == 2, HI, np.asarray(parents.targets)))
    taus = np.where(rng.random(parents.taus.shape) < 0.5, TAU_MIN, TAU_MAX)
    splits = np.sort(rng.choice([0.0, 0.01, T_PER - 0.01, T_PER], parents.splits.shape), axis=1)
    c = eqx.tree_at(
        lambda c: (c.splits, c.targets, c.taus),
        parents,
        tuple(jnp.asarray(x, dtype=float) for x in (splits, targets, taus)),
    )
    for seed in range(20):
        c = perturb_many(SPACE, c, seed=100 + seed)
        assert_within_bounds(c, SPACE)


# ------------------------------------------------------------------ validation

GOOD = dict(splits=[0.3, 0.6], targets=[[0.1, 0.2]] * 3, taus=[0.1, 0.2, 0.3], t_per=1.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(taus=[0.1, 0.2]), r"taus \(R,\) and targets \(R, num_free\).*\(2,\) and \(3, 2\)"),
        (dict(targets=[0.1, 0.2, 0.3]), r"taus \(R,\) and targets \(R, num_free\)"),
        (dict(taus=[]), r"R >= 1"),
        (dict(splits=[0.3]), r"R - 1 = 2 splits; got shape \(1,\)"),
        (dict(splits=[0.3, 1.5]), r"split 1 is 1.5; allowed: 0 <= split <= t_per = 1"),
        (dict(splits=[-0.1, 0.5]), r"split 0 is -0.1; allowed: 0 <= split"),
        (dict(splits=[0.3, float("nan")]), r"split 1 is nan"),
        (dict(splits=[0.6, 0.3]), r"splits = \[0.6, 0.3\]; allowed: ascending"),
        (dict(taus=[0.1, 0.0, 0.3]), r"rule 1 has tau 0; allowed: a number > 0"),
        (dict(taus=[0.1, 0.2, -0.3]), r"rule 2 has tau -0.3"),
        (dict(targets=[[0.1, 0.2], [np.inf, 0.2], [0.1, 0.2]]), r"targets must be finite"),
        (dict(targets=[[0.1, 0.2], [0.1, np.nan], [0.1, 0.2]]), r"targets must be finite"),
        (dict(t_per=0.0), r"t_per = 0.0; allowed: a number > 0"),
        (dict(t_per=-2.0), r"t_per = -2.0; allowed: a number > 0"),
        (dict(t_per=[1.0, 2.0]), r"t_per = \[1.0, 2.0\]; allowed: a number > 0"),
    ],
)
def test_bad_time_bsr_raises(kwargs, message):
    args = dict(GOOD)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        jm.TimeBSR(**args)


def test_good_time_bsr_is_accepted():
    c = jm.TimeBSR(**GOOD)
    assert c.num_rules == 3
    # Splits on the ends of the period and equal splits are allowed (empty segments).
    jm.TimeBSR([0.0, 1.0], GOOD["targets"], GOOD["taus"], 1.0)
    jm.TimeBSR([0.5, 0.5], GOOD["targets"], GOOD["taus"], 1.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(num_rules=0), r"num_rules = 0; allowed: an integer >= 1"),
        (dict(num_rules=-2), r"num_rules = -2; allowed: an integer >= 1"),
        (dict(num_rules=2.0), r"num_rules = 2.0; allowed: an integer >= 1"),
        (dict(tau_min=0.6, tau_max=0.5), r"tau_min = 0.6 > tau_max = 0.5"),
        (dict(t_per=0.0), r"t_per = 0.0; allowed: a number > 0"),
        (dict(t_per=-1.0), r"t_per = -1.0; allowed: a number > 0"),
        (dict(tau_min=0.0), r"tau_min = 0.0; allowed: a number > 0"),
        (dict(creep=0.0), r"creep = 0.0; allowed: 0 < creep <= 1"),
        (dict(reinit_probability=1.5), r"reinit_probability = 1.5; allowed: 0..1"),
    ],
)
def test_bad_space_raises(kwargs, message):
    with pytest.raises(ValueError, match=message):
        jm.TimeBSRSpace(jm.figures.star_man(), **kwargs)


def test_prepare_checks_the_body():
    c = jm.TimeBSR(**GOOD)  # 2 target angles per rule
    with pytest.raises(TypeError, match=r"TimeBSR controls articulated figures; got a Lattice"):
        c.prepare(jm.lattices.cube())
    with pytest.raises(
        ValueError, match=r"targets for 2 joint angles but figure 'star_man' has 4 free angles"
    ):
        c.prepare(jm.figures.star_man())
    assert jm.TimeBSRSpace(REX).sample(key=jr.key(0)).prepare(REX) is None


# ------------------------------------------------------------------ gradients' view


def test_trainable_marks_splits_targets_and_taus():
    c = SPACE.sample(key=jr.key(0))
    spec = SPACE.trainable(c)
    assert spec.splits is True and spec.targets is True and spec.taus is True
    assert spec.t_per is False
    params, static = eqx.partition(c, spec)
    assert params.t_per is None and static.t_per is not None


def test_project_clips_into_the_bounds_and_sorts_the_splits():
    c = SPACE.sample(key=jr.key(0))
    for x, y in zip(as_numpy(SPACE.project(c)), as_numpy(c), strict=True):
        np.testing.assert_array_equal(x, y)  # in bounds: unchanged
    targets = np.asarray(c.targets).copy()
    targets[0] = HI + 1.0
    targets[1] = LO - 1.0
    bad = eqx.tree_at(
        lambda c: (c.splits, c.targets, c.taus),
        c,
        (
            jnp.asarray([2.5, -0.3, 0.7]),
            jnp.asarray(targets),
            jnp.asarray([1e-4, 0.1, 5.0, 0.2]),
        ),
    )
    splits, targets, taus = as_numpy(SPACE.project(bad))
    np.testing.assert_allclose(splits, [0.0, 0.7, T_PER], rtol=1e-6)
    np.testing.assert_allclose(targets[0], HI, rtol=1e-6)
    np.testing.assert_allclose(targets[1], LO, rtol=1e-6)
    np.testing.assert_array_equal(targets[2:], np.asarray(c.targets)[2:])
    np.testing.assert_allclose(taus, [TAU_MIN, 0.1, TAU_MAX, 0.2], rtol=1e-6)
    assert float(SPACE.project(bad).t_per) == T_PER
    assert SPACE.family == "time_bsr"


# ------------------------------------------------------------------ a figure driven by it

# After 1 s = 20 tau the critically damped law has left (1 + 20) e^-20 ~ 4e-8 of the step.
MOTION_TAU = 0.05
MOTION_TARGETS = np.array([0.3, -0.5, 0.7, -0.2])  # within star_man's -45..45 degrees
FINAL_ATOL = 1e-3  # rad
# The law's solution at the saved times, against semi-implicit Euler at dt = 1 ms
# (dt / tau = 0.02): a first-order error, measured 0.6% of the largest step (4.4e-3 rad).
PATH_ATOL = 0.015 * np.abs(MOTION_TARGETS).max()


def star_man_angles(points, rest_points):
    """Free angles of Mr. Star-Man from his nodes: rod k (node 0 to node k + 1) against the
    head, rod 0, in the x-z plane, relative to the rest pose. A positive angle turns a rod
    clockwise seen from +y (its polar angle atan2(z, x) decreases)."""

    def polar(p):
        v = p[..., 1:, :] - p[..., :1, :]
        phi = np.arctan2(v[..., 2], v[..., 0])
        return phi[..., 1:] - phi[..., :1]

    turn = -(polar(points) - polar(rest_points))
    return (turn + np.pi) % (2 * np.pi) - np.pi


def test_a_figure_follows_its_active_rule():
    """Free flight (no gravity, no floor): Mr. Star-Man's joint angles follow the critically
    damped law `th(t) = th0 (1 - (1 + t / tau) e^(-t / tau))` to the rule's targets."""
    fig = jm.figures.star_man()
    np.testing.assert_allclose(
        star_man_angles(fig.pose(MOTION_TARGETS), fig.pose()), MOTION_TARGETS
    )
    ctrl = jm.TimeBSR(np.zeros(0), MOTION_TARGETS[None], [MOTION_TAU], t_per=1.0)
    world = jm.World(gravity=0.0, floor=False)
    traj = jax.jit(lambda c: jm.simulate(fig, c, world, 1.0))(ctrl)
    assert bool(traj.finite)
    points = np.asarray(traj.points, dtype=float)
    angles = star_man_angles(points, fig.pose())
    np.testing.assert_allclose(angles[-1], MOTION_TARGETS, atol=FINAL_ATOL)
    s = np.asarray(traj.ts, dtype=float)[:, None] / MOTION_TAU
    law = MOTION_TARGETS * (1 - (1 + s) * np.exp(-s))
    np.testing.assert_allclose(angles, law, atol=PATH_ATOL)
    # No gravity or contact: the centre of mass stays where it was.
    com = np.asarray(traj.com, dtype=float)
    np.testing.assert_allclose(com, np.broadcast_to(com[0], com.shape), atol=1e-4)


def mirrored_rex_controller():
    partner, sign = REX.mirror
    targets = np.random.default_rng(3).uniform(LO, HI, (3, REX.num_free))
    return jm.TimeBSR([0.1, 0.3], targets, [0.05, 0.1, 0.2], 1.0, mirror=REX.mirror), partner, sign


def test_a_mirrored_controller_repeats_its_half_period_mirrored():
    c, partner, sign = mirrored_rex_controller()
    targets = np.asarray(c.targets)
    # Dyadic times: the phases are exact in float32.
    for phase, rule in {0.0: 0, 0.0625: 0, 0.125: 1, 0.375: 2, 0.4375: 2}.items():
        for period in range(3):
            first, second = period + phase, period + 0.5 + phase
            assert int(c.active(jnp.asarray(first))) == rule
            assert int(c.active(jnp.asarray(second))) == rule + 3
            target, tau = acting(c, jnp.asarray(first))
            np.testing.assert_array_equal(np.asarray(target), targets[rule].astype(np.float32))
            target, tau_m = acting(c, jnp.asarray(second))
            expected = (np.asarray(sign) * targets[rule][list(partner)]).astype(np.float32)
            np.testing.assert_array_equal(np.asarray(target), expected)
            assert float(tau_m) == float(tau) == float(c.taus[rule])


def test_a_mirrored_space_samples_and_mutates_within_the_half_period():
    space = jm.TimeBSRSpace(
        REX, num_rules=4, t_per=T_PER, tau_min=TAU_MIN, tau_max=TAU_MAX, mirror=True
    )
    c = space.sample(key=jr.key(0))
    assert c.mirror == REX.mirror
    for k in range(200):
        c = space.perturb(c, key=jr.key(k))
        splits = np.asarray(c.splits)
        assert np.all((splits >= 0) & (splits <= T_PER / 2)) and np.all(np.diff(splits) >= 0)
    assert c.mirror == REX.mirror
    assert np.asarray(space.sample(key=jr.key(1)).splits).max() <= T_PER / 2
    with pytest.raises(ValueError, match=r"figure 'star_man' is planar.*allowed: mirror = False"):
        jm.TimeBSRSpace(jm.figures.star_man(), mirror=True)


def test_a_mirrored_controller_round_trips_and_is_checked():
    from jaxmotion.experiment import controller_from_dict, controller_to_dict

    c, _, _ = mirrored_rex_controller()
    back = controller_from_dict(controller_to_dict(c, "time_bsr"))
    assert back.mirror == c.mirror
    assert eqx.tree_equal(back, c)
    with pytest.raises(ValueError, match=r"split 1 is 0.6; allowed: 0 <= split <= t_per / 2"):
        jm.TimeBSR([0.1, 0.6], c.targets, c.taus, 1.0, mirror=REX.mirror)
    with pytest.raises(ValueError, match=r"a permutation of the 10 free angles"):
        jm.TimeBSR([0.1, 0.3], c.targets, c.taus, 1.0, mirror=((0,) * 10, (1.0,) * 10))
    with pytest.raises(ValueError, match=r"is not figure 'bob'"):
        jm.TimeBSR(np.zeros(0), np.zeros((1, 10)), [0.1], 1.0, mirror=REX.mirror).prepare(
            jm.figures.bob()
        )
