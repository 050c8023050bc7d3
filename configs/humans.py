"""Built-in synthetic humans (an S-Up3D analogue, data/humans.py): no download.

  python -m c3dpo_jax.main --config=configs/humans.py --workdir=runs/humans
  python -m c3dpo_jax.main --config=configs/humans.py:smoke --workdir=/tmp/humans_smoke

17 joints in Human3.6M order (plot with the ``h36m`` skeleton), 300 train / 50 test
people and poses, each seen by 30 upright cameras (the paper's S-Up3D protocol),
self-occlusion computed geometrically. ``--config.data.humans.dense_points=300`` adds
surface points (then set --config.model.n_keypoints=317 and a larger basis, e.g. 30).
CPU-sized networks and Adam, as configs/synthetic.py; the method is the paper's.
"""

from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.name = "humans"
    c.data.source = "humans"
    c.data.protocol = "up3d"  # mean depth of pred and gt set to 0, as for S-Up3D
    c.model.n_keypoints = 17 + c.data.humans.dense_points
    default.cpu_recipe(c)
    return default.apply_variants(c, arg)
