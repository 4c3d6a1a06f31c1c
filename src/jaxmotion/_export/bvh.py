"""BVH (Biovision hierarchy) files of a figure's motion, for Blender, Maya, MotionBuilder and
game engines.

**The skeleton.** One BVH joint per rod, named `rod<k>`, placed at the rod's proximal node
(where its joint is); the root joint is the root rod (rod 0). A rod's children are the rods
whose parent it is (`Figure.parents`); each child's `OFFSET` is the rest-pose vector from this
rod's proximal node to the child's, so offsets come from the rod lengths and rest directions.
A rod whose far end no child starts from (a leaf, or a rod whose children all hang from its
near end, like Star-Man's head) has an `End Site` at its distal node, so every rod endpoint is
in the file, and Blender, which takes a bone's tail from its `End Site`, draws each rod as one
bone from its proximal to its distal node.

**Channels.** The root has `Xposition Yposition Zposition` (its proximal node's world
position; its `OFFSET` is zero) and its rotation: `Xrotation` for a planar figure (it turns
about the world's y axis only), else `Zrotation Xrotation Yrotation`. Every other rod has
one rotation channel per joint angle it has (`Figure.joints`, in their order: the rod turns
about the first axis, then about the second as the first carried it, which is BVH's order of
channels), with the angle in degrees, clamped to its range as the simulation clamps it; a
joint fixed at 0 has none, and a rod without joint angles has `CHANNELS 0`. Where a joint's
axis is not along a coordinate axis, the rod gets `Zrotation Xrotation Yrotation` instead,
the Euler angles of its rotation relative to its parent.

**Axes and units.** BVH is conventionally Y-up; jaxmotion's world is z-up with figures facing
+x. The file's axes are `(X, Y, Z) = (y, z, x)`: X is the figure's left, Y up, Z forward
(a proper rotation, no mirroring). Lengths are metres. Blender's BVH importer with its
defaults (forward -Z, up Y, scale 1) then stands the figure on Blender's floor, z up,
facing -Y (Blender's front view), in metres.

**Time.** One frame per saved sample (`Trajectory.ts`), `Frame Time` the saved interval (the
results' `[simulation] save_dt`): the file plays in real time at the rate the motion was
saved.
"""

import os
from pathlib import Path

import numpy as np

from .._body.figure import Figure
from .._sim.trajectory import Trajectory
from .base import frame_time, write_atomically

# The file's axes from the world's: (X, Y, Z) = (y, z, x).
TO_BVH = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
_AXIS_NAMES = ("X", "Y", "Z")
_EULER = ("Z", "X", "Y")  # the three-channel order, BVH's usual
_ALONG = 1e-12  # how close a joint axis must be to a coordinate axis to get its own channel
_DIGITS = "%.10g"


def _check(trajectory: Trajectory, figure: Figure) -> np.ndarray:
    if not isinstance(figure, Figure):
        raise ValueError(
            f"BVH exports articulated figures (jaxmotion.Figure); got {type(figure).__name__} "
            "(a lattice has no skeleton)"
        )
    if not isinstance(trajectory, Trajectory):
        raise ValueError(f"trajectory is a {type(trajectory).__name__}; allowed: a Trajectory")
    if trajectory.positions is None:
        raise ValueError(
            "the trajectory has no positions (Trajectory.positions is None); simulate with "
            "positions=True (simulate(..., positions=True), Task.simulate(..., "
            "positions=True)) so that every rod's pose can be rebuilt"
        )
    ts, _ = frame_time(trajectory)
    com = np.asarray(trajectory.positions[0])
    if com.shape[:1] != ts.shape or com.shape[1:] != ((2,) if figure.planar else (3,)):
        raise ValueError(
            f"the trajectory's positions (centre of mass of shape {com.shape}) are not this "
            f"figure's ({figure.name}, {'planar' if figure.planar else '3D'}) over "
            f"{ts.shape[0]} samples"
        )
    if not all(np.all(np.isfinite(np.asarray(x))) for x in trajectory.positions):
        raise ValueError("the trajectory blew up (its positions are not finite); nothing to export")
    return ts


def _euler_zxy(m: np.ndarray) -> np.ndarray:
    """`(..., 3)` angles `(z, x, y)` in radians with `m = Rz(z) Rx(x) Ry(y)`."""
    sx = np.clip(m[..., 2, 1], -1.0, 1.0)
    x = np.arcsin(sx)
    y = np.arctan2(-m[..., 2, 0], m[..., 2, 2])
    z = np.arctan2(-m[..., 0, 1], m[..., 1, 1])
    # Gimbal lock (x = +-90 degrees): only z + y or z - y is defined; put it all in z.
    locked = np.abs(np.cos(x)) < 1e-9
    y = np.where(locked, 0.0, y)
    z = np.where(locked, np.arctan2(m[..., 1, 0], m[..., 0, 0]), z)
    return np.stack([z, x, y], axis=-1)


def _axis_channel(axis) -> tuple[str, float] | None:
    """The BVH channel and sign of a rotation about `axis` (world), or None when the axis is
    not along a coordinate axis of the file."""
    b = TO_BVH @ np.asarray(axis, dtype=np.float64)
    i = int(np.argmax(np.abs(b)))
    rest = np.delete(b, i)
    if np.max(np.abs(rest)) > _ALONG or abs(abs(b[i]) - 1.0) > _ALONG:
        return None
    return f"{_AXIS_NAMES[i]}rotation", float(np.sign(b[i]))


def _layout(figure: Figure):
    """Per rod: its channel names and how to compute their values, `("angles", [(joint,
    sign)])` or `("euler", None)`; the children of each rod; whether it has an End Site."""
    parents = figure.parents
    children = {
        k: [j for j in range(figure.num_rods) if parents[j] == k] for k in range(figure.num_rods)
    }
    channels = {}
    for k in range(1, figure.num_rods):
        turns = [
            (j, jt)
            for j, jt in enumerate(figure.joints)
            if jt.rod == k and not (jt.lo == jt.hi == 0.0)
        ]
        found = [_axis_channel(jt.axis) for _, jt in turns]
        if all(f is not None for f in found):
            names = [f[0] for f in found]
            channels[k] = (
                names,
                ("angles", [(j, f[1]) for (j, _), f in zip(turns, found, strict=True)]),
            )
        else:
            channels[k] = ([f"{a}rotation" for a in _EULER], ("euler", None))
    root = ["Xposition", "Yposition", "Zposition"]
    root += ["Xrotation"] if figure.planar else [f"{a}rotation" for a in _EULER]
    channels[0] = (root, ("root", None))
    end_site = {}
    for k, (_, d) in enumerate(figure.rods):
        kids = children[k]
        end_site[k] = not kids or any(figure.rods[j][0] != d for j in kids)
    return channels, children, end_site


def _hierarchy(figure: Figure, channels, children, end_site) -> tuple[list[str], list[int]]:
    nodes = np.array(figure.nodes)
    lines: list[str] = ["HIERARCHY"]
    order: list[int] = []
    fmt = lambda v: " ".join(_DIGITS % x for x in (TO_BVH @ v) + 0.0)

    def joint(k: int, depth: int) -> None:
        pad = "  " * depth
        p, d = figure.rods[k]
        offset = np.zeros(3) if k == 0 else nodes[p] - nodes[figure.rods[figure.parents[k]][0]]
        lines.append(f"{pad}{'ROOT' if k == 0 else 'JOINT'} rod{k}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {fmt(offset)}")
        names = channels[k][0]
        lines.append(f"{pad}  CHANNELS {len(names)}" + "".join(f" {n}" for n in names))
        order.append(k)
        for child in children[k]:
            joint(child, depth + 1)
        if end_site[k]:
            lines.extend(
                [
                    f"{pad}  End Site",
                    f"{pad}  {{",
                    f"{pad}    OFFSET {fmt(nodes[d] - nodes[p])}",
                    f"{pad}  }}",
                ]
            )
        lines.append(f"{pad}}}")

    joint(0, 0)
    return lines, order


def _motion(trajectory: Trajectory, figure: Figure, channels, order) -> np.ndarray:
    """`(num_saves, num_channels)` the channel values of every frame."""
    rotations, origins = figure.rod_poses(trajectory.positions)
    world = np.einsum("ij,tkjl,ml->tkim", TO_BVH, rotations, TO_BVH)  # P R P^T
    angles = np.asarray(trajectory.positions[2], dtype=np.float64).reshape(len(origins), -1)
    ranges = figure.ranges
    angles = np.clip(angles, ranges[:, 0], ranges[:, 1]) if angles.shape[1] else angles
    free = {j: i for i, j in enumerate(figure.free)}
    columns = []
    for k in order:
        kind, spec = channels[k][1]
        if kind == "root":
            columns.append(origins[:, 0] @ TO_BVH.T)
            if figure.planar:
                q = np.asarray(trajectory.positions[1], dtype=np.float64)
                turn = 2.0 * np.arctan2(q[:, 1], q[:, 0])  # about the world's y: the file's X
                columns.append(np.degrees(np.unwrap(turn))[:, None])
            else:
                columns.append(_degrees(_euler_zxy(world[:, 0])))
        elif kind == "angles":
            for j, sign in spec:
                value = (
                    angles[:, free[j]] if j in free else np.full(len(origins), figure.joints[j].lo)
                )
                columns.append(np.degrees(sign * value)[:, None])
        else:
            parent = figure.parents[k]
            local = np.einsum("tji,tjl->til", world[:, parent], world[:, k])
            columns.append(_degrees(_euler_zxy(local)))
    return np.concatenate(columns, axis=1) if columns else np.zeros((len(origins), 0))


def _degrees(euler: np.ndarray) -> np.ndarray:
    # Unwrapped over time, so that a turn through 180 degrees does not jump by 360 between
    # frames (the same rotation either way; an importer interpolating keys would spin).
    return np.degrees(np.unwrap(euler, axis=0))


def bvh(trajectory: Trajectory, figure: Figure, path: str | os.PathLike) -> Path:
    """Write a figure's motion as a BVH file (see this module's docstring for the skeleton,
    the channels, the Y-up axes and the frame time).

    The file is written to a temporary file beside `path` and renamed into place, so a
    failed export leaves no half-written file and an existing file is replaced whole.

    **Arguments:**

    - `trajectory`: one motion of `figure` with its positions recorded
        (`simulate(..., positions=True)` or `Task.simulate(..., positions=True)`).
    - `figure`: the `Figure` that moved.
    - `path`: the file to write (conventionally `*.bvh`).

    **Returns:** the path written.

    **Raises:** `ValueError` for a body that is not a `Figure`, a trajectory without
    positions, a batched, non-finite or unevenly sampled one, or one of another figure.
    """
    ts = _check(trajectory, figure)
    _, dt = frame_time(trajectory)
    channels, children, end_site = _layout(figure)
    lines, order = _hierarchy(figure, channels, children, end_site)
    values = _motion(trajectory, figure, channels, order)
    lines += ["MOTION", f"Frames: {len(ts)}", f"Frame Time: {dt!r}"]
    lines += [" ".join(_DIGITS % x for x in row + 0.0) for row in values]
    text = "\n".join(lines) + "\n"
    return write_atomically(path, lambda tmp: tmp.write_text(text))


__all__ = ["TO_BVH", "bvh"]
