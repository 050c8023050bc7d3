"""Pictures: what they show (axes, skeleton, hidden points, error, up direction), the files a
run gets, and that plotting never breaks training."""

import json
import os
import shutil

import jax
import numpy as np
import pytest
from absl import logging

from c3dpo_jax import curves, model, skeletons, visualise
from c3dpo_jax.data import synthetic
from c3dpo_jax.reconstruct import C3DPOParams, load, reconstruct_data, save_workdir

CFG = model.ModelConfig(n_keypoints=17, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1)
BASELINES = {"fitted mean shape": {"mpjpe": 0.30}, "zero depth": {"mpjpe": 0.40}}


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
    save_workdir(C3DPOParams(model.init_variables(jax.random.key(0), CFG), CFG), workdir,
                 {"data": {"source": "humans"}})
    with open(os.path.join(workdir, "metrics.jsonl"), "w") as f:
        for step in (5, 10, 15):
            f.write(json.dumps({"step": step, "loss": 1.0 / step, "loss/reprojection": 0.8 / step,
                                "loss/canonicalisation": 0.2 / step}) + "\n")
    history = [{"step": 10, "mpjpe": 0.5}, {"step": 15, "mpjpe": 0.25}]
    with open(os.path.join(workdir, "eval_results.json"), "w") as f:
        json.dump({"history": history, "final": history[-1], "baselines": BASELINES}, f)
    data = synthetic.make_split(4, n_keypoints=17, n_modes=2, deformation=0.3, occlusion=0.2,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    return workdir, data


def test_skeletons_by_name_by_text_or_by_pairs_and_unknown_names_are_errors():
    counts = {"h36m": 17, "coco": 17, "cub_birds": 15, "pascal3d/car": 12, "pascal3d/aeroplane": 8,
              "pascal3d/motorbike": 10, "pascal3d/sofa": 10, "pascal3d/chair": 10}
    for name, k in counts.items():
        assert skeletons.skeleton(name, k) == skeletons.SKELETONS[name]
    # COCO's lines: every body joint reached, each limb's on one side of the body.
    from c3dpo_jax.data.humans import COCO_JOINT_NAMES as coco
    pairs = [(coco[a], coco[b]) for a, b in skeletons.SKELETONS["coco"]]
    assert {n for p in pairs for n in p} == set(coco)
    assert all(a[:2] == b[:2] for a, b in pairs  # but the nose's and left-right lines
               if "nose" not in (a, b) and a[2:] != b[2:])
    assert sum(a[2:] == b[2:] for a, b in pairs) == 3  # eyes, shoulders, hips
    assert skeletons.skeleton("0-1, 1-2 2-3", 4) == [(0, 1), (1, 2), (2, 3)]
    assert skeletons.skeleton([[3, 0]], 4) == [(3, 0)]
    assert skeletons.skeleton(None, 4) == skeletons.skeleton("", 4) == []
    assert skeletons.from_parents([-1, 0, 1, 0]) == [(0, 1), (1, 2), (0, 3)]
    with pytest.raises(ValueError, match="unknown skeleton 'hand': one of h36m"):
        skeletons.skeleton("hand", 17)
    with pytest.raises(ValueError, match=r"skeleton 'h36m' joins keypoints .* data has 10"):
        skeletons.skeleton("h36m", 10)
    with pytest.raises(ValueError, match="not of the form I-J"):
        skeletons.skeleton("0-1,2", 4)
    with pytest.raises(ValueError, match="joins keypoints"):
        skeletons.skeleton([(0, 4)], 4)


def test_ground_truth_takes_the_depth_sign_that_fits_and_gives_the_sample_mpjpe():
    shape = np.random.default_rng(0).normal(size=(6, 3))
    pred, gt, err = visualise.align_ground_truth(shape, shape * np.array([1.0, 1.0, -1.0]))
    np.testing.assert_allclose(gt, pred, atol=1e-12)
    assert err == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(pred.mean(0), 0.0, atol=1e-12)
    # A depth offset is removed (default protocol); a shift in x is an error of 0.5 per point.
    _, _, err = visualise.align_ground_truth(shape, shape + np.array([0.5, 0.0, 3.0]))
    assert err == pytest.approx(0.5)


def _scatters(ax):
    from mpl_toolkits.mplot3d.art3d import Path3DCollection

    return [c for c in ax.collections if isinstance(c, Path3DCollection)]


@pytest.mark.parametrize("y_up", [False, True])
def test_reconstruction_figure_shows_error_axes_skeleton_hidden_points_and_up(y_up):
    shape = np.random.default_rng(0).normal(size=(17, 3))
    vis = np.ones(17)
    vis[[2, 5]] = 0
    fig = visualise.plot_reconstruction_3d(
        shape, gt=shape + 0.1, edges=skeletons.SKELETONS["h36m"], kp=shape[:, :2] * vis[:, None],
        vis=vis, y_up=y_up, unit="m", kp_reprojected=shape[:, :2])
    ax2d, *axes3d = fig.axes
    assert len(axes3d) == 3
    assert "MPJPE 0.1" in fig._suptitle.get_text() and fig._suptitle.get_text().endswith(" m")
    # Up is up: y-down data get their y axis (and, a half turn not a mirror, depth) reversed.
    assert (ax2d.get_ylim()[0] > ax2d.get_ylim()[1]) == (not y_up)
    for ax in axes3d:
        assert (ax.get_ylim3d()[0] > ax.get_ylim3d()[1]) == (not y_up)
        assert (ax.get_zlim3d()[0] > ax.get_zlim3d()[1]) == (not y_up)
        # 16 bones, twice (truth, prediction); prediction drawn after and above the truth.
        assert len(ax.lines) == 32
        assert min(ln.get_zorder() for ln in ax.lines[16:]) > max(
            ln.get_zorder() for ln in ax.lines[:16])
        # Hidden points are hollow: white faces, blue edges.
        hidden = [c for c in _scatters(ax) if len(c.get_offsets()) == 2]
        assert len(hidden) == 1 and np.allclose(hidden[0].get_facecolor()[0], 1.0)
    front, side, top = axes3d
    assert (front.get_xlabel(), front.get_ylabel()) == ("x [m]", "y [m]") == (
        ax2d.get_xlabel(), ax2d.get_ylabel())
    assert side.get_zlabel() == "z (depth) [m]"
    # Views along an axis hide that axis's ticks (the top view's would pile up).
    assert front.get_zlabel() == "" and side.get_xlabel() == "" and top.get_ylabel() == ""
    assert not any(t.get_text() for t in top.get_yticklabels())
    # Hidden input points are drawn hollow at their reprojection, with dashed lines.
    assert any(ln.get_linestyle() == "--" for ln in ax2d.lines)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == [
        "C3DPO", "C3DPO, hidden in input", "ground truth"]
    visualise._plt().close(fig)


@pytest.mark.parametrize("y_up", [False, True])
def test_the_y_labels_of_the_3d_panels_read_upright(y_up):
    """y is drawn vertical, where matplotlib's label angle wraps: it drew "y [px]" upside
    down in the camera view (either up direction) and the side view (y up)."""
    shape = np.random.default_rng(0).normal(size=(10, 3)) * 100 + 300
    fig = visualise.plot_reconstruction_3d(shape, gt=shape + 3, kp=shape[:, :2], y_up=y_up,
                                           unit="px")
    fig.canvas.draw()  # the 3D axes place and turn their labels as they are drawn
    front, side, _ = fig.axes[1:]
    for ax in (front, side):
        assert ax.get_ylabel() == "y [px]" and ax.yaxis.label.get_rotation() == 90
    visualise._plt().close(fig)


def test_training_curves_show_losses_and_test_error_with_baselines(run, tmp_path):
    workdir, _ = run
    fig = curves.plot_training_curves(workdir)
    losses, test = fig.axes
    assert [ln.get_label() for ln in losses.lines] == [
        "loss", "loss/reprojection", "loss/canonicalisation"]
    c3dpo, *baselines = test.lines
    assert c3dpo.get_xdata().tolist() == [10, 15] and c3dpo.get_ydata().tolist() == [0.5, 0.25]
    assert [ln.get_ydata()[0] for ln in baselines] == [0.30, 0.40]
    assert [t.get_text() for t in test.get_legend().get_texts()] == [
        "C3DPO (0.25)", "fitted mean shape (0.3)", "zero depth (0.4)"]
    visualise._plt().close(fig)
    # Without evaluations: the losses alone (a metrics.jsonl path works too).
    shutil.copy(os.path.join(workdir, "metrics.jsonl"), tmp_path)
    fig = curves.plot_training_curves(str(tmp_path / "metrics.jsonl"))
    assert len(fig.axes) == 1
    visualise._plt().close(fig)
    # 2D-only data (protocol "none"): the test 2D reprojection error instead.
    (tmp_path / "eval_results.json").write_text(json.dumps({
        "history": [{"step": 10, "reprojection": 0.2}], "final": {"step": 15, "reprojection": 0.1},
        "baselines": {}}))
    fig = curves.plot_training_curves(str(tmp_path / "metrics.jsonl"))
    _, test = fig.axes
    assert test.get_ylabel() == "test 2D reprojection error"
    assert test.lines[0].get_ydata().tolist() == [0.2, 0.1]
    visualise._plt().close(fig)
    fig = curves.plot_training_curves(str(tmp_path / "metrics.jsonl"), unit="px")  # the data's
    assert fig.axes[1].get_ylabel() == "test 2D reprojection error [px]"
    visualise._plt().close(fig)


def test_run_style_from_the_data_file_or_the_built_in_dataset(tmp_path):
    path = tmp_path / "mine_test.json"
    path.write_text(json.dumps({"dataset": "mine", "y_up": True, "skeleton": [[0, 1]],
                                "data": []}))
    config = {"data": {"source": "json", "test_path": str(path)}}
    assert visualise.run_style(config) == {"y_up": True, "skeleton": [[0, 1]], "unit": ""}
    assert visualise.run_style({"data": {"source": "humans"}}) == {
        "skeleton": "h36m", "y_up": True, "unit": "m"}
    assert visualise.run_style({"data": {"source": "release", "name": "h36m"}}) == {
        "skeleton": "h36m", "y_up": False, "unit": ""}
    assert visualise.run_style({}) == {"skeleton": None, "y_up": False, "unit": ""}


def test_write_run_figures_writes_curves_reconstructions_and_a_gif(run, tmp_path):
    from PIL import Image

    workdir, data = run
    rec = reconstruct_data(load(workdir), data, 2)
    assert rec.shape_3d.shape == (2, 17, 3)
    paths = visualise.write_run_figures(workdir, data, rec, n_samples=3, out_dir=str(tmp_path))
    names = sorted(os.path.basename(p) for p in paths)
    assert names == ["reconstruction_0.png", "reconstruction_1.png", "rotation_0.gif",
                     "training_curves.png"]
    for p in paths:
        if p.endswith(".png"):
            _assert_picture(p)
    with Image.open(os.path.join(str(tmp_path), "rotation_0.gif")) as gif:
        assert gif.n_frames == 24
        gif.seek(6)
        img = np.asarray(gif.convert("RGB"), np.float64) / 255
    # The shape fills the frame, and both the prediction (blue) and the truth (grey) show.
    rows = np.flatnonzero((img.sum(-1) < 2.9).any(1))
    assert rows[-1] - rows[0] > 0.6 * img.shape[0]
    blue = (img[..., 2] - img[..., 0] > 0.3).sum()
    grey = ((np.ptp(img, -1) < 0.05) & (img.mean(-1) > 0.5) & (img.mean(-1) < 0.9)).sum()
    assert blue > 200 and grey > 200
    with pytest.raises(ValueError, match="unknown skeleton"):
        visualise.write_run_figures(workdir, data, rec, skeleton="hand", out_dir=str(tmp_path))
    with pytest.raises(ValueError, match="pass both"):
        visualise.write_run_figures(workdir, data, out_dir=str(tmp_path))


def test_a_plotting_failure_only_logs_a_warning(tmp_path, monkeypatch):
    from c3dpo_jax import main

    messages = []
    monkeypatch.setattr(logging, "warning", lambda msg, *args: messages.append(msg % args))
    main._write_figures(None, str(tmp_path))  # no config: load_splits fails inside
    assert messages and "could not write figures" in messages[0]


def test_the_plots_name_a_wrong_shape_or_skeleton_in_one_line(tmp_path):
    shape = np.zeros((2, 4, 3))  # a batch where one shape is drawn
    with pytest.raises(ValueError, match=r"one shape \(N, 3\), got \(2, 4, 3\) \(index a batch"):
        visualise.plot_reconstruction_3d(shape)
    with pytest.raises(ValueError, match=r"ground truth has shape \(5, 3\), the shape \(4, 3\)"):
        visualise.plot_reconstruction_3d(shape[0], np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"joins keypoints \[\(0, 7\)\] but the data has 4"):
        visualise.save_rotation_gif(shape[0], str(tmp_path / "a.gif"), edges=[(0, 7)])
