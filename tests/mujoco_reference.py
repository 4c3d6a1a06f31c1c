"""Trusted references for the free flight of a planar chain of rigid rods with prescribed joint
angles: a MuJoCo simulation (`planar_chain_free_flight`) and an independent plain-NumPy one
(`planar_chain_numpy`) of the same model, with the same signature and return dict.

Conventions (shared by both functions and by jaxmotion's articulated-figure simulator):

- The chain lies in the world x-z plane (y = 0); gravity is ``(0, 0, -gravity)``. No floor, no
  contact, no damping, no joint limits.
- Rod 0 is the root; rod k >= 1 is attached at its proximal end to the distal end of rod k-1.
  Rod k is a uniform solid cylinder (mass m_k, length l_k, radius r_k): in its own frame, x along
  the rod, its inertia about its centre is diag(m r²/2, m (3 r² + l²)/12, m (3 r² + l²)/12).
- An angle φ about +y is the right-hand rotation R_y(φ) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]: it
  turns +x toward -z. Rod 0 points (proximal to distal) along R_y(root_angle) x̂ and rod k along
  R_y(root_angle + θ_1 + ... + θ_k) x̂: θ_k is the hinge angle of rod k relative to rod k-1.
- ``theta``, ``theta_dot``, ``theta_ddot`` are callables t -> array of shape (n-1,) that prescribe
  the joints exactly; the root is free and unactuated, so the joint motion cannot change the total
  linear momentum or the angular momentum about the centre of mass.
- Initial conditions: joints at theta(0) moving at theta_dot(0); centre of mass at ``com0`` (a
  3-vector with y = 0) moving at ``com_velocity0``; rod 0 turning at ``root_angular_velocity0``
  (rad/s about +y).
- Angular momentum about the centre of mass, about +y, with positions relative to the centre of
  mass: L_y = Σ m (z v_x - x v_z) + I_yy ω_y.

Both return a dict of float64 arrays over the saved times (every ``save_every``-th step, always
including t = 0 and t = duration): ``t`` (T,), ``com`` (T, 3), ``root_angle`` (T,) unwrapped,
``root_proximal`` (T, 3) the proximal end of rod 0, ``angular_momentum_y`` (T,), ``points``
(T, n+1, 3) the rod endpoints (proximal end of rod 0, then the distal ends of rods 0..n-1) and
``theta`` (T, n-1) the joint angles the simulation actually had.

MuJoCo model: the root body carries slide-x, slide-z and hinge-y joints (exactly planar), its frame
origin at the proximal end of rod 0; each rod has an explicit ``<inertial>`` at its centre (no
geoms, so nothing is derived from geometry and nothing can collide). MuJoCo's RK4 integrator
advances the whole state; at every RK4 stage a control callback applies to the hinges the exact
inverse-dynamics torque: with the dense mass matrix M and the bias c (gravity, Coriolis), it solves
M [a_root; θ̈(t)] + c = [0; τ] for a_root and τ. The joints thus follow θ(t) to the integrator's
accuracy, and the root receives no generalised force.

NumPy model: in free flight the centre of mass follows its parabola and L_y is constant, so with
I_yy(θ) the figure's inertia about its centre of mass and h(θ, θ̇) the angular momentum the joint
rates alone carry (each rod's own spin included), the root angle obeys
φ̇ = (L_y - h(θ(t), θ̇(t))) / I_yy(θ(t)), integrated with RK4.
"""

from collections.abc import Callable

import mujoco
import numpy as np

ArrayFn = Callable[[float], np.ndarray]


def _rod_inertias(lengths, masses, radii):
    """Axial and transverse moments of inertia of uniform solid cylinders about their centres."""
    axial = masses * radii**2 / 2
    transverse = masses * (3 * radii**2 + lengths**2) / 12
    return axial, transverse


def _steps(duration, dt, save_every):
    n_steps = round(duration / dt)
    if n_steps < 1 or abs(n_steps * dt - duration) > 1e-9 * max(duration, 1.0):
        raise ValueError(f"duration {duration} is not a whole number of steps of {dt}")
    saved = sorted(set(range(0, n_steps + 1, save_every)) | {n_steps})
    return n_steps, saved


def _chain_xml(lengths, masses, radii, gravity, dt):
    axial, transverse = _rod_inertias(lengths, masses, radii)

    def f(x):  # shortest repr that round-trips the float64 exactly
        return repr(float(x))

    def rod(k):
        inner = rod(k + 1) if k + 1 < len(lengths) else ""
        if k == 0:
            joints = (
                '<joint name="root_x" type="slide" axis="1 0 0"/>'
                '<joint name="root_z" type="slide" axis="0 0 1"/>'
                '<joint name="root_y" type="hinge" axis="0 1 0"/>'
            )
            pos = "0 0 0"
        else:
            joints = f'<joint name="theta{k}" type="hinge" axis="0 1 0"/>'
            pos = f"{f(lengths[k - 1])} 0 0"
        return (
            f'<body name="rod{k}" pos="{pos}">{joints}'
            f'<inertial pos="{f(lengths[k] / 2)} 0 0" mass="{f(masses[k])}" '
            f'diaginertia="{f(axial[k])} {f(transverse[k])} {f(transverse[k])}"/>'
            f'<site name="distal{k}" pos="{f(lengths[k])} 0 0"/>'
            f"{inner}</body>"
        )

    return (
        '<mujoco model="planar_chain">'
        '<compiler angle="radian" inertiafromgeom="false"/>'
        f'<option timestep="{f(dt)}" gravity="0 0 {f(-gravity)}" integrator="RK4">'
        '<flag contact="disable" constraint="disable"/></option>'
        f"<worldbody>{rod(0)}</worldbody></mujoco>"
    )


def _dense_mass_matrix(model, data, out):
    """Dense joint-space inertia from the current `qM` (via mj_mulM: its signature is the same in
    MuJoCo 3 and 4, unlike mj_fullM's)."""
    unit = np.zeros(model.nv)
    column = np.zeros(model.nv)
    for j in range(model.nv):
        unit[:] = 0.0
        unit[j] = 1.0
        mujoco.mj_mulM(model, data, column, unit)
        out[:, j] = column
    return out


def planar_chain_free_flight(
    lengths,
    masses,
    radii,
    theta: ArrayFn,
    theta_dot: ArrayFn,
    theta_ddot: ArrayFn,
    *,
    root_angle0: float,
    com0,
    com_velocity0,
    root_angular_velocity0: float,
    gravity: float,
    duration: float,
    dt: float,
    save_every: int = 1,
) -> dict[str, np.ndarray]:
    """Free flight of the planar chain simulated by MuJoCo (RK4, float64), the hinges driven by
    the exact inverse-dynamics torque that realises the prescribed theta(t); see the module
    docstring for the conventions and the returned dict."""
    return _mujoco_chain(
        lengths,
        masses,
        radii,
        lambda t, th, thd: np.asarray(theta_ddot(t), dtype=np.float64),
        None,
        theta0=theta(0.0),
        theta_dot0=theta_dot(0.0),
        root_angle0=root_angle0,
        com0=com0,
        com_velocity0=com_velocity0,
        root_angular_velocity0=root_angular_velocity0,
        gravity=gravity,
        duration=duration,
        dt=dt,
        save_every=save_every,
    )


def planar_chain_torque_limited(
    lengths, masses, radii, target: ArrayFn, tau: float, max_torque, *, theta0, theta_dot0, **flight
) -> dict[str, np.ndarray]:
    """Free flight of the planar chain simulated by MuJoCo with torque-limited hinges: at every
    RK4 stage each hinge asks for the joint law's acceleration
    `(target(t) - theta - 2 tau theta') / tau^2`, the inverse-dynamics torque that realises it
    (root free) is clipped to `[-max_torque, max_torque]` and applied. The chain starts with
    its joints at `theta0` moving at `theta_dot0`; `flight` holds the keyword arguments of
    `planar_chain_free_flight` (start, gravity, duration, dt, save_every)."""

    def wanted(t, th, thd):
        return (np.asarray(target(t), dtype=np.float64) - th - 2 * tau * thd) / tau**2

    return _mujoco_chain(
        lengths,
        masses,
        radii,
        wanted,
        np.asarray(max_torque, dtype=np.float64),
        theta0=theta0,
        theta_dot0=theta_dot0,
        **flight,
    )


def _mujoco_chain(
    lengths,
    masses,
    radii,
    joint_acceleration: Callable[[float, np.ndarray, np.ndarray], np.ndarray],
    max_torque: np.ndarray | None,
    *,
    theta0,
    theta_dot0,
    root_angle0: float,
    com0,
    com_velocity0,
    root_angular_velocity0: float,
    gravity: float,
    duration: float,
    dt: float,
    save_every: int,
) -> dict[str, np.ndarray]:
    """MuJoCo's free flight of the chain whose hinges apply, at every RK4 stage, the
    inverse-dynamics torque for `joint_acceleration(t, theta, theta')` (root free), clipped to
    `max_torque` when it is given."""
    lengths, masses, radii = (np.asarray(a, dtype=np.float64) for a in (lengths, masses, radii))
    n = len(lengths)
    n_steps, saved = _steps(duration, dt, save_every)
    model = mujoco.MjModel.from_xml_string(_chain_xml(lengths, masses, radii, gravity, dt))
    data = mujoco.MjData(model)
    nv = model.nv
    assert nv == n + 2 and model.nq == nv
    root_body = model.body("rod0").id
    distal_sites = [model.site(f"distal{k}").id for k in range(n)]

    # Initial state: place the root so that the centre of mass is at com0 with velocity
    # com_velocity0 (the slides translate every point alike).
    data.qpos[:3] = (0.0, 0.0, root_angle0)
    data.qvel[:3] = (0.0, 0.0, root_angular_velocity0)
    data.qpos[3:] = theta0
    data.qvel[3:] = theta_dot0
    mujoco.mj_forward(model, data)
    mujoco.mj_subtreeVel(model, data)
    com0, com_velocity0 = np.asarray(com0, float), np.asarray(com_velocity0, float)
    data.qpos[:2] = com0[[0, 2]] - data.subtree_com[root_body][[0, 2]]
    data.qvel[:2] = com_velocity0[[0, 2]] - data.subtree_linvel[root_body][[0, 2]]

    mass_matrix = np.zeros((nv, nv))

    def control(model_, data_):
        # MuJoCo calls this at every RK4 stage, after computing qM and qfrc_bias and with
        # data.time at the stage's time.
        _dense_mass_matrix(model_, data_, mass_matrix)
        bias = data_.qfrc_bias
        a_joint = joint_acceleration(data_.time, data_.qpos[3:].copy(), data_.qvel[3:].copy())
        a_root = -np.linalg.solve(mass_matrix[:3, :3], bias[:3] + mass_matrix[:3, 3:] @ a_joint)
        torque = mass_matrix[3:, :3] @ a_root + mass_matrix[3:, 3:] @ a_joint + bias[3:]
        if max_torque is not None:
            torque = np.clip(torque, -max_torque, max_torque)
        data_.qfrc_applied[:3] = 0.0
        data_.qfrc_applied[3:] = torque

    out = {
        "t": [],
        "com": [],
        "root_angle": [],
        "root_proximal": [],
        "angular_momentum_y": [],
        "points": [],
        "theta": [],
    }

    def record():
        # Position and velocity quantities of the current state (after mj_step they are stale).
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_comVel(model, data)
        mujoco.mj_subtreeVel(model, data)
        out["t"].append(data.time)
        out["com"].append(data.subtree_com[root_body].copy())
        out["root_angle"].append(data.qpos[2])
        out["root_proximal"].append(data.xpos[root_body].copy())
        out["angular_momentum_y"].append(data.subtree_angmom[root_body][1])
        out["points"].append(np.vstack([data.xpos[root_body], data.site_xpos[distal_sites]]))
        out["theta"].append(data.qpos[3:].copy())

    previous = mujoco.get_mjcb_control()
    mujoco.set_mjcb_control(control)
    try:
        data.time = 0.0
        saved_set = set(saved)
        record()
        for step in range(1, n_steps + 1):
            mujoco.mj_step(model, data)
            data.time = step * dt  # no accumulated rounding in the times
            if step in saved_set:
                record()
    finally:
        mujoco.set_mjcb_control(previous)
    return {key: np.asarray(value, dtype=np.float64) for key, value in out.items()}


def _planar_kinematics(lengths, masses, inertia_yy, phi, th, thd):
    """Rod endpoints relative to the proximal end of rod 0 (as (x, z) pairs), the centre of mass
    relative to it, the figure's I_yy about its centre of mass and the joint-rate angular
    momentum h, for root angle phi, joint angles th and rates thd."""
    angles = phi + np.concatenate([[0.0], np.cumsum(th)])
    rates = np.concatenate([[0.0], np.cumsum(thd)])  # each rod's rate relative to the root
    u = np.stack([np.cos(angles), -np.sin(angles)], axis=1)  # R_y(a) x̂ in (x, z)
    du = np.stack([-np.sin(angles), -np.cos(angles)], axis=1)  # d u / d a
    ends = np.vstack([[0.0, 0.0], np.cumsum(lengths[:, None] * u, axis=0)])
    centres = ends[:-1] + 0.5 * lengths[:, None] * u
    com = masses @ centres / masses.sum()
    rel = centres - com

    def momentum(rod_rates):
        # Velocities with the root's proximal end held still (translation adds nothing to the
        # angular momentum about the centre of mass).
        end_vel = np.vstack([[0.0, 0.0], np.cumsum((lengths * rod_rates)[:, None] * du, axis=0)])
        centre_vel = end_vel[:-1] + (0.5 * lengths * rod_rates)[:, None] * du
        orbital = masses * (rel[:, 1] * centre_vel[:, 0] - rel[:, 0] * centre_vel[:, 1])
        return orbital.sum() + inertia_yy @ rod_rates

    i_yy = momentum(np.ones_like(lengths))
    h = momentum(rates)
    return ends, com, i_yy, h


def planar_chain_numpy(
    lengths,
    masses,
    radii,
    theta: ArrayFn,
    theta_dot: ArrayFn,
    theta_ddot: ArrayFn,
    *,
    root_angle0: float,
    com0,
    com_velocity0,
    root_angular_velocity0: float,
    gravity: float,
    duration: float,
    dt: float,
    save_every: int = 1,
) -> dict[str, np.ndarray]:
    """The same free flight without MuJoCo: L_y constant, the centre of mass on its parabola, and
    φ̇ = (L_y - h) / I_yy integrated with RK4. `theta_ddot` is not needed (accepted for the common
    signature)."""
    del theta_ddot
    lengths, masses, radii = (np.asarray(a, dtype=np.float64) for a in (lengths, masses, radii))
    _, inertia_yy = _rod_inertias(lengths, masses, radii)
    n_steps, saved = _steps(duration, dt, save_every)
    com0, com_velocity0 = np.asarray(com0, float), np.asarray(com_velocity0, float)
    g = np.array([0.0, 0.0, -gravity])

    def kin(phi, t):
        return _planar_kinematics(
            lengths, masses, inertia_yy, phi, np.asarray(theta(t)), np.asarray(theta_dot(t))
        )

    _, _, i0, h0 = kin(root_angle0, 0.0)
    momentum = i0 * root_angular_velocity0 + h0

    def phi_rate(t):  # I_yy and h do not depend on the root angle
        _, _, i_yy, h = kin(0.0, t)
        return (momentum - h) / i_yy

    phis = np.empty(n_steps + 1)
    phis[0] = root_angle0
    for step in range(n_steps):
        t = step * dt
        k1 = phi_rate(t)
        k23 = phi_rate(t + dt / 2)
        k4 = phi_rate(t + dt)
        phis[step + 1] = phis[step] + dt / 6 * (k1 + 4 * k23 + k4)

    out = {key: [] for key in ("t", "com", "root_angle", "root_proximal", "angular_momentum_y")}
    out |= {"points": [], "theta": []}
    for step in saved:
        t = step * dt
        phi = phis[step]
        ends, com_rel, i_yy, h = kin(phi, t)
        com = com0 + com_velocity0 * t + 0.5 * g * t**2
        proximal = com - np.array([com_rel[0], 0.0, com_rel[1]])
        points = proximal + np.stack([ends[:, 0], np.zeros(len(ends)), ends[:, 1]], axis=1)
        out["t"].append(t)
        out["com"].append(com)
        out["root_angle"].append(phi)
        out["root_proximal"].append(proximal)
        out["angular_momentum_y"].append(i_yy * phi_rate(t) + h)
        out["points"].append(points)
        out["theta"].append(np.asarray(theta(t), dtype=np.float64))
    return {key: np.asarray(value, dtype=np.float64) for key, value in out.items()}
