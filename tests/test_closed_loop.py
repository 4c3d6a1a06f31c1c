"""The closed loop (`jaxmotion._sim.system`, `jaxmotion._sim.solver`): control ticks, starting
from any state and continuing exactly, samples that never change the motion, fixed-step and
adaptive solvers integrating the same hybrid system, controllers with continuous state."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

FIGURE_WORLD = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)


def lattice_task(body, duration, save_dt):
    return jm.Task(
        body,
        jm.World(),
        jm.RegimesSpace(4, 0.1),
        jm.Objective({"forward": 1.0}),
        duration=duration,
        dt=1e-3,
        save_dt=save_dt,
    )


def figure_task(body, duration, save_dt, sense=False):
    if sense:
        space = jm.SenseBSRSpace(body, num_rules=6, tau_min=0.02, tau_max=0.2, filter_time=0.02)
    else:
        space = jm.TimeBSRSpace(body, num_rules=4, t_per=0.1, tau_min=0.02, tau_max=0.2)
    return jm.Task(
        body,
        FIGURE_WORLD,
        space,
        jm.Objective({"forward": 1.0}),
        duration=duration,
        dt=4e-3,
        save_dt=save_dt,
    )


def lively_sense_bsr(task, seed=0):
    """A sense-based controller whose rules do switch: rules reinitialised by the relevance
    heuristic on its own motion."""
    c = task.space.sample(key=jr.key(seed))
    for k in range(4):
        _, motion = task.evaluate_sensed(jax.tree_util.tree_map(lambda a: a[None], c))
        c = task.space.reinitialise(c, key=jr.key(100 + k), motion=motion[0])
    return c


CASES = {
    # name: (task maker, body, the save intervals compared: every step and a multiple)
    "cube": (lattice_task, jm.lattices.cube, (1e-3, 0.02)),
    "star_man/sense_bsr": (
        lambda b, d, s: figure_task(b, d, s, sense=True),
        jm.figures.star_man,
        (4e-3, 0.02),
    ),
    "cujo/time_bsr": (figure_task, jm.figures.cujo, (4e-3, 0.04)),
}


@pytest.mark.parametrize(
    "name",
    # Cujo (a 3D figure) is one more compilation of paths the suite covers: `-m slow`.
    [pytest.param(n, marks=pytest.mark.slow) if n.startswith("cujo") else n for n in CASES],
)
def test_samples_never_change_the_motion_and_continuing_is_exact(name):
    """On the fixed-step path (the search's), for each kind of body (lattice, planar figure,
    3D figure) and controller (regimes, sense-based, time-based BSR):

    - saving every step or every few steps computes bitwise the same states (the samples
        common to both, and the final state, are equal);
    - simulating [0, T/2] and then [T/2, T] from the first half's final state computes
        bitwise what [0, T] does: samples, final body state and the controller's state.
    """
    make, builder, (fine, coarse) = CASES[name]
    body = builder()
    full, half, every = make(body, 0.4, coarse), make(body, 0.2, coarse), make(body, 0.2, fine)
    controller = full.space.sample(key=jr.key(3))
    first = half.simulate(controller)
    a = every.simulate(controller)
    step = round(coarse / fine)
    for field in ("ts", "points", "com", "frame", "contact"):
        np.testing.assert_array_equal(
            np.asarray(getattr(a, field))[::step], np.asarray(getattr(first, field)), err_msg=field
        )
    leaves = lambda s: jax.tree_util.tree_leaves((s.t, s.body, s.controller))
    for x, y in zip(leaves(a.final), leaves(first.final), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    b = full.simulate(controller)
    second = half.simulate(controller, initial_state=first.final)
    n = first.ts.shape[0]
    assert float(second.ts[0]) == float(b.ts[n - 1]) == float(np.float32(0.2))
    for field in ("points", "com", "frame", "contact"):
        joined = np.concatenate(
            [np.asarray(getattr(first, field)), np.asarray(getattr(second, field))[1:]]
        )
        np.testing.assert_array_equal(joined, np.asarray(getattr(b, field)), err_msg=field)
    for x, y in zip(leaves(second.final), leaves(b.final), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert bool(b.finite)
    assert np.ptp(np.asarray(b.points)[:, :, 2]) > 0.01  # not vacuous: the body moved
    if "sense" in name:
        # One controller alone and in a batch: bitwise the same fitness (the playback above
        # is a batch of one, padded).
        batch = full.sample(20, key=jr.key(5))
        batch = jax.tree_util.tree_map(lambda a, c: a.at[7].set(c), batch, controller)
        assert float(full.evaluate(batch)[7]) == float(full.fitness(b))


def test_a_task_starts_every_controller_from_its_initial_state():
    """`Task(initial_state=...)`: the seriatim searches' start, e.g. where another motion
    ended; each controller starts from its own initial state, at time 0."""
    star = jm.figures.star_man()
    up = star.state(com=(0.0, 0.0, 1.2), velocity=(0.5, 0.0, 1.0))
    task = figure_task(star, 0.2, 0.02)
    lifted = jm.Task(
        star,
        task.world,
        task.space,
        task.objective,
        duration=0.2,
        dt=task.dt,
        save_dt=0.02,
        initial_state=up,
    )
    params = task.sample(3, key=jr.key(4))
    tr = lifted.trajectories(params)
    np.testing.assert_allclose(np.asarray(tr.com[:, 0]), [[0.0, 0.0, 1.2]] * 3, atol=1e-6)
    assert np.all(np.asarray(tr.ts[:, 0]) == 0.0)
    # The same as starting the rest-pose task there.
    again = task.trajectories(params, initial_state=up)
    np.testing.assert_array_equal(np.asarray(again.points), np.asarray(tr.points))
    with pytest.raises(ValueError, match=r"initial_state has a part of shape \(2,\) where the"):
        jm.Task(
            jm.figures.cujo(),
            task.world,
            jm.TimeBSRSpace(jm.figures.cujo()),
            task.objective,
            duration=0.2,
            initial_state=up,
        )


class Oscillator(jm.AbstractController):
    """A controller with continuous state: a unit-mass spring `x'' = -omega^2 x` whose
    position is the target of every free joint (paper 001's spring nets in miniature)."""

    omega: jax.Array
    tau: float = 0.05

    def prepare(self, body):
        return body.num_free

    def init(self, senses, plan):
        del senses, plan
        one = jnp.ones_like(self.omega)
        return jm.ControllerState(None, (0.3 * one, 0.0 * one))

    def actuation(self, t, state, plan):
        x, _ = state.continuous
        return jnp.full((plan,), 1.0) * x, self.tau

    def rates(self, t, state, plan):
        x, v = state.continuous
        return v, -(self.omega**2) * x


def test_continuous_controller_state_is_integrated_with_the_body(x64):
    """The spring's state moves with the figure's in one solve: semi-implicit Euler
    (converging as its step shrinks) and the adaptive solver (to its tolerance) against the
    closed form `x = 0.3 cos(omega t)`."""
    star = jm.figures.star_man()
    omega = 2 * np.pi * 2.0
    c = Oscillator(jnp.asarray(omega))
    kw = dict(save_dt=0.01, initial_state=star.state(com=(0, 0, 30.0)))
    world = jm.World(gravity=0.0, floor=False)
    adaptive = jm.simulate(star, c, world, 1.0, solver="tsit5", dt=1e-3, **kw)
    x, _ = adaptive.final.controller.continuous
    assert float(x) == pytest.approx(0.3 * np.cos(omega * 1.0), abs=1e-6)  # TOL: rtol 1e-8
    errors = []
    dts = (1e-3, 5e-4, 2.5e-4)
    for dt in dts:
        fixed = jm.simulate(star, c, world, 1.0, dt=dt, **kw)
        errors.append(abs(float(fixed.final.controller.continuous[0]) - 0.3 * np.cos(omega)))
    assert errors[0] > errors[1] > errors[2]
    assert errors[-1] < 1e-4  # CONVERGED: 0.03% of the amplitude at dt = 0.25 ms
    # The joints follow the spring through their law `tau^2 th'' + 2 tau th' + th = x`:
    # after the transient (exp(-t / tau)), the steady response to `0.3 cos(omega t)`, of
    # gain 1 / (1 + (omega tau)^2) and lag 2 atan(omega tau).
    angles = np.asarray(adaptive.final.body.positions.angles)
    wt = omega * c.tau
    expected = 0.3 * np.cos(omega * 1.0 - 2 * np.arctan(wt)) / (1 + wt**2)
    np.testing.assert_allclose(angles, expected, atol=1e-5)  # TOL: transient e^-20, rtol 1e-8


def test_fixed_step_and_adaptive_run_the_same_hybrid_system(x64):
    """A sense-based controller on a short contact-rich motion, the control period held at
    4 ms: the fixed-step path converges to the adaptive one as its physics step shrinks (the
    discrete state changes only at the ticks, where both sense the same state up to the
    integration error, so they choose the same rules, once that error is small against
    the scores' margins at the switches: a tick where a score crosses zero decides by a
    hair, and at dt = 1 ms this motion's switch came one tick early)."""
    star = jm.figures.star_man()
    task = figure_task(star, 0.3, 0.02, sense=True)
    c = lively_sense_bsr(task)
    kw = dict(control_dt=4e-3, save_dt=4e-3, senses=True)
    ref = jm.simulate(star, c, FIGURE_WORLD, 0.3, dt=4e-3, solver="dopri5", **kw)
    rules = lambda tr: np.asarray(c.active_rules(tr.senses))
    assert len(set(rules(ref).tolist())) > 1  # the rules do switch
    errors = []
    for dt in (5e-4, 2.5e-4):
        fixed = jm.simulate(star, c, FIGURE_WORLD, 0.3, dt=dt, **kw)
        np.testing.assert_array_equal(rules(fixed), rules(ref))
        errors.append(np.abs(np.asarray(fixed.points) - np.asarray(ref.points)).max())
    assert errors[-1] < 2e-3  # AGREE: 2 mm at dt = 0.25 ms
    assert errors[0] > errors[-1]
