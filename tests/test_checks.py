"""The motion checks accept hand-built trajectories that do the motion and reject ones that
do not."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmotion as jm

CUBE = np.asarray(jm.lattices.cube().points)


def rot(axis, angle):
    c, s = math.cos(angle), math.sin(angle)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def trajectory(duration, com, angles=None, axis="y", contact=None):
    """A rigid cube following `com(t)` and turning by `angles(t)` about a world axis."""
    ts = np.linspace(0, duration, int(duration / 0.02) + 1)
    com = np.array([com(t) for t in ts])
    frames = np.array([rot(axis, angles(t) if angles else 0.0) for t in ts])
    rel = CUBE - CUBE.mean(0)
    points = com[:, None] + np.einsum("tij,nj->tni", frames, rel)
    if contact is None:
        contact = points[..., 2] < 1e-6
    else:
        contact = np.array([contact(t) for t in ts])
    return recorded(ts, points, com, frames, contact)


def recorded(ts, points, com, frames, contact):
    """A finite trajectory of these samples."""
    return jm.Trajectory(
        ts=jnp.asarray(ts),
        points=jnp.asarray(points),
        com=jnp.asarray(com),
        frame=jnp.asarray(frames),
        contact=jnp.asarray(contact),
        finite=jnp.asarray(True),
    )


def hopping(t, period=1.0, airborne=0.3):
    """All points down except for the first `airborne` of every period (after t = 0)."""
    return np.full(8, not (0 < (t % period) < airborne))


def hop(speed, height=0.1, period=1.0, airborne=0.3):
    """The unit cube's centre of mass (its bottom face on the floor at z = 0.5) travelling
    along x at `speed`, lifted `height` off the floor over the first `airborne` of every
    period (after t = 0), in step with `hopping`."""
    return lambda t: [speed * t, 0, 0.5 + (height if 0 < (t % period) < airborne else 0.0)]


def test_leap_accepts_a_leaping_spider_and_rejects_a_shuffle_or_a_fall():
    leaper = trajectory(4.5, hop(1.0), contact=hopping)
    result = jm.checks.leap(leaper, body_length=1.0, period=1.0)
    assert result.passed, result.summary()
    assert result.figures["airborne_periods"] == 5  # periods 0..4 each start with a leap
    assert result.figures["forward_body_lengths"] == pytest.approx(4.5)
    shuffle = trajectory(4.5, lambda t: [t, 0, 0.5], contact=lambda t: np.ones(8, bool))
    assert not jm.checks.leap(shuffle, body_length=1.0, period=1.0)
    short = trajectory(4.5, hop(0.5), contact=hopping)
    assert not jm.checks.leap(short, body_length=1.0, period=1.0)
    # 2.25 m is 4.5 of its lengths (and the 0.1 m hops clear 0.05 of 0.5 m).
    assert jm.checks.leap(short, body_length=0.5, period=1.0)
    fallen = trajectory(4.5, hop(1.0), angles=lambda t: 0.3 * t, contact=hopping)
    result = jm.checks.leap(fallen, body_length=1.0, period=1.0)
    assert not result and result.figures["max_tilt_degrees"] > 45


def test_somersault_accepts_a_backward_flip_and_rejects_a_forward_one_or_a_bad_landing():
    # 1.05 turns backwards: lands 18 degrees past upright.
    back = trajectory(
        3.0, lambda t: [t, 0, 0.5 + np.sin(np.pi * t / 3)], angles=lambda t: -2.1 * np.pi * t / 3
    )
    result = jm.checks.somersault(back)
    assert result.passed, result.summary()
    assert result.figures["backward_turns"] == pytest.approx(1.05, abs=1e-3)
    assert result.figures["final_tilt_degrees"] == pytest.approx(18.0, abs=0.1)
    front = trajectory(
        3.0, lambda t: [t, 0, 0.5 + np.sin(np.pi * t / 3)], angles=lambda t: 2 * np.pi * t / 3
    )
    assert not jm.checks.somersault(front)
    crooked = trajectory(
        3.0,
        lambda t: [t, 0, 0.5 + np.sin(np.pi * t / 3)],
        angles=lambda t: -(2 * np.pi + 0.8) * t / 3,
    )
    result = jm.checks.somersault(crooked)
    assert not result and result.figures["final_tilt_degrees"] > 30
    backwards_travel = trajectory(
        3.0, lambda t: [-t, 0, 0.5 + np.sin(np.pi * t / 3)], angles=lambda t: -2 * np.pi * t / 3
    )
    assert not jm.checks.somersault(backwards_travel)


def test_pirouette_accepts_a_spin_in_place_and_rejects_drift_tilt_or_too_little_turn():
    spin = trajectory(
        3.0, lambda t: [0.1 * t, 0, 0.5], angles=lambda t: 2.2 * np.pi * t / 3, axis="z"
    )
    result = jm.checks.pirouette(spin, body_length=1.0)
    assert result.passed, result.summary()
    assert result.figures["turns"] == pytest.approx(1.1, abs=1e-3)
    drift = trajectory(
        3.0, lambda t: [0.3 * t, 0, 0.5], angles=lambda t: 2.2 * np.pi * t / 3, axis="z"
    )
    assert not jm.checks.pirouette(drift, body_length=1.0)
    half = trajectory(3.0, lambda t: [0, 0, 0.5], angles=lambda t: np.pi * t / 3, axis="z")
    assert not jm.checks.pirouette(half, body_length=1.0)
    airborne_end = trajectory(
        3.0, lambda t: [0, 0, 0.5 + t], angles=lambda t: 2.2 * np.pi * t / 3, axis="z"
    )
    assert not jm.checks.pirouette(airborne_end, body_length=1.0)


def test_a_run_that_blew_up_fails_and_bad_arguments_raise():
    leaper = trajectory(4.5, hop(1.0), contact=hopping)
    broken = jm.Trajectory(
        ts=leaper.ts,
        points=leaper.points,
        com=leaper.com,
        frame=leaper.frame,
        contact=leaper.contact,
        finite=jnp.asarray(False),
    )
    result = jm.checks.leap(broken, body_length=1.0, period=1.0)
    assert not result and "FAIL  the simulation stayed finite" in result.summary()
    with pytest.raises(ValueError, match=r"body_length = 0.0; allowed: a number > 0"):
        jm.checks.leap(leaper, body_length=0.0, period=1.0)
    batched = jm.Trajectory(
        *(
            jnp.stack([a, a])
            for a in (
                leaper.ts,
                leaper.points,
                leaper.com,
                leaper.frame,
                leaper.contact,
                leaper.finite,
            )
        )
    )
    with pytest.raises(ValueError, match="batched"):
        jm.checks.somersault(batched)


def test_shuffle_needs_a_point_on_the_floor_after_the_start_and_forward_travel():
    # Resting exactly on the floor at t = 0 is not contact; the check starts after it.
    grounded = lambda t: np.full(8, t > 0)
    shuffler = trajectory(5.0, lambda t: [0.4 * t, 0, 0.5], contact=grounded)
    result = jm.checks.shuffle(shuffler, body_length=1.0)
    assert result.passed, result.summary()
    assert result.figures["grounded_share"] == 1.0
    hopper = trajectory(5.0, hop(0.4), contact=hopping)
    assert not jm.checks.shuffle(hopper, body_length=1.0)
    slow = trajectory(5.0, lambda t: [0.1 * t, 0, 0.5], contact=grounded)
    assert not jm.checks.shuffle(slow, body_length=1.0)


def test_cartwheel_needs_a_full_turn_about_the_lateral_axis_and_forward_travel():
    wheel = trajectory(2.0, lambda t: [t, 0, 0.5], angles=lambda t: 1.1 * math.pi * t)
    result = jm.checks.cartwheel(wheel, body_length=1.0)
    assert result.passed, result.summary()
    assert result.figures["turns"] == pytest.approx(1.1, rel=1e-5)
    rocking = trajectory(2.0, lambda t: [t, 0, 0.5], angles=lambda t: math.sin(6 * t))
    assert not jm.checks.cartwheel(rocking, body_length=1.0)
    spin_in_place = trajectory(2.0, lambda t: [0, 0, 0.5], angles=lambda t: 1.1 * math.pi * t)
    assert not jm.checks.cartwheel(spin_in_place, body_length=1.0)
    pirouette = trajectory(2.0, lambda t: [t, 0, 0.5], angles=lambda t: 2 * math.pi * t, axis="z")
    assert not jm.checks.cartwheel(pirouette, body_length=1.0)


def test_bound_needs_airborne_phases_and_two_body_lengths():
    bounder = trajectory(5.0, hop(0.6), contact=hopping)
    result = jm.checks.bound(bounder, body_length=1.0)
    assert result.passed, result.summary()
    assert result.figures["airborne_phases"] == 5  # each of periods 0..4 starts with a leap
    assert result.figures["max_clearance_body_lengths"] == pytest.approx(0.1)
    # Skimming: no contact flag (every point 2 mm up) is not flying.
    skimmer = trajectory(5.0, hop(0.6, height=0.002), contact=hopping)
    result = jm.checks.bound(skimmer, body_length=1.0)
    assert not result and result.figures["airborne_phases"] == 0
    # Hops of one 20 ms sample are shorter than a flight's 40 ms.
    flicks = trajectory(5.0, hop(0.6, airborne=0.03), contact=lambda t: hopping(t, airborne=0.03))
    assert not jm.checks.bound(flicks, body_length=1.0)
    assert jm.checks.bound(flicks, body_length=1.0, min_flight_seconds=0.02)
    walker = trajectory(5.0, lambda t: [0.6 * t, 0, 0.5])
    assert not jm.checks.bound(walker, body_length=1.0)
    assert not jm.checks.bound(bounder, body_length=2.0)  # 3 m is 1.5 of its lengths


def test_jump_needs_every_point_clear_of_the_floor_at_once_and_an_upright_landing():
    # The unit cube's bottom face rests on the floor at a CoM height of 0.5: a jump of
    # height h lifts every point by h at the top and lands at t = 1.
    def jumper(h, tilt=0.0, duration=1.0):
        return trajectory(
            duration,
            lambda t: [0.2 * t, 0, 0.5 + h * max(0.0, math.sin(math.pi * t))],
            angles=lambda t: tilt * t,
        )

    result = jm.checks.jump(jumper(0.3), body_length=1.0)
    assert result.passed, result.summary()
    assert result.figures["clearance_m"] == pytest.approx(0.3, rel=1e-6)
    assert not jm.checks.jump(jumper(0.2), body_length=1.0)  # 0.2 < 0.25 body lengths
    assert jm.checks.jump(jumper(0.2), body_length=0.5)  # 0.4 of its lengths
    # Lands 40 degrees off upright (the cube turns as it flies).
    crooked = jm.checks.jump(jumper(0.3, tilt=math.radians(40)), body_length=1.0)
    assert not crooked and crooked.figures["final_tilt_degrees"] == pytest.approx(40, abs=0.1)
    still_up = jm.checks.jump(jumper(0.3, duration=0.5), body_length=1.0)  # ends at the top
    assert not still_up and still_up.figures["on_floor_at_end"] == 0.0


def biped(
    duration=5.0, speed=0.8, stride=0.5, heading=lambda t: 0.0, com_z=lambda t: 1.0, down=None
):
    """Three points, a left foot, a right foot and a head 1.7 m up (the standing height),
    walking along x at `speed` with the heading `heading(t)` (rad about z); by default each
    foot is down for 60% of every `stride` s, the right half a stride after the left."""
    ts = np.linspace(0, duration, int(duration / 0.02) + 1)
    com = np.array([[speed * t, 0.0, com_z(t)] for t in ts])
    frames = np.array([rot("z", heading(t)) for t in ts])
    rel = np.array([[0.0, 0.1, -1.0], [0.0, -0.1, -1.0], [0.0, 0.0, 0.7]])
    points = com[:, None] + np.einsum("tij,nj->tni", frames, rel)
    if down is None:
        down = lambda t: [(t / stride) % 1 < 0.6, ((t / stride) + 0.5) % 1 < 0.6, False]
    contact = np.array([down(t) for t in ts], dtype=bool)
    return recorded(ts, points, com, frames, contact)


FEET = ((0,), (1,))


def test_walk_accepts_alternating_steps_and_rejects_hops_turns_and_falls():
    walker = biped()
    result = jm.checks.walk(walker, feet=FEET)
    assert result.passed, result.summary()
    # 4 m along x over a standing height of 1.7 m; both feet start down, then a step every
    # half stride: the right foot lands at 0.25, 0.75, ..., 4.75 s, the left at 0.5, ...,
    # 5.0 s.
    assert result.figures["forward_heights"] == pytest.approx(4.0 / 1.7)
    assert result.figures["standing_height_m"] == pytest.approx(1.7)
    assert result.figures["steps"] == result.figures["touch_downs"] == 20
    # Both feet landing together (a two-footed hop): touch-downs but no step.
    hop = biped(down=lambda t: [(t / 0.5) % 1 < 0.6] * 2 + [False])
    result = jm.checks.walk(hop, feet=FEET)
    assert not result and result.figures["steps"] == 0 and result.figures["touch_downs"] == 20
    # One foot only, the other held up: its first landing is one step, the rest repeat it.
    limp = biped(down=lambda t: [(t / 0.5) % 1 < 0.6, False, False])
    result = jm.checks.walk(limp, feet=FEET)
    assert not result and result.figures["steps"] == 1
    # A steady turn of 45 degrees over the walk leaves the heading criterion.
    turning = jm.checks.walk(biped(heading=lambda t: math.radians(9.0) * t), feet=FEET)
    assert not turning and turning.figures["max_heading_degrees"] == pytest.approx(45.0)
    # A crouch to half the starting height of the centre of mass is a fall.
    crouch = jm.checks.walk(biped(com_z=lambda t: 1.0 - 0.1 * t), feet=FEET)
    assert not crouch and crouch.figures["min_com_height_share"] == pytest.approx(0.5)
    # Too slow: 0.4 m/s for 5 s is 1.18 standing heights.
    assert not jm.checks.walk(biped(speed=0.4), feet=FEET)
    with pytest.raises(ValueError, match="walk needs the body's feet"):
        jm.checks.walk(walker, feet=())


def test_walk_counts_a_chattering_foot_once():
    # From 1 s on, the left foot flickers up and down within its stance: each flicker is a
    # touch-down, no step; the walk still alternates.
    def chatter(t):
        phase = (t / 0.5) % 1
        left = phase < 0.6 and not (t > 1 and 0.2 < phase < 0.25)
        return [left, ((t / 0.5) + 0.5) % 1 < 0.6, False]

    result = jm.checks.walk(biped(down=chatter), feet=FEET)
    assert result.passed, result.summary()
    assert result.figures["touch_downs"] > result.figures["steps"] == 20


def turned(motion, degrees, start):
    """`motion` turned about the vertical by `degrees` and moved so that its centre of mass
    starts above `start` (x, y)."""
    r = rot("z", math.radians(degrees))
    com = np.asarray(motion.com) @ r.T
    shift = np.array([start[0] - com[0, 0], start[1] - com[0, 1], 0.0])
    points = np.asarray(motion.points) @ r.T + shift
    frames = np.einsum("ij,tjk->tik", r, np.asarray(motion.frame))
    return recorded(motion.ts, points, com + shift, frames, motion.contact)


def walk_turn_walk(turn_degrees=90.0, turn_com_z=lambda t: 1.0, again_com_z=lambda t: 1.0):
    """A walk along x, a steady turn of `turn_degrees` stepping in place, and a walk along
    the new heading, each starting where the one before ended."""
    walk = biped()
    end = np.asarray(walk.com)[-1, :2]
    rate = math.radians(turn_degrees) / 5.0
    turn = turned(biped(speed=0.0, heading=lambda t: rate * t, com_z=turn_com_z), 0.0, end)
    again = turned(biped(com_z=again_com_z), turn_degrees, end)
    return [walk, turn, again]


def test_walk_turn_walk_needs_two_walks_a_turn_and_no_fall():
    result = jm.checks.walk_turn_walk(walk_turn_walk(), feet=FEET)
    assert result.passed, result.summary()
    assert result.figures["turn_degrees"] == pytest.approx(90.0, rel=1e-4)
    # The second walk goes along its own start heading (90 degrees from the first's).
    assert result.figures["stage_3_forward_heights"] == pytest.approx(4.0 / 1.7)
    assert result.figures["stage_1_walk_passed"] == result.figures["stage_3_walk_passed"] == 1
    assert list(result.criteria)[1:] == [
        "stage 1 walks (the walk check passed)",
        "stage 2 turns >= 45 degrees (got 90.0)",
        "stage 3 walks (the walk check passed)",
        "centre of mass never below 60% of its height at the start of stage 1 (min 100%, in "
        "stage 1)",
    ]
    # Either way round.
    assert jm.checks.walk_turn_walk(walk_turn_walk(turn_degrees=-60.0), feet=FEET)
    # A turn of 30 degrees is too little.
    small = jm.checks.walk_turn_walk(walk_turn_walk(turn_degrees=30.0), feet=FEET)
    assert not small and small.criteria["stage 2 turns >= 45 degrees (got 30.0)"] is False
    # Sinking to half the height while turning is a fall, though both walks pass.
    sink = jm.checks.walk_turn_walk(walk_turn_walk(turn_com_z=lambda t: 1.0 - 0.1 * t), feet=FEET)
    assert not sink and sink.figures["min_com_height_share"] == pytest.approx(0.5)
    assert sink.figures["stage_1_walk_passed"] == sink.figures["stage_3_walk_passed"] == 1
    assert "(min 50%, in stage 2)" in list(sink.criteria)[-1]
    # A last walk at 55% of the first start's height passes its own walk check (it holds its
    # own start height) but not the sequence's fall criterion.
    low = jm.checks.walk_turn_walk(walk_turn_walk(again_com_z=lambda t: 0.55), feet=FEET)
    assert not low and low.figures["stage_3_walk_passed"] == 1
    assert low.figures["stage_3_min_com_height_share"] == 1.0  # the walk's, of its own start
    assert low.figures["stage_3_min_com_height_share_of_stage_1"] == pytest.approx(0.55)


def test_walk_turn_walk_reports_which_walk_failed():
    walk, turn, _ = walk_turn_walk()
    # The last "walk" stands still after the turn: its walk check fails, and says why.
    still = turned(biped(speed=0.0), 90.0, np.asarray(turn.com)[-1, :2])
    result = jm.checks.walk_turn_walk([walk, turn, still], feet=FEET)
    assert not result and result.figures["stage_3_walk_passed"] == 0
    failed = [text for text, ok in result.criteria.items() if not ok]
    assert len(failed) == 1 and failed[0].startswith("stage 3 walks (the walk check failed: ")
    assert "travels forward >= 1.5 standing heights (got 0.00)" in failed[0]
    with pytest.raises(ValueError, match="walk_turn_walk checks 3 trajectories"):
        jm.checks.walk_turn_walk([walk, turn], feet=FEET)
    with pytest.raises(ValueError, match="walk_turn_walk needs the body's feet"):
        jm.checks.walk_turn_walk([walk, turn, still], feet=())
