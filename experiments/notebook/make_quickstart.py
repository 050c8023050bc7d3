"""Writes c3dpo_quickstart.ipynb, executed, with its outputs and pictures (run from the
repository root: python experiments/notebook/make_quickstart.py; --noexecute writes the
cells only).

The notebook trains a tiny C3DPO on the built-in synthetic data, evaluates it,
reconstructs new keypoints with ``c3dpo_jax.reconstruct`` and shows the pictures.
Executed end to end by tests/notebook_test.py (about a minute on 2 CPU cores).
"""

import os
import sys

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

CELLS = [
    new_markdown_cell(
        "# C3DPO quickstart\n"
        "Train a tiny model on the built-in synthetic data (no download), evaluate it, "
        "reconstruct new 2D keypoints in 3D and look at the result. It runs from any "
        "directory once the package is installed. The real run is "
        "`python -m c3dpo_jax.main --config=configs/synthetic.py --workdir=runs/synthetic` "
        "(a few minutes); here we use the `:smoke` settings."
    ),
    new_code_cell(
        "import tempfile\n"
        "\n"
        "import numpy as np\n"
        "from IPython.display import Image, display\n"
        "\n"
        "from c3dpo_jax import evaluation, load, reconstruct, reconstruct_data, train, visualise\n"
        "from c3dpo_jax.cli import get_config\n"
        "from c3dpo_jax.data import load_splits, synthetic"
    ),
    new_markdown_cell(
        "## Train\nSmoke settings (32-wide networks, 2 blocks) for 40 steps: seconds of "
        "training, and far from a trained model. Its error is above the fitted mean shape's "
        "(the rigid baseline in the table), and the pictures below show it. The real run "
        "above trains the full network for 5,000 steps and ends about 5x below that "
        "baseline (the README's Results). The numbers stored here are those of the machine "
        "that ran the notebook; another CPU's floating-point order changes them a little."),
    new_code_cell(
        "config = get_config('configs/synthetic.py:smoke')  # the bundled config\n"
        "config.train.num_steps = 40\n"
        "config.train.progress_bar = False\n"
        "workdir = tempfile.mkdtemp(prefix='c3dpo_quickstart_')\n"
        "results = train.train_and_evaluate(config, workdir)\n"
        "print(evaluation.format_table({'C3DPO': results['final'], **results['baselines']}))"
    ),
    new_markdown_cell(
        "## Reconstruct new keypoints\n"
        "`load` reads the workdir (config.json + latest checkpoint); `reconstruct` takes "
        "`(N, 2)` or `(B, N, 2)` keypoints and visibilities and returns numpy arrays."
    ),
    new_code_cell(
        "params = load(workdir)\n"
        "cfg = config.data.synthetic\n"
        "new = synthetic.make_split(8, n_keypoints=cfg.n_keypoints, n_modes=cfg.n_modes,\n"
        "                           deformation=cfg.deformation, occlusion=cfg.occlusion,\n"
        "                           noise=0.0, perspective=False, cameras=cfg.cameras,\n"
        "                           max_elevation=cfg.max_elevation, shape_seed=cfg.seed,\n"
        "                           seed=1234)  # new poses, seen as in training\n"
        "rec = reconstruct(params, new.kp, new.vis)\n"
        "print({k: v.shape for k, v in rec._asdict().items()})\n"
        "one = reconstruct(params, new.kp[0], new.vis[0])  # a single pose: no batch axis\n"
        "# The same view alone or in a batch: equal up to rounding, which the refinement's\n"
        "# accept test can carry to ~1e-3 of the shape's size (its steps are taken or not).\n"
        "assert np.allclose(one.shape_3d, rec.shape_3d[0], atol=1e-2)\n"
        "scores = evaluation.evaluate(rec.shape_3d, new, 'default')\n"
        "print('MPJPE on the new poses:', scores['mpjpe'])"
    ),
    new_markdown_cell(
        "## Pictures\n"
        "Training curves (the losses, and the test error against the baselines), then test "
        "poses in 3D over the ground truth (grey), with each sample's error in the title; "
        "points hidden in the input are hollow. `tensorboard --logdir` on the workdir shows "
        "the same curves."),
    new_code_cell(
        "test = load_splits(config.data)[1]\n"
        "paths = visualise.write_run_figures(workdir, test, reconstruct_data(params, test, 2))\n"
        "for p in paths:\n"
        "    if p.endswith('.png'):\n"
        "        display(Image(filename=p))"
    ),
    new_code_cell(
        "fig = visualise.plot_reconstruction_3d(rec.shape_3d[0], new.kp3d[0], kp=new.kp[0],\n"
        "                                       vis=new.vis[0], title='a new pose',\n"
        "                                       kp_reprojected=rec.kp_reprojected[0])\n"
        "fig.savefig(f'{workdir}/new_pose.png')\n"
        "display(Image(filename=f'{workdir}/new_pose.png'))"
    ),
    new_markdown_cell("The run's folder (checkpoints, metrics, pictures) was a temporary one; "
                      "keep it to explore further, or remove it:"),
    new_code_cell(
        "import shutil\n"
        "\n"
        "shutil.rmtree(workdir)"
    ),
]


def execute(nb, root: str):
    """Runs ``nb`` in place from ``root``; drops the run's timestamps (noise in a diff)."""
    from nbclient import NotebookClient

    NotebookClient(nb, kernel_name="python3", timeout=600,
                   resources={"metadata": {"path": root}}).execute()
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
    return nb


def main(run: bool = True):
    nb = new_notebook(cells=CELLS, metadata={
        "kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"},
        "language_info": {"name": "python"},
    })
    here = os.path.dirname(os.path.abspath(__file__))
    if run:
        execute(nb, os.path.dirname(os.path.dirname(here)))
    path = os.path.join(here, "c3dpo_quickstart.ipynb")
    nbformat.write(nb, path)
    return path


if __name__ == "__main__":
    print(main(run="--noexecute" not in sys.argv[1:]))
