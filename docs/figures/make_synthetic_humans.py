"""Renders docs/figures/synthetic_humans.png: python docs/figures/make_synthetic_humans.py"""

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from c3dpo_jax.data import humans  # noqa: E402

SKELETON = [[10, 9], [9, 8], [8, 14], [14, 15], [15, 16], [8, 11], [11, 12], [12, 13],
            [8, 7], [7, 0], [1, 0], [1, 2], [2, 3], [0, 4], [4, 5], [5, 6]]
LEFT = {4, 5, 6, 11, 12, 13}


def main():
    data = humans.make_split(4, views_per_pose=3, dense_points=300, seed=3)
    fig = plt.figure(figsize=(16, 9))
    for p in range(4):
        for v in range(3):
            i = p * 3 + v
            ax = fig.add_subplot(3, 5, v * 5 + p + 1)
            vis, x3 = data.vis[i], data.kp3d[i]
            ax.scatter(x3[17:, 0], x3[17:, 1], s=3, c=np.where(vis[17:] > 0, "tab:gray", "0.85"))
            for a, b in SKELETON:
                ax.plot(x3[[a, b], 0], x3[[a, b], 1], c="tab:red" if b in LEFT else "tab:blue")
            ax.scatter(x3[:17, 0], x3[:17, 1], s=20, c=np.where(vis[:17] > 0, "k", "w"),
                       edgecolors="k", zorder=3)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"pose {p} view {v}: {int(vis.sum())}/{len(vis)} visible", fontsize=8)
    for p in range(2):
        ax = fig.add_subplot(3, 5, 5 * (p + 1), projection="3d")
        x3 = data.kp3d[p * 3]
        for a, b in SKELETON:
            ax.plot(x3[[a, b], 0], x3[[a, b], 2], x3[[a, b], 1],
                    c="tab:red" if b in LEFT else "tab:blue")
        ax.scatter(x3[17:, 0], x3[17:, 2], x3[17:, 1], s=1, c="tab:gray")
        ax.set_title(f"pose {p} in 3D (camera frame)", fontsize=8)
        ax.set_box_aspect((1, 1, 1.6))
    vis_j, vis_s = data.vis[:, :17].mean(), data.vis[:, 17:].mean()
    fig.suptitle(f"Synthetic humans (17 joints + 300 surface points). Filled: visible, hollow/"
                 f"light: self-occluded. Visible: joints {vis_j:.0%}, surface {vis_s:.0%}. "
                 "Red = left limbs.")
    out = os.path.join(os.path.dirname(__file__), "synthetic_humans.png")
    fig.savefig(out, dpi=80, bbox_inches="tight")
    print("wrote", out)


if __name__ == "__main__":
    main()
