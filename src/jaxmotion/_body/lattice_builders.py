"""The lattices of the first paper, and a builder for your own."""

import itertools

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from .lattice import Lattice


def _on_floor(points: np.ndarray, masses) -> np.ndarray:
    """Shift a shape so its lowest point is on the floor and its centre of mass is above
    the origin."""
    m = np.broadcast_to(np.asarray(masses, dtype=float), (points.shape[0],))
    com = (points * m[:, None]).sum(0) / m.sum()
    return points - np.array([com[0], com[1], points[:, 2].min()])


def from_points(
    points: Float[ArrayLike, "num_masses 3"],
    springs: Int[ArrayLike, "num_springs 2"],
    *,
    masses: float | Float[ArrayLike, " num_masses"] = 1.0,
    stiffness: float | Float[ArrayLike, " num_springs"] = 2000.0,
    damping: float | Float[ArrayLike, " num_springs"] = 20.0,
    rest_lengths: Float[ArrayLike, " num_springs"] | None = None,
    frame: Float[ArrayLike, "3 3"] | None = None,
    name: str = "lattice",
) -> Lattice:
    """A lattice from your own points and springs, used exactly where they are.

    **Arguments:**

    - `points`: `(num_masses, 3)` positions at t = 0 (the floor is z = 0, z is up).
    - `springs`: `(num_springs, 2)` pairs of mass indices.
    - `masses`: kg, one number for all or one per mass.
    - `stiffness`, `damping`: N/m and N s/m, one number for all or one per spring.
    - `rest_lengths`: per-spring rest lengths; default the distances in `points` (no
        prestress).
    - `frame`: `(3, 3)` columns forward, left, up; default the world axes.
    - `name`: a label.

    **Raises:** `ValueError` for a spring to a missing mass, a duplicate or self spring, a
    zero-length spring, a non-positive mass, a negative stiffness or damping, or a frame that
    is not a rotation; the message names the spring or mass and its value.
    """
    return Lattice(
        points,
        springs,
        masses=masses,
        stiffness=stiffness,
        damping=damping,
        rest_lengths=rest_lengths,
        frame=frame,
        name=name,
    )


def cube(
    size: float = 1.0,
    *,
    mass: float = 1.0,
    stiffness: float = 2000.0,
    damping: float = 20.0,
) -> Lattice:
    """The first paper's Figure 1: eight masses at the corners of a cube, 28 springs.

    Springs are ordered as 12 edges, 12 face diagonals, then 4 body diagonals. The cube sits
    on the floor with its faces along the world axes; forward is +x, left +y, up +z.

    **Arguments:** `size` (edge length, m); `mass` of each corner (kg); spring `stiffness`
    (N/m) and `damping` (N s/m).
    """
    corners = np.array(list(itertools.product([0.0, 1.0], repeat=3))) * size
    pairs = list(itertools.combinations(range(8), 2))
    # Order by length: edges (size), face diagonals (size*sqrt2), body diagonals (size*sqrt3).
    pairs.sort(key=lambda p: round(float(np.linalg.norm(corners[p[1]] - corners[p[0]])), 9))
    return Lattice(
        _on_floor(corners, mass),
        np.array(pairs),
        masses=mass,
        stiffness=stiffness,
        damping=damping,
        name="cube",
    )


def pyramid(
    base: float = 1.0,
    height: float = 1.0,
    *,
    mass: float = 1.0,
    stiffness: float = 2000.0,
    damping: float = 20.0,
) -> Lattice:
    """The spider of the first paper (Figures 5 and 7): a square-based pyramid.

    Masses 0-3 are the base corners (the spider's feet), mass 4 is the apex (the top of its
    head). Springs: the 4 base edges, the 2 base diagonals (without them the base could
    shear flat) and the 4 slant edges, 10 in all. Forward is +x, along a base edge.

    **Arguments:** `base` (edge of the square base, m), `height` (apex above the base, m),
    `mass` of each point, spring `stiffness` and `damping`.
    """
    h = base / 2
    pts = np.array([[h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0], [-h, h, 0.0], [0.0, 0.0, height]])
    springs = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2), (1, 3), (0, 4), (1, 4), (2, 4), (3, 4)]
    return Lattice(
        _on_floor(pts, mass),
        np.array(springs),
        masses=mass,
        stiffness=stiffness,
        damping=damping,
        name="pyramid",
    )


def chair(
    depth: float = 1.0,
    width: float = 1.0,
    seat_height: float = 0.8,
    back_height: float = 0.8,
    *,
    mass: float = 1.0,
    stiffness: float = 2000.0,
    damping: float = 20.0,
) -> Lattice:
    """The chair-like lattice of the first paper's Figure 5: ten masses, 31 springs.

    Masses 0-3 are the feet and 4-7 the seat corners above them (front-left, front-right,
    back-right, back-left; the chair faces +x), 8 and 9 the top of the backrest above the
    back-right and back-left seat corners. Springs: 4 legs; the seat's edges and diagonals;
    the feet's edges and diagonals; crossed diagonals on the four sides; and the backrest's
    top edge, posts, crossed diagonals and two braces to the front of the seat (31 in all;
    every face is triangulated, so the lattice holds its shape at rest).

    **Arguments:** `depth` (x) and `width` (y) of the seat, `seat_height` above the floor,
    `back_height` of the backrest above the seat, all in m; `mass` of each point; spring
    `stiffness` and `damping`.
    """
    d, w = depth / 2, width / 2
    square = [(d, w), (d, -w), (-d, -w), (-d, w)]
    feet = [(x, y, 0.0) for x, y in square]
    seat = [(x, y, seat_height) for x, y in square]
    top = [(-d, -w, seat_height + back_height), (-d, w, seat_height + back_height)]
    pts = np.array(feet + seat + top)
    ring = [(0, 1), (1, 2), (2, 3), (3, 0)]
    springs = [(k, 4 + k) for k in range(4)]  # legs
    springs += [(4 + a, 4 + b) for a, b in ring] + [(4, 6), (5, 7)]  # seat
    springs += [*ring, (0, 2), (1, 3)]  # feet
    springs += [p for a, b in ring for p in ((a, 4 + b), (b, 4 + a))]  # sides
    springs += [(8, 9), (6, 8), (7, 9), (6, 9), (7, 8), (8, 5), (9, 4)]  # backrest
    return Lattice(
        _on_floor(pts, mass),
        np.array(springs),
        masses=mass,
        stiffness=stiffness,
        damping=damping,
        name="chair",
    )
