import sys

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from matplotlib.animation import PillowWriter
from matplotlib.figure import Figure
from PIL import Image, ImageChops

import jaxmotion as jm
import jaxmotion.viz as viz
from jaxmotion._viz import animation as animation_module


@pytest.fixture(scope="module")
def cube_motion():
    """One second of a cube under a random controller (it moves from the first instant)."""
    task = jm.Task(
        jm.lattices.cube(),
        jm.World(),
        jm.RegimesSpace(4, 1.0),
        jm.Objective({"forward": 1.0, "upright": -10.0}),
        duration=1.0,
    )
    controllers = task.sample(2, key=jr.key(0))
    trajectory = task.simulate(jax.tree_util.tree_map(lambda a: a[0], controllers))
    return trajectory, task.body


def _sliding(num_saves: int = 11, save_dt: float = 0.1) -> jm.Trajectory:
    """Two points sliding along x at 1 m/s, as jax arrays: a small motion made by hand."""
    ts = jnp.arange(num_saves) * save_dt
    rest = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    points = rest[None] + ts[:, None, None] * jnp.array([1.0, 0.0, 0.0])
    return jm.Trajectory(
        ts=ts,
        points=points,
        com=points.mean(axis=1),
        frame=jnp.broadcast_to(jnp.eye(3), (num_saves, 3, 3)),
        contact=points[..., 2] <= 0.0,
        finite=jnp.asarray(True),
    )


def _batched(trajectory: jm.Trajectory) -> jm.Trajectory:
    return jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), trajectory)


def test_learning_plot_draws_each_finite_evaluation_and_the_best_so_far():
    fitness = np.random.default_rng(0).normal(size=50)
    blew_up = [3, 17, 40]
    fitness[blew_up] = -np.inf
    history = jm.History(fitness, np.repeat(np.arange(5), 10))

    fig = viz.learning_plot(history, title="cube")

    assert isinstance(fig, Figure)
    (ax,) = fig.axes
    finite = np.isfinite(fitness)
    (scatter,) = ax.collections
    offsets = np.asarray(scatter.get_offsets())
    evaluation = np.arange(1, 51)
    np.testing.assert_array_equal(offsets[:, 0], evaluation[finite])
    np.testing.assert_array_equal(offsets[:, 1], fitness[finite])
    (best,) = ax.lines
    np.testing.assert_array_equal(best.get_xdata(), evaluation)
    np.testing.assert_array_equal(best.get_ydata(), np.maximum.accumulate(fitness))
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("3 blew up" in text for text in legend)
    assert ax.get_title() == "cube"


def test_learning_plot_of_an_array_into_given_axes_starts_at_the_first_finite():
    fitness = jnp.array([-jnp.inf, -jnp.inf, 1.0, 0.5, -jnp.inf, 2.0, 1.5])
    fig = Figure()
    ax = fig.add_subplot()

    assert viz.learning_plot(fitness, ax=ax) is fig

    (scatter,) = ax.collections
    assert len(scatter.get_offsets()) == 4
    (best,) = ax.lines
    np.testing.assert_array_equal(best.get_xdata(), [3, 4, 5, 6, 7])
    np.testing.assert_array_equal(best.get_ydata(), [1.0, 1.0, 1.0, 2.0, 2.0])
    assert any("3 blew up" in t.get_text() for t in ax.get_legend().get_texts())


def test_learning_plot_rejects_fitness_that_is_not_1d():
    with pytest.raises(ValueError, match="shape"):
        viz.learning_plot(np.zeros((3, 4)))


def test_learning_curves_draw_each_runs_best_so_far():
    runs = [np.array([1.0, 0.5, 2.0, 1.0]), np.array([-np.inf, 0.0, 3.0, -1.0, 4.0])]
    fig = viz.learning_curves(runs, title="five runs")
    (ax,) = fig.axes
    first, second = ax.lines
    np.testing.assert_array_equal(first.get_xdata(), [1, 2, 3, 4])
    np.testing.assert_array_equal(first.get_ydata(), [1.0, 1.0, 2.0, 2.0])
    # The second run's line starts at its first finite evaluation.
    np.testing.assert_array_equal(second.get_xdata(), [2, 3, 4, 5])
    np.testing.assert_array_equal(second.get_ydata(), [0.0, 3.0, 3.0, 4.0])
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["run 0", "run 1"]
    assert ax.get_title() == "five runs"
    with pytest.raises(ValueError, match="2 labels for 1 runs"):
        viz.learning_curves(runs[:1], labels=["a", "b"])
    with pytest.raises(ValueError, match="at least one"):
        viz.learning_curves([])


def test_animate_saves_a_gif_with_one_frame_per_tick(cube_motion, tmp_path):
    trajectory, body = cube_motion
    fps = 10
    animation = viz.animate(trajectory, body, fps=fps)
    assert float(trajectory.ts[-1]) == pytest.approx(1.0)
    expected = 11  # frames at 0, 0.1, ..., 1.0 s

    assert len(animation) == expected
    path = tmp_path / "cube.gif"
    assert animation.save(path) == path

    with Image.open(path) as gif:
        assert gif.n_frames == expected
        first = gif.convert("RGB")
        gif.seek(gif.n_frames - 1)
        last = gif.convert("RGB")
    assert ImageChops.difference(first, last).getbbox() is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.gif"]


def test_animate_picks_the_nearest_saved_samples():
    trajectory = _sliding(num_saves=11, save_dt=0.1)  # 0 to 1 s
    animation = viz.animate(trajectory, fps=4)
    np.testing.assert_allclose(animation.times, [0.0, 0.2, 0.5, 0.7, 1.0], atol=1e-6)
    # Fewer saved samples than frames: samples repeat rather than being interpolated.
    assert len(viz.animate(trajectory, fps=20)) == 21


def test_animation_shows_inline_as_html():
    html = viz.animate(_sliding(num_saves=3), fps=10)._repr_html_()
    assert "<script" in html and "<img" in html


def test_save_to_an_unknown_suffix_is_an_error_and_writes_nothing(tmp_path):
    animation = viz.animate(_sliding(num_saves=3), fps=10)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4 files; got suffix '\.avi'"):
        animation.save(tmp_path / "motion.avi")
    with pytest.raises(ValueError, match="none"):
        animation.save(tmp_path / "motion")
    assert list(tmp_path.iterdir()) == []


class _FailingWriter(PillowWriter):
    """Writes half a file, then fails, as a full disk would."""

    def finish(self):
        with open(self.outfile, "wb") as f:
            f.write(b"GIF89a")
        raise OSError("disk full")


def test_a_failed_save_leaves_no_partial_file(tmp_path, monkeypatch):
    monkeypatch.setattr(animation_module, "_pillow", lambda fps: _FailingWriter(fps=fps))
    animation = viz.animate(_sliding(num_saves=3), fps=10)
    with pytest.raises(OSError, match="disk full"):
        animation.save(tmp_path / "new.gif")
    assert list(tmp_path.iterdir()) == []

    # An existing file is left as it was.
    (tmp_path / "old.gif").write_bytes(b"old")
    with pytest.raises(OSError, match="disk full"):
        animation.save(tmp_path / "old.gif")
    assert [p.name for p in tmp_path.iterdir()] == ["old.gif"]
    assert (tmp_path / "old.gif").read_bytes() == b"old"


def test_mp4_without_imageio_ffmpeg_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # makes the import fail
    animation = viz.animate(_sliding(num_saves=3), fps=10)
    with pytest.raises(RuntimeError, match=r"pip install imageio-ffmpeg.*\.gif"):
        animation.save(tmp_path / "motion.mp4")
    assert list(tmp_path.iterdir()) == []


def test_mp4_with_imageio_ffmpeg(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    path = viz.animate(_sliding(num_saves=6), fps=10).save(tmp_path / "motion.mp4")
    assert path.stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir()] == ["motion.mp4"]


@pytest.mark.parametrize("follow", [False, True])
def test_filmstrip_has_one_panel_per_pose_at_one_scale(cube_motion, follow):
    trajectory, body = cube_motion
    fig = viz.filmstrip(trajectory, 4, body, follow=follow)

    assert isinstance(fig, Figure)
    assert len(fig.axes) == 4
    sizes = {
        tuple(np.round([np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()), np.ptp(ax.get_zlim())], 9))
        for ax in fig.axes
    }
    assert len(sizes) == 1
    labels = [[t.get_text() for t in ax.texts] for ax in fig.axes]
    assert labels[0] == ["t = 0.00 s"] and labels[-1] == ["t = 1.00 s"]
    for ax in fig.axes:
        assert ax.get_zlim()[0] <= 0.0  # the floor is in view


def test_filmstrip_needs_at_least_one_pose():
    with pytest.raises(ValueError, match="n >= 1"):
        viz.filmstrip(_sliding(), 0)
    assert len(viz.filmstrip(_sliding(), 1).axes) == 1


def test_a_batched_trajectory_is_an_error():
    batched = _batched(_sliding())
    with pytest.raises(ValueError, match="tree_map"):
        viz.animate(batched)
    with pytest.raises(ValueError, match="tree_map"):
        viz.filmstrip(batched)


def test_the_body_must_match_the_trajectory(cube_motion):
    trajectory, _ = cube_motion
    with pytest.raises(ValueError, match="8 points"):
        viz.animate(trajectory, jm.lattices.pyramid())


def test_fps_must_be_positive():
    with pytest.raises(ValueError, match="fps"):
        viz.animate(_sliding(), fps=0)


def test_a_run_that_blew_up_draws_its_finite_part(tmp_path):
    trajectory = _sliding()
    points = trajectory.points.at[6:].set(jnp.nan)
    trajectory = jm.Trajectory(
        ts=trajectory.ts,
        points=points,
        com=points.mean(axis=1),
        frame=trajectory.frame,
        contact=trajectory.contact,
        finite=jnp.asarray(False),
    )
    fig = viz.filmstrip(trajectory, 2)
    assert [t.get_text() for t in fig.axes[1].texts] == ["t = 1.00 s (blew up)"]
    viz.animate(trajectory, fps=10).save(tmp_path / "blew_up.gif")


def test_reflexes_draws_twelve_deformed_shapes():
    fig = jm.viz.reflexes(jm.lattices.pyramid(), -1.0)
    axes = fig.get_axes()
    assert len(axes) == 12
    assert [ax.get_title().split(":")[0] for ax in axes] == [str(r) for r in range(12)]
    with pytest.raises(ValueError, match=r"coefficient = 2.0; allowed: -1 <= coefficient <= 1"):
        jm.viz.reflexes(jm.lattices.cube(), 2.0)
