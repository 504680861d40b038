"""The notebooks in notebooks/ run top to bottom (nbclient) with the data present.

Slow (about 2-3 minutes for both on 2 cores) and data-dependent; skipped without the data or
without nbclient/ipykernel (``pip install -e ".[dev]"``). The notebooks are executed from
their source cells, in a temporary copy, so the committed outputs are left alone.
"""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"

# heavy: about 40 s of a cold CI run; the notebooks' helpers are tested in test_notebook_helpers.py
pytestmark = [pytest.mark.data, pytest.mark.slow, pytest.mark.heavy]


@pytest.mark.parametrize("name", ["01_stages_and_learning.ipynb", "02_evaluation.ipynb"])
def test_notebook_runs(name, data_dir, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    if not (data_dir / "crbd" / "Images").is_dir():
        pytest.skip(f"CRBD not found under {data_dir}")
    monkeypatch.setenv("TORCHROW_DATA", str(data_dir))  # the kernel inherits it
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    for cell in nb.cells:  # run from the sources, not the stored outputs
        if cell.cell_type == "code":
            cell.outputs = []
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError naming the failing cell
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
    assert any(o.get("output_type") == "display_data" for c in nb.cells if c.cell_type == "code"
               for o in c.get("outputs", []))
