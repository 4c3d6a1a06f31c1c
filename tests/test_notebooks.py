"""The notebooks run top to bottom (with small budgets) and are committed without outputs
(the figures' notebooks run in `test_notebooks_figures.py`; see `notebook_runner`)."""

import json

import pytest
from notebook_runner import FIGURE_NOTEBOOKS, NOTEBOOKS, SLOW_NOTEBOOKS, run_notebook


def test_there_are_notebooks():
    assert {p.name for p in NOTEBOOKS} >= {
        "quickstart.ipynb",
        "reflexes.ipynb",
        "paper000_motions.ipynb",
        "composite.ipynb",
        *FIGURE_NOTEBOOKS,
    }


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            assert cell["outputs"] == [] and cell["execution_count"] is None


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_NOTEBOOKS else p
        for p in NOTEBOOKS
        if p.name not in FIGURE_NOTEBOOKS
    ],
    ids=lambda p: p.name,
)
def test_notebook_runs(path):
    assert run_notebook(path) == []
