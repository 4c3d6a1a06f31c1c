"""The bodies' sense variables (second paper, Table 1 and section 4.2): normalised to [0, 1],
in the documented order, and each moving the way its definition says."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxmotion as jm

G = 9.81
EXACT = 1e-5  # float32 rounding of a sense computed from a known state (values in [0, 1])


def senses_of(body, state, world=None, control_dt=4e-3):
    world = jm.World() if world is None else world
    return np.asarray(body.dynamics().senses(state, world, control_dt))


def test_planar_figures_sense_table_1():
    """An N-rod planar figure senses its N - 1 joint angles, N + 1 endpoint contact forces,
    the centre of mass's height and vertical velocity: 2 N + 2 senses."""
    star = jm.figures.star_man()
    assert star.num_senses == 2 * star.num_rods + 2 == 12
    assert star.sense_names[:4] == tuple(f"angle[{k}]" for k in range(4))
    assert star.sense_names[-2:] == ("height", "vertical_velocity")
    # At the start: angles at 0 in ranges of -45..45 degrees read 0.5; at rest, vertical
    # velocity 0 reads 0.5; the height is the centre of mass's over [0, 2 size].
    state = star.state()
    s = senses_of(star, state)
    np.testing.assert_allclose(s[:4], 0.5, atol=EXACT)
    assert s[-1] == pytest.approx(0.5, abs=EXACT)
    com_z = float(state.positions.com[1])
    assert s[-2] == pytest.approx(com_z / (2 * star.size), abs=EXACT)
    # A joint at the end of its range reads 0 or 1.
    lo, hi = star.ranges.T
    at_ends = star.state(angles=[lo[0], hi[1], lo[2], hi[3]])
    np.testing.assert_allclose(senses_of(star, at_ends)[:4], [0, 1, 0, 1], atol=EXACT)


def test_3d_figures_sense_section_4_2():
    cujo = jm.figures.cujo()
    names = cujo.sense_names
    n = cujo.num_nodes
    assert cujo.num_senses == 1 + 9 + 2 * n + cujo.num_free
    assert names[:10] == (
        "height",
        "velocity_forward",
        "velocity_left",
        "velocity_up",
        "spin_forward",
        "spin_left",
        "spin_up",
        "up_forward",
        "up_left",
        "up_up",
    )
    s = senses_of(cujo, cujo.state())
    # Upright and at rest: velocities and spin 0 read 0.5, the up axis reads (0, 0, 1).
    np.testing.assert_allclose(s[1:7], 0.5, atol=EXACT)
    np.testing.assert_allclose(s[7:10], [0.5, 0.5, 1.0], atol=EXACT)
    # Turned a quarter turn nose-down about the left axis (y): the world's up axis points
    # backward in the figure's frame; falling at half the velocity scale is moving forward,
    # read 0.75.
    q = (np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0)
    _, v_scale = jm._body._senses.scales(jm.World(), cujo.size)
    moving = cujo.state(com=(0, 0, 5.0), orientation=q, velocity=(0, 0, -0.5 * v_scale))
    s = senses_of(cujo, moving)
    np.testing.assert_allclose(s[7:10], [0.0, 0.5, 0.5], atol=EXACT)
    # Falling (world -z) is moving along the figure's +x (its nose points down).
    np.testing.assert_allclose(s[1:4], [0.75, 0.5, 0.5], atol=EXACT)
    # Spinning about the world's z axis, which is the figure's -forward axis now.
    spinning = cujo.state(com=(0, 0, 5.0), orientation=q, angular_velocity=(0, 0, 1.0))
    w_scale = 2 * v_scale / cujo.size
    assert senses_of(cujo, spinning)[4] == pytest.approx(0.5 - 0.5 / w_scale, abs=EXACT)


def test_lattices_sense_height_velocity_up_and_contact():
    cube = jm.lattices.cube()
    assert cube.num_senses == 7 + cube.num_masses
    # Resting on its bottom face (sunk to equilibrium), the floor carries the whole weight:
    # the contact senses (each over [0, M g]) sum to 1.
    settled = jm.simulate(cube, None, jm.World(), 1.0).final.body
    s = senses_of(cube, settled)
    assert float(np.sum(s[7:])) == pytest.approx(1.0, abs=1e-3)
    assert np.count_nonzero(s[7:] > 0.01) == 4
    np.testing.assert_allclose(s[4:7], [0.5, 0.5, 1.0], atol=1e-4)


@pytest.mark.parametrize(
    "make",
    [jm.lattices.cube, jm.figures.star_man, jm.figures.cujo],
    ids=["cube", "star_man", "cujo"],
)
def test_senses_stay_in_the_unit_interval_over_random_motions(make):
    """Violent random motions (the senses' ranges are exceeded: they are clipped)."""
    body = make()
    if isinstance(body, jm.Lattice):
        space, dt = jm.RegimesSpace(4, 0.5), 1e-3
    else:
        space, dt = jm.TimeBSRSpace(body, num_rules=4, t_per=0.5, tau_min=0.02), 4e-3
    world = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)
    task = jm.Task(body, world, space, jm.Objective({"forward": 1.0}), duration=1.0, dt=dt)
    tr = task.trajectories(task.sample(16, key=jr.key(0)), senses=True)
    s = np.asarray(tr.senses)
    assert s.shape == (16, tr.ts.shape[1], body.num_senses)
    assert np.all(np.asarray(tr.finite))
    assert s.min() >= 0.0 and s.max() <= 1.0
    # Not vacuous: the senses do move, and some contact force saturates.
    assert np.ptp(s, axis=(0, 1)).max() > 0.5


def test_a_falling_figure_senses_its_fall_and_its_landing():
    """Star-Man dropped from 1 m: until he lands his height sense falls as the semi-implicit
    Euler solution of free fall, `z0 - g t (t + dt) / 2`, his vertical velocity sense as
    `-g t` (both over their documented ranges), no contact force is sensed; landing makes
    the feet's contact forces appear."""
    star = jm.figures.star_man()
    start = star.state(com=(0, 0, 1.5))
    world = jm.World(floor_stiffness=1.0e4, floor_damping=100.0, friction_velocity=0.1)
    task = jm.Task(
        star,
        world,
        jm.TimeBSRSpace(star, num_rules=1, t_per=1.0, tau_min=1.0, tau_max=1.0),
        jm.Objective({"forward": 1.0}),
        duration=1.0,
        dt=1e-3,
        save_dt=0.01,
        initial_state=start,
    )
    hold = jm.TimeBSR(np.zeros(0), np.zeros((1, 4)), [1.0], 1.0)  # holds the rest pose
    tr = task.trajectories(
        jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], hold), senses=True
    )
    ts, s = np.asarray(tr.ts[0]), np.asarray(tr.senses[0])
    _, v_scale = jm._body._senses.scales(world, star.size)
    lowest = 1.5 - float(np.asarray(tr.com[0, 0, 2]) - np.asarray(tr.points[0, 0, :, 2]).min())
    flying = ts < np.sqrt(2 * lowest / G) - 0.01
    assert flying.sum() > 20
    expected_height = (1.5 - G * ts[flying] * (ts[flying] + 1e-3) / 2) / (2 * star.size)
    np.testing.assert_allclose(s[flying, 10], expected_height, atol=1e-5)
    # The fall from 1.5 m outruns the velocity range (a fall through the body's size): the
    # sense is clipped at 0 then.
    expected_velocity = np.clip(0.5 - 0.5 * G * ts[flying] / v_scale, 0.0, 1.0)
    np.testing.assert_allclose(s[flying, 11], expected_velocity, atol=1e-5)
    assert np.any(expected_velocity == 0.0)
    assert np.all(s[flying, 4:10] == 0.0)
    # A node senses a force only while it is below the floor (where the penalty acts), and
    # landing makes the feet's (nodes 4 and 5) appear, up to the clipped whole weight.
    contact = np.asarray(tr.contact[0])
    assert np.all(contact[s[:, 4:10] > 0])
    feet = s[:, [8, 9]]
    assert np.all(feet[flying] == 0.0) and feet.max() == 1.0


def test_senses_of_a_batch_are_each_bodys_senses():
    """The batch-last layout senses each controller's state as one body would."""
    star = jm.figures.star_man()
    rng = np.random.default_rng(0)
    states = [
        star.state(
            com=(0, 0, rng.uniform(0.3, 1.0)),
            velocity=(rng.normal(), 0, rng.normal()),
            angles=rng.uniform(*star.ranges.T),
        )
        for _ in range(5)
    ]
    world = jm.World()
    one = np.stack([senses_of(star, s, world) for s in states])
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a, axis=-1), *states)
    batch = np.asarray(star.dynamics().senses(stacked, world, 4e-3))
    np.testing.assert_allclose(batch.T, one, atol=EXACT)
