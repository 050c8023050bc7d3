"""The measurements and the figure of the Psi consistency experiment (numpy and matplotlib).

Glossary: P poses, A rotation angles, N keypoints. A pose's views are its 3D points turned
about the camera's vertical (y) axis by each angle and projected orthographically; a model
predicts a canonical shape for each view, ``canonical (P, A, N, 3)``.

Canonical spread of a pose: the RMS distance of its A canonical shapes from their mean
shape (over angles and points), divided by the RMS radius of that mean shape about its
centroid. 0 when every view gives the same canonical shape; no alignment of any kind is
made. ``run.py`` runs the experiment; this module holds no flags so that tests import it.
"""

import numpy as np


def y_rotations(angles: np.ndarray) -> np.ndarray:
    """(A,) angles in radians -> (A, 3, 3) rotations about the y axis."""
    c, s = np.cos(angles), np.sin(angles)
    zero, one = np.zeros_like(angles), np.ones_like(angles)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1),
                     np.stack([-s, zero, c], -1)], -2)


def rotate_about_y(points: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Each of ``points`` (P, N, 3), centred on its centroid, turned about the y axis by
    each of ``angles`` (A,) radians: (P, A, N, 3)."""
    points = np.asarray(points, np.float64)
    centred = points - points.mean(1, keepdims=True)
    return np.einsum("aij,pnj->pani", y_rotations(np.asarray(angles, np.float64)), centred)


def _rms_radius(shapes: np.ndarray) -> np.ndarray:
    """RMS distance of the points of each shape (..., N, 3) from its centroid: (...)."""
    centred = shapes - shapes.mean(-2, keepdims=True)
    return np.sqrt((centred ** 2).sum(-1).mean(-1))


def deviation_per_angle(canonical: np.ndarray) -> np.ndarray:
    """(..., A, N, 3) -> (..., A): the RMS distance of each angle's canonical shape from
    the mean over angles, divided by the RMS radius of that mean shape."""
    canonical = np.asarray(canonical, np.float64)
    mean = canonical.mean(-3, keepdims=True)
    rms = np.sqrt(((canonical - mean) ** 2).sum(-1).mean(-1))
    return rms / _rms_radius(mean)


def canonical_spread(canonical: np.ndarray) -> np.ndarray:
    """(..., A, N, 3) -> (...): the canonical spread (module docstring) of each pose."""
    return np.sqrt((deviation_per_angle(canonical) ** 2).mean(-1))


def spread_own_radius(canonical: np.ndarray) -> np.ndarray:
    """(..., A, N, 3) -> (...): the same RMS distance from the mean shape, divided by the
    RMS radius of the A shapes themselves instead of their mean's (which shrinks when the
    shapes turn with the view)."""
    canonical = np.asarray(canonical, np.float64)
    mean = canonical.mean(-3, keepdims=True)
    rms = np.sqrt(((canonical - mean) ** 2).sum(-1).mean((-2, -1)))
    return rms / np.sqrt((_rms_radius(canonical) ** 2).mean(-1))


def sign_agreement(pred: np.ndarray, gt: np.ndarray) -> float:
    """Fraction of views ``pred``/``gt`` (M, N, 3) (camera frame, every point counted) whose
    prediction fits the truth at least as well as its depth flip, as
    ``experiments/dev_suite/analyse.py`` measures it: near 1 or 0 when every view has the
    same handedness, 0.5 when the depth sign is a coin toss per view."""
    from c3dpo_jax import evaluation

    mask = np.ones(np.shape(pred)[:2])
    per = evaluation.mpjpe(evaluation.center_depth(np.asarray(pred, np.float64), mask),
                           evaluation.center_depth(np.asarray(gt, np.float64), mask), mask)
    return float(np.mean(per["mpjpe_orig"] <= per["mpjpe_flip"]))


def mpjpe(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean flip-resolved MPJPE of views (M, N, 3), mean depth removed (the up3d protocol)."""
    from c3dpo_jax import evaluation

    mask = np.ones(np.shape(pred)[:2])
    per = evaluation.mpjpe(evaluation.center_depth(np.asarray(pred, np.float64), mask),
                           evaluation.center_depth(np.asarray(gt, np.float64), mask), mask)
    return float(per["mpjpe"].mean())


def display_frame(canonical: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) to draw a model's canonical shapes (..., N, 3) with: the principal
    axes of all of them (largest first, then second, then third), so that the widest
    extent is drawn vertically. One rotation for all shapes of a model: no distance between
    them changes."""
    pts = np.asarray(canonical, np.float64)
    pts = (pts - pts.mean(-2, keepdims=True)).reshape(-1, 3)
    _, _, vt = np.linalg.svd(pts, full_matrices=False)
    if np.linalg.det(vt) < 0:
        vt[2] *= -1
    return vt


def plot_consistency(models: dict, angles_deg: np.ndarray, example_poses, shown_angles,
                     edges, reference_curve: np.ndarray | None = None):
    """The figure: example poses' canonical shapes at ``shown_angles`` overlaid (two
    projections per model), and the deviation from the mean canonical shape against the
    rotation angle.

    Args:
      models: ``{label: {"canonical": (P, A, N, 3), "curve": (A,), "spread": float}}``.
      angles_deg: (A,) the rotation angles in degrees.
      example_poses: indices into P of the poses to draw (one row each).
      shown_angles: indices into A of the angles to overlay.
      edges: skeleton index pairs.
      reference_curve: (A,) the same curve for the camera-frame truth, drawn dashed.
    """
    from c3dpo_jax.curves import pyplot

    plt = pyplot()
    labels = list(models)
    n_rows = len(example_poses)
    fig = plt.figure(figsize=(3.1 * 2 * len(labels), 3.3 * n_rows + 4.0))
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.07, top=0.86)
    grid = fig.add_gridspec(n_rows + 1, 2 * len(labels),
                            height_ratios=[1.0] * n_rows + [1.05], hspace=0.45, wspace=0.32)
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 0.92, len(shown_angles)))
    for m, label in enumerate(labels):
        canonical = np.asarray(models[label]["canonical"], np.float64)
        frame = display_frame(canonical)
        for r, pose in enumerate(example_poses):
            shapes = canonical[pose] @ frame.T  # (A, N, 3): principal axes 1, 2, 3
            shapes = shapes - shapes.mean((0, 1))
            extent = np.abs(shapes[list(shown_angles)]).max() * 1.08
            spread = float(canonical_spread(canonical[pose]))
            for k, h in enumerate((1, 2)):
                ax = fig.add_subplot(grid[r, 2 * m + k])
                for c, a in zip(colours, shown_angles, strict=True):
                    pts = shapes[a][:, [h, 0]]  # horizontal, vertical (largest axis up)
                    for i, j in edges:
                        ax.plot(*pts[[i, j]].T, "-", color=c, lw=1.4, alpha=0.85)
                    ax.scatter(*pts.T, color=c, s=9, zorder=3, label=f"{angles_deg[a]:.0f}°")
                ax.set_xlim(-extent, extent)
                ax.set_ylim(-extent, extent)
                ax.set_aspect("equal")
                ax.tick_params(labelsize=7)
                ax.set_xlabel(f"canonical axis {h + 1}", fontsize=8)
                ax.set_ylabel("canonical axis 1", fontsize=8)
                ax.set_title(f"pose {pose}, axes {h + 1} and 1\n(spread of this pose "
                             f"{spread:.3f})", fontsize=9)
        first = fig.axes[m * 2 * n_rows]
        last = fig.axes[m * 2 * n_rows + 1]
        x = (first.get_position().x0 + last.get_position().x1) / 2
        fig.text(x, 0.905, label, ha="center", va="bottom", fontsize=12, weight="bold")
    handles, names = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="upper center", ncol=len(shown_angles), fontsize=9,
               frameon=False, bbox_to_anchor=(0.5, 0.995), markerscale=2.0,
               title="canonical shape predicted from the view turned about the camera's "
                     "vertical axis by", title_fontsize=10)
    ax = fig.add_subplot(grid[n_rows, 1:-1])
    styles = ("tab:blue", "tab:orange", "tab:green", "tab:red")
    for colour, label in zip(styles, labels, strict=False):
        info = models[label]
        ax.plot(angles_deg, info["curve"], "o-", ms=3, color=colour,
                label=f"{label} (canonical spread {info['spread']:.3f})")
    if reference_curve is not None:
        ax.plot(angles_deg, reference_curve, "--", color="0.5",
                label="camera-frame truth, no canonicalisation")
    ax.set_xlabel("rotation of the view about the camera's vertical axis [degrees]")
    ax.set_ylabel("distance from the mean\ncanonical shape / its radius")
    ax.set_xticks(np.arange(0, 361, 45))
    ax.set_xlim(angles_deg.min() - 5, angles_deg.max() + 5)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title("mean over the test poses", fontsize=10)
    return fig
