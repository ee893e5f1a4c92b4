"""The tutorials run: a broken tutorial fails the test suite.

The quick-start notebook is executed cell by cell in a kernel of the Python
running pytest, on a small map (``GEOMDIC_TUTORIAL_QUICK=1`` makes its first
cell choose a 6 x 6 map). The other tutorials take minutes each and are
executed when the book is built (``jupyter-book build docs -W``); here they
are only checked to be valid notebooks without stored outputs or errors.
"""

import os
import sys
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

TUTORIALS = Path(__file__).resolve().parents[1] / "tutorials"
NOTEBOOKS = sorted(TUTORIALS.glob("*.ipynb"))


def _run(path: Path, timeout: int = 600) -> nbformat.NotebookNode:
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name="python3",  # jupyter_client starts it with sys.executable
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    return nb


def _stdout(nb: nbformat.NotebookNode) -> str:
    return "".join(
        out.get("text", "")
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.get("outputs", [])
        if out.get("output_type") == "stream" and out.get("name") == "stdout"
    )


def test_tutorials_exist():
    names = [p.name for p in NOTEBOOKS]
    assert "01_quickstart.ipynb" in names
    assert len(names) >= 5, names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_clean(path):
    """Valid nbformat, no stored outputs: the book executes them fresh."""
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.cells[0].cell_type == "markdown"
    assert nb.cells[0].source.startswith("# "), "the first cell holds the title"
    assert "Run time" in nb.cells[0].source, "each tutorial states its run time"
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert not cell.outputs, f"{path.name} has stored outputs"


@pytest.mark.slow
def test_quickstart_runs(monkeypatch):
    monkeypatch.setenv("GEOMDIC_TUTORIAL_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # The kernel is started with the Python running the tests
    assert os.path.exists(sys.executable)
    nb = _run(TUTORIALS / "01_quickstart.ipynb")
    out = _stdout(nb)
    assert "refined, calibrated detector" in out
    assert "This notebook ran in" in out
    assert "(6 x 6 map)" in out
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.outputs
        if o.get("output_type") == "error"
    ]
    assert not errors
