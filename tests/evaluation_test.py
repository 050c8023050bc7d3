"""Evaluation protocol against brute-force numpy loops and known answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from c3dpo_jax import evaluation
from c3dpo_jax.data import KeypointData


def _data(gt, **kw):
    m, n, _ = gt.shape
    return KeypointData(kp=gt[..., :2].copy(), vis=np.ones((m, n)), kp3d=gt, **kw)


def _loop_mpjpe(pred, gt):
    return np.mean([np.linalg.norm(p - g) for p, g in zip(pred, gt)])


def _loop_stress(pred, gt):
    n = len(pred)
    vals = [abs(np.linalg.norm(pred[i] - pred[j]) - np.linalg.norm(gt[i] - gt[j]))
            for i in range(n) for j in range(i + 1, n)]
    return np.mean(vals)


def test_mpjpe_flip_and_stress_match_brute_force():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(5, 6, 3))
    pred = gt * np.array([1, 1, -1]) + 0.1 * rng.normal(size=gt.shape)
    res = evaluation.evaluate(pred, _data(gt), "default")
    gt_c = evaluation.center_depth(gt, np.ones((5, 6)))
    pred_c = evaluation.center_depth(pred, np.ones((5, 6)))
    orig = [_loop_mpjpe(p, g) for p, g in zip(pred_c, gt_c)]
    flip = [_loop_mpjpe(p * [1, 1, -1], g) for p, g in zip(pred_c, gt_c)]
    np.testing.assert_allclose(res["mpjpe_orig"], np.mean(orig))
    np.testing.assert_allclose(res["mpjpe_flip"], np.mean(flip))
    np.testing.assert_allclose(res["mpjpe"], np.mean(np.minimum(orig, flip)))
    assert res["mpjpe"] < res["mpjpe_orig"]  # the flipped prediction is the better one
    np.testing.assert_allclose(
        res["stress"], np.mean([_loop_stress(p, g) for p, g in zip(pred_c, gt_c)])
    )


def test_stress_is_the_per_sample_brute_force_over_the_pairs_the_mask_keeps():
    rng = np.random.default_rng(3)
    gt, pred = rng.normal(size=(2, 7, 9, 3))
    mask = (rng.uniform(size=(7, 9)) > 0.3).astype(float)
    mask[0] = 1.0  # every point
    mask[1, 1:] = 0.0  # one point: no pair, stress 0
    expected = [_loop_stress(p[m > 0], g[m > 0]) if m.sum() >= 2 else 0.0
                for p, g, m in zip(pred, gt, mask)]
    np.testing.assert_allclose(evaluation.stress(pred, gt, mask), expected, rtol=1e-12)
    assert evaluation.stress(pred, gt, mask)[1] == 0.0


def test_known_answer_depth_offset_is_ignored_and_shift_is_not():
    gt = np.zeros((1, 2, 3))
    gt[0, 1] = [1, 0, 0]
    pred = gt + np.array([0.0, 0.0, 7.0])  # a pure depth offset: removed by the protocol
    assert evaluation.evaluate(pred, _data(gt))["mpjpe"] == pytest.approx(0.0)
    pred = gt + np.array([0.3, 0.4, 0.0])  # an xy shift of length 0.5
    assert evaluation.evaluate(pred, _data(gt))["mpjpe"] == pytest.approx(0.5)
    assert evaluation.evaluate(pred, _data(gt))["stress"] == pytest.approx(0.0)


def test_h36m_protocol_is_root_relative_scaled_and_averaged_per_action():
    gt = np.zeros((3, 2, 3))
    gt[:, 1] = [1, 0, 0]
    pred = gt.copy()
    pred[:, 1, 0] += np.array(
        [0.1, 0.2, 0.6]
    )  # per-sample errors 0.05, 0.1, 0.3 (mean over 2 joints)
    pred += 5.0  # a global offset: removed by the root alignment
    data = _data(gt, scale=np.array([10.0, 10.0, 10.0]), group=np.array([0, 0, 1]),
                 group_names=("Walking", "Sitting"))
    res = evaluation.evaluate(pred, data, "h36m")
    np.testing.assert_allclose(res["per_group"]["Walking"], 0.75)
    np.testing.assert_allclose(res["per_group"]["Sitting"], 3.0)
    np.testing.assert_allclose(res["mpjpe"], (0.75 + 3.0) / 2)


def test_pascal3d_protocol_masks_points_outside_the_class():
    gt = np.zeros((1, 3, 3))
    gt[0, 1] = [1, 0, 0]
    pred = gt.copy()
    pred[0, 2] = [100, 100, 100]  # garbage on a point of another class
    data = _data(
        gt, class_mask=np.array([[1.0, 1.0, 0.0]]), group=np.array([0]), group_names=("car",)
    )
    assert evaluation.evaluate(pred, data, "pascal3d")["mpjpe"] == pytest.approx(0.0)


def test_missing_ground_truth_and_unknown_protocol_are_clear_errors():
    data = KeypointData(kp=np.zeros((1, 2, 2)), vis=np.ones((1, 2)))
    with pytest.raises(ValueError, match="no 3D ground truth"):
        evaluation.evaluate(np.zeros((1, 2, 3)), data)
    with pytest.raises(ValueError, match="protocol"):
        evaluation.evaluate(np.zeros((1, 2, 3)), _data(np.zeros((1, 2, 3))), "nope")


def test_reprojection_error_counts_visible_points_only():
    data = KeypointData(kp=np.zeros((1, 3, 2)), vis=np.array([[1.0, 1.0, 0.0]]))
    reproj = np.array([[[3.0, 4.0], [0.0, 1.0], [100.0, 100.0]]])
    assert evaluation.reprojection_error(reproj, data) == pytest.approx(3.0)


def test_table_marks_missing_metrics():
    table = evaluation.format_table({"a": {"mpjpe": 1.0, "reprojection": 2.0}, "b": {"mpjpe": 3.0}})
    assert "reprojection" in table and table.splitlines()[2].rstrip().endswith("-")


def test_table_columns_keep_their_width_and_tiny_values_their_digits():
    table = evaluation.format_table({"a": {"mpjpe": 1.8e9, "stress": 0.25},
                                     "b": {"mpjpe": 1.234e-5, "stress": 0.0}})
    header, a, b = table.splitlines()
    assert len(a) == len(b) == len(header)
    assert a.split()[1:] == ["1.800e+09", "0.2500"] and b.split()[1:] == ["1.234e-05", "0.0000"]


def test_errors_of_visible_and_hidden_points_are_split_after_the_flip():
    rng = np.random.default_rng(4)
    gt = rng.normal(size=(3, 5, 3))
    vis = np.ones((3, 5))
    vis[:, [1, 3]] = 0.0
    data = KeypointData(kp=gt[..., :2] * vis[..., None], vis=vis, kp3d=gt)
    pred = gt * np.array([1.0, 1.0, -1.0])  # every sample depth-flipped: the flip undoes it
    pred[:, 1] += [0.3, 0.0, 0.0]  # errors on hidden point 1 only (0.3, then 0 elsewhere)
    pred[0, 0] += [0.0, 0.4, 0.0]  # and on visible point 0 of sample 0
    pred = pred + np.array([0.0, 0.0, 2.0])  # a depth offset is removed first
    out = evaluation.mpjpe_by_visibility(pred, data)
    # Hidden: 3 samples x points {1, 3} -> 0.3 x 3 over 6; visible: 0.4 once over 9.
    assert out["mpjpe_hidden"] == pytest.approx(0.3 * 3 / 6)
    assert out["mpjpe_visible"] == pytest.approx(0.4 / 9)
    assert evaluation.mpjpe_by_visibility(gt, _data(gt)) == {}


def _rotations(rng, m):
    q = rng.normal(size=(m, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Rotation.from_quat(q).as_matrix()


def test_mirrored_fraction_counts_the_views_of_the_other_handedness():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(12, 3))  # a generic (chiral) point set
    m = 40
    shapes = base + 0.02 * rng.normal(size=(m, 12, 3))  # small deformations
    shapes = np.einsum("mij,mnj->mni", _rotations(rng, m), shapes)  # any orientation
    assert evaluation.mirrored_fraction(shapes) == 0.0
    flip = np.zeros(m, bool)
    flip[rng.choice(m, 10, replace=False)] = True
    # A reflection through any plane, then a rotation: the mirror image of the shape.
    mixed = np.where(flip[:, None, None], shapes * np.array([-1.0, 1.0, 1.0]), shapes)
    mixed = np.einsum("mij,mnj->mni", _rotations(rng, m), mixed)
    got = evaluation.mirrored_fraction(mixed)
    assert got in (10 / 40, 30 / 40)  # which handedness is the majority's is arbitrary
    assert evaluation.mirrored_fraction(mixed[~flip]) == 0.0


def test_mpjpe_global_is_the_split_as_it_is_or_all_mirrored_not_per_view():
    rng = np.random.default_rng(5)
    gt = rng.normal(size=(6, 8, 3))
    flip = np.array([1.0, 1.0, -1.0])
    mixed = gt.copy()
    mixed[:2] *= flip  # two views of six mirrored: the protocol's per-view flip hides them
    res = evaluation.evaluate(mixed, _data(gt), "default")
    gt_c = evaluation.center_depth(gt, np.ones((6, 8)))
    pred_c = evaluation.center_depth(mixed, np.ones((6, 8)))
    as_is = np.mean([_loop_mpjpe(p, g) for p, g in zip(pred_c, gt_c)])
    all_flipped = np.mean([_loop_mpjpe(p * flip, g) for p, g in zip(pred_c, gt_c)])
    np.testing.assert_allclose(res["mpjpe_global"], min(as_is, all_flipped))
    assert res["mpjpe"] < 1e-12 < res["mpjpe_global"]
    # Every view mirrored: one flip of the whole split undoes it.
    res = evaluation.evaluate(gt * flip, _data(gt), "default")
    assert res["mpjpe_global"] < 1e-12 and res["mpjpe_orig"] > 0.1
