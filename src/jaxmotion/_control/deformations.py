"""The twelve canonical global deformations ("reflexes") of the first paper, section 2.2."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

KINDS = ("scale", "shear", "splay", "twist")
AXES = ("forward", "left", "up")
REFLEX_NAMES = tuple(f"{kind}-{axis}" for kind in KINDS for axis in AXES)
"""Reflex `r` is kind `KINDS[r // 3]` along axis `AXES[r % 3]`: 0-2 scale, 3-5 shear,
6-8 splay, 9-11 twist."""

DEFAULT_AMPLITUDES = (0.3, 0.3, 0.3, 0.5)
"""Full-strength (coefficient +-1) amplitude of scale, shear, splay and twist."""


def deform(
    local: Float[Array, "n 3"],
    reflex: Int[Array, ""],
    coefficient: Float[Array, ""],
    amplitudes: tuple[float, float, float, float] = DEFAULT_AMPLITUDES,
) -> Float[Array, "n 3"]:
    """Apply reflex `reflex` with coefficient `coefficient` to a shape.

    `local` holds the rest shape in the lattice-centric frame, relative to the centre of mass
    (column 0 forward, 1 left, 2 up). For a reflex along axis `a`, write `u` for the
    coordinate along `a`, `v` and `w` for the coordinates along the axes `(a + 1) mod 3` and
    `(a + 2) mod 3`, `h = max |u|` over the rest shape, and `A` for the kind's amplitude:

    - **scale** stretches (coefficient > 0) or squashes along the axis:
        `u' = (1 + A c) u`.
    - **shear** slides layers along the axis in proportion to their height along the next
        axis but one: `u' = u + A c w` (shear-forward leans the lattice forwards, shear-left
        skews it in the floor plane, shear-up tilts it sideways).
    - **splay** widens cross-sections along the axis: the cross-section at `u` is scaled by
        `1 + A c u / h`, so one end flares out and the other narrows.
    - **twist** rotates cross-sections about the axis in proportion to their position along
        it: `(v', w')` is `(v, w)` turned by the angle `A c u / h` (radians).

    A coefficient of 0 is the identity for every reflex. With the default amplitudes no
    reflex folds or inverts a shape.
    """
    a_scale, a_shear, a_splay, a_twist = amplitudes
    half = jnp.max(jnp.abs(local), axis=0)
    half = jnp.where(half > 0, half, 1.0)

    def along(axis: int):
        u_col, v_col, w_col = axis, (axis + 1) % 3, (axis + 2) % 3
        u, v, w = local[:, u_col], local[:, v_col], local[:, w_col]
        rel = u / half[axis]

        def assemble(u2, v2, w2):
            out = jnp.zeros_like(local)
            return out.at[:, u_col].set(u2).at[:, v_col].set(v2).at[:, w_col].set(w2)

        scale = lambda: assemble((1 + a_scale * coefficient) * u, v, w)
        shear = lambda: assemble(u + a_shear * coefficient * w, v, w)

        def splay():
            f = 1 + a_splay * coefficient * rel
            return assemble(u, f * v, f * w)

        def twist():
            angle = a_twist * coefficient * rel
            c, s = jnp.cos(angle), jnp.sin(angle)
            return assemble(u, c * v - s * w, s * v + c * w)

        return scale, shear, splay, twist

    per_axis = [along(axis) for axis in range(3)]
    branches = [per_axis[r % 3][r // 3] for r in range(12)]
    return jax.lax.switch(jnp.clip(reflex, 0, 11), branches)
