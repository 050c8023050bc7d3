"""The committed quickstart notebook is what its generator writes, executed. (It is run
end to end by a fresh installation of the package: tests/install_test.py.)"""

import os

import nbformat

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(ROOT, "experiments", "notebook", "c3dpo_quickstart.ipynb")


def test_notebook_file_is_what_the_generator_writes(tmp_path, monkeypatch, load_script):
    gen = load_script("experiments/notebook/make_quickstart.py")
    fresh = nbformat.v4.new_notebook(cells=gen.CELLS)
    stored = nbformat.read(NOTEBOOK, as_version=4)
    assert [c.source for c in fresh.cells] == [c.source for c in stored.cells]
    # Committed executed: a reader sees the results and pictures without running it.
    outputs = [o for c in stored.cells if c.cell_type == "code" for o in c.outputs]
    assert len([o for o in outputs if "image/png" in o.get("data", {})]) >= 4
    assert all(c.execution_count for c in stored.cells if c.cell_type == "code")
