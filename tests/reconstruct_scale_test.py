"""reconstruct warns, in one line, about keypoints far from the training data's scale."""

import jax
import numpy as np
import pytest
from absl import logging

from c3dpo_jax import model
from c3dpo_jax.data import auto_keypoint_rescale, synthetic
from c3dpo_jax.reconstruct import C3DPOParams, reconstruct

DATA = synthetic.make_split(6, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.2,
                            noise=0.0, perspective=False, shape_seed=0, seed=1)


@pytest.fixture(scope="module")
def params():
    """A model whose input scale is set from DATA in metres, as training sets it."""
    cfg = model.ModelConfig(n_keypoints=8, shape_basis_size=2, n_fully_connected=16, n_layers=1,
                            canonicalization_n_fully_connected=16, canonicalization_n_layers=1,
                            keypoint_rescale=auto_keypoint_rescale(DATA))
    return C3DPOParams(model.init_variables(jax.random.key(0), cfg), cfg)


@pytest.mark.parametrize(("factor", "warned"), [(1.0, None), (2.5, None), (0.5, None),
                                                (100.0, "100x"), (0.1, "0.1x")])
def test_a_warning_names_how_far_the_scale_is_from_the_training_data(
        params, monkeypatch, factor, warned):
    messages = []
    monkeypatch.setattr(logging, "warning", lambda msg, *args: messages.append(msg % args))
    reconstruct(params, DATA.kp * factor, DATA.vis)
    if warned is None:
        assert messages == []
    else:
        (line,) = messages
        assert f"spread is {warned} the training data's" in line and "\n" not in line
    messages.clear()
    reconstruct(params, DATA.kp[0] * factor, DATA.vis[0])  # one sample: its own spread
    assert len(messages) == (warned is not None)


def test_views_whose_visible_points_coincide_are_named_not_blamed_on_units(params, monkeypatch):
    messages = []
    monkeypatch.setattr(logging, "warning", lambda msg, *args: messages.append(msg % args))
    coincide = ("kp of sample(s) {}: the visible points coincide (all at one place), so the "
                "view shows no shape; its 3D shape is the model's guess")
    # 0.1 three times has a mean of 0.10000000000000002: no spread all the same.
    reconstruct(params, np.full_like(DATA.kp, 0.1), DATA.vis)
    assert messages == [coincide.format(list(range(len(DATA.kp))))]  # no scale to compare
    messages.clear()
    kp = DATA.kp.copy()
    kp[:2] = 0.1
    reconstruct(params, kp, DATA.vis)
    assert messages == [coincide.format([0, 1])]  # the other views' scale is the training's
