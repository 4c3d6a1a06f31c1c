"""The world every body lives in: gravity, the floor z = 0 and its contact model."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_number(name: str, value, *, minimum: float, strict: bool) -> None:
    if not _is_concrete(value):
        return
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"World.{name} = {value!r} is not a number") from None
    bad = (v <= minimum) if strict else (v < minimum)
    if not math.isfinite(v) or bad:
        rel = ">" if strict else ">="
        raise ValueError(f"World.{name} = {value!r}; allowed: a finite number {rel} {minimum}")


class World(eqx.Module):
    """Gravity, the floor (the plane z = 0, z up) and the contact model shared by every body.

    Contact is a penalty force acting on every point below the floor: a spring-damper normal
    force `Fn = max(0, -floor_stiffness * z - floor_damping * vz)`, and Coulomb friction
    regularised so that it stays differentiable,
    `f_t = -Fn * mu(v_t) v_t / sqrt(|v_t|^2 + friction_velocity^2)`: for sliding speeds well
    above `friction_velocity` this is Coulomb friction of magnitude `mu Fn` against the sliding
    direction; below it friction acts as a stiff viscous drag, which is what lets a body rest.

    Anisotropic friction (the first paper's "friction ... stronger in one preferred direction"):
    when `friction_direction` is a horizontal vector `d`, the component of the sliding velocity
    along `+d` meets the coefficient `friction_preferred` and every other component meets
    `friction`. The switch between the two is smoothed over `friction_velocity`. To let a
    lattice push off backwards and travel towards `+x`, make sliding towards `-x` harder:
    `friction_direction=(-1, 0), friction_preferred=2 * friction`.

    **Arguments:**

    - `gravity`: gravitational acceleration in m/s^2, pointing down (-z). `0` turns it off.
    - `floor`: whether the floor exists at all (`False` for free flight).
    - `floor_stiffness`: penalty stiffness per contact point, N/m.
    - `floor_damping`: penalty damping per contact point, N s/m.
    - `friction`: Coulomb coefficient (in every direction but the preferred one).
    - `friction_preferred`: Coulomb coefficient for sliding along `friction_direction`; `None`
        means the same as `friction`.
    - `friction_direction`: the preferred horizontal direction `(dx, dy)`, or `None` for
        isotropic friction. It is normalised.
    - `friction_velocity`: regularisation speed of the friction law, m/s.
    """

    gravity: float | Float[Array, ""] = 9.81
    floor: bool = eqx.field(default=True, static=True)
    floor_stiffness: float | Float[Array, ""] = 2.0e4
    floor_damping: float | Float[Array, ""] = 200.0
    friction: float | Float[Array, ""] = 0.8
    friction_preferred: float | Float[Array, ""] | None = None
    friction_direction: tuple[float, float] | None = eqx.field(default=None, static=True)
    friction_velocity: float | Float[Array, ""] = 0.05

    def __check_init__(self):
        _check_number("gravity", self.gravity, minimum=0.0, strict=False)
        _check_number("floor_stiffness", self.floor_stiffness, minimum=0.0, strict=True)
        _check_number("floor_damping", self.floor_damping, minimum=0.0, strict=False)
        _check_number("friction", self.friction, minimum=0.0, strict=False)
        _check_number("friction_velocity", self.friction_velocity, minimum=0.0, strict=True)
        if self.friction_preferred is not None:
            _check_number("friction_preferred", self.friction_preferred, minimum=0.0, strict=False)
        if self.friction_direction is not None:
            d = self.friction_direction
            if (
                not isinstance(d, tuple)
                or len(d) != 2
                or not all(isinstance(c, int | float) and math.isfinite(c) for c in d)
                or math.hypot(*d) == 0.0
            ):
                raise ValueError(
                    f"World.friction_direction = {d!r}; allowed: None or a non-zero horizontal "
                    "vector given as a tuple of two finite numbers (dx, dy)"
                )

    def __init__(
        self,
        gravity=9.81,
        floor: bool = True,
        floor_stiffness=2.0e4,
        floor_damping=200.0,
        friction=0.8,
        friction_preferred=None,
        friction_direction=None,
        friction_velocity=0.05,
    ):
        self.gravity = gravity
        self.floor = bool(floor)
        self.floor_stiffness = floor_stiffness
        self.floor_damping = floor_damping
        self.friction = friction
        self.friction_preferred = friction_preferred
        if friction_direction is not None:
            try:
                d = tuple(float(c) for c in friction_direction)
            except (TypeError, ValueError):
                raise ValueError(
                    f"World.friction_direction = {friction_direction!r}; allowed: None or a "
                    "non-zero horizontal vector (dx, dy)"
                ) from None
            n = math.hypot(*d) if len(d) == 2 else 0.0
            friction_direction = (d[0] / n, d[1] / n) if n > 0 and math.isfinite(n) else d
        self.friction_direction = friction_direction
        self.friction_velocity = friction_velocity


def floor_force(
    world: World,
    px: Float[ArrayLike, "*points"],
    py: Float[ArrayLike, "*points"],
    pz: Float[ArrayLike, "*points"],
    vx: Float[ArrayLike, "*points"],
    vy: Float[ArrayLike, "*points"],
    vz: Float[ArrayLike, "*points"],
) -> tuple[Float[Array, "*points"], Float[Array, "*points"], Float[Array, "*points"]]:
    """Contact force of the floor on points at `p` moving with `v` (the one contact model).

    Components are passed and returned separately so that batched callers fuse into
    elementwise loops (see `perf-lab`); every argument broadcasts against the others.
    Gravity is not included. Returns `(fx, fy, fz)`; zero everywhere when `world.floor` is off.

    **Arguments:** `world`; the point positions `px, py, pz` and velocities `vx, vy, vz`.

    **Returns:** the force components, each shaped like the broadcast inputs.
    """
    del px, py  # the floor is the whole plane z = 0
    if not world.floor:
        zero = jnp.zeros(jnp.broadcast_shapes(jnp.shape(pz), jnp.shape(vz)), jnp.result_type(pz))
        return zero, zero, zero
    penetrating = pz < 0
    push = -world.floor_stiffness * pz - world.floor_damping * vz
    fn = jnp.where(penetrating, jnp.maximum(push, 0.0), 0.0)
    eps = world.friction_velocity
    scale = fn / jnp.sqrt(vx * vx + vy * vy + eps * eps)
    fx = -world.friction * scale * vx
    fy = -world.friction * scale * vy
    if world.friction_direction is not None and world.friction_preferred is not None:
        dx, dy = world.friction_direction
        along = vx * dx + vy * dy
        # Extra resistance for the velocity component along +d, switched on smoothly.
        extra = (world.friction_preferred - world.friction) * jax.nn.sigmoid(along / eps)
        fx = fx - extra * scale * along * dx
        fy = fy - extra * scale * along * dy
    return fx, fy, fn


def floor_force_vectors(
    world: World,
    positions: Float[ArrayLike, "*points 3"],
    velocities: Float[ArrayLike, "*points 3"],
) -> Float[Array, "*points 3"]:
    """`floor_force` for points given as `(..., 3)` arrays; returns a `(..., 3)` array."""
    p = jnp.asarray(positions)
    v = jnp.asarray(velocities)
    f = floor_force(world, p[..., 0], p[..., 1], p[..., 2], v[..., 0], v[..., 1], v[..., 2])
    return jnp.stack(f, axis=-1)
