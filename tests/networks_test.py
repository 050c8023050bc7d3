"""Network shapes, parameter counts and per-example BatchNorm under vmap."""

import flax.linen as nn
import jax
import numpy as np

from c3dpo_jax import model, networks


def _trunk_params(dim_in, h, n_layers):
    first = dim_in * h + h + 2 * h  # dense + BN scale/bias
    q = h // 4
    block = (h * q + q) + (q * q + q) + (q * h + h) + 2 * (q + q + h)
    return first + n_layers * block


def test_parameter_count_matches_the_architecture():
    cfg = model.ModelConfig(n_keypoints=17, shape_basis_size=10, n_fully_connected=64, n_layers=2,
                            canonicalization_n_fully_connected=32, canonicalization_n_layers=1)
    params = model.init_variables(jax.random.key(0), cfg)["params"]
    n, d = 17, 10
    expected = (
        _trunk_params(3 * n, 64, 2) + (64 * d + d) + (64 * 3 + 3)  # phi, alpha, rot
        + (d * 3 * n + 3 * n)  # shape layer (basis + mean shape)
        + _trunk_params(3 * n, 32, 1) + (32 * d + d)  # psi, alpha_psi
    )
    assert networks.count_params(params) == expected


def test_official_sized_network_has_the_expected_layers():
    cfg = model.ModelConfig(
        n_keypoints=17, shape_basis_size=10, camera_translation=True, camera_scale=True
    )
    params = model.init_variables(jax.random.key(0), cfg)["params"]
    shapes = dict(networks.param_shapes(params))
    assert shapes["['phi_trunk']['conv1']['kernel']"] == (51, 1024)
    assert shapes["['phi_trunk']['block6']['conv2']['kernel']"] == (256, 256)
    assert shapes["['shape_layer']['kernel']"] == (10, 51)
    assert shapes["['translation_layer']['kernel']"] == (1024, 3)
    assert shapes["['scale_layer']['kernel']"] == (1024, 1)
    assert "['phi_trunk']['block7']['conv1']['kernel']" not in shapes


def test_heads_are_initialised_small_and_batchnorm_scale_uniform():
    cfg = model.ModelConfig(n_keypoints=17, shape_basis_size=10)
    params = model.init_variables(jax.random.key(1), cfg)["params"]
    rot = np.asarray(params["rot_layer"]["kernel"])
    assert 0.007 < rot.std() < 0.013 and np.all(np.asarray(params["rot_layer"]["bias"]) == 0)
    scale = np.asarray(params["phi_trunk"]["bn1"]["scale"])
    assert scale.min() >= 0 and scale.max() <= 1 and 0.4 < scale.mean() < 0.6


def test_per_example_batchnorm_under_vmap_equals_batched_batchnorm(key):
    trunk = networks.Trunk(features=16, n_layers=2, axis_name="batch")
    x = jax.random.normal(key, (8, 12))
    variables = trunk.init(key, x[0], False)

    def one(xi):
        return trunk.apply(variables, xi, True, mutable=["batch_stats"])

    y_vmap, stats = jax.vmap(one, axis_name="batch")(x)

    class Batched(nn.Module):  # the same trunk written for a batch, without vmap
        @nn.compact
        def __call__(self, x):
            return networks.Trunk(16, 2, axis_name=None, name="t")(x, True)

    y_batched, stats_b = Batched().apply({"params": {"t": variables["params"]},
                                          "batch_stats": {"t": variables["batch_stats"]}},
                                         x, mutable=["batch_stats"])
    np.testing.assert_allclose(y_vmap, y_batched, atol=1e-5)
    np.testing.assert_allclose(stats["batch_stats"]["bn1"]["mean"][0],
                               stats_b["batch_stats"]["t"]["bn1"]["mean"], atol=1e-6)
