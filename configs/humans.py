"""Built-in synthetic humans (an S-Up3D analogue, data/humans.py): no download.

  python -m c3dpo_jax.main --config=configs/humans.py --workdir=runs/humans
  python -m c3dpo_jax.main --config=configs/humans.py:smoke --workdir=runs/humans_smoke

17 joints in Human3.6M order (plot with the ``h36m`` skeleton), 300 train / 50 test
people and poses, each seen by 30 upright cameras (the paper's S-Up3D protocol),
self-occlusion computed geometrically. ``--config.data.humans.dense_points=300`` adds
surface points (``model.n_keypoints`` follows: 17 + 300).
The CPU recipe (``default.cpu_recipe``: CPU-sized networks, Adam, the handedness term)
with a 3x canonicalisation weight, each view's camera and coefficients refined at inference
(``default.refined_inference``; ``--config.inference.refine_iters=0`` gives Phi's single
pass) and the h36m body's handedness (the points are in its joint order). Evidence:
experiments/time_to_accuracy/README.md.
"""

from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.name = "humans"
    c.data.source = "humans"
    c.data.protocol = "up3d"  # mean depth of pred and gt set to 0, as for S-Up3D
    # A reference, so that ``--config.data.humans.dense_points=M`` alone gives K = 17 + M.
    c.model.n_keypoints = c.data.humans.get_ref("dense_points") + 17
    default.cpu_recipe(c)
    # 1 lets these varied, self-occluding bodies factorise degenerately, 10 makes the model
    # rigid (evidence: experiments/time_to_accuracy/README.md).
    c.loss.w_canonicalization = 3.0
    default.refined_inference(c)
    return default.apply_variants(c, arg)
