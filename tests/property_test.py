"""Property-based tests (hypothesis) of the numerical core and the inputs' gates.

Each property is checked against an independent computation (scipy's rotations, float64
numpy formulas) or against an invariance the code must have, over values hypothesis draws:
rotations at 0 and pi, squared distances from 0 to 1e30, hidden points holding inf, NaN or
1e30, keypoints at scales from 1e-3 to 1e6, malformed JSON entries. The profile in
conftest.py makes the draws derandomised (the same examples on every run).
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation

from c3dpo_jax import geometry, losses, model, so3
from c3dpo_jax.data import json_dataset
from c3dpo_jax.losses import huber
from c3dpo_jax.reconstruct import C3DPOParams, reconstruct

finite = st.floats(-1e3, 1e3, allow_nan=False, width=32)
junk = st.sampled_from([np.inf, -np.inf, np.nan, 1e30, -3e38])

exp_map = jax.jit(so3.exp_map)
log_map = jax.jit(so3.log_map)
exp_jacobian = jax.jit(jax.jacfwd(so3.exp_map))


# ---- so3 -------------------------------------------------------------------------------

rotation_vectors = hnp.arrays(np.float64, 3, elements=st.floats(-7.0, 7.0))


@given(rotation_vectors)
@example(np.zeros(3))
@example(np.array([np.pi, 0.0, 0.0]))
@example(np.array([0.0, 0.0, -np.pi]))
@example(np.array([1e-9, -2e-9, 0.0]))
@example(np.array([1e-3, 0.0, 2e-3]))  # just above the Taylor branch's switch
def test_exp_map_is_scipys_rotation_and_orthonormal(w):
    r = np.asarray(exp_map(jnp.asarray(w, jnp.float32)), np.float64)
    np.testing.assert_allclose(r, Rotation.from_rotvec(w).as_matrix(), atol=2e-6)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=2e-6)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=2e-6)
    assert np.isfinite(np.asarray(exp_jacobian(jnp.asarray(w, jnp.float32)))).all()


quaternions = hnp.arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(
    lambda q: np.linalg.norm(q) > 1e-3)


@given(quaternions)
@example(np.array([0.0, 0.0, 0.0, 1.0]))  # identity (scipy's scalar-last order)
@example(np.array([1.0, 0.0, 0.0, 0.0]))  # a half turn about x
@example(np.array([0.0, 1.0, 1.0, 0.0]))  # a half turn about a diagonal
@example(np.array([1.0, 0.0, 0.0, 1e-4]))  # just short of a half turn
def test_log_map_inverts_exp_map_up_to_pi(q):
    rot = Rotation.from_quat(q)
    w = np.asarray(log_map(jnp.asarray(rot.as_matrix(), jnp.float32)), np.float64)
    assert np.linalg.norm(w) <= np.pi + 1e-5
    # Compared through the rotation it encodes: at a half turn w and -w are both right.
    np.testing.assert_allclose(Rotation.from_rotvec(w).as_matrix(), rot.as_matrix(), atol=2e-5)
    if np.linalg.norm(rot.as_rotvec()) < np.pi - 1e-2:
        np.testing.assert_allclose(w, rot.as_rotvec(), atol=2e-5)


# ---- the penalty and the loss reductions -------------------------------------------------

@given(st.floats(0.0, 1e30), st.floats(1e-3, 1e3))
@example(0.0, 0.01)
@example(1e-30, 0.01)
@example(1e30, 1e-3)
def test_pseudo_huber_matches_its_float64_formula(d2, eps):
    value, grad = jax.value_and_grad(huber)(jnp.float32(d2), eps)
    d2_32 = float(np.float32(d2))  # the input as float32 holds it
    # sqrt(1 + x) - 1 as expm1(log1p(x) / 2): accurate in float64 down to x ~ 1e-300.
    expected = eps * math.expm1(0.5 * math.log1p(d2_32 / eps**2))
    # abs: XLA on CPU flushes float32 subnormals (d2 < 1.2e-38) to zero.
    assert float(value) == pytest.approx(expected, rel=1e-5, abs=1e-30)
    expected_grad = 0.5 / (eps * np.sqrt(1.0 + d2_32 / eps**2))  # d/d(d2) of the formula
    assert float(grad) == pytest.approx(expected_grad, rel=1e-4)
    assert np.isfinite(float(grad)) and float(grad) > 0


B, N = 4, 6
batches = st.tuples(
    hnp.arrays(np.float32, (B, N), elements=st.floats(0.0, 1e3, width=32)),
    hnp.arrays(np.float32, (B, N), elements=st.sampled_from([0.0, 1.0])),
    hnp.arrays(np.float32, (B, N), elements=junk),
)


@given(batches)
def test_reprojection_reductions_are_masked_means_that_ignore_hidden_values(batch):
    repro, vis, garbage = batch
    dirty = np.where(vis > 0, repro, garbage)
    total = losses.reprojection(jnp.asarray(dirty), jnp.asarray(vis), "kp_total_count")
    per_image = losses.reprojection(jnp.asarray(dirty), jnp.asarray(vis), "kp_count_per_image")
    r64, v64 = repro.astype(np.float64), vis.astype(np.float64)
    expected_total = (r64 * v64).sum() / max(v64.sum(), 1.0)
    expected_per_image = np.mean((r64 * v64).sum(1) / np.maximum(v64.sum(1), 1.0))
    assert float(total) == pytest.approx(expected_total, rel=1e-5, abs=1e-6)
    assert float(per_image) == pytest.approx(expected_per_image, rel=1e-5, abs=1e-6)


# ---- geometry ------------------------------------------------------------------------------

@given(hnp.arrays(np.float64, (N, 2), elements=st.floats(-1e3, 1e3)),
       hnp.arrays(np.float64, N, elements=st.sampled_from([0.0, 1.0])).filter(
           lambda v: v.sum() >= 1),
       st.floats(1e-3, 1e3), hnp.arrays(np.float64, 2, elements=st.floats(-1e4, 1e4)),
       junk)
def test_normalised_keypoints_forget_position_scale_and_hidden_values(kp, vis, scale, shift,
                                                                      garbage):
    def visible_normalised(points):
        points = np.where(vis[:, None] > 0, points, garbage)
        out, _ = geometry.normalise_keypoints(jnp.asarray(points, jnp.float32),
                                              jnp.asarray(vis, jnp.float32),
                                              norm_type="to_mean", rescale=1.0)
        return np.asarray(out, np.float64)[vis > 0]

    base = visible_normalised(kp)
    expected = kp[vis > 0] - kp[vis > 0].mean(0)  # numpy's mean of the visible points
    np.testing.assert_allclose(base, expected, rtol=1e-4, atol=1e-3)
    moved = visible_normalised(kp * scale + shift)
    np.testing.assert_allclose(moved, base * scale, rtol=1e-3, atol=2e-3 * max(scale, 1.0))


# ---- reconstruct ---------------------------------------------------------------------------

CFG = model.ModelConfig(n_keypoints=N, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1)


@pytest.fixture(scope="module")
def params():
    return C3DPOParams(model.init_variables(jax.random.key(5), CFG), CFG)


views = st.tuples(
    hnp.arrays(np.float64, (2, N, 2), elements=st.floats(-1.0, 1.0)),
    hnp.arrays(np.float64, (2, N), elements=st.sampled_from([0.0, 1.0])),
    st.floats(-3.0, 6.0),  # log10 of the keypoints' scale
    hnp.arrays(np.float64, (2, N, 2), elements=junk),
)


@given(views)
def test_reconstruct_gives_finite_shapes_or_one_line_error(params, batch):
    unit, vis, log_scale, garbage = batch
    kp = unit * 10.0**log_scale
    try:
        clean = reconstruct(params, kp, vis)
    except ValueError as err:
        assert "\n" not in str(err) and str(err)
        return
    assert clean.shape_3d.shape == (2, N, 3) and np.isfinite(clean.shape_3d).all()
    dirty = reconstruct(params, np.where(vis[..., None] > 0, kp, garbage), vis)
    np.testing.assert_array_equal(dirty.shape_3d, clean.shape_3d)


# ---- the JSON loader -----------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10, 10) | st.floats(allow_nan=False, width=32)
    | st.text(max_size=3),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=3),
    max_leaves=12,
)


def _good_entry(draw_floats, k):
    return {"kp_loc": [draw_floats[:k], draw_floats[k:2 * k]], "kp_vis": [1] * k}


@st.composite
def json_datasets(draw):
    """Mostly well-formed datasets of 3-5 keypoints with one field of a few entries
    replaced by a random JSON value, or a random value altogether."""
    if draw(st.integers(0, 9)) == 0:
        return draw(json_values)
    k, m = draw(st.integers(3, 5)), draw(st.integers(1, 5))
    entries = [_good_entry(draw(st.lists(finite, min_size=2 * k, max_size=2 * k)), k)
               for _ in range(m)]
    for _ in range(draw(st.integers(0, 2))):
        entry = entries[draw(st.integers(0, m - 1))]
        field = draw(st.sampled_from(["kp_loc", "kp_vis", "kp_loc_3d", "K", "p3d_info",
                                      "class_mask"]))
        entry[field] = draw(json_values)
    return entries


@given(json_datasets())
@example([{"kp_loc": [[0.0, 1.0, 2.0], [0.0, 1.0]], "kp_vis": [1, 1, 1]}])
@example([{"kp_vis": [1, 1, 1]}])
@example({"dataset": "x"})
def test_json_loader_returns_data_or_names_what_is_wrong_in_one_line(obj):
    obj = json.loads(json.dumps(obj))  # only what a JSON file can hold
    try:
        data = json_dataset.parse(obj, "fuzz")
    except ValueError as err:
        assert "\n" not in str(err) and str(err)
        return
    assert data.kp.ndim == 3 and np.isfinite(data.kp).all()
    assert set(np.unique(data.vis)) <= {0.0, 1.0}
