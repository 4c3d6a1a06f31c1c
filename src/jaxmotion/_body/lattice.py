"""Mass-spring lattices (the first paper's bodies)."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._sim.system import computed_here
from .._sim.trajectory import Observation
from .._world import World, floor_force
from ._frame import polar_rotation
from ._senses import scales as _scales
from ._senses import signed as _signed
from ._senses import unit as _unit
from .base import AbstractBody, AbstractDynamics, BodyState


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _fmt(values) -> str:
    return "(" + ", ".join(f"{float(v):g}" for v in values) + ")"


class Lattice(AbstractBody):
    """A 3D mass-spring lattice: point masses joined by damped linear springs.

    Each spring pulls its two masses together with the tension
    `k (length - rest_length) + d * d(length)/dt` along the line between them (tension
    positive; the damping term resists any change of length, so it only ever dissipates
    energy). Actuation changes the rest lengths; the first paper's reflexes compute them from
    a deformed copy of the rest shape.

    **Fields:**

    - `points`: `(num_masses, 3)` rest shape, which is also the pose at t = 0 (builders put
        the lowest mass on the floor, z = 0, and the centre of mass above the origin).
    - `masses`: `(num_masses,)` masses in kg.
    - `springs`: `(num_springs, 2)` integer index pairs.
    - `stiffness`, `damping`, `rest_lengths`: `(num_springs,)` per-spring constants.
    - `frame`: `(3, 3)` the lattice-centric frame; columns are the forward, left and up axes
        in world coordinates at rest (right-handed, orthonormal). The reflexes deform along
        these axes and the objectives measure "forward" and "upright" with them.
    - `name`: a label for plots and summaries.

    Build one with `jaxmotion.lattices.cube()`, `pyramid()`, `chair()` or `from_points()`.
    Constructing a `Lattice` checks it: a spring to a missing mass, a duplicate spring, a
    zero-length spring, a non-positive mass or a non-orthonormal frame is a `ValueError`
    naming the spring or mass and its value.
    """

    points: Float[Array, "num_masses 3"]
    masses: Float[Array, " num_masses"]
    springs: Int[Array, "num_springs 2"]
    stiffness: Float[Array, " num_springs"]
    damping: Float[Array, " num_springs"]
    rest_lengths: Float[Array, " num_springs"]
    frame: Float[Array, "3 3"]
    name: str = eqx.field(static=True)

    def __init__(
        self,
        points: Float[ArrayLike, "num_masses 3"],
        springs: Int[ArrayLike, "num_springs 2"],
        *,
        masses: float | Float[ArrayLike, " num_masses"] = 1.0,
        stiffness: float | Float[ArrayLike, " num_springs"] = 2000.0,
        damping: float | Float[ArrayLike, " num_springs"] = 20.0,
        rest_lengths: Float[ArrayLike, " num_springs"] | None = None,
        frame: Float[ArrayLike, "3 3"] | None = None,
        name: str = "lattice",
    ):
        if _concrete(points, springs, masses, stiffness, damping, rest_lengths, frame):
            points, springs, masses, stiffness, damping, rest_lengths, frame = _validated(
                points, springs, masses, stiffness, damping, rest_lengths, frame
            )
        self.points = jnp.asarray(points, dtype=float)
        self.springs = jnp.asarray(springs, dtype=jnp.int32)
        n, s = self.points.shape[0], self.springs.shape[0]
        self.masses = jnp.broadcast_to(jnp.asarray(masses, dtype=float), (n,))
        self.stiffness = jnp.broadcast_to(jnp.asarray(stiffness, dtype=float), (s,))
        self.damping = jnp.broadcast_to(jnp.asarray(damping, dtype=float), (s,))
        if rest_lengths is None:
            d = self.points[self.springs[:, 1]] - self.points[self.springs[:, 0]]
            rest_lengths = jnp.sqrt(jnp.sum(d * d, axis=-1))
        self.rest_lengths = jnp.asarray(rest_lengths, dtype=float)
        self.frame = jnp.eye(3) if frame is None else jnp.asarray(frame, dtype=float)
        self.name = str(name)

    @property
    def num_masses(self) -> int:
        return self.points.shape[0]

    @property
    def num_springs(self) -> int:
        return self.springs.shape[0]

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def total_mass(self) -> float:
        """Total mass, kg."""
        return float(np.sum(np.asarray(self.masses, dtype=np.float64)))

    @property
    def com(self) -> Float[Array, "3"]:
        """Centre of mass of the rest shape."""
        return jnp.sum(self.points * self.masses[:, None], axis=0) / jnp.sum(self.masses)

    @property
    def extent(self) -> Float[Array, "3"]:
        """Size of the rest shape along the frame's forward, left and up axes."""
        local = (self.points - self.com) @ self.frame
        return jnp.max(local, axis=0) - jnp.min(local, axis=0)

    @property
    def body_length(self) -> float:
        """Size of the rest shape along its forward axis, m (the unit of "body lengths")."""
        return float(np.asarray(self.extent)[0])

    @property
    def size(self) -> float:
        """The largest extent of the rest shape, m (the scale of the senses' ranges)."""
        return float(np.max(np.asarray(self.extent)))

    @property
    def sense_names(self) -> tuple[str, ...]:
        """The lattice's senses (the kinds the second paper gives 3D figures, section 4.2):
        `height` of the centre of mass; its `velocity_forward`, `_left`, `_up` and the
        world's up vector `up_forward`, `_left`, `_up` in the lattice's frame; the normal
        `contact[i]` force on each mass. See `LatticeDynamics.senses` for their ranges."""
        axes = ("forward", "left", "up")
        return (
            "height",
            *(f"velocity_{a}" for a in axes),
            *(f"up_{a}" for a in axes),
            *(f"contact[{i}]" for i in range(self.num_masses)),
        )

    def rest_length_matrix(self, shape: Float[ArrayLike, "num_masses 3"] | None = None):
        """Dense `(num_masses, num_masses)` table of rest lengths for a deformed rest shape.

        Each spring's rest length is scaled by how much the deformation stretches the line
        between its masses (`rest_length * |p'_j - p'_i| / |p_j - p_i|`), so the identity
        deformation gives back `rest_lengths` exactly, even for prestressed lattices. Entries
        of pairs without a spring are 1 (they are never used).
        """
        i, j = self.springs[:, 0], self.springs[:, 1]
        rest = self.rest_lengths
        if shape is not None:
            shape = jnp.asarray(shape)
            d_new = shape[j] - shape[i]
            d_old = self.points[j] - self.points[i]
            ratio = jnp.sqrt(jnp.sum(d_new * d_new, -1) / jnp.sum(d_old * d_old, -1))
            rest = rest * ratio
        n = self.num_masses
        table = jnp.ones((n, n), dtype=rest.dtype)
        return table.at[i, j].set(rest).at[j, i].set(rest)

    def initial_state(self) -> BodyState:
        return self.state()

    def state(
        self,
        *,
        points: Float[ArrayLike, "num_masses 3"] | None = None,
        velocities: Float[ArrayLike, "num_masses 3"] | None = None,
    ) -> BodyState:
        """A simulation state for `simulate(..., initial_state=...)`: the masses at `points`
        (default: the rest shape) moving with `velocities` (default: at rest). Its
        `positions` and `velocities` are `(3, num_masses)` arrays (components first)."""
        x = jnp.transpose(self.points if points is None else jnp.asarray(points, dtype=float))
        v = jnp.zeros_like(x) if velocities is None else jnp.transpose(jnp.asarray(velocities))
        if x.shape != (3, self.num_masses) or v.shape != x.shape:
            raise ValueError(
                f"Lattice.state needs points and velocities of shape ({self.num_masses}, 3)"
            )
        return BodyState(x, v.astype(x.dtype))

    def dynamics(self) -> "LatticeDynamics":
        n = self.num_masses
        i, j = self.springs[:, 0], self.springs[:, 1]
        zeros = jnp.zeros((n, n), dtype=self.points.dtype)
        stiffness = zeros.at[i, j].set(self.stiffness).at[j, i].set(self.stiffness)
        damping = zeros.at[i, j].set(self.damping).at[j, i].set(self.damping)
        no_spring = jnp.ones((n, n), dtype=self.points.dtype).at[i, j].set(0.0).at[j, i].set(0.0)
        rest_rel = jnp.transpose(self.points - self.com)
        return LatticeDynamics(
            masses=self.masses,
            stiffness=stiffness,
            damping=damping,
            rest=self.rest_length_matrix(),
            no_spring=no_spring,
            rest_rel=rest_rel,
            frame0=self.frame,
            size=jnp.max(self.extent),
        )


class LatticeDynamics(AbstractDynamics):
    """A lattice prepared for simulation: springs as dense `(n, n)` tables.

    State layout: positions and velocities as `(3, num_masses)` arrays (components first,
    so the batched step works on whole component vectors; see `perf-lab`).
    """

    masses: Float[Array, " n"]
    stiffness: Float[Array, "n n"]
    damping: Float[Array, "n n"]
    rest: Float[Array, "n n"]
    no_spring: Float[Array, "n n"]
    rest_rel: Float[Array, "3 n"]
    frame0: Float[Array, "3 3"]
    size: Float[Array, ""]

    supports_batch_last: ClassVar[bool] = True

    def rates(self, state, actuation, world: World):
        x, v = state
        # Any axes after (3, n) are batch axes (the fast path's batch-last layout): the
        # lattice's own tables get matching trailing singleton axes and broadcast.
        extra = x.ndim - 2
        own = lambda a: a.reshape(a.shape + (1,) * extra)
        rest = own(self.rest) if actuation is None else actuation
        stiffness, damping, no_spring = own(self.stiffness), own(self.damping), own(self.no_spring)
        px, py, pz = x[0], x[1], x[2]
        vx, vy, vz = v[0], v[1], v[2]
        fx, fy, fz = _spring_forces(x, v, rest, stiffness, damping, no_spring)
        cx, cy, cz = floor_force(world, px, py, pz, vx, vy, vz)
        inv_m = own(1.0 / self.masses)
        ax = (fx + cx) * inv_m
        ay = (fy + cy) * inv_m
        az = (fz + cz) * inv_m - world.gravity
        return BodyState(v, jnp.stack([ax, ay, az]))

    def _com(self, x):
        """Mass-weighted mean over the masses of `(3, n, *batch)`: `(3, *batch)`."""
        n = x.shape[1]
        masses = [self.masses[k] for k in range(n)]
        return sum(masses[k] * x[:, k] for k in range(n)) / sum(masses)

    def _frame(self, x, com):
        """The body frame `(3, 3, *batch)` of masses at `x` with centre of mass `com`: the
        rotation that best maps the rest shape onto them, applied to the rest frame."""
        n = x.shape[1]
        masses = [self.masses[k] for k in range(n)]
        rel = x - com[:, None]
        # h[a, c] = sum_k m_k rel[a, k] rest_rel[c, k]
        h = jnp.stack(
            [
                jnp.stack(
                    [
                        sum(masses[k] * self.rest_rel[c, k] * rel[a, k] for k in range(n))
                        for c in range(3)
                    ]
                )
                for a in range(3)
            ]
        )
        rotation = polar_rotation(h)
        # frame = rotation @ frame0, with the batch axes trailing.
        return jnp.stack(
            [
                jnp.stack(
                    [sum(rotation[a, b] * self.frame0[b, c] for b in range(3)) for c in range(3)]
                )
                for a in range(3)
            ]
        )

    def senses(self, state, world: World, control_dt: float):
        """The lattice's senses, normalised to [0, 1] and clipped (`Lattice.sense_names`):

        - `height`: the centre of mass's height over `[0, 2 size]` (`size`: the rest shape's
            largest extent);
        - `velocity_*`: its velocity in the lattice frame over `[-v, v]`,
            `v = sqrt(2 g size)` (the speed of a fall through the body's size; `g` is the
            world's gravity, or 9.81 m/s^2 without it);
        - `up_*`: the world's up axis in the lattice frame, each component over `[-1, 1]`;
        - `contact[i]`: the floor's normal force on mass `i` over `[0, M g]` (the whole
            weight).
        """
        del control_dt
        x, v = state
        g, v_scale = _scales(world, self.size)
        com = self._com(x)
        com_vel = self._com(v)
        frame = self._frame(x, com)
        # Velocity and up axis in the lattice frame: frame^T applied.
        velocity = [sum(frame[a, c] * com_vel[a] for a in range(3)) for c in range(3)]
        up = [frame[2, c] for c in range(3)]
        if world.floor:
            _, _, fn = floor_force(world, x[0], x[1], x[2], v[0], v[1], v[2])
        else:
            fn = jnp.zeros_like(x[2])
        weight = g * jnp.sum(self.masses)
        return jnp.concatenate(
            [
                jnp.stack(
                    [
                        _unit(com[2], 0.0, 2.0 * self.size),
                        *(_signed(c, v_scale) for c in velocity),
                        *(_signed(c, 1.0) for c in up),
                    ]
                ),
                jnp.clip(fn / weight, 0.0, 1.0),
            ]
        )

    def observe(self, positions, world: World) -> Observation:
        # Written for positions (3, n, *batch) with any trailing batch axes (time, controllers):
        # everything is elementwise over them, with explicit sums over the masses, so it
        # vectorises and gives each sample the same rounding whatever the batch.
        x = positions
        com = self._com(x)  # (3, *batch)
        frame = self._frame(x, com)
        if world.floor:
            contact = x[2] < 0
        else:
            contact = jnp.zeros(x.shape[1:], dtype=bool)
        return Observation(points=jnp.swapaxes(x, 0, 1), com=com, frame=frame, contact=contact)


def _rows(table):
    """`table[:, 0] + table[:, 1] + ...`: the sum over a pair table's second (partner) axis,
    written as explicit adds, which fuse into the elementwise loops of the batch-last layout
    (XLA's reduction over a middle axis does not)."""
    return sum(table[:, k] for k in range(table.shape[1]))


def _differences(a):
    """The pair tables of a per-mass vector `(3, n, ...)`: one `(n, n, ...)` table per
    component, entry `[i, j]` is `a_j - a_i`."""
    return [a[c][None] - a[c][:, None] for c in range(a.shape[0])]


def _pairs(x, v, rest, stiffness, damping, no_spring):
    """Per pair `[i, j]`: the separation `d = x_j - x_i`, its rate, the inverse length and
    the tension per length `w = (k (L - r) + c dL/dt) / L`."""
    d, dv = _differences(x), _differences(v)
    # `no_spring` keeps the diagonal and unconnected pairs away from 0/0; their stiffness
    # and damping are zero, so they exert nothing.
    length = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + no_spring)
    inv = 1.0 / length
    dot = dv[0] * d[0] + dv[1] * d[1] + dv[2] * d[2]
    w = (stiffness * (length - rest) + damping * (dot * inv)) * inv
    return d, dv, length, inv, dot, w


@jax.custom_vjp
def _spring_forces(x, v, rest, stiffness, damping, no_spring):
    """The springs' force on every mass, `(fx, fy, fz)`, each `(n, ...)`: mass i feels
    `sum_j w_ij (x_j - x_i)`.

    Its reverse-mode derivative is written out (`_spring_forces_bwd`) in the same form,
    sums over partners of per-pair terms: JAX's own transposes the pair tables' slices
    into padded tables, and XLA recomputed the pair arithmetic for each of them (a
    backward pass of 30-100 forward passes on the cube). Checked against JAX's own in the
    tests."""
    d, _, _, _, _, w = _pairs(x, v, rest, stiffness, damping, no_spring)
    return tuple(_rows(w * d[c]) for c in range(3))


def _spring_forces_fwd(x, v, rest, stiffness, damping, no_spring):
    inputs = (x, v, rest, stiffness, damping, no_spring)
    return _spring_forces(*inputs), inputs


def _spring_forces_bwd(inputs, g):
    x, v, rest, stiffness, damping, no_spring = inputs
    # The inputs are residuals, read from the stack a backward pass keeps them in:
    # computed once here (`computed_here`), or XLA slices them out of the stack in every
    # loop below, and those loops ran several times slower.
    x, v, rest = computed_here(x), computed_here(v), computed_here(rest)
    g = computed_here(jnp.stack(g))
    d, dv, length, inv, dot, w = _pairs(x, v, rest, stiffness, damping, no_spring)
    # The force on mass i is sum_j w_ij d_ij with d_ij = x_j - x_i, w = (k (L - r) + c s) / L,
    # s = (dv . d) / L, L = sqrt(d . d + no_spring). With the force's cotangent g, pair
    # [i, j] contributes w (g_i . d) to the loss, whose derivatives along the chain are
    # (g_i . d) times: dw/dd = alpha d + beta dv, dw/d(dv) = beta d, dw/dr = -k / L, with
    # alpha = (k - w - c s / L) / L^2 and beta = c / L^2. Mass m's position appears in
    # every d_mk (as -x_m) and d_km (as +x_m); with d_km = -d_mk, dv_km = -dv_mk and the
    # pair scalars symmetric (as every lattice's tables are), the two collect into terms
    # of the cotangent differences dg = g_k - g_m:
    #   x_bar_m = sum_k w dg + (dg . d)(alpha d + beta dv),   v_bar_m = sum_k beta (dg . d) d.
    dg = _differences(g)
    gd = g[0][:, None] * d[0] + g[1][:, None] * d[1] + g[2][:, None] * d[2]  # g_i . d_ij
    dgd = dg[0] * d[0] + dg[1] * d[1] + dg[2] * d[2]
    inv2 = inv * inv
    alpha = (stiffness - w - damping * dot * inv2) * inv2
    beta = damping * inv2
    x_bar = jnp.stack([_rows(w * dg[c] + dgd * (alpha * d[c] + beta * dv[c])) for c in range(3)])
    v_bar = jnp.stack([_rows(beta * dgd * d[c]) for c in range(3)])
    tension_bar = gd * inv  # the cotangent of k (L - r) + c s
    return (
        x_bar,
        v_bar,
        _sum_to(-tension_bar * stiffness, rest),
        _sum_to(tension_bar * (length - rest), stiffness),
        _sum_to(tension_bar * dot * inv, damping),
        _sum_to(gd * alpha * 0.5, no_spring),  # dL/d(no_spring) = 1 / (2 L)
    )


_spring_forces.defvjp(_spring_forces_fwd, _spring_forces_bwd)


def _sum_to(cotangent, like):
    """`cotangent` summed over the axes `like` broadcasts along (a lattice's own tables
    carry singleton batch axes)."""
    axes = tuple(
        k
        for k, (a, b) in enumerate(zip(cotangent.shape, jnp.shape(like), strict=True))
        if a != b and b == 1
    )
    return jnp.sum(cotangent, axis=axes, keepdims=True) if axes else cotangent


def _validated(points, springs, masses, stiffness, damping, rest_lengths, frame):
    """Check a lattice's arrays; raise `ValueError` naming the offending entry."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 2:
        raise ValueError(
            f"Lattice points must be an array of shape (num_masses, 3) with at least 2 masses; "
            f"got shape {pts.shape}"
        )
    n = pts.shape[0]
    bad = np.flatnonzero(~np.all(np.isfinite(pts), axis=1))
    if bad.size:
        k = int(bad[0])
        raise ValueError(f"mass {k} has a non-finite position {_fmt(pts[k])}")
    spr = np.asarray(springs)
    if spr.ndim != 2 or spr.shape[1] != 2 or spr.shape[0] < 1:
        raise ValueError(
            f"Lattice springs must be an array of shape (num_springs, 2) with at least one "
            f"spring; got shape {spr.shape}"
        )
    if not np.issubdtype(spr.dtype, np.integer):
        if not np.all(np.isfinite(spr)) or np.any(spr != np.round(spr)):
            raise ValueError(f"Lattice springs must be integer mass indices; got {spr.tolist()}")
        spr = spr.astype(np.int64)
    seen: dict[tuple[int, int], int] = {}
    for s, (a, b) in enumerate(spr.tolist()):
        for m in (a, b):
            if not 0 <= m < n:
                raise ValueError(
                    f"spring {s} = ({a}, {b}) refers to mass {m}, which does not exist: the "
                    f"lattice has {n} masses, numbered 0 to {n - 1}"
                )
        if a == b:
            raise ValueError(f"spring {s} = ({a}, {b}) connects mass {a} to itself")
        key = (min(a, b), max(a, b))
        if key in seen:
            t = seen[key]
            raise ValueError(
                f"spring {s} = ({a}, {b}) duplicates spring {t} = {tuple(spr[t].tolist())}"
            )
        seen[key] = s
    ns = spr.shape[0]

    def per(name, quantity, value, count, what, *, positive):
        arr = np.asarray(value, dtype=float)
        try:
            arr = np.broadcast_to(arr, (count,))
        except ValueError:
            raise ValueError(
                f"Lattice {name} must be a number or an array of {count} values (one per "
                f"{what}); got shape {np.shape(value)}"
            ) from None
        bad = np.flatnonzero(~np.isfinite(arr) | ((arr <= 0) if positive else (arr < 0)))
        if bad.size:
            k = int(bad[0])
            rule = "> 0" if positive else ">= 0"
            label = f"spring {k} = {tuple(spr[k].tolist())}" if what == "spring" else f"mass {k}"
            raise ValueError(f"{label} has {quantity} {arr[k]:g}; allowed: a finite number {rule}")
        return arr

    m = per("masses", "mass", masses, n, "mass", positive=True)
    k = per("stiffness", "stiffness", stiffness, ns, "spring", positive=False)
    d = per("damping", "damping", damping, ns, "spring", positive=False)
    lengths = np.linalg.norm(pts[spr[:, 1]] - pts[spr[:, 0]], axis=1)
    zero = np.flatnonzero(lengths <= 1e-9 * max(1.0, float(np.ptp(pts))))
    if zero.size:
        s = int(zero[0])
        a, b = spr[s].tolist()
        raise ValueError(
            f"spring {s} = ({a}, {b}) has zero length: masses {a} and {b} are both at "
            f"{_fmt(pts[a])}"
        )
    if rest_lengths is not None:
        rl = per("rest_lengths", "rest length", rest_lengths, ns, "spring", positive=True)
    else:
        rl = lengths
    if frame is not None:
        f = np.asarray(frame, dtype=float)
        if f.shape != (3, 3) or not np.allclose(f.T @ f, np.eye(3), atol=1e-6):
            raise ValueError(
                f"Lattice frame must be a 3x3 orthonormal matrix (columns forward, left, up); "
                f"got {f.tolist()}"
            )
        if np.linalg.det(f) < 0:
            raise ValueError(
                "Lattice frame must be right-handed (forward x left = up); got a reflection "
                f"{f.tolist()}"
            )
    else:
        f = np.eye(3)
    # Everything is computed here in NumPy and converted once: eager jax.numpy operations
    # would each compile a tiny kernel, about a second in all for building one lattice.
    real = np.dtype(jnp.result_type(float))
    return (
        pts.astype(real),
        spr.astype(np.int32),
        m.astype(real),
        k.astype(real),
        d.astype(real),
        rl.astype(real),
        f.astype(real),
    )
