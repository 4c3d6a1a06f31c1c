"""`filmstrip`: poses of one trajectory side by side, as in the papers' figures."""

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .._body.figure import Figure as ArticulatedFigure
from .._body.lattice import Lattice
from .._sim.trajectory import Trajectory
from . import scene


def filmstrip(
    trajectory: Trajectory,
    n: int = 6,
    body: Lattice | ArticulatedFigure | None = None,
    *,
    panel_size: float = 2.5,
    elev: float = 20.0,
    azim: float = -60.0,
    follow: bool = False,
    title: str | None = None,
) -> Figure:
    """`n` poses of one trajectory side by side at evenly spaced times (the first paper's
    Figures 7-9): each panel a 3D view with the springs of `body`, the floor and the body
    frame (forward red, left green, up blue), its time written under it.

    Every panel has the same scale. By default they also show the same region, the whole
    motion, so the body is seen to travel; `follow=True` centres each panel on the body
    instead (same scale still), which keeps the body large on a long walk.

    **Arguments:**

    - `trajectory`: one (unbatched) `Trajectory`.
    - `n`: how many poses; the first is at the start and the last at the end.
    - `body`: the `Lattice` or `Figure` that was simulated, to draw its springs or rods;
        `None` draws the points
        only.
    - `panel_size`: width and height of each panel, inches.
    - `elev`, `azim`: viewing angles in degrees (as `Axes3D.view_init`).
    - `follow`: centre each panel on the body's centre of mass (horizontally).
    - `title`: drawn above the strip.

    **Returns:** the `matplotlib.figure.Figure`, with one 3D axes per pose, left to right.

    **Raises:** `ValueError` for `n < 1`, a batched trajectory or a body with another number
    of masses.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"filmstrip needs n >= 1 poses (an integer); got n={n!r}")
    n = int(n)
    m = scene.motion(trajectory, body, caller="filmstrip")
    wanted = np.linspace(m.ts[0], m.ts[-1], n)
    frames = np.argmin(np.abs(m.ts[None, :] - wanted[:, None]), axis=1)
    whole = scene.view(m)

    fig = Figure(figsize=(panel_size * n, panel_size + (0.4 if title else 0.1)))
    FigureCanvasAgg(fig)  # renders without pyplot or a GUI backend
    axes = fig.subplots(1, n, squeeze=False, subplot_kw={"projection": "3d"})[0]
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.1, top=0.85 if title else 1.0, wspace=0.0)
    if title is not None:
        fig.suptitle(title)
    for ax, i in zip(axes, frames, strict=True):
        v = _followed(whole, m, int(i)) if follow else whole
        step = scene.setup_axes(ax, v, elev=elev, azim=azim)
        scene.Pose(ax, m, v).update(m, int(i))
        ax.text2D(0.5, 0.0, scene.time_label(m, int(i)), transform=ax.transAxes, ha="center")
    # Every panel has the same scale, so the same grid spacing.
    fig.text(0.995, 0.01, f"floor grid {step:g} m", ha="right", va="bottom", color="0.4")
    return fig


def _followed(whole: scene.View, m: scene.Motion, i: int) -> scene.View:
    """A view of the same size as the widest pose needs, centred horizontally on pose `i`."""
    rel = m.points - m.com[:, None, :]
    half = np.nanmax(np.abs(rel[..., :2]), axis=(0, 1)) + 0.5 * whole.arrow
    # Same size in x and y (and so equal scale) in every panel.
    half = np.full(2, np.max(half))
    centre = m.com[i, :2]
    if not np.all(np.isfinite(centre)):
        return whole
    lo = np.concatenate([centre - half, whole.lo[2:]])
    hi = np.concatenate([centre + half, whole.hi[2:]])
    return scene.View(lo=lo, hi=hi, arrow=whole.arrow)
