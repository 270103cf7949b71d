"""The notebooks in notebooks/ run top to bottom, and are committed without outputs.

Each notebook is executed with nbclient in a fresh python3 kernel, from the notebooks/ folder,
with JAXMPM_NOTEBOOK_SMALL=1 (each notebook's first cell then picks coarse grids, short runs
and few iterations: a smoke test of the code shown, not of the physics, which the notebooks
report at their full settings). The kernel imports jaxmpm and inverse from this working tree
and writes its pictures and files into a temporary folder (JAXMPM_NOTEBOOK_OUTPUT). The kernel
compiles with LLVM's optimisations off (--xla_backend_optimization_level=0, beside the suite's
own XLA flags): at the SMALL settings compiling is most of a notebook's time, and it takes
2-2.5 times less, while the short runs go 2-4 times slower (notebooks 01-06: 123 -> 105 s of
kernel CPU). A cell that raises fails the test, with the cell's source and traceback in the
message.

Committed notebooks must hold no outputs and no execution counts, so that their diffs stay
small and no stale result is kept in git: strip them before committing (e.g.
`jupyter nbconvert --clear-output --inplace notebooks/*.ipynb`).
"""

import os
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
CELL_TIMEOUT = 600          # seconds per cell: generous, the SMALL settings need a few
QUICK_TO_COMPILE = "--xla_backend_optimization_level=0"


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 5, f"expected the five notebooks in {ROOT / 'notebooks'}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[path.stem for path in NOTEBOOKS])
def test_notebook_is_stored_without_outputs(path):
    notebook = nbformat.read(path, as_version=4)
    nbformat.validate(notebook)
    for index, cell in enumerate(notebook.cells):
        if cell.cell_type != "code":
            continue
        assert cell.get("outputs") == [], f"{path.name}: code cell {index} holds outputs: strip them"
        assert cell.get("execution_count") is None, f"{path.name}: code cell {index} has an execution count"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[path.stem for path in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    notebook = nbformat.read(path, as_version=4)
    first = next(cell for cell in notebook.cells if cell.cell_type == "code")
    assert "JAXMPM_NOTEBOOK_SMALL" in first.source, f"{path.name}: the first code cell must read JAXMPM_NOTEBOOK_SMALL"

    # The kernel inherits this environment: quick settings, quick compiling, this tree's
    # packages first, and outputs in a temporary folder.
    monkeypatch.setenv("JAXMPM_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("XLA_FLAGS", f"{os.environ.get('XLA_FLAGS', '')} {QUICK_TO_COMPILE}".strip())
    monkeypatch.setenv("JAXMPM_NOTEBOOK_OUTPUT", str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    client = nbclient.NotebookClient(
        notebook, timeout=CELL_TIMEOUT, kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as error:
        pytest.fail(f"{path.name}: a cell failed:\n{error}", pytrace=False)
    print(f"{path.name}: {time.perf_counter() - start:.1f} s with JAXMPM_NOTEBOOK_SMALL=1")
    assert any(path.suffix == ".png" for path in tmp_path.iterdir()), f"{path.name} saved no picture"
