"""What `animate` and `filmstrip` share: a trajectory as numpy arrays, a view that holds the
whole motion, the floor, and the artists of one pose (points, springs, body frame)."""

from dataclasses import dataclass

import numpy as np
from matplotlib.ticker import MaxNLocator
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from .._body.figure import Figure
from .._body.lattice import Lattice
from .._sim.trajectory import Trajectory

# Red, green and blue for the body's forward, left and up axes.
FRAME_COLOURS = ("tab:red", "tab:green", "tab:blue")
POINT_COLOUR = "black"
CONTACT_COLOUR = "tab:orange"
SPRING_COLOUR = "0.35"


@dataclass(frozen=True)
class Motion:
    """One trajectory as numpy arrays, with the body's springs (`(0, 2)` when there are none).

    Non-finite positions are NaN, so matplotlib leaves them out instead of failing.
    """

    ts: np.ndarray  # (num_saves,)
    points: np.ndarray  # (num_saves, num_points, 3)
    com: np.ndarray  # (num_saves, 3)
    frame: np.ndarray  # (num_saves, 3, 3), columns forward, left, up
    contact: np.ndarray  # (num_saves, num_points) bool
    springs: np.ndarray  # (num_springs, 2) int

    def pose_is_finite(self, i: int) -> bool:
        return bool(np.all(np.isfinite(self.points[i])) and np.all(np.isfinite(self.com[i])))


def motion(trajectory: Trajectory, body: Lattice | Figure | None, *, caller: str) -> Motion:
    """Check one unbatched trajectory (and its body) and convert it to numpy."""
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"{caller} needs a jaxmotion Trajectory; got {type(trajectory).__name__}")
    points = np.asarray(trajectory.points, dtype=float)
    if points.ndim == 4:
        raise ValueError(
            f"{caller} draws one trajectory, but this one is batched: points have shape "
            f"{points.shape} (batch, time, points, 3). Pick one controller first, e.g. "
            "`jax.tree_util.tree_map(lambda a: a[0], trajectory)`"
        )
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] < 1:
        raise ValueError(
            f"{caller} needs trajectory.points of shape (num_saves, num_points, 3) with at "
            f"least one save; got shape {points.shape}"
        )
    num_saves, num_points, _ = points.shape
    ts = np.asarray(trajectory.ts, dtype=float).reshape(-1)
    if ts.shape != (num_saves,):
        raise ValueError(
            f"{caller} needs one time per saved pose: trajectory.ts has shape {ts.shape} but "
            f"trajectory.points has {num_saves} saves"
        )
    com = np.asarray(trajectory.com, dtype=float)
    frame = np.asarray(trajectory.frame, dtype=float)
    contact = np.asarray(trajectory.contact, dtype=bool)
    points = np.where(np.isfinite(points), points, np.nan)
    com = np.where(np.isfinite(com), com, np.nan)
    frame = np.where(np.isfinite(frame), frame, np.nan)
    return Motion(
        ts=ts,
        points=points,
        com=com,
        frame=frame,
        contact=contact,
        springs=_springs(body, num_points, caller=caller),
    )


def _springs(body: Lattice | Figure | None, num_points: int, *, caller: str) -> np.ndarray:
    """The segments to draw between points: a lattice's springs or a figure's rods."""
    if body is None:
        return np.zeros((0, 2), dtype=int)
    if isinstance(body, Lattice):
        segments, what = np.asarray(body.springs, dtype=int), "masses"
    elif isinstance(body, Figure):
        segments, what = np.asarray(body.rods, dtype=int), "nodes"
    else:
        raise TypeError(
            f"{caller} draws the springs of a Lattice or the rods of a Figure; got body of "
            f"type {type(body).__name__}. Pass body=None to draw the points only"
        )
    if body.num_points != num_points:
        raise ValueError(
            f"{caller}: body {body.name!r} has {body.num_points} {what} but the trajectory "
            f"has {num_points} points; pass the body that was simulated"
        )
    return segments.reshape(-1, 2)


@dataclass(frozen=True)
class View:
    """Fixed axes limits holding every pose and the floor, and the length of the frame
    arrows."""

    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)
    arrow: float


def view(motion: Motion) -> View:
    """Limits that hold every saved pose and the floor."""
    pts = np.concatenate([motion.points.reshape(-1, 3), motion.com])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        raise ValueError("the trajectory has no finite position to draw (the run blew up at once)")
    lo = np.minimum(pts.min(axis=0), [np.inf, np.inf, 0.0])
    hi = np.maximum(pts.max(axis=0), [-np.inf, -np.inf, 0.0])
    first = motion.points[0]
    first = first[np.all(np.isfinite(first), axis=1)]
    size = float(np.max(np.ptp(first, axis=0))) if first.shape[0] else 0.0
    span = float(np.max(hi - lo))
    if size <= 0.0:
        size = 0.2 * span if span > 0 else 1.0
    # A margin of a fraction of the body size, and no axis much thinner than the longest, so a
    # long walk still shows the body's height.
    lo = lo - 0.15 * size
    hi = hi + 0.15 * size
    centre = 0.5 * (lo + hi)
    half = np.maximum(0.5 * (hi - lo), 0.15 * float(np.max(hi - lo)))
    return View(lo=centre - half, hi=centre + half, arrow=0.6 * size)


def setup_axes(ax: Axes3D, v: View, *, elev: float, azim: float) -> float:
    """Fixed limits with equal scale on x, y and z, the floor z = 0 under everything.
    Returns the spacing of the floor grid, m."""
    ax.set_xlim(v.lo[0], v.hi[0])
    ax.set_ylim(v.lo[1], v.hi[1])
    ax.set_zlim(v.lo[2], v.hi[2])
    # Equal scale: the box's sides are proportional to the ranges they show.
    # With the axis box hidden, the default zoom leaves wide margins around a compact motion;
    # a long box's corners reach the edges in perspective already, so it is zoomed less.
    sides = v.hi - v.lo
    ax.set_box_aspect(tuple(sides), zoom=1.0 + 0.2 * float(np.min(sides) / np.max(sides)))
    ax.view_init(elev=elev, azim=azim)
    # The floor is drawn first and the body over it: depth sorting of a large plane against
    # thin lines makes parts of the body flicker behind the floor.
    ax.computed_zorder = False
    # No axis box, ticks or labels: they look cluttered around a moving body and take most
    # of the drawing time of a frame. The floor grid shows the scale instead.
    ax.set_axis_off()
    x0, y0 = v.lo[:2]
    x1, y1 = v.hi[:2]
    plane = Poly3DCollection(
        [[(x0, y0, 0.0), (x1, y0, 0.0), (x1, y1, 0.0), (x0, y1, 0.0)]],
        facecolor="0.85",
        edgecolor="none",
        alpha=0.35,
        zorder=0,
    )
    ax.add_collection3d(plane)
    step = grid_step(v)
    xs = np.arange(np.ceil(x0 / step), np.floor(x1 / step) + 1) * step
    ys = np.arange(np.ceil(y0 / step), np.floor(y1 / step) + 1) * step
    grid = [[(x, y0, 0.0), (x, y1, 0.0)] for x in xs] + [[(x0, y, 0.0), (x1, y, 0.0)] for y in ys]
    ax.add_collection3d(Line3DCollection(grid, colors="0.7", linewidths=0.5, zorder=0.5))
    return step


def grid_step(v: View) -> float:
    """Spacing of the floor grid: a round number of metres, about 8 lines across."""
    span = float(np.max(v.hi[:2] - v.lo[:2]))
    ticks = MaxNLocator(nbins=8, steps=[1, 2, 5, 10]).tick_values(0.0, span)
    return float(ticks[1] - ticks[0])


class Pose:
    """The artists of one pose, created once and updated in place (fast animation)."""

    def __init__(self, ax: Axes3D, motion: Motion, v: View):
        self._springs = motion.springs
        self._arrow = v.arrow
        self.springs = None
        if len(motion.springs):
            self.springs = Line3DCollection(
                np.zeros((len(motion.springs), 2, 3)),
                colors=SPRING_COLOUR,
                linewidths=0.8,
                zorder=2,
            )
            ax.add_collection3d(self.springs)
        (self.points,) = ax.plot(
            [], [], [], linestyle="", marker="o", markersize=3, color=POINT_COLOUR, zorder=3
        )
        (self.touching,) = ax.plot(
            [], [], [], linestyle="", marker="o", markersize=4, color=CONTACT_COLOUR, zorder=3
        )
        self.axes = Line3DCollection(
            np.zeros((3, 2, 3)), colors=FRAME_COLOURS, linewidths=2.0, zorder=4
        )
        ax.add_collection3d(self.axes)

    def update(self, motion: Motion, i: int) -> None:
        points = motion.points[i]
        contact = motion.contact[i]
        if self.springs is not None:
            self.springs.set_segments(points[self._springs])
        free, touching = points[~contact], points[contact]
        self.points.set_data_3d(free[:, 0], free[:, 1], free[:, 2])
        self.touching.set_data_3d(touching[:, 0], touching[:, 1], touching[:, 2])
        com = motion.com[i]
        tips = com[None, :] + self._arrow * motion.frame[i].T  # rows forward, left, up
        self.axes.set_segments(np.stack([np.broadcast_to(com, (3, 3)), tips], axis=1))


def time_label(motion: Motion, i: int) -> str:
    label = f"t = {motion.ts[i]:.2f} s"
    return label if motion.pose_is_finite(i) else label + " (blew up)"
