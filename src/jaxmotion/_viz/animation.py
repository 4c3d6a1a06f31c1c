"""`animate`: a 3D animation of one trajectory, shown inline in Jupyter or saved as GIF/MP4."""

import os
import uuid
from pathlib import Path

import numpy as np
from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter
from matplotlib.figure import Figure

from .._body.figure import Figure as ArticulatedFigure
from .._body.lattice import Lattice
from .._sim.trajectory import Trajectory
from . import scene

SUFFIXES = (".gif", ".mp4")


class Animation:
    """A 3D animation of one trajectory, rendered when it is shown or saved.

    It holds the motion as numpy arrays, not a figure: each `save` or `to_jshtml` draws a
    fresh figure and lets it go, so keeping animations around costs no figure memory.
    Make one with `jaxmotion.viz.animate`.

    - `times`: `(num_frames,)` the simulated time of each frame, s.
    - `fps`: frames per second of simulated time (playback runs in real time).
    """

    def __init__(
        self,
        motion: scene.Motion,
        frames: np.ndarray,
        *,
        fps: float,
        figsize: tuple[float, float],
        dpi: float,
        elev: float,
        azim: float,
        title: str | None,
    ):
        self._motion = motion
        self._frames = frames
        self._view = scene.view(motion)
        self.fps = fps
        self._figsize = figsize
        self._dpi = dpi
        self._elev = elev
        self._azim = azim
        self._title = title

    @property
    def num_frames(self) -> int:
        return len(self._frames)

    def __len__(self) -> int:
        return self.num_frames

    @property
    def times(self) -> np.ndarray:
        return self._motion.ts[self._frames]

    def __repr__(self) -> str:
        return (
            f"Animation(num_frames={self.num_frames}, fps={self.fps:g}, "
            f"times={self.times[0]:g}..{self.times[-1]:g} s)"
        )

    def _render(self) -> FuncAnimation:
        """A fresh figure with the artists of one pose, and the animation that moves them."""
        # No pyplot and no GUI: the figure's default canvas draws nothing by itself, and each
        # saved frame is rendered once, by Agg, when the writer grabs it. (An Agg canvas here
        # would render every frame twice, once more on the animation's `draw_idle`.)
        fig = Figure(figsize=self._figsize, dpi=self._dpi)
        ax = fig.add_subplot(projection="3d")
        fig.subplots_adjust(left=0.0, right=1.0, bottom=0.02, top=0.98)
        step = scene.setup_axes(ax, self._view, elev=self._elev, azim=self._azim)
        ax.text2D(0.98, 0.02, f"grid {step:g} m", transform=ax.transAxes, ha="right", color="0.4")
        if self._title is not None:
            ax.set_title(self._title)
        pose = scene.Pose(ax, self._motion, self._view)
        clock = ax.text2D(0.02, 0.95, "", transform=ax.transAxes, family="monospace")

        def draw(k: int):
            i = int(self._frames[k])
            pose.update(self._motion, i)
            clock.set_text(scene.time_label(self._motion, i))
            return ()

        return FuncAnimation(
            fig,
            draw,
            frames=range(self.num_frames),
            interval=1000.0 / self.fps,
            blit=False,
            cache_frame_data=False,
        )

    def to_jshtml(self) -> str:
        """The animation as HTML with embedded frames and playback controls (Jupyter)."""
        return self._render().to_jshtml(fps=self.fps, default_mode="loop")

    def _repr_html_(self) -> str:
        return self.to_jshtml()

    def save(self, path: str | os.PathLike) -> Path:
        """Write the animation to a file: GIF for `.gif`, MP4 (H.264) for `.mp4`.

        The file appears whole or not at all: frames go to a temporary file in the same
        directory, which replaces `path` only once it is complete.

        **Arguments:**

        - `path`: where to write; its suffix chooses the format.

        **Returns:** the path written.

        **Raises:** `ValueError` for another suffix; `RuntimeError` for `.mp4` when the
        `imageio-ffmpeg` package (which ships the ffmpeg binary) is not installed.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in SUFFIXES:
            raise ValueError(
                f"Animation.save writes {' or '.join(SUFFIXES)} files; got suffix "
                f"{path.suffix or '(none)'!r} in {str(path)!r}"
            )
        writer = _pillow(self.fps) if suffix == ".gif" else _ffmpeg(self.fps)
        # The writers pick the format from the suffix, so the temporary keeps it.
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp{suffix}")
        try:
            self._render().save(tmp, writer=writer)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return path


def _pillow(fps: float) -> PillowWriter:
    return PillowWriter(fps=fps)


def _ffmpeg(fps: float) -> FFMpegWriter:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RuntimeError(
            "saving an .mp4 needs the ffmpeg binary of the imageio-ffmpeg package: run "
            "`pip install imageio-ffmpeg`, or save a .gif instead"
        ) from None
    exe = imageio_ffmpeg.get_ffmpeg_exe()

    # Point matplotlib at imageio-ffmpeg's binary for this writer only, rather than through
    # the global rcParams["animation.ffmpeg_path"].
    class _Writer(FFMpegWriter):
        @classmethod
        def bin_path(cls) -> str:
            return exe

    # yuv420p plays everywhere (browsers, QuickTime) but needs even sides, hence the pad.
    pad = ["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p"]
    return _Writer(fps=fps, codec="h264", extra_args=pad)


def frame_indices(ts: np.ndarray, fps: float) -> np.ndarray:
    """Indices of the saved samples nearest to the times `ts[0] + k / fps`, up to `ts[-1]`."""
    span = float(ts[-1] - ts[0])
    # The tolerance keeps the last frame when float32 times stop just short of the duration.
    num = int(np.floor(span * fps + 1e-3)) + 1
    wanted = ts[0] + np.arange(num) / fps
    if len(ts) == 1:
        return np.zeros(num, dtype=int)
    right = np.clip(np.searchsorted(ts, wanted), 1, len(ts) - 1)
    left = right - 1
    nearer_left = np.abs(wanted - ts[left]) <= np.abs(ts[right] - wanted)
    return np.where(nearer_left, left, right)


def animate(
    trajectory: Trajectory,
    body: Lattice | ArticulatedFigure | None = None,
    *,
    fps: float = 25.0,
    figsize: tuple[float, float] = (5.0, 4.0),
    dpi: float = 80.0,
    elev: float = 20.0,
    azim: float = -60.0,
    title: str | None = None,
) -> Animation:
    """A 3D animation of one trajectory: the points, the springs of `body`, the floor, the
    body frame at the centre of mass (forward red, left green, up blue) and the time.

    The axes are fixed for the whole motion, with the same scale on x, y and z and the floor
    z = 0 in view. Points touching the floor are orange. Frames are the saved samples
    nearest to every `1 / fps` s of simulated time, so playback runs in real time.

    **Arguments:**

    - `trajectory`: one (unbatched) `Trajectory`, e.g. from `task.simulate(controller)`.
    - `body`: the `Lattice` or `Figure` that was simulated, to draw its springs or rods;
        `None` draws the points
        only.
    - `fps`: frames per second of simulated time.
    - `figsize`, `dpi`: size of the figure in inches and its resolution (pixels per inch).
    - `elev`, `azim`: viewing angles in degrees (as `Axes3D.view_init`).
    - `title`: drawn above the view.

    **Returns:** an `Animation`: shown inline in Jupyter; `.save("walk.gif")` or
    `.save("walk.mp4")` writes a file.

    **Raises:** `ValueError` for a batched trajectory, a body with another number of masses,
    or a non-positive `fps`.
    """
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"animate needs fps > 0 (frames per second); got fps={fps}")
    m = scene.motion(trajectory, body, caller="animate")
    return Animation(
        m,
        frame_indices(m.ts, fps),
        fps=fps,
        figsize=figsize,
        dpi=dpi,
        elev=elev,
        azim=azim,
        title=title,
    )
