"""Pictures: files are written, are not blank, and plotting never breaks training."""

import json
import os

import jax
import numpy as np
import pytest
from absl import logging

from c3dpo_jax import model, visualise
from c3dpo_jax.data import synthetic
from c3dpo_jax.reconstruct import C3DPOParams, save_workdir

CFG = model.ModelConfig(n_keypoints=17, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1)


def _assert_picture(path, min_bytes=5000):
    import matplotlib.image

    assert os.path.getsize(path) > min_bytes, path
    img = matplotlib.image.imread(path)[..., :3]
    # Not blank: many pixels differ from the background, in more than one colour.
    assert (np.abs(img - img[0, 0]).sum(-1) > 0.1).mean() > 0.01
    assert len(np.unique(img.reshape(-1, 3).round(2), axis=0)) > 10


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    workdir = str(tmp_path_factory.mktemp("run"))
    save_workdir(C3DPOParams(model.init_variables(jax.random.key(0), CFG), CFG), workdir)
    with open(os.path.join(workdir, "metrics.jsonl"), "w") as f:
        for step in (5, 10, 15):
            f.write(json.dumps({"step": step, "loss": 1.0 / step, "loss/reprojection": 0.8 / step,
                                "loss/canonicalisation": 0.2 / step}) + "\n")
    data = synthetic.make_split(4, n_keypoints=17, n_modes=2, deformation=0.3, occlusion=0.2,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    return workdir, data


def test_skeletons_are_index_pairs_within_their_keypoint_counts():
    counts = {"h36m": 17, "cub_birds": 15, "pascal3d/car": 12, "pascal3d/aeroplane": 8,
              "pascal3d/motorbike": 10, "pascal3d/sofa": 10, "pascal3d/chair": 10}
    for name, k in counts.items():
        assert visualise.skeleton(name, k) == visualise.SKELETONS[name]
    assert visualise.skeleton("h36m", 10) != visualise.SKELETONS["h36m"]
    assert visualise.skeleton("unknown", 17) == []


def test_write_run_figures_writes_curves_reconstructions_and_a_gif(run, tmp_path):
    workdir, data = run
    paths = visualise.write_run_figures(workdir, data, n_samples=2, skeleton_name="h36m",
                                        out_dir=str(tmp_path))
    names = sorted(os.path.basename(p) for p in paths)
    assert names == ["reconstruction_0.png", "reconstruction_1.png", "rotation_0.gif",
                     "training_curves.png"]
    for p in paths:
        if p.endswith(".png"):
            _assert_picture(p)
    from PIL import Image

    with Image.open(os.path.join(str(tmp_path), "rotation_0.gif")) as gif:
        assert gif.n_frames == 24


def test_reconstruction_plot_with_ground_truth_and_input_panel(tmp_path):
    shape = np.random.default_rng(0).normal(size=(17, 3))
    fig = visualise.plot_reconstruction_3d(
        shape, gt=shape * np.array([1.0, 1.0, -1.0]), edges=visualise.SKELETONS["h36m"],
        kp=shape[:, :2], vis=np.ones(17), views=((10, 0), (10, 90)))
    assert len(fig.axes) == 3
    path = visualise.save_figure(fig, str(tmp_path / "r.png"))
    _assert_picture(path)


def test_a_plotting_failure_only_logs_a_warning(tmp_path, monkeypatch):
    from c3dpo_jax import main

    messages = []
    monkeypatch.setattr(logging, "warning", lambda msg, *args: messages.append(msg % args))
    main._write_figures(None, str(tmp_path))  # no config: load_splits fails inside
    assert messages and "could not write figures" in messages[0]
