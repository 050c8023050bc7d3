"""Train on your own keypoints in the release's JSON format (docs/data.md).

  python -m c3dpo_jax.data.importers sequence my_seq.npz --out_dir data --name my_seq
  python -m c3dpo_jax.main --config=configs/own_json.py --workdir=runs/my_seq \\
      --config.data.train_path=data/my_seq_train.json \\
      --config.data.test_path=data/my_seq_test.json --config.model.n_keypoints=K

Set ``n_keypoints`` to your K (training stops with a message naming K if it differs),
``--config.model.shape_basis_size`` (D, default 10: fewer for nearly rigid objects, more
for dense or very deformable ones) and ``--config.data.protocol=none`` for 2D-only
data. CPU-sized defaults, as configs/synthetic.py, with one addition that is not in the
paper: a Gaussian prior on the deformations (weight 1) for the first 1,000 steps, ramped to
0 at step 2,000. Two mirror-image reconstructions fit a view's 2D points equally; the prior
makes every view take one of them early on, after which the paper's objective trains alone
(experiments/dev_suite, sixth screen: on real human motion it stops the error from rising
as training goes on). ``--config.loss.w_deformation=0`` trains the paper's objective.
The learning rate is warmed up linearly over the first 500 steps: at the full rate from
step 0, one seed in ten of the suite's humans started with part of the views lifted as
mirror images, a state the training never left (experiments/dev_suite, eleventh screen).
Also not in the paper, at inference only: Phi's camera and shape coefficients for each
view are the start of 20 Levenberg-Marquardt steps on the view's 2D reprojection error plus
0.3 times the mean squared distance of the canonical shape's points to Phi's
(``inference.refine_iters``, ``inference.refine_prior``). Against the median
depth over 32 copies turned in-plane (experiments/dev_suite's ``union32``): 7.7% lower test
error on average over 27 runs of experiments/dev_suite not used to choose it (seeds 3-5),
25% on the nearly rigid face (whose regressed camera was what it lost against a rigid
fit), 2% higher on CMU 131's 17 joints (the section "Refining the regressed camera and
coefficients at test time" there).
``--config.inference.refine_iters=0`` gives Phi's own output (the release's single
pass); with it, ``--config.inference.turns=32
--config.inference.turn_span=circle_and_range`` gives the 32 turned copies.
Handedness at inference (``inference.handedness_reference="auto"``): when the points
are those of people in Human3.6M's 17-joint order or in COCO's 17 keypoints (a human body's
projections fit the training views, ``resolve.resolve_handedness``), every view gets that
body's handedness, so the reconstructions are not mirror images (CMU 131: error without the
protocol's flip 0.08 instead of 0.35-0.58; the flip-resolved error unchanged;
experiments/dev_suite, "The handedness of a human body"); other points keep the model's
own, view by view.
``--config.inference.handedness_reference=mean_shape`` turns it off;
``--config.inference.handedness_reference=my_body.npy`` (or .json, .txt, .csv: one 3D
example of your points, N rows of x, y, z, any pose, orientation and scale) gives every
view that example's handedness, weighed with the model's mean shape given it, for points in
any order (experiments/dev_suite, "The handedness from one 3D example").
Subjects at different distances (``model.keypoint_scaling="auto"``: training views that
look alike differ in size by more than 1.18x, median, as for people photographed at
different distances, not a subject filmed at one) get each view scaled by its own size
before Phi and its reconstruction scaled back (``resolve.resolve_keypoint_scaling``;
experiments/dev_suite, "People at different distances"); other data keep one input scale for
every view, which is much better there. ``--config.model.keypoint_scaling=global`` or
``per_view`` sets it.
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
    # People in Human3.6M's or COCO's 17-joint order get a human body's handedness at
    # inference (resolve.resolve_handedness); other points the mean shape's, as before.
    c.inference.handedness_reference = "auto"
    # Subjects at different distances get each view scaled by its own size
    # (resolve.resolve_keypoint_scaling); others one input scale, as before.
    c.model.keypoint_scaling = "auto"
    return default.apply_variants(c, arg)
