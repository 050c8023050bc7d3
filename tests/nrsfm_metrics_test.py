"""NRSfM metrics against hand-worked values (an octahedron scaled, mirrored, rotated) and
against scipy's rotation alignment and numpy's std on random shapes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from c3dpo_jax import nrsfm_metrics as nm

# Two frames: the unit octahedron and the same at twice the size. Per frame the points are
# centred and every coordinate has std sqrt(2/6) = 1/sqrt(3) times the size, so
# sigma = (3/sqrt(3) + 6/sqrt(3)) / 6 = sqrt(3)/2.
OCTAHEDRON = np.concatenate([np.eye(3), -np.eye(3)])
GT = np.stack([OCTAHEDRON, 2 * OCTAHEDRON]) + np.array([[[5.0, -1.0, 3.0]], [[0.0, 2.0, 7.0]]])
CENTRED = GT - GT.mean(1, keepdims=True)
QUARTER_TURN = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # x -> y, y -> -x
ALL = nm.ALIGNMENTS


@pytest.mark.parametrize("align", ALL)
def test_a_reconstruction_ten_percent_too_large(align):
    pred = GT.mean(1, keepdims=True) + 1.1 * CENTRED + np.array([1.0, 2.0, 3.0])
    # Point errors 0.1 and 0.2 (mean 0.15), divided by sigma = sqrt(3)/2: 0.1 sqrt(3).
    assert nm.e3d(pred, GT, align=align) == pytest.approx(0.1 * np.sqrt(3), rel=1e-12)
    np.testing.assert_allclose(nm.relative_error(pred, GT, align=align), [0.1, 0.1], rtol=1e-12)


@pytest.mark.parametrize("align", ALL)
def test_a_mirror_image_in_depth(align):
    pred = GT * np.array([1.0, 1.0, -1.0])
    # Unaligned: the two points on the z axis swap (errors 2 and 4 at 1 and 2 of 6 points of
    # each frame, mean 1), e3D = 1 / (sqrt(3)/2); relative: sqrt(2 * 2^2) / sqrt(6) per frame.
    want_e3d, want_rel = (2 / np.sqrt(3), 2 / np.sqrt(3)) if align == "none" else (0.0, 0.0)
    assert nm.e3d(pred, GT, align=align) == pytest.approx(want_e3d, rel=1e-12, abs=1e-12)
    np.testing.assert_allclose(nm.relative_error(pred, GT, align=align), [want_rel] * 2,
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("align", ALL)
def test_a_quarter_turn_about_the_optical_axis(align):
    pred = CENTRED @ QUARTER_TURN.T
    # Four of six points move by sqrt(2) times the size: mean error sqrt(2), e3D = 2 sqrt(2/3);
    # relative sqrt(4 * 2) / sqrt(6). A depth flip does not help; a rotation undoes it.
    rotated = align in ("sequence", "frame")
    want_e3d, want_rel = (0.0, 0.0) if rotated else (2 * np.sqrt(2 / 3), 2 / np.sqrt(3))
    assert nm.e3d(pred, GT, align=align) == pytest.approx(want_e3d, rel=1e-12, abs=1e-12)
    np.testing.assert_allclose(nm.relative_error(pred, GT, align=align), [want_rel] * 2,
                               rtol=1e-12, atol=1e-12)


def test_one_rotation_per_sequence_against_scipy_and_numpy():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(6, 9, 3)) * [1.0, 0.6, 0.4] + rng.normal(size=(6, 1, 3))
    turn = Rotation.random(random_state=1).as_matrix()
    pred = (gt + 0.1 * rng.normal(size=gt.shape)) @ turn.T
    pred[::2] = pred[::2] @ Rotation.from_euler("y", 20, degrees=True).as_matrix().T
    p = pred - pred.mean(1, keepdims=True)
    g = gt - gt.mean(1, keepdims=True)
    sigma = np.std(g, axis=1).sum(1).mean() / 3
    best = np.inf  # the best rotation of pred or of its mirror image, pooled over frames
    for mirror in (1.0, -1.0):
        q = p * [1.0, 1.0, mirror]
        rot, _ = Rotation.align_vectors(g.reshape(-1, 3), q.reshape(-1, 3))
        err = np.linalg.norm(rot.apply(q.reshape(-1, 3)) - g.reshape(-1, 3), axis=1)
        if (err**2).sum() < best:
            best, want = (err**2).sum(), err.mean() / sigma
    assert nm.e3d(pred, gt) == pytest.approx(want, rel=1e-10)
    assert 0 < nm.e3d(pred, gt, align="frame") < nm.e3d(pred, gt) < nm.e3d(pred, gt, align="none")
    per_frame = [np.linalg.norm(Rotation.align_vectors(g[m], p[m])[0].apply(p[m]) - g[m])
                 / np.linalg.norm(g[m]) for m in range(6)]  # frames never mirrored here
    np.testing.assert_allclose(nm.relative_error(pred, gt, align="frame"), per_frame, rtol=1e-9)


def test_points_outside_the_mask_change_nothing():
    rng = np.random.default_rng(2)
    gt, pred = rng.normal(size=(2, 5, 8, 3))
    mask = np.ones((5, 8))
    mask[:, 6:] = 0
    junk = pred.copy()
    junk[:, 6:] = 1e6
    for align in ALL:
        want = nm.e3d(pred[:, :6], gt[:, :6], align=align)
        assert nm.e3d(junk, gt, mask, align) == pytest.approx(want, rel=1e-12)
        np.testing.assert_allclose(nm.relative_error(junk, gt, mask, align),
                                   nm.relative_error(pred[:, :6], gt[:, :6], align=align),
                                   rtol=1e-12)
    scores = nm.scores(pred, gt)
    assert scores["e3d/flip"] == nm.e3d(pred, gt, align="flip") and len(scores) == 4


@pytest.mark.parametrize("args, message", [
    ((np.zeros((2, 4, 3)), np.zeros((2, 5, 3))), r"pred \(2, 4, 3\) and gt \(2, 5, 3\)"),
    ((np.zeros((2, 4, 2)), np.zeros((2, 4, 2))), "must both be"),
    ((GT, GT, np.ones((2, 5))), r"mask has shape \(2, 5\), expected \(2, 6\)"),
    ((GT, GT, None, "procrustes"), "unknown alignment 'procrustes'"),
])
def test_bad_inputs_are_one_line_errors(args, message):
    with pytest.raises(ValueError, match=message):
        nm.e3d(*args)
