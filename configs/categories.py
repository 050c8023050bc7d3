"""Built-in synthetic object categories (a PASCAL3D+ analogue, data/categories.py).

  python -m c3dpo_jax.main --config=configs/categories.py --workdir=runs/categories
  python -m c3dpo_jax.main --config=configs/categories.py:smoke --workdir=runs/categories_smoke

Five classes (aeroplane 8, bottle 7, car 12, chair 10, diningtable 8 keypoints) packed
into one 45-keypoint layout with ``class_mask``; samples drawn class-balanced; the
``pascal3d`` protocol averages the error per class. The CPU recipe
(``default.cpu_recipe``). At inference each view's camera and coefficients are refined from
Phi's output (``default.refined_inference``);
``--config.inference.refine_iters=0`` gives Phi's single pass.
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
    default.cpu_recipe(c)
    default.refined_inference(c)
    return default.apply_variants(c, arg)
