"""Objective terms on hand-built trajectories with known answers, and `Objective` itself."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmotion as jm

CUBE_POINTS = np.asarray(jm.lattices.cube().points)
ONE_POINT = np.zeros((1, 3))

# Float32 sums of a few hundred per-sample increments: relative error of angles and lengths.
ACCUMULATED_RTOL = 1e-5
# Float32 cancellation of increments that should sum to nothing (rad, turns or m).
CANCELLED_ATOL = 1e-5
# Central finite differences in float64: step and agreement with the gradient.
FD_STEP = 1e-6
FD_RTOL = 1e-6
FD_ATOL = 1e-8


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def make(com, frames=None, contact=None, duration=1.0, shape=CUBE_POINTS):
    """A trajectory of a rigid shape following `com` (T, 3) with orientation `frames`."""
    com = np.asarray(com, dtype=float)
    t = com.shape[0]
    frames = np.broadcast_to(np.eye(3), (t, 3, 3)) if frames is None else np.asarray(frames)
    rel = shape - shape.mean(0)
    points = com[:, None, :] + np.einsum("tij,nj->tni", frames, rel)
    if contact is None:
        contact = points[..., 2] < 1e-9
    return jm.Trajectory(
        ts=jnp.linspace(0.0, duration, t),
        points=jnp.asarray(points),
        com=jnp.asarray(com),
        frame=jnp.asarray(frames),
        contact=jnp.asarray(contact, dtype=bool),
        finite=jnp.asarray(True),
    )


def value(name, trajectory, **options):
    spec = {"weight": 1.0, **options} if options else 1.0
    return float(jm.Objective({name: spec}).values(trajectory)[name])


def line(start, end, t=11):
    return np.linspace(start, end, t)


def test_forward_and_sideways_follow_the_initial_frame():
    tr = make(line([0, 0, 0.5], [3.0, -1.0, 0.5]))
    assert value("forward", tr) == pytest.approx(3.0)
    assert value("sideways", tr) == pytest.approx(1.0)
    assert value("distance", tr) == pytest.approx(np.hypot(3.0, 1.0))
    # A body facing +y at the start: its forward travel is the y displacement.
    turned = make(
        line([0, 0, 0.5], [3.0, -1.0, 0.5]), frames=np.broadcast_to(rot_z(np.pi / 2), (11, 3, 3))
    )
    assert value("forward", turned) == pytest.approx(-1.0)
    assert value("sideways", turned) == pytest.approx(3.0)


def test_feet_forward_moves_with_the_points_that_start_on_the_floor():
    # Two feet on the floor and a head 1 m up; the body faces +y (rotated a quarter turn).
    start = np.array([[0.0, 0.1, 0.0], [0.0, -0.1, 0.003], [0.0, 0.0, 1.0]])
    frames = np.broadcast_to(rot_z(np.pi / 2), (3, 3, 3))
    points = np.stack([start, start, start])
    # The feet step 0.4 and 0.2 m along +y (forward) and 5 m along x (sideways, ignored); the
    # head leans 3 m forward, which must not count.
    points[-1, 0] += [5.0, 0.4, 0.0]
    points[-1, 1] += [5.0, 0.2, 0.0]
    points[-1, 2] += [0.0, 3.0, 0.0]
    tr = jm.Trajectory(
        ts=jnp.linspace(0.0, 1.0, 3),
        points=jnp.asarray(points),
        com=jnp.asarray(points.mean(1)),
        frame=jnp.asarray(frames),
        contact=jnp.asarray(points[..., 2] < 0),
        finite=jnp.asarray(True),
    )
    assert value("feet_forward", tr) == pytest.approx(0.3)
    # A tolerance below the second foot's 3 mm leaves the first foot alone.
    assert value("feet_forward", tr, tolerance=0.001) == pytest.approx(0.4)
    # A rigid body sliding 2 m forward: its bottom face (the cube's feet) moves 2 m.
    slid = make(line([0, 0, 0.5], [2.0, 0.0, 0.5]))
    assert value("feet_forward", slid) == pytest.approx(2.0)


def test_until_fall_and_standing_time_stop_at_the_first_sample_below_60_percent():
    # The cube walks 1 m in 0.5 s at its standing height 0.5 m, then dives: at t = 0.6 s its
    # centre of mass is 0.25 m up (below 60% of 0.5) and 1.5 m along; it ends 3.5 m along.
    x = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5]
    z = [0.5] * 6 + [0.25] * 5
    dive = make(np.stack([x, np.zeros(11), z], axis=1))
    assert value("forward", dive) == pytest.approx(3.5)
    assert value("forward", dive, until_fall=True) == pytest.approx(1.5)
    assert value("feet_forward", dive, until_fall=True) == pytest.approx(1.5)
    assert value("standing_time", dive) == pytest.approx(0.6)
    # Dropping to exactly 60% is not yet a fall; a body that never falls counts to the end.
    crouch = make(np.stack([x, np.zeros(11), [0.5] * 6 + [0.3] * 5], axis=1))
    assert value("standing_time", crouch) == pytest.approx(1.0)
    assert value("forward", crouch, until_fall=True) == pytest.approx(3.5)
    assert value("feet_forward", crouch, until_fall=True) == pytest.approx(3.5)
    # A stricter fall (fall_share 0.85): the crouch to 60% at t = 0.6 s is one.
    strict = dict(until_fall=True, fall_share=0.85)
    assert value("standing_time", crouch, fall_share=0.85) == pytest.approx(0.6)
    assert value("forward", crouch, **strict) == pytest.approx(1.5)
    assert value("feet_forward", crouch, **strict) == pytest.approx(1.5)
    with pytest.raises(ValueError, match=r"fall_share = 1.5; allowed: a number between 0 and 1"):
        value("standing_time", crouch, fall_share=1.5)


def test_final_spin_is_the_last_intervals_turn_rate():
    # Pitching at 2 rad/s about the left axis for the last 0.1 s (after resting), or yawing
    # at 3 rad/s throughout: the rate over the last interval, whatever the axis.
    angles = [0.0] * 10 + [0.2]
    pitching = make(np.zeros((11, 3)), frames=np.stack([rot_y(a) for a in angles]))
    assert value("final_spin", pitching) == pytest.approx(2.0, rel=ACCUMULATED_RTOL)
    yawing = make(np.zeros((11, 3)), frames=np.stack([rot_z(0.3 * k) for k in range(11)]))
    assert value("final_spin", yawing) == pytest.approx(3.0, rel=ACCUMULATED_RTOL)
    still = make(np.zeros((11, 3)))
    assert value("final_spin", still) == pytest.approx(0.0, abs=CANCELLED_ATOL)


def test_heading_deviation_is_the_largest_veer_even_when_it_comes_back():
    # Veering 40 degrees left and back again: heading's net turn is 0, the deviation 40
    # degrees; veering 100 degrees right stays 100 degrees whatever the sign.
    veer = np.deg2rad([0, 10, 25, 40, 30, 15, 0, 0, 0, 0, 0])
    tr = make(np.zeros((11, 3)), frames=np.stack([rot_z(a) for a in veer]))
    assert value("heading", tr) == pytest.approx(0.0, abs=CANCELLED_ATOL)
    assert value("heading_deviation", tr) == pytest.approx(np.deg2rad(40), rel=ACCUMULATED_RTOL)
    right = make(np.zeros((11, 3)), frames=np.stack([rot_z(-a) for a in np.linspace(0, 1.745, 11)]))
    assert value("heading_deviation", right) == pytest.approx(1.745, rel=ACCUMULATED_RTOL)


def test_flight_time_counts_intervals_with_every_point_high_enough():
    # The unit cube hops 0.1 m up over 5 of every 10 samples (intervals of 0.1 s), or
    # skims 2 mm up (no contact flag either way).
    lift = np.array([0.0] + [0.1 if k % 10 < 5 else 0.0 for k in range(1, 21)])
    hopping = make(np.stack([np.zeros(21), np.zeros(21), 0.5 + lift], axis=1), duration=2.0)
    assert value("flight_time", hopping) == pytest.approx(1.0)
    assert value("flight_time", hopping, height=0.2) == 0.0
    skimming = make(np.stack([np.zeros(21), np.zeros(21), 0.5 + lift / 50], axis=1), duration=2.0)
    assert value("flight_time", skimming) == 0.0
    assert value("flight_time", skimming, height=0.001) == pytest.approx(1.0)
    # air_height: the lowest point's mean height over the 20 instants after the start, 10 of
    # them 0.1 m up (or 2 mm), the others resting on the floor.
    assert value("air_height", hopping) == pytest.approx(0.05)
    assert value("air_height", skimming) == pytest.approx(0.001)
    sunk = make(np.stack([np.zeros(21), np.zeros(21), np.full(21, 0.49)], axis=1))
    assert value("air_height", sunk) == 0.0  # pressed 1 cm into the floor: no flight


def test_max_height():
    z = 0.5 + np.sin(np.linspace(0, np.pi, 21)) * 2.0
    tr = make(np.stack([np.zeros(21), np.zeros(21), z], axis=1))
    assert value("max_height", tr) == pytest.approx(2.0)


def test_clearance_is_the_highest_height_every_point_clears_at_once():
    # The unit cube rests with its bottom face on the floor: clearance 0 at rest, h at the top
    # of a jump of height h; a cube stood on one edge (tilted 45 degrees) clears nothing
    # however high its CoM, while a tall thin stick lifted by 0.1 clears 0.1.
    z = 0.5 + 0.7 * np.sin(np.linspace(0, np.pi, 21))
    tr = make(np.stack([np.zeros(21), np.zeros(21), z], axis=1))
    assert value("clearance", tr) == pytest.approx(0.7, rel=1e-6)
    assert value("clearance", make(np.full((5, 3), 0.5))) == pytest.approx(0.0, abs=1e-9)
    edge = make(
        np.full((5, 3), [0.0, 0.0, np.sqrt(0.5)]),
        frames=np.broadcast_to(rot_y(np.pi / 4), (5, 3, 3)),
    )
    assert value("clearance", edge) == pytest.approx(0.0, abs=1e-6)
    stick = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    lifted = make(line([0, 0, 1.0], [0, 0, 1.1]), shape=stick)
    assert value("clearance", lifted) == pytest.approx(0.1, rel=1e-5)


def test_contact_terms():
    # 8 points; contact pattern over 6 samples (the first, t = 0, is ignored).
    pattern = np.zeros((6, 8), bool)
    pattern[1, :4] = True  # on the ground
    pattern[2, :] = False  # airborne: hop 1
    pattern[3, :2] = True
    pattern[4, :] = False  # hop 2
    pattern[5, :3] = True
    tr = make(np.full((6, 3), 0.5), contact=pattern, duration=1.0)
    assert value("hops", tr) == 2
    assert value("min_contacts", tr) == 0
    assert value("grounded", tr) == 0  # airborne at samples 2 and 4
    assert value("contact_time", tr) == pytest.approx(3 * 0.2)
    assert value("on_ground_at_end", tr) == 1
    assert value("on_ground_at_end", tr, min_points=4) == 0
    # Some point down at every sample, a different one each time: grounded, and the fewest
    # points down at once is 1 (the start, t = 0, is not counted: nothing touches yet).
    walking = np.zeros((6, 8), bool)
    walking[np.arange(1, 6), np.arange(1, 6)] = True
    walking[3, 0] = True
    tr = make(np.full((6, 3), 0.5), contact=walking, duration=1.0)
    assert value("grounded", tr) == 1
    assert value("min_contacts", tr) == 1
    assert value("contact_time", tr) == pytest.approx(1.0)


def spin(axis_rot, total, t=41):
    angles = np.linspace(0.0, total, t)
    return np.stack([axis_rot(a) for a in angles])


def test_rotation_terms_measure_angles_and_signs():
    still = np.full((41, 3), 0.5)
    yaw = make(still, frames=spin(rot_z, 2 * np.pi))
    assert value("net_yaw", yaw) == pytest.approx(2 * np.pi, rel=1e-5)
    assert value(
        "net_yaw", make(still, frames=spin(rot_z, -2 * np.pi)), signed=True
    ) == pytest.approx(-2 * np.pi, rel=1e-5)
    assert value("rotation", yaw) == pytest.approx(2 * np.pi, rel=1e-5)
    assert value("rotation", yaw, axis="up") == pytest.approx(2 * np.pi, rel=1e-5)
    # A backward somersault (nose up and over): negative about the left axis.
    back = make(still, frames=spin(rot_y, -2 * np.pi))
    assert value("rotation", back, axis="left") == pytest.approx(-2 * np.pi, rel=1e-5)
    assert value("net_yaw", back) == pytest.approx(0.0, abs=1e-6)
    # Rocking back and forth: large total rotation, no net rotation.
    rock = np.concatenate([spin(rot_x, 1.0, 21), spin(rot_x, 1.0, 21)[::-1][1:]])
    tr = make(np.full((41, 3), 0.5), frames=rock)
    assert value("rotation", tr) == pytest.approx(2.0, rel=1e-5)
    assert value("rotation", tr, axis="forward") == pytest.approx(0.0, abs=1e-6)


def test_orientation_losses():
    still = np.full((21, 3), 0.5)
    tilt30 = make(still, frames=spin(rot_y, np.deg2rad(30), 21))
    assert value("upright", tilt30) == 0
    assert value("upright", tilt30, max_degrees=20) == 1
    assert value("tilt", tilt30) == pytest.approx(np.deg2rad(30), rel=1e-4)
    assert value("final_tilt", tilt30) == pytest.approx(np.deg2rad(30), rel=1e-4)
    # A full backward somersault ends upright: large tilt on the way, none at the end.
    back = make(still, frames=spin(rot_y, -2 * np.pi, 21))
    assert value("tilt", back) == pytest.approx(np.pi, rel=1e-4)
    assert value("final_tilt", back) == pytest.approx(0.0, abs=1e-3)
    assert value("fallen", back) == 0
    assert value("fallen", tilt30) == 0
    assert value("fallen", tilt30, max_degrees=20) == 1
    flipped = make(still, frames=spin(rot_x, np.deg2rad(120), 21))
    assert value("upright", flipped) == 1
    assert value("left_right", flipped) == 1
    assert value("front_facing", flipped) == 0
    turned = make(still, frames=spin(rot_z, np.deg2rad(60), 21))
    assert value("front_facing", turned) == 1
    assert value("left_right", turned) == 0
    assert value("upright", turned) == 0


def test_asymmetry_is_zero_for_symmetric_motion_and_grows_with_asymmetry():
    still = np.full((5, 3), 0.5)
    assert value("asymmetry", make(still)) == pytest.approx(0.0, abs=1e-5)
    # Stretch the left half (+y) of the cube outwards at later times.
    base = make(still)
    points = np.array(base.points)
    left = CUBE_POINTS[:, 1] > 0
    points[1:, left, 1] += 0.2
    lopsided = jm.Trajectory(
        ts=base.ts,
        points=jnp.asarray(points),
        com=base.com,
        frame=base.frame,
        contact=base.contact,
        finite=base.finite,
    )
    assert value("asymmetry", lopsided) == pytest.approx(0.2 * 4 / 5, rel=1e-3)
    # Mirrored across the horizontal plane, each point meets the one above or below it,
    # which moved the same way: no up-down asymmetry.
    assert value("asymmetry", lopsided, axis="up") == pytest.approx(0.0, abs=1e-5)


def test_objective_weights_and_non_finite_runs():
    tr = make(line([0, 0, 0.5], [2.0, 0.0, 0.5]))
    objective = jm.Objective(
        {"forward": 1.5, "upright": -10.0, "height": {"term": "max_height", "weight": 2.0}}
    )
    assert float(objective(tr)) == pytest.approx(3.0)
    assert set(objective.values(tr)) == {"forward", "upright", "height"}
    broken = jm.Trajectory(
        ts=tr.ts,
        points=tr.points,
        com=tr.com,
        frame=tr.frame,
        contact=tr.contact,
        finite=jnp.asarray(False),
    )
    assert float(objective(broken)) == -np.inf
    nan_com = jm.Trajectory(
        ts=tr.ts,
        points=tr.points,
        com=tr.com.at[-1, 0].set(jnp.nan),
        frame=tr.frame,
        contact=tr.contact,
        finite=jnp.asarray(True),
    )
    assert float(objective(nan_com)) == -np.inf


def test_objective_round_trips_and_is_vmappable():
    spec = {
        "forward": 1.0,
        "upright": {"weight": -10.0, "max_degrees": 30.0},
        "roll": {"term": "rotation", "weight": -0.5, "axis": "forward"},
    }
    objective = jm.Objective(spec)
    assert jm.Objective(objective.to_dict()).spec == objective.spec
    trs = [make(line([0, 0, 0.5], [d, 0, 0.5])) for d in (1.0, 2.0, 3.0)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trs)
    np.testing.assert_allclose(np.asarray(jax.vmap(objective)(batch)), [1.0, 2.0, 3.0], rtol=1e-6)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"forwards": 1.0}, r"'forwards': unknown term 'forwards'; allowed: .*forward"),
        ({"forward": "1"}, r"'forward': weight = '1'; allowed: a finite number"),
        (
            {"upright": {"weight": -1, "max_tilt": 3}},
            r"unknown option 'max_tilt'; allowed: term, weight, max_degrees",
        ),
        ({"upright": {"max_degrees": 3}}, r"must give its weight"),
        (
            {"upright": {"weight": 1, "max_degrees": "x"}},
            r"option max_degrees = 'x'; allowed: a number",
        ),
        ({"x": {"term": "nope", "weight": 1}}, r"unknown term 'nope'"),
        ({}, r"non-empty"),
    ],
)
def test_bad_objectives_raise(spec, message):
    with pytest.raises(ValueError, match=message):
        jm.Objective(spec)


def test_registering_a_term():
    name = "test_final_height"
    if name not in jm.objective_terms():

        @jm.register_term(name)
        def final_height(trajectory, offset: float = 0.0):
            """Final height of the centre of mass plus `offset`."""
            return trajectory.com[-1, 2] + offset

    assert jm.objective_terms()[name].options == {"offset": 0.0}
    tr = make(line([0, 0, 0.5], [0, 0, 1.5]))
    assert float(jm.Objective({name: {"weight": 2.0, "offset": 1.0}})(tr)) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="already registered"):
        jm.register_term(name)(lambda trajectory: trajectory.com[-1, 2])


def slide(start, end, contact, t=11):
    """One point moving in a straight line with the given contact pattern (t,) or (t, 1)."""
    contact = np.asarray(contact, bool).reshape(t, 1)
    return make(line(start, end, t), contact=contact, shape=ONE_POINT)


def test_contact_distance_counts_only_travel_in_contact_at_both_ends():
    always = np.ones(11, bool)
    assert value("contact_distance", slide([0, 0, 0], [1, 0, 0], always)) == pytest.approx(
        1.0, rel=ACCUMULATED_RTOL
    )
    # Horizontal length only: a 3-4-5 slide that also sinks counts 5, not its 3D length.
    assert value("contact_distance", slide([0, 0, 0], [3, 4, -1], always)) == pytest.approx(
        5.0, rel=ACCUMULATED_RTOL
    )
    assert value("contact_distance", slide([0, 0, 0.5], [1, 0, 0.5], ~always)) == 0
    # Contact over samples 2..5 (4 samples): only the 3 intervals inside it count; the
    # intervals where contact starts (1 -> 2) and ends (5 -> 6) count nothing.
    window = np.zeros(11, bool)
    window[2:6] = True
    assert value("contact_distance", slide([0, 0, 0], [1, 0, 0], window)) == pytest.approx(
        0.3, rel=ACCUMULATED_RTOL
    )
    # Hopping: contact at every other sample, so every interval starts or ends a contact.
    hopping = np.arange(11) % 2 == 0
    assert value("contact_distance", slide([0, 0, 0], [1, 0, 0], hopping)) == 0


def test_contact_distance_sums_over_points_like_a_python_loop():
    rng = np.random.default_rng(0)
    t, n = 30, 5
    points = rng.normal(size=(t, n, 3))
    contact = rng.random((t, n)) < 0.6
    expected = 0.0
    for k in range(t - 1):
        for i in range(n):
            if contact[k, i] and contact[k + 1, i]:
                expected += np.hypot(*(points[k + 1, i, :2] - points[k, i, :2]))
    tr = make(np.zeros((t, 3)), contact=contact, shape=ONE_POINT)
    tr = jm.Trajectory(
        ts=tr.ts,
        points=jnp.asarray(points),
        com=tr.com,
        frame=tr.frame,
        contact=tr.contact,
        finite=tr.finite,
    )
    assert value("contact_distance", tr) == pytest.approx(expected, rel=ACCUMULATED_RTOL)
    # A rigid cube sliding 1 m with its 4 bottom points down: 4 points, 1 m each.
    cube = make(line([0, 0, 0.5], [0, 1, 0.5]))
    assert value("contact_distance", cube) == pytest.approx(4.0, rel=ACCUMULATED_RTOL)


@pytest.mark.parametrize("direction", [1.0, -1.0])
@pytest.mark.parametrize("samples", [4, 5, 9, 41, 200])
def test_rotations_counts_turns_about_the_lateral_axis_whatever_the_spacing(samples, direction):
    """A cartwheel about world y (the left axis) by 2 pi, in steps from 120 degrees down."""
    still = np.full((samples, 3), 0.5)
    once = make(still, frames=spin(rot_y, direction * 2 * np.pi, samples))
    assert value("rotations", once) == pytest.approx(1.0, rel=ACCUMULATED_RTOL)
    twice = make(
        np.full((2 * samples - 1, 3), 0.5),
        frames=spin(rot_y, direction * 4 * np.pi, 2 * samples - 1),
    )
    assert value("rotations", twice) == pytest.approx(2.0, rel=ACCUMULATED_RTOL)


def test_rotations_ignores_rocking_and_other_axes():
    # Rocking about the lateral axis, 0 -> +60 -> -60 -> 0 degrees, three times.
    swing = np.concatenate(
        [np.linspace(0, 60, 7), np.linspace(60, -60, 13)[1:], np.linspace(-60, 0, 7)[1:-1]]
    )
    angles = np.deg2rad(np.concatenate([np.tile(swing, 3), [0.0]]))
    rocking = make(np.full((angles.size, 3), 0.5), frames=np.stack([rot_y(a) for a in angles]))
    assert value("rotation", rocking) > 2 * np.pi  # it did turn a lot, back and forth
    assert value("rotations", rocking) == pytest.approx(0.0, abs=CANCELLED_ATOL)
    still = np.full((41, 3), 0.5)
    assert value("rotations", make(still, frames=spin(rot_z, 2 * np.pi))) == pytest.approx(
        0.0, abs=CANCELLED_ATOL
    )
    assert value("rotations", make(still, frames=spin(rot_x, 2 * np.pi))) == pytest.approx(
        0.0, abs=CANCELLED_ATOL
    )
    # The lateral axis is the body's, not world y: facing +y, the left axis is world -x.
    facing_y = np.stack([rot_x(a) @ rot_z(np.pi / 2) for a in np.linspace(0, 2 * np.pi, 41)])
    assert value("rotations", make(still, frames=facing_y)) == pytest.approx(
        1.0, rel=ACCUMULATED_RTOL
    )


@pytest.mark.parametrize("samples", [4, 7, 61])
def test_heading_is_the_signed_unwrapped_turn_of_the_forward_axis(samples):
    still = np.full((samples, 3), 0.5)
    for degrees in (90.0, -90.0, 270.0, -270.0, 300.0):
        turn = make(still, frames=spin(rot_z, np.deg2rad(degrees), samples))
        assert value("heading", turn) == pytest.approx(np.deg2rad(degrees), rel=ACCUMULATED_RTOL)
        assert value("heading", turn, absolute=True) == pytest.approx(
            np.deg2rad(abs(degrees)), rel=ACCUMULATED_RTOL
        )
        # An upright turn: the same as the net rotation about the vertical.
        assert value("heading", turn) == pytest.approx(
            value("net_yaw", turn, signed=True), rel=ACCUMULATED_RTOL
        )
    # Crossing the -pi / pi cut of atan2: from 170 to 190 degrees is +20 degrees.
    across = make(
        still, frames=np.stack([rot_z(a) for a in np.deg2rad(np.linspace(170, 190, samples))])
    )
    assert value("heading", across) == pytest.approx(np.deg2rad(20), rel=ACCUMULATED_RTOL)


def test_heading_follows_the_forward_axis_not_the_vertical_spin():
    still = np.full((41, 3), 0.5)
    # Pitched 45 degrees nose down, then rolled a quarter turn about its own forward axis:
    # the forward axis never moves, but the angular velocity has a vertical component.
    rolled = np.stack([rot_y(np.pi / 4) @ rot_x(a) for a in np.linspace(0, np.pi / 2, 41)])
    tr = make(still, frames=rolled)
    assert value("heading", tr) == pytest.approx(0.0, abs=CANCELLED_ATOL)
    assert value("net_yaw", tr, signed=True) == pytest.approx(
        -np.pi / 2 * np.sin(np.pi / 4), rel=ACCUMULATED_RTOL
    )
    # A somersault points the forward axis straight down on the way: no heading change.
    assert value("heading", make(still, frames=spin(rot_y, 2 * np.pi))) == pytest.approx(
        0.0, abs=CANCELLED_ATOL
    )


def motions():
    """A few varied motions of the cube: sliding, pitching, turning, all at once. The pitch
    stays under 90 degrees: where the forward axis passes vertical, `heading` jumps by pi."""
    t = 21
    out = []
    for k in range(4):
        com = line([0, 0, 0.5 - 0.01 * k], [0.3 * k, 0.2, 0.5 - 0.01 * k], t)
        frames = np.stack(
            [rot_z(0.4 * k * s) @ rot_y((k - 1.5) * 0.8 * s) for s in np.linspace(0, 1, t)]
        )
        out.append(make(com, frames=frames))
    return out


NEW_TERMS = ["contact_distance", "rotations", "heading", "heading_deviation", "final_spin"]
# heading_deviation is |angle|, maximised over samples: at a motion that never turns (the
# first of `motions`) it sits on the kink at 0, where central differences give 0 and the
# gradient a one-sided slope, as for `sideways`.
SMOOTH_TERMS = [n for n in NEW_TERMS if n != "heading_deviation"] + ["rotation", "final_tilt"]


@pytest.mark.parametrize("name", NEW_TERMS)
def test_new_terms_vmap_equals_a_python_loop_and_jit_equals_no_jit(name):
    fn = jm.objective_terms()[name].fn
    trs = motions()
    loop = np.array([float(fn(tr)) for tr in trs])
    assert np.ptp(loop) > 0  # the motions differ in this term
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trs)
    np.testing.assert_allclose(
        np.asarray(jax.jit(jax.vmap(fn))(batch)), loop, rtol=ACCUMULATED_RTOL
    )


@pytest.mark.parametrize("name", SMOOTH_TERMS)
def test_new_terms_have_finite_gradients_that_match_finite_differences(name, x64):
    fn = jm.objective_terms()[name].fn

    @jax.jit
    def f(points, frame, tr):
        return fn(
            jm.Trajectory(
                ts=tr.ts,
                points=points,
                com=tr.com,
                frame=frame,
                contact=tr.contact,
                finite=tr.finite,
            )
        )

    # Standing still (points resting, zero rotation) and a somersault (forward axis vertical
    # at two samples): where sqrt and atan2 have singular slopes, the gradient stays finite.
    grad = jax.jit(jax.grad(f, argnums=(0, 1)))
    still = make(np.full((11, 3), 0.5))
    flip = make(np.full((5, 3), 0.5), frames=spin(rot_y, 2 * np.pi, 5))
    for tr in (still, flip):
        for g in grad(tr.points, tr.frame, tr):
            assert np.all(np.isfinite(np.asarray(g)))
    rng = np.random.default_rng(1)
    for tr in motions():
        grads = grad(tr.points, tr.frame, tr)
        dp, df = rng.normal(size=tr.points.shape), rng.normal(size=tr.frame.shape)
        plus = f(tr.points + FD_STEP * dp, tr.frame + FD_STEP * df, tr)
        minus = f(tr.points - FD_STEP * dp, tr.frame - FD_STEP * df, tr)
        numeric = (float(plus) - float(minus)) / (2 * FD_STEP)
        analytic = float(jnp.sum(grads[0] * dp) + jnp.sum(grads[1] * df))
        assert analytic == pytest.approx(numeric, rel=FD_RTOL, abs=FD_ATOL)


def test_new_terms_in_an_objective():
    # One point sliding 1 m in contact while the body turns a quarter turn clockwise.
    tr = make(
        line([0, 0, 0], [1.0, 0, 0]),
        frames=spin(rot_z, -np.pi / 2, 11),
        contact=np.ones((11, 1), bool),
        shape=ONE_POINT,
    )
    objective = jm.Objective(
        {"contact_distance": 1.0, "turn": {"term": "heading", "weight": 2.0, "absolute": True}}
    )
    assert float(objective(tr)) == pytest.approx(1.0 + 2 * np.pi / 2, rel=ACCUMULATED_RTOL)
    assert jm.Objective(objective.to_dict()).spec == objective.spec


def biped(contact, com_z=None):
    """Two point feet (left at y = +0.1, right at y = -0.1) on the floor and a head 1 m up,
    standing still facing +x, with the feet's contact flags `contact` `(samples, 2)` and the
    centre of mass at heights `com_z` (default 0.5 throughout)."""
    contact = np.asarray(contact, bool)
    t = contact.shape[0]
    points = np.broadcast_to([[0.0, 0.1, 0.0], [0.0, -0.1, 0.0], [0.0, 0.0, 1.0]], (t, 3, 3))
    com_z = np.full(t, 0.5) if com_z is None else np.asarray(com_z, float)
    return jm.Trajectory(
        ts=jnp.linspace(0.0, 1.0, t),
        points=jnp.asarray(points),
        com=jnp.asarray(np.stack([np.zeros(t), np.zeros(t), com_z], axis=1)),
        frame=jnp.asarray(np.broadcast_to(np.eye(3), (t, 3, 3))),
        contact=jnp.asarray(np.concatenate([contact, np.zeros((t, 1), bool)], axis=1)),
        finite=jnp.asarray(True),
    )


def test_steps_counts_alternating_touch_downs():
    # Left lifts and lands, right lifts and lands, left lifts and lands twice (a chatter:
    # one step), then both land at once (no step, and the alternation starts afresh), then
    # left lands alone (a step again).
    down = [(0, 0), (1, 1), (0, 1), (1, 1), (1, 0), (1, 1), (0, 1), (1, 1), (0, 1), (1, 1)]
    down += [(0, 0), (1, 1), (0, 1), (1, 1)]
    tr = biped(down)
    assert value("steps", tr) == 4.0
    assert value("steps", tr, cap=2.0) == 2.0
    # The start counts as its next sample's state: feet resting without flags never land.
    assert value("steps", biped([(0, 0)] + [(1, 1)] * 5)) == 0.0
    # Only the steps before a fall count with until_fall (below 60% from the 5th sample).
    z = [0.5] * 4 + [0.2] * (len(down) - 4)
    assert value("steps", biped(down, z), until_fall=True) == 1.0
    # A fall at 85%: a dip to 80% from the 3rd sample ends the count there.
    z = [0.5] * 2 + [0.4] * (len(down) - 2)
    assert value("steps", biped(down, z), until_fall=True) == 4.0
    assert value("steps", biped(down, z), until_fall=True, fall_share=0.85) == 0.0
    assert value("steps", biped(down, z)) == 4.0


@pytest.mark.parametrize("seed", range(5))
def test_steps_agrees_with_the_walk_checks_count(seed):
    down = np.random.default_rng(seed).random((40, 2)) < 0.6
    taken, _ = jm.checks.steps(np.asarray(biped(down).contact), ((0,), (1,)))
    assert value("steps", biped(down)) == taken


def test_heading_deviation_allows_a_margin():
    veer = np.deg2rad([0, 10, 25, 40, 30, 15, 0, 0, 0, 0, 0])
    tr = make(np.zeros((11, 3)), frames=np.stack([rot_z(a) for a in veer]))
    allowed = value("heading_deviation", tr, allowed_degrees=15.0)
    assert allowed == pytest.approx(np.deg2rad(25), rel=ACCUMULATED_RTOL)
    assert value("heading_deviation", tr, allowed_degrees=45.0) == 0.0
