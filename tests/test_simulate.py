"""Physics of the lattice simulation: conservation laws, known solutions, solver agreement."""

import jax
import jax.random as jr
import numpy as np
import pytest
from scipy.stats import linregress

import jaxmotion as jm
from jaxmotion._sim.simulate import simulate_batch

G = 9.81
NO_FLOOR = dict(floor=False)


def random_controller(seed, t_per=0.5, num_regimes=4):
    return jm.RegimesSpace(num_regimes, t_per).sample(key=jr.key(seed))


def squeezed_cube(damping=20.0, factor=0.8):
    """A cube and a start state squeezed along x, so the springs oscillate without any
    controller."""
    cube = jm.lattices.cube(damping=damping)
    points = np.asarray(cube.points) * np.array([factor, 1.0, 1.0])
    return cube, cube.state(points=points)


def lattice_energy(lattice, points, velocities, gravity):
    """Kinetic + spring + gravitational energy for every saved sample."""
    m = np.asarray(lattice.masses)
    i, j = np.asarray(lattice.springs).T
    k = np.asarray(lattice.stiffness)
    rest = np.asarray(lattice.rest_lengths)
    length = np.linalg.norm(points[:, j] - points[:, i], axis=-1)
    spring = 0.5 * np.sum(k * (length - rest) ** 2, axis=-1)
    kinetic = 0.5 * np.sum(m * np.sum(velocities**2, axis=-1), axis=-1)
    return kinetic + spring + gravity * np.sum(m * points[..., 2], axis=-1)


def test_free_flight_conserves_momentum_and_com_moves_uniformly(x64):
    """No gravity, no floor: internal (spring) forces cancel pairwise, so the centre of mass
    moves at constant velocity whatever the controller does."""
    cube = jm.lattices.cube()
    v0 = np.array([0.3, -0.2, 0.5])
    spin = np.cross(np.array([0.0, 0.0, 2.0]), np.asarray(cube.points) - np.asarray(cube.com))
    start = cube.state(velocities=v0 + spin)
    world = jm.World(gravity=0.0, **NO_FLOOR)
    tr = jm.simulate(cube, random_controller(0), world, 2.0, dt=1e-3, initial_state=start)
    expected = np.asarray(cube.com) + np.asarray(tr.ts)[:, None] * v0
    np.testing.assert_allclose(np.asarray(tr.com), expected, atol=1e-10)  # rounding only
    # The body did deform and turn (the test is not vacuous).
    assert float(jm.Objective({"rotation": 1.0})(tr)) > 1.0


def test_semi_implicit_euler_keeps_energy_bounded_without_damping(x64):
    """Damping off: over 10^4 steps the symplectic solver's energy oscillates within a band
    of O(dt) and does not drift."""
    cube, start = squeezed_cube(damping=0.0)
    world = jm.World(gravity=G, **NO_FLOOR)
    dt = 1e-3
    tr = jm.simulate(cube, None, world, 10.0, dt=dt, save_dt=dt, initial_state=start)
    points = np.asarray(tr.points)
    assert points.shape[0] == 10_001
    # x_{n+1} = x_n + h v_{n+1}, so (x_{n+1} - x_{n-1}) / 2h is the velocity midway between
    # v_n and v_{n+1}: the estimate that matches positions x_n to second order.
    velocities = (points[2:] - points[:-2]) / (2 * dt)
    energy = lattice_energy(cube, points[1:-1], velocities, G)
    swing = energy.max() - energy.min()
    rest = lattice_energy(cube, np.asarray(cube.points)[None], np.zeros((1, 8, 3)), G)[0]
    stored = energy[0] - rest
    assert swing < 0.05 * stored  # BAND: 5% of the oscillation energy
    first, last = energy[:1000].mean(), energy[-1000:].mean()
    assert abs(last - first) < 0.005 * stored  # DRIFT: under 0.5% over 10^4 steps


def test_damping_dissipates_energy(x64):
    """With spring damping, energy only goes down (tension k(x - L) + D xdot resists
    stretching; a sign error would feed energy in)."""
    cube, start = squeezed_cube(damping=20.0)
    world = jm.World(gravity=0.0, **NO_FLOOR)
    dt = 1e-4
    tr = jm.simulate(cube, None, world, 0.5, dt=dt, save_dt=dt, initial_state=start)
    points = np.asarray(tr.points)
    energy = lattice_energy(cube, points[1:-1], (points[2:] - points[:-2]) / (2 * dt), 0.0)
    assert energy[-1] < 0.5 * energy[0]
    # Monotone up to the O(dt) wobble of the integrator.
    assert np.all(np.diff(energy) < 1e-3 * energy[0])


def test_free_fall_of_the_com(x64):
    cube = jm.lattices.cube()
    world = jm.World(gravity=G, **NO_FLOOR)
    z0 = float(cube.com[2])
    exact = lambda t: z0 - 0.5 * G * t**2
    adaptive = jm.simulate(cube, random_controller(1), world, 1.0, solver="tsit5")
    t = np.asarray(adaptive.ts)
    np.testing.assert_allclose(np.asarray(adaptive.com[:, 2]), exact(t), atol=1e-8)
    dt = 1e-3
    fixed = jm.simulate(cube, random_controller(1), world, 1.0, dt=dt)
    # Semi-implicit Euler's z_n = z0 - g h^2 n(n+1)/2 = exact(t) - g h t / 2.
    np.testing.assert_allclose(np.asarray(fixed.com[:, 2]), exact(t) - 0.5 * G * dt * t, atol=1e-9)


@pytest.mark.parametrize("builder", [jm.lattices.cube, jm.lattices.pyramid, jm.lattices.chair])
def test_lattice_at_rest_on_the_floor_settles_and_stays(builder):
    lattice = builder()
    tr = jm.simulate(lattice, None, jm.World(), 4.0, dt=1e-3)
    com = np.asarray(tr.com)
    last_second = com[np.asarray(tr.ts) >= 3.0]
    # Settled: no motion in the last second beyond 0.1 mm.
    assert np.ptp(last_second, axis=0).max() < 1e-4
    # It sags under gravity (springs and floor penalty), by less than 2% of its height, and
    # the sag of an asymmetric body (the chair's backrest) shifts its centre of mass a little.
    height = float(np.ptp(np.asarray(lattice.points)[:, 2]))
    np.testing.assert_allclose(com[-1, :2], com[0, :2], atol=0.005 * height)
    assert 0 < com[0, 2] - com[-1, 2] < 0.02 * height
    assert bool(np.all(np.asarray(tr.contact)[-1] == (np.asarray(lattice.points)[:, 2] < 1e-6)))
    assert bool(np.all(np.asarray(tr.frame)[-1] == pytest.approx(np.eye(3), abs=1e-2)))  # < 0.6 deg


def test_fixed_step_and_adaptive_solvers_agree_and_converge_at_first_order(x64):
    """A smooth motion (free oscillation in flight): the fixed-step solution converges to the
    adaptive fifth-order one with order 1."""
    cube, start = squeezed_cube()
    world = jm.World(gravity=G, **NO_FLOOR)
    kw = dict(initial_state=start, save_dt=0.01)
    reference = np.asarray(jm.simulate(cube, None, world, 1.0, solver="tsit5", **kw).points)
    dts = [4e-4, 2e-4, 1e-4, 5e-5]
    errors = [
        np.abs(
            np.asarray(jm.simulate(cube, None, world, 1.0, dt=dt, **kw).points) - reference
        ).max()
        for dt in dts
    ]
    assert errors[-1] < 1e-3  # AGREE: within 1 mm at dt = 5e-5
    slope = linregress(np.log(dts), np.log(errors)).slope
    assert abs(slope - 1.0) < 0.2  # ORDER: first order


# Two adaptive solvers against each other: the fixed-step one is checked against an adaptive
# one in CI (the test above); this is one more pair of adaptive compilations: `-m slow`.
@pytest.mark.slow
def test_adaptive_solvers_agree_with_each_other(x64):
    cube, start = squeezed_cube()
    world = jm.World()
    kw = dict(initial_state=start, save_dt=0.02)
    controller = random_controller(3)
    a = jm.simulate(cube, controller, world, 1.0, solver="tsit5", **kw)
    b = jm.simulate(cube, controller, world, 1.0, solver="dopri5", **kw)
    assert bool(a.finite) and bool(b.finite)
    np.testing.assert_allclose(np.asarray(a.points), np.asarray(b.points), atol=1e-5)


def test_vmap_equals_a_python_loop_and_jit_equals_no_jit(x64):
    cube = jm.lattices.cube()
    world = jm.World()
    controllers = jm.Task(
        cube, world, jm.RegimesSpace(4, 0.7), jm.Objective({"forward": 1.0}), 0.5
    ).sample(3, key=jr.key(0))
    run = lambda c: jm.simulate(cube, c, world, 0.5, dt=1e-3)
    batched = jax.vmap(run)(controllers)
    jitted = jax.jit(run)
    for b in range(3):
        one = jax.tree_util.tree_map(lambda a, b=b: a[b], controllers)
        looped = run(one)
        for name in ("points", "com", "frame"):
            np.testing.assert_allclose(
                np.asarray(getattr(batched, name)[b]), np.asarray(getattr(looped, name)), atol=1e-12
            )
            np.testing.assert_allclose(
                np.asarray(getattr(jitted(one), name)),
                np.asarray(getattr(looped, name)),
                atol=1e-12,
            )


LATTICES = {
    "cube": jm.lattices.cube,
    "pyramid": jm.lattices.pyramid,
    "chair": jm.lattices.chair,
    "random": lambda: jm.lattices.from_points(
        np.random.default_rng(7).uniform(0, 1, (6, 3)) + np.array([0, 0, 0.01]),
        [(i, j) for i in range(6) for j in range(i + 1, 6) if (i + j) % 4],
        masses=np.random.default_rng(8).uniform(0.5, 2.0, 6),
        stiffness=1500.0,
    ),
}


# The pyramid, the chair and the random lattice run the same code as the cube, at other
# shapes (a compilation each, CI's time): `-m slow`.
@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n != "cube" else n for n in LATTICES],
)
def test_fast_batched_path_computes_the_same_trajectories(name, x64):
    """`Task.evaluate`'s batch-last path against the plain vmap of `simulate` (float64)."""
    lattice = LATTICES[name]()
    world = jm.World(friction_direction=(-1.0, 0.0), friction_preferred=1.5)
    space = jm.RegimesSpace(4, 0.6)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(1), 5))
    fast = simulate_batch(lattice, controllers, world, 1.0, dt=1e-3)
    plain = jax.vmap(lambda c: jm.simulate(lattice, c, world, 1.0, dt=1e-3))(controllers)
    for field in ("points", "com", "frame"):
        np.testing.assert_allclose(
            np.asarray(getattr(fast, field)), np.asarray(getattr(plain, field)), atol=1e-9
        )  # FAST_PATH tolerance: float64 rounding over 1000 contact-rich steps
    np.testing.assert_array_equal(np.asarray(fast.contact), np.asarray(plain.contact))


def test_blow_up_is_flagged_not_raised():
    """A step far too long for the springs makes the simulation explode: the trajectory says
    so, inside a batch, without an exception, and other controllers are unaffected."""
    stiff = jm.lattices.cube(stiffness=5e6)
    world = jm.World()
    space = jm.RegimesSpace(4, 0.5)
    controllers = jax.vmap(lambda k: space.sample(key=k))(jr.split(jr.key(2), 4))
    bad = simulate_batch(stiff, controllers, world, 1.0, dt=5e-3)
    assert not np.any(np.asarray(bad.finite))
    one = jm.simulate(stiff, None, world, 1.0, dt=5e-3)
    assert not bool(one.finite)
    good = simulate_batch(jm.lattices.cube(), controllers, world, 1.0, dt=1e-3)
    assert np.all(np.asarray(good.finite))


def test_adaptive_solver_out_of_steps_is_flagged():
    cube = jm.lattices.cube()
    tr = jm.simulate(cube, random_controller(0), jm.World(), 1.0, solver="tsit5", max_steps=10)
    assert not bool(tr.finite)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(duration=-1.0), r"duration = -1.0; allowed: a number of seconds > 0"),
        (dict(duration=float("nan")), r"duration = nan"),
        (dict(dt=0.0), r"dt = 0.0; allowed"),
        (dict(dt=2.0), r"dt = 2.0 is longer than duration = 1.0"),
        (dict(save_dt=1e-4), r"save_dt = 0.0001 is shorter than dt = 0.001"),
        (dict(control_dt=5e-4), r"control_dt = 0.0005 is shorter than dt = 0.001"),
        (dict(solver="rk4"), r"solver = 'rk4'; allowed: one of 'symplectic', 'tsit5', 'dopri5'"),
    ],
)
def test_bad_simulation_arguments_raise_before_compiling(kwargs, message):
    args = dict(duration=1.0, dt=1e-3)
    args.update(kwargs)
    duration = args.pop("duration")
    with pytest.raises(ValueError, match=message):
        jm.simulate(jm.lattices.cube(), None, jm.World(), duration, **args)


def test_time_grid_fills_the_duration_with_whole_steps_and_refuses_to_round():
    from jaxmotion._sim.simulate import time_grid

    grid = time_grid(3.15, 1e-3, 0.035)
    assert (grid.num_ticks, grid.substeps, grid.save_every, grid.num_saves) == (3150, 1, 35, 90)
    # The default save interval is the longest whole number of steps up to 20 ms that
    # divides the duration (3150 steps: 18).
    assert time_grid(3.15, 1e-3).save_every == 18
    assert time_grid(5.0, 4e-3).save_every == 5
    grid = time_grid(1.0, 1e-3, 0.02, control_dt=4e-3)
    assert (grid.num_ticks, grid.substeps, grid.save_every) == (250, 4, 5)
    # Nothing is rounded silently: a sample interval, control period or duration that is not
    # a whole number of the shorter one is refused, naming both and the nearest that are.
    with pytest.raises(ValueError, match=r"save_dt = 0.0045 is not a whole number of dt = 0.001"):
        time_grid(1.0, 1e-3, 0.0045)
    with pytest.raises(ValueError, match=r"duration = 3.15 is not a whole number of save_dt"):
        time_grid(3.15, 1e-3, 0.02)
    with pytest.raises(ValueError, match=r"duration = 1.0005 is not a whole number of dt"):
        time_grid(1.0005, 1e-3)
    with pytest.raises(ValueError, match=r"control_dt = 0.0025 is not a whole number of dt"):
        time_grid(1.0, 1e-3, control_dt=2.5e-3)
    tr = jm.simulate(jm.lattices.cube(), None, jm.World(), 0.42, dt=1e-3, save_dt=0.105)
    np.testing.assert_allclose(np.asarray(tr.ts), np.linspace(0, 0.42, 5), atol=1e-6)
    assert tr.points.shape == (5, 8, 3)


def test_contact_and_frame_observables():
    cube = jm.lattices.cube()
    tilted = (
        np.asarray(cube.points)
        @ np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]]).T
    )
    tr = jm.simulate(
        cube,
        None,
        jm.World(gravity=0.0, floor=False),
        0.01,
        initial_state=cube.state(points=tilted),
    )
    # The frame of a rigidly rotated lattice is that rotation (rotation about +y by 0.3 rad).
    frame = np.asarray(tr.frame)[0]
    assert frame[0, 0] == pytest.approx(np.cos(0.3), abs=1e-5)
    assert frame[2, 0] == pytest.approx(-np.sin(0.3), abs=1e-5)
    assert not np.any(np.asarray(tr.contact))  # no floor, no contact
    sunk = jm.simulate(cube, None, jm.World(), 0.05)
    assert np.asarray(sunk.contact)[-1].sum() == 4  # the bottom face rests on the floor
