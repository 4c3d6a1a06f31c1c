"""Normalising sense variables to [0, 1] (the second paper's Table 1: "All sense-variable values
are normalized to lie in the range [0.0, 1.0]"). A value outside its documented range is
clipped, so the hyper-rectangles of sense-based rules keep their geometry."""

import math

import jax.numpy as jnp

G_REFERENCE = 9.81  # m/s^2: the scale of forces and speeds in a world without gravity


def unit(x, lo: float, hi: float):
    """`x` over `[lo, hi]`, as `[0, 1]`, clipped."""
    return jnp.clip((x - lo) / (hi - lo), 0.0, 1.0)


def signed(x, scale):
    """`x` over `[-scale, scale]`, as `[0, 1]` (0 maps to 0.5), clipped."""
    return jnp.clip(0.5 + 0.5 * x / scale, 0.0, 1.0)


def scales(world, size: float):
    """`(g, v)`: the gravity that scales forces (the world's, or `G_REFERENCE` without it)
    and the speed of a fall through the body's `size`, `sqrt(2 g size)`."""
    g = world.gravity
    if isinstance(g, int | float):
        g = float(g) if g > 0 else G_REFERENCE
    else:
        g = jnp.where(g > 0, g, G_REFERENCE)
    if isinstance(g, float) and isinstance(size, int | float):
        return g, math.sqrt(2.0 * g * size)
    return g, jnp.sqrt(2.0 * g * size)
