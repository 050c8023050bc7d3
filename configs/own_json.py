"""Train on your own keypoints in the release's JSON format (docs/data.md).

  python -m c3dpo_jax.data.importers sequence my_seq.npz --out_dir data --name my_seq
  python -m c3dpo_jax.main --config=configs/own_json.py --workdir=runs/my_seq \\
      --config.data.train_path=data/my_seq_train.json \\
      --config.data.test_path=data/my_seq_test.json --config.model.n_keypoints=K

Set ``n_keypoints`` to your K (training stops with a message naming K if it differs),
``--config.model.shape_basis_size`` (D, default 10: fewer for nearly rigid objects, more
for dense or very deformable ones) and ``--config.data.protocol=none`` for 2D-only
data. CPU-sized defaults, as configs/synthetic.py.
"""

from configs import default


def get_config(arg=None):
    c = default.get_config()
    c.data.name = "own_json"
    c.data.source = "json"  # train_path/test_path must be given
    c.model.shape_basis_size = 10
    c.model.n_fully_connected = c.model.canonicalization_n_fully_connected = 256
    c.model.n_layers = c.model.canonicalization_n_layers = 3
    c.model.argmin_translation = True
    c.model.z_augment = True
    c.model.z_augment_rot_angle = 0.3925
    c.optim.optimizer = "adam"
    c.optim.lr = 3e-3
    c.optim.weight_decay = 0.0
    c.optim.lr_milestones = (8,)
    c.train.batch_size = 256
    c.train.samples_per_epoch = 256 * 200
    c.train.epochs = 10
    return default.apply_variants(c, arg)
