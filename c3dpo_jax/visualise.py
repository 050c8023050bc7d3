"""Pictures of inputs, reconstructions and training curves (matplotlib, Agg backend).

Numpy in, figure or file out. matplotlib is imported lazily inside each function, so
importing this module (or the package) never loads it. Glossary: N keypoints,
points on the last axis: ``kp (N, 2)``, ``vis (N,)``, ``shape (N, 3)``.
"""

import json
import os

import numpy as np
from absl import logging

# Keypoint index pairs of the release's plots (REFERENCE.md "Skeletons for plots").
SKELETONS: dict[str, list[tuple[int, int]]] = {
    "h36m": [(10, 9), (9, 8), (8, 14), (14, 15), (15, 16), (8, 11), (11, 12), (12, 13), (8, 7),
             (7, 0), (1, 0), (1, 2), (2, 3), (0, 4), (4, 5), (5, 6)],
    "cub_birds": [(1, 5), (5, 4), (4, 9), (9, 0), (0, 13), (0, 12), (0, 8), (12, 13), (1, 14),
                  (14, 3), (3, 2), (2, 7), (1, 10), (1, 6), (2, 11), (2, 7), (8, 13)],
    "pascal3d/car": [(0, 8), (0, 4), (4, 10), (8, 10), (10, 9), (9, 11), (8, 11), (11, 6), (9, 2),
                     (2, 6), (4, 1), (5, 1), (0, 5), (5, 7), (1, 3), (7, 3), (3, 2), (7, 6)],
    "pascal3d/aeroplane": [(2, 5), (1, 4), (5, 3), (3, 7), (7, 0), (0, 5), (5, 7), (5, 6), (6, 0),
                           (6, 3), (2, 4), (2, 1)],
    "pascal3d/motorbike": [(6, 2), (2, 9), (2, 3), (3, 8), (5, 8), (3, 5), (2, 1), (1, 0), (0, 7),
                           (0, 4), (4, 7), (1, 4), (1, 7), (1, 5), (1, 8)],
    "pascal3d/sofa": [(1, 5), (5, 4), (4, 6), (6, 2), (2, 0), (1, 0), (0, 4), (1, 3), (7, 5),
                      (2, 3), (3, 7), (9, 7), (7, 6), (6, 8), (8, 9)],
    "pascal3d/chair": [(7, 3), (6, 2), (9, 5), (8, 4), (7, 9), (8, 6), (6, 7), (9, 8), (9, 1),
                       (8, 0), (1, 0)],
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def skeleton(name: str | None, n_keypoints: int) -> list[tuple[int, int]]:
    """Edges for ``name`` (empty when unknown or when indices exceed ``n_keypoints``)."""
    edges = SKELETONS.get(name or "", [])
    return [e for e in edges if max(e) < n_keypoints]


def plot_keypoints_2d(kp, vis=None, edges=(), ax=None, title: str = ""):
    """Input 2D keypoints (image convention: y down) with the skeleton; returns the axes."""
    kp = np.asarray(kp, np.float64)
    vis = np.ones(len(kp)) if vis is None else np.asarray(vis)
    if ax is None:
        ax = _plt().figure(figsize=(4, 4)).add_subplot(111)
    for i, j in edges:
        if vis[i] > 0 and vis[j] > 0:
            ax.plot(kp[[i, j], 0], kp[[i, j], 1], "-", color="tab:blue", lw=2)
    ax.scatter(*kp[vis > 0].T, c="tab:red", s=20, zorder=3, label="visible")
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_title(title or "input 2D keypoints")
    return ax


def _draw_3d(ax, shape, edges, color, label):
    ax.scatter(*shape.T, color=color, s=12, label=label)
    for i, j in edges:
        ax.plot(*shape[[i, j]].T, "-", color=color, lw=1.5)


def _set_equal_3d(ax, points):
    centre = points.reshape(-1, 3).mean(0)
    r = np.abs(points.reshape(-1, 3) - centre).max() + 1e-9
    for axis, c in zip("xyz", centre, strict=True):
        getattr(ax, f"set_{axis}lim")(c - r, c + r)


def plot_reconstruction_3d(shape, gt=None, edges=(), views=((15, -75), (15, 15), (80, -90)),
                           kp=None, vis=None, title: str = ""):
    """The 3D shape (N, 3) seen from ``views`` (elev, azim), next to ``gt`` if given.

    ``gt`` is flipped in depth when that matches ``shape`` better (the learned depth
    sign is arbitrary) and centred on ``shape``'s mean. ``kp``/``vis`` add an input panel.
    """
    plt = _plt()
    shape = np.asarray(shape, np.float64)
    shape = shape - shape.mean(0)
    if gt is not None:
        gt = np.asarray(gt, np.float64)
        gt = gt - gt.mean(0)
        flipped = gt * np.array([1.0, 1.0, -1.0])
        if np.abs(flipped - shape).sum() < np.abs(gt - shape).sum():
            gt = flipped
    panels = len(views) + (kp is not None)
    fig = plt.figure(figsize=(4 * panels, 4))
    if kp is not None:
        plot_keypoints_2d(kp, vis, edges, ax=fig.add_subplot(1, panels, 1))
    for k, (elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, panels, k + 1 + (kp is not None), projection="3d")
        # Camera frame: x right, y down, z forward; plot with y up for readability.
        flip = np.array([1.0, -1.0, 1.0])
        _draw_3d(ax, shape * flip, edges, "tab:blue", "C3DPO")
        if gt is not None:
            _draw_3d(ax, gt * flip, edges, "tab:gray", "ground truth")
        _set_equal_3d(ax, np.concatenate([shape, shape if gt is None else gt]) * flip)
        ax.view_init(elev=elev, azim=azim, vertical_axis="y")
        ax.set_title(f"elev {elev}, azim {azim}")
        if k == 0:
            ax.legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def save_rotation_gif(shape, path: str, edges=(), n_frames: int = 24, fps: int = 8) -> str:
    """A GIF of ``shape`` (N, 3) turning once about the vertical axis."""
    plt = _plt()
    from matplotlib.animation import FuncAnimation, PillowWriter

    shape = (np.asarray(shape, np.float64) - np.mean(shape, 0)) * np.array([1.0, -1.0, 1.0])
    fig = plt.figure(figsize=(3.5, 3.5))
    ax = fig.add_subplot(111, projection="3d")

    def frame(t):
        ax.cla()
        _draw_3d(ax, shape, edges, "tab:blue", None)
        _set_equal_3d(ax, shape)
        ax.view_init(elev=15, azim=-90 + 360 * t / n_frames, vertical_axis="y")
        return []

    FuncAnimation(fig, frame, frames=n_frames).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def plot_training_curves(metrics_path: str):
    """Losses (log scale) against step from a workdir's ``metrics.jsonl``."""
    plt = _plt()
    with open(metrics_path) as f:
        records = [json.loads(line) for line in f if line.strip()]
    if not records:
        raise ValueError(f"{metrics_path} has no records")
    steps = [r["step"] for r in records]
    fig, ax = plt.subplots(figsize=(6, 4))
    for name in ("loss", "loss/reprojection", "loss/canonicalisation"):
        values = [r.get(name, np.nan) for r in records]
        if np.any(np.asarray(values) > 0):
            ax.plot(steps, values, marker=".", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def save_figure(fig, path: str) -> str:
    fig.savefig(path, dpi=90)
    _plt().close(fig)
    return path


def write_run_figures(workdir: str, data=None, n_samples: int = 3, skeleton_name: str | None = None,
                      out_dir: str | None = None) -> list[str]:
    """Training curves and reconstructions of the first ``n_samples`` of ``data``.

    Args:
      workdir: a trained workdir (config.json, checkpoints, metrics.jsonl).
      data: a ``KeypointData`` (e.g. the test split); ground truth is drawn if it has any.
      n_samples: how many samples to draw (plus one rotating GIF of the first).
      skeleton_name: a key of ``SKELETONS`` (default: the data's name when it is one).
      out_dir: where to write (default ``workdir/figures``).

    Returns:
      The paths written.
    """
    from c3dpo_jax.reconstruct import load, reconstruct

    out_dir = out_dir or os.path.join(workdir, "figures")
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    metrics = os.path.join(workdir, "metrics.jsonl")
    if os.path.exists(metrics):
        curves = plot_training_curves(metrics)
        paths.append(save_figure(curves, os.path.join(out_dir, "training_curves.png")))
    if data is None:
        return paths
    params = load(workdir)
    n = min(n_samples, len(data))
    inputs = data.model_inputs()
    perspective = params.config.projection_type == "perspective"
    rec = reconstruct(params, data.kp[:n], data.vis[:n], class_mask=inputs["class_mask"][:n],
                      K=data.intrinsics[:n] if perspective else None)
    edges = skeleton(skeleton_name or data.name, data.n_keypoints)
    for i in range(n):
        gt = None if data.kp3d is None else data.kp3d[i]
        fig = plot_reconstruction_3d(rec.shape_3d[i], gt, edges, kp=data.kp[i], vis=data.vis[i],
                                     title=f"sample {i}")
        paths.append(save_figure(fig, os.path.join(out_dir, f"reconstruction_{i}.png")))
    paths.append(save_rotation_gif(rec.shape_3d[0], os.path.join(out_dir, "rotation_0.gif"), edges))
    logging.info("wrote %d figures to %s", len(paths), out_dir)
    return paths
