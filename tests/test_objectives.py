"""Objective terms on hand-built trajectories with known answers, and `Objective` itself."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmotion as jm

CUBE_POINTS = np.asarray(jm.lattices.cube().points)


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


def test_max_height():
    z = 0.5 + np.sin(np.linspace(0, np.pi, 21)) * 2.0
    tr = make(np.stack([np.zeros(21), np.zeros(21), z], axis=1))
    assert value("max_height", tr) == pytest.approx(2.0)


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
    assert value("contact_time", tr) == pytest.approx(3 * 0.2)
    assert value("on_ground_at_end", tr) == 1
    assert value("on_ground_at_end", tr, min_points=4) == 0


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
