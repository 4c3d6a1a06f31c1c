"""BVH export (`jaxmotion.export.bvh`, `python -m jaxmotion export`, `[output] export`),
checked by reading the files back with an independent reader (bvhio, test-only): its parse
of the channels, then forward kinematics, must put every rod endpoint where the simulation
did."""

from pathlib import Path

import bvhio
import equinox as eqx
import jax
import numpy as np
import pytest
from pxr import Usd, UsdGeom

import jaxmotion as jm
from jaxmotion import figures
from jaxmotion._export import bvh as bvh_module
from jaxmotion._export.bvh import TO_BVH
from jaxmotion.experiment import ConfigError, parse_config, run_experiment

FK_TOLERANCE = 1e-4  # m: the bound on rod endpoints rebuilt from the file
USD_TOLERANCE = 1e-5  # m: the bound on USD world transforms and points
TIME_TOLERANCE = 1e-9  # s: the frame time against the save interval (written to 7 digits)
DURATION = 0.3  # s: long enough for joints to reach their limits and the root to turn
SAVE_DT = 0.02  # s
# Free flight: the export does not care what moved the rods, and a world without a floor
# compiles a sixth faster.
WORLD = jm.World(floor=False)
FIGURES = ("star_man", "beryl_biped", "cujo", "rex", "bob", "snake", "luxo")
# Each figure's flight is one more compilation (about 4 s): the fast suite exports a 3D
# biped, the 15-rod Rex and a planar figure; `-m slow` the other four (the same writer on
# other trees).
FAST_FIGURES = ("star_man", "rex", "snake")
FIGURE_PARAMS = [
    name if name in FAST_FIGURES else pytest.param(name, marks=pytest.mark.slow) for name in FIGURES
]


def _start(figure, seed: int):
    """A start that exercises every channel: random angles and rates (some joints run into
    their limits), the root spinning, the figure thrown up."""
    rng = np.random.default_rng(seed)
    lo, hi = figure.ranges[:, 0], figure.ranges[:, 1]
    spin = [0.0, 3.0, 0.0] if figure.planar else [1.5, 3.0, -2.0]
    velocity = [0.5, 0.0, 2.0] if figure.planar else [0.5, 0.3, 2.0]
    return figure.state(
        com=None,
        velocity=velocity,
        angular_velocity=spin,
        angles=rng.uniform(lo, hi),
        rates=rng.uniform(-4.0, 4.0, figure.num_free),
    )


class _Flights(dict):
    """Each figure's free flight (the figure, its trajectory with positions), simulated
    the first time a test asks for it."""

    def __missing__(self, name):
        figure = getattr(figures, name)()
        trajectory = jm.simulate(
            figure,
            None,
            WORLD,
            DURATION,
            save_dt=SAVE_DT,
            initial_state=_start(figure, FIGURES.index(name)),
            positions=True,
        )
        self[name] = (figure, trajectory)
        return self[name]


@pytest.fixture(scope="module")
def motions():
    return _Flights()


def _quat_matrix(q) -> np.ndarray:
    w, x, y, z = q.w, q.x, q.y, q.z
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _forward_kinematics(path: Path, frame: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each joint's world position and its End Site's (None without one), from the reader's
    parse (its keyframes hold each joint's local rotation as the channels say)."""
    root = bvhio.readAsBvh(str(path)).Root
    out = {}

    def visit(joint, position, rotation, is_root):
        key = joint.Keyframes[frame]
        local = np.array(key.Position, dtype=float)
        here = local if is_root else position + rotation @ np.array(joint.Offset, dtype=float)
        turn = rotation @ _quat_matrix(key.Rotation)
        end = None
        if _has_end_site(path, joint.Name):
            end = here + turn @ np.array(joint.EndSite, dtype=float)
        out[joint.Name] = (here, end)
        for child in joint.Children:
            visit(child, here, turn, False)

    visit(root, np.zeros(3), np.eye(3), True)
    return out


def _has_end_site(path: Path, name: str) -> bool:
    """Whether joint `name` declares an End Site of its own (bvhio keeps a default one)."""
    lines = [line.strip() for line in path.read_text().splitlines()]
    start = next(i for i, line in enumerate(lines) if line.split()[-1:] == [name])
    depth = 0
    for line in lines[start + 1 :]:
        if line == "{":
            depth += 1
        elif line == "}":
            depth -= 1
            if depth == 0:
                return False
        elif line == "End Site" and depth == 1:
            return True
    return False


def _worst_endpoint_error(figure, trajectory, path: Path) -> float:
    """The largest distance (per axis, m) between a rod endpoint the file puts somewhere
    and where the simulation had it, over every rod and frame. A rod's far end is its End
    Site, or the joints of its children that start there."""
    children = {k: [] for k in range(figure.num_rods)}
    for k, parent in enumerate(figure.parents):
        if parent >= 0:
            children[parent].append(k)
    worst = 0.0
    for frame in range(len(trajectory.ts)):
        got = _forward_kinematics(path, frame)
        for k, (near, far) in enumerate(_expected(figure, trajectory, frame).values()):
            here, end = got[f"rod{k}"]
            worst = max(worst, np.abs(here - near).max())
            ends = [end] if end is not None else []
            ends += [
                got[f"rod{c}"][0] for c in children[k] if figure.rods[c][0] == figure.rods[k][1]
            ]
            assert ends, f"rod {k}'s far end is not in the file"
            worst = max(worst, max(np.abs(e - far).max() for e in ends))
    return worst


def _expected(figure, trajectory, frame: int):
    """Each rod's proximal and distal node, simulated, in the file's axes."""
    points = np.asarray(trajectory.points[frame], dtype=float) @ TO_BVH.T
    return {f"rod{k}": (points[p], points[d]) for k, (p, d) in enumerate(figure.rods)}


@pytest.mark.parametrize("name", FIGURE_PARAMS)
def test_bvh_read_back_reproduces_every_rod_at_every_frame(motions, tmp_path, name):
    figure, trajectory = motions[name]
    assert bool(trajectory.finite)
    path = jm.export.bvh(trajectory, figure, tmp_path / f"{name}.bvh")
    parsed = bvhio.readAsBvh(str(path))
    num = len(trajectory.ts)
    assert parsed.FrameCount == num
    assert abs(parsed.FrameTime - SAVE_DT) <= TIME_TOLERANCE
    worst = _worst_endpoint_error(figure, trajectory, path)
    assert worst <= FK_TOLERANCE, f"{name}: worst endpoint error {worst:.3g} m"


@pytest.mark.parametrize("name", ["star_man", "rex"])
def test_bvh_reader_hierarchy_agrees(motions, tmp_path, name):
    # bvhio's own forward kinematics (its joint hierarchy) puts every joint at its rod's
    # proximal node.
    figure, trajectory = motions[name]
    path = jm.export.bvh(trajectory, figure, tmp_path / f"{name}.bvh")
    root = bvhio.readAsHierarchy(str(path))
    worst = 0.0
    for frame in (0, len(trajectory.ts) // 2, len(trajectory.ts) - 1):
        root.loadPose(frame)
        expected = _expected(figure, trajectory, frame)
        for joint, _, _ in root.layout():
            worst = max(
                worst, np.abs(np.array(joint.PositionWorld) - expected[joint.Name][0]).max()
            )
    assert worst <= FK_TOLERANCE


@pytest.mark.parametrize("name", FIGURE_PARAMS)
def test_bvh_channels_are_the_joints_degrees_of_freedom(motions, tmp_path, name):
    figure, trajectory = motions[name]
    path = jm.export.bvh(trajectory, figure, tmp_path / f"{name}.bvh")
    parsed = bvhio.readAsBvh(str(path))
    joints = {j.Name: j for j, _, _ in parsed.Root.layout()}
    assert set(joints) == {f"rod{k}" for k in range(figure.num_rods)}
    root = joints["rod0"].Channels
    assert root[:3] == ["Xposition", "Yposition", "Zposition"]
    assert len(root) == (4 if figure.planar else 6)
    for k in range(1, figure.num_rods):
        moving = [jt for jt in figure.joints if jt.rod == k and not jt.lo == jt.hi == 0.0]
        assert len(joints[f"rod{k}"].Channels) == len(moving)
        if figure.planar:
            assert joints[f"rod{k}"].Channels == ["Xrotation"]  # about y: the file's X


def test_recording_positions_changes_nothing_else(motions):
    figure, posed = motions["snake"]
    start = _start(figure, FIGURES.index("snake"))
    plain = jm.simulate(figure, None, WORLD, DURATION, save_dt=SAVE_DT, initial_state=start)
    assert plain.positions is None
    np.testing.assert_array_equal(np.asarray(plain.points), np.asarray(posed.points))
    np.testing.assert_array_equal(np.asarray(plain.frame), np.asarray(posed.frame))
    assert np.asarray(posed.positions.com).shape[0] == len(posed.ts)


def test_a_joint_off_the_axes_gets_euler_channels(tmp_path):
    # A joint about a diagonal axis cannot be one channel: its rod gets three Euler angles,
    # and the root turns through the Euler angles' gimbal lock (pitch 90 degrees).
    figure = jm.Figure(
        [[0, 0, 0], [0.5, 0, 0], [0.5, 0.3, 0.4]],
        [(0, 1), (1, 2)],
        joints=[figures.Joint(1, (1.0, 1.0, 0.0), -1.0, 1.0)],
    )
    num = 12
    turn = np.linspace(0.0, np.pi, num)
    # Root about the file's X (the world's y) by up to 180 degrees, then some yaw.
    half = 0.5 * turn
    quat = np.stack([np.cos(half), 0.3 * np.sin(half), np.sin(half), 0.1 * np.sin(half)], 1)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    positions = jm.FigurePositions(
        jax.numpy.asarray(np.stack([turn, 0 * turn, 1 + turn], 1)),
        jax.numpy.asarray(quat),
        jax.numpy.asarray(np.linspace(-1.5, 1.5, num)[:, None]),  # beyond the range: clamped
    )
    # The simulation's own observation of those states (its batch-last layout, not compiled).
    obs = figure.dynamics().observe(
        jm.FigurePositions(*(a.T for a in positions)), jm.World(floor=False)
    )
    trajectory = jm.Trajectory(
        ts=jax.numpy.arange(num) * SAVE_DT,
        points=jax.numpy.moveaxis(obs.points, -1, 0),
        com=obs.com.T,
        frame=jax.numpy.moveaxis(obs.frame, -1, 0),
        contact=obs.contact.T,
        finite=jax.numpy.asarray(True),
        positions=positions,
    )
    path = jm.export.bvh(trajectory, figure, tmp_path / "diagonal.bvh")
    parsed = bvhio.readAsBvh(str(path))
    assert parsed.Root.Children[0].Channels == ["Zrotation", "Xrotation", "Yrotation"]
    assert _worst_endpoint_error(figure, trajectory, path) <= FK_TOLERANCE


def test_bvh_refuses_what_it_cannot_write(motions, tmp_path):
    figure, trajectory = motions["star_man"]
    bare = eqx.tree_at(lambda t: t.positions, trajectory, None)
    with pytest.raises(ValueError, match="positions=True"):
        jm.export.bvh(bare, figure, tmp_path / "a.bvh")
    with pytest.raises(ValueError, match="a lattice has no skeleton"):
        jm.export.bvh(trajectory, jm.lattices.cube(), tmp_path / "b.bvh")
    with pytest.raises(ValueError, match="not this figure's"):
        jm.export.bvh(trajectory, figures.cujo(), tmp_path / "c.bvh")
    assert list(tmp_path.iterdir()) == []


def test_bvh_is_written_atomically(motions, tmp_path, monkeypatch):
    figure, trajectory = motions["star_man"]
    path = tmp_path / "motion.bvh"
    path.write_text("the earlier file\n")

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(bvh_module.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        jm.export.bvh(trajectory, figure, path)
    assert path.read_text() == "the earlier file\n"
    assert [p.name for p in tmp_path.iterdir()] == ["motion.bvh"]  # no temporary left
    monkeypatch.undo()
    jm.export.bvh(trajectory, figure, path)
    assert path.read_text().startswith("HIERARCHY\n")
    assert [p.name for p in tmp_path.iterdir()] == ["motion.bvh"]


# ------------------------------------------------------------------------------------ USD


def _check_stage(stage, num: int) -> None:
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert abs(stage.GetTimeCodesPerSecond() - 1.0 / SAVE_DT) <= TIME_TOLERANCE / SAVE_DT**2
    assert stage.GetFramesPerSecond() == stage.GetTimeCodesPerSecond()
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, float(num - 1))
    assert stage.GetPrimAtPath("/World/floor").IsValid()


@pytest.mark.parametrize("name", FIGURE_PARAMS)
def test_usd_world_transforms_put_every_rod_where_it_was(motions, tmp_path, name):
    figure, trajectory = motions[name]
    path = jm.export.usd(trajectory, figure, tmp_path / f"{name}.usda")
    stage = Usd.Stage.Open(str(path))
    num = len(trajectory.ts)
    _check_stage(stage, num)
    rods = {p.GetName(): p for p in stage.Traverse() if p.GetName().startswith("rod")}
    assert set(rods) == {f"rod{k}" for k in range(figure.num_rods)}
    nodes = np.array(figure.nodes)
    homogeneous = np.concatenate([nodes, np.ones((len(nodes), 1))], axis=1)
    worst = 0.0
    for k, (p, d) in enumerate(figure.rods):
        xformable = UsdGeom.Xformable(rods[f"rod{k}"])
        assert xformable.GetTimeSamples() == [float(t) for t in range(num)]
        for t in range(num):
            world = np.array(xformable.ComputeLocalToWorldTransform(float(t)))  # p' = p M
            placed = homogeneous[[p, d]] @ world
            simulated = np.asarray(trajectory.points[t])[[p, d]]
            worst = max(worst, np.abs(placed[:, :3] - simulated).max())
    assert worst <= USD_TOLERANCE, f"{name}: worst endpoint error {worst:.3g} m"


def test_usd_lattice_points_and_springs_follow_the_masses(tmp_path):
    # A lattice's motion is its masses' positions: any will do (a tumbling, stretching cube
    # drawn at random here costs no compilation).
    cube = jm.lattices.cube()
    rng = np.random.default_rng(0)
    num = 16
    points = np.asarray(cube.points)[None] + rng.normal(0.0, 0.1, (num, cube.num_points, 3))
    trajectory = jm.Trajectory(
        ts=jax.numpy.arange(num) * SAVE_DT,
        points=jax.numpy.asarray(points, dtype=jax.numpy.float32),
        com=jax.numpy.asarray(points.mean(axis=1)),
        frame=jax.numpy.broadcast_to(jax.numpy.eye(3), (num, 3, 3)),
        contact=jax.numpy.zeros((num, cube.num_points), dtype=bool),
        finite=jax.numpy.asarray(True),
    )
    path = jm.export.usd(trajectory, cube, tmp_path / "cube.usd")
    stage = Usd.Stage.Open(str(path))
    num = len(trajectory.ts)
    _check_stage(stage, num)
    masses = UsdGeom.Points(stage.GetPrimAtPath("/World/cube/masses")).GetPointsAttr()
    springs = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/cube/springs"))
    assert list(springs.GetCurveVertexCountsAttr().Get()) == [2] * len(cube.springs)
    ends = np.asarray(cube.springs).reshape(-1)
    worst = 0.0
    for t in range(num):
        simulated = np.asarray(trajectory.points[t])
        worst = max(worst, np.abs(np.array(masses.Get(float(t))) - simulated).max())
        curve = np.array(springs.GetPointsAttr().Get(float(t)))
        worst = max(worst, np.abs(curve - simulated[ends]).max())
    assert worst <= USD_TOLERANCE


def test_usd_refuses_what_it_cannot_write(motions, tmp_path):
    figure, trajectory = motions["star_man"]
    with pytest.raises(ValueError, match=r"allowed: a name ending in \.usd"):
        jm.export.usd(trajectory, figure, tmp_path / "a.fbx")
    with pytest.raises(ValueError, match="positions=True"):
        jm.export.usd(
            eqx.tree_at(lambda t: t.positions, trajectory, None), figure, tmp_path / "b.usd"
        )
    with pytest.raises(ValueError, match="this body"):
        jm.export.usd(trajectory, figures.rex(), tmp_path / "c.usd")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------- config and command line

SNAKE = {
    "name": "export-snake",
    "body": {"figure": "snake"},
    "controller": {"family": "time_bsr", "num_rules": 2},
    "objective": {"forward": 1.0},
    "simulation": {"duration": 0.2, "dt": 0.005},
    "search": {"evaluations": 4, "batch": 2, "size": 2},
    "output": {"animation": False, "export": ["bvh", "usd"]},
}


def test_output_export_is_checked():
    lattice = {"objective": {"forward": 1.0}, "simulation": {"duration": 1.0}}
    with pytest.raises(
        ConfigError, match=r"\[output\] export = \['bvh'\]: BVH exports articulated"
    ):
        parse_config({**lattice, "output": {"export": ["bvh"]}})
    with pytest.raises(ConfigError, match=r"\[output\] export = \['fbx'\]; allowed: .*\"bvh\""):
        parse_config({**SNAKE, "output": {"export": ["fbx"]}})
    with pytest.raises(ConfigError, match=r"\[output\] export = 'bvh'; allowed: a list of strings"):
        parse_config({**SNAKE, "output": {"export": "bvh"}})
    assert "export" not in parse_config(lattice).output  # optional: configs resolve as before


@pytest.fixture(scope="module")
def snake_results(tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    return run_experiment(parse_config(SNAKE), directory=out, progress=False)


def _cli(monkeypatch, *argv) -> int:
    # In this process: JAX has started already, so the CLI's device set-up is skipped.
    import jaxmotion._devices as devices
    from jaxmotion._cli.main import main

    monkeypatch.setattr(devices, "use_cpu_cores", lambda: 1)
    return main(list(argv))


def test_run_writes_the_bvh_and_export_rewrites_it(snake_results, tmp_path, monkeypatch, capsys):
    written = snake_results / "motion.bvh"
    parsed = bvhio.readAsBvh(str(written))
    experiment, controller = jm.experiment.load_result(snake_results)
    replay = experiment.task.simulate(controller, positions=True)
    assert parsed.FrameCount == len(replay.ts)
    assert abs(parsed.FrameTime - experiment.task.save_dt) <= TIME_TOLERANCE
    out = tmp_path / "again.bvh"
    assert (
        _cli(monkeypatch, "export", str(snake_results), "--format", "bvh", "--out", str(out)) == 0
    )
    assert capsys.readouterr().out.strip() == str(out)
    figure = experiment.task.body
    worst = 0.0
    for frame in range(len(replay.ts)):
        got = _forward_kinematics(out, frame)
        for rod, (near, _) in _expected(figure, replay, frame).items():
            worst = max(worst, np.abs(got[rod][0] - near).max())
    assert worst <= FK_TOLERANCE
    # The USD `run` wrote, and the one `export` writes, read back alike.
    again = tmp_path / "again.usda"
    assert (
        _cli(monkeypatch, "export", str(snake_results), "--format", "usd", "--out", str(again)) == 0
    )
    for usd_path in (snake_results / "motion.usd", again):
        _check_stage(Usd.Stage.Open(str(usd_path)), len(replay.ts))


def test_export_refuses_bad_input_with_exit_2(snake_results, tmp_path, monkeypatch, capsys):
    lattice = tmp_path / "lattice-run"
    lattice.mkdir()
    (lattice / "config.toml").write_text('[body]\nlattice = "cube"\n')
    nowhere = tmp_path / "nowhere"
    cases = [
        ([str(tmp_path / "missing"), "--format", "bvh"], "not a results folder"),
        ([str(snake_results), "--format", "fbx"], "--format = 'fbx'; allowed: one of 'bvh'"),
        ([str(lattice), "--format", "bvh"], "exports articulated figures"),
        ([str(snake_results), "--format", "bvh", "--out", str(tmp_path)], "is a folder"),
        (
            [str(snake_results), "--format", "bvh", "--out", str(nowhere / "x.bvh")],
            "does not exist",
        ),
        ([str(snake_results), "--format", "usd", "--out", str(tmp_path / "x.bvh")], "a USD file"),
    ]
    before = sorted(p.name for p in snake_results.iterdir())
    for argv, message in cases:
        assert _cli(monkeypatch, "export", *argv) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lattice-run"]
    assert list(lattice.iterdir()) == [lattice / "config.toml"]
    assert sorted(p.name for p in snake_results.iterdir()) == before
