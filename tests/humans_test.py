"""Synthetic humans: skeleton order, reproducibility, occlusion, views, proportions."""

import numpy as np
import pytest

from c3dpo_jax.data import humans

H36M_SKELETON = [[10, 9], [9, 8], [8, 14], [14, 15], [15, 16], [8, 11], [11, 12], [12, 13],
                 [8, 7], [7, 0], [1, 0], [1, 2], [2, 3], [0, 4], [4, 5], [5, 6]]


def test_kinematic_tree_is_the_h36m_skeleton():
    bones = {tuple(sorted((j, p))) for j, p in enumerate(humans.PARENTS) if p >= 0}
    assert bones == {tuple(sorted(b)) for b in H36M_SKELETON}


def test_splits_are_reproducible_and_sized():
    a, _ = humans.make_splits(3, 2, views_per_pose=4, dense_points=20, seed=5)
    b, test = humans.make_splits(3, 2, views_per_pose=4, dense_points=20, seed=5)
    np.testing.assert_array_equal(a.kp, b.kp)
    assert a.kp.shape == (12, 37, 2) and a.kp3d.shape == (12, 37, 3) and len(test) == 8
    c, _ = humans.make_splits(3, 2, views_per_pose=4, dense_points=20, seed=6)
    assert not np.allclose(a.kp3d, c.kp3d)


def test_views_of_one_pose_are_rotations_of_one_shape_and_bodies_are_human_sized():
    data = humans.make_split(5, views_per_pose=6, self_occlusion=False, seed=0)
    x = data.kp3d.reshape(5, 6, 17, 3)
    dist = np.linalg.norm(x[:, :, :, None] - x[:, :, None], axis=-1)
    np.testing.assert_allclose(dist, np.broadcast_to(dist[:, :1], dist.shape), atol=1e-4)
    thigh = dist[:, 0, 1, 2]
    assert np.all((thigh > 0.3) & (thigh < 0.6))
    assert data.vis.min() == 1.0  # no occlusion asked for
    np.testing.assert_allclose(data.kp, data.kp3d[..., :2], atol=1e-6)


def test_self_occlusion_hides_points_behind_the_body():
    data = humans.make_split(20, views_per_pose=8, dense_points=100, seed=1)
    joints, surface = data.vis[:, :17].mean(), data.vis[:, 17:].mean()
    assert 0.6 < joints < 0.97  # most joints are seen, some are hidden
    assert 0.3 < surface < 0.7  # about the back half of every capsule is hidden
    assert np.all(data.kp[data.vis == 0] == 0)  # invisible points are zeroed


def test_a_point_behind_a_sphere_is_hidden_and_one_in_front_is_not():
    centres = np.zeros((1, 1, 3))
    points = np.array([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.5, 0.0, 1.0]]])
    vis = humans.occlusion_visibility(points, centres, np.array([0.2]), np.zeros((3, 1), bool))
    assert vis.tolist() == [[0.0, 1.0, 1.0]]  # the camera looks along +z


def _bone_lengths(data, n_poses, views):
    x = data.kp3d.reshape(n_poses, views, 17, 3)[:, 0]
    parents = np.array(humans.PARENTS[1:])
    return np.linalg.norm(x[:, 1:] - x[:, parents], axis=-1)  # (P, 16)


def test_proportions_spread_sets_how_much_bodies_differ():
    same = _bone_lengths(humans.make_split(6, views_per_pose=2, self_occlusion=False,
                                           proportions=0.0, seed=2), 6, 2)
    np.testing.assert_allclose(same, np.broadcast_to(same[:1], same.shape), atol=1e-5)
    spreads = [np.std(_bone_lengths(humans.make_split(
        200, views_per_pose=1, self_occlusion=False, proportions=p, seed=2), 200, 1) / same[0],
        axis=0).mean() for p in (0.5, 1.0)]
    assert 0 < spreads[0] < spreads[1]  # relative bone-length spread grows with it
    assert 0.04 < spreads[1] < 0.15  # height +-15% and limbs +-10% (uniform)
    with pytest.raises(ValueError, match="proportions spread must be in"):
        humans.make_split(2, views_per_pose=1, proportions=-0.5)


def test_coco_order_keeps_the_limbs_and_puts_a_face_on_the_front_of_the_head():
    """``coco_from_h36m``: COCO's shoulders to ankles are the same joints (left before
    right); the nose is in front of the neck, above it, between the eyes, the left eye and
    ear on the body's left; a rotated and shifted body gets the rotated and shifted points
    (checked with scipy's rotations), a mirrored one the mirrored face; the face points
    are shown where the head is."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    pos, _ = humans.forward_kinematics(humans.random_proportions(rng, 6),
                                       np.zeros((6, 17, 3)))  # rest: y up, facing +z, left +x
    coco = humans.coco_from_h36m(pos)
    assert coco.shape == (6, 17, 3) and len(humans.COCO_JOINT_NAMES) == 17
    names = dict(zip(humans.JOINT_NAMES, range(17)))
    for i, name in enumerate(humans.COCO_JOINT_NAMES[5:], start=5):
        np.testing.assert_array_equal(coco[:, i], pos[:, names[name]])
    nose, l_eye, r_eye, l_ear, r_ear = (coco[:, i] for i in range(5))
    neck = pos[:, names["neck"]]
    assert np.all(nose[:, 2] > neck[:, 2] + 0.05) and np.all(nose[:, 1] > neck[:, 1])
    assert np.all(l_eye[:, 0] > nose[:, 0]) and np.all(r_eye[:, 0] < nose[:, 0])
    assert np.all(l_ear[:, 0] > l_eye[:, 0]) and np.all(r_ear[:, 0] < r_eye[:, 0])
    rot = Rotation.random(6, random_state=1).as_matrix()
    shift = rng.normal(size=(6, 1, 3))
    np.testing.assert_allclose(
        humans.coco_from_h36m(np.einsum("pij,pnj->pni", rot, pos) + shift),
        np.einsum("pij,pnj->pni", rot, coco) + shift, atol=1e-12)
    swap = [0, 4, 5, 6, 1, 2, 3, 7, 8, 9, 10, 14, 15, 16, 11, 12, 13]  # left <-> right
    vis = np.ones((6, 17))
    vis[:, [10, 13]] = 0  # the head and the left wrist hidden
    got = humans.coco_visibility_from_h36m(vis)
    assert got[:, :5].sum() == 0 and got[:, humans.COCO_JOINT_NAMES.index("l_wrist")].sum() == 0
    assert got.sum() == 6 * 11
    mirrored = humans.coco_from_h36m(pos[:, swap] * [-1, 1, 1])
    np.testing.assert_allclose(mirrored[:, [0, 2, 1, 4, 3]], coco[:, :5] * [-1, 1, 1],
                               atol=1e-12)


def test_average_bodies_of_both_orders_are_one_body():
    """``mean_pose(order="coco")`` is the COCO order of the same people's average (the
    limbs' joints are the h36m body's); an unknown order is refused."""
    h36m, coco = humans.mean_pose(n=200), humans.mean_pose(n=200, order="coco")
    assert h36m.shape == coco.shape == (17, 3)
    np.testing.assert_allclose(coco.mean(0), 0, atol=1e-12)
    limbs = coco[5:] - coco[5:].mean(0)
    same = h36m[[11, 14, 12, 15, 13, 16, 4, 1, 5, 2, 6, 3]]
    np.testing.assert_allclose(limbs, same - same.mean(0), atol=1e-12)
    with pytest.raises(ValueError, match="unknown joint order 'openpose'"):
        humans.mean_pose(order="openpose")
