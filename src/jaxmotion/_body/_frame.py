"""Best-fit rotation of a deformed point set: the body frame of a lattice."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

_POLAR_ITERATIONS = 6  # float32-converged for condition numbers up to ~100 (4 suffice below 20)


def _inverse_transpose(m):
    """(M^-T, det M) of 3x3 matrices stored as `(3, 3, *batch)`, from cofactors (elementwise
    over the trailing batch axes, so it vectorises)."""
    a, b, c = m[0, 0], m[0, 1], m[0, 2]
    d, e, f = m[1, 0], m[1, 1], m[1, 2]
    g, h, i = m[2, 0], m[2, 1], m[2, 2]
    cof = jnp.stack(
        [
            jnp.stack([e * i - f * h, f * g - d * i, d * h - e * g]),
            jnp.stack([c * h - b * i, a * i - c * g, b * g - a * h]),
            jnp.stack([b * f - c * e, c * d - a * f, a * e - b * d]),
        ]
    )
    det = a * cof[0, 0] + b * cof[0, 1] + c * cof[0, 2]
    return cof / det, det


def polar_rotation(h: Float[Array, "3 3 *batch"]) -> Float[Array, "3 3 *batch"]:
    """The orthogonal factor `R` of the polar decomposition `h = R S` (S symmetric positive),
    for 3x3 matrices stored as `(3, 3, *batch)` (any trailing batch axes).

    `R` is the rotation that best maps the rest shape onto the current one when
    `h = sum_i m_i (x_i - c)(p_i - c0)^T` (the Kabsch/Procrustes solution). Computed with
    determinant-scaled Newton iterations `X <- (z X + (z X)^-T) / 2`, which converge
    quadratically, are smooth (differentiable) and use only elementwise arithmetic.
    """
    extra = h.ndim - 2
    scale = jnp.sqrt(jnp.sum(h * h, axis=(0, 1))) + jnp.finfo(h.dtype).tiny
    x = h / scale
    # A tiny multiple of the identity keeps a degenerate (flattened) shape from dividing by 0.
    x = x + 1e-6 * jnp.eye(3, dtype=h.dtype).reshape((3, 3) + (1,) * extra)

    def newton(_, x):
        inv_t, det = _inverse_transpose(x)
        z = jnp.cbrt(jnp.abs(det))
        return 0.5 * (x / z + inv_t * z)

    # A loop rather than unrolled iterations keeps compilation quick.
    return jax.lax.fori_loop(0, _POLAR_ITERATIONS, newton, x)
