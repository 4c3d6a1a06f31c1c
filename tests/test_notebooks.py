"""The notebooks run top to bottom (with small budgets) and are committed without outputs."""

import json
import re
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
SMALL = {
    "EVALUATIONS": "200",
    "BATCH": "50",
    "DURATION": "1.0",
    "MOTIONS": '("star_man",)',
    "FPS": "4",  # rendering the animations' frames is a large share of a notebook's run
}
HERE = Path(__file__).resolve().parents[1] / "notebooks"


def test_there_are_notebooks():
    assert {p.name for p in NOTEBOOKS} >= {
        "quickstart.ipynb",
        "reflexes.ipynb",
        "paper000_motions.ipynb",
    }


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            assert cell["outputs"] == [] and cell["execution_count"] is None


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if "parameters" in cell.get("metadata", {}).get("tags", []):
            for name, value in SMALL.items():
                cell.source = re.sub(
                    rf"^{name} = .*$", f"{name} = {value}", cell.source, flags=re.M
                )
    # Run from the notebooks folder, as a user would (they find ../configs from there).
    NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
    ).execute()
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert errors == []
