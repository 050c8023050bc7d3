"""Built-in synthetic object categories (a PASCAL3D+ analogue, data/categories.py).

  python -m c3dpo_jax.main --config=configs/categories.py --workdir=runs/categories
  python -m c3dpo_jax.main --config=configs/categories.py:smoke --workdir=/tmp/cat_smoke

Five classes (aeroplane 8, bottle 7, car 12, chair 10, diningtable 8 keypoints) packed
into one 45-keypoint layout with ``class_mask``; samples drawn class-balanced; the
``pascal3d`` protocol averages the error per class. CPU-sized networks and Adam.
"""

from c3dpo_jax.data import categories
from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.name = "categories"
    c.data.source = "categories"
    c.data.protocol = "pascal3d"
    c.data.class_balanced = True
    c.model.n_keypoints = categories.n_keypoints(c.data.categories.classes)
    c.model.shape_basis_size = 10
    c.model.n_fully_connected = c.model.canonicalization_n_fully_connected = 256
    c.model.n_layers = c.model.canonicalization_n_layers = 3
    c.model.argmin_translation = True
    c.model.z_augment = True
    c.model.z_augment_rot_angle = 0.3925
    c.optim.optimizer = "adam"
    c.optim.lr = 3e-3
    c.optim.weight_decay = 0.0
    c.optim.lr_milestones = (8,)
    c.train.batch_size = 256
    c.train.samples_per_epoch = 256 * 500
    c.train.epochs = 10
    return default.apply_variants(c, arg)
