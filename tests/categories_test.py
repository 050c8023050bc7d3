"""Synthetic object categories: packed multi-class layout, masks, groups, variation."""

import numpy as np

from c3dpo_jax.data import categories


def test_packed_layout_masks_and_groups():
    train, test = categories.make_splits(200, 50, seed=3)
    n = categories.n_keypoints()
    assert train.kp.shape == (200, n, 2) and n == 45 and len(test) == 50
    assert train.group_names == tuple(categories.CLASSES)
    starts = np.cumsum([0] + [k for _, k in categories.CLASSES.values()])
    for i in range(20):
        c = train.group[i]
        expected = np.zeros(n)
        expected[starts[c]:starts[c + 1]] = 1
        np.testing.assert_array_equal(train.class_mask[i], expected)
    assert np.all(train.vis <= train.class_mask) and np.all(train.vis.sum(1) >= 3)
    assert np.all(train.kp3d[train.class_mask == 0] == 0)
    np.testing.assert_array_equal(train.kp_defined, train.class_mask)


def test_shapes_vary_within_a_class_and_runs_are_reproducible():
    a = categories.make_split(100, classes=("car",), occlusion=0.0, seed=0)
    b = categories.make_split(100, classes=("car",), occlusion=0.0, seed=0)
    np.testing.assert_array_equal(a.kp, b.kp)
    d = np.linalg.norm(a.kp3d[:, :, None] - a.kp3d[:, None], axis=-1)  # rotation invariant
    assert d.std(0).max() > 0.05  # instances differ
    assert a.group_names == ("car",) and a.n_keypoints == 12
