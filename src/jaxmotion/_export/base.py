"""What every export shares: the checks of a trajectory's times and the atomic write."""

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .._sim.trajectory import Trajectory

SAME_SPACING = 1e-4  # relative: saved times this evenly spaced make one frame time
TIME_DIGITS = 7  # significant digits of the frame time (the saved times are float32)


def frame_time(trajectory: Trajectory) -> tuple[np.ndarray, float]:
    """The saved times of one motion and the interval between them (to `TIME_DIGITS`).

    **Raises:** `ValueError` for something not a `Trajectory`, a batched one, one of a
    single sample or one sampled unevenly."""
    if not isinstance(trajectory, Trajectory):
        raise ValueError(f"trajectory is a {type(trajectory).__name__}; allowed: a Trajectory")
    ts = np.asarray(trajectory.ts, dtype=np.float64)
    if ts.ndim != 1:
        raise ValueError(f"the trajectory is batched (ts of shape {ts.shape}); export one motion")
    if ts.shape[0] < 2:
        raise ValueError("the trajectory has one sample; an animation needs a frame time")
    steps = np.diff(ts)
    if not np.all(np.abs(steps - steps[0]) <= SAME_SPACING * steps[0]):
        raise ValueError(
            "the trajectory's saved times are not evenly spaced; an animation needs one frame time"
        )
    return ts, float(f"{(ts[-1] - ts[0]) / (len(ts) - 1):.{TIME_DIGITS}g}")


def write_atomically(path: str | os.PathLike, write: Callable[[Path], None]) -> Path:
    """`write(temporary)` to a temporary file beside `path` (same suffix), then renamed to
    `path`: a failed export leaves no half-written file, and an existing one is replaced
    whole. Returns `path`."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".partial{path.suffix}", dir=path.parent
    )
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
