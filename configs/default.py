"""Base config: the release's model and optimiser defaults; dataset configs override it.

Not a recipe to run by itself (its data are the generated shapes of 20 points, its model
the release's 17): run a dataset config, e.g. ``python -m c3dpo_jax.main
--config=configs/synthetic.py --workdir=runs/synthetic``.
``--config=FILE:ARGS`` takes comma-separated variant words:
  smoke  tiny networks (H=32, 2 layers), 20 steps (loss-weight ramps shrunk with the run):
         checks that everything runs;
  base   C3DPO-base (reprojection loss only: no equivariance, no Psi);
  equiv  C3DPO-equiv (+ in-plane equivariance, no Psi);
  full   C3DPO (the default: + canonicalisation network Psi);
  paper  the paper's objective: without the terms this library adds to it (the handedness
         term and the early deformation prior of the built-in and own-data recipes);
  supervised
         the same networks trained with the 3D ground truth instead of C3DPO's losses
         (``loss.w_supervised=1``, every other weight 0, no Psi, Phi's own output at
         inference): a reference for what the views allow, not C3DPO; the training split
         needs its 3D points (``kp_loc_3d``).
"""

import dataclasses

import ml_collections

from c3dpo_jax import losses
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.model import ModelConfig

VARIANTS = ("smoke", "base", "equiv", "full", "paper", "supervised")


def parse_args(arg: str | None) -> set[str]:
    words = {w for w in (arg or "").split(",") if w}
    unknown = words - set(VARIANTS)
    if unknown:
        raise ValueError(f"unknown config variant(s) {sorted(unknown)}; known: {VARIANTS}")
    return words


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.seed = 0
    c.data = dict(
        name="synthetic",  # with source="release": a release dataset name (data/download.py)
        # Used when train_path is empty: "synthetic" | "humans" | "categories" | "release".
        source="synthetic",
        train_path="",
        test_path="",
        data_dir="",  # release downloads: "" = $C3DPO_DATA_DIR or ~/.cache/c3dpo_jax
        min_visible=2,  # JSON entries with fewer visible points are invalid
        drop_invalid=False,  # drop (and log) invalid JSON entries instead of failing
        protocol="default",  # "default" | "up3d" | "h36m" | "pascal3d"
        class_balanced=False,  # draw a class uniformly, then an image of it
        synthetic=dict(
            n_keypoints=20, n_modes=3, deformation=0.35, occlusion=0.1, noise=0.0,
            perspective=False, n_train=5000, n_test=1000, cameras="uniform",
            max_elevation=0.5, seed=0,
        ),
        humans=dict(  # data/humans.py: 17 H36M-order joints (+ dense surface points)
            n_train_poses=300, n_test_poses=50, views_per_pose=30, dense_points=0,
            cameras="upright", max_elevation=0.5, noise=0.0, self_occlusion=True,
            proportions=1.0,  # spread of body proportions (0: one body for everyone)
            seed=0,
        ),
        categories=dict(  # data/categories.py: 5 classes packed into 45 keypoints
            n_train=5000, n_test=1000,
            classes=("aeroplane", "bottle", "car", "chair", "diningtable"),
            variation=1.0, occlusion=0.1, noise=0.0, max_elevation=0.6, seed=0,
        ),
    )
    c.model = dataclasses.asdict(ModelConfig())
    # lift.InferenceConfig: how a trained model lifts a view (refinement, turned copies,
    # handedness); none of it changes training.
    c.inference = dataclasses.asdict(InferenceConfig())
    # losses.LossConfig: the weights (canonicalization_ramp=(first, last) steps moves the
    # canonicalisation weight linearly to w_canonicalization_final; () keeps it constant)
    # and the options of the terms (the release keeps them with the model); w_deformation
    # (not in the paper: 0) weights a Gaussian prior on the deformations, deformation_ramp
    # and w_deformation_final ramp it as the canonicalisation weight; w_supervised (not
    # C3DPO: 0) weights the distance to the training split's 3D ground truth; w_multiview
    # (not in the paper: 0) the agreement of the canonical shapes of one frame's views, in
    # batches of groups of multiview_views views of a frame (the split's frame ids).
    c.loss = dict(
        w_reprojection=1.0, w_canonicalization=1.0,
        w_canonicalization_final=ml_collections.config_dict.placeholder(float),
        canonicalization_ramp=(), w_deformation=0.0,
        w_deformation_final=ml_collections.config_dict.placeholder(float), deformation_ramp=(),
        w_supervised=0.0, huber_scaling=0.01, reprojection_normalization="kp_total_count",
        squared_reprojection_loss=False, w_multiview=0.0, multiview_views=3,
        w_handedness=0.0, w_handedness_final=ml_collections.config_dict.placeholder(float),
        handedness_ramp=(), handedness_margin=0.0, handedness_evidence="procrustes",
        handedness_prototype="basis_mean",
    )
    c.optim = dict(
        optimizer="sgd", lr=1e-3, momentum=0.9, weight_decay=5e-4,
        lr_milestones=(), gamma=0.1, warmup_steps=0,
        schedule="multistep", cosine_steps=0,  # state.OptimConfig
    )
    c.train = dict(
        batch_size=256,
        samples_per_epoch=256_000,
        epochs=10,
        num_steps=0,  # > 0 overrides epochs * samples_per_epoch // batch_size
        log_every=50,
        ckpt_every=1000,
        eval_every_epochs=1,  # 0 disables evaluation at epoch ends
        eval_every_steps=0,  # > 0 overrides eval_every_epochs
        eval_batch_size=1024,
        progress_bar=True,
        data_parallel=True,  # split each batch over all devices when there are several
        init_from="",  # a workdir (or WORKDIR/checkpoints/<step>) whose model starts the run
    )
    return c


def cpu_recipe(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """The CPU-sized training recipe: the default of the built-in datasets and of "train on
    my own data" (evidence: experiments/dev_suite/README.md; for the equivariance range,
    experiments/time_to_accuracy/README.md).

    Only what the paper leaves to taste changes: 256-wide 3-block trunks instead of
    1024 x 6, Adam (lr 3e-3, x0.1 at epoch 8 of 10) instead of SGD, no weight decay,
    in-plane equivariance rotations within +-0.1 rad instead of +-0.3925, the input scale
    set from the training data (``keypoint_rescale=0``: the centred 2D views get a median
    RMS radius of 1, whatever the units), and 10,000 steps of batch 256: about 4 minutes
    on a 2-core CPU that makes 45 steps/s, under 10 minutes at 20 steps/s. The three losses,
    Phi and Psi are the paper's; a handedness term is added to their losses
    (``one_handedness``). The release-dataset configs keep the official recipe
    (configs/release.py).
    """
    c.model.shape_basis_size = 10
    c.model.n_fully_connected = c.model.canonicalization_n_fully_connected = 256
    c.model.n_layers = c.model.canonicalization_n_layers = 3
    c.model.keypoint_rescale = 0.0  # from the training data (resolve.resolve_input_scale)
    c.model.argmin_translation = True  # robust to occluded points (paper Sec. 4.4)
    c.model.z_augment = True
    c.model.z_augment_rot_angle = 0.3925
    c.model.z_equivariance_rot_angle = 0.1
    c.optim.optimizer = "adam"
    c.optim.lr = 3e-3
    c.optim.weight_decay = 0.0
    c.optim.lr_milestones = (8,)
    c.train.batch_size = 256
    c.train.samples_per_epoch = 256 * 1000
    c.train.epochs = 10
    one_handedness(c)
    return c


def one_handedness(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Not in the paper: every view lifted with one handedness. A hinge (weight 10, margin
    0.02) on each canonical shape's handedness evidence against the basis' mean shape
    (``losses.handedness``: how much better a proper rotation than a reflection aligns
    them) keeps a view from being lifted as the mirror image of the others, which fits its
    2D points as well; at inference the handedness reference is taken from the data
    (``resolve.resolve_handedness``: a built-in body whose joint order the views fit, else
    the training views' mean, each output weighed by its small corners where they keep
    their chirality, else the model's own). ``:paper`` turns the term off (evidence:
    experiments/dev_suite/handedness.md)."""
    c.loss.w_handedness, c.loss.handedness_margin = 10.0, 0.02
    c.inference.handedness_reference = "auto"
    return c


def refined_inference(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Not in the paper, at inference only: Phi's camera and shape coefficients for each view
    start 20 Levenberg-Marquardt steps on the view's 2D reprojection error plus 0.3 times the
    mean squared distance of the canonical shape's points to Phi's
    (``inference.refine_iters``, ``inference.refine_prior``; evidence:
    experiments/dev_suite/inference.md)."""
    c.inference.refine_iters, c.inference.refine_prior = 20, 0.3
    return c


def apply_variants(c: ml_collections.ConfigDict, arg: str | None) -> ml_collections.ConfigDict:
    """Applies the ``:smoke``, ``:base``, ``:equiv``, ``:paper``, ``:supervised`` words (see
    the module docstring)."""
    words = parse_args(arg)
    if "supervised" in words:
        c.loss.w_supervised = 1.0
        for term in ("reprojection", *losses.RAMPED_TERMS):
            c.loss[f"w_{term}"] = 0.0
        for term in losses.RAMPED_TERMS:  # no ramps: constant weights
            c.loss[f"w_{term}_final"], c.loss[f"{term}_ramp"] = None, ()
        c.model.canonicalization = False
        c.inference.refine_iters = 0
    if "paper" in words:
        for term in ("handedness", "deformation"):
            c.loss[f"w_{term}"], c.loss[f"w_{term}_final"], c.loss[f"{term}_ramp"] = 0.0, None, ()
    if "base" in words:
        c.model.z_equivariance = False
        c.model.canonicalization = False
    if "equiv" in words:
        c.model.z_equivariance = True
        c.model.canonicalization = False
    if "smoke" in words:
        recipe_steps = c.train.num_steps or (
            c.train.epochs * c.train.samples_per_epoch // c.train.batch_size)
        c.model.n_fully_connected = c.model.canonicalization_n_fully_connected = 32
        c.model.n_layers = c.model.canonicalization_n_layers = 2
        c.train.batch_size = 32
        c.train.num_steps = 20
        c.train.samples_per_epoch = 10 * 32
        c.train.log_every = 5
        c.train.ckpt_every = 10
        c.train.eval_batch_size = 64
        c.data.synthetic.n_train = 256
        c.data.synthetic.n_test = 64
        c.data.humans.n_train_poses, c.data.humans.n_test_poses = 16, 4
        c.data.humans.views_per_pose = 16
        c.data.categories.n_train, c.data.categories.n_test = 256, 64
        for term in losses.RAMPED_TERMS:  # loss-weight ramps: same fractions
            ramp = c.loss[f"{term}_ramp"]
            c.loss[f"{term}_ramp"] = tuple(s * c.train.num_steps // recipe_steps for s in ramp)
        c.optim.warmup_steps = c.optim.warmup_steps * c.train.num_steps // recipe_steps
    return c
