"""Running a notebook as the tests do: top to bottom from the notebooks folder (as a user
would: they find ../configs from there), its `parameters` cell set to small budgets.

The notebook tests are split over two files (`test_notebooks.py`, `test_notebooks_figures.py`)
so that pytest-xdist's `--dist loadfile` can run them on two workers at once: in one file
they were the last minutes of the suite on one worker."""

import re
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(HERE.glob("*.ipynb"))
FIGURE_NOTEBOOKS = ("figures.ipynb", "walking.ipynb")  # run by test_notebooks_figures.py
# Notebooks whose small-budget run still takes a minute or more (several searches compile):
# run with `-m slow`, as the README's test section says.
SLOW_NOTEBOOKS = ("walking.ipynb", "composite.ipynb", "stochastic_vs_gradient.ipynb")
SMALL = {
    "EVALUATIONS": "200",
    "BATCH": "50",
    "DURATION": "1.0",
    "MOTIONS": '("star_man",)',
    "FPS": "4",  # rendering the animations' frames is a large share of a notebook's run
    "GENERATIONS": "3",
    "POPULATION": "20",  # spring_nets.ipynb: 4 survivors, one call of 16 per generation
    "SHOW": "2",
    "ROUNDS": "1",
}


def run_notebook(path: Path) -> list:
    """Execute the notebook at `path` with `SMALL` budgets; return its error outputs."""
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if "parameters" in cell.get("metadata", {}).get("tags", []):
            for name, value in SMALL.items():
                cell.source = re.sub(
                    rf"^{name} = .*$", f"{name} = {value}", cell.source, flags=re.M
                )
    NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
    ).execute()
    return [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
