"""Reproduction checks: does a motion really leap, somersault, pirouette, shuffle,
cartwheel, bound, jump, walk, hop or roll, and does a sequence walk, turn and walk again?

Each check is a function of one (unbatched) `Trajectory` with documented thresholds (a
sequence check, `walk_turn_walk`, of the stages' trajectories in order), and returns a
`CheckResult` that says which criteria held and what was measured. They encode the first
paper's Figures 7-9 (the spider's leap, the poodle's somersault, the table's pirouette) and
the second paper's Figures 9, 10 and 13-17 (Star-Man's shuffle, cartwheel and jump, Cujo's
bounding, Rex's and Bob's walks) and the third paper's Figures 3-6 (the snake's and the
Luxo lamp's hopping and rolling) as numbers a user can test their own results against.
Flight has one definition for all of them (`flights`).
"""

import math
from dataclasses import dataclass, field

import numpy as np

from ._objective.terms import FALL_SHARE, heading, net_yaw, rotation, rotations
from ._sim.trajectory import Trajectory


@dataclass(frozen=True)
class CheckResult:
    """The verdict of a motion check.

    - `name`: which check.
    - `passed`: whether every criterion held.
    - `figures`: what was measured (lengths in m or body lengths, angles in degrees).
    - `criteria`: each criterion, in words, and whether it held.
    """

    name: str
    passed: bool
    figures: dict[str, float] = field(default_factory=dict)
    criteria: dict[str, bool] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.passed

    def summary(self) -> str:
        """One line per criterion, marked pass or fail, then the verdict."""
        lines = [f"{'pass' if ok else 'FAIL'}  {text}" for text, ok in self.criteria.items()]
        lines.append(f"{self.name}: {'passed' if self.passed else 'failed'}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "passed": self.passed,
            "figures": dict(self.figures),
            "criteria": dict(self.criteria),
        }


def _single(trajectory: Trajectory, caller: str) -> dict[str, np.ndarray]:
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"{caller} needs a Trajectory; got {type(trajectory).__name__}")
    if np.ndim(trajectory.com) != 2:
        raise ValueError(
            f"{caller} checks one trajectory; this one is batched (com has shape "
            f"{np.shape(trajectory.com)}). Pick one: jax.tree_util.tree_map(lambda a: a[i], t)"
        )
    return {
        "ts": np.asarray(trajectory.ts, float),
        "com": np.asarray(trajectory.com, float),
        "frame": np.asarray(trajectory.frame, float),
        "contact": np.asarray(trajectory.contact, bool),
        "finite": bool(np.asarray(trajectory.finite)),
    }


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} = {value!r}; allowed: a number > 0")
    return value


def _tilt_degrees(frame: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(frame[:, 2, 2], -1.0, 1.0)))


def _forward(t: dict) -> float:
    heading = t["frame"][0, :2, 0]
    heading = heading / max(np.linalg.norm(heading), 1e-12)
    return float(np.dot(t["com"][-1, :2] - t["com"][0, :2], heading))


def _travel(t: dict, body_length: float, min_lengths: float) -> tuple[dict, dict]:
    """The figures and the criterion of "the centre of mass travels forward at least
    `min_lengths` body lengths", shared by the locomotion checks."""
    body_length = _positive("body_length", body_length)
    lengths = _forward(t) / body_length
    figures = {"forward_body_lengths": lengths, "forward_m": lengths * body_length}
    label = f"travels forward >= {min_lengths:g} body lengths (got {lengths:.2f})"
    return figures, {label: lengths >= min_lengths}


def _result(name: str, finite: bool, figures: dict, criteria: dict) -> CheckResult:
    criteria = {"the simulation stayed finite": finite, **criteria}
    return CheckResult(name, all(criteria.values()), figures, criteria)


FLIGHT_CLEARANCE = 0.05
"""A flight's clearance: every point at least this many body lengths above the floor."""
FLIGHT_SECONDS = 0.04
"""A flight's shortest duration, s (two samples at the usual 20 ms save interval)."""


def flights(
    trajectory: Trajectory,
    *,
    body_length: float,
    clearance: float = FLIGHT_CLEARANCE,
    min_seconds: float = FLIGHT_SECONDS,
) -> list[tuple[int, int]]:
    """The flight phases of a motion, the one definition of "airborne" every check uses:
    maximal runs of saved instants at which every point is at least `clearance` body
    lengths above the floor, lasting at least `min_seconds` (a run of `k` samples lasts `k`
    save intervals). Returns each flight's first and last sample index.

    A contact flag alone says too little: a point 1 mm above a penalty floor has none, so a
    body skimming the floor looked airborne. Off the floor means visibly off it.
    """
    clearance = float(clearance)
    if not (math.isfinite(clearance) and clearance >= 0):
        raise ValueError(f"clearance = {clearance!r}; allowed: a number >= 0 (body lengths)")
    body_length = _positive("body_length", body_length)
    ts = np.asarray(trajectory.ts, float)
    lowest = np.min(np.asarray(trajectory.points, float)[:, :, 2], axis=1)
    up = lowest >= clearance * body_length
    if clearance == 0:
        up &= ~np.any(np.asarray(trajectory.contact, bool), axis=1)
    up[0] = False  # the start, resting on the floor, is no flight
    interval = float(ts[1] - ts[0]) if len(ts) > 1 else 0.0
    out, start = [], None
    for i, flying in enumerate([*up.tolist(), False]):
        if flying and start is None:
            start = i
        elif not flying and start is not None:
            if (i - start) * interval >= min_seconds - 1e-9:
                out.append((start, i - 1))
            start = None
    return out


def leap(
    trajectory: Trajectory,
    *,
    body_length: float,
    period: float,
    min_lengths: float = 3.0,
    max_tilt_degrees: float = 45.0,
    min_airborne_periods: int = 3,
    clearance: float = FLIGHT_CLEARANCE,
    min_flight_seconds: float = FLIGHT_SECONDS,
) -> CheckResult:
    """The spider's leap (first paper, Figure 7): travels forward by leaps, staying upright.

    Passes when the centre of mass travels forward at least `min_lengths` body lengths over
    the trajectory, the body's up axis never tilts more than `max_tilt_degrees` from vertical,
    and at least `min_airborne_periods` of the controller's periods hold a flight (`flights`:
    every point `clearance` body lengths off the floor for `min_flight_seconds`).

    **Arguments:** the trajectory; `body_length` (m, e.g. `lattice.body_length`); the
    controller's `period` (s, `t_per`); the thresholds.
    """
    t = _single(trajectory, "leap")
    travel, far = _travel(t, body_length, min_lengths)
    period = _positive("period", period)
    tilt = float(_tilt_degrees(t["frame"]).max())
    phases = flights(
        trajectory, body_length=body_length, clearance=clearance, min_seconds=min_flight_seconds
    )
    periods = np.floor(t["ts"] / period + 1e-9).astype(int)
    airborne_periods = len({int(periods[i]) for a, b in phases for i in range(a, b + 1)})
    figures = {
        **travel,
        "max_tilt_degrees": tilt,
        "airborne_periods": float(airborne_periods),
        "flights": float(len(phases)),
        "periods": float(t["ts"][-1] / period),
    }
    steady = f"never tilts more than {max_tilt_degrees:g} degrees (max {tilt:.1f})"
    leaps = (
        f"flies (every point >= {clearance:g} body lengths up for >= {min_flight_seconds:g} s) "
        f"in >= {min_airborne_periods} periods (got {airborne_periods})"
    )
    criteria = {
        **far,
        steady: tilt <= max_tilt_degrees,
        leaps: airborne_periods >= min_airborne_periods,
    }
    return _result("leap", t["finite"], figures, criteria)


def somersault(
    trajectory: Trajectory,
    *,
    min_turns: float = 1.0,
    max_final_tilt_degrees: float = 30.0,
) -> CheckResult:
    """The poodle's backward somersault (first paper, Figure 8).

    Passes when the body frame turns at least `min_turns` full turns (net) backwards about its
    left (lateral) axis, the centre of mass ends ahead of where it started, and the body ends
    touching the floor with its up axis within `max_final_tilt_degrees` of vertical.
    "Backwards" is nose up and over: negative about the left axis (see the `rotation` term).
    """
    t = _single(trajectory, "somersault")
    turns = -float(rotation(trajectory, axis="left")) / (2 * math.pi)
    forward = _forward(t)
    final_tilt = float(_tilt_degrees(t["frame"])[-1])
    on_floor = bool(np.any(t["contact"][-1]))
    figures = {
        "backward_turns": turns,
        "forward_m": forward,
        "final_tilt_degrees": final_tilt,
        "on_floor_at_end": float(on_floor),
    }
    turned = f"turns >= {min_turns:g} times backwards about the lateral axis (got {turns:.2f})"
    upright = f"ends within {max_final_tilt_degrees:g} degrees of upright (got {final_tilt:.1f})"
    criteria = {
        turned: turns >= min_turns,
        f"moves forward (got {forward:.2f} m)": forward > 0,
        f"ends on the floor (got {on_floor})": on_floor,
        upright: final_tilt <= max_final_tilt_degrees,
    }
    return _result("somersault", t["finite"], figures, criteria)


def pirouette(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_turns: float = 1.0,
    max_tilt_degrees: float = 30.0,
    max_displacement_lengths: float = 0.5,
) -> CheckResult:
    """The table's pirouette (first paper, Figure 9): spins in place, upright.

    Passes when the net rotation about the vertical is at least `min_turns` full turns (either
    way), the up axis never tilts more than `max_tilt_degrees`, the centre of mass ends less
    than `max_displacement_lengths` body lengths (horizontally) from where it started, and the
    body touches the floor at the end.
    """
    t = _single(trajectory, "pirouette")
    body_length = _positive("body_length", body_length)
    turns = float(net_yaw(trajectory, signed=True)) / (2 * math.pi)
    tilt = float(_tilt_degrees(t["frame"]).max())
    shift = float(np.linalg.norm(t["com"][-1, :2] - t["com"][0, :2])) / body_length
    on_floor = bool(np.any(t["contact"][-1]))
    figures = {
        "turns": turns,
        "max_tilt_degrees": tilt,
        "displacement_body_lengths": shift,
        "on_floor_at_end": float(on_floor),
    }
    spun = f"turns >= {min_turns:g} times about the vertical (got {abs(turns):.2f})"
    steady = f"never tilts more than {max_tilt_degrees:g} degrees (max {tilt:.1f})"
    still = f"moves less than {max_displacement_lengths:g} body lengths (got {shift:.2f})"
    criteria = {
        spun: abs(turns) >= min_turns,
        steady: tilt <= max_tilt_degrees,
        still: shift < max_displacement_lengths,
        f"ends on the floor (got {on_floor})": on_floor,
    }
    return _result("pirouette", t["finite"], figures, criteria)


def shuffle(trajectory: Trajectory, *, body_length: float, min_lengths: float = 1.0) -> CheckResult:
    """Star-Man's shuffle (second paper, Figure 9): travels forward with some point always on
    the floor.

    Passes when the centre of mass travels forward at least `min_lengths` body lengths and at
    every saved instant after the start at least one point touches the floor.
    """
    t = _single(trajectory, "shuffle")
    travel, far = _travel(t, body_length, min_lengths)
    # The start is skipped: resting exactly on the floor (z = 0) is not contact yet.
    grounded = np.any(t["contact"][1:], axis=1)
    share = float(np.mean(grounded))
    figures = {**travel, "grounded_share": share}
    criteria = {
        **far,
        f"some point always on the floor (got {100 * share:.1f}% of instants)": bool(
            np.all(grounded)
        ),
    }
    return _result("shuffle", t["finite"], figures, criteria)


def cartwheel(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_turns: float = 1.0,
    min_lengths: float = 0.5,
) -> CheckResult:
    """Star-Man's cartwheel (second paper, Figure 10): turns over about the lateral axis
    while travelling forward.

    Passes when the body frame turns at least `min_turns` full turns (net, either way) about
    its left (lateral) axis and the centre of mass travels forward at least `min_lengths`
    body lengths.
    """
    t = _single(trajectory, "cartwheel")
    travel, far = _travel(t, body_length, min_lengths)
    turned, turns = _turned(trajectory, min_turns)
    return _result("cartwheel", t["finite"], {**turned, **travel}, {**turns, **far})


def _airborne(
    trajectory: Trajectory,
    body_length: float,
    clearance: float,
    min_flight_seconds: float,
    min_phases: int,
) -> tuple[dict, dict]:
    """The figures and the criterion of "flies in at least `min_phases` separate phases"
    (`flights`), shared by `bound` and `hop`."""
    phases = flights(
        trajectory, body_length=body_length, clearance=clearance, min_seconds=min_flight_seconds
    )
    label = (
        f"flies (every point >= {clearance:g} body lengths up for >= {min_flight_seconds:g} s) "
        f"in >= {min_phases} phases (got {len(phases)})"
    )
    return {"airborne_phases": float(len(phases))}, {label: len(phases) >= min_phases}


def _turned(trajectory: Trajectory, min_turns: float) -> tuple[dict, dict]:
    """The figures and the criterion of "turns at least `min_turns` full turns about the
    lateral axis" (`rotations`), shared by `cartwheel` and `roll`."""
    turns = float(rotations(trajectory))
    label = f"turns >= {min_turns:g} times about the lateral axis (got {turns:.2f})"
    return {"turns": turns}, {label: turns >= min_turns}


def bound(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_lengths: float = 2.0,
    min_airborne_phases: int = 2,
    clearance: float = FLIGHT_CLEARANCE,
    min_flight_seconds: float = FLIGHT_SECONDS,
) -> CheckResult:
    """Cujo's bounding (second paper, Figure 15): travels forward by leaps.

    Passes when the centre of mass travels forward at least `min_lengths` body lengths and
    the body flies (`flights`: every point `clearance` body lengths off the floor for
    `min_flight_seconds`) in at least `min_airborne_phases` separate phases.
    """
    t = _single(trajectory, "bound")
    travel, far = _travel(t, body_length, min_lengths)
    flown, flies = _airborne(
        trajectory, body_length, clearance, min_flight_seconds, min_airborne_phases
    )
    lowest = np.min(np.asarray(trajectory.points, float)[1:, :, 2], axis=1)
    figures = {
        **travel,
        **flown,
        "max_clearance_body_lengths": float(lowest.max()) / float(body_length),
    }
    criteria = {**far, **flies}
    return _result("bound", t["finite"], figures, criteria)


def jump(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_clearance_lengths: float = 0.25,
    max_landing_tilt_degrees: float = 30.0,
    min_flight_seconds: float = FLIGHT_SECONDS,
) -> CheckResult:
    """A jump (the second paper's Table 4 jump phase, Figures 13 and 14): leaves the floor
    entirely, high, and lands upright.

    Passes when the body flies with every point at least `min_clearance_lengths` body
    lengths above the floor for at least `min_flight_seconds` (`flights`; the highest height
    all points clear at once, `max_t min_i z_i(t)`, is the paper's jump measure), and at
    the end some point touches the floor with the body's up axis within
    `max_landing_tilt_degrees` of vertical.
    """
    t = _single(trajectory, "jump")
    body_length = _positive("body_length", body_length)
    points = np.asarray(trajectory.points, float)
    clearance = float(np.max(np.min(points[:, :, 2], axis=1)))
    lengths = clearance / body_length
    high = flights(
        trajectory,
        body_length=body_length,
        clearance=min_clearance_lengths,
        min_seconds=min_flight_seconds,
    )
    tilt = float(_tilt_degrees(t["frame"][-1:])[0])
    landed = bool(np.any(t["contact"][-1]))
    figures = {
        "clearance_m": clearance,
        "clearance_body_lengths": lengths,
        "final_tilt_degrees": tilt,
        "on_floor_at_end": float(landed),
    }
    criteria = {
        f"every point clears the floor by >= {min_clearance_lengths:g} body lengths for "
        f">= {min_flight_seconds:g} s (highest clearance {lengths:.2f})": bool(high),
        f"lands: a point on the floor at the end (got {landed})": landed,
        f"upright at the end, within {max_landing_tilt_degrees:g} degrees (got {tilt:.1f})": tilt
        <= max_landing_tilt_degrees,
    }
    return _result("jump", t["finite"], figures, criteria)


def _feet(feet, num_points: int, caller: str) -> tuple[tuple[int, ...], ...]:
    feet = tuple(tuple(int(n) for n in foot) for foot in (feet or ()))
    if len(feet) < 2 or any(not foot for foot in feet):
        raise ValueError(
            f"{caller} needs the body's feet (at least a left and a right one, e.g. "
            f"Figure(feet=...); the builders set them); got feet = {feet!r}"
        )
    for foot in feet:
        if any(not 0 <= n < num_points for n in foot):
            raise ValueError(f"{caller}: foot {foot} names a point outside 0..{num_points - 1}")
    return feet


def _heading_degrees(frame: np.ndarray) -> np.ndarray:
    """Each sample's heading (the forward axis seen from above) away from the first
    sample's, degrees in [0, 180]; 180 where the forward axis is vertical (no heading)."""
    h = frame[:, :2, 0]
    norm = np.linalg.norm(h, axis=1)
    unit = h / np.where(norm > 1e-9, norm, 1.0)[:, None]
    cos = np.clip(unit @ unit[0], -1.0, 1.0)
    return np.where(norm > 1e-9, np.degrees(np.arccos(cos)), 180.0)


def steps(contact: np.ndarray, feet) -> tuple[int, int]:
    """`(steps, touch_downs)` of a contact record `(samples, points)`: a foot is down when
    any of its points touches the floor, and touches down when it goes from up to down
    (the start, resting on the floor with no contact flag yet, counts as its state at the
    next sample). Feet alternate sides by their order (left, right, left, ...). A touch-down
    is a step when it is the only one at its sample and on the other side from the last
    step (the first touch-down alone is the first step); a foot touching down again
    (chatter, a hop) is no step, and feet of both sides touching down at once (a two-footed
    hop) reset the alternation."""
    down = np.stack([np.any(contact[:, list(foot)], axis=1) for foot in feet], axis=1)
    if len(down) > 1:
        down[0] = down[1]
    landing = down[1:] & ~down[:-1]
    count, last = 0, None
    for row in landing:
        sides = {int(f) % 2 for f in np.flatnonzero(row)}
        if len(sides) > 1:  # both sides at once: a two-footed landing, no step
            last = None
        elif sides and (side := sides.pop()) != last:
            count, last = count + 1, side
    return count, int(landing.sum())


def walk(
    trajectory: Trajectory,
    *,
    feet,
    min_heights: float = 1.5,
    max_heading_degrees: float = 30.0,
    min_height_share: float = FALL_SHARE,
    min_steps: int = 4,
) -> CheckResult:
    """A walk (the second paper's section 4: Bob's walk, Rex's walking stages): travels
    forward along the initial heading on alternating feet, without falling.

    Passes when the centre of mass travels at least `min_heights` standing heights along
    the figure's initial heading (its forward axis seen from above), the heading stays
    within `max_heading_degrees` of the initial one at every saved instant, the centre of
    mass never drops below `min_height_share` of its starting height, and the feet take at
    least `min_steps` alternating steps: touch-downs, left and right taking turns (see
    `steps`).

    **Arguments:** the trajectory; `feet` (the body's feet, `Figure.feet`: tuples of point
    indices, left and right alternating); the thresholds. The standing height is the
    extent of the points above the lowest one at the start.
    """
    t = _single(trajectory, "walk")
    points = np.asarray(trajectory.points, float)
    feet = _feet(feet, points.shape[1], "walk")
    height = float(points[0, :, 2].max() - points[0, :, 2].min())
    height = _positive("the standing height", height)
    forward = _forward(t)
    heights = forward / height
    heading = float(_heading_degrees(t["frame"]).max())
    share = float(t["com"][:, 2].min() / t["com"][0, 2])
    taken, touch_downs = steps(t["contact"], feet)
    figures = {
        "forward_m": forward,
        "forward_heights": heights,
        "standing_height_m": height,
        "max_heading_degrees": heading,
        "min_com_height_share": share,
        "steps": float(taken),
        "touch_downs": float(touch_downs),
    }
    criteria = {
        f"travels forward >= {min_heights:g} standing heights (got {heights:.2f})": heights
        >= min_heights,
        f"heading within {max_heading_degrees:g} degrees of the start's (max {heading:.1f})": (
            heading <= max_heading_degrees
        ),
        f"centre of mass never below {100 * min_height_share:g}% of its start height "
        f"(min {100 * share:.0f}%)": share >= min_height_share,
        f">= {min_steps} steps, left and right taking turns (got {taken} of "
        f"{touch_downs} touch-downs)": taken >= min_steps,
    }
    return _result("walk", t["finite"], figures, criteria)


def walk_turn_walk(
    trajectories,
    *,
    feet,
    min_turn_degrees: float = 45.0,
    min_height_share: float = FALL_SHARE,
    min_heights: float = 1.5,
    max_heading_degrees: float = 30.0,
    min_steps: int = 4,
) -> CheckResult:
    """Rex's seriatim walk, turn and walk (the second paper's section 4, Figure 16): three
    motions, each starting where the one before ended.

    Passes when the first and the last motion each pass the `walk` check (each on its own
    trajectory: its own start heading and standing height; `min_heights`,
    `max_heading_degrees` and `min_steps` are passed on), the middle one changes the heading
    by at least `min_turn_degrees` either way (the `heading` objective term: the net turn of
    the forward axis seen from above), and nobody falls: in every motion the centre of mass
    stays at or above `min_height_share` of its height at the start of the first (which
    also holds the walks' own fall criterion to the first start).

    **Arguments:** the three trajectories in order (e.g. the stages of a multi-stage run);
    `feet` (the body's feet, `Figure.feet`, as for `walk`); the thresholds.
    """
    parts = list(trajectories) if not isinstance(trajectories, Trajectory) else [trajectories]
    if len(parts) != 3:
        raise ValueError(
            f"walk_turn_walk checks 3 trajectories (a walk, a turn, a walk); got {len(parts)}"
        )
    data = [_single(t, "walk_turn_walk") for t in parts]
    feet = _feet(feet, np.shape(parts[0].points)[1], "walk_turn_walk")
    walks = [
        walk(
            parts[i],
            feet=feet,
            min_heights=min_heights,
            max_heading_degrees=max_heading_degrees,
            min_height_share=min_height_share,
            min_steps=min_steps,
        )
        for i in (0, 2)
    ]
    turn = math.degrees(float(heading(parts[1], absolute=True)))
    start_height = float(data[0]["com"][0, 2])
    start_height = _positive("the first motion's starting centre-of-mass height", start_height)
    shares = [float(t["com"][:, 2].min()) / start_height for t in data]
    lowest = int(np.argmin(shares))
    figures = {
        "turn_degrees": turn,
        "min_com_height_share": shares[lowest],
        **{f"stage_{i + 1}_min_com_height_share_of_stage_1": v for i, v in enumerate(shares)},
    }
    for number, result in zip((1, 3), walks, strict=True):
        figures[f"stage_{number}_walk_passed"] = float(result.passed)
        figures.update({f"stage_{number}_{k}": v for k, v in result.figures.items()})

    def verdict(number: int, result: CheckResult) -> str:
        if result.passed:
            return f"stage {number} walks (the walk check passed)"
        failed = "; ".join(text for text, ok in result.criteria.items() if not ok)
        return f"stage {number} walks (the walk check failed: {failed})"

    criteria = {
        verdict(1, walks[0]): walks[0].passed,
        f"stage 2 turns >= {min_turn_degrees:g} degrees (got {turn:.1f})": turn >= min_turn_degrees,
        verdict(3, walks[1]): walks[1].passed,
        f"centre of mass never below {100 * min_height_share:g}% of its height at the start "
        f"of stage 1 (min {100 * shares[lowest]:.0f}%, in stage {lowest + 1})": shares[lowest]
        >= min_height_share,
    }
    return _result("walk_turn_walk", all(t["finite"] for t in data), figures, criteria)


def _distance(t: dict, body_length: float, min_lengths: float) -> tuple[dict, dict]:
    """The figures and the criterion of "the centre of mass ends at least `min_lengths` body
    lengths (horizontally, any direction) from where it started": the third paper's
    fitness, the absolute horizontal distance travelled."""
    body_length = _positive("body_length", body_length)
    metres = float(np.linalg.norm(t["com"][-1, :2] - t["com"][0, :2]))
    lengths = metres / body_length
    figures = {"distance_body_lengths": lengths, "distance_m": metres}
    label = f"travels >= {min_lengths:g} body lengths, any direction (got {lengths:.2f})"
    return figures, {label: lengths >= min_lengths}


def hop(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_lengths: float = 2.0,
    min_airborne_phases: int = 3,
    clearance: float = FLIGHT_CLEARANCE,
    min_flight_seconds: float = FLIGHT_SECONDS,
    max_turns: float = 1.0,
) -> CheckResult:
    """A hopping gait (third paper, Figures 3 and 5: the Luxo lamp and the snake jumping),
    periodic: travels by repeated flights, without turning over.

    Passes when the centre of mass ends at least `min_lengths` body lengths from where it
    started, horizontally and in any direction (the paper's fitness is the absolute
    distance), the body flies (`flights`: every point `clearance` body lengths off the
    floor for `min_flight_seconds`) in at least `min_airborne_phases` separate phases, and
    its frame turns less than `max_turns` full turns (net, either way) about its lateral
    axis: a body that tumbles over as it flies rolls (`roll`), it does not hop.
    """
    t = _single(trajectory, "hop")
    travel, far = _distance(t, body_length, min_lengths)
    flown, flies = _airborne(
        trajectory, body_length, clearance, min_flight_seconds, min_airborne_phases
    )
    turns = float(rotations(trajectory))
    upright = {
        f"turns < {max_turns:g} times about the lateral axis (got {turns:.2f})": abs(turns)
        < max_turns
    }
    return _result(
        "hop", t["finite"], {**travel, **flown, "turns": turns}, {**far, **flies, **upright}
    )


def roll(
    trajectory: Trajectory,
    *,
    body_length: float,
    min_turns: float = 1.0,
    min_lengths: float = 2.0,
) -> CheckResult:
    """A rolling gait (third paper, Figures 4 and 6: the Luxo lamp and the snake rolling),
    not periodic: travels while turning over.

    Passes when the body frame turns at least `min_turns` full turns (net, either way)
    about its lateral axis (`rotations`) and the centre of mass ends at least `min_lengths`
    body lengths from where it started, horizontally and in any direction.
    """
    t = _single(trajectory, "roll")
    travel, far = _distance(t, body_length, min_lengths)
    turned, turns = _turned(trajectory, min_turns)
    return _result("roll", t["finite"], {**turned, **travel}, {**turns, **far})


def hop_or_roll(trajectory: Trajectory, *, body_length: float) -> CheckResult:
    """Which of the third paper's gaits a motion found: passes when `hop` or `roll` passes
    (each with its defaults). Its figures are both checks' figures and `hop` and `roll`
    (1.0 where that check passed, else 0.0); its criteria are both checks' verdicts, each
    followed by its failed criteria."""
    results = {
        "hop": hop(trajectory, body_length=body_length),
        "roll": roll(trajectory, body_length=body_length),
    }
    figures: dict[str, float] = {}
    criteria: dict[str, bool] = {}
    for name, result in results.items():
        figures.update(result.figures)
        figures[name] = float(result.passed)
        failed = "; ".join(text for text, ok in result.criteria.items() if not ok)
        label = f"{name}: passed" if result.passed else f"{name}: failed ({failed})"
        criteria[label] = result.passed
    passed = any(r.passed for r in results.values())
    return CheckResult("hop_or_roll", passed, figures, criteria)


CHECKS = {
    "leap": leap,
    "somersault": somersault,
    "pirouette": pirouette,
    "shuffle": shuffle,
    "cartwheel": cartwheel,
    "bound": bound,
    "jump": jump,
    "walk": walk,
    "walk_turn_walk": walk_turn_walk,
    "hop": hop,
    "roll": roll,
    "hop_or_roll": hop_or_roll,
}
