"""Small-vector algebra in which constants known at trace time fold away.

An articulated figure's geometry (rest directions, joint axes, inertias, fixed joint angles)
is known when the simulation is traced, and much of it is zero: a planar figure has no y
components at all, a joint about the y axis has a rotation matrix with four zeros. Writing the
kinematics on "scalars" that are either Python floats (constants) or arrays (traced values)
lets Python do the constant arithmetic while tracing, so `0 * x` and `1 * x` never reach XLA
(XLA keeps them: `0 * x` is not `0` for `x = inf`). The same code then costs a planar figure
what a hand-written planar simulator would, and a joint fixed in place costs nothing per step.

Vectors are tuples of three scalars, matrices tuples of three row tuples. Arrays may carry any
trailing batch shape; everything here is elementwise over it.
"""

from collections.abc import Iterable

import jax.numpy as jnp

Scalar = float | jnp.ndarray


def const(x) -> bool:
    """Whether `x` is a trace-time constant (a Python float)."""
    return isinstance(x, float)


def add(a, b):
    if const(a) and a == 0.0:
        return b
    if const(b) and b == 0.0:
        return a
    return a + b


def sub(a, b):
    if const(b) and b == 0.0:
        return a
    if const(a) and a == 0.0:
        return neg(b)
    return a - b


def neg(a):
    return -a if not const(a) else (0.0 if a == 0.0 else -a)


def mul(a, b):
    if const(a):
        if a == 0.0:
            return 0.0
        if a == 1.0:
            return b
        if a == -1.0:
            return neg(b)
    if const(b):
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
        if b == -1.0:
            return neg(a)
    return a * b


def total(items: Iterable) -> Scalar:
    out: Scalar = 0.0
    for x in items:
        out = add(out, x)
    return out


def vadd(u, v):
    return tuple(add(a, b) for a, b in zip(u, v, strict=True))


def vsub(u, v):
    return tuple(sub(a, b) for a, b in zip(u, v, strict=True))


def vscale(s, v):
    return tuple(mul(s, a) for a in v)


def dot(u, v) -> Scalar:
    return total(mul(a, b) for a, b in zip(u, v, strict=True))


def cross(u, v):
    return (
        sub(mul(u[1], v[2]), mul(u[2], v[1])),
        sub(mul(u[2], v[0]), mul(u[0], v[2])),
        sub(mul(u[0], v[1]), mul(u[1], v[0])),
    )


def matvec(m, v):
    return tuple(dot(row, v) for row in m)


def tmatvec(m, v):
    """`m^T v`."""
    return tuple(total(mul(m[i][j], v[i]) for i in range(3)) for j in range(3))


def matmul(a, b):
    return tuple(
        tuple(total(mul(a[i][k], b[k][j]) for k in range(3)) for j in range(3)) for i in range(3)
    )


def transpose(m):
    return tuple(tuple(m[j][i] for j in range(3)) for i in range(3))


def madd(a, b):
    return tuple(vadd(r, s) for r, s in zip(a, b, strict=True))


IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
ZERO = (0.0, 0.0, 0.0)


def rotation(axis, c, s):
    """Rotation by the angle with cosine `c` and sine `s` about the constant unit `axis`
    (Rodrigues: `c 1 + s [axis]x + (1 - c) axis axis^T`)."""
    x, y, z = axis
    k = ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))
    omc = sub(1.0, c)
    return tuple(
        tuple(
            add(add(mul(1.0 if i == j else 0.0, c), mul(k[i][j], s)), mul(axis[i] * axis[j], omc))
            for j in range(3)
        )
        for i in range(3)
    )


def solve_symmetric(m, b):
    """`m^-1 b` for a symmetric positive definite 3x3 `m`, by cofactors."""
    (a, d, e), (_, f, g), (_, _, h) = m  # m = [[a, d, e], [d, f, g], [e, g, h]]
    c00 = sub(mul(f, h), mul(g, g))
    c01 = sub(mul(e, g), mul(d, h))
    c02 = sub(mul(d, g), mul(e, f))
    c11 = sub(mul(a, h), mul(e, e))
    c12 = sub(mul(d, e), mul(a, g))
    c22 = sub(mul(a, f), mul(d, d))
    det = add(add(mul(a, c00), mul(d, c01)), mul(e, c02))
    inv_det = 1.0 / det
    adj = ((c00, c01, c02), (c01, c11, c12), (c02, c12, c22))
    return tuple(mul(x, inv_det) for x in matvec(adj, b))


def quaternion_matrix(q):
    """Rotation matrix of the unit quaternion `q = (w, x, y, z)` (normalised here)."""
    w, x, y, z = q
    inv = 1.0 / jnp.sqrt(total(mul(c, c) for c in q))
    w, x, y, z = (mul(c, inv) for c in (w, x, y, z))
    xx, yy, zz = mul(x, x), mul(y, y), mul(z, z)
    xy, xz, yz = mul(x, y), mul(x, z), mul(y, z)
    wx, wy, wz = mul(w, x), mul(w, y), mul(w, z)
    two = lambda v: mul(2.0, v)
    return (
        (sub(1.0, two(add(yy, zz))), two(sub(xy, wz)), two(add(xz, wy))),
        (two(add(xy, wz)), sub(1.0, two(add(xx, zz))), two(sub(yz, wx))),
        (two(sub(xz, wy)), two(add(yz, wx)), sub(1.0, two(add(xx, yy)))),
    )


def quaternion_rate(q, w_body):
    """`dq/dt = q (x) (0, w) / 2` for the angular velocity `w_body` in the body frame."""
    qw, qx, qy, qz = q
    wx, wy, wz = w_body
    half = lambda v: mul(0.5, v)
    return (
        half(neg(total((mul(qx, wx), mul(qy, wy), mul(qz, wz))))),
        half(total((mul(qw, wx), mul(qy, wz), neg(mul(qz, wy))))),
        half(total((mul(qw, wy), mul(qz, wx), neg(mul(qx, wz))))),
        half(total((mul(qw, wz), mul(qx, wy), neg(mul(qy, wx))))),
    )
