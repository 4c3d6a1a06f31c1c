"""The lattice model of `jaxmotion.simulate` written in vectorised NumPy: the baseline that
`benchmarks/evaluate.py` compares `Task.evaluate` against.

The same physics, step for step: springs with tension `k (l - L) + d dl/dt`, gravity, the
penalty floor with regularised (optionally anisotropic) Coulomb friction, the regimes
controller's nearest-regime-time rest lengths chosen at each control tick, and semi-implicit
Euler on the same time grid.
The controllers' per-regime rest lengths come from `Regimes.prepare` (the deformations are
not what is being timed). State is laid out batch-last, `(3, n, batch)`, so every NumPy call
works on whole batches; springs are gathered and forces scattered with `np.add.at`.
"""

import numpy as np

import jaxmotion as jm
from jaxmotion._sim.simulate import time_grid


def prepare(task: jm.Task, params, dtype=np.float64):
    """Arrays for `simulate`: the lattice, the world and each controller's rest lengths."""
    import jax

    lattice = task.body
    i, j = (np.asarray(lattice.springs[:, k]) for k in range(2))
    tables = np.asarray(jax.vmap(lambda c: c.prepare(lattice))(params))  # (B, C, n, n)
    rest = np.moveaxis(tables[:, :, i, j], 0, -1).astype(dtype)  # (C, S, B)
    return dict(
        i=i,
        j=j,
        k=np.asarray(lattice.stiffness, dtype)[:, None],
        d=np.asarray(lattice.damping, dtype)[:, None],
        m=np.asarray(lattice.masses, dtype)[:, None],
        x0=np.asarray(lattice.points, dtype).T,
        rest=rest,
        times=np.asarray(params.times, dtype).T,  # (C, B)
        t_per=np.asarray(params.t_per, dtype),  # (B,)
        world=task.world,
        grid=time_grid(task.duration, task.dt, task.save_dt, task.control_dt),
        dtype=dtype,
    )


def simulate(model) -> np.ndarray:
    """Final positions `(3, n, batch)` after the task's duration."""
    i, j, k, d, m = model["i"], model["j"], model["k"], model["d"], model["m"]
    rest, times, t_per, world, grid = (
        model[key] for key in ("rest", "times", "t_per", "world", "grid")
    )
    dtype = model["dtype"]
    n = m.shape[0]
    # Incidence matrix: force on the masses = incidence @ force on each spring's first mass.
    incidence = np.zeros((n, len(i)), dtype)
    incidence[i, np.arange(len(i))] = 1
    incidence[j, np.arange(len(i))] = -1
    x = np.repeat(model["x0"][:, :, None], t_per.shape[0], axis=2)
    v = np.zeros_like(x)
    h = dtype(grid.dt)
    eps = dtype(world.friction_velocity)
    direction = world.friction_direction
    control_dt = dtype(grid.control_dt)
    for step in range(grid.num_steps):
        # The regime is chosen at each control tick (every `substeps` steps) and held.
        t = dtype(step // grid.substeps) * control_dt
        phase = np.mod(t, t_per)
        best = np.abs(phase - times[0])
        length0 = rest[0]
        for c in range(1, times.shape[0]):  # the nearest regime time, ties to the first
            dist = np.abs(phase - times[c])
            nearer = dist < best
            best = np.where(nearer, dist, best)
            length0 = np.where(nearer, rest[c], length0)
        dx = x[:, j] - x[:, i]
        dv = v[:, j] - v[:, i]
        length = np.sqrt(np.sum(dx * dx, axis=0))
        rate = np.sum(dv * dx, axis=0) / length
        f = (k * (length - length0) + d * rate) / length * dx  # force on mass i, (3, S, B)
        force = np.matmul(incidence, f)
        if world.floor:
            z, vz = x[2], v[2]
            push = -world.floor_stiffness * z - world.floor_damping * vz
            fn = np.where(z < 0, np.maximum(push, 0), 0)
            scale = fn / np.sqrt(v[0] * v[0] + v[1] * v[1] + eps * eps)
            force[0] -= world.friction * scale * v[0]
            force[1] -= world.friction * scale * v[1]
            if direction is not None and world.friction_preferred is not None:
                along = v[0] * direction[0] + v[1] * direction[1]
                extra = (world.friction_preferred - world.friction) / (1 + np.exp(-along / eps))
                force[0] -= extra * scale * along * direction[0]
                force[1] -= extra * scale * along * direction[1]
            force[2] += fn
        force[2] -= m * world.gravity
        v = v + h * force / m
        x = x + h * v
    return x


def forward(model, x: np.ndarray) -> np.ndarray:
    """Forward travel of the centre of mass (x displacement: the lattices face +x)."""
    m = model["m"]
    com = np.sum(x[0] * m, axis=0) / m.sum()
    com0 = np.sum(model["x0"][0][:, None] * m, axis=0) / m.sum()
    return com - com0


__all__ = ["forward", "prepare", "simulate"]
