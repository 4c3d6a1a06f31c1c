"""The built-in objective terms: the first paper's Table 1, the second paper's Table 3 and a
few more.

Each term is a function of one `Trajectory` (sampled at its save times) and returns a scalar.
Angles are in radians unless an option says degrees; lengths in metres; times in seconds.
"""

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._sim.trajectory import Trajectory
from .registry import register_term

_AXES = {"forward": 0, "left": 1, "up": 2}


def _horizontal_unit(v):
    h = v[..., :2]
    n = jnp.sqrt(jnp.sum(h * h, axis=-1, keepdims=True))
    return h / jnp.where(n > 0, n, 1.0)


def _increments(frame: Float[Array, "t 3 3"], world: bool) -> Float[Array, "t-1 3"]:
    """Rotation vectors between consecutive frames: in body coordinates (`world=False`) or
    world coordinates (`world=True`). Smooth (differentiable) even at zero rotation."""
    a, b = frame[:-1], frame[1:]
    if world:
        rel = b @ jnp.swapaxes(a, -1, -2)
    else:
        rel = jnp.swapaxes(a, -1, -2) @ b
    skew = 0.5 * (rel - jnp.swapaxes(rel, -1, -2))
    vee = jnp.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)
    s2 = jnp.sum(vee * vee, axis=-1)
    c = 0.5 * (jnp.trace(rel, axis1=-2, axis2=-1) - 1.0)
    small = s2 < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    factor = jnp.where(small, 1.0 + s2 / 6.0, jnp.arctan2(s, c) / s)
    return vee * factor[..., None]


FALL_SHARE = 0.6
"""A body has fallen once its centre of mass is below this share of its starting height (the
`walk` check's criterion); see `until_fall` and `standing_time`."""


def _fall_index(trajectory: Trajectory, share: float = FALL_SHARE) -> Int[Array, ""]:
    """The first saved sample at which the centre of mass is below `share` of its starting
    height, or the last sample if it never is."""
    if isinstance(share, bool) or not (isinstance(share, int | float) and 0 < share < 1):
        raise ValueError(f"fall_share = {share!r}; allowed: a number between 0 and 1")
    z = trajectory.com[:, 2]
    below = z < share * z[0]
    return jnp.where(jnp.any(below), jnp.argmax(below), z.shape[0] - 1)


def _end(trajectory: Trajectory, until_fall: bool, share: float = FALL_SHARE):
    return _fall_index(trajectory, share) if until_fall else -1


@register_term("forward")
def forward(
    trajectory: Trajectory, until_fall: bool = False, fall_share: float = FALL_SHARE
) -> Float[Array, ""]:
    """Final horizontal displacement of the centre of mass along the body's initial forward
    direction (m; Table 1's primary term for walking and bounding).

    With `until_fall`, the displacement when the body falls (the first sample with its
    centre of mass below 60% of its starting height), or at the end if it never does: a
    dive forward earns only what it travelled standing, as an episode that ends at a fall
    scores in reinforcement learning. `fall_share` (0..1): a stricter (or laxer) fall, the
    centre of mass below that share of its starting height.
    """
    direction = _horizontal_unit(trajectory.frame[0, :, 0])
    end = _end(trajectory, until_fall, fall_share)
    shift = trajectory.com[end, :2] - trajectory.com[0, :2]
    return jnp.dot(shift, direction)


@register_term("sideways")
def sideways(trajectory: Trajectory) -> Float[Array, ""]:
    """Absolute final horizontal displacement of the centre of mass along the body's initial
    left axis (m)."""
    direction = _horizontal_unit(trajectory.frame[0, :, 1])
    shift = trajectory.com[-1, :2] - trajectory.com[0, :2]
    return jnp.abs(jnp.dot(shift, direction))


@register_term("feet_forward")
def feet_forward(
    trajectory: Trajectory,
    tolerance: float = 0.01,
    until_fall: bool = False,
    fall_share: float = FALL_SHARE,
) -> Float[Array, ""]:
    """Mean final horizontal displacement of the feet along the body's initial forward
    direction (m; the second paper rewarded Bob's feet moving forward with his centre of
    mass, footnote 10).

    The feet are the points that stand on the floor at the start: within `tolerance` m of
    the lowest point at the first sample (Bob's and Star-Man's two point feet, Rex's four
    foot nodes, a lattice's bottom masses). A body that only leans forward moves its centre
    of mass but not its feet; one that walks moves both. `until_fall`, `fall_share`: as
    `forward`'s.
    """
    z0 = trajectory.points[0, :, 2]
    feet = z0 <= jnp.min(z0) + tolerance
    direction = _horizontal_unit(trajectory.frame[0, :, 0])
    end = _end(trajectory, until_fall, fall_share)
    shift = trajectory.points[end, :, :2] - trajectory.points[0, :, :2]
    along = shift @ direction
    return jnp.sum(jnp.where(feet, along, 0.0)) / jnp.sum(feet)


def _start_feet(trajectory: Trajectory, tolerance: float):
    """The points that stand on the floor at the first sample (within `tolerance` m of the
    lowest), and which of them are on the left of the centre of mass (the body's initial
    left axis)."""
    z0 = trajectory.points[0, :, 2]
    feet = z0 <= jnp.min(z0) + tolerance
    lateral = (trajectory.points[0] - trajectory.com[0]) @ trajectory.frame[0, :, 1]
    return feet, lateral > 0


@register_term("steps")
def steps(
    trajectory: Trajectory,
    tolerance: float = 0.01,
    until_fall: bool = False,
    cap: float = 20.0,
    fall_share: float = FALL_SHARE,
) -> Float[Array, ""]:
    """Alternating steps, counted as the `walk` check counts them (at most `cap`): a touch-
    down of one side's feet (up at one sample, down at the next) is a step when it is the only
    side touching down there and the other side from the last step; a foot landing again,
    or both sides at once, is none.

    The feet are the points on the floor at the start (as `feet_forward`'s), each side the
    ones left or right of the centre of mass along the initial left axis. `until_fall`:
    only the steps before the body falls (see `forward`, and its `fall_share`). A reward
    for stepping, which a body that stands still or dives forward lacks.
    """
    feet, left = _start_feet(trajectory, tolerance)
    contact = trajectory.contact
    down = jnp.stack(
        [jnp.any(contact & feet & left, axis=1), jnp.any(contact & feet & ~left, axis=1)], axis=1
    )
    down = down.at[0].set(down[1])  # resting on the floor at the start has no flag yet
    landing = down[1:] & ~down[:-1]
    end = _end(trajectory, until_fall, fall_share)
    counted = jnp.arange(landing.shape[0]) < end if until_fall else True
    landing = landing & jnp.asarray(counted)[..., None]

    def one(carry, row):
        count, last = carry  # last: the side of the last step, -1 for none
        both = row[0] & row[1]
        side = jnp.where(row[0], 0, 1)
        step = (row[0] ^ row[1]) & (side != last)
        last = jnp.where(both, -1, jnp.where(step, side, last))
        return (count + step.astype(count.dtype), last), None

    (count, _), _ = jax.lax.scan(one, (jnp.zeros((), float), jnp.asarray(-1)), landing)
    return jnp.minimum(count, cap)


@register_term("standing_time")
def standing_time(trajectory: Trajectory, fall_share: float = FALL_SHARE) -> Float[Array, ""]:
    """Time from the start until the body falls (s): the first saved instant with its centre
    of mass below 60% (`fall_share`) of its starting height, or the whole duration if it
    never falls (a slope toward staying up for longer; reinforcement learning's "alive"
    reward)."""
    return trajectory.ts[_fall_index(trajectory, fall_share)] - trajectory.ts[0]


@register_term("distance")
def distance(trajectory: Trajectory) -> Float[Array, ""]:
    """Final horizontal displacement of the centre of mass in any direction (m)."""
    shift = trajectory.com[-1, :2] - trajectory.com[0, :2]
    return jnp.sqrt(jnp.sum(shift * shift) + 1e-12)


@register_term("max_height")
def max_height(trajectory: Trajectory) -> Float[Array, ""]:
    """Maximum height of the centre of mass above its starting height (m; Table 1's primary
    term for jumping)."""
    return jnp.max(trajectory.com[:, 2]) - trajectory.com[0, 2]


@register_term("clearance")
def clearance(trajectory: Trajectory) -> Float[Array, ""]:
    """The highest height that every point clears at once, `max_t min_i z_i(t)` (m; the
    second paper's jump measure, Table 4): how high the whole body leaves the floor."""
    return jnp.max(jnp.min(trajectory.points[:, :, 2], axis=1))


@register_term("min_contacts")
def min_contacts(trajectory: Trajectory) -> Float[Array, ""]:
    """Minimum number of points touching the floor at any saved time after the start
    (Table 1: reward it to keep the body on the ground)."""
    return jnp.min(jnp.sum(trajectory.contact[1:], axis=-1)).astype(float)


@register_term("grounded")
def grounded(trajectory: Trajectory) -> Float[Array, ""]:
    """1 if some point touches the floor at every saved time after the start, else 0 (the
    shuffle check's criterion: reward it for a gait that never leaves the floor, whichever
    point keeps it there; `min_contacts` also rewards keeping more points down)."""
    touching = jnp.any(trajectory.contact[1:], axis=-1)
    return jnp.all(touching).astype(float)


def _interval_lengths(trajectory: Trajectory):
    return jnp.diff(trajectory.ts)


@register_term("contact_time")
def contact_time(trajectory: Trajectory) -> Float[Array, ""]:
    """Total time during which any point touches the floor (s; Table 1: penalise it to keep
    the body airborne). Counted per save interval, by the contact at its end."""
    touching = jnp.any(trajectory.contact[1:], axis=-1)
    return jnp.sum(jnp.where(touching, _interval_lengths(trajectory), 0.0))


@register_term("flight_time")
def flight_time(trajectory: Trajectory, height: float = 0.05) -> Float[Array, ""]:
    """Total time during which every point is at least `height` m above the floor (s):
    visible flight, as the `leap`, `bound` and `jump` checks count it (`jaxmotion.checks.
    flights`), where `contact_time` and `hops` also count skimming a few millimetres up.
    Counted per save interval, by the heights at its end."""
    lowest = jnp.min(trajectory.points[1:, :, 2], axis=-1)
    return jnp.sum(jnp.where(lowest >= height, _interval_lengths(trajectory), 0.0))


@register_term("air_height")
def air_height(trajectory: Trajectory) -> Float[Array, ""]:
    """Mean height of the lowest point above the floor over the saved instants after the
    start, 0 while some point touches it (m): a smooth reward for leaving the floor, which
    grows with every millimetre and every instant off it (`flight_time` counts only
    flights above its height, so a search finds no slope toward them)."""
    lowest = jnp.min(trajectory.points[1:, :, 2], axis=-1)
    return jnp.mean(jnp.maximum(lowest, 0.0))


@register_term("hops")
def hops(trajectory: Trajectory) -> Float[Array, ""]:
    """Number of times the body leaves the ground: saved samples where some point touched the
    floor followed by one where none does."""
    touching = jnp.any(trajectory.contact[1:], axis=-1)
    return jnp.sum(touching[:-1] & ~touching[1:]).astype(float)


@register_term("contact_distance")
def contact_distance(trajectory: Trajectory) -> Float[Array, ""]:
    """Horizontal distance travelled by points while in contact with the floor (m; the second
    paper's Table 3, reward it for a shuffling or sliding gait).

    For every point and every save interval in which the point touches the floor at both
    ends, the horizontal (x-y) length of its displacement over the interval; summed over
    points and intervals. An interval in which contact starts or ends counts nothing, so a
    hopping gait scores low. The sum is over points, so a body sliding rigidly with `k` points
    down scores `k` times its own slide.
    """
    step = jnp.diff(trajectory.points[..., :2], axis=0)
    d2 = jnp.sum(step * step, axis=-1)
    # sqrt has an infinite slope at 0: a point resting still would give a NaN gradient.
    moved = d2 > 0
    length = jnp.where(moved, jnp.sqrt(jnp.where(moved, d2, 1.0)), 0.0)
    held = trajectory.contact[:-1] & trajectory.contact[1:]
    return jnp.sum(jnp.where(held, length, 0.0))


@register_term("on_ground_at_end")
def on_ground_at_end(trajectory: Trajectory, min_points: int = 1) -> Float[Array, ""]:
    """1 if at least `min_points` points touch the floor at the final time, else 0."""
    return (jnp.sum(trajectory.contact[-1]) >= min_points).astype(float)


@register_term("rotation")
def rotation(trajectory: Trajectory, axis: str = "any", absolute: bool = False) -> Float[Array, ""]:
    """Rotation of the body frame (Table 1's "total rotation of a triplet of point masses
    about the centre of mass"; the frame is the best-fit rotation of all the masses).

    `axis="any"`: the total angle turned, summed over save intervals whatever the axis
    (rad, >= 0). `axis="forward"`, `"left"` or `"up"`: the net signed angle turned about that
    body axis (rad), accumulated from the increments between samples, positive by the
    right-hand rule. With forward +x, left +y and up +z, pitching nose-down is positive about
    `"left"`, so a backward somersault is negative about `"left"`, and rolling onto the right
    side is positive about `"forward"`. `absolute=True` gives the size of the net rotation
    about the axis whichever way it went (to penalise rolling or turning).
    """
    inc = _increments(trajectory.frame, world=False)
    if axis == "any":
        return jnp.sum(jnp.sqrt(jnp.sum(inc * inc, axis=-1) + 1e-20))
    if axis not in _AXES:
        raise ValueError(f"rotation axis = {axis!r}; allowed: any, forward, left, up")
    net = jnp.sum(inc[:, _AXES[axis]])
    return jnp.abs(net) if absolute else net


@register_term("rotations")
def rotations(trajectory: Trajectory) -> Float[Array, ""]:
    """Number of full-body rotations about the body's lateral axis (turns, >= 0; the second
    paper's Table 3, reward it for a cartwheel or a somersault).

    The size of the net signed rotation about the body's left axis in turns (1.0 = one full
    turn): `rotation(axis="left", absolute=True) / (2 pi)`. The angle is accumulated from the
    rotations between consecutive samples (each must be under half a turn), so it unwraps:
    two cartwheels give 2.0, while rocking back and forth gives about 0. For a planar figure
    whose left axis is normal to its plane of motion, this counts its turns in that plane
    whichever way it goes; turning about the body's up or forward axis does not count.
    """
    return rotation(trajectory, axis="left", absolute=True) / (2.0 * math.pi)


@register_term("net_yaw")
def net_yaw(trajectory: Trajectory, signed: bool = False) -> Float[Array, ""]:
    """Net rotation about the world vertical (rad): the absolute value unless `signed`
    (then counter-clockwise seen from above is positive). Rewarded by the pirouette."""
    inc = _increments(trajectory.frame, world=True)
    total = jnp.sum(inc[:, 2])
    return total if signed else jnp.abs(total)


def _signed_angles(a, b):
    """Signed angles (rad, in (-pi, pi]) from 2D vectors `a` to `b`, counter-clockwise
    positive; 0 where either vector vanishes (and there, gradient 0 rather than NaN)."""
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    dot = jnp.sum(a * b, axis=-1)
    ok = cross * cross + dot * dot > 1e-24
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, cross, 0.0), jnp.where(ok, dot, 1.0)), 0.0)


@register_term("heading")
def heading(
    trajectory: Trajectory, absolute: bool = False, cap_degrees: float = math.inf
) -> Float[Array, ""]:
    """Change of heading: the net signed turn of the body's forward axis seen from above,
    from the first to the last sample (rad, counter-clockwise positive; the second paper's
    measure for Rex's turn). `absolute=True` gives its size whichever way it went;
    `cap_degrees` limits it to that angle either way (a turn of more earns no more, so that
    a search for a turn has no reason to spin or tumble).

    The heading is the direction of the forward axis's horizontal part. It is unwrapped by
    summing the signed angles between consecutive samples (each must be under half a turn),
    so a turn of 270 degrees gives 3 pi / 2, not -pi / 2. The heading is undefined while the
    forward axis is vertical: such a sample adds nothing, and passing through vertical (a
    somersault) flips the heading by half a turn, either way.

    Compared with `net_yaw`: the two agree while the body turns about the world vertical (an
    upright turn). `net_yaw` integrates the vertical component of the body's angular
    velocity; `heading` follows only where the forward axis points, so rolling a pitched body
    about its own forward axis changes `net_yaw` but not `heading`.
    """
    h = trajectory.frame[:, :2, 0]
    net = jnp.sum(_signed_angles(h[:-1], h[1:]))
    net = jnp.abs(net) if absolute else net
    cap = math.radians(cap_degrees)
    return jnp.clip(net, -cap, cap)


@register_term("heading_deviation")
def heading_deviation(trajectory: Trajectory, allowed_degrees: float = 0.0) -> Float[Array, ""]:
    """Largest angle between the heading at a saved instant and the initial heading (rad,
    0 to pi), as the `walk` check measures it: penalise it so that a walk keeps its
    direction throughout (`heading` and `net_yaw` see only the net turn, so a walk that
    veers and comes back costs them nothing). A sample whose forward axis is vertical (no
    heading) counts 0. `allowed_degrees` is a free margin: only the deviation beyond it
    counts (a walk may sway within it at no cost)."""
    h = trajectory.frame[:, :2, 0]
    worst = jnp.max(jnp.abs(_signed_angles(h[:1], h)))
    return jnp.maximum(worst - math.radians(allowed_degrees), 0.0)


def _angle_between(a, b):
    cos = jnp.sum(a * b, axis=-1)
    return jnp.clip(cos, -1.0, 1.0)


@register_term("upright")
def upright(trajectory: Trajectory, max_degrees: float = 45.0) -> Float[Array, ""]:
    """1 if the body's up axis ever tilts more than `max_degrees` from vertical, else 0
    (Table 1's loss of uprightness; give it a negative weight)."""
    cos_tilt = trajectory.frame[:, 2, 2]
    return jnp.any(cos_tilt < jnp.cos(jnp.deg2rad(max_degrees))).astype(float)


def _tilt_from_cos(cos):
    """arccos of the up axis's vertical component, clipped to [-1, 1]; exactly upright
    (cos >= 1) gives 0 with gradient 0 rather than arccos's infinite slope (NaN)."""
    upright = cos >= 1.0
    safe = jnp.where(upright, 0.0, jnp.clip(cos, -1.0, 1.0))
    return jnp.where(upright, 0.0, jnp.arccos(safe))


@register_term("tilt")
def tilt(trajectory: Trajectory) -> Float[Array, ""]:
    """Largest tilt of the body's up axis from vertical over the motion (rad): a continuous
    companion of `upright`."""
    return _tilt_from_cos(jnp.min(trajectory.frame[:, 2, 2]))


@register_term("final_tilt")
def final_tilt(trajectory: Trajectory) -> Float[Array, ""]:
    """Tilt of the body's up axis from vertical at the final time (rad, 0 to pi): penalise it
    to make a motion end the right way up, whatever it did in between (a somersault)."""
    return _tilt_from_cos(trajectory.frame[-1, 2, 2])


@register_term("final_spin")
def final_spin(trajectory: Trajectory) -> Float[Array, ""]:
    """How fast the body turns at the final time (rad/s): the rotation between the last two
    saved frames over their interval. Penalise it so that a motion ends where the next can
    start (a walk that ends pitching forward still stands at its last instant, but falls
    at the next)."""
    inc = _increments(trajectory.frame[-2:], world=True)[0]
    angle = jnp.sqrt(jnp.sum(inc * inc) + 1e-20)
    return angle / (trajectory.ts[-1] - trajectory.ts[-2])


@register_term("fallen")
def fallen(trajectory: Trajectory, max_degrees: float = 45.0) -> Float[Array, ""]:
    """1 if at the final time the body's up axis tilts more than `max_degrees` from vertical,
    else 0: the motion ended fallen over (give it a negative weight). Unlike `upright`, what
    happens on the way does not count."""
    return (trajectory.frame[-1, 2, 2] < jnp.cos(jnp.deg2rad(max_degrees))).astype(float)


@register_term("left_right")
def left_right(trajectory: Trajectory, max_degrees: float = 90.0) -> Float[Array, ""]:
    """1 if the body's left axis ever turns more than `max_degrees` away from its initial
    direction (Table 1's loss of left-right orientation), else 0."""
    left = trajectory.frame[:, :, 1]
    cos = _angle_between(left, left[0])
    return jnp.any(cos < jnp.cos(jnp.deg2rad(max_degrees))).astype(float)


@register_term("front_facing")
def front_facing(trajectory: Trajectory, max_degrees: float = 45.0) -> Float[Array, ""]:
    """1 if the body's heading (its forward axis seen from above) ever turns more than
    `max_degrees` from its initial heading (Table 1's loss of front-facing direction), else 0.
    """
    heading = _horizontal_unit(trajectory.frame[:, :, 0])
    cos = _angle_between(heading, heading[0])
    return jnp.any(cos < jnp.cos(jnp.deg2rad(max_degrees))).astype(float)


@register_term("asymmetry")
def asymmetry(trajectory: Trajectory, axis: str = "left") -> Float[Array, ""]:
    """Average asymmetry of the body about the plane through its centre of mass
    perpendicular to a body axis (m; Table 1, to promote asymmetric movement).

    Each point is mirrored across the plane in the body frame and compared with its mirror
    partner (the point nearest to its mirror image at t = 0); the mean distance over points
    and saved times is the asymmetry. `axis="left"` measures left-right asymmetry.
    """
    if axis not in _AXES:
        raise ValueError(f"asymmetry axis = {axis!r}; allowed: forward, left, up")
    a = _AXES[axis]
    rel = trajectory.points - trajectory.com[:, None, :]
    local = jnp.einsum("tnk,tkj->tnj", rel, trajectory.frame)  # body coordinates
    flip = jnp.ones(3).at[a].set(-1.0)
    mirrored = local * flip
    d0 = mirrored[0][:, None, :] - local[0][None, :, :]
    partner = jnp.argmin(jnp.sum(d0 * d0, axis=-1), axis=1)
    gap = mirrored - local[:, partner, :]
    return jnp.mean(jnp.sqrt(jnp.sum(gap * gap, axis=-1) + 1e-12))
