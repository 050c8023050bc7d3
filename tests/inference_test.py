"""The shared eval path: padding by wrap-around, and a split predicted in padded batches
equals the per-example model on each sample."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from c3dpo_jax import inference, lift, model
from c3dpo_jax.data import synthetic

CFG = model.ModelConfig(n_keypoints=6, shape_basis_size=2, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1)


def test_padding_repeats_valid_rows_and_buckets_are_powers_of_two():
    assert inference.wrap_indices(0, 4, 3).tolist() == [0, 1, 2, 0]
    assert inference.wrap_indices(4, 4, 7).tolist() == [4, 5, 6, 0]
    assert [inference.bucket_size(b) for b in (1, 2, 3, 4, 5, 8, 9)] == [1, 2, 4, 4, 8, 8, 16]


def test_split_in_padded_batches_equals_the_per_example_model():
    data = synthetic.make_split(7, n_keypoints=6, n_modes=2, deformation=0.3, occlusion=0.2,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    variables = model.init_variables(jax.random.key(0), CFG)
    options = lift.InferenceConfig()
    pred = inference.predict_split(variables, data, CFG, options, batch_size=3)  # 3 + 3 + 1
    inputs = data.model_inputs()
    one = jax.jit(partial(lift.forward_eval, variables, cfg=CFG, options=options))
    for i in range(len(data)):
        ref = one(jnp.asarray(inputs["kp"][i]), jnp.asarray(inputs["vis"][i]),
                  jnp.asarray(inputs["class_mask"][i]), None, None)
        for name in ("shape_3d", "alpha", "kp_reprojected"):
            assert pred[name].shape[0] == 7
            np.testing.assert_allclose(pred[name][i], ref[name], rtol=1e-5, atol=1e-5)
