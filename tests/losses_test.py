"""Pseudo-Huber and the masked reductions against numpy re-implementations; where the
objective lives."""

import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import procrustes_evidence

from c3dpo_jax import losses


def test_huber_matches_its_definition_and_is_zero_at_zero():
    d = np.array([0.0, 1e-6, 0.01, 1.0, 25.0])
    eps = 0.01
    expected = (np.sqrt(1 + d**2 / eps**2) - 1) * eps
    np.testing.assert_allclose(losses.huber(jnp.asarray(d**2), eps), expected, rtol=1e-5, atol=1e-9)
    assert float(losses.huber(jnp.zeros(()), eps)) == 0.0
    # Large residuals are penalised linearly, small ones quadratically.
    assert abs(float(losses.huber(jnp.asarray(100.0), eps)) - (10.0 - eps)) < 1e-3
    np.testing.assert_allclose(losses.huber(jnp.asarray(1e-8), eps), 1e-8 / (2 * eps), rtol=1e-3)


@pytest.mark.parametrize("normalization", ["kp_total_count", "kp_count_per_image"])
def test_reprojection_reduction_matches_numpy(normalization):
    rng = np.random.default_rng(0)
    err = rng.uniform(size=(4, 7))
    vis = (rng.uniform(size=(4, 7)) > 0.4).astype(float)
    vis[0] = 0  # an image with nothing visible must not produce NaN
    if normalization == "kp_total_count":
        expected = (err * vis).sum() / vis.sum()
    else:
        expected = np.mean([(e * v).sum() / max(v.sum(), 1) for e, v in zip(err, vis)])
    got = losses.reprojection(jnp.asarray(err), jnp.asarray(vis), normalization)
    np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_reprojection_ignores_invisible_points():
    err = jnp.array([[0.1, 0.2, 5.0]])
    vis = jnp.array([[1.0, 1.0, 0.0]])
    changed = err.at[0, 2].set(1e6)
    assert float(losses.reprojection(err, vis, "kp_total_count")) == float(
        losses.reprojection(changed, vis, "kp_total_count")
    )


def test_unknown_normalization_is_an_error():
    with pytest.raises(ValueError, match="kp_per_nothing"):
        losses.reprojection(jnp.ones((1, 2)), jnp.ones((1, 2)), "kp_per_nothing")


def test_canonicalisation_is_the_mean_and_zero_without_samples():
    c = jnp.array([[0.1, 0.3], [0.2, 0.4]])
    np.testing.assert_allclose(losses.canonicalisation(c), 0.25, rtol=1e-6)
    assert float(losses.canonicalisation(jnp.zeros((3, 0)))) == 0.0


def test_canonicalisation_per_sample_is_the_class_mean_of_the_penalty():
    rng = np.random.default_rng(2)
    d2 = rng.uniform(size=(3, 4, 6)) ** 3
    mask = (rng.uniform(size=(3, 6)) > 0.3).astype(float)
    mask[1] = 0  # an example with no point of its class: 0, not NaN
    eps = 0.05
    pen = (np.sqrt(1 + d2 / eps**2) - 1) * eps
    expected = (pen * mask[:, None]).sum(-1) / np.maximum(mask.sum(-1), 1)[:, None]
    got = losses.canonicalisation_per_sample(jnp.asarray(d2), jnp.asarray(mask), eps)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-8)


def test_loss_config_owns_the_penalty_and_checks_its_options():
    d2 = jnp.array([0.0, 1e-4, 4.0])
    np.testing.assert_allclose(losses.LossConfig(huber_scaling=0.1).penalty(d2),
                               losses.huber(d2, 0.1))
    np.testing.assert_array_equal(losses.LossConfig(squared_reprojection_loss=True).penalty(d2), d2)
    with pytest.raises(ValueError, match="reprojection_normalization 'per_nothing'"):
        losses.LossConfig(reprojection_normalization="per_nothing")


def test_the_objective_lives_here_and_stays_importable_from_train():
    import dataclasses

    from c3dpo_jax import model, train

    assert train.LossConfig is losses.LossConfig and train.make_loss_fn is losses.make_loss_fn
    loss_fields = {f.name for f in dataclasses.fields(losses.LossConfig)}
    model_fields = {f.name for f in dataclasses.fields(model.ModelConfig)}
    assert set(model.MOVED_TO_LOSS) <= loss_fields and not set(model.MOVED_TO_LOSS) & model_fields
    assert not hasattr(model, "huber")  # the model returns distances; the loss penalises them
    # A model section saved with the loss options (older runs, the release) still loads.
    legacy = dict(model.ModelConfig().to_dict(), huber_scaling=0.01,
                  reprojection_normalization="kp_total_count", squared_reprojection_loss=False)
    assert model.ModelConfig.from_dict(legacy) == model.ModelConfig()


def test_rotations_of_a_training_example_follow_the_model_config():
    import dataclasses

    import jax

    from c3dpo_jax import model

    cfg = model.ModelConfig(z_augment=True, z_augment_rot_angle=0.2, z_equivariance_rot_angle=0.1,
                            n_rand_samples=5)
    rots = jax.vmap(lambda k: losses.draw_rotations(k, cfg))(
        jax.random.split(jax.random.key(0), 200))
    for r2, limit in ((rots.augment, 0.2), (rots.equivariance, 0.1)):
        angles = np.arctan2(np.asarray(r2[:, 1, 0]), np.asarray(r2[:, 0, 0]))
        assert np.abs(angles).max() <= limit + 1e-6 and np.abs(angles).max() > 0.8 * limit
        np.testing.assert_allclose(np.einsum("bij,bkj->bik", r2, r2),
                                   np.tile(np.eye(2), (200, 1, 1)), atol=1e-5)
    psi = np.asarray(rots.canonicalisation)
    assert psi.shape == (200, 5, 3, 3)
    np.testing.assert_allclose(np.linalg.det(psi), 1.0, atol=1e-5)
    # Off: identities, and no rotation for Psi.
    off = losses.draw_rotations(jax.random.key(1), dataclasses.replace(
        cfg, z_augment=False, z_equivariance=False, canonicalization=False))
    np.testing.assert_array_equal(off.augment, np.eye(2))
    np.testing.assert_array_equal(off.equivariance, np.eye(2))
    assert off.canonicalisation.shape == (0, 3, 3)


def test_handedness_term_is_the_hinge_on_the_procrustes_evidence():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    mean = rng.normal(size=(9, 3)) * [1.0, 0.7, 0.4]
    rots = Rotation.random(6, random_state=1).as_matrix()
    shapes = np.einsum("mij,nj->mni", rots, mean) + 0.15 * rng.normal(size=(6, 9, 3))
    shapes[3:] *= np.array([1.0, 1.0, -1.0])  # three mirror images
    evidence = np.array([procrustes_evidence(x, mean) for x in shapes])
    assert np.all(evidence[:3] > 0.2) and np.all(evidence[3:] < -0.2)
    ones = np.ones((6, 9))
    for margin in (0.0, 0.5):
        got = losses.handedness(jnp.asarray(shapes, jnp.float32),
                                jnp.broadcast_to(jnp.asarray(mean, jnp.float32), shapes.shape),
                                jnp.asarray(ones), margin)
        np.testing.assert_allclose(got, np.mean(np.maximum(margin - evidence, 0.0)), rtol=1e-4)


def test_handedness_term_has_finite_gradients_at_the_mean_shape_itself():
    import jax

    mean = jnp.asarray(np.random.default_rng(2).normal(size=(7, 3)), jnp.float32)
    x = jnp.stack([mean, mean * jnp.array([[1.0, 1.0, -1.0]])])

    def loss(x):
        return losses.handedness(x, jnp.broadcast_to(mean, x.shape), jnp.ones((2, 7)), 0.1)

    grad = jax.grad(loss)(x)
    assert np.all(np.isfinite(np.asarray(grad))) and float(jnp.abs(grad[1]).sum()) > 0
    # The shape given is held fixed: no gradient reaches it.
    g_mean = jax.grad(lambda m: losses.handedness(x, jnp.broadcast_to(m, x.shape),
                                                  jnp.ones((2, 7)), 0.1))(mean)
    np.testing.assert_array_equal(np.asarray(g_mean), 0.0)


def _tetrahedra_evidence_numpy(x, ref, mask):
    """Independent of ``lift.local_handedness_evidence``: scipy's k-d tree finds each class
    point's three nearest class points in ``ref``; numpy's determinants of the corners."""
    from scipy.spatial import cKDTree

    inside = np.flatnonzero(mask > 0)
    _, near = cKDTree(ref[inside]).query(ref[inside], k=4)  # itself first
    num = den = 0.0
    for corner in inside[near]:
        def chirality(y):
            edges = y[corner[1:]] - y[corner[0]]
            return np.linalg.det(edges) / np.prod(np.linalg.norm(edges, axis=1))
        num += chirality(ref) * chirality(x)
        den += abs(chirality(ref))
    return num / den


def test_handedness_term_on_tetrahedra_is_the_hinge_on_their_chirality():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    mean = rng.normal(size=(11, 3)) * [1.0, 0.7, 0.4]
    mask = np.ones((6, 11))
    mask[:, 9:] = 0.0  # two points outside the class: in no tetrahedron
    rots = Rotation.random(6, random_state=2).as_matrix()
    shapes = 1.7 * np.einsum("mij,nj->mni", rots, mean) + 0.1 * rng.normal(size=(6, 11, 3))
    shapes[3:] *= np.array([1.0, 1.0, -1.0])  # three mirror images
    evidence = np.array([_tetrahedra_evidence_numpy(x, mean, m) for x, m in zip(shapes, mask)])
    assert np.all(evidence[:3] > 0.2) and np.all(evidence[3:] < -0.2)
    # The points outside the class do not count: moving them changes nothing.
    moved = shapes.copy()
    moved[:, 9:] += 5.0
    for margin in (0.0, 0.5):
        for x in (shapes, moved):
            got = losses.handedness(jnp.asarray(x, jnp.float32),
                                    jnp.broadcast_to(jnp.asarray(mean, jnp.float32), x.shape),
                                    jnp.asarray(mask), margin, "tetrahedra")
            np.testing.assert_allclose(got, np.mean(np.maximum(margin - evidence, 0.0)),
                                       rtol=1e-4)


def test_views_mean_is_each_point_s_mean_over_the_examples_that_have_it():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(4, 6, 3))
    mask = np.ones((4, 6))
    mask[:2, 4:] = 0.0  # the first two examples' class lacks the last two points
    got = np.asarray(losses.views_mean(jnp.asarray(x), jnp.asarray(mask)))
    np.testing.assert_allclose(got[:4], x[:, :4].mean(0), rtol=1e-5)
    np.testing.assert_allclose(got[4:], x[2:, 4:].mean(0), rtol=1e-5)


@pytest.mark.parametrize("field, value", [("handedness_evidence", "chirality"),
                                          ("handedness_prototype", "median")])
def test_an_unknown_handedness_setting_is_refused_in_one_line(field, value):
    with pytest.raises(ValueError, match=rf"^unknown {field} '{value}'; known: \("):
        losses.LossConfig(**{field: value})
