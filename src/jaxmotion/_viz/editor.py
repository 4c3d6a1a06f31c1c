"""The composite-motion editor for Jupyter (the second paper's section 3): a slider per
transition, the motion re-simulated and redrawn on release, the script's values beside it,
and a button that searches the transitions from where the sliders are."""

import html
import io
from typing import Any

import jax.random as jr
import numpy as np

from .._composite import Composite
from .filmstrip import filmstrip


def _widgets():
    try:
        import ipywidgets
    except ImportError:
        raise ImportError(
            "the composite editor needs ipywidgets: pip install 'jaxmotion[editor]'"
        ) from None
    return ipywidgets


class CompositeEditor:
    """An interactive editor of a `Composite`'s transitions (ipywidgets).

    - one slider per transition (s, on the tick grid), named after the phases it joins;
        moving one re-simulates the composite and redraws it when the slider is released
        (a slider cannot pass its neighbours: the phases keep their order);
    - a filmstrip of the motion (`frames` poses; `animate` renders the GIF on demand);
    - a table of every value the script assigns (each phase's credit and the total);
    - a button that runs the transition-point search (`Composite.search`, with `search`'s
        settings) from the sliders' values and moves the sliders to its result.

    Display it as the last expression of a cell (or `display(editor)`). Everything is also
    reachable from Python, which is how it is tested: set `editor.sliders[i].value`, call
    `editor.search_button.click()`, read `editor.transitions`, `editor.values` and
    `editor.trajectory`.

    **Arguments:** `composite`; `transitions` to start from (default: equally spaced);
    `frames`: poses in the filmstrip; `search`: keyword arguments of `Composite.search`
    (`num_arrays`, `rounds`, `mutations`); `key`: the searches' PRNG key (each press draws
    from `fold_in(key, press)`); `elev`, `azim`: the view (default: side-on for a planar
    figure).

    **Raises:** `ImportError` naming the extra to install when ipywidgets is missing.
    """

    def __init__(
        self,
        composite: Composite,
        transitions=None,
        *,
        frames: int = 8,
        search: dict[str, Any] | None = None,
        key=None,
        elev: float | None = None,
        azim: float | None = None,
    ):
        w = _widgets()
        self.composite = composite
        self.frames = frames
        self.search_settings = dict(search or {})
        self.key = jr.key(0) if key is None else key
        self.presses = 0
        planar = getattr(composite.body, "planar", False)
        self.elev = (0.0 if planar else 20.0) if elev is None else elev
        self.azim = (-90.0 if planar else -60.0) if azim is None else azim
        start = composite.equally_spaced() if transitions is None else np.asarray(transitions)
        names = composite.phases
        tick = composite.tick
        self.sliders = [
            w.FloatSlider(
                value=float(t),
                min=0.0,
                max=composite.duration,
                step=tick,
                description=f"{names[i]} → {names[i + 1]}",
                continuous_update=False,
                readout_format=".3f",
                style={"description_width": "initial"},
                layout=w.Layout(width="95%"),
            )
            for i, t in enumerate(start)
        ]
        self._quiet = False
        for i, slider in enumerate(self.sliders):
            slider.observe(lambda change, i=i: self._moved(i, change), names="value")
        self.search_button = w.Button(description="Search transitions", icon="search")
        self.search_button.on_click(self._search)
        self.animate_button = w.Button(description="Animate", icon="play")
        self.animate_button.on_click(lambda _: self.animate())
        self.status = w.Label()
        self.table = w.HTML()
        self.picture = w.Image(format="png")
        self.movie = w.Image(format="gif")
        self.widget = w.VBox(
            [
                *self.sliders,
                w.HBox([self.search_button, self.animate_button, self.status]),
                self.table,
                self.picture,
                self.movie,
            ]
        )
        self.trajectory = None
        self.values: dict[str, float] = {}
        self.refresh()

    @property
    def transitions(self) -> np.ndarray:
        """The sliders' transition times (s), in order."""
        return np.array([s.value for s in self.sliders], dtype=float)

    def refresh(self) -> None:
        """Simulate the composite at the sliders' transitions and redraw it."""
        transitions = self.transitions
        self.trajectory = self.composite.trajectory(transitions)
        self.values = self.composite.values(transitions)
        rows = "".join(
            f"<tr><td>{html.escape(k)}</td><td style='text-align:right'>{v:.4g}</td></tr>"
            for k, v in self.values.items()
        )
        self.table.value = f"<table><tr><th>script</th><th>value</th></tr>{rows}</table>"
        fig = filmstrip(
            self.trajectory,
            self.frames,
            self.composite.body,
            panel_size=2.0,
            elev=self.elev,
            azim=self.azim,
            title=f"total = {self.values['total']:.4g}",
        )
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=80)
        self.picture.value = buffer.getvalue()
        self.movie.value = b""

    def animate(self, fps: int = 25) -> None:
        """Render the present motion as a GIF under the filmstrip."""
        import os
        import tempfile

        from .animation import animate

        with tempfile.TemporaryDirectory() as folder:
            path = os.path.join(folder, "motion.gif")
            animate(self.trajectory, self.composite.body, fps=fps).save(path)
            with open(path, "rb") as f:
                self.movie.value = f.read()

    def _moved(self, i: int, change) -> None:
        if self._quiet:
            return
        lo = self.sliders[i - 1].value if i > 0 else 0.0
        hi = self.sliders[i + 1].value if i + 1 < len(self.sliders) else self.composite.duration
        value = min(max(change["new"], lo), hi)
        if value != change["new"]:
            self._quiet = True
            self.sliders[i].value = value
            self._quiet = False
        self.status.value = ""
        self.refresh()

    def _search(self, _button=None) -> None:
        self.status.value = "searching..."
        key = jr.fold_in(self.key, self.presses)
        self.presses += 1
        result = self.composite.search(key=key, initial=self.transitions, **self.search_settings)
        self._quiet = True
        try:
            for slider, t in zip(self.sliders, np.asarray(result.best), strict=True):
                slider.value = float(t)
        finally:
            self._quiet = False
        self.refresh()
        self.status.value = (
            f"searched: total {result.best_fitness:.4g} ({int(result.evaluations)} simulations)"
        )

    def _repr_mimebundle_(self, **kwargs):
        return self.widget._repr_mimebundle_(**kwargs)


def composite_editor(composite: Composite, transitions=None, **kwargs) -> CompositeEditor:
    """`CompositeEditor(composite, transitions, **kwargs)`: the interactive editor of a
    composite motion's transitions (needs the `editor` extra, ipywidgets)."""
    return CompositeEditor(composite, transitions, **kwargs)
