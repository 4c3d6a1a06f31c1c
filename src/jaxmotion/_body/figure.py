"""Articulated figures of rigid rods (second paper, section 2.1.1): kinematic joints, a root
that moves by rigid-body dynamics of the whole figure, penalty contact at the rod endpoints.

The formulation follows `notes/articulated-physics.md` (checked there against MuJoCo):

- each free joint angle follows `tau^2 th'' + 2 tau th' + (th - th0) = 0` toward the target
  `th0` the controller commands, and stops at the joint's range;
- the centre of mass `c` obeys `M c'' = sum of external forces` (gravity, contact);
- the angular momentum about `c`, `L` (world frame), obeys `L' = sum (p_i - c) x f_i` over the
  contact forces `f_i` at the rod endpoints `p_i`;
- the root's angular velocity follows from `L = I w + h`, with `I` the whole figure's inertia
  about `c` as it stands now and `h` the angular momentum the joint rates alone carry (rod
  centres moving and rods spinning relative to the root): internal motion changes `I` and the
  root turns so that, without contact, `L` stays what it was (a falling cat turns with
  `L = 0`).

A planar figure can have torque-limited joints instead (`Figure(max_torque=...)`): each joint
applies the torque the law asks for, clipped, and the joint angles move by Lagrangian
dynamics (`FigureDynamics._torque_limited`); the centre of mass and `L` obey the same laws.
"""

import math
from collections.abc import Sequence
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._sim.trajectory import Observation
from .._world import World, floor_force
from . import _symbolic as s
from ._senses import scales as _scales
from ._senses import signed as _signed
from ._senses import unit as _unit
from .base import AbstractBody, AbstractDynamics, BodyState


class FigurePositions(NamedTuple):
    """The positions half of a figure's state.

    - `com`: the centre of mass, world (`(3,)`; planar figures `(2,)`: x, z).
    - `orientation`: the root rod's orientation relative to the rest pose, a unit quaternion
        `(w, x, y, z)` (planar figures `(2,)`: w, y).
    - `angles`: `(num_free,)` the free joint angles, radians.
    """

    com: Float[Array, " c"]
    orientation: Float[Array, " q"]
    angles: Float[Array, " num_free"]


class FigureVelocities(NamedTuple):
    """The velocities half of a figure's state.

    - `com_velocity`: velocity of the centre of mass (`(3,)`; planar `(2,)`: x, z).
    - `momentum`: angular momentum about the centre of mass, world (`(3,)`; planar `(1,)`:
        y).
    - `angle_rates`: `(num_free,)` rates of the free joint angles, rad/s.
    """

    com_velocity: Float[Array, " c"]
    momentum: Float[Array, " m"]
    angle_rates: Float[Array, " num_free"]


class Joint(NamedTuple):
    """One joint angle of a `Figure`: rod `rod` (never the root, rod 0) turns relative to its
    parent rod by this angle about `axis`, within `[lo, hi]` (radians).

    `axis` is given in the rest pose's world coordinates and turns with the parent rod. A rod
    with two joint angles (a 3D joint, the second paper's Figure 6) turns first about the
    first one's axis, then about the second one's axis as the first rotation carried it. A
    joint with `lo == hi` is fixed at that angle: the controller does not command it and it
    costs nothing per step.
    """

    rod: int
    axis: tuple[float, float, float]
    lo: float
    hi: float


_AXIS_Y = (0.0, 1.0, 0.0)


def _fail(message: str):
    raise ValueError(message)


def _floats(name, value, shape) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"Figure.{name} = {value!r}; allowed: numbers of shape {shape}") from None
    return a


class Figure(AbstractBody):
    """An articulated figure: a tree of rigid rods joined at their endpoints (second paper).

    Each rod is a uniform solid cylinder between two nodes. Rod 0 is the root; every other rod
    starts at a node some earlier rod placed (its proximal node, where its joint is) and ends
    at a node of its own, so the rods form a tree and `num_nodes = num_rods + 1`. The rest pose
    (every joint angle 0) is given by the nodes' positions; joint angles turn rods relative to
    their parent (the earliest rod that has the proximal node), about axes given in the rest
    pose (see `Joint`).

    The state is the centre of mass and its velocity, the root's orientation (a quaternion),
    the angular momentum about the centre of mass, and the free joint angles and their rates.
    Observables: `points` are the nodes (rod endpoints, the contact points), `frame` is the
    root rod's orientation applied to the figure's `frame`.

    **Arguments:**

    - `nodes`: `(num_nodes, 3)` node positions in the rest pose (z up; the figure is placed
        with its lowest point on the floor, whatever the heights given).
    - `rods`: `(num_rods, 2)` node pairs `(proximal, distal)`; rod 0 is the root.
    - `masses`: kg per rod (one number for all, or one per rod).
    - `joints`: the joint angles (`Joint(rod, axis, lo, hi)`, radians). Rods without a joint
        are rigidly attached to their parent.
    - `radii`: rod radii (m; one for all or one per rod): the rods' inertia about their own
        axis, which keeps the figure's inertia invertible when rods line up.
    - `planar`: a planar figure moves in the world's x-z plane: its nodes have y = 0 and every
        joint turns about the y axis. Its state then carries only the planar components.
    - `frame`: the body frame at rest, columns forward, left, up (default: x, y, z).
    - `name`: a label for plots and summaries.
    - `feet`: the figure's feet, each a tuple of the nodes it stands on (a point foot one
        node, a foot rod its two), in left-right pairs (left first; a planar figure's front
        leg counts as its left). Walking terms and checks read them (a foot is down when
        any of its nodes touches the floor, and is where its nodes' mean is); default none.
    - `max_torque`: the joints' strength, N m (one number for every free joint angle, or
        one per free angle; planar figures only). `None` (the default): kinematic joints,
        the second paper's model, which follow the joint law whatever it takes. With a limit,
        each joint applies the torque the law needs to follow its target, clipped to
        `[-max_torque, max_torque]`, and the whole figure moves by Lagrangian rigid-body
        dynamics under it (see `FigureDynamics`); `0` gives limp joints.

    The start pose has every free angle at 0, or at the nearer end of its range when 0 is
    outside it.

    **Raises:** `ValueError`, naming the rod, node or joint, for a rod to a missing node or a
    node no earlier rod placed, a rod of non-positive length, mass or radius, a joint of a
    missing rod or of the root, a joint range with `lo > hi`, a zero axis, or a planar figure
    off the plane.

    The geometry is kept as constants (static fields): the simulation is traced with the
    figure's numbers built in, so zeros of a planar figure and fixed joints fold away at
    compile time (one compilation per figure).
    """

    nodes: tuple[tuple[float, float, float], ...] = eqx.field(static=True)
    rods: tuple[tuple[int, int], ...] = eqx.field(static=True)
    masses: tuple[float, ...] = eqx.field(static=True)
    radii: tuple[float, ...] = eqx.field(static=True)
    joints: tuple[Joint, ...] = eqx.field(static=True)
    planar: bool = eqx.field(static=True)
    frame: tuple[tuple[float, float, float], ...] = eqx.field(static=True)
    name: str = eqx.field(static=True)
    feet: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    max_torque: tuple[float, ...] | None = eqx.field(static=True)

    def __init__(
        self,
        nodes: Float[ArrayLike, "num_nodes 3"],
        rods: Sequence[tuple[int, int]],
        *,
        masses: float | Float[ArrayLike, " num_rods"] = 1.0,
        joints: Sequence[Joint | tuple] = (),
        radii: float | Float[ArrayLike, " num_rods"] = 0.03,
        planar: bool = False,
        frame: Float[ArrayLike, "3 3"] | None = None,
        name: str = "figure",
        feet: Sequence[Sequence[int]] = (),
        max_torque: float | Sequence[float] | None = None,
    ):
        nodes_a = _floats("nodes", nodes, "(num_nodes, 3)")
        if nodes_a.ndim != 2 or nodes_a.shape[1] != 3 or not np.all(np.isfinite(nodes_a)):
            _fail(f"Figure.nodes has shape {nodes_a.shape}; allowed: finite (num_nodes, 3)")
        try:
            rods_a = np.array(rods, dtype=np.int64)
        except (TypeError, ValueError):
            rods_a = np.zeros((0, 3))
        if rods_a.ndim != 2 or rods_a.shape[1] != 2 or rods_a.shape[0] < 1:
            _fail(f"Figure.rods = {rods!r}; allowed: at least one (proximal, distal) node pair")
        num_rods, num_nodes = rods_a.shape[0], nodes_a.shape[0]
        if num_nodes != num_rods + 1:
            _fail(
                f"Figure has {num_nodes} nodes and {num_rods} rods; a tree of rods has exactly "
                "one node more than rods"
            )
        placed: set[int] = set()
        for k, (p, d) in enumerate(rods_a.tolist()):
            for n in (p, d):
                if not 0 <= n < num_nodes:
                    _fail(
                        f"rod {k} = ({p}, {d}) uses node {n}, which does not exist "
                        f"(nodes are 0..{num_nodes - 1})"
                    )
            if k == 0:
                if p == d:
                    _fail(f"rod 0 = ({p}, {d}) joins a node to itself")
                placed.update((p, d))
                continue
            if p not in placed:
                _fail(
                    f"rod {k} = ({p}, {d}) starts at node {p}, which no earlier rod reaches; "
                    "allowed: a rod starts at a node of an earlier rod (the rods form a tree)"
                )
            if d in placed:
                _fail(
                    f"rod {k} = ({p}, {d}) ends at node {d}, which an earlier rod already "
                    "reaches; allowed: each rod ends at a new node (no loops)"
                )
            placed.add(d)
        lengths = np.linalg.norm(nodes_a[rods_a[:, 1]] - nodes_a[rods_a[:, 0]], axis=1)
        for k, length in enumerate(lengths):
            if not length > 0:
                _fail(f"rod {k} has length {length:g}; allowed: > 0 (its two nodes coincide)")
        masses_a = np.broadcast_to(_floats("masses", masses, "(num_rods,)"), (num_rods,))
        radii_a = np.broadcast_to(_floats("radii", radii, "(num_rods,)"), (num_rods,))
        for k in range(num_rods):
            if not (math.isfinite(masses_a[k]) and masses_a[k] > 0):
                _fail(f"rod {k} has mass {masses_a[k]:g}; allowed: a number > 0 (kg)")
            if not (math.isfinite(radii_a[k]) and radii_a[k] > 0):
                _fail(f"rod {k} has radius {radii_a[k]:g}; allowed: a number > 0 (m)")
        checked: list[Joint] = []
        per_rod: dict[int, int] = {}
        for j, joint in enumerate(joints):
            try:
                rod, axis, lo, hi = joint
                rod_i = int(rod)
                axis_a = np.array(axis, dtype=float).reshape(3)
                lo, hi = float(lo), float(hi)
            except (TypeError, ValueError):
                _fail(f"joint {j} = {joint!r}; allowed: Joint(rod, (ax, ay, az), lo, hi)")
            if rod_i != rod or not 0 <= rod_i < num_rods:
                _fail(
                    f"joint {j} turns rod {rod!r}, which does not exist "
                    f"(rods are 0..{num_rods - 1})"
                )
            if rod_i == 0:
                _fail(f"joint {j} turns rod 0, the root, which has no parent to turn against")
            norm = float(np.linalg.norm(axis_a))
            if not (math.isfinite(norm) and norm > 0):
                _fail(f"joint {j} (rod {rod_i}) has axis {tuple(axis_a)}; allowed: non-zero")
            if not (math.isfinite(lo) and math.isfinite(hi)):
                _fail(f"joint {j} (rod {rod_i}) has range ({lo:g}, {hi:g}); allowed: finite")
            if lo > hi:
                _fail(
                    f"joint {j} (rod {rod_i}) has range lo = {lo:g} > hi = {hi:g} (radians); "
                    "allowed: lo <= hi (lo == hi fixes the angle)"
                )
            per_rod[rod_i] = per_rod.get(rod_i, 0) + 1
            unit = tuple(float(x) for x in axis_a / norm)
            if planar and np.max(np.abs(np.array(unit) - np.array(_AXIS_Y))) > 1e-12:
                _fail(
                    f"joint {j} (rod {rod_i}) of a planar figure has axis {unit}; allowed: "
                    "(0, 1, 0) (planar figures turn about the y axis)"
                )
            checked.append(Joint(rod_i, _AXIS_Y if planar else unit, lo, hi))
        for rod_i, count in per_rod.items():
            if count > (1 if planar else 2):
                _fail(
                    f"rod {rod_i} has {count} joint angles; allowed: "
                    + ("1 (planar figure)" if planar else "at most 2 (second paper, Figure 6)")
                )
        if planar and np.any(nodes_a[:, 1] != 0):
            bad = int(np.argmax(nodes_a[:, 1] != 0))
            _fail(f"node {bad} of a planar figure has y = {nodes_a[bad, 1]:g}; allowed: y = 0")
        frame_a = np.eye(3) if frame is None else _floats("frame", frame, "(3, 3)")
        if frame_a.shape != (3, 3) or not np.allclose(frame_a.T @ frame_a, np.eye(3), atol=1e-9):
            _fail(f"Figure.frame = {frame!r}; allowed: a 3x3 rotation (orthonormal columns)")
        if np.linalg.det(frame_a) < 0:
            _fail("Figure.frame is a reflection; allowed: a right-handed rotation")
        feet_t = []
        for f, foot in enumerate(feet):
            try:
                foot_t = tuple(int(n) for n in foot)
            except (TypeError, ValueError):
                foot_t = ()
            if not foot_t or any(not 0 <= n < num_nodes for n in foot_t):
                _fail(
                    f"Figure.feet[{f}] = {foot!r}; allowed: a non-empty tuple of node indices "
                    f"0..{num_nodes - 1}"
                )
            feet_t.append(foot_t)
        # Order joints by rod (stable), so kinematics visits each rod's angles together.
        checked.sort(key=lambda jt: jt.rod)
        self.nodes = tuple(tuple(float(x) for x in row) for row in nodes_a)
        self.rods = tuple((int(p), int(d)) for p, d in rods_a.tolist())
        self.masses = tuple(float(m) for m in masses_a)
        self.radii = tuple(float(r) for r in radii_a)
        self.joints = tuple(checked)
        self.planar = bool(planar)
        self.frame = tuple(tuple(float(x) for x in row) for row in frame_a)
        self.name = str(name)
        self.feet = tuple(feet_t)
        self.max_torque = None if max_torque is None else self._check_torque(max_torque)

    def _check_torque(self, max_torque) -> tuple[float, ...]:
        if not self.planar:
            _fail(
                f"{self.name}: max_torque = {max_torque!r} on a 3D figure; allowed: None "
                "(kinematic joints); torque-limited joints are implemented for planar figures"
            )
        n = self.num_free
        limits = np.atleast_1d(_floats("max_torque", max_torque, f"() or ({n},)"))
        if limits.ndim != 1 or limits.shape[0] not in (1, n):
            _fail(
                f"Figure.max_torque = {max_torque!r}; allowed: one number or {n} (one per free "
                "joint angle), N m"
            )
        limits = np.broadcast_to(limits, (n,))
        for i, x in enumerate(limits):
            if not (math.isfinite(x) and x >= 0):
                _fail(
                    f"Figure.max_torque[{i}] = {x:g}; allowed: a finite number >= 0 (N m; "
                    "None for kinematic joints)"
                )
        return tuple(float(x) for x in limits)

    # ------------------------------------------------------------------ structure

    @property
    def num_rods(self) -> int:
        return len(self.rods)

    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    @property
    def num_points(self) -> int:
        return len(self.nodes)

    @property
    def free(self) -> tuple[int, ...]:
        """Indices (into `joints`) of the free joint angles, the ones a controller commands."""
        return tuple(j for j, jt in enumerate(self.joints) if jt.lo < jt.hi)

    @property
    def num_free(self) -> int:
        return len(self.free)

    @property
    def ranges(self) -> np.ndarray:
        """`(num_free, 2)` ranges `(lo, hi)` of the free joint angles, radians."""
        return np.array([(self.joints[j].lo, self.joints[j].hi) for j in self.free]).reshape(-1, 2)

    @property
    def start_angles(self) -> np.ndarray:
        """`(num_free,)` the free angles at t = 0: 0, or the nearer end of the range."""
        r = self.ranges
        return np.clip(0.0, r[:, 0], r[:, 1]) if len(r) else np.zeros(0)

    @property
    def mirror(self) -> tuple[tuple[int, ...], tuple[float, ...]] | None:
        """The figure's left-right mirror image as a map of its free angles, `(partner,
        sign)`: the mirror image of a pose `th` (free angles) is the pose
        `sign[i] * th[partner[i]]`. `None` for a planar figure (it has no left and right) or
        one that is not left-right symmetric.

        The mirror is the reflection across the vertical x-z plane through the middle of
        the rest pose (`y -> -y` for a figure centred at y = 0; the builders' figures face
        +x, so it swaps their left and right). Joint
        angle `i`, on the rod ending at node `n` about axis `a`, mirrors to the angle, in
        the same place of its rod's joints, on the rod ending at `n`'s reflection about the
        reflected axis `a'` (or `-a'`): a reflection turns a rotation by `th` into one by
        `-th` about the reflected axis, so a pitch (about y) keeps its sign and a roll or
        yaw (about x or z) changes it. A rod ending on the midline (a torso, a tail, a neck)
        is its own mirror. The figure is symmetric when every joint has such a partner with
        the mirrored range (a fixed angle the mirrored angle) and every node a reflection
        (lengths within 1e-6 of the figure's size).

        The map is exact for rods whose joints pivot on the midline or in mirrored places,
        and for pitch about any pivot. A midline rod hung from one side (Bob's torso from
        his left hip, Rex's tail from his right) rolls or yaws about its own pivot, so the
        mirrored angle turns it about the mirror of that pivot only up to a sideways shift
        (the pivots' distance times the angle, a few cm at those joints' ranges): the map
        is then the mirror image of the joint commands, not exactly of the pose.
        """
        images = self._mirror_images()
        return None if images is None else self._free_mirror(*images[1:])

    def _free_mirror(self, partner, sign):
        """The joints' mirror partners and signs restricted to the free angles."""
        index = {j: i for i, j in enumerate(self.free)}
        return (
            tuple(index[partner[j]] for j in self.free),
            tuple(sign[j] for j in self.free),
        )

    @property
    def sense_mirror(self) -> tuple[tuple[int, ...], tuple[bool, ...]] | None:
        """The left-right mirror image (`Figure.mirror`'s) as a map of the 3D senses,
        `(source, flip)`: the senses `S` of a motion read, in its mirror image, as
        `S'[j] = 1 - S[source[j]]` where `flip[j]`, else `S[source[j]]`. `None` where
        `Figure.mirror` is (a planar or lopsided figure), or when the figure's frame does
        not keep its left axis across the mirror plane.

        The reflection `y -> -y` (the figure frame's left axis) maps the centre of mass's
        velocity `(f, l, u)` to `(f, -l, u)`, the world's up vector in the figure frame
        alike, and the root's angular velocity, an axial vector, to `(-f, l, -u)`; a
        normalised sense `signed(x)` of a negated `x` reads `1 - signed(x)`. Each node's
        contact force and impulse is its reflection's. A free angle is `sign[i]` times its
        partner's (`Figure.mirror`); its range is its partner's mirrored, so its sense is
        the partner's, or one minus it where `sign[i] = -1`. The map is its own inverse.
        """
        images = self._mirror_images()
        if images is None:
            return None
        frame = np.array(self.frame)
        flip_y = np.diag([1.0, -1.0, 1.0])
        if not np.allclose(flip_y @ frame, frame @ flip_y, atol=1e-9):
            return None
        image, joint_partner, joint_sign = images
        partner, sign = self._free_mirror(joint_partner, joint_sign)
        n, f = self.num_nodes, self.num_free
        # height; velocity f, l, u; spin f, l, u; up f, l, u.
        source = list(range(10))
        flip = [False, False, True, False, True, False, True, False, True, False]
        for start in (10, 10 + n):  # contact[i], impulse[i]
            source += [start + image[i] for i in range(n)]
            flip += [False] * n
        source += [10 + 2 * n + partner[k] for k in range(f)]
        flip += [sign[k] < 0 for k in range(f)]
        return tuple(source), tuple(flip)

    def _mirror_images(self):
        """`(image, partner, sign)`: each node's reflection, each joint's mirror partner and
        sign (see `mirror`); `None` for a planar or lopsided figure."""
        if self.planar:
            return None
        nodes = np.array(self.nodes)
        tol = 1e-6 * max(1.0, float(np.ptp(nodes, axis=0).max()))
        centre = 0.5 * (nodes[:, 1].min() + nodes[:, 1].max())
        reflected = nodes * np.array([1.0, -1.0, 1.0]) + np.array([0.0, 2 * centre, 0.0])
        image = []
        for p in reflected:
            near = np.flatnonzero(np.linalg.norm(nodes - p, axis=1) <= tol)
            if len(near) != 1:
                return None
            image.append(int(near[0]))
        rod_ending = {d: k for k, (_, d) in enumerate(self.rods)}
        on_rod: dict[int, list[int]] = {}
        for j, joint in enumerate(self.joints):
            on_rod.setdefault(joint.rod, []).append(j)
        partner = {}
        sign = {}
        for j, joint in enumerate(self.joints):
            rod = rod_ending.get(image[self.rods[joint.rod][1]])
            twins = on_rod.get(rod, []) if rod is not None else []
            place = on_rod[joint.rod].index(j)
            if len(twins) != len(on_rod[joint.rod]):
                return None
            twin = self.joints[twins[place]]
            axis = np.array(joint.axis) * np.array([1.0, -1.0, 1.0])
            along = float(np.dot(axis, twin.axis))
            if abs(abs(along) - 1.0) > 1e-6:
                return None
            s = -1.0 if along > 0 else 1.0
            lo, hi = sorted((s * joint.lo, s * joint.hi))
            if abs(lo - twin.lo) > 1e-9 or abs(hi - twin.hi) > 1e-9:
                return None
            partner[j], sign[j] = twins[place], s
        return image, partner, sign

    @property
    def parents(self) -> tuple[int, ...]:
        """Parent rod of each rod (-1 for the root): the earliest rod reaching its proximal
        node."""
        first: dict[int, int] = {}
        out = []
        for k, (p, d) in enumerate(self.rods):
            out.append(-1 if k == 0 else first[p])
            for n in (p, d):
                first.setdefault(n, k)
        return tuple(out)

    @property
    def lengths(self) -> np.ndarray:
        n = np.array(self.nodes)
        r = np.array(self.rods)
        return np.linalg.norm(n[r[:, 1]] - n[r[:, 0]], axis=1)

    @property
    def total_mass(self) -> float:
        """Total mass, kg."""
        return float(sum(self.masses))

    @property
    def body_length(self) -> float:
        """Size of the rest pose along the forward axis, m (the unit of "body lengths")."""
        local = np.array(self.nodes) @ np.array(self.frame)
        return float(np.ptp(local[:, 0]))

    @property
    def size(self) -> float:
        """The largest extent of the rest pose, m (the scale of the senses' ranges)."""
        return float(np.max(np.ptp(np.array(self.nodes), axis=0)))

    @property
    def sense_names(self) -> tuple[str, ...]:
        """The figure's senses (see `FigureDynamics.senses` for their ranges).

        Planar figures, the second paper's Table 1: `angle[k]` for each free joint angle,
        `contact[i]` (the floor's normal force) at each node (rod endpoint), `height` and
        `vertical_velocity` of the centre of mass: `2 N + 2` for `N` rods with every joint
        free.

        3D figures, its section 4.2: `height`; `velocity_forward`, `_left`, `_up` of the
        centre of mass, the root's angular velocity `spin_*` and the world's up vector
        `up_*`, all in the figure's frame; `contact[i]` and `impulse[i]` (the collision
        impulse: force times control period) at each node; `angle[k]` for each free angle.
        """
        angles = tuple(f"angle[{k}]" for k in range(self.num_free))
        contacts = tuple(f"contact[{i}]" for i in range(self.num_nodes))
        if self.planar:
            return (*angles, *contacts, "height", "vertical_velocity")
        axes = ("forward", "left", "up")
        return (
            "height",
            *(f"velocity_{a}" for a in axes),
            *(f"spin_{a}" for a in axes),
            *(f"up_{a}" for a in axes),
            *contacts,
            *(f"impulse[{i}]" for i in range(self.num_nodes)),
            *angles,
        )

    # ------------------------------------------------------------------ kinematics

    def _rod_inertias(self):
        """The rods' `(axial, transverse)` moments of inertia about their centres (constant
        arrays): about each rod's own axis and about any axis across it."""
        m, r, length = np.asarray(self.masses), np.asarray(self.radii), self.lengths
        return m * r * r / 2, m * (3 * r * r + length * length) / 12

    def _all_angles(self, free_angles, free_rates=None):
        """Every joint angle (and rate) as scalars: free ones from the given lists, fixed ones
        as constants."""
        angles, rates = [], []
        free = {j: i for i, j in enumerate(self.free)}
        for j, jt in enumerate(self.joints):
            if j in free:
                angles.append(free_angles[free[j]])
                rates.append(0.0 if free_rates is None else free_rates[free[j]])
            else:
                angles.append(float(jt.lo))
                rates.append(0.0)
        return angles, rates

    def _kinematics(self, angles, rates):
        """Root-frame kinematics: node positions relative to the root's proximal node, rod
        orientations relative to the root, and (with rates) node velocities and rod angular
        velocities relative to the root, all as symbolic scalars."""
        nodes = [np.array(n) for n in self.nodes]
        parents = self.parents
        by_rod: dict[int, list[int]] = {}
        for j, jt in enumerate(self.joints):
            by_rod.setdefault(jt.rod, []).append(j)
        num_nodes = self.num_nodes
        pos = [None] * num_nodes
        vel = [None] * num_nodes
        orient = [None] * self.num_rods
        spin = [None] * self.num_rods
        p0, _d0 = self.rods[0]
        pos[p0], vel[p0] = s.ZERO, s.ZERO
        for k, (p, d) in enumerate(self.rods):
            if k == 0:
                g, w = s.IDENTITY, s.ZERO
            else:
                g, w = orient[parents[k]], spin[parents[k]]
                for j in by_rod.get(k, ()):
                    axis = self.joints[j].axis
                    angle, rate = angles[j], rates[j]
                    if not (s.const(rate) and rate == 0.0):
                        w = s.vadd(w, s.vscale(rate, s.matvec(g, axis)))
                    if isinstance(angle, tuple):
                        c, sn = angle  # precomputed (cos, sin)
                    elif s.const(angle):
                        c, sn = math.cos(angle), math.sin(angle)
                    else:
                        c, sn = jnp.cos(angle), jnp.sin(angle)
                    g = s.matmul(g, s.rotation(axis, c, sn))
            orient[k], spin[k] = g, w
            rest = tuple(float(x) for x in nodes[d] - nodes[p])
            seg = s.matvec(g, rest)
            pos[d] = s.vadd(pos[p], seg)
            vel[d] = s.vadd(vel[p], s.cross(w, seg))
        return pos, vel, orient, spin

    def _centre(self, pos, like):
        """Centre of mass of the figure whose nodes are at `pos` (or its velocity, given the
        nodes' velocities), and the rods' centres as a vector of `(rods, *batch)` arrays."""
        mids = _nodes([s.vscale(0.5, s.vadd(pos[p], pos[d])) for p, d in self.rods], like)
        share = _column(np.asarray(self.masses) / self.total_mass, self.num_rods, like)
        return tuple(_sum_leading(s.mul(share, x)) for x in mids), mids

    def _mass_properties(self, pos, vel, spin, like):
        """Centre of mass (root frame), its velocity relative to the root, the inertia about
        it and the angular momentum `h` of the joint motion about it (root frame), from the
        nodes' positions and velocities and the rods' angular velocities (all relative to
        the root), for all rods at once.

        A rod with direction `u` has the inertia `t 1 + (a - t) u u^T` about its centre
        (`a` axial, `t` transverse): the whole figure's inertia is the constant `sum t` on
        the diagonal plus, per rod, the dyad `(a - t) / l^2 seg seg^T` of its segment and
        the parallel-axis term; only the six distinct entries are computed.
        """
        axial, transverse = self._rod_inertias()
        com, mids = self._centre(pos, like)
        com_vel, mid_vel = self._centre(vel, like)
        column = lambda values: _column(values, self.num_rods, like)
        seg = _nodes([s.vsub(pos[d], pos[p]) for p, d in self.rods], like)
        dyad = s.vscale(column((axial - transverse) / self.lengths**2), seg)
        r = s.vsub(mids, com)
        mr = s.vscale(column(self.masses), r)
        squares = [s.mul(mr[i], r[i]) for i in range(3)]
        mrr = s.total(squares)
        entries = {}
        for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
            if i == j:
                per_rod = s.add(s.sub(mrr, squares[i]), s.mul(dyad[i], seg[i]))
                entries[i, j] = s.add(float(transverse.sum()), _sum_leading(per_rod))
            else:
                per_rod = s.sub(s.mul(dyad[i], seg[j]), s.mul(mr[i], r[j]))
                entries[i, j] = _sum_leading(per_rod)
        inertia = tuple(tuple(entries[min(i, j), max(i, j)] for j in range(3)) for i in range(3))
        spins = _nodes(spin, like)
        own = s.vadd(s.vscale(column(transverse), spins), s.vscale(s.dot(seg, spins), dyad))
        h = tuple(_sum_leading(x) for x in s.vadd(s.cross(mr, mid_vel), own))
        return com, com_vel, inertia, h

    def _chain_constants(self):
        """Constants of a planar figure's Lagrangian dynamics (torque-limited joints).

        Rod `l`'s segment `seg_l` (proximal to distal node) turns at `phi'_l = S_l . (w, th')`
        (the root's rate plus the free joint rates on its chain). A rod's centre and a node
        sit at `B seg` and `B_nodes seg` relative to the centre of mass, so the kinetic
        energy about it is `1/2 sum_lk g_lk (d seg_l / dt) . (d seg_k / dt) + 1/2 sum_l t_l
        phi'_l^2` with `g = B^T diag(m) B` and `t_l` the rod's transverse inertia.

        **Returns:** `(S, g, B_nodes, t)`: `(num_rods, 1 + num_free)`,
        `(num_rods, num_rods)`, `(num_nodes, num_rods)`, `(num_rods,)` NumPy arrays.
        """
        num_rods = self.num_rods
        path: dict[int, list[int]] = {self.rods[0][0]: []}
        for k, (p, d) in enumerate(self.rods):
            path[d] = path[p] + [k]
        centres = np.zeros((num_rods, num_rods))
        for k, (p, _d) in enumerate(self.rods):
            centres[k, path[p]] = 1.0
            centres[k, k] = 0.5
        share = np.asarray(self.masses) / self.total_mass
        com = share @ centres
        b_nodes = np.zeros((self.num_nodes, num_rods))
        for n, rods in path.items():
            b_nodes[n, rods] = 1.0
        b_rods, b_nodes = centres - com, b_nodes - com
        g = b_rods.T @ (np.asarray(self.masses)[:, None] * b_rods)
        free = {j: i for i, j in enumerate(self.free)}
        joint_of = {jt.rod: j for j, jt in enumerate(self.joints)}
        chain = np.zeros((num_rods, 1 + self.num_free))
        chain[:, 0] = 1.0
        parents = self.parents
        for k in range(num_rods):
            r = k
            while r > 0:
                if joint_of.get(r) in free:
                    chain[k, 1 + free[joint_of[r]]] = 1.0
                r = parents[r]
        return chain, g, b_nodes, self._rod_inertias()[1]

    def pose(self, angles: Float[ArrayLike, " num_free"] | None = None) -> np.ndarray:
        """`(num_nodes, 3)` node positions for the free joint angles `angles` (default: the
        start angles), root as at rest, lowest node on the floor (NumPy; for drawing and
        checks)."""
        a = self.start_angles if angles is None else np.asarray(angles, dtype=float)
        all_angles, rates = self._all_angles([float(x) for x in a])
        pos, _, _, _ = self._kinematics(all_angles, rates)
        origin = np.array(self.nodes[self.rods[0][0]])
        out = np.array([[float(c) for c in p] for p in pos]) + origin
        out[:, 2] -= out[:, 2].min()
        return out

    def rod_poses(self, positions) -> tuple[np.ndarray, np.ndarray]:
        """Every rod's whole pose (twist included) at each saved time, from the figure's
        positions state there (`Trajectory.positions`, time leading), computed as the
        simulation observes it (joint angles clamped to their ranges; NumPy, float64).

        **Arguments:**

        - `positions`: `FigurePositions` with a leading time axis on every leaf (or none:
            one instant).

        **Returns:** `(rotations, origins)`: `(num_saves, num_rods, 3, 3)` each rod's
        world orientation relative to the rest pose (a rest-pose vector `u` along the rod
        lies along `rotations[t, k] @ u` at time `t`), and `(num_saves, num_rods, 3)` the
        world position of each rod's proximal node; the distal node is `origins[t, k] +
        rotations[t, k] @ (nodes[d] - nodes[p])`. Without a time axis, the time axis is
        dropped.
        """
        com, quat, angles = (np.asarray(x, dtype=np.float64) for x in positions)
        single = com.ndim == 1
        if single:
            com, quat, angles = com[None], quat[None], angles[None]
        num = com.shape[0]
        if self.planar:
            zeros = np.zeros(num)
            com = np.stack([com[:, 0], zeros, com[:, 1]], axis=1)
            quat = np.stack([quat[:, 0], zeros, quat[:, 1], zeros], axis=1)
        ranges = self.ranges
        trig = [
            (np.cos(a), np.sin(a))
            for a in np.clip(angles, ranges[:, 0], ranges[:, 1]).T.reshape(-1, num)
        ]
        all_a, all_r = self._all_angles(trig)
        pos, _, orient, _ = self._kinematics(all_a, all_r)
        like = np.zeros(num)
        com_rel = self._centre(pos, like)[0]
        as_array = lambda v: np.stack([np.broadcast_to(np.asarray(x, float), (num,)) for x in v])
        rot = np.stack([as_array(row) for row in s.quaternion_matrix(tuple(quat.T))]).transpose(
            2, 0, 1
        )  # (num, 3, 3)
        rest_rel = np.stack([as_array(pos[p]) - as_array(com_rel) for p, _ in self.rods])
        origins = com[:, None, :] + np.einsum("tij,kjt->tki", rot, rest_rel)
        orients = np.stack(
            [np.stack([as_array(row) for row in orient[k]]) for k in range(self.num_rods)]
        ).transpose(3, 0, 1, 2)  # (num, rods, 3, 3)
        rotations = np.einsum("tij,tkjl->tkil", rot, orients)
        return (rotations[0], origins[0]) if single else (rotations, origins)

    # ------------------------------------------------------------------ state

    def initial_state(self) -> BodyState:
        return self.state()

    def state(
        self,
        *,
        com: Float[ArrayLike, "3"] | None = None,
        velocity: Float[ArrayLike, "3"] | None = None,
        orientation: Float[ArrayLike, "4"] | None = None,
        angular_velocity: Float[ArrayLike, "3"] | None = None,
        angles: Float[ArrayLike, " num_free"] | None = None,
        rates: Float[ArrayLike, " num_free"] | None = None,
    ) -> BodyState:
        """A simulation state `(positions, velocities)`: by default the start pose, at rest,
        lowest node on the floor.

        **Arguments** (all optional):

        - `com`: centre of mass (world); default above the origin's rest position so the
            lowest node touches the floor.
        - `velocity`: velocity of the centre of mass.
        - `orientation`: the root's orientation relative to the rest pose, a quaternion
            `(w, x, y, z)`; for a planar figure it must turn about y only.
        - `angular_velocity`: the root's angular velocity (world frame); it is converted to
            the angular momentum about the centre of mass, joint rates included.
        - `angles`, `rates`: free joint angles and their rates.

        The positions are `FigurePositions(com, orientation, angles)` and the velocities
        `FigureVelocities(com_velocity, momentum, angle_rates)` (the angular momentum about
        the centre of mass); a planar figure keeps only the x and z components of the
        centre of mass and its velocity, the w and y of the quaternion and the y component
        of the angular momentum.
        """
        f = self.num_free
        a = self.start_angles if angles is None else np.asarray(angles, dtype=float).reshape(f)
        ad = np.zeros(f) if rates is None else np.asarray(rates, dtype=float).reshape(f)
        q = np.array([1.0, 0, 0, 0]) if orientation is None else np.asarray(orientation, float)
        q = q / np.linalg.norm(q)
        all_a, all_r = self._all_angles([float(x) for x in a], [float(x) for x in ad])
        pos, vel, _, spin = self._kinematics(all_a, all_r)
        com_rel, _, inertia, h = self._mass_properties(pos, vel, spin, np.zeros(()))
        rot = np.array([[float(x) for x in row] for row in s.quaternion_matrix(tuple(q))])
        if com is None:
            rel = np.array([[float(c) for c in p] for p in pos]) - np.array(
                [float(c) for c in com_rel]
            )
            world_rel = rel @ rot.T
            origin = np.array(self.nodes[self.rods[0][0]]) + np.array([float(c) for c in com_rel])
            com = np.array([origin[0], origin[1], -world_rel[:, 2].min()])
        com = np.asarray(com, dtype=float).reshape(3)
        v = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=float).reshape(3)
        w = np.zeros(3) if angular_velocity is None else np.asarray(angular_velocity, float)
        inertia_a = np.array([[float(x) for x in row] for row in inertia])
        h_a = np.array([float(x) for x in h])
        # L (world) = R (I w_body + h), w_body = R^T w.
        momentum = rot @ (inertia_a @ (rot.T @ w) + h_a)
        if self.planar:
            bad = (abs(q[1]) > 1e-12 or abs(q[3]) > 1e-12, abs(com[1]) > 0 or abs(v[1]) > 0)
            if any(bad) or abs(w[0]) > 0 or abs(w[2]) > 0:
                raise ValueError(
                    f"{self.name}: a planar figure's state must stay in the x-z plane (turn "
                    "about y only, no y position or velocity)"
                )
            positions = (com[[0, 2]], q[[0, 2]], a)
            velocities = (v[[0, 2]], momentum[[1]], ad)
        else:
            positions = (com, q, a)
            velocities = (v, momentum, ad)
        cast = lambda t: tuple(jnp.asarray(x, dtype=float) for x in t)
        return BodyState(FigurePositions(*cast(positions)), FigureVelocities(*cast(velocities)))

    def dynamics(self) -> "FigureDynamics":
        return FigureDynamics(self)


_BARRIER_BLOCK = 8

# s: how fast a torque-limited joint's outward rate dies out at its stop when no controller
# gives a time constant (a passive figure).
_STOP_TIME = 0.05


def _barrier(tree):
    """Materialise the traced arrays of `tree` here.

    XLA's CPU compiler fuses a whole step of the figure's scalar arithmetic into a few huge
    loops and copies shared producers (sines, kinematic chains) into each of them; loops that
    large also stop vectorising. It removes `lax.optimization_barrier` on CPU, but it never
    fuses through a matrix product: multiplying the values by an identity matrix (exact: each
    is `1 * x` plus exact zeros) cuts the step into loops of a good size. Measured on Rex at
    500 controllers per core: 30 us per controller-step without, 3 us with; compile 60 s ->
    11 s. Blocks of `_BARRIER_BLOCK` values keep the products' cost linear in their number.
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    arrays = [i for i, x in enumerate(leaves) if not s.const(x)]
    if not arrays:
        return tree
    shape = jnp.broadcast_shapes(*(jnp.shape(leaves[i]) for i in arrays))
    for start in range(0, len(arrays), _BARRIER_BLOCK):
        block = arrays[start : start + _BARRIER_BLOCK]
        stacked = jnp.stack([jnp.broadcast_to(leaves[i], shape) for i in block])
        eye = jnp.eye(len(block), dtype=stacked.dtype)
        kept = jnp.dot(
            eye, stacked.reshape(len(block), -1), precision=jax.lax.Precision.HIGHEST
        ).reshape(stacked.shape)
        for k, i in enumerate(block):
            leaves[i] = kept[k]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _trig(angles):
    """`(cos, sin)` of each angle, computed once for all of them."""
    if not angles:
        return []
    stacked = jnp.stack(angles)
    c, sn = _barrier((jnp.cos(stacked), jnp.sin(stacked)))
    return [(c[i], sn[i]) for i in range(len(angles))]


def _nodes(vectors, like):
    """Per-node (or per-rod) vectors, a list of symbolic 3-vectors, as one vector of
    `(nodes, *batch)` arrays; a component that is zero at every node stays the constant
    0.0."""
    out = []
    for i in range(3):
        values = [v[i] for v in vectors]
        if all(s.const(x) and x == 0.0 for x in values):
            out.append(0.0)
        else:
            out.append(_broadcast(values, like))
    return tuple(out)


def _sum_leading(x):
    """Sum over the leading (node or rod) axis; a constant 0.0 stays 0.0. Written as adds of
    rows, which XLA fuses into the elementwise loops around them (a reduction would be a loop
    of its own, see `jaxmotion._sim.compile`)."""
    if s.const(x):
        return 0.0
    if isinstance(x, np.ndarray):
        return x.sum(axis=0)
    total = x[0]
    for k in range(1, x.shape[0]):
        total = total + x[k]
    return total


def _column(values, n, like):
    """Per-rod constants shaped to broadcast against `(n, *batch)` arrays."""
    return np.asarray(values, dtype=like.dtype).reshape(n, *(1,) * np.ndim(like))


def _rows_or_none(values, like):
    """`_broadcast(values, like)`, or an empty `(0, *batch)` array for no values."""
    if not values:
        return jnp.zeros((0, *like.shape), dtype=like.dtype)
    return _broadcast(values, like)


def _rows(x, n):
    return [x[i] for i in range(n)]


def _broadcast(values, like):
    xp = np if isinstance(like, np.ndarray) else jnp
    return xp.stack([xp.broadcast_to(xp.asarray(v, like.dtype), like.shape) for v in values])


def _solve_positive(a, b):
    """Solve `a x = b` for a small symmetric positive definite `a` given as nested lists of
    arrays (elementwise over their batch axes): Gaussian elimination without pivoting,
    unrolled."""
    n = len(b)
    a = [list(row) for row in a]
    b = list(b)
    for k in range(n):
        for i in range(k + 1, n):
            f = a[i][k] / a[k][k]
            for j in range(k + 1, n):
                a[i][j] = a[i][j] - f * a[k][j]
            b[i] = b[i] - f * b[k]
    x = [None] * n
    for i in reversed(range(n)):
        acc = b[i]
        for j in range(i + 1, n):
            acc = acc - a[i][j] * x[j]
        x[i] = acc / a[i][i]
    return x


class _Contact(NamedTuple):
    com: tuple
    com_vel: tuple
    angles: list
    rates: list
    state_rates: list
    quat: tuple
    rot: tuple
    w_body: tuple
    arm: tuple | None
    forces: tuple | None
    like: Array
    pos: list
    kin_rates: list
    pushing: list
    outside: list


class FigureDynamics(AbstractDynamics):
    """A `Figure` prepared for simulation (the figure itself: its geometry is constant).

    `rates` and `observe` work elementwise over any trailing batch axes.

    **Joint limits.** A joint angle at the end of its range does not move further out: its
    rate, as the rods see it, is zero while the law's rate points out of the range, and the
    law keeps acting on that rate, which turns back into the range within about `tau` (the
    targets always lie inside the range).

    **Torque-limited joints** (planar figures with `max_torque`): the joint applies the
    torque that the law's acceleration needs, clipped to `[-max_torque, max_torque]`, and
    the figure moves under it (`_torque_limited`; checked against MuJoCo in the tests). A
    joint held at its stop is rigid, as above. A weak joint lets its rod move almost on its
    own, so a contact at its tip acts on a light mass: the fixed-step solver needs a shorter
    step there than for kinematic joints (the configs that use them say what they need).
    """

    figure: Figure

    supports_batch_last: ClassVar[bool] = True

    def _unpack(self, positions, velocities=None):
        fig = self.figure
        c, q, th = positions
        if fig.planar:
            com = (c[0], 0.0, c[1])
            quat = (q[0], 0.0, q[1], 0.0)
        else:
            com = tuple(_rows(c, 3))
            quat = tuple(_rows(q, 4))
        angles = _rows(th, fig.num_free)
        if velocities is None:
            return com, quat, angles
        cd, L, thd = velocities
        if fig.planar:
            com_vel = (cd[0], 0.0, cd[1])
            momentum = (0.0, L[0], 0.0)
        else:
            com_vel = tuple(_rows(cd, 3))
            momentum = tuple(_rows(L, 3))
        return com, quat, angles, com_vel, momentum, _rows(thd, fig.num_free)

    def _limits(self, angles, rates):
        """Angles clamped to their ranges, the rates the rods see, the state's angle rates
        (zero while pushing out of the range), and per joint whether it pushes out of its
        range at its stop and whether it is beyond its range (either way the rods see no
        joint motion: the joint is held at its stop)."""
        kin_angles, kin_rates, state_rates, pushing_all, outside_all = [], [], [], [], []
        for (lo, hi), a, r in zip(self.figure.ranges, angles, rates, strict=True):
            lo, hi = float(lo), float(hi)
            pushing = ((a >= hi) & (r > 0)) | ((a <= lo) & (r < 0))
            outside = (a > hi) | (a < lo)
            kin_angles.append(jnp.clip(a, lo, hi))
            kin_rates.append(jnp.where(pushing | outside, 0.0, r))
            state_rates.append(jnp.where(pushing, 0.0, r))
            pushing_all.append(pushing)
            outside_all.append(outside)
        return kin_angles, kin_rates, state_rates, pushing_all, outside_all

    def _contact(self, positions, velocities, world: World):
        """What the rates and the senses share (computed once when both are traced
        together): the unpacked state, the root's rotation and angular velocity, and the
        floor's force at every node with its lever arm about the centre of mass."""
        fig = self.figure
        com, quat, angles, com_vel, momentum, rates = self._unpack(positions, velocities)
        kin_angles, kin_rates, state_rates, pushing, outside = self._limits(angles, rates)
        all_a, all_r = fig._all_angles(_trig(kin_angles), kin_rates)
        # What depends on the positions alone is kept apart from what depends on the
        # velocities too: the semi-implicit step evaluates the rates twice at the same
        # positions, and XLA then computes the shared part once.
        pos, vel, _, spin = fig._kinematics(all_a, all_r)
        pos = _barrier(pos)
        vel, spin = _barrier((vel, spin))
        like = positions[0][0]
        com_rel, com_rel_vel, inertia, h = fig._mass_properties(pos, vel, spin, like)
        com_rel, inertia = _barrier((com_rel, inertia))
        com_rel_vel, h = _barrier((com_rel_vel, h))
        rot = _barrier(s.quaternion_matrix(quat))
        w_body = _barrier(s.solve_symmetric(inertia, s.vsub(s.tmatvec(rot, momentum), h)))
        arm = forces = None
        if world.floor:
            # Contact at every node, all nodes at once (leading node axis): world positions
            # and velocities relative to the com.
            rel = s.vsub(_nodes(pos, like), com_rel)
            rel_vel = s.vadd(s.cross(w_body, rel), s.vsub(_nodes(vel, like), com_rel_vel))
            arm = s.matvec(rot, rel)
            px, py, pz = s.vadd(com, arm)
            vx, vy, vz = s.vadd(com_vel, s.matvec(rot, rel_vel))
            fx, fy, fz = floor_force(world, px, py, pz, vx, vy, vz)
            forces = (fx, 0.0 if fig.planar else fy, fz)
        return _Contact(
            com,
            com_vel,
            angles,
            rates,
            state_rates,
            quat,
            rot,
            w_body,
            arm,
            forces,
            like,
            pos,
            kin_rates,
            pushing,
            outside,
        )

    def rates(self, state, actuation, world: World) -> BodyState:
        fig = self.figure
        positions, _ = state
        c = self._contact(*state, world)
        force, torque = s.ZERO, s.ZERO
        if c.forces is not None:
            force = tuple(_sum_leading(f) for f in c.forces)
            torque = tuple(_sum_leading(t) for t in s.cross(c.arm, c.forces))
        m = fig.total_mass
        acc = (
            s.mul(1.0 / m, force[0]),
            s.mul(1.0 / m, force[1]),
            s.sub(s.mul(1.0 / m, force[2]), world.gravity),
        )
        q_rate = s.quaternion_rate(c.quat, c.w_body)
        angles, rates = c.angles, c.rates
        if actuation is None:
            angle_acc = [jnp.zeros_like(r) for r in rates]
        else:
            target, tau = actuation
            angle_acc = [
                (target[i] - angles[i] - 2.0 * tau * rates[i]) / (tau * tau)
                for i in range(fig.num_free)
            ]
        if fig.max_torque is not None and fig.num_free:
            stop_time = _STOP_TIME if actuation is None else actuation[1]
            angle_acc = self._torque_limited(c, angle_acc, stop_time)
        pack = lambda values: _broadcast(values, c.like)
        th = positions[2]
        com_vel = c.com_vel
        if fig.planar:
            d_pos = (pack([com_vel[0], com_vel[2]]), pack([q_rate[0], q_rate[2]]))
            d_vel = (pack([acc[0], acc[2]]), pack([torque[1]]))
        else:
            d_pos = (pack(com_vel), pack(q_rate))
            d_vel = (pack(acc), pack(torque))
        if fig.num_free:
            d_th, d_thd = jnp.stack(c.state_rates), jnp.stack(angle_acc)
        else:
            d_th, d_thd = jnp.zeros_like(th), jnp.zeros_like(th)
        return BodyState(FigurePositions(*d_pos, d_th), FigureVelocities(*d_vel, d_thd))

    def _torque_limited(self, c: _Contact, desired: list, stop_time) -> list:
        """The joint accelerations a planar figure's torque-limited joints give, from the
        accelerations `desired` that the joint law asks for.

        The figure's angular motion about its centre of mass, in the coordinates `psi =
        (root angle, free joint angles)`, obeys Lagrange's equations `M(psi) psi'' + b = (0,
        tau)`: `M = S^T N S` with `N_ll' = g_ll' seg_l . seg_l' + delta_ll' t_l` (see
        `Figure._chain_constants`), and `b = S^T (Gamma - Q)` with the velocity terms
        `Gamma_l = -sum g_ll' phi'_l'^2 (y x seg_l) . seg_l'` and the floor's generalised
        forces `Q_l = (y x seg_l) . sum_i B_il f_i` (uniform gravity exerts none about the
        centre of mass). The root row has no actuator (it is `L' = torque`, which the state
        already integrates); eliminating it leaves the joints' `K th'' + beta = tau`. The
        joints apply the torque `K th''_desired + beta` the law needs, clipped to
        `max_torque`, and move by `th'' = th''_desired + K^-1 (tau - tau_needed)`. A joint
        held at its stop does not move: it leaves the system (its stop takes any torque).
        Its state rate (pushing out of the range) dies out over `stop_time` (the law's time
        constant), and turns back into the range only when the joint, were it free, would
        accelerate that way: a weak joint that a load presses into its stop stays there
        (were it to leave whenever the law's rate turned, as a kinematic joint does, it
        would chatter in and out of the stop, and an adaptive solver stalls there).
        """
        fig = self.figure
        chain, g, b_nodes, inertia = fig._chain_constants()
        like = c.like
        extra = (1,) * like.ndim
        const = lambda a: jnp.asarray(a, dtype=like.dtype).reshape(a.shape + extra)
        n = fig.num_free
        seg = [
            _broadcast([s.sub(c.pos[d][i], c.pos[p][i]) for p, d in fig.rods], like) for i in (0, 2)
        ]
        sx, sz = seg
        dots = sx[:, None] * sx[None, :] + sz[:, None] * sz[None, :]
        turned = sz[:, None] * sx[None, :] - sx[:, None] * sz[None, :]  # (y x seg_l) . seg_l'
        inertia_matrix = const(g) * dots + const(np.diag(inertia))
        velocity = _broadcast([c.w_body[1], *c.kin_rates], like)
        spin = jnp.einsum("la,a...->l...", chain, velocity)
        bias = -jnp.einsum("lm...,m...->l...", const(g) * turned, spin * spin)
        if c.forces is not None:
            fx, _, fz = s.tmatvec(c.rot, c.forces)
            fx, fz = (jnp.einsum("il,i...->l...", b_nodes, f) for f in (fx, fz))
            bias = bias - (sz * fx - sx * fz)
        m = jnp.einsum("la,lm...,mb->ab...", chain, inertia_matrix, chain)
        b = jnp.einsum("la,l...->a...", chain, bias)
        k = m[1:, 1:] - m[1:, :1] * m[:1, 1:] / m[0, 0]
        beta = b[1:] - m[1:, 0] * b[0] / m[0, 0]
        eye = const(np.eye(n)) > 0.5
        limit = const(np.asarray(fig.max_torque))
        wanted_all = jnp.stack(desired)

        def accelerations(held):
            k_held = jnp.where(held[:, None] | held[None, :], eye, k)
            wanted = jnp.where(held, 0.0, wanted_all)
            needed = jnp.einsum("ij...,j...->i...", k_held, wanted) + beta
            excess = jnp.where(held, 0.0, jnp.clip(needed, -limit, limit) - needed)
            rows = [[k_held[i, j] for j in range(n)] for i in range(n)]
            return wanted_all + jnp.stack(_solve_positive(rows, _rows(excess, n)))

        pushing = jnp.stack(c.pushing)
        moving = accelerations(pushing | jnp.stack(c.outside))
        # A joint pushing into its stop: what it would do if it were free decides when it
        # leaves (a weak joint under a load stays), and its outward state rate dies out.
        free = accelerations(jnp.zeros_like(pushing))
        out = []
        for i, r in enumerate(c.rates):
            leave = jnp.where(r > 0, jnp.minimum(free[i], 0.0), jnp.maximum(free[i], 0.0))
            out.append(jnp.where(c.pushing[i], leave - r / stop_time, moving[i]))
        return out

    def senses(self, state, world: World, control_dt: float):
        """The figure's senses, normalised to [0, 1] and clipped (`Figure.sense_names`).
        With `size` the rest pose's largest extent, `M` the total mass, `g` the world's
        gravity (9.81 m/s^2 without it) and `v = sqrt(2 g size)` (the speed of a fall
        through the body's size):

        - `angle[k]`: the free angle over its range `[lo, hi]`;
        - `contact[i]`: the floor's normal force at node `i` over `[0, M g]` (the whole
            weight);
        - `impulse[i]` (3D): that force times the control period over `[0, M v]` (the
            momentum of the whole body at speed `v`; with a penalty floor the collision
            impulse is the force over the tick);
        - `height`: the centre of mass's height over `[0, 2 size]`;
        - `vertical_velocity` (planar), `velocity_*` (3D, figure frame): over `[-v, v]`;
        - `spin_*` (3D): the root's angular velocity in the figure frame over
            `[-2 v / size, 2 v / size]`;
        - `up_*` (3D): the world's up axis in the figure frame, each over `[-1, 1]`.
        """
        fig = self.figure
        c = self._contact(*state, world)
        g, v_scale = _scales(world, fig.size)
        weight = g * fig.total_mass
        like = c.like
        if c.forces is None:
            fn = jnp.zeros((fig.num_nodes, *like.shape), dtype=like.dtype)
        else:
            fn = c.forces[2]
        contact = jnp.clip(fn / weight, 0.0, 1.0)
        ranges = fig.ranges
        angles = [
            _unit(a, float(lo), float(hi)) for (lo, hi), a in zip(ranges, c.angles, strict=True)
        ]
        height = _unit(c.com[2], 0.0, 2.0 * fig.size)
        angles = _rows_or_none(angles, like)
        if fig.planar:
            tail = [height, _signed(c.com_vel[2], v_scale)]
            return jnp.concatenate([angles, contact, _broadcast(tail, like)])
        # The figure frame F = R frame0: a world vector u reads frame0^T R^T u in it.
        frame0 = fig.frame
        to_figure = lambda u: s.tmatvec(frame0, s.tmatvec(c.rot, u))
        velocity = to_figure(c.com_vel)
        spin = s.tmatvec(frame0, c.w_body)
        up = s.tmatvec(frame0, c.rot[2])
        w_scale = 2.0 * v_scale / fig.size
        head = [
            height,
            *(_signed(x, v_scale) for x in velocity),
            *(_signed(x, w_scale) for x in spin),
            *(_signed(x, 1.0) for x in up),
        ]
        impulse = jnp.clip(fn * control_dt / (fig.total_mass * v_scale), 0.0, 1.0)
        return jnp.concatenate([_broadcast(head, like), contact, impulse, angles])

    def observe(self, positions, world: World) -> Observation:
        fig = self.figure
        com, quat, angles = self._unpack(positions)
        kin_angles = [
            jnp.clip(a, float(lo), float(hi))
            for (lo, hi), a in zip(fig.ranges, angles, strict=True)
        ]
        all_a, all_r = fig._all_angles(_trig(kin_angles))
        pos = _barrier(fig._kinematics(all_a, all_r)[0])
        like = positions[0][0]
        com_rel = _barrier(fig._centre(pos, like)[0])
        rot = _barrier(s.quaternion_matrix(quat))
        world_points = s.vadd(com, s.matvec(rot, s.vsub(_nodes(pos, like), com_rel)))
        points = jnp.stack(
            [jnp.broadcast_to(c, (fig.num_nodes, *like.shape)) for c in world_points], axis=1
        )  # (num_nodes, 3, *batch)
        frame = s.matmul(rot, fig.frame)
        frame = jnp.stack([_broadcast(row, like) for row in frame])
        if world.floor:
            contact = points[:, 2] < 0
        else:
            contact = jnp.zeros((fig.num_nodes, *like.shape), dtype=bool)
        return Observation(points=points, com=_broadcast(com, like), frame=frame, contact=contact)
