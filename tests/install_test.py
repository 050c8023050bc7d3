"""The package as a user installs it: the wheel's contents, and ``pip install`` of it into a
fresh virtual environment, then training, prediction and the quickstart notebook run from a
directory with no ``configs/`` and no checkout on the path.

The fresh environment gets this package from the wheel only; its dependencies (jax, flax, ...)
are made visible from the test's own environment by a ``.pth`` line rather than downloaded,
so the test needs no network. That line adds a directory to the path without running the
``.pth`` files in it, so the editable install of the checkout is not visible there (the
test checks which ``c3dpo_jax`` each step imported).
"""

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile

import nbformat
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(ROOT, "experiments", "notebook", "c3dpo_quickstart.ipynb")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """The wheel built from a copy of the package's sources (not the checkout itself, which
    holds build outputs and virtual environments)."""
    pytest.importorskip("setuptools", minversion="77")  # PEP 639 license fields
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(os.path.join(ROOT, name), src)
    for name in ("c3dpo_jax", "configs"):
        shutil.copytree(os.path.join(ROOT, name), src / name,
                        ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-c", "from setuptools import build_meta as b; "
                    f"b.build_wheel({str(tmp / 'dist')!r})"],
                   cwd=src, check=True, capture_output=True, timeout=120)
    (name,) = os.listdir(tmp / "dist")
    return str(tmp / "dist" / name)


def test_wheel_holds_the_configs_under_the_package_and_no_top_level_configs(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        entry_points = z.read("c3dpo_jax-0.1.0.dist-info/entry_points.txt").decode()
        top_level = z.read("c3dpo_jax-0.1.0.dist-info/top_level.txt").decode().split()
    assert top_level == ["c3dpo_jax"]
    assert {n.split("/")[0] for n in names} == {"c3dpo_jax", "c3dpo_jax-0.1.0.dist-info"}
    configs = sorted(n for n in os.listdir(os.path.join(ROOT, "configs")) if n.endswith(".py"))
    assert sorted(n.split("/")[-1] for n in names if n.startswith("c3dpo_jax/configs/")) == configs
    assert "c3dpo_jax-0.1.0.dist-info/licenses/LICENSE" in names
    for script in ("c3dpo-train = c3dpo_jax.main:cli_main",
                   "c3dpo-predict = c3dpo_jax.predict:cli_main",
                   "c3dpo-import = c3dpo_jax.data.importers:cli_main"):
        assert script in entry_points


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory):
    """``(env, venv)``: a fresh virtual environment with the wheel pip-installed, and the
    environment variables that run its commands from elsewhere."""
    venv = tmp_path_factory.mktemp("install") / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"),
                    "install", "--quiet", "--no-deps", "--no-index", wheel],
                   check=True, capture_output=True, timeout=300)
    out = subprocess.run([str(venv / "bin" / "python"), "-c",
                          "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         check=True, capture_output=True, text=True)
    ours = [p for p in (sysconfig.get_paths()["purelib"], *site.getsitepackages())
            if os.path.isdir(p)]
    with open(os.path.join(out.stdout.strip(), "dependencies.pth"), "w") as f:
        f.write("\n".join(dict.fromkeys(ours)) + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"  # the kernel's "python"
    return env, venv


def _run(args, cwd, env, timeout=600):
    out = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True,
                         timeout=timeout)
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-4000:])
    return out


def test_the_installed_package_trains_predicts_and_runs_the_notebook_from_elsewhere(
        installed, tmp_path, smoke_subprocess_env):
    env, venv = installed
    env = dict(env, XLA_FLAGS=smoke_subprocess_env()["XLA_FLAGS"])  # smoke-sized models
    where = _run([str(venv / "bin" / "python"), "-c",
                  "import c3dpo_jax, os; print(os.path.dirname(c3dpo_jax.__file__))"],
                 tmp_path, env).stdout.strip()
    assert where.startswith(str(venv)), where  # the wheel, not the checkout

    train = _run([str(venv / "bin" / "c3dpo-train"), "--config=configs/synthetic.py:smoke",
                  "--workdir=run"], tmp_path, env)
    assert f"{venv}" in train.stdout.splitlines()[0]  # the bundled config
    for script, start in (("c3dpo-train", "Command line: trains C3DPO and scores it"),
                          ("c3dpo-predict", "Command line: 2D keypoints in a file")):
        usage = subprocess.run([str(venv / "bin" / script), "--help"], cwd=tmp_path, env=env,
                               capture_output=True, text=True, timeout=300)
        assert (usage.stdout + usage.stderr).startswith(start), usage  # the module's account
    with open(tmp_path / "run" / "eval_results.json") as f:
        assert f.read().count('"final"') == 1

    from c3dpo_jax.cli import get_config
    from c3dpo_jax.data import json_dataset, synthetic

    k = get_config("configs/synthetic.py:smoke").model.n_keypoints
    views = synthetic.make_split(5, n_keypoints=k, n_modes=2, deformation=0.3, occlusion=0.0,
                                 noise=0.0, perspective=False, shape_seed=0, seed=9)
    json_dataset.save(views, str(tmp_path / "views.json"))
    _run([str(venv / "bin" / "c3dpo-predict"), "--workdir=run", "--input=views.json",
          "--output=out/shapes.json"], tmp_path, env)
    with open(tmp_path / "out" / "shapes.json") as f:
        shapes = json.load(f)
    assert len(shapes) == 5

    # The quickstart notebook, executed by a kernel of the fresh environment, with a last
    # cell saying which package it imported.
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(
        "import os\nimport c3dpo_jax\nprint('package:', os.path.dirname(c3dpo_jax.__file__))"))
    nbformat.write(nb, str(tmp_path / "quickstart.ipynb"))
    script = ("import nbformat, sys\nfrom nbclient import NotebookClient\n"
              "nb = nbformat.read('quickstart.ipynb', as_version=4)\n"
              "NotebookClient(nb, kernel_name='python3', timeout=300, "
              "resources={'metadata': {'path': '.'}}).execute()\n"
              "nbformat.write(nb, 'executed.ipynb')\n")
    _run([str(venv / "bin" / "python"), "-c", script], tmp_path, env)
    nb = nbformat.read(str(tmp_path / "executed.ipynb"), as_version=4)
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 4  # training curves, two test poses, one new pose
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "MPJPE on the new poses" in text and "C3DPO" in text
    assert f"package: {venv}" in text
    assert not [o for o in outputs if o.get("name") == "stderr"], "no warnings, no log lines"
