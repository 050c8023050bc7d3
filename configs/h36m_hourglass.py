"""Human3.6M with Stacked-Hourglass 2D detections. Release pretrained: MPJPE 145.02, stress 84.69.

  python -m c3dpo_jax.main --config=configs/h36m_hourglass.py --workdir=runs/h36m_hourglass \
      --config.data.train_path=h36m_hourglass_train.json \
      --config.data.test_path=h36m_hourglass_val.json

Official hyperparameters (release cfgs, see configs/release.py). `:smoke` runs on
generated data with K=17 so it works without the files.
"""

from configs.release import release_config


def get_config(arg=None):
    return release_config(
        arg, name="h36m_hourglass", n_keypoints=17, basis=10, batch_size=1024, rescale=1.0,
        argmin_translation=False, z_augment_angle=0.3925, samples_per_epoch=1_249_280, epochs=90,
        milestones=(60, 80), protocol="h36m", class_balanced=False,
    )
