"""Train on your own keypoints in the release's JSON format (docs/data.md).

  python -m c3dpo_jax.data.importers sequence my_seq.npz --out_dir data --name my_seq
  python -m c3dpo_jax.main --config=configs/own_json.py --workdir=runs/my_seq \\
      --config.data.train_path=data/my_seq_train.json \\
      --config.data.test_path=data/my_seq_test.json --config.model.n_keypoints=K

Set ``n_keypoints`` to your K (training stops with a message naming K if it differs),
``--config.model.shape_basis_size`` (D, default 10: fewer for nearly rigid objects, more
for dense or very deformable ones) and ``--config.data.protocol=none`` for 2D-only data.

The CPU recipe (``default.cpu_recipe``, with its handedness term) plus, not in the paper:
a Gaussian prior on the deformations for the first 2,000 steps, the learning rate warmed
up over the first 500, and each view's camera and coefficients refined at inference
(``default.refined_inference``) with a term that keeps that fit from carrying a view near
the boundary over to the other handedness (``inference.refine_handedness``; this config
only). At inference the handedness comes from a built-in human
body when the points are people in Human3.6M's or COCO's 17-joint order, else from the
model (``inference.handedness_reference``; give one 3D example of your points as a .npy,
.json, .txt or .csv file to fix the mirror bit, docs/inference.md); subjects seen at
different distances get each view scaled by its own size (``model.keypoint_scaling``).
``:paper`` trains the paper's objective. Evidence for each: experiments/dev_suite/README.md.
"""

from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.name = "own_json"
    c.data.source = "json"  # train_path/test_path must be given
    default.cpu_recipe(c)
    c.loss.w_deformation, c.loss.w_deformation_final = 1.0, 0.0
    c.loss.deformation_ramp = (1000, 2000)
    c.optim.warmup_steps = 500
    default.refined_inference(c)
    # The refinement keeps each view's handedness evidence at least the lower of Phi's and
    # 0.05 (experiments/dev_suite/handedness.md, "The refinement's handedness").
    c.inference.refine_handedness, c.inference.refine_handedness_margin = 100.0, 0.05
    # People in Human3.6M's or COCO's 17-joint order get a human body's handedness at
    # inference (resolve.resolve_handedness); other points the mean shape's, as before.
    c.inference.handedness_reference = "auto"
    # Subjects at different distances get each view scaled by its own size
    # (resolve.resolve_keypoint_scaling); others one input scale, as before.
    c.model.keypoint_scaling = "auto"
    return default.apply_variants(c, arg)
