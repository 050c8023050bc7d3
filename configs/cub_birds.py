"""CUB-200-2011 birds, 15 keypoints, 2D only (no 3D ground truth: evaluation reports
the reprojection error). The release published no CUB model and no CUB hyperparameters:
these settings follow PASCAL3D+ (image coordinates, so keypoint_rescale 0.01; occlusions,
so argmin_translation) and are our choice, not the release's.

  python -m c3dpo_jax.main --config=configs/cub_birds.py --workdir=runs/cub_birds \
      --config.data.train_path=cub_birds_train.json --config.data.test_path=cub_birds_val.json
"""

from configs.release import release_config


def get_config(arg=None):
    return release_config(
        arg, name="cub_birds", n_keypoints=15, basis=10, batch_size=1024, rescale=0.01,
        argmin_translation=True, z_augment_angle=0.3925, samples_per_epoch=1_249_280,
        epochs=60, milestones=(20, 40), protocol="none",
    )
