"""Pictures of inputs and reconstructions (matplotlib, Agg backend).

Numpy in, figure or file out. matplotlib is imported lazily inside each function, so
importing this module (or the package) never loads it. Glossary: N keypoints, points on
the last axis: ``kp (N, 2)``, ``vis (N,)``, ``shape (N, 3)`` in the camera frame.

Up direction: the release's files are in image convention (x right, y **down**, camera
looking along +z), the built-in humans and categories and the importers' views of
motion capture have y **up** (``y_up=True``). The plots draw either with "up" up: for
y-down data the y and depth axes run the other way (a half turn about x, not a mirror).
Where a plot compares with ground truth, the truth is taken with the depth sign that
fits the prediction better (the learned depth sign is arbitrary) and the title gives
that sample's MPJPE (the ``default`` protocol: mean depth removed, in the data's units).
``plot_training_curves`` (from ``c3dpo_jax.curves``) draws a run's losses and test error;
``write_run_figures`` writes all of a run's pictures.
"""

import json
import os

import numpy as np
from absl import logging

from c3dpo_jax import evaluation, skeletons
from c3dpo_jax.curves import plot_training_curves
from c3dpo_jax.curves import pyplot as _plt
from c3dpo_jax.data import json_dataset

SKELETONS = skeletons.SKELETONS
skeleton = skeletons.skeleton

# Views of a reconstruction: (title, elevation, azimuth from the camera's direction), deg.
VIEWS = (("camera view", 10, 0), ("side", 10, 90), ("top", 90, 0))
# How to draw a dataset: skeleton, whether y points up, the unit of the coordinates.
STYLE_DEFAULTS = {"skeleton": None, "y_up": False, "unit": ""}
# ... for the datasets the package knows (config data.source, or data.name for the release's).
_DATASET_STYLES = {"humans": {"skeleton": "h36m", "y_up": True, "unit": "m"},
                   "categories": {"y_up": True},
                   "h36m": {"skeleton": "h36m"}, "h36m_hourglass": {"skeleton": "h36m"},
                   "cub_birds": {"skeleton": "cub_birds"},
                   "cub_birds_hrnet": {"skeleton": "cub_birds"}}
_PRED, _GT = "tab:blue", "0.55"


def align_ground_truth(shape, gt) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Prediction and truth as the plots draw them, and the sample's MPJPE.

    Both get their mean depth removed (the ``default`` protocol), the truth the depth sign
    that gives the lower MPJPE, and both the same shift that centres the prediction.
    Returns ``(shape, gt, mpjpe)``; ``gt`` None gives ``(centred shape, None, nan)``.
    """
    shape = np.asarray(shape, np.float64)
    if shape.ndim != 2 or shape.shape[1] != 3:
        raise ValueError(f"a picture draws one shape (N, 3), got {shape.shape} (index a batch: "
                         "rec.shape_3d[i])")
    if gt is None:
        return shape - shape.mean(0), None, float("nan")
    if np.shape(gt) != shape.shape:
        raise ValueError(f"the ground truth has shape {np.shape(gt)}, the shape {shape.shape}")
    ones = np.ones((1, len(shape)))
    pred = evaluation.center_depth(shape[None], ones)[0]
    gt = evaluation.center_depth(np.asarray(gt, np.float64)[None], ones)[0]
    err = evaluation.mpjpe(pred[None], gt[None], ones)
    if err["mpjpe_flip"][0] < err["mpjpe_orig"][0]:
        gt = gt * np.array([1.0, 1.0, -1.0])
    centre = pred.mean(0)
    return pred - centre, gt - centre, float(err["mpjpe"][0])


def plot_keypoints_2d(kp, vis=None, edges=(), ax=None, title: str = "", y_up: bool = False,
                      kp_hidden=None, unit: str = ""):
    """Input 2D keypoints with the skeleton; returns the axes.

    Visible points are filled. Hidden points have no input position: with ``kp_hidden``
    (N, 2), e.g. the model's reprojection, they are drawn hollow there, their lines dashed.
    """
    kp = np.asarray(kp, np.float64)
    vis = np.ones(len(kp)) if vis is None else np.asarray(vis) > 0
    hidden_at = None if kp_hidden is None else np.asarray(kp_hidden, np.float64)
    pos = kp if hidden_at is None else np.where(vis[:, None], kp, hidden_at)
    if ax is None:
        ax = _plt().figure(figsize=(4, 4)).add_subplot(111)
    for i, j in edges:
        if vis[i] and vis[j]:
            ax.plot(*pos[[i, j]].T, "-", color=_PRED, lw=2)
        elif hidden_at is not None:
            ax.plot(*pos[[i, j]].T, "--", color=_PRED, lw=1, alpha=0.7)
    ax.scatter(*pos[vis].T, color=_PRED, s=22, zorder=3, label="visible")
    if hidden_at is not None and (~vis).any():
        ax.scatter(*pos[~vis].T, facecolors="white", edgecolors=_PRED, s=22, zorder=3,
                   label="hidden (reprojected)")
        ax.legend(loc="best", fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    if not y_up:
        ax.invert_yaxis()  # image convention: y grows downwards
    suffix = f" [{unit}]" if unit else ""
    ax.set_xlabel("x" + suffix)
    ax.set_ylabel("y" + suffix)
    ax.set_title(title or "input 2D keypoints")
    return ax


def _draw_3d(ax, shape, edges, vis, color, *, gt: bool):
    """One shape: the truth as wide pale lines and crosses, the prediction as thin lines
    with filled (visible) and hollow (hidden in the input) dots drawn on top of it."""
    z = 1 if gt else 3
    for i, j in edges:
        ax.plot(*shape[[i, j]].T, "-", color=color, lw=4.5 if gt else 1.6,
                alpha=0.45 if gt else 1.0, solid_capstyle="round", zorder=z)
    if gt:
        ax.scatter(*shape.T, color=color, marker="x", s=22, zorder=z + 1, depthshade=False)
        return
    ax.scatter(*shape[vis].T, color=color, s=18, zorder=z + 1, depthshade=False)
    if (~vis).any():
        ax.scatter(*shape[~vis].T, facecolors="white", edgecolors=color, s=26, lw=1.2,
                   zorder=z + 2, depthshade=False)


def _frame_3d(ax, points, y_up: bool, *, ticks: bool = True, unit: str = ""):
    """Equal axes around ``points``; y-down data get their y and depth axes reversed."""
    centre = points.reshape(-1, 3).mean(0)
    r = np.abs(points.reshape(-1, 3) - centre).max() * 1.05 + 1e-9
    flip = (1, 1, 1) if y_up else (1, -1, -1)
    for axis, c, s in zip("xyz", centre, flip, strict=True):
        getattr(ax, f"set_{axis}lim")(*(c - s * r, c + s * r))
    ax.set_box_aspect((1, 1, 1), zoom=1.1)
    suffix = f" [{unit}]" if unit else ""
    if ticks:
        ax.set_xlabel("x" + suffix, labelpad=-6)
        ax.set_ylabel("y" + suffix, labelpad=-6)
        # y is drawn vertical (view_init's vertical_axis="y"), where matplotlib's label angle
        # wraps between +90 and -90 degrees and could turn the label upside down.
        ax.yaxis.set_rotate_label(False)
        ax.yaxis.label.set_rotation(90)
        ax.set_zlabel("z (depth)" + suffix, labelpad=-6)
        ax.tick_params(labelsize=7, pad=-2)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(_plt().MaxNLocator(4))
    else:
        ax.set_axis_off()


def _legend_handles(has_gt: bool, has_hidden: bool):
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=_PRED, marker="o", ms=4, lw=1.6, label="C3DPO")]
    if has_hidden:
        handles.append(Line2D([], [], color=_PRED, marker="o", mfc="white", ms=5, lw=0,
                              label="C3DPO, hidden in input"))
    if has_gt:
        handles.append(Line2D([], [], color=_GT, marker="x", ms=5, lw=4, alpha=0.6,
                              label="ground truth"))
    return handles


def plot_reconstruction_3d(shape, gt=None, edges=(), views=VIEWS, kp=None, vis=None,
                           title: str = "", y_up: bool = False, unit: str = "",
                           kp_reprojected=None):
    """The 3D shape (N, 3) seen from ``views`` ((title, elev, azim from the camera)), with
    the ground truth ``gt`` (N, 3) under it when given and its MPJPE in the title.

    ``kp``/``vis`` add an input panel (hidden points at ``kp_reprojected`` when given);
    ``vis`` also marks the prediction's hidden points hollow. ``y_up``: the module
    docstring. Returns the figure.
    """
    plt = _plt()
    shape, gt, err = align_ground_truth(shape, gt)
    edges = skeletons.skeleton(edges, len(shape))  # names allowed, indices checked
    vis = np.ones(len(shape), bool) if vis is None else np.asarray(vis) > 0
    panels = len(views) + (kp is not None)
    fig = plt.figure(figsize=(3.8 * panels, 4.2))
    if kp is not None:
        plot_keypoints_2d(kp, vis, edges, ax=fig.add_subplot(1, panels, 1), y_up=y_up,
                          kp_hidden=kp_reprojected, unit=unit)
    points = shape if gt is None else np.concatenate([shape, gt])
    for k, (name, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, panels, k + 1 + (kp is not None), projection="3d")
        ax.computed_zorder = False  # draw the prediction over the truth
        if gt is not None:
            _draw_3d(ax, gt, edges, vis, _GT, gt=True)
        _draw_3d(ax, shape, edges, vis, _PRED, gt=False)
        _frame_3d(ax, points, y_up, unit=unit)
        ax.view_init(elev=elev, azim=azim, vertical_axis="y")
        _hide_axis_along_view(ax, elev, azim)
        ax.set_title(name, fontsize=10, pad=0)
    fig.legend(handles=_legend_handles(gt is not None, bool((~vis).any())), loc="lower center",
               ncol=3, fontsize=8, frameon=False)
    head = title
    if gt is not None:
        head += f"{': ' if title else ''}MPJPE {err:.3g}{' ' + unit if unit else ''}"
    if head:
        fig.suptitle(head)
    fig.subplots_adjust(left=0.04, right=0.98, bottom=0.12, top=0.86, wspace=0.12)
    return fig


def _hide_axis_along_view(ax, elev, azim) -> None:
    """An axis that points at the viewer shows as a dot: its tick labels would pile up."""
    e, a = np.deg2rad(elev), np.deg2rad(azim)
    towards_viewer = np.abs([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])
    if towards_viewer.max() > 0.9:
        axis = "xyz"[int(np.argmax(towards_viewer))]
        getattr(ax, f"set_{axis}ticklabels")([])
        getattr(ax, f"set_{axis}label")("")


def save_rotation_gif(shape, path: str, edges=(), gt=None, vis=None, y_up: bool = False,
                      n_frames: int = 24, fps: int = 8) -> str:
    """A GIF of ``shape`` (N, 3) (over ``gt`` when given) turning once about the vertical."""
    plt = _plt()
    from matplotlib.animation import FuncAnimation, PillowWriter

    shape, gt, err = align_ground_truth(shape, gt)
    edges = skeletons.skeleton(edges, len(shape))  # names allowed, indices checked
    vis = np.ones(len(shape), bool) if vis is None else np.asarray(vis) > 0
    points = shape if gt is None else np.concatenate([shape, gt])
    fig = plt.figure(figsize=(4, 4.4))
    ax = fig.add_axes((0, 0, 1, 0.92), projection="3d")
    ax.computed_zorder = False
    head = "C3DPO (blue)" + ("" if gt is None else f" and truth (grey): MPJPE {err:.3g}")
    fig.text(0.5, 0.96, head, ha="center", va="center", fontsize=10)

    def frame(t):
        ax.cla()
        if gt is not None:
            _draw_3d(ax, gt, edges, vis, _GT, gt=True)
        _draw_3d(ax, shape, edges, vis, _PRED, gt=False)
        _frame_3d(ax, points, y_up, ticks=False)
        ax.set_box_aspect((1, 1, 1), zoom=1.3)  # no ticks to make room for
        ax.view_init(elev=10, azim=360 * t / n_frames, vertical_axis="y")
        return []

    FuncAnimation(fig, frame, frames=n_frames).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def save_figure(fig, path: str) -> str:
    fig.savefig(path, dpi=90)
    _plt().close(fig)
    return path


def data_file_style(path: str) -> dict:
    """The ``STYLE_DEFAULTS`` keys a JSON data file's wrapper holds (``{}`` when none)."""
    obj = json_dataset.read_json(path)
    if not isinstance(obj, dict):
        return {}
    return {k: obj[k] for k in STYLE_DEFAULTS if obj.get(k) is not None}


def run_style(config: dict) -> dict:
    """``skeleton``, ``y_up`` and ``unit`` for a run's pictures, from its ``config.json``
    content: what its test (else train) file says (found by the absolute path the run
    recorded, ``data_files``, else by the path as given), else the built-in dataset's
    defaults. A data file that cannot be found is named in a warning."""
    data, files = config.get("data", {}), config.get("data_files", {})
    missing = []
    for key in ("test_path", "train_path"):
        found = [p for p in (files.get(key), data.get(key)) if p and os.path.exists(p)]
        if found:
            style = data_file_style(found[0])
            if style:
                return {**STYLE_DEFAULTS, **style}
        elif data.get(key):
            missing.append(files.get(key) or data[key])
    if missing:
        logging.warning("the run's data file %s is not found: its pictures take the default "
                        "style (skeleton, y axis, unit)", missing[0])
    name = data.get("name") if data.get("source") == "release" else data.get("source")
    return {**STYLE_DEFAULTS, **_DATASET_STYLES.get(name or "", {})}


def write_reconstruction_figures(rec, kp, vis, out_dir: str, *, gt=None, n: int = 3,
                                 edges=(), y_up: bool = False, unit: str = "",
                                 titles=None, gif: bool = False) -> list[str]:
    """``reconstruction_I.png`` for the first ``n`` samples of a reconstruction ``rec``
    (``reconstruct.Reconstruction``) of the 2D inputs ``kp``, ``vis`` (and ``gt``, their
    3D ground truth, or None), and with ``gif`` a rotating GIF of the first; returns the
    paths written. ``titles`` (one per sample) default to "sample I"."""
    os.makedirs(out_dir, exist_ok=True)
    n = min(n, len(rec.shape_3d), len(kp))
    paths = []
    for i in range(n):
        fig = plot_reconstruction_3d(rec.shape_3d[i], None if gt is None else gt[i], edges,
                                     kp=kp[i], vis=vis[i],
                                     title=titles[i] if titles is not None else f"sample {i}",
                                     y_up=y_up, unit=unit, kp_reprojected=rec.kp_reprojected[i])
        paths.append(save_figure(fig, os.path.join(out_dir, f"reconstruction_{i}.png")))
    if gif and n:
        paths.append(save_rotation_gif(rec.shape_3d[0], os.path.join(out_dir, "rotation_0.gif"),
                                       edges, gt=None if gt is None else gt[0], vis=vis[0],
                                       y_up=y_up))
    return paths


def write_run_figures(workdir: str, data=None, reconstruction=None, n_samples: int = 3,
                      skeleton=None, y_up: bool | None = None,
                      out_dir: str | None = None) -> list[str]:
    """A trained run's pictures: its training curves and, given ``data`` and its
    ``reconstruction``, the reconstructions of the first ``n_samples`` and a rotating GIF
    of the first. This module draws; it does not load models::

        params = reconstruct.load(workdir)
        visualise.write_run_figures(workdir, test, reconstruct.reconstruct_data(params, test, 3))

    Args:
      workdir: a trained workdir (config.json, metrics.jsonl, eval_results.json).
      data: a ``KeypointData`` (e.g. the test split); ground truth is drawn if it has any.
      reconstruction: a ``reconstruct.Reconstruction`` of the first samples of ``data``.
      n_samples: how many samples to draw (at most as many as were reconstructed).
      skeleton: a name in ``SKELETONS``, ``"0-1,1-2"`` or index pairs (default:
        ``run_style`` of the workdir's config).
      y_up: whether the data's y axis points up (default: ``run_style``).
      out_dir: where to write (default ``workdir/figures``).

    Returns:
      The paths written.
    """
    if (data is None) != (reconstruction is None):
        raise ValueError("write_run_figures draws data with its reconstruction: pass both "
                         "(reconstruction=reconstruct.reconstruct_data(params, data, n)) or "
                         "neither")
    if data is not None and np.shape(reconstruction.shape_3d)[-2:] != (data.n_keypoints, 3):
        raise ValueError(f"the reconstruction's shapes are {np.shape(reconstruction.shape_3d)}, "
                         f"the data's {data.n_keypoints} keypoints: not the same views")
    out_dir = out_dir or os.path.join(workdir, "figures")
    os.makedirs(out_dir, exist_ok=True)
    config_path = os.path.join(workdir, "config.json")  # the run's config; no model is loaded
    config = {}
    if os.path.exists(config_path):
        with open(config_path) as f:
            config = json.load(f)
    style = run_style(config)
    paths = []
    if os.path.exists(os.path.join(workdir, "metrics.jsonl")):
        fig = plot_training_curves(workdir, unit=style["unit"])
        paths.append(save_figure(fig, os.path.join(out_dir, "training_curves.png")))
    if data is None:
        return paths
    spec = style.get("skeleton") if skeleton is None else skeleton
    edges = skeletons.skeleton(spec, data.n_keypoints)
    y_up = bool(style.get("y_up", False)) if y_up is None else y_up
    paths += write_reconstruction_figures(reconstruction, data.kp, data.vis, out_dir,
                                          gt=data.kp3d, n=n_samples, edges=edges, y_up=y_up,
                                          unit=style["unit"], gif=True)
    logging.info("wrote %d figures to %s", len(paths), out_dir)
    return paths
