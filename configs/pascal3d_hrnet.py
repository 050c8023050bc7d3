"""PASCAL3D+ with HRNet 2D detections. Release pretrained: MPJPE 56.89, stress 40.18.

  python -m c3dpo_jax.main --config=configs/pascal3d_hrnet.py --workdir=runs/pascal3d_hrnet \
      --config.data.train_path=pascal3d_hrnet_train.json \
      --config.data.test_path=pascal3d_hrnet_val.json

Official hyperparameters (release cfgs, see configs/release.py). `:smoke` runs on
generated data with K=124 so it works without the files.
"""

from configs.release import release_config


def get_config(arg=None):
    return release_config(
        arg, name="pascal3d_hrnet", n_keypoints=124, basis=10, batch_size=1024, rescale=0.01,
        argmin_translation=True, z_augment_angle=0.3925, samples_per_epoch=4_997_120, epochs=60,
        milestones=(20, 40), protocol="pascal3d", class_balanced=True,
    )
