"""USD (Pixar's Universal Scene Description) files of any body's motion, through `usd-core`
(the `usd` extra): Blender, Maya, Houdini, Omniverse and USD viewers open them.

**The stage.** Z up and metres (`upAxis = "Z"`, `metersPerUnit = 1`, jaxmotion's own axes:
no conversion), `timeCodesPerSecond` and `framesPerSecond` the saved samples' rate, one
time code per saved sample from 0. The default prim `/World` holds the body and the floor
(`/World/floor`, a square mesh at z = 0 under the motion).

**Figures** are a transform hierarchy: `/World/<name>/rod0` (the root rod) and each rod
under its parent rod (`Figure.parents`), named `rod<k>`; each has one time-sampled
`xformOp:transform` (its pose relative to its parent; its world transform maps the rest
pose's rod onto the rod at that time: the rotation relative to the rest pose, the
translation putting the rest pose's proximal node where the proximal node is), and a
`Capsule` child (`rod<k>/shape`) placed along the rod's rest-pose segment, with the rod's
radius.

**Lattices** are `/World/<name>/masses`, `Points` with time-sampled positions, and
`/World/<name>/springs`, linear `BasisCurves` (two points per spring) with time-sampled
points. USD has no spring primitive and Blender imports points and curves as they are:
keeping the springs as curves shows the lattice as it moves without any rig.
"""

import os
from pathlib import Path

import numpy as np

from .._body.figure import Figure
from .._body.lattice import Lattice
from .._sim.trajectory import Trajectory
from .base import frame_time, write_atomically

SUFFIXES = (".usd", ".usda", ".usdc")  # what USD writes: its choice of format, or text or binary
_FLOOR_MARGIN = 1.0  # m beyond the motion's extent on every side
_MASS_WIDTH = 0.05  # m: the drawn diameter of a lattice's point masses
_SPRING_WIDTH = 0.01  # m: the drawn width of its springs


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError:
        raise ImportError(
            "USD export needs usd-core (Pixar's USD for Python): pip install 'jaxmotion[usd]'"
        ) from None
    return Gf, Sdf, Usd, UsdGeom, Vt


def _matrix(Gf, rotation: np.ndarray, translation: np.ndarray):
    """A USD matrix (row vectors: `p' = p M`) of `x -> rotation x + translation`."""
    m = np.eye(4)
    m[:3, :3] = rotation.T
    m[3, :3] = translation
    return Gf.Matrix4d(m.tolist())


def _figure(stage, figure: Figure, trajectory: Trajectory, root: str, modules) -> None:
    Gf, _, _, UsdGeom, _ = modules
    rotations, origins = figure.rod_poses(trajectory.positions)
    nodes = np.array(figure.nodes)
    parents = figure.parents
    paths: dict[int, str] = {}
    for k, (p, d) in enumerate(figure.rods):
        parent = parents[k]
        paths[k] = f"{root}/rod{k}" if parent < 0 else f"{paths[parent]}/rod{k}"
        xform = UsdGeom.Xform.Define(stage, paths[k])
        op = xform.AddTransformOp(precision=UsdGeom.XformOp.PrecisionDouble)
        # World: x -> R x + (o - R n_p) (the rest pose's proximal node n_p to o).
        world_t = origins[:, k] - np.einsum("tij,j->ti", rotations[:, k], nodes[p])
        if parent >= 0:
            pr = rotations[:, parent]
            pt = origins[:, parent] - np.einsum("tij,j->ti", pr, nodes[figure.rods[parent][0]])
            local_r = np.einsum("tji,tjl->til", pr, rotations[:, k])
            local_t = np.einsum("tji,tj->ti", pr, world_t - pt)
        else:
            local_r, local_t = rotations[:, k], world_t
        for t in range(len(local_r)):
            op.Set(_matrix(Gf, local_r[t], local_t[t]), float(t))
        segment = nodes[d] - nodes[p]
        length = float(np.linalg.norm(segment))
        radius = float(figure.radii[k])
        shape = UsdGeom.Capsule.Define(stage, f"{paths[k]}/shape")
        shape.CreateAxisAttr("Z")
        shape.CreateHeightAttr(max(length - 2 * radius, 0.0))
        shape.CreateRadiusAttr(radius)
        # The capsule's z axis along the rest segment, centred on it.
        z = segment / length
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        place = np.stack([x, np.cross(z, x), z], axis=1)
        shape.AddTransformOp().Set(_matrix(Gf, place, nodes[p] + segment / 2))


def _lattice(stage, lattice: Lattice, trajectory: Trajectory, root: str, modules) -> None:
    _, _, _, UsdGeom, Vt = modules
    points = np.asarray(trajectory.points, dtype=np.float64)
    springs = np.asarray(lattice.springs)
    masses = UsdGeom.Points.Define(stage, f"{root}/masses")
    masses.CreateWidthsAttr(Vt.FloatArray([_MASS_WIDTH] * points.shape[1]))
    curves = UsdGeom.BasisCurves.Define(stage, f"{root}/springs")
    curves.CreateTypeAttr("linear")
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([2] * len(springs)))
    curves.CreateWidthsAttr(Vt.FloatArray([_SPRING_WIDTH]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    mass_points, spring_points = masses.CreatePointsAttr(), curves.CreatePointsAttr()
    for t, frame in enumerate(points):
        mass_points.Set(Vt.Vec3fArray.FromNumpy(frame.astype(np.float32)), float(t))
        ends = frame[springs.reshape(-1)].astype(np.float32)
        spring_points.Set(Vt.Vec3fArray.FromNumpy(ends), float(t))


def _floor(stage, trajectory: Trajectory, modules) -> None:
    Gf, _, _, UsdGeom, Vt = modules
    xy = np.asarray(trajectory.points, dtype=np.float64)[..., :2].reshape(-1, 2)
    lo, hi = xy.min(axis=0) - _FLOOR_MARGIN, xy.max(axis=0) + _FLOOR_MARGIN
    floor = UsdGeom.Mesh.Define(stage, "/World/floor")
    corners = [(lo[0], lo[1], 0.0), (hi[0], lo[1], 0.0), (hi[0], hi[1], 0.0), (lo[0], hi[1], 0.0)]
    floor.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*c) for c in corners]))
    floor.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    floor.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    floor.CreateNormalsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 1)]))
    floor.SetNormalsInterpolation(UsdGeom.Tokens.constant)


def usd(trajectory: Trajectory, body, path: str | os.PathLike) -> Path:
    """Write a body's motion as a USD file (see this module's docstring for the stage, the
    figure's transform hierarchy and the lattice's points and curves).

    The stage is written to a temporary file beside `path` and renamed into place, so a
    failed export leaves no half-written file and an existing file is replaced whole.

    **Arguments:**

    - `trajectory`: one motion of `body`; a figure's needs its positions
        (`simulate(..., positions=True)` or `Task.simulate(..., positions=True)`).
    - `body`: the `Figure` or `Lattice` that moved.
    - `path`: the file to write: `.usd` (binary), `.usdc` (binary) or `.usda` (text).

    **Returns:** the path written.

    **Raises:** `ValueError` for another suffix or body, a figure's trajectory without
    positions, a batched, non-finite or unevenly sampled trajectory, or one of another
    body; `ImportError` without usd-core.
    """
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise ValueError(f"USD file {str(path)!r}; allowed: a name ending in {', '.join(SUFFIXES)}")
    if not isinstance(body, Figure | Lattice):
        raise ValueError(f"body is a {type(body).__name__}; allowed: a Figure or a Lattice")
    ts, dt = frame_time(trajectory)
    points = np.asarray(trajectory.points)
    if points.shape != (len(ts), body.num_points, 3):
        raise ValueError(
            f"the trajectory's points have shape {points.shape}; this body ({body.name}) has "
            f"{body.num_points} points over {len(ts)} samples"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("the trajectory blew up (its points are not finite); nothing to export")
    if isinstance(body, Figure) and trajectory.positions is None:
        raise ValueError(
            "the trajectory has no positions (Trajectory.positions is None); simulate with "
            "positions=True (simulate(..., positions=True), Task.simulate(..., "
            "positions=True)) so that every rod's pose can be rebuilt"
        )
    modules = _pxr()
    _, _, Usd, UsdGeom, _ = modules
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(1.0 / dt)
    stage.SetFramesPerSecond(1.0 / dt)
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(float(len(ts) - 1))
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    root = f"/World/{_prim_name(body.name)}"
    UsdGeom.Xform.Define(stage, root)
    if isinstance(body, Figure):
        _figure(stage, body, trajectory, root, modules)
    else:
        _lattice(stage, body, trajectory, root, modules)
    _floor(stage, trajectory, modules)
    return write_atomically(path, lambda tmp: stage.GetRootLayer().Export(str(tmp)))


def _prim_name(name: str) -> str:
    """`name` as a USD prim name (letters, digits and underscores, not starting with a
    digit)."""
    clean = "".join(c if c.isalnum() or c == "_" else "_" for c in name) or "body"
    return clean if not clean[0].isdigit() else f"_{clean}"


__all__ = ["SUFFIXES", "usd"]
