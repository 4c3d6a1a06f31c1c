"""Physics of articulated figures: conservation laws in flight (a falling cat turns with zero
angular momentum), the joint law and joint limits, solver agreement and order, a cross-check
against MuJoCo, batching, builders and the errors of bad figures.

Every momentum and energy here is measured from the observed motion (points, frame) with an
independent NumPy forward kinematics of the documented joint semantics, never read back from
the simulation state. The joints are driven by `PrescribedJoints`, whose target makes the
joint law reproduce a known angle curve exactly, so each rod's orientation is known at every
saved time.

Simulations are compiled once per (figure, controller type, solver, timing): `_simulate`
takes the world (gravity as an array), controller and start state as arguments, so the tests
of one figure share one compilation.
"""

import math
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import linregress

import jaxmotion as jm
from jaxmotion.figures import Joint

G = 9.81
Y_AXIS = (0.0, 1.0, 0.0)

# Adaptive runs: tight tolerances in float64 (one setting for all, so compilations are shared).
DOPRI = dict(solver="dopri5", rtol=1e-10, atol=1e-12)
FLIGHT_DURATION = 1.0  # s, star_man and cujo runs
FLIGHT_SAVE_DT = 2e-3  # s, fine enough for fourth-order finite differences of the motion

# Tolerances (measured values in the comments, float64).
KINEMATICS_TOL = 1e-9  # m: observed nodes vs the prescribed angles' forward kinematics (~1e-11)
LINEAR_MOMENTUM_TOL = 1e-9  # relative to M |v|: sum of m_k x_k' vs M v (~5e-12)
ANGULAR_MOMENTUM_TOL = (
    1e-6  # relative: L(t) - L(0) (star_man ~1e-8, cujo ~3e-10; finite differences)
)
FALLING_CAT_MIN_TURN = 0.03  # rad: the frame must turn at least this much with L = 0 (0.06)
PARABOLA_TOL = 1e-9  # m: centre of mass vs z0 + vz t - g t^2 / 2 (~1e-13)
ENERGY_TOL = 1e-7  # relative: kinetic energy of a frozen spinning figure (~6e-9)
MIN_PRECESSION = 0.1  # rad: a non-principal spin turns the direction of w at least this (0.8)
SPIN_RATE_TOL = 1e-4  # rad: planar rigid spin, root angle vs phi0 + w t, symplectic (~7e-6)
SYMPLECTIC_ENERGY_TOL = 1e-5  # relative: same spin's kinetic energy, symplectic (~5e-13)
SETTLED_SPEED = 1e-4  # m/s: |com velocity| after 2 s standing (~3e-18)
SETTLED_HEIGHT = 1e-6  # m: peak-to-peak com height over the last second standing (0)
MAX_DEPTH = 5e-3  # m: no node deeper than this while standing (2.2 mm; static sag 1.7 mm)
UPRIGHT_TOL = 1e-3  # frame entries: standing figure does not tip (~1e-16)
JOINT_LAW_TOL = 1e-8  # rad: joint angle vs the critically damped closed form (~9e-12)
LIMIT_TOL = 1e-12  # rad: observed joint angles stay in [lo, hi] (~4e-16 beyond)
SOLVER_AGREEMENT = 5e-3  # m: symplectic at dt = 5e-4 vs dopri5 (3.7e-3 = g dt t / 2 at 1.5 s)
ORDER_TOL = 0.2  # fitted convergence order of the symplectic solver vs 1 (1.0000)
MUJOCO_TOL = 1e-6  # m and rad: jaxmotion vs MuJoCo (~7e-11; MuJoCo's RK4 at 2 ms)
NUMPY_TOL = 1e-6  # m and rad: jaxmotion vs the NumPy reference (~4e-12)
VMAP_TOL = 1e-12  # vmap vs a Python loop, float64 (~4e-15)
ROUNDING_TOL = 1e-12  # quantities that differ by rounding only (start frame, start pose)
RIGID_TOL = 1e-6  # rad/s: every rod of a frozen figure turns with the root (0)
BRUTE_FORCE_TOL = 1e-8  # relative: I w and h vs a sum over rods by central differences (~4e-11)
AT_LIMIT = 1e-9  # rad: an observed angle this close to a range end sits at the limit
RETURN_TOL = 0.05  # rad: after the limit the joint is back near its target by 1.5 s (6e-3)


class PrescribedJoints(jm.AbstractController):
    """Drives every free joint along `th(t) = mid + amp cos(omega t + phase)`: the target
    `th + 2 tau th' + tau^2 th''` makes the joint law `tau^2 th'' + 2 tau th' + th = target`
    hold for that curve, so a figure started at `th(0)`, `th'(0)` follows it exactly (the
    error of any other start decays critically damped). `amp = 0` holds the joints still."""

    mid: jax.Array
    amp: jax.Array
    omega: jax.Array
    phase: jax.Array
    tau: jax.Array

    def __init__(self, mid, amp, omega, phase, tau):
        self.mid, self.amp, self.omega, self.phase = (
            jnp.asarray(x, dtype=float) for x in (mid, amp, omega, phase)
        )
        self.tau = jnp.asarray(tau, dtype=float)

    def prepare(self, body):
        del body
        return None

    def actuation(self, t, state, plan):
        del state, plan
        arg = self.omega * t + self.phase
        th = self.mid + self.amp * jnp.cos(arg)
        thd = -self.amp * self.omega * jnp.sin(arg)
        thdd = -self.amp * self.omega**2 * jnp.cos(arg)
        return th + 2 * self.tau * thd + self.tau**2 * thdd, self.tau

    def _curve(self, t, derivative):
        t = np.asarray(t, dtype=float)[..., None]
        mid, amp, omega, phase = (
            np.asarray(x) for x in (self.mid, self.amp, self.omega, self.phase)
        )
        arg = omega * t + phase
        if derivative == 0:
            return mid + amp * np.cos(arg)
        if derivative == 1:
            return -amp * omega * np.sin(arg)
        return -amp * omega**2 * np.cos(arg)

    def angles(self, t):
        return self._curve(t, 0)

    def angle_rates(self, t):
        return self._curve(t, 1)

    def accelerations(self, t):
        return self._curve(t, 2)


@eqx.filter_jit
def _simulate(figure, controller, world, state, *, duration, solver, save_dt, dt=1e-3, **tols):
    return jm.simulate(
        figure,
        controller,
        world,
        duration,
        dt=dt,
        save_dt=save_dt,
        solver=solver,
        initial_state=state,
        **tols,
    )


def flight(gravity):
    """No floor; gravity as an array so that every gravity shares one compilation."""
    return jm.World(gravity=jnp.asarray(gravity, dtype=float), floor=False)


def on_floor(gravity=G):
    return jm.World(gravity=jnp.asarray(gravity, dtype=float))


def swinging(figure, *, fraction=0.8, tau=0.05, phase=None):
    """Every free joint swings about the middle of its range over `fraction` of its half
    range, each at its own frequency (so the shape traces a loop: a falling cat's turn).
    With `phase=None` every rate is 0 at t = 0."""
    ranges = figure.ranges
    n = figure.num_free
    phase = np.zeros(n) if phase is None else phase
    return PrescribedJoints(
        ranges.mean(axis=1),
        fraction * (ranges[:, 1] - ranges[:, 0]) / 2,
        np.linspace(5.0, 11.0, n),
        phase,
        tau,
    )


def start_of(figure, controller, **kw):
    return figure.state(angles=controller.angles(0.0), rates=controller.angle_rates(0.0), **kw)


def flight_run(figure, controller, state, gravity=0.0):
    return _simulate(
        figure,
        controller,
        flight(gravity),
        state,
        duration=FLIGHT_DURATION,
        save_dt=FLIGHT_SAVE_DT,
        **DOPRI,
    )


# ---------------------------------------------------------------- independent kinematics


def rotation(axis, angle):
    """Right-handed rotation about `axis` (Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.cos(angle) * np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * np.outer(a, a)


def rod_kinematics(figure, free_angles):
    """The documented joint semantics in NumPy: each rod's orientation relative to the rest
    pose (its parent's, then turned about each of its joint axes in order) and the nodes
    relative to the root's proximal node, root as at rest."""
    angles = [jt.lo for jt in figure.joints]  # fixed joints sit at lo == hi
    for i, j in enumerate(figure.free):
        angles[j] = free_angles[i]
    nodes = np.asarray(figure.nodes)
    orient = []
    pos = {figure.rods[0][0]: np.zeros(3)}
    for k, (p, d) in enumerate(figure.rods):
        g = np.eye(3) if k == 0 else orient[figure.parents[k]]
        for j, jt in enumerate(figure.joints):
            if jt.rod == k:
                g = g @ rotation(jt.axis, angles[j])
        orient.append(g)
        pos[d] = pos[p] + g @ (nodes[d] - nodes[p])
    return np.array(orient), np.array([pos[n] for n in range(len(nodes))])


def derivative(f, h):
    """Fourth-order central difference along axis 0 (drops two samples at each end)."""
    return (f[:-4] - 8 * f[1:-3] + 8 * f[3:-1] - f[4:]) / (12 * h)


def measured_motion(figure, trajectory, angles):
    """Momenta and kinetic energy of the observed motion, from the nodes and root frame of
    `trajectory` and the joint angles `angles` (T, num_free) at its saved times.

    Returns a dict over the interior samples: `P` total linear momentum, `L` angular
    momentum about the centre of mass (world frame, each rod's own spin included), `KE`,
    `w` each rod's angular velocity, `scale` the largest orbital momentum sum m |r| |v|
    (the size L is compared against), and `kinematics_error` (observed nodes vs the forward
    kinematics of `angles`, which also checks that the joints followed the prescription).
    """
    ts = np.asarray(trajectory.ts)
    h = ts[1] - ts[0]
    points = np.asarray(trajectory.points)
    com = np.asarray(trajectory.com)
    root = np.asarray(trajectory.frame) @ np.asarray(figure.frame).T
    rods = np.asarray(figure.rods)
    m = np.asarray(figure.masses)
    radius = np.asarray(figure.radii)
    nodes = np.asarray(figure.nodes)
    axis = nodes[rods[:, 1]] - nodes[rods[:, 0]]
    length = np.linalg.norm(axis, axis=1)
    axis = axis / length[:, None]
    # Solid cylinders about their centres, rest pose, world axes.
    axial, transverse = m * radius**2 / 2, m * (3 * radius**2 + length**2) / 12
    rest_inertia = transverse[:, None, None] * np.eye(3) + (axial - transverse)[
        :, None, None
    ] * np.einsum("ki,kj->kij", axis, axis)
    orient = np.empty((len(ts), len(rods), 3, 3))
    kinematics_error = 0.0
    for i in range(len(ts)):
        g, pos = rod_kinematics(figure, angles[i])
        orient[i] = root[i] @ g
        observed = points[i] - points[i, figure.rods[0][0]]
        kinematics_error = max(kinematics_error, np.abs(observed - pos @ root[i].T).max())
    centres = 0.5 * (points[:, rods[:, 0]] + points[:, rods[:, 1]])
    com_error = np.abs(np.einsum("k,tki->ti", m, centres) / m.sum() - com).max()
    v = derivative(centres, h)
    spin_matrix = np.einsum("tkij,tklj->tkil", derivative(orient, h), orient[2:-2])
    w = np.stack([spin_matrix[..., 2, 1], spin_matrix[..., 0, 2], spin_matrix[..., 1, 0]], -1)
    turned = orient[2:-2]
    inertia = np.einsum("tkij,kjl,tkml->tkim", turned, rest_inertia, turned)
    spin = np.einsum("tkij,tkj->tki", inertia, w)
    r = centres[2:-2] - com[2:-2, None]
    P = np.einsum("k,tki->ti", m, v)
    L = np.sum(m[None, :, None] * np.cross(r, v) + spin, axis=1)
    KE = 0.5 * np.einsum("k,tk->t", m, np.sum(v * v, -1)) + 0.5 * np.sum(w * spin, axis=(1, 2))
    relative_v = v - P[:, None] / m.sum()
    scale = np.max(
        np.einsum("k,tk->t", m, np.linalg.norm(r, axis=-1) * np.linalg.norm(relative_v, axis=-1))
    )
    return dict(
        t=ts[2:-2],
        P=P,
        L=L,
        KE=KE,
        w=w,
        scale=scale,
        kinematics_error=max(kinematics_error, com_error),
    )


def turn_angle(a, b):
    """Angle of the rotation taking frame `a` to frame `b`."""
    return float(np.arccos(np.clip((np.trace(b @ a.T) - 1) / 2, -1.0, 1.0)))


def planar_root_angle(trajectory):
    """Root angle about +y (R_y(phi) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]), unwrapped."""
    frame = np.asarray(trajectory.frame)
    return np.unwrap(np.arctan2(frame[:, 0, 2], frame[:, 0, 0]))


def planar_joint_angles(figure, trajectory):
    """Each non-root rod's angle about +y relative to its parent, from the nodes."""
    points = np.asarray(trajectory.points)
    rods = np.asarray(figure.rods)
    d = points[:, rods[:, 1]] - points[:, rods[:, 0]]
    alpha = np.arctan2(-d[..., 2], d[..., 0])  # R_y(alpha) x = (cos, 0, -sin)
    parents = np.array(figure.parents[1:])
    relative = alpha[:, 1:] - alpha[:, parents]
    return (relative + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------- 1-3: conservation in flight

FLYING = {"star_man": jm.figures.star_man, "cujo": jm.figures.cujo}


def initial_motion(figure, controller, com, velocity, orientation, angular_velocity, eps=1e-4):
    """The momenta at t = 0 of a figure placed at `com` moving at `velocity`, its root turned
    by the matrix `orientation` and turning at `angular_velocity` (world frame), its joints
    at the controller's angles and rates: `measured_motion` of a synthetic five-sample
    motion around t = 0 built with the NumPy kinematics alone."""
    m = np.asarray(figure.masses)
    rods = np.asarray(figure.rods)
    w = np.asarray(angular_velocity, dtype=float)
    speed = np.linalg.norm(w)
    ts = eps * np.arange(-2.0, 3.0)
    angles = controller.angles(0.0) + controller.angle_rates(0.0) * ts[:, None]
    points, centres, frames = [], [], []
    for t, th in zip(ts, angles, strict=True):
        turn = rotation(w, speed * t) if speed > 0 else np.eye(3)
        root = turn @ orientation
        _, pos = rod_kinematics(figure, th)
        com_rel = m @ (0.5 * (pos[rods[:, 0]] + pos[rods[:, 1]])) / m.sum()
        centres.append(np.asarray(com) + np.asarray(velocity) * t)
        points.append(centres[-1] + (pos - com_rel) @ root.T)
        frames.append(root @ np.asarray(figure.frame))
    fake = SimpleNamespace(
        ts=ts, points=np.array(points), com=np.array(centres), frame=np.array(frames)
    )
    return measured_motion(figure, fake, angles)


@pytest.mark.parametrize("spinning", [False, True], ids=["falling_cat", "spinning"])
@pytest.mark.parametrize("name", list(FLYING))
def test_flight_conserves_linear_and_angular_momentum(name, spinning, x64):
    """No gravity, no floor, joints swinging: the total linear momentum and the angular
    momentum about the centre of mass (measured from the observed motion, the rods' own
    spin included) stay what the start state gave. A falling cat (L = 0, joints at rest at
    t = 0) turns nonetheless; a spinning start (turned root, joint rates and root angular
    velocity at t = 0) checks the conversion `Figure.state` makes to L."""
    figure = FLYING[name]()
    n = figure.num_free
    c0, v0 = np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.0, 0.5])
    if not spinning:
        controller = swinging(figure)
        axis, angle, w0 = Y_AXIS, 0.0, np.zeros(3)
    elif figure.planar:
        controller = swinging(figure, phase=np.linspace(0.5, 3.0, n))
        axis, angle, w0 = Y_AXIS, 0.3, np.array([0.0, 1.5, 0.0])
    else:
        controller = swinging(figure, phase=np.linspace(0.5, 3.0, n))
        axis, angle, w0 = (1 / np.sqrt(2), 1 / np.sqrt(2), 0.0), 0.4, np.array([0.5, -1.0, 0.8])
    quaternion = (np.cos(angle / 2), *(np.sin(angle / 2) * np.asarray(axis)))
    start = start_of(
        figure, controller, com=c0, velocity=v0, orientation=quaternion, angular_velocity=w0
    )
    tr = flight_run(figure, controller, start)
    assert bool(tr.finite)
    frame = np.asarray(tr.frame)
    np.testing.assert_allclose(frame[0], rotation(axis, angle), atol=ROUNDING_TOL)
    motion = measured_motion(figure, tr, controller.angles(tr.ts))
    assert motion["kinematics_error"] < KINEMATICS_TOL
    M = figure.total_mass
    linear_error = np.abs(motion["P"] - M * v0).max() / (M * np.linalg.norm(v0))
    assert linear_error < LINEAR_MOMENTUM_TOL
    L0 = initial_motion(figure, controller, c0, v0, rotation(axis, angle), w0)["L"][0]
    size = motion["scale"] + np.linalg.norm(L0)
    assert np.abs(motion["L"] - L0).max() / size < ANGULAR_MOMENTUM_TOL
    if not spinning:
        assert np.all(np.asarray(start[1][1]) == 0.0)  # the state's L
        assert turn_angle(frame[0], frame[-1]) > FALLING_CAT_MIN_TURN


@pytest.mark.parametrize("name", list(FLYING))
def test_centre_of_mass_follows_a_parabola_whatever_the_joints_do(name, x64):
    figure = FLYING[name]()
    controller = swinging(figure, phase=np.linspace(0.0, 2.0, figure.num_free))
    c0, v0 = np.array([0.2, 0.0, 3.0]), np.array([0.7, 0.0, 2.5])
    if not figure.planar:
        v0[1] = -0.4
    tr = flight_run(figure, controller, start_of(figure, controller, com=c0, velocity=v0), G)
    t = np.asarray(tr.ts)[:, None]
    expected = c0 + v0 * t - 0.5 * G * t**2 * np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.asarray(tr.com), expected, rtol=0, atol=PARABOLA_TOL)
    # The nodes move as the centre of mass says: sum of m_k x_k' = M (v0 - g t z).
    motion = measured_motion(figure, tr, controller.angles(tr.ts))
    M = figure.total_mass
    expected_p = M * (v0 - G * motion["t"][:, None] * np.array([0.0, 0.0, 1.0]))
    linear_error = np.abs(motion["P"] - expected_p).max() / (M * np.linalg.norm(v0))
    assert linear_error < LINEAR_MOMENTUM_TOL


def test_frozen_3d_figure_spinning_off_axis_keeps_momentum_and_energy(x64):
    """Joints held still (`amp = 0`: zero target error and rate, so th'' = 0 as with no
    controller; it shares the compilation of the other Cujo runs), free flight, a spin about
    a non-principal axis: w wobbles, while the world-frame L and the kinetic energy stay."""
    cujo = jm.figures.cujo()
    n = cujo.num_free
    hold = PrescribedJoints(cujo.start_angles, np.zeros(n), np.ones(n), np.zeros(n), 0.05)
    v0, w0 = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, 3.0])
    start = start_of(cujo, hold, com=(0, 0, 1), velocity=v0, angular_velocity=w0)
    tr = flight_run(cujo, hold, start)
    motion = measured_motion(cujo, tr, hold.angles(tr.ts))
    assert motion["kinematics_error"] < KINEMATICS_TOL
    L = motion["L"]
    size = np.linalg.norm(L[0])
    assert np.abs(L - L[0]).max() / size < ANGULAR_MOMENTUM_TOL
    assert np.ptp(np.linalg.norm(L, axis=1)) / size < ANGULAR_MOMENTUM_TOL
    KE = motion["KE"]
    assert np.ptp(KE) / KE[0] < ENERGY_TOL
    w = motion["w"][:, 0]  # rigid: every rod turns with the root
    np.testing.assert_allclose(
        motion["w"], np.broadcast_to(w[:, None], motion["w"].shape), atol=RIGID_TOL
    )
    cos = w @ w[0] / (np.linalg.norm(w, axis=1) * np.linalg.norm(w[0]))
    assert np.arccos(np.clip(cos, -1, 1)).max() > MIN_PRECESSION


# ---------------------------------------------------------------- 3-4, 10: no controller

STAND = dict(duration=3.0, solver="symplectic", save_dt=0.02)


def test_frozen_planar_figure_spins_at_a_constant_rate(x64):
    """No controller (joints frozen), no gravity, far above the floor: a planar rigid body
    turns at the rate it was given and keeps its kinetic energy (symplectic solver; the
    floor is never reached, so this shares the standing test's compilation)."""
    star = jm.figures.star_man()
    w0, v0 = 3.0, np.array([0.4, 0.0, 0.3])
    start = star.state(com=(0, 0, 50.0), velocity=v0, angular_velocity=(0, w0, 0))
    tr = _simulate(star, None, on_floor(0.0), start, **STAND)
    assert not np.any(np.asarray(tr.contact))
    t = np.asarray(tr.ts)
    np.testing.assert_allclose(planar_root_angle(tr), w0 * t, rtol=0, atol=SPIN_RATE_TOL)
    expected = np.array([0, 0, 50.0]) + v0 * t[:, None]
    np.testing.assert_allclose(np.asarray(tr.com), expected, rtol=0, atol=PARABOLA_TOL)
    motion = measured_motion(star, tr, np.broadcast_to(star.start_angles, (len(t), 4)))
    assert np.ptp(motion["KE"]) / motion["KE"][0] < SYMPLECTIC_ENERGY_TOL


def test_figure_standing_on_the_floor_settles_and_stays(x64):
    star = jm.figures.star_man()
    tr = _simulate(star, None, on_floor(), star.state(), **STAND)
    t = np.asarray(tr.ts)
    com = np.asarray(tr.com)
    speed = np.linalg.norm(np.gradient(com, t, axis=0), axis=1)
    assert speed[t >= 2.0].max() < SETTLED_SPEED
    assert np.ptp(com[t >= 2.0, 2]) < SETTLED_HEIGHT
    assert np.asarray(tr.points)[..., 2].min() > -MAX_DEPTH
    np.testing.assert_allclose(
        np.asarray(tr.frame), np.broadcast_to(np.eye(3), tr.frame.shape), atol=UPRIGHT_TOL
    )
    # Both feet (nodes 4 and 5) carry it, nothing else touches.
    assert np.all(np.asarray(tr.contact)[-1] == np.array([0, 0, 0, 0, 1, 1], dtype=bool))


def test_planar_figure_stays_in_its_plane_through_contact(x64):
    """Thrown tumbling onto the floor (impacts, sliding friction): every node's y is
    exactly 0 all the time."""
    star = jm.figures.star_man()
    start = star.state(com=(0, 0, 0.9), velocity=(1.5, 0, 0), angular_velocity=(0, 4.0, 0))
    tr = _simulate(star, None, on_floor(), start, **STAND)
    assert bool(tr.finite)
    assert np.asarray(tr.contact).any()
    assert np.all(np.asarray(tr.points)[..., 1] == 0.0)
    assert np.all(np.asarray(tr.com)[:, 1] == 0.0)


# ---------------------------------------------------------------- 5-8: a planar chain

CHAIN_LENGTHS = (0.4, 0.3, 0.35)
CHAIN_MASSES = (1.0, 0.6, 0.8)
CHAIN_RADII = (0.03, 0.02, 0.025)
CHAIN_LIMIT = 1.0  # rad: joint ranges (-1, 1), wider than any prescribed swing below
CHAIN = dict(duration=1.5, save_dt=0.01)
MUJOCO_DT = 2e-3


def chain(max_torque=None, limit=CHAIN_LIMIT):
    """A serial chain along +x: rod k joins nodes k and k + 1, a hinge about y per non-root
    rod (the MuJoCo reference's model), its joints within (-limit, limit)."""
    x = np.concatenate([[0.0], np.cumsum(CHAIN_LENGTHS)])
    nodes = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    return jm.Figure(
        nodes,
        [(k, k + 1) for k in range(3)],
        masses=CHAIN_MASSES,
        radii=CHAIN_RADII,
        joints=[Joint(k, Y_AXIS, -limit, limit) for k in (1, 2)],
        planar=True,
        name="chain",
        max_torque=max_torque,
    )


def chain_run(figure, controller, state, gravity=0.0, **kw):
    settings = dict(CHAIN, **DOPRI) if not kw else dict(CHAIN, **kw)
    return _simulate(figure, controller, flight(gravity), state, **settings)


@pytest.mark.parametrize("tau", [0.05, 0.3])
def test_joint_follows_the_critically_damped_law_to_its_target(tau, x64):
    figure = chain()
    start, target = np.array([0.0, 0.3]), np.array([0.7, -0.4])
    controller = PrescribedJoints(target, np.zeros(2), np.ones(2), np.zeros(2), tau)
    tr = chain_run(figure, controller, figure.state(angles=start))
    t = np.asarray(tr.ts)[:, None]
    expected = target + (start - target) * (1 + t / tau) * np.exp(-t / tau)
    observed = planar_joint_angles(figure, tr)
    np.testing.assert_allclose(observed, expected, rtol=0, atol=JOINT_LAW_TOL)


@pytest.mark.parametrize("max_torque", [None, 1.0])
def test_joint_stops_at_its_limit_and_comes_back(max_torque, x64):
    """Started at +-0.5 rad moving at +-10 rad/s outward with tau = 0.2 s, the free law would
    overshoot to +-1.24; the joints stop at +-1, stay there while the law pushes outward, then
    return to their targets: kinematic joints, and torque-limited ones (1 N m: too weak to
    stop the swing before the stop)."""
    figure = chain(max_torque=max_torque)
    start, tau = np.array([0.5, -0.5]), 0.2
    assert start[0] + 10.0 * tau / np.e > CHAIN_LIMIT  # the unconstrained peak
    controller = PrescribedJoints(start, np.zeros(2), np.ones(2), np.zeros(2), tau)
    tr = chain_run(figure, controller, figure.state(angles=start, rates=(10.0, -10.0)))
    angles = planar_joint_angles(figure, tr)  # from the nodes
    # The observed pose clamps the angle to its range; what the dynamics must get right is
    # that the joint sits there (no rate into the limit) and then leaves it by the law.
    assert np.all(np.abs(angles) <= CHAIN_LIMIT + LIMIT_TOL)
    at_limit = np.abs(np.abs(angles) - CHAIN_LIMIT) < AT_LIMIT
    assert np.all(at_limit.sum(axis=0) >= 3)  # it rests there for several samples
    np.testing.assert_allclose(angles[-1], start, atol=RETURN_TOL)  # back toward its target


def chain_motion():
    """Two hinges swinging, their rates non-zero at t = 0."""
    return PrescribedJoints(
        np.zeros(2), np.array([0.6, -0.8]), np.array([3.0, 4.2]), np.array([0.3, 1.1]), 0.05
    )


CHAIN_START = dict(root_angle=0.2, com=(0.1, 0.0, 1.5), velocity=(0.4, 0.0, 2.0), spin=1.3)


def chain_start(figure, controller):
    s = CHAIN_START
    half = s["root_angle"] / 2
    return start_of(
        figure,
        controller,
        com=s["com"],
        velocity=s["velocity"],
        orientation=(np.cos(half), 0.0, np.sin(half), 0.0),
        angular_velocity=(0.0, s["spin"], 0.0),
    )


def test_fixed_step_solver_agrees_with_dopri5_at_first_order(x64):
    figure = chain()
    controller = chain_motion()
    start = chain_start(figure, controller)
    reference = np.asarray(chain_run(figure, controller, start, G).points)
    dts = [2e-3, 1e-3, 5e-4]
    errors = []
    for dt in dts:
        fixed = chain_run(figure, controller, start, G, solver="symplectic", dt=dt)
        errors.append(np.abs(np.asarray(fixed.points) - reference).max())
    assert errors[-1] < SOLVER_AGREEMENT
    slope = linregress(np.log(dts), np.log(errors)).slope
    assert abs(slope - 1.0) < ORDER_TOL


def chain_flight():
    """The references' keyword arguments for the chain's start and timing."""
    s = CHAIN_START
    return dict(
        root_angle0=s["root_angle"],
        com0=s["com"],
        com_velocity0=s["velocity"],
        root_angular_velocity0=s["spin"],
        gravity=G,
        duration=CHAIN["duration"],
        dt=MUJOCO_DT,
        save_every=round(CHAIN["save_dt"] / MUJOCO_DT),
    )


def test_planar_chain_agrees_with_mujoco_and_the_numpy_reference(x64):
    """Prescribed joint motion, free root, gravity, no floor: root angle, centre of mass and
    every node against MuJoCo (hinges driven by exact inverse dynamics, RK4 at 2 ms) and the
    NumPy reference."""
    pytest.importorskip("mujoco")
    import mujoco_reference

    figure = chain()
    controller = chain_motion()
    tr = chain_run(figure, controller, chain_start(figure, controller), G)
    s = CHAIN_START
    args = (
        CHAIN_LENGTHS,
        CHAIN_MASSES,
        CHAIN_RADII,
        controller.angles,
        controller.angle_rates,
        controller.accelerations,
    )
    kwargs = chain_flight()
    ours = dict(
        root_angle=planar_root_angle(tr), com=np.asarray(tr.com), points=np.asarray(tr.points)
    )
    for reference, tol in (
        (mujoco_reference.planar_chain_free_flight(*args, **kwargs), MUJOCO_TOL),
        (mujoco_reference.planar_chain_numpy(*args, **kwargs), NUMPY_TOL),
    ):
        np.testing.assert_allclose(reference["t"], np.asarray(tr.ts), atol=ROUNDING_TOL)
        for key, value in ours.items():
            np.testing.assert_allclose(value, reference[key], rtol=0, atol=tol, err_msg=key)
    # The root did turn, and not only at its initial rate (the joints moved it).
    turned = ours["root_angle"][-1] - s["root_angle"]
    assert abs(turned - s["spin"] * CHAIN["duration"]) > 0.1


# Torque-limited joints.
WIDE_LIMIT = 3.0  # rad: joint ranges no swing below reaches (MuJoCo's hinges have no stops)
TORQUE_MUJOCO_TOL = 5e-5  # m and rad: vs MuJoCo (limp ~8e-11; clipped ~1.5e-5: RK4 at 2 ms
# steps through the clip's kinks)
MIN_CLIP_EFFECT = 0.05  # m: a clipped torque moves some node this far off the kinematic run (0.11)


@pytest.mark.parametrize("max_torque", [0.0, 0.05])
def test_torque_limited_chain_agrees_with_mujoco(max_torque, x64):
    """Torque-limited hinges, free root, gravity, no floor: limp joints (0 N m) and joints
    too weak for the swing the law asks for (0.05 N m: clipped most of the time) against
    MuJoCo, whose hinges apply the inverse-dynamics torque of the same law clipped alike
    (RK4 at 2 ms). With the torque clipped, the motion is far from the kinematic joints'."""
    pytest.importorskip("mujoco")
    import mujoco_reference

    figure = chain(max_torque=max_torque, limit=WIDE_LIMIT)
    controller = chain_motion()
    tr = chain_run(figure, controller, chain_start(figure, controller), G)
    tau = float(controller.tau)

    def target(t):
        return (
            controller.angles(t)
            + 2 * tau * controller.angle_rates(t)
            + tau**2 * controller.accelerations(t)
        )

    reference = mujoco_reference.planar_chain_torque_limited(
        CHAIN_LENGTHS,
        CHAIN_MASSES,
        CHAIN_RADII,
        target,
        tau,
        max_torque,
        theta0=controller.angles(0.0),
        theta_dot0=controller.angle_rates(0.0),
        **chain_flight(),
    )
    assert np.abs(reference["theta"]).max() < WIDE_LIMIT
    np.testing.assert_allclose(reference["t"], np.asarray(tr.ts), atol=ROUNDING_TOL)
    ours = dict(
        root_angle=planar_root_angle(tr), com=np.asarray(tr.com), points=np.asarray(tr.points)
    )
    for key, value in ours.items():
        np.testing.assert_allclose(
            value, reference[key], rtol=0, atol=TORQUE_MUJOCO_TOL, err_msg=key
        )
    kinematic = chain(limit=WIDE_LIMIT)
    free = chain_run(kinematic, controller, chain_start(kinematic, controller), G)
    assert np.abs(ours["points"] - np.asarray(free.points)).max() > MIN_CLIP_EFFECT


def test_a_torque_limit_never_reached_leaves_the_kinematic_joints(x64):
    """With a limit far above any torque the law needs, the joints follow the law exactly
    as kinematic joints do."""
    controller = chain_motion()
    runs = [
        np.asarray(chain_run(f, controller, chain_start(f, controller), G).points)
        for f in (chain(), chain(max_torque=1e6))
    ]
    np.testing.assert_allclose(runs[1], runs[0], rtol=0, atol=ROUNDING_TOL)


HEAD_RAISED = math.radians(30.0)  # the snake's head starts this far above the floor
STRENGTH_MARGIN = 0.1  # the joint is this much stronger or weaker than the weight needs
MIN_HEAD_TURN = math.radians(5.0)  # rad: the head rises or sinks at least this (~15 degrees)


@pytest.mark.parametrize(
    ("strength", "rises"), [(1 + STRENGTH_MARGIN, True), (1 - STRENGTH_MARGIN, False)]
)
def test_a_joint_lifts_a_rod_lying_on_the_floor_only_with_the_torque_its_weight_needs(
    strength, rises, x64
):
    """The snake lies on the floor with its head raised 30 degrees, its head joint pulling
    it up with all it has (target 60 degrees). The floor carries the rest of the body (the
    contact forces' generalised forces: uniform gravity exerts none about the centre of
    mass), so the head joint holds the head's weight moment `m g (l / 2) cos 30` alone:
    10% more torque lifts the head, 10% less lets it sink."""
    snake = jm.figures.snake()
    mass, length = snake.masses[1], snake.lengths[1]
    moment = mass * G * length / 2 * math.cos(HEAD_RAISED)
    figure = jm.figures.snake(max_torque=strength * moment)
    lift = np.array([-2 * HEAD_RAISED, 0.0])  # a negative angle raises the head's tip
    controller = PrescribedJoints(lift, np.zeros(2), np.ones(2), np.zeros(2), 0.05)
    state = figure.state(angles=(-HEAD_RAISED, 0.0))
    tr = _simulate(
        figure,
        controller,
        on_floor(),
        state,
        duration=0.4,
        solver="symplectic",
        dt=5e-4,
        save_dt=0.01,
    )
    points = np.asarray(tr.points)
    head = points[:, 2] - points[:, 1]
    elevation = np.arctan2(head[:, 2], head[:, 0])
    turned = elevation[-1] - elevation[0]
    assert abs(elevation[0] - HEAD_RAISED) < ROUNDING_TOL**0.5
    assert (turned > MIN_HEAD_TURN) if rises else (turned < -MIN_HEAD_TURN)


STOP_ANGLE = 0.3  # rad: the leaning rod's stop, 0.3 rad past upright
STOP_TOL = 1e-3  # rad: the rod held at its stop leans 0.3 rad (the base's sag tilts it 6e-4)


@pytest.mark.parametrize(("strength", "leaves"), [(0.7, False), (1.4, True)])
def test_a_weak_joint_that_a_load_presses_into_its_stop_stays_there(strength, leaves, x64):
    """A rod stands on a heavy base lying on the floor, leaning 0.3 rad forward against its
    joint's stop; its law asks for upright. Gravity's moment `m g (l / 2) sin 0.3` presses it
    into the stop: a joint weaker than that stays at the stop for the whole second (it does
    not chatter in and out of it, so the adaptive solver gets through), a stronger one
    leaves it and stands the rod up."""
    nodes = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 0.0, 0.5]])
    rod, length = 1.0, 0.5
    moment = rod * G * length / 2 * math.sin(STOP_ANGLE)
    figure = jm.Figure(
        nodes,
        [(0, 1), (1, 2)],
        masses=[5.0, rod],
        joints=[Joint(1, Y_AXIS, -1.0, STOP_ANGLE)],  # a positive angle leans it forward
        planar=True,
        max_torque=strength * moment,
    )
    controller = PrescribedJoints(np.zeros(1), np.zeros(1), np.ones(1), np.zeros(1), 0.05)
    state = figure.state(angles=(STOP_ANGLE,))
    tr = _simulate(figure, controller, on_floor(), state, duration=1.0, save_dt=0.05, **DOPRI)
    points = np.asarray(tr.points)
    rod_vector = points[:, 2] - points[:, 1]
    lean = np.arctan2(rod_vector[:, 0], rod_vector[:, 2])  # from upright, forward positive
    assert np.all(np.isfinite(lean))
    if leaves:
        assert abs(lean[-1]) < RETURN_TOL
    else:
        np.testing.assert_allclose(lean, STOP_ANGLE, rtol=0, atol=STOP_TOL)


def brute_force_momentum(figure, angles, rates, w, eps=1e-6):
    """Angular momentum about the centre of mass of a figure at rest orientation turning at
    `w` with joint rates `rates`, from each rod's full rotated inertia tensor, its centre's
    velocity and its angular velocity (central differences of the rods' motion in time)."""
    nodes = np.asarray(figure.nodes)

    def rods_at(time):
        turn = rotation(w, np.linalg.norm(w) * time) if np.any(w) else np.eye(3)
        orient, pos = rod_kinematics(figure, angles + time * rates)
        orient = turn @ orient
        centres = np.array([0.5 * (pos[p] + pos[d]) for p, d in figure.rods]) @ turn.T
        return orient, centres

    (g0, c0), (gm, cm), (gp, cp) = rods_at(0.0), rods_at(-eps), rods_at(eps)
    masses = np.asarray(figure.masses)
    com = masses @ c0 / masses.sum()
    velocity = (cp - cm) / (2 * eps)
    com_velocity = masses @ velocity / masses.sum()
    momentum = np.zeros(3)
    for k, (p, d) in enumerate(figure.rods):
        u = nodes[d] - nodes[p]
        length = np.linalg.norm(u)
        u = u / length
        m, r = masses[k], figure.radii[k]
        axial, transverse = m * r * r / 2, m * (3 * r * r + length**2) / 12
        rest = transverse * np.eye(3) + (axial - transverse) * np.outer(u, u)
        spin = (gp[k] - gm[k]) @ g0[k].T / (2 * eps)  # skew: [omega]x
        omega = np.array([spin[2, 1], spin[0, 2], spin[1, 0]])
        own = g0[k] @ rest @ g0[k].T @ omega
        momentum += m * np.cross(c0[k] - com, velocity[k] - com_velocity) + own
    return momentum


@pytest.mark.parametrize("name", ["cujo", "rex", "bob"])
def test_state_momentum_matches_a_brute_force_sum_over_rods(name, x64):
    """The figure's inertia (a constant diagonal plus each rod's segment dyad and
    parallel-axis term) and the joint-rate momentum `h` against the textbook sum over rods
    of `g I_rod g^T omega + m r x v`, at random angles and rates."""
    figure = getattr(jm.figures, name)()
    rng = np.random.default_rng(3)
    lo, hi = figure.ranges.T
    angles = rng.uniform(lo, hi)
    rates = rng.normal(size=figure.num_free)
    w = rng.normal(size=3)
    zero = np.zeros(figure.num_free)
    # Root turning only: L = I w.
    _, (_, spin_only, _) = figure.state(angles=angles, angular_velocity=w)
    expected = brute_force_momentum(figure, angles, zero, w)
    np.testing.assert_allclose(
        spin_only, expected, rtol=0, atol=BRUTE_FORCE_TOL * np.linalg.norm(expected)
    )
    # Joints moving only: L = h.
    _, (_, joints_only, _) = figure.state(angles=angles, rates=rates)
    expected = brute_force_momentum(figure, angles, rates, np.zeros(3))
    np.testing.assert_allclose(
        joints_only, expected, rtol=0, atol=BRUTE_FORCE_TOL * np.linalg.norm(expected)
    )


# ---------------------------------------------------------------- 9: batching


def test_vmap_over_controllers_equals_a_python_loop(x64):
    """`jax.vmap(simulate)` over controllers (and their start states) against one call per
    controller, float64. Star-Man's loop shares the flight tests' compilation; a vmapped
    Cujo would add a second Cujo compilation (~25 s on two busy cores)."""
    star = jm.figures.star_man()
    n = star.num_free
    controllers = [
        swinging(star, fraction=f, phase=np.linspace(0, p, n))
        for f, p in ((0.8, 0.0), (0.5, 2.0), (0.3, 5.0))
    ]
    starts = [start_of(star, c, com=(0, 0, 1)) for c in controllers]
    stack = lambda trees: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)
    batched = jax.vmap(lambda c, s: flight_run(star, c, s))(stack(controllers), stack(starts))
    for b, (c, s) in enumerate(zip(controllers, starts, strict=True)):
        looped = flight_run(star, c, s)
        for field in ("points", "com", "frame"):
            np.testing.assert_allclose(
                np.asarray(getattr(batched, field)[b]),
                np.asarray(getattr(looped, field)),
                rtol=0,
                atol=VMAP_TOL,
                err_msg=field,
            )


# ---------------------------------------------------------------- 11-12: builders and errors

BUILDERS = {
    # name: (builder, rods, free angles, planar)
    "star_man": (jm.figures.star_man, 5, 4, True),
    "beryl_biped": (jm.figures.beryl_biped, 5, 4, True),
    "cujo": (jm.figures.cujo, 7, 12, False),
    "rex": (jm.figures.rex, 15, 10, False),
    "bob": (jm.figures.bob, 9, 10, False),
}


@pytest.mark.parametrize("name", list(BUILDERS))
def test_builders_have_their_documented_numbers_and_stand_on_the_floor(name, x64):
    builder, rods, free, planar = BUILDERS[name]
    figure = builder()
    assert (figure.num_rods, figure.num_nodes, figure.num_free) == (rods, rods + 1, free)
    assert figure.planar is planar
    assert figure.name == name
    pose = figure.pose()
    assert pose[:, 2].min() == 0.0
    # The default start state puts the figure exactly there: lowest node on the floor.
    positions, _ = figure.state()
    observed = figure.dynamics().observe(positions, jm.World())
    np.testing.assert_allclose(np.asarray(observed.points), pose, rtol=0, atol=ROUNDING_TOL)


MOVE_TOL = 0.01  # m: a joint's documented sense must move a foot by more than this


def _leg(figure, foot) -> list[int]:
    """The rods from the hip (a rod hanging from the root) down to the foot's first node."""
    ending_at = {d: k for k, (_, d) in enumerate(figure.rods)}
    chain = [ending_at[foot[0]]]
    while figure.parents[chain[-1]] != 0:
        chain.append(figure.parents[chain[-1]])
    return chain[::-1]


def _swing(figure, rod) -> int:
    """The free-angle index of `rod`'s joint about y (its swing in the sagittal plane)."""
    for i, j in enumerate(figure.free):
        joint = figure.joints[j]
        if joint.rod == rod and joint.axis == (0.0, 1.0, 0.0):
            return i
    raise AssertionError(f"rod {rod} of {figure.name} has no free joint about y")


def _moved(figure, index, angle):
    """The rest pose and the pose with free angle `index` at `angle`, the root held."""
    start = np.asarray(figure.start_angles, dtype=float)
    moved = start.copy()
    moved[index] = angle
    # Unshifted: the lowest node is put on the floor, which a moved leg may change.
    rest, after = figure.pose(start), figure.pose(moved)
    return rest - rest[:, 2].min(), after - after[:, 2].min()


@pytest.mark.parametrize("name", ["beryl_biped", "cujo", "rex", "bob"])
def test_hips_and_knees_move_the_feet_the_way_the_builders_document(name, x64):
    # The builders' convention (figure_builders' docstring): for a figure facing +x a hip
    # flexes with a negative angle about y (the foot goes forward) and a knee with a positive
    # one (the foot goes back); each foot's other joints and the other feet stay put.
    figure = BUILDERS[name][0]()
    assert len(figure.feet) >= 2
    knees = 0
    for f, foot in enumerate(figure.feet):
        others = [n for g, other in enumerate(figure.feet) if g != f for n in other]
        chain = _leg(figure, foot)
        hip = _swing(figure, chain[0])
        lo, hi = figure.ranges[hip]
        assert lo < 0 < hi
        rest, flexed = _moved(figure, hip, lo)
        assert np.all(flexed[list(foot), 0] > rest[list(foot), 0] + MOVE_TOL), (foot, "hip")
        np.testing.assert_allclose(flexed[others, :2], rest[others, :2], atol=ROUNDING_TOL)
        if len(chain) < 2:
            continue  # Cujo's legs are single rods: no knee
        knees += 1
        knee = _swing(figure, chain[1])
        lo, hi = figure.ranges[knee]
        assert lo == 0 < hi, "a knee bends one way only, positive"
        rest, flexed = _moved(figure, knee, hi)
        assert np.all(flexed[list(foot), 0] < rest[list(foot), 0] - MOVE_TOL), (foot, "knee")
        np.testing.assert_allclose(flexed[others, :2], rest[others, :2], atol=ROUNDING_TOL)
    assert knees == (0 if name == "cujo" else 2)


def test_rex_ankles_lift_the_toes_and_set_a_bent_leg_flat(x64):
    # Rex's ankles turn -40..0 degrees: negative lifts the toes; with the knee bent by an
    # angle, the ankle at minus that angle puts the foot back parallel to the floor.
    figure = jm.figures.rex()
    for ankle_node, toe in figure.feet:
        knee = _swing(figure, _leg(figure, (ankle_node,))[1])
        foot_rod = next(k for k, rod in enumerate(figure.rods) if rod == (ankle_node, toe))
        ankle = _swing(figure, foot_rod)
        lo, hi = figure.ranges[ankle]
        assert lo < 0 == hi
        rest, lifted = _moved(figure, ankle, lo)
        rise = lambda pose, toe=toe, ankle_node=ankle_node: pose[toe, 2] - pose[ankle_node, 2]
        assert rise(lifted) > rise(rest) + MOVE_TOL
        angles = np.asarray(figure.start_angles, dtype=float).copy()
        angles[knee], angles[ankle] = 0.5, -0.5
        bent = figure.pose(angles)
        assert abs(rise(bent)) < ROUNDING_TOL * 1e3, rise(bent)


def test_figure_feet_name_existing_nodes():
    with pytest.raises(ValueError, match=r"Figure.feet\[1\] = \(7,\).*0..3"):
        jm.Figure(NODES, RODS, feet=[(3,), (7,)])
    assert jm.Figure(NODES, RODS, feet=[[3], (1, 2)]).feet == ((3,), (1, 2))


NODES = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
RODS = [(0, 1), (1, 2), (2, 3)]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(joints=[Joint(1, Y_AXIS, 0.5, -0.5)]), r"joint 0 \(rod 1\) has range lo = 0.5 > hi"),
        (
            dict(nodes=NODES[[0, 1, 1, 3]]),
            r"rod 1 has length 0; allowed: > 0 \(its two nodes coincide\)",
        ),
        (dict(masses=[1.0, 1.0, -2.0]), r"rod 2 has mass -2; allowed: a number > 0"),
        (dict(masses=0.0), r"rod 0 has mass 0; allowed: a number > 0"),
        (
            dict(joints=[Joint(1, Y_AXIS, -1, 1), Joint(3, Y_AXIS, -1, 1)]),
            r"joint 1 turns rod 3, which does not exist \(rods are 0..2\)",
        ),
        (dict(joints=[Joint(0, Y_AXIS, -1, 1)]), r"joint 0 turns rod 0, the root"),
        (
            dict(rods=[(0, 1), (2, 3), (1, 2)]),
            r"rod 1 = \(2, 3\) starts at node 2, which no earlier rod reaches",
        ),
        (dict(max_torque=1.0), r"max_torque = 1.0 on a 3D figure; allowed: None"),
        (
            dict(planar=True, joints=[Joint(1, Y_AXIS, -1, 1)], max_torque=[1.0, 2.0]),
            r"Figure.max_torque = \[1.0, 2.0\]; allowed: one number or 1",
        ),
        (
            dict(planar=True, joints=[Joint(1, Y_AXIS, -1, 1)], max_torque=-0.5),
            r"Figure.max_torque\[0\] = -0.5; allowed: a finite number >= 0",
        ),
    ],
)
def test_bad_figures_raise_naming_the_rod_or_joint(kwargs, message):
    args = dict(nodes=NODES, rods=RODS)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        jm.Figure(args.pop("nodes"), args.pop("rods"), **args)


# Node positions of a pose and of its mirror image agree to float64 rounding (m).
MIRROR_ATOL = 1e-9


@pytest.mark.parametrize(
    ("name", "off_centre"),
    # Free angles of midline rods hung from one side (Bob's torso roll, Rex's tail yaw):
    # their mirror is a turn about the other pivot (see `Figure.mirror`), so they stay 0.
    [("cujo", []), ("rex", [1]), ("bob", [1])],
)
def test_the_mirror_map_poses_the_mirror_image(name, off_centre):
    fig = getattr(jm.figures, name)()
    partner, sign = fig.mirror
    rest = fig.pose()
    reflect = lambda p: p * np.array([1.0, -1.0, 1.0])  # the builders are centred at y = 0
    image = [int(np.argmin(np.linalg.norm(rest - q, axis=1))) for q in reflect(rest)]
    assert sorted(image) == list(range(fig.num_nodes))
    lo, hi = fig.ranges[:, 0], fig.ranges[:, 1]
    rng = np.random.default_rng(0)
    for _ in range(5):
        angles = rng.uniform(lo, hi)
        angles[off_centre] = 0.0
        mirrored = np.asarray(sign) * angles[list(partner)]
        assert np.all((lo <= mirrored) & (mirrored <= hi))
        np.testing.assert_allclose(
            reflect(fig.pose(angles)), fig.pose(mirrored)[image], atol=MIRROR_ATOL
        )


def test_planar_and_lopsided_figures_have_no_mirror():
    assert jm.figures.star_man().mirror is None
    assert jm.figures.beryl_biped().mirror is None
    bob = jm.figures.bob()
    joints = list(bob.joints)
    hip = next(i for i, j in enumerate(joints) if j.rod == 3 and j.axis == (0.0, 1.0, 0.0))
    joints[hip] = joints[hip]._replace(lo=-0.3)  # the left hip swings further than the right
    lopsided = jm.Figure(
        bob.nodes, bob.rods, masses=bob.masses, joints=joints, radii=bob.radii, feet=bob.feet
    )
    assert lopsided.mirror is None
    # An off-centre midline rod's roll mirrors onto itself with its sign changed.
    partner, sign = bob.mirror
    assert (partner[1], sign[1]) == (1, -1.0)
