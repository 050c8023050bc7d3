"""The quickstart notebook runs end to end and shows its pictures."""

import os

import nbformat
from nbclient import NotebookClient

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(ROOT, "experiments", "notebook", "c3dpo_quickstart.ipynb")


def test_quickstart_notebook_executes_and_displays_images(tmp_path):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    # Run where there is no configs/ (as a notebook beside one's own data after pip install).
    client = NotebookClient(nb, kernel_name="python3", timeout=300,
                            resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 4  # training curves, two test poses, one new pose
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "MPJPE on the new poses" in text and "C3DPO" in text
    assert not [o for o in outputs if o.get("name") == "stderr"], "no warnings, no log lines"


def test_notebook_file_is_what_the_generator_writes(tmp_path, monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "make_quickstart", os.path.join(ROOT, "experiments", "notebook", "make_quickstart.py"))
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    fresh = nbformat.v4.new_notebook(cells=gen.CELLS)
    stored = nbformat.read(NOTEBOOK, as_version=4)
    assert [c.source for c in fresh.cells] == [c.source for c in stored.cells]
    # Committed executed: a reader sees the results and pictures without running it.
    outputs = [o for c in stored.cells if c.cell_type == "code" for o in c.outputs]
    assert len([o for o in outputs if "image/png" in o.get("data", {})]) >= 4
    assert all(c.execution_count for c in stored.cells if c.cell_type == "code")
