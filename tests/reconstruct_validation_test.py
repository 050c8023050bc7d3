"""reconstruct() on bad input: one-line ValueErrors naming ``kp``/``vis`` and the samples,
never non-finite shapes; hidden points may hold anything."""

import dataclasses

import jax
import numpy as np
import pytest

from c3dpo_jax import model
from c3dpo_jax.reconstruct import MAX_NORMALISED_EXTENT, C3DPOParams, reconstruct

CFG = model.ModelConfig(
    n_keypoints=7,
    shape_basis_size=3,
    n_fully_connected=16,
    n_layers=1,
    canonicalization_n_fully_connected=16,
    canonicalization_n_layers=1,
    argmin_translation=True,
)


@pytest.fixture(scope="module")
def params():
    return C3DPOParams(model.init_variables(jax.random.key(3), CFG), CFG)


def _inputs(b=3, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(b, 7, 2)) * 50 + 200).astype(np.float32), np.ones((b, 7), np.float32)


def _error(params, *args) -> str:
    with pytest.raises(ValueError) as err:
        reconstruct(params, *args)
    assert "\n" not in str(err.value)
    return str(err.value)


@pytest.mark.parametrize("value", [1e20, -1e20, 3e38, 1e9])
def test_absurd_visible_values_are_refused(params, value):
    kp, vis = _inputs()
    kp[1, 4, 0] = value
    assert _error(params, kp, vis).startswith("kp of sample(s) [1]: the visible points lie up to ")
    assert _error(params, kp[1], vis[1]).startswith("kp of sample(s) [0]: the visible points")


def test_the_limit_is_in_normalised_units(params):
    kp, vis = _inputs(1)
    kp[0, 0] = kp[0, 1:].mean(0) + [0.5 * MAX_NORMALISED_EXTENT, 0]
    assert np.all(np.isfinite(reconstruct(params, kp, vis).shape_3d))  # large but legal
    small = C3DPOParams(params.variables, dataclasses.replace(CFG, keypoint_rescale=0.001))
    kp[0, 0] = kp[0, 1:].mean(0) + [3 * MAX_NORMALISED_EXTENT, 0]
    assert np.all(np.isfinite(reconstruct(small, kp, vis).shape_3d))  # x0.001: within
    assert "lie up to" in _error(params, kp, vis)


def test_non_finite_values_only_matter_where_visible(params):
    kp, vis = _inputs()
    vis[2, 5] = 0
    clean = reconstruct(params, kp, vis)
    for junk in (np.nan, np.inf, 1e30):
        kp2 = kp.copy()
        kp2[2, 5] = junk
        np.testing.assert_array_equal(reconstruct(params, kp2, vis).shape_3d, clean.shape_3d)
    kp[0, 3, 1] = np.nan
    assert _error(params, kp, vis) == "kp contains NaN or inf at visible points of sample(s) [0]"


def test_empty_and_ragged_input(params):
    assert _error(params, np.zeros((0, 7, 2)), np.zeros((0, 7))) == (
        "kp is an empty batch (B = 0): pass at least one sample"
    )
    assert _error(params, [[1.0, 2.0]] * 6 + [[3.0]], [1] * 7).startswith(
        "kp is not a numeric array (a ragged or non-numeric list?"
    )
    kp, vis = _inputs(1)
    assert _error(params, kp[0], [[1]] * 6 + [[1, 1]]).startswith("vis is not a numeric array")


def test_a_view_with_one_visible_point_is_lifted_with_a_warning(params, caplog):
    kp, vis = _inputs()
    vis[1] = 0
    vis[1, 4] = 1
    with caplog.at_level("WARNING"):
        out = reconstruct(params, kp, vis)
    assert np.all(np.isfinite(out.shape_3d))
    assert "sample(s) [1] have one visible keypoint" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        reconstruct(params, kp[[0, 2]], vis[[0, 2]])
    assert "visible keypoint" not in caplog.text
