"""S-Up3D, 79 SMPL vertices. Release pretrained: MPJPE 0.0673, stress 0.0407 (paper: 0.068 / 0.040).

  python -m c3dpo_jax.main --config=configs/up3d.py --workdir=runs/up3d \
      --config.data.train_path=up3d_79kp_train.json --config.data.test_path=up3d_79kp_test.json

Official hyperparameters (release cfgs, see configs/release.py). `:smoke` runs on
generated data with K=79 so it works without the files.
"""

from configs.release import release_config


def get_config(arg=None):
    return release_config(
        arg, name="up3d_79kp", n_keypoints=79, basis=50, batch_size=256, rescale=1.0,
        argmin_translation=True, z_augment_angle=3.14, samples_per_epoch=2_700_000, epochs=70,
        milestones=(50, 60), protocol="up3d", class_balanced=False,
    )
