"""The figures' notebooks run top to bottom with small budgets (a file of their own so that
they run beside the other notebooks; see `notebook_runner`)."""

import pytest
from notebook_runner import FIGURE_NOTEBOOKS, HERE, SLOW_NOTEBOOKS, run_notebook


@pytest.mark.parametrize(
    "name",
    # Bob's sense-based search compiles for about a minute: `-m slow`.
    [
        pytest.param(n, marks=pytest.mark.slow) if n in SLOW_NOTEBOOKS else n
        for n in FIGURE_NOTEBOOKS
    ],
)
def test_notebook_runs(name):
    assert run_notebook(HERE / name) == []
