"""PASCAL3D+, 12 classes in one 124-keypoint layout, class-balanced sampling.

Release pretrained: MPJPE 36.64, stress 31.08.

  python -m c3dpo_jax.main --config=configs/pascal3d.py --workdir=runs/pascal3d \
      --config.data.train_path=pascal3d_train.json --config.data.test_path=pascal3d_val.json

Official hyperparameters (release cfgs, see configs/release.py). `:smoke` runs on
generated data with K=124 so it works without the files.
"""

from configs.release import release_config


def get_config(arg=None):
    return release_config(
        arg, name="pascal3d", n_keypoints=124, basis=10, batch_size=1024, rescale=0.01,
        argmin_translation=True, z_augment_angle=0.3925, samples_per_epoch=4_997_120, epochs=60,
        milestones=(20, 40), protocol="pascal3d", class_balanced=True,
    )
