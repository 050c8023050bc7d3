"""Shared body of the release-dataset configs (official hyperparameters).

Numbers are the release's ``cfgs/*.yaml``: SGD with momentum 0.9, weight decay 5e-4
added to the gradient, lr 1e-3 x0.1 at the milestones, 1024-wide 6-block trunks for Phi
and Psi, 4 canonicalisation samples with any rotation, z-equivariance angle 0.3925, seed 0.
The ``:smoke`` variant swaps the files for generated low-rank data with the dataset's
number of keypoints (unless --config.data.train_path is given), so it runs anywhere.
"""

from configs import default


def release_config(
    arg,
    *,
    name: str,
    n_keypoints: int,
    basis: int,
    batch_size: int,
    rescale: float,
    argmin_translation: bool,
    z_augment_angle: float,
    samples_per_epoch: int,
    epochs: int,
    milestones: tuple[int, ...],
    protocol: str,
    class_balanced: bool = False,
):
    c = default.get_config()
    c.data.name = name
    c.data.source = "release"
    c.data.protocol = protocol
    c.data.class_balanced = class_balanced
    # The release trains on every entry; one with no visible point adds nothing to the
    # losses (masked means clamp their counts), so the release's files load unfiltered.
    c.data.min_visible = 0
    c.model.n_keypoints = n_keypoints
    c.model.shape_basis_size = basis
    c.model.keypoint_rescale = rescale
    c.model.argmin_translation = argmin_translation
    c.model.z_augment = True
    c.model.z_augment_rot_angle = z_augment_angle
    c.model.z_equivariance = True
    c.model.z_equivariance_rot_angle = 0.3925
    c.model.canonicalization = True
    c.train.batch_size = batch_size
    c.train.samples_per_epoch = samples_per_epoch
    c.train.epochs = epochs
    c.train.ckpt_every = 2000
    c.train.log_every = 20
    c.optim.update(optimizer="sgd", lr=1e-3, momentum=0.9, weight_decay=5e-4,
                   lr_milestones=milestones, gamma=0.1)
    if "smoke" in default.parse_args(arg):
        c.data.source = "synthetic"
        c.data.protocol = "default"
        c.data.class_balanced = False
        c.data.synthetic.n_keypoints = n_keypoints
        c.model.keypoint_rescale = 1.0
    return default.apply_variants(c, arg)
