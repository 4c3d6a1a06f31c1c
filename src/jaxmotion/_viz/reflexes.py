"""A picture of the twelve reflexes of a lattice (the first paper's Figure 3, for all axes)."""

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection

from .._body.lattice import Lattice
from .._control.deformations import AXES, DEFAULT_AMPLITUDES, KINDS
from .._control.regimes import Regimes


def reflexes(
    lattice: Lattice,
    coefficient: float = 1.0,
    *,
    amplitudes: tuple[float, float, float, float] = DEFAULT_AMPLITUDES,
    panel_size: float = 2.2,
    elev: float = 18.0,
    azim: float = -60.0,
) -> Figure:
    """Draw the twelve reflexes of `lattice`: one panel per deformation (rows scale, shear,
    splay, twist; columns along the forward, left and up axes), each showing the rest shape
    in grey and the shape deformed with `coefficient` in colour.

    **Arguments:** `lattice`; the reflex `coefficient` in `[-1, 1]`; the deformation
    `amplitudes` (as in `Regimes`); the panel size in inches and the view angles.

    **Returns:** the matplotlib Figure.
    """
    if not isinstance(lattice, Lattice):
        raise TypeError(f"reflexes draws a Lattice; got {type(lattice).__name__}")
    if not -1.0 <= coefficient <= 1.0:
        raise ValueError(f"coefficient = {coefficient!r}; allowed: -1 <= coefficient <= 1")
    controller = Regimes(
        times=np.zeros(12),
        reflexes=np.arange(12),
        coefficients=np.full(12, coefficient),
        t_per=1.0,
        amplitudes=amplitudes,
    )
    shapes = np.asarray(controller.shapes(lattice))
    rest = np.asarray(lattice.points)
    springs = np.asarray(lattice.springs)
    everything = np.concatenate([rest, shapes.reshape(-1, 3)])
    centre = 0.5 * (everything.min(0) + everything.max(0))
    half = 0.5 * float(np.max(np.ptp(everything, axis=0))) * 1.05
    fig = Figure(figsize=(3 * panel_size, 4 * panel_size))
    for r in range(12):
        ax = fig.add_subplot(4, 3, r + 1, projection="3d")
        for shape, colour, width in ((rest, "0.75", 0.8), (shapes[r], "tab:blue", 1.2)):
            ax.add_collection3d(Line3DCollection(shape[springs], colors=colour, linewidths=width))
        ax.plot(*shapes[r].T, linestyle="", marker="o", markersize=2.5, color="black")
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(f"{r}: {KINDS[r // 3]} along {AXES[r % 3]}", fontsize=9)
    fig.suptitle(f"The 12 reflexes of the {lattice.name}, coefficient {coefficient:+g}")
    fig.tight_layout()
    return fig
