"""`learning_plot`: the fitness of every evaluation of a search and the best so far;
`learning_curves`: the best so far of several independent runs."""

from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .._search.history import History


def learning_plot(
    history: History | Float[ArrayLike, " num_evaluations"],
    *,
    ax: Axes | None = None,
    title: str | None = None,
) -> Figure:
    """The learning plot of a search (the first paper's Figure 6): the fitness of every
    evaluation as a small point, and the best fitness so far as a line. Fitness is
    maximised.

    Evaluations whose fitness is not finite (`-inf` marks a simulation that blew up) are not
    drawn and do not count towards the best so far; the legend says how many there were.

    **Arguments:**

    - `history`: a `History` (e.g. `parallel_hill_climb(...).history`) or a 1-D array of the
        fitness of each evaluation, in order.
    - `ax`: axes to draw into; `None` makes a new figure.
    - `title`: drawn above the plot.

    **Returns:** the `matplotlib.figure.Figure` drawn into (the one holding `ax` if given).
    Evaluation numbers on the x-axis start at 1.

    **Raises:** `ValueError` if the fitness is not one-dimensional.
    """
    fitness = _fitness(history, "learning_plot")
    fig, ax = _axes(ax)
    evaluation = np.arange(1, fitness.shape[0] + 1)
    finite = np.isfinite(fitness)
    num_nonfinite = int(np.sum(~finite))
    label = "evaluation"
    if num_nonfinite:
        label += f" ({num_nonfinite} blew up, not drawn)"
    ax.scatter(
        evaluation[finite],
        fitness[finite],
        s=4,
        color="tab:blue",
        alpha=0.5,
        linewidths=0,
        label=label,
    )
    _plot_best_so_far(ax, fitness, color="tab:red", label="best so far")
    ax.set_xlabel("evaluation")
    ax.set_ylabel("fitness")
    if title is not None:
        ax.set_title(title)
    ax.legend(loc="lower right", markerscale=3)
    return fig


def learning_curves(
    histories: Sequence[History | Float[ArrayLike, " num_evaluations"]],
    *,
    labels: Sequence[str] | None = None,
    ax: Axes | None = None,
    title: str | None = None,
) -> Figure:
    """The learning curves of independent runs of one search (the second paper's Figure 8,
    its run-to-run spread): the best fitness so far of each run against its evaluations,
    one line per run. Non-finite evaluations do not count; a run's line starts at its first
    finite evaluation.

    **Arguments:** `histories` (one `History` or 1-D fitness array per run, e.g.
    `[r.history for r in serial_search(..., seeds=5).runs]`); `labels` (one per run;
    default "run 0", "run 1", ...); `ax`; `title`.

    **Returns:** the `matplotlib.figure.Figure` drawn into.

    **Raises:** `ValueError` for no runs, a fitness that is not one-dimensional, or a number
    of labels that is not the number of runs.
    """
    runs = [_fitness(h, f"learning_curves (run {i})") for i, h in enumerate(histories)]
    if not runs:
        raise ValueError("learning_curves needs at least one run's history")
    labels = [f"run {i}" for i in range(len(runs))] if labels is None else list(labels)
    if len(labels) != len(runs):
        raise ValueError(f"learning_curves: {len(labels)} labels for {len(runs)} runs")
    fig, ax = _axes(ax)
    for fitness, label in zip(runs, labels, strict=True):
        _plot_best_so_far(ax, fitness, label=label)
    ax.set_xlabel("evaluation")
    ax.set_ylabel("best fitness so far")
    if title is not None:
        ax.set_title(title)
    ax.legend(loc="lower right")
    return fig


def _fitness(history, who: str) -> np.ndarray:
    """The fitness of every evaluation of `history` (a `History` or an array), 1-D."""
    fitness = np.asarray(history.fitness if isinstance(history, History) else history, float)
    if fitness.ndim != 1:
        raise ValueError(
            f"{who} needs one fitness per evaluation (a History or a 1-D array); got an "
            f"array of shape {fitness.shape}"
        )
    return fitness


def _axes(ax: Axes | None) -> tuple[Figure, Axes]:
    """The figure holding `ax`, or a new figure and axes (rendered without pyplot or a GUI
    backend)."""
    if ax is not None:
        return _root_figure(ax), ax
    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


def _plot_best_so_far(ax: Axes, fitness: np.ndarray, **style) -> None:
    """The best finite fitness so far against the evaluation number (from 1), as steps. The
    line starts at the first finite evaluation: before it there is no best yet."""
    finite = np.isfinite(fitness)
    best = np.maximum.accumulate(np.where(finite, fitness, -np.inf))
    start = int(np.argmax(finite)) if finite.any() else fitness.shape[0]
    evaluation = np.arange(1, fitness.shape[0] + 1)
    ax.plot(evaluation[start:], best[start:], linewidth=1.5, drawstyle="steps-post", **style)


def _root_figure(ax: Axes) -> Figure:
    fig = ax.figure
    # Axes in a SubFigure report the subfigure; its own `figure` is the root Figure.
    return fig if isinstance(fig, Figure) else fig.figure
