"""Built-in dataset (generated in code, no download): the README's main job.

  python -m c3dpo_jax.main --config=configs/synthetic.py --workdir=runs/synthetic

Low-rank non-rigid shapes (20 points, 3 deformation modes), cameras at any azimuth
with elevation within +-0.5 rad and roll within +-0.25 rad ("upright", like cameras
around a standing person), orthographic views, 10% of points hidden at random; 5000
train / 1000 test views. The CPU recipe (``default.cpu_recipe``: networks narrower than
the release's, 256 wide with 3 residual blocks, Adam instead of SGD, and the handedness
term) so that the run takes a few minutes on 2 CPU cores; at inference each view's camera
and coefficients are refined from Phi's output (``default.refined_inference``;
``--config.inference.refine_iters=0`` gives Phi's own). Evidence: experiments/synthetic.
"""

from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.synthetic.cameras = "upright"
    c.model.n_keypoints = c.data.synthetic.n_keypoints
    default.cpu_recipe(c)
    c.train.samples_per_epoch = 256 * 500  # 5000 steps: the quick-start job (~2 min)
    default.refined_inference(c)
    return default.apply_variants(c, arg)
