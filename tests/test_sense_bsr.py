"""The sense-based BSR controller and its search space (second paper, sections 2.1.2, 2.1.3
and 4.2, Figure 2, Table 2): the score, the rule choice with hysteresis, the low-pass filter,
sampling, mutation and the relevance heuristic."""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from scipy import stats

import jaxmotion as jm
from jaxmotion._control.sense_bsr import LAMBDA_MIN

ALPHA = 1e-3  # significance level of every distribution test (fixed keys)
EXACT = 1e-5  # float32 rounding of scores of order 1-10
STAR = jm.figures.star_man()
WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)


def two_rules(**kw):
    """Two rules over two senses: rule 0 a big square around (0.5, 0.5), rule 1 a small one
    around (0.8, 0.2)."""
    return jm.SenseBSR(
        centres=[[0.5, 0.5], [0.8, 0.2]],
        sides=[[2.0, 2.0], [0.4, 0.4]],
        targets=[[0.1], [0.2]],
        taus=[0.1, 0.2],
        **kw,
    )


def plan_of(c):
    return c.prepare_rules()


def hand_score(centre, side, s):
    lam = 2.0 / np.asarray(side)
    w = np.sum(np.log(lam / LAMBDA_MIN))
    return w * (1 - np.max((lam * (np.asarray(s) - centre)) ** 2))


def test_score_formula_against_hand_computed_cases():
    c = two_rules()
    for s in ([0.5, 0.5], [0.8, 0.2], [0.75, 0.3], [0.0, 1.0], [1.4, -0.3]):
        got = np.asarray(c.scores(jnp.asarray(s), plan_of(c)))
        want = [hand_score(c.centres[r], c.sides[r], s) for r in range(2)]
        np.testing.assert_allclose(got, want, rtol=EXACT)
    # Worked by hand: rule 1 (lambda 5, W = 2 log 10) at (0.75, 0.3): the worst sense is the
    # second, 5 * 0.1 = 0.5, so the score is 2 log 10 (1 - 0.25).
    score = float(c.scores(jnp.asarray([0.75, 0.3]), plan_of(c))[1])
    assert score == pytest.approx(2 * math.log(10) * 0.75, rel=EXACT)
    # Positive exactly inside the rectangle: zero on its boundary.
    edge = float(c.scores(jnp.asarray([1.0, 0.2]), plan_of(c))[1])
    assert edge == pytest.approx(0.0, abs=EXACT)
    # The biggest rectangle (sides 4: lambda = lambda_min) weighs nothing.
    widest = jm.SenseBSR([[0.5]], [[4.0]], [[0.0]], [0.1])
    assert float(widest.scores(jnp.asarray([0.5]), plan_of(widest))[0]) == 0.0


def tick(c, t, state, s):
    return c.update(jnp.asarray(t, dtype=float), state, jnp.asarray(s, dtype=float), plan_of(c))


def test_highest_positive_score_wins_and_none_positive_keeps_the_previous_rule():
    c = two_rules()
    state = c.init(jnp.asarray([0.5, 0.5]), plan_of(c))
    assert int(state.discrete.active) == 0
    # Rule 0 over the first period: the first tick keeps it (Figure 2 acts, then senses),
    # even where rule 1 scores higher.
    state = tick(c, 0.0, state, [0.8, 0.2])
    assert int(state.discrete.active) == 0
    # Inside both: the smaller rectangle scores higher.
    state = tick(c, 0.01, state, [0.8, 0.2])
    assert int(state.discrete.active) == 1
    # Outside both (rule 0 covers [-0.5, 1.5]^2): nothing scores positive, rule 1 stays.
    state = tick(c, 0.02, state, [1.6, 0.2])
    assert int(state.discrete.active) == 1
    # Inside rule 0 only: it takes over, and keeps on outside both again.
    state = tick(c, 0.03, state, [0.2, 0.9])
    assert int(state.discrete.active) == 0
    state = tick(c, 0.04, state, [-0.6, 2.0])
    assert int(state.discrete.active) == 0
    # Ties go to the lower index.
    twins = jm.SenseBSR([[0.5], [0.5]], [[1.0], [1.0]], [[0.0], [1.0]], [0.1, 0.1])
    s = tick(twins, 0.0, twins.init(jnp.asarray([0.5]), plan_of(twins)), [0.5])
    s = tick(twins, 0.01, eqx.tree_at(lambda x: x.discrete.active, s, jnp.asarray(1)), [0.5])
    assert int(s.discrete.active) == 0
    # The actuation is the active rule's response.
    target, tau = c.actuation(0.0, tick(c, 0.05, state, [0.8, 0.2]), plan_of(c))
    assert (float(target[0]), float(tau)) == pytest.approx((0.2, 0.2))


def test_the_low_pass_filter_follows_its_closed_form_step_response():
    """A first-order filter of time constant T sampled at the ticks: after a step of the
    senses from a to b at t0, `f(t) = b + (a - b) exp(-(t - t0) / T)`, at any tick spacing."""
    T = 0.05
    c = jm.SenseBSR([[0.5, 0.5]], [[4.0, 4.0]], [[0.0]], [0.1], filter_time=T)
    a, b = np.array([0.2, 0.9]), np.array([0.7, 0.1])
    state = c.init(jnp.asarray(a), plan_of(c))
    ticks = np.concatenate([np.arange(1, 40) * 4e-3, 0.156 + np.arange(1, 30) * 7e-3])
    for t in ticks:
        state = tick(c, t, state, b)
        want = b + (a - b) * np.exp(-t / T)
        np.testing.assert_allclose(np.asarray(state.discrete.filtered), want, atol=EXACT)
    # What the rules scored is what the controller perceives (recorded by searches).
    t = jnp.asarray(ticks[-1])
    np.testing.assert_array_equal(
        np.asarray(c.perceive(t, state, jnp.asarray(b), None)),
        np.asarray(state.discrete.filtered),
    )
    # Off: the senses themselves.
    raw = two_rules()
    s = tick(raw, 0.01, raw.init(jnp.asarray(a), plan_of(raw)), b)
    assert not bool(s.discrete.first)
    np.testing.assert_array_equal(np.asarray(s.discrete.filtered), b.astype(np.float32))


def test_a_batch_last_stack_ticks_and_acts_as_each_controller_alone():
    space = jm.SenseBSRSpace(STAR, num_rules=6, filter_time=0.03)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(1), 9))
    # Rectangles centred on the senses below, so that rules do become active.
    senses = jr.uniform(jr.key(2), (5, 9, STAR.num_senses))
    controllers = eqx.tree_at(
        lambda c: c.centres, controllers, controllers.centres.at[:, 2].set(senses[1])
    )
    seen = ticks_of_a_batch_last_stack(controllers, STAR, senses)
    assert len(seen) > 1  # rules did switch


def ticks_of_a_batch_last_stack(controllers, figure, senses):
    """Tick a batch of controllers (leading batch axis) through `senses` `(ticks, batch,
    num_senses)` both vmapped and as one batch-last stack, asserting that the two choose,
    filter and act alike to the bit; returns the rules chosen."""
    plans = jax.vmap(lambda c: c.prepare(figure))(controllers)
    last = lambda tree: jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), tree)
    one = jax.vmap(lambda c, p, s: c.init(s, p))(controllers, plans, senses[0])
    stack = last(controllers).init(senses[0].T, last(plans))
    seen = set()
    for k in range(1, senses.shape[0]):
        t = jnp.asarray(k * 4e-3)
        one = jax.vmap(lambda c, st, s, p, t=t: c.update(t, st, s, p))(
            controllers, one, senses[k], plans
        )
        stack = last(controllers).update(t, stack, senses[k].T, last(plans))
        np.testing.assert_array_equal(np.asarray(last(one).discrete.active), stack.discrete.active)
        np.testing.assert_array_equal(
            np.asarray(last(one).discrete.filtered), stack.discrete.filtered
        )
        act_one = jax.vmap(lambda c, st, p, t=t: c.actuation(t, st, p))(controllers, one, plans)
        act_stack = last(controllers).actuation(t, stack, last(plans))
        for a, b in zip(act_one, act_stack, strict=True):
            np.testing.assert_array_equal(np.moveaxis(np.asarray(b), -1, 0), np.asarray(a))
        seen |= set(np.asarray(stack.discrete.active).tolist())
    return seen


def test_parameter_count_is_the_papers_for_2d_figures():
    c = jm.SenseBSRSpace(STAR).sample(key=jr.key(0))
    n = STAR.num_rods
    assert c.num_rules == 10
    assert c.num_parameters == (5 * n + 4) * 10


# ------------------------------------------------------------------ sampling (Table 2)


def test_sampling_follows_table_2():
    space = jm.SenseBSRSpace(STAR, num_rules=4, tau_min=0.008, tau_max=1.25)
    many = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(3), 1500))
    centres = np.asarray(many.centres).ravel()
    sides = np.asarray(many.sides).ravel()
    taus = np.asarray(many.taus).ravel()
    assert stats.kstest(centres, stats.uniform(-0.5, 2.0).cdf).pvalue > ALPHA
    log_sides = (np.log(sides) - np.log(0.4)) / np.log(10.0)
    assert stats.kstest(log_sides, "uniform").pvalue > ALPHA
    log_taus = (np.log(taus) - np.log(0.008)) / np.log(1.25 / 0.008)
    assert stats.kstest(log_taus, "uniform").pvalue > ALPHA
    lo, hi = STAR.ranges.T
    targets = (np.asarray(many.targets) - lo) / (hi - lo)
    assert stats.kstest(targets.ravel(), "uniform").pvalue > ALPHA


# ------------------------------------------------------------------ mutation (sections 2.1.3, 4.2)


def changed_rules(parent, child):
    fields = ("centres", "sides", "targets", "taus")
    diff = [
        np.any(
            np.asarray(getattr(parent, f)).reshape(parent.taus.shape[0], -1)
            != np.asarray(getattr(child, f)).reshape(parent.taus.shape[0], -1),
            axis=1,
        )
        for f in fields
    ]
    return np.flatnonzero(np.any(diff, axis=0))


def test_a_mutation_changes_one_rule_within_the_bounds():
    space = jm.SenseBSRSpace(STAR, num_rules=5, creep=0.1, reinit_probability=0.0)
    parent = space.sample(key=jr.key(4))
    children = jax.vmap(lambda k: space.perturb(parent, key=k))(jr.split(jr.key(5), 200))
    counts = np.zeros(5)
    for i in range(200):
        child = jax.tree_util.tree_map(lambda a, i=i: a[i], children)
        rules = changed_rules(parent, child)
        assert len(rules) == 1
        counts[rules[0]] += 1
        r = rules[0]
        # Creep: at most 10% of each range (sides and tau on a log scale), clipped.
        step = np.abs(np.asarray(child.centres[r]) - np.asarray(parent.centres[r]))
        assert step.max() <= 0.1 * 2.0 * (1 + 1e-5)
        ratio = np.abs(np.log(np.asarray(child.sides[r]) / np.asarray(parent.sides[r])))
        assert ratio.max() <= 0.1 * np.log(10.0) * (1 + 1e-4)
    assert stats.chisquare(counts).pvalue > ALPHA  # the rule is chosen uniformly
    c = np.asarray(children.centres)
    s = np.asarray(children.sides)
    assert c.min() >= -0.5 and c.max() <= 1.5 and s.min() >= 0.4 * (1 - 1e-6)
    assert s.max() <= 4.0 * (1 + 1e-6)


def parent_motions(count=12, seed=6):
    """Random sense-based Star-Man controllers and the senses they perceived (2 s)."""
    space = jm.SenseBSRSpace(STAR, tau_min=0.05, tau_max=0.5)
    task = jm.Task(STAR, WORLD, space, jm.Objective({"forward": 1.0}), duration=2.0, dt=4e-3)
    parents = task.sample(count, key=jr.key(seed))
    _, motion = task.evaluate_sensed(parents)
    return space, parents, motion


@pytest.fixture(scope="module")
def motions():
    return parent_motions()


def with_relevance(space, relevance):
    return jm.SenseBSRSpace(
        STAR, space.num_rules, space.tau_min, space.tau_max, relevance=relevance
    )


def activation_rate(space, parents, motion, relevance, per_parent=10, seed=7):
    """The share of reinitialised rules that become active at least once along the
    parent's recorded motion."""
    space = with_relevance(space, relevance)
    hits = total = 0
    for i in range(parents.taus.shape[0]):
        parent = jax.tree_util.tree_map(lambda a, i=i: a[i], parents)
        keys = jr.split(jr.fold_in(jr.key(seed), i), per_parent)
        children = jax.vmap(
            lambda k, p=parent, m=motion[i]: space.reinitialise(p, key=k, motion=m)
        )(keys)
        rules = jax.vmap(lambda c, m=motion[i]: c.active_rules(m))(children)
        for k in range(per_parent):
            child = jax.tree_util.tree_map(lambda a, k=k: a[k], children)
            (new,) = changed_rules(parent, child)
            hits += bool(np.any(np.asarray(rules[k]) == new))
            total += 1
    return hits / total


def test_the_relevance_heuristic_makes_reinitialised_rules_active(motions):
    """Section 2.1.3: a rule reinitialised with a corner on the parent's sense trajectory
    becomes active on that motion (>= 0.9 of them; measured over 400: 0.98), where a rule
    drawn from Table 2 seldom does (measured: 0.12); containing a point of it (section
    4.2, 3D) works as well (1.0)."""
    space, parents, motion = motions
    corner = activation_rate(space, parents, motion, "corner")
    contain = activation_rate(space, parents, motion, "contain")
    uniform = activation_rate(space, parents, motion, "none")
    assert corner >= 0.9, corner
    assert contain >= 0.9, contain
    assert uniform <= 0.25, uniform


def test_a_corner_lies_on_the_motion_and_a_contained_point_inside(motions):
    space, parents, motion = motions
    parent = jax.tree_util.tree_map(lambda a: a[0], parents)
    for relevance in ("corner", "contain"):
        s = with_relevance(space, relevance)
        children = jax.vmap(lambda k, s=s: s.reinitialise(parent, key=k, motion=motion[0]))(
            jr.split(jr.key(8), 50)
        )
        for k in range(50):
            child = jax.tree_util.tree_map(lambda a, k=k: a[k], children)
            (r,) = changed_rules(parent, child)
            centre, half = np.asarray(child.centres[r]), np.asarray(child.sides[r]) / 2
            offset = np.abs(np.asarray(motion[0]) - centre) / half  # (samples, senses)
            inside = np.max(offset, axis=1)
            if relevance == "contain":
                assert inside.min() <= 0.95 + 1e-4  # a sample of the motion is inside
            else:
                # A corner within 5% of the half sides of a sample in every sense.
                corner = np.min(np.max(np.abs(offset - 1.0), axis=1))
                assert corner <= 0.05 + 1e-4


# ------------------------------------------------------------------ smoothing, validation


def test_smoothing_width_zero_is_the_hard_switch_and_small_widths_approach_it():
    c = two_rules()
    assert c.smoothed(0.0) == c
    senses = [[0.5, 0.5], [0.8, 0.2], [1.6, 0.2], [0.2, 0.9], [0.8, 0.25]]
    hard = c.init(jnp.asarray(senses[0]), plan_of(c))
    soft = c.smoothed(1e-3)
    soft_state = soft.init(jnp.asarray(senses[0]), plan_of(soft))
    for k, s in enumerate(senses):
        hard = tick(c, 0.01 * k, hard, s)
        soft_state = tick(soft, 0.01 * k, soft_state, s)
        weights = np.asarray(soft_state.discrete.active)
        assert weights[int(hard.discrete.active)] == pytest.approx(1.0, abs=1e-4)
        a_hard = c.actuation(0.0, hard, plan_of(c))
        a_soft = soft.actuation(0.0, soft_state, plan_of(soft))
        np.testing.assert_allclose(np.asarray(a_soft[0]), np.asarray(a_hard[0]), atol=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            dict(sides=[[2.0, 0.0], [0.4, 0.4]]),
            r"rule 0 has side 0 on sense 1; allowed: a number > 0",
        ),
        (dict(taus=[0.1, -1.0]), r"rule 1 has tau -1; allowed"),
        (dict(targets=[[0.1]]), r"targets of shape \(R, num_free\), R = 2"),
        (dict(filter_time=-0.1), r"SenseBSR.filter_time = -0.1; allowed: a number >= 0"),
    ],
)
def test_bad_sense_bsr_raises(kwargs, message):
    args = dict(
        centres=[[0.5, 0.5], [0.8, 0.2]],
        sides=[[2.0, 2.0], [0.4, 0.4]],
        targets=[[0.1], [0.2]],
        taus=[0.1, 0.2],
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        jm.SenseBSR(**args)


def test_prepare_and_the_space_check_the_body():
    c = jm.SenseBSRSpace(STAR).sample(key=jr.key(0))
    with pytest.raises(TypeError, match=r"SenseBSR controls articulated figures"):
        c.prepare(jm.lattices.cube())
    few = jm.SenseBSR(np.zeros((2, 5)), np.ones((2, 5)), np.zeros((2, 4)), [0.1, 0.1])
    with pytest.raises(ValueError, match=r"rectangles over 5 senses but figure 'star_man' has 12"):
        few.prepare(STAR)
    with pytest.raises(ValueError, match=r"targets for 4 joint angles but figure 'cujo' has 12"):
        c.prepare(jm.figures.cujo())
    with pytest.raises(ValueError, match=r"relevance = 'near'; allowed"):
        jm.SenseBSRSpace(STAR, relevance="near")
    assert jm.SenseBSRSpace(STAR).relevance == "corner"
    assert jm.SenseBSRSpace(jm.figures.cujo()).relevance == "contain"


def test_trainable_and_project():
    space = jm.SenseBSRSpace(STAR, num_rules=3, tau_min=0.05, tau_max=0.5)
    c = space.sample(key=jr.key(0))
    spec = space.trainable(c)
    assert spec.centres and spec.sides and spec.targets and spec.taus
    wild = eqx.tree_at(
        lambda x: (x.centres, x.sides, x.taus),
        c,
        (c.centres + 5.0, c.sides * 100.0, c.taus * 0.01),
    )
    p = space.project(wild)
    assert float(p.centres.max()) <= 1.5 and float(p.sides.max()) <= 4.0
    assert float(p.taus.min()) >= 0.05


# ------------------------------------------------------------------ mirror twins

CUJO = jm.figures.cujo()  # exactly left-right symmetric (its mass too)


def mirror_state(fig, rng):
    """A random state of `fig` (moving, turned, legs in the floor so contacts push) and its
    mirror image across the world's x-z plane."""
    partner, sign = fig.mirror
    lo, hi = fig.ranges[:, 0], fig.ranges[:, 1]
    angles = rng.uniform(lo, hi)
    rates = rng.normal(0.0, 2.0, fig.num_free)
    q = rng.normal(0.0, 1.0, 4) * np.array([1.0, 0.2, 0.2, 0.2]) + np.array([3.0, 0, 0, 0])
    q = q / np.linalg.norm(q)
    com = np.array([0.3, 0.1, 0.37])
    velocity, spin = rng.normal(0.0, 1.0, 3), rng.normal(0.0, 2.0, 3)
    flip = np.array([1.0, -1.0, 1.0])
    state = fig.state(
        com=com,
        velocity=velocity,
        orientation=q,
        angular_velocity=spin,
        angles=angles,
        rates=rates,
    )
    # A reflection M = diag(1, -1, 1): positions and velocities M x, the root's rotation
    # M R M (the quaternion (w, -x, y, -z)), an angular velocity (axial) -M w.
    mirrored = fig.state(
        com=flip * com,
        velocity=flip * velocity,
        orientation=q * np.array([1.0, -1.0, 1.0, -1.0]),
        angular_velocity=-flip * spin,
        angles=np.asarray(sign) * angles[list(partner)],
        rates=np.asarray(sign) * rates[list(partner)],
    )
    return state, mirrored


# Senses of a state and of its mirror image, float32 arithmetic on values in [0, 1].
MIRROR_SENSE_ATOL = 1e-5


def test_the_sense_map_reads_the_senses_of_the_mirror_image():
    """`Figure.sense_mirror` applied to the senses of a state gives the senses of its mirror
    image, sense by sense (velocities, spin, up vector, contacts, impulses, angles)."""
    dynamics, world = CUJO.dynamics(), jm.World(gravity=9.81, friction=0.8)
    source, flip = CUJO.sense_mirror
    assert sorted(source) == list(range(CUJO.num_senses))
    twin = jm.SenseBSR(
        np.zeros((1, CUJO.num_senses)),
        np.ones((1, CUJO.num_senses)),
        np.zeros((1, CUJO.num_free)),
        [0.1],
        mirror=CUJO.sense_mirror,
    )
    rng = np.random.default_rng(0)
    for _ in range(4):
        state, mirrored = mirror_state(CUJO, rng)
        s = np.asarray(dynamics.senses(state, world, 4e-3))
        m = np.asarray(dynamics.senses(mirrored, world, 4e-3))
        assert np.ptp(s[2:7]) > 0.05 and s[10 : 10 + CUJO.num_nodes].max() > 0  # moving, pushed
        np.testing.assert_allclose(
            np.asarray(twin.mirrored_senses(jnp.asarray(s))), m, atol=MIRROR_SENSE_ATOL
        )
        np.testing.assert_allclose(
            np.where(flip, 1 - s[list(source)], s[list(source)]), m, atol=MIRROR_SENSE_ATOL
        )


def test_bob_rex_and_cujo_have_sense_maps_and_planar_figures_none():
    for fig in (jm.figures.bob(), jm.figures.rex(), CUJO):
        source, flip = fig.sense_mirror
        names = fig.sense_names
        # An involution that keeps a sense's kind (contact to contact, angle to angle).
        assert all(source[source[j]] == j for j in range(fig.num_senses))
        kind = lambda name: name.split("[")[0]
        assert all(kind(names[source[j]]) == kind(names[j]) for j in range(fig.num_senses))
        flipped = {names[j] for j in range(10) if flip[j]}
        assert flipped == {"velocity_left", "spin_forward", "spin_up", "up_left"}
    assert jm.figures.star_man().sense_mirror is None
    with pytest.raises(ValueError, match=r"mirror = True but figure 'star_man' is planar"):
        jm.SenseBSRSpace(STAR, mirror=True)


def with_twins_as_rules(c: jm.SenseBSR, fig) -> jm.SenseBSR:
    """The plain 2R-rule controller that a mirrored R-rule one stands for: rules 0..R-1,
    then each rule's twin as a rule of its own (its rectangle over the mirrored senses moved
    onto the senses, its targets mirrored)."""
    source, flip = (np.asarray(x) for x in c.mirror)
    centres, sides = np.asarray(c.centres), np.asarray(c.sides)
    twin_centres, twin_sides = np.empty_like(centres), np.empty_like(sides)
    twin_centres[:, source] = np.where(flip, 1.0 - centres, centres)
    twin_sides[:, source] = sides
    partner, sign = fig.mirror
    targets = np.asarray(c.targets)
    twin_targets = np.asarray(sign) * targets[:, list(partner)]
    return jm.SenseBSR(
        np.concatenate([centres, twin_centres]),
        np.concatenate([sides, twin_sides]),
        np.concatenate([targets, twin_targets]),
        np.concatenate([np.asarray(c.taus)] * 2),
        filter_time=c.filter_time,
    )


# Scores of a twin and of the plain rule it stands for: `1 - S` against `c` or `S` against
# `1 - c`, the same in real arithmetic, float32 rounding apart (scores of order 10-50).
TWIN_SCORE_ATOL = 1e-4


def test_mirror_twins_act_as_rules_of_their_own():
    """A mirrored controller chooses and acts as the plain controller holding each rule and
    each rule's twin (rule R + r: the mirrored rectangle, the mirrored pose) would, tick by
    tick over random senses; in a simulation, twins do become active."""
    space = jm.SenseBSRSpace(CUJO, num_rules=4, filter_time=0.02, mirror=True)
    c = space.sample(key=jr.key(0))
    senses = jr.uniform(jr.key(1), (40, CUJO.num_senses))
    mirrored = jax.vmap(c.mirrored_senses)(senses)
    # Rules 1-3 around senses of ticks 5, 15 and (mirrored) 25, sides 1: rules and twins act.
    c = eqx.tree_at(
        lambda x: (x.centres, x.sides),
        c,
        (
            c.centres.at[1].set(senses[5]).at[2].set(senses[15]).at[3].set(mirrored[25]),
            jnp.full_like(c.sides, 1.0),
        ),
    )
    plain = with_twins_as_rules(c, CUJO)
    plan, plain_plan = c.prepare(CUJO), plain.prepare(CUJO)
    np.testing.assert_allclose(
        np.asarray(jax.vmap(lambda s: c.scores(s, plan))(senses)),
        np.asarray(jax.vmap(lambda s: plain.scores(s, plain_plan))(senses)),
        atol=TWIN_SCORE_ATOL,
    )
    a, b = c.init(senses[0], plan), plain.init(senses[0], plain_plan)
    chosen = []
    for k in range(1, 40):
        t = jnp.asarray(k * 5e-3)
        a, b = c.update(t, a, senses[k], plan), plain.update(t, b, senses[k], plain_plan)
        assert int(a.discrete.active) == int(b.discrete.active)
        for x, y in zip(c.actuation(t, a, plan), plain.actuation(t, b, plain_plan), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        chosen.append(int(a.discrete.active))
    assert any(r >= 4 for r in chosen) and any(0 < r < 4 for r in chosen), chosen
    # In a simulation: rule 1 holds from the rest pose (its rectangle around the rest's
    # senses) and poses the legs unevenly; rule 2's twin is placed on the mirror image of
    # where that motion goes (its rectangle around the mirrored senses of a later sample),
    # so the twin, not rule 2 itself, takes over there.
    task = jm.Task(
        body=CUJO,
        world=jm.World(gravity=9.81, friction=0.8),
        space=space,
        objective=jm.Objective({"forward": 1.0}),
        duration=0.5,
        dt=0.005,
    )
    rest = CUJO.dynamics().senses(CUJO.state(), task.world, 0.005)
    c = eqx.tree_at(
        lambda x: (x.centres, x.sides), c, (c.centres.at[1].set(rest), c.sides.at[2].set(0.4))
    )
    sensed = lambda c: task.trajectories(jax.tree_util.tree_map(lambda x: x[None], c), senses=True)
    later = sensed(c).senses[0, 10]
    c = eqx.tree_at(lambda x: x.centres, c, c.centres.at[2].set(c.mirrored_senses(later)))
    trajectory = sensed(c)
    active = np.asarray(c.active_rules(trajectory.senses[0]))
    assert {1, 6} <= set(active.tolist()), active
    assert np.all(np.isfinite(np.asarray(trajectory.points)))


def test_a_batch_last_stack_of_mirrored_controllers_acts_as_each_alone():
    space = jm.SenseBSRSpace(CUJO, num_rules=4, filter_time=0.03, mirror=True)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(3), 7))
    senses = jr.uniform(jr.key(4), (5, 7, CUJO.num_senses))
    # Rule 1 around the senses, rule 2 around their mirror image: rules and twins act.
    twin = jax.tree_util.tree_map(lambda a: a[0], controllers)
    mirrored = jax.vmap(jax.vmap(twin.mirrored_senses))(senses)
    controllers = eqx.tree_at(
        lambda c: c.centres,
        controllers,
        controllers.centres.at[:, 1].set(senses[1]).at[:, 2].set(mirrored[3]),
    )
    controllers = eqx.tree_at(lambda c: c.sides, controllers, jnp.full_like(controllers.sides, 2.0))
    seen = ticks_of_a_batch_last_stack(controllers, CUJO, senses)
    assert any(r >= 4 for r in seen) and any(0 < r < 4 for r in seen)  # twins and rules


def test_a_twins_pose_is_its_rules_mirrored_and_soft_choice_blends_twins():
    c = jm.SenseBSRSpace(CUJO, num_rules=3, mirror=True).sample(key=jr.key(5))
    partner, sign = CUJO.mirror
    plan = c.prepare(CUJO)
    state = c.init(jnp.full(CUJO.num_senses, 0.5), plan)
    for r in range(2 * c.num_rules):
        st = state._replace(
            discrete=eqx.tree_at(lambda d: d.active, state.discrete, jnp.asarray(r))
        )
        target, tau = c.actuation(0.0, st, plan)
        rule = np.asarray(c.targets[r % 3])
        want = rule if r < 3 else np.asarray(sign) * rule[list(partner)]
        np.testing.assert_array_equal(np.asarray(target), want)
        assert float(tau) == float(c.taus[r % 3])
    # The soft choice with all its weight on twin 4 poses twin 4's targets.
    soft = c.smoothed(0.1)
    assert soft.mirror == c.mirror
    weights = jnp.zeros(6).at[4].set(1.0)
    st = state._replace(discrete=eqx.tree_at(lambda d: d.active, state.discrete, weights))
    target, _ = soft.actuation(0.0, st, plan)
    np.testing.assert_allclose(
        np.asarray(target), np.asarray(sign) * np.asarray(c.targets[1])[list(partner)], atol=EXACT
    )


def test_a_mirrored_space_samples_and_mutates_mirrored_controllers():
    space = jm.SenseBSRSpace(CUJO, num_rules=3, mirror=True)
    c = space.sample(key=jr.key(0))
    assert c.mirror == CUJO.sense_mirror and c.num_choices == 6
    assert space.perturb(c, key=jr.key(1)).mirror == c.mirror
    assert space.reinitialise(c, key=jr.key(2)).mirror == c.mirror
    assert jm.SenseBSRSpace(CUJO).sample(key=jr.key(0)).mirror is None


def test_a_mirrored_controller_round_trips_and_is_checked():
    from jaxmotion.experiment import controller_from_dict, controller_to_dict

    c = jm.SenseBSRSpace(CUJO, num_rules=2, mirror=True).sample(key=jr.key(0))
    back = controller_from_dict(json.loads(json.dumps(controller_to_dict(c, "sense_bsr"))))
    assert back.mirror == c.mirror
    np.testing.assert_array_equal(np.asarray(back.centres), np.asarray(c.centres))
    identity = (tuple(range(CUJO.num_senses)), (False,) * CUJO.num_senses)  # an involution
    with pytest.raises(ValueError, match=r"is not figure 'cujo''s sense map"):
        jm.SenseBSR(c.centres, c.sides, c.targets, c.taus, mirror=identity).prepare(CUJO)
    source, flip = CUJO.sense_mirror
    cycled = [1, 3, 0, 2, *source[4:]]  # a permutation, not its own inverse
    for bad in ((cycled, flip), (source, flip[:-1]), (source, [1] * len(flip)), "yes"):
        with pytest.raises(ValueError, match=r"SenseBSR.mirror = .*allowed: None or"):
            jm.SenseBSR(c.centres, c.sides, c.targets, c.taus, mirror=bad)
