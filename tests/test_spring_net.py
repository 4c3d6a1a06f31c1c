"""Spring-net controllers (third paper): the net's physics in the closed loop (energy, the
two-mass frequency, fixed-step and adaptive solves), the output map, the family's sampling
and mutations, the snake and the Luxo lamp, and the `hop` and `roll` checks."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from scipy import stats

import jaxmotion as jm

# A float32 closed-loop run and the net run alone compute the same steps (the same
# semi-implicit Euler); XLA may fuse them differently, so they agree to rounding, which the
# net's oscillation keeps bounded over 1 s.
SAME_STEPS_RTOL = 1e-4
# Semi-implicit Euler keeps a shadow energy: the true energy oscillates in a band of
# relative width O(omega dt) and does not drift (measured: 1.3% and 2e-5 over 100 s).
ENERGY_BAND = 0.05
# The secular drift over the whole run, from a straight-line fit of the energy's relative
# deviation (explicit Euler, the non-symplectic step, gains 900% in 15 s on this net).
ENERGY_DRIFT = 1e-3
# The measured period of two masses against the analytic one, float64, dt = 0.1 ms.
PERIOD_RTOL = 1e-3
# The adaptive solver (float64, rtol 1e-8) against the closed form.
ADAPTIVE_ATOL = 1e-6
# Chi-square tests: reject only what is very unlikely at the fixed keys.
P_VALUE = 1e-3


@pytest.fixture(scope="module")
def snake():
    return jm.figures.snake()


@pytest.fixture(scope="module")
def net(snake):
    """A random four-mass net for the snake (its two joints read masses 0 and 1)."""
    return jm.SpringNetSpace(snake).sample(key=jr.key(3))


def two_masses(snake, m1=0.7, m2=1.6, k=9.0, x1=0.8, x2=-0.5):
    return jm.SpringNet([m1, m2], [k], [x1, x2], 0.1, snake.ranges)


def test_the_net_moves_with_the_body_in_one_solve(snake, net):
    """The net's state is integrated by the body's solver: after 1 s of the closed loop its
    masses are where the net alone, by the same steps, puts them, and they drive the joints
    (the snake's angles follow the net's targets)."""
    world = jm.World(gravity=0.0, floor=False)
    run = eqx.filter_jit(lambda c: jm.simulate(snake, c, world, 1.0, dt=0.005).final)
    final = run(net)
    x, v = final.controller.continuous
    _, (xs, vs) = net.oscillate_state(1.0, 0.005)
    np.testing.assert_allclose(x, xs[-1], rtol=SAME_STEPS_RTOL, atol=SAME_STEPS_RTOL)
    np.testing.assert_allclose(v, vs[-1], rtol=SAME_STEPS_RTOL, atol=SAME_STEPS_RTOL)
    moved = np.abs(np.asarray(final.body.positions.angles) - snake.start_angles)
    assert np.all(moved > 0)  # the joints left their start pose, driven by the net


def test_energy_is_conserved_without_damping_and_lost_with_it(snake, net):
    """Undamped, the net's energy stays in a bounded band around its start and does not
    drift over 100 s (20,000 semi-implicit Euler steps); damped, it decays."""
    dt, duration = 0.005, 100.0
    ts, (xs, vs) = net.oscillate_state(duration, dt)
    energy = np.asarray(net.energy(xs.T, vs.T), dtype=np.float64)
    deviation = energy / energy[0] - 1.0
    assert np.max(np.abs(deviation)) < ENERGY_BAND
    slope = stats.linregress(ts, deviation).slope
    assert abs(slope * duration) < ENERGY_DRIFT
    damped = jm.SpringNet(
        net.masses, net.stiffness, net.positions, net.tau, net.ranges, net.outputs, damping=0.5
    )
    _, (xd, vd) = damped.oscillate_state(10.0, dt)
    lost = np.asarray(damped.energy(xd.T, vd.T))
    assert lost[-1] < 0.1 * lost[0]  # e^{-0.5 * 10} of the kinetic part, and more


def test_two_masses_oscillate_at_the_analytic_frequency(snake, x64):
    """Two masses on one spring: their separation is `d0 cos(omega t)`, `omega^2 = k (1/m1 +
    1/m2)`, and their centre of mass stays put. Measured from the zero crossings of the
    net alone, and in the closed loop with the adaptive solver."""
    m1, m2, k = 0.7, 1.6, 9.0
    net = two_masses(snake, m1, m2, k)
    omega = math.sqrt(k * (1 / m1 + 1 / m2))
    ts, xs = net.oscillate(4.0, 1e-4)
    xs = np.asarray(xs)
    d = xs[:, 0] - xs[:, 1]
    crossings = ts[:-1][np.sign(d[:-1]) != np.sign(d[1:])]
    period = 2 * np.mean(np.diff(crossings))
    assert period == pytest.approx(2 * math.pi / omega, rel=PERIOD_RTOL)
    centre = (m1 * xs[:, 0] + m2 * xs[:, 1]) / (m1 + m2)
    np.testing.assert_allclose(centre, centre[0], atol=1e-9)
    world = jm.World(gravity=0.0, floor=False)
    T = 0.5
    final = jm.simulate(snake, net, world, T, solver="tsit5", dt=1e-3, save_dt=T).final
    x = np.asarray(final.controller.continuous[0])
    assert x[0] - x[1] == pytest.approx(1.3 * math.cos(omega * T), abs=ADAPTIVE_ATOL)


def test_the_output_map_stays_in_the_joint_ranges(snake):
    """Targets are the affine map of `[-1, 1]` onto each joint's range, clipped: the ends
    and the middle map to lo, hi and the middle of the range, and positions far outside
    still give targets inside it."""
    luxo = jm.figures.luxo()
    for figure in (snake, luxo):
        net = jm.SpringNetSpace(figure, num_masses=5).sample(key=jr.key(0))
        lo, hi = np.asarray(figure.ranges, dtype=np.float32).T  # the targets' dtype
        x = jnp.asarray(np.random.default_rng(0).uniform(-3, 3, (5, 1000)))
        targets = np.asarray(net.outputs_to_targets(x))
        assert targets.shape == (figure.num_free, 1000)
        assert np.all(targets >= lo[:, None]) and np.all(targets <= hi[:, None])
        for value, expected in ((-1.0, lo), (1.0, hi), (0.0, (lo + hi) / 2)):
            out = np.asarray(net.outputs_to_targets(jnp.full((5,), value)))
            np.testing.assert_allclose(out, expected, atol=1e-6)


def classify(parent, child) -> int:
    """Which kind of mutation turned `parent` into `child` (an index into
    `MUTATION_KINDS`)."""
    dk = np.asarray(child.stiffness) != np.asarray(parent.stiffness)
    dm = np.asarray(child.masses) != np.asarray(parent.masses)
    dx = np.asarray(child.positions) != np.asarray(parent.positions)
    if dk.sum() > 1:
        return 0
    if dk.sum() == 1:
        return 1
    if dm.sum() == 1:
        return 2
    if dx.sum() == 1:
        return 3
    raise AssertionError(f"no single mutation: {dk}, {dm}, {dx}")


def mid_net(space):
    """A net in the middle of every bound, so no mutation is clipped away."""
    n, p = space.num_masses, space.num_springs
    return jm.SpringNet(np.full(n, 1.0), np.full(p, 7.0), np.zeros(n), space.tau, space.ranges)


def test_mutation_kinds_follow_the_paper(snake):
    """`perturb` makes one mutation, of the paper's kinds in its shares (2/10 all springs,
    6/10 one spring, 1/10 one mass, 1/10 one initial position): a chi-square test at a
    fixed key. One-spring, one-mass and one-position mutations pick uniformly."""
    space = jm.SpringNetSpace(snake)
    parent = mid_net(space)
    n = 4000
    children = jax.vmap(lambda k: space.perturb(parent, key=k))(jr.split(jr.key(7), n))
    one = lambda i: jax.tree_util.tree_map(lambda a: a[i], children)
    kinds = np.array([classify(parent, one(i)) for i in range(n)])
    counts = np.bincount(kinds, minlength=4)
    expected = n * np.asarray(jm.MUTATION_PROBABILITIES)
    assert stats.chisquare(counts, expected).pvalue > P_VALUE
    springs = np.asarray(children.stiffness)[kinds == 1] != 7.0
    assert stats.chisquare(springs.sum(axis=0)).pvalue > P_VALUE


def test_sampling_is_in_the_documented_bounds(snake):
    space = jm.SpringNetSpace(snake, num_masses=5)
    nets = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(1), 2000))
    m, k, x = (np.asarray(a) for a in (nets.masses, nets.stiffness, nets.positions))
    assert m.shape == (2000, 5) and k.shape == (2000, 10) and x.shape == (2000, 5)
    assert m.min() >= 0.5 and m.max() <= 2.0
    assert k.min() >= 1.0 and k.max() <= 50.0
    assert x.min() >= -1.0 and x.max() <= 1.0
    # log-uniform: the logs are uniform (Kolmogorov-Smirnov against the uniform law)
    u = (np.log(k.ravel()) - np.log(1.0)) / (np.log(50.0) - np.log(1.0))
    assert stats.kstest(u, "uniform").pvalue > P_VALUE
    assert stats.kstest((x.ravel() + 1) / 2, "uniform").pvalue > P_VALUE


def test_bad_nets_and_spaces_are_named(snake):
    with pytest.raises(ValueError, match="num_masses = 1"):
        jm.SpringNetSpace(snake, num_masses=1)
    with pytest.raises(ValueError, match=r"num_masses = 2.*3"):
        jm.SpringNetSpace(jm.figures.luxo(), num_masses=2)
    with pytest.raises(ValueError, match=r"tau = -1"):
        jm.SpringNetSpace(snake, tau=-1)
    with pytest.raises(ValueError, match=r"stiffness_min = 60\.0 > stiffness_max"):
        jm.SpringNetSpace(snake, stiffness_min=60.0)
    with pytest.raises(ValueError, match="stiffness has shape"):
        jm.SpringNet([1.0, 1.0, 1.0], [1.0], [0.0, 0.0, 0.0], 0.1, snake.ranges)
    with pytest.raises(ValueError, match="masses"):
        jm.SpringNet([1.0, -1.0], [1.0], [0.0, 0.0], 0.1, snake.ranges)
    with pytest.raises(ValueError, match="2 joint angles but figure 'luxo' has 3"):
        two_masses(snake).prepare(jm.figures.luxo())
    with pytest.raises(TypeError, match="Figure"):
        jm.SpringNetSpace(jm.lattices.cube())


def test_snake_and_luxo_are_built_as_documented():
    snake, luxo = jm.figures.snake(), jm.figures.luxo()
    assert (snake.num_rods, snake.num_free, snake.planar) == (3, 2, True)
    assert snake.body_length == pytest.approx(0.9)
    np.testing.assert_allclose(np.degrees(snake.ranges), [[-90, 90]] * 2)
    np.testing.assert_allclose(snake.lengths, 0.3)
    assert (luxo.num_rods, luxo.num_free, luxo.planar) == (4, 3, True)
    np.testing.assert_allclose(np.degrees(luxo.ranges), [[-60, 60], [-75, 75], [-60, 60]])
    np.testing.assert_allclose(luxo.lengths, [0.25, 0.3, 0.3, 0.2])
    assert luxo.total_mass == pytest.approx(2.1)
    # The documented senses: a positive angle turns the snake's head tip down and its tail
    # tip up (against the root), and tips the lamp's lower arm forward.
    bent = snake.pose([0.5, 0.5])
    root = bent[0, 2]
    assert bent[2, 2] < root < bent[3, 2]
    assert luxo.pose([0.5, 0.0, 0.0])[2, 0] > luxo.pose()[2, 0]
    # Both rest on the floor; the lamp stands on its base.
    assert snake.pose()[:, 2].min() == pytest.approx(0.0)
    base = luxo.pose()[[0, 1], 2]
    np.testing.assert_allclose(base, 0.0, atol=1e-12)


def synthetic(com, frames, lowest):
    """A trajectory with the given centre of mass path, frames and lowest point."""
    t = len(com)
    points = np.repeat(np.asarray(com, float)[:, None, :], 2, axis=1)
    points[:, :, 2] = np.asarray(lowest, float)[:, None]
    return jm.Trajectory(
        ts=jnp.arange(t) * 0.02,
        points=jnp.asarray(points),
        com=jnp.asarray(com, dtype=float),
        frame=jnp.asarray(frames, dtype=float),
        contact=jnp.asarray(np.asarray(lowest)[:, None] <= 0.0).repeat(2, axis=1),
        finite=jnp.asarray(True),
    )


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_hop_and_roll_checks():
    """`hop`: >= 3 flights and >= 2 body lengths travelled (backwards counts: the paper's
    fitness is the absolute distance); `roll`: >= 1 full turn about the lateral axis while
    travelling; `hop_or_roll` says which."""
    t = 101
    x = -np.linspace(0.0, 2.5, t)  # backwards, 2.5 m
    com = np.stack([x, np.zeros(t), np.full(t, 0.2)], axis=1)
    hops = np.where((np.arange(t) // 10) % 2 == 1, 0.2, 0.0)
    hops[0] = 0.0
    upright = np.stack([np.eye(3)] * t)
    rolling = np.stack([rot_y(a) for a in np.linspace(0.0, 2.4 * math.pi, t)])
    hopper = synthetic(com, upright, hops)
    roller = synthetic(com, rolling, np.zeros(t))
    assert jm.checks.hop(hopper, body_length=1.0).passed
    assert not jm.checks.roll(hopper, body_length=1.0).passed
    assert jm.checks.roll(roller, body_length=1.0).passed
    assert not jm.checks.hop(roller, body_length=1.0).passed
    assert not jm.checks.hop(hopper, body_length=1.5).passed  # 1.67 body lengths
    assert not jm.checks.roll(roller, body_length=1.0, min_turns=1.5).passed  # 1.2 turns
    # Flights while turning over 1.2 times: a tumble, a roll and not a hop.
    tumbler = synthetic(com, rolling, hops)
    assert jm.checks.roll(tumbler, body_length=1.0).passed
    assert not jm.checks.hop(tumbler, body_length=1.0).passed
    assert jm.checks.hop(tumbler, body_length=1.0, max_turns=1.5).passed
    both = jm.checks.hop_or_roll(hopper, body_length=1.0)
    assert both.passed and both.figures["hop"] == 1.0 and both.figures["roll"] == 0.0
    still = synthetic(np.zeros((t, 3)), upright, hops)
    assert not jm.checks.hop_or_roll(still, body_length=1.0).passed
    assert jm.checks.CHECKS["hop"] is jm.checks.hop
    assert jm.checks.CHECKS["roll"] is jm.checks.roll


CONFIGS = ("snake_travel", "luxo_travel")


def config_path(name):
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "configs" / f"{name}.toml"


@pytest.mark.parametrize("name", CONFIGS)
def test_the_configs_describe_the_papers_largest_run(name):
    from jaxmotion.experiment import load_config

    experiment = load_config(config_path(name))
    assert isinstance(experiment.task.space, jm.SpringNetSpace)
    assert experiment.search == {
        "algorithm": "evolve",
        "generations": 20,
        "size": 2000,
        "mutations": 3,
        "accurate_candidates": 0,
    }
    assert experiment.task.objective.to_dict() == {"distance": 1.0}
    # T = 5 s with the paper's 5 ms step as the control period; torque-limited joints on a
    # 1 ms physics step (README, "Spring nets").
    task = experiment.task
    assert (task.duration, task.control_dt, task.dt) == (5.0, 0.005, 0.001)
    assert task.body.max_torque is not None
    assert experiment.check == "hop_or_roll"


def test_bad_config_values_are_named():
    """A wrong key or value names the field, the value and what is allowed."""
    import tomllib

    from jaxmotion.experiment import ConfigError, parse_config

    raw = tomllib.loads(config_path("snake_travel").read_text())

    def broken(section, key, value):
        bad = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
        bad[section][key] = value
        with pytest.raises(ConfigError) as e:
            parse_config(bad)
        return str(e.value)

    assert "size = 12; allowed: an integer >= 5, a multiple of 5" in broken("search", "size", 12)
    assert "generations = 0; allowed: an integer >= 1" in broken("search", "generations", 0)
    message = broken("search", "evaluations", 100)
    assert "unknown key 'evaluations'; allowed: algorithm, generations, size, mutations" in message
    message = broken("controller", "num_masses", 1)
    assert "num_masses = 1; allowed: an integer >= 2" in message
    message = broken("controller", "stiffness_min", 100.0)
    assert "stiffness_min = 100.0 > stiffness_max = 50.0" in message
    assert "tau = -0.1; allowed: a number > 0" in broken("controller", "tau", -0.1)
    message = broken("check", "motion", "hopp")
    assert "motion = 'hopp'; allowed:" in message and '"hop_or_roll"' in message
    lattice = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    lattice["body"] = {"lattice": "cube"}
    with pytest.raises(ConfigError, match="'spring_net' does not control a mass-spring lattice"):
        parse_config(lattice)


def test_a_saved_net_loads_back(net):
    from jaxmotion.experiment import controller_from_dict, controller_to_dict

    data = controller_to_dict(net)
    assert data["family"] == "spring_net"
    back = controller_from_dict(data)
    assert type(back) is jm.SpringNet
    assert (back.ranges, back.outputs, back.damping) == (net.ranges, net.outputs, net.damping)
    for field in ("masses", "stiffness", "positions", "tau"):
        np.testing.assert_array_equal(getattr(back, field), getattr(net, field))


@pytest.mark.slow
@pytest.mark.parametrize("name", CONFIGS)
def test_the_config_finds_a_gait_with_the_papers_budget(name, tmp_path):
    """The paper's largest evolution (20 generations of 2,000), seed 0, through the CLI (which
    compiles as a user's run does: the test processes compile unoptimised, 10x slower for a
    full budget): the best net travels >= 2 body lengths by hopping or rolling, and replays
    to its recorded fitness."""
    import json
    import subprocess
    import sys

    command = [sys.executable, "-m", "jaxmotion", "run", str(config_path(name))]
    command += ["--seed", "0", "--no-animation", "--out", str(tmp_path)]
    run = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    (folder,) = tmp_path.iterdir()
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["check"]["passed"]
    assert summary["replay_fitness"] == summary["best_fitness"]
