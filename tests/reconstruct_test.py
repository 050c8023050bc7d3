"""reconstruct(): same numbers as the per-example model, one compile per bucket, clear errors."""

import dataclasses
import json
import os
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import c3dpo_jax
from c3dpo_jax import checkpoint, lift, model, run_config
from c3dpo_jax.data import synthetic
from c3dpo_jax.reconstruct import (
    C3DPOParams,
    Reconstruction,
    _reconstruct_batch,
    load,
    reconstruct,
    save_workdir,
)

CFG = model.ModelConfig(n_keypoints=7, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1,
                        argmin_translation=True)


@pytest.fixture(scope="module")
def params():
    return C3DPOParams(model.init_variables(jax.random.key(3), CFG), CFG)


def _inputs(b, n=7, seed=0):
    rng = np.random.default_rng(seed)
    kp = rng.normal(size=(b, n, 2)).astype(np.float32) * 50 + 200
    vis = (rng.uniform(size=(b, n)) > 0.3).astype(np.float32)
    vis[:, 0] = 1
    return kp, vis


def _direct(params, kp, vis):
    """Independent path: vmapped forward_eval on the un-padded batch, invisible zeroed."""
    fn = lambda k, v: lift.forward_eval(params.variables, k * v[:, None], v,  # noqa: E731
                                        jnp.ones_like(v), None, None, params.config,
                                        params.inference)
    return jax.jit(jax.vmap(fn))(jnp.asarray(kp), jnp.asarray(vis))


def test_batch_matches_the_per_example_model(params):
    kp, vis = _inputs(5)
    rec = reconstruct(params, kp, vis)
    ref = _direct(params, kp, vis)
    assert isinstance(rec, Reconstruction) and isinstance(rec.shape_3d, np.ndarray)
    assert rec.shape_3d.shape == (5, 7, 3) and rec.rotation.shape == (5, 3, 3)
    assert rec.alpha.shape == (5, 3) and rec.kp_reprojected.shape == (5, 7, 2)
    for ours, theirs in [(rec.shape_3d, "shape_3d"),
                         (rec.shape_canonical, "shape_canonical"),
                         (rec.rotation, "rotation"), (rec.alpha, "alpha"),
                         (rec.kp_reprojected, "kp_reprojected")]:
        np.testing.assert_allclose(ours, ref[theirs], rtol=1e-5, atol=1e-4)
    # Visible points come back as the input (pixel units), as forward_eval's contract says.
    np.testing.assert_allclose(rec.shape_3d[..., :2][vis > 0], kp[vis > 0], atol=1e-4)


def test_one_sample_has_no_batch_axis_and_equals_its_row_in_a_batch(params):
    kp, vis = _inputs(4)
    batch = reconstruct(params, kp, vis)
    one = reconstruct(params, jnp.asarray(kp[2]), vis[2].astype(np.int32))
    assert one.shape_3d.shape == (7, 3) and one.rotation.shape == (3, 3)
    np.testing.assert_allclose(one.shape_3d, batch.shape_3d[2], atol=1e-4)


def test_invisible_coordinates_do_not_matter(params):
    kp, vis = _inputs(3)
    moved = np.where(vis[..., None] > 0, kp, 1e4)
    np.testing.assert_allclose(reconstruct(params, moved, vis).shape_canonical,
                               reconstruct(params, kp, vis).shape_canonical, atol=1e-5)


def test_coordinates_far_from_zero_keep_their_precision(params):
    # Georeferenced or mosaic coordinates: a float64 offset of 1e6 (float32 steps of 0.06
    # there) changes nothing but the offset itself.
    kp, vis = _inputs(3)
    base = reconstruct(params, kp, vis)
    assert base.shape_3d.dtype == np.float32  # float32 in, float32 out
    far = reconstruct(params, kp.astype(np.float64) + 1e6, vis)
    assert far.shape_3d.dtype == np.float64 and far.kp_reprojected.dtype == np.float64
    np.testing.assert_allclose(far.shape_3d[..., :2] - 1e6, base.shape_3d[..., :2], atol=1e-4)
    np.testing.assert_allclose(far.shape_3d[..., 2], base.shape_3d[..., 2], atol=1e-4)
    np.testing.assert_allclose(far.kp_reprojected - 1e6, base.kp_reprojected, atol=1e-4)
    np.testing.assert_allclose(far.shape_canonical, base.shape_canonical, atol=1e-5)


def test_turns_override_the_models_own_setting_and_are_checked(params):
    kp, vis = _inputs(4)
    augmented = dataclasses.replace(CFG, z_augment=True)
    turned = C3DPOParams(params.variables, augmented, lift.InferenceConfig(turns=3))
    own = reconstruct(turned, kp, vis)
    np.testing.assert_allclose(own.shape_3d, _direct(turned, kp, vis)["shape_3d"],
                               rtol=1e-5, atol=1e-4)
    plain = C3DPOParams(params.variables, augmented)
    np.testing.assert_allclose(reconstruct(plain, kp, vis, turns=3).shape_3d, own.shape_3d,
                               rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(turned, kp, vis, turns=1).shape_3d,
                               reconstruct(plain, kp, vis).shape_3d, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(plain, kp, vis, turns=np.int64(3)).shape_3d,
                               own.shape_3d, rtol=1e-5, atol=1e-4)  # numpy integers too
    with pytest.raises(ValueError, match=r"^turns=4 \(must be an odd number\)$"):
        reconstruct(plain, kp, vis, turns=4)
    # Trained without in-plane augmentation: the argument to pass is named.
    with pytest.raises(ValueError, match=r"^turns=3 \(must be used with "
                       r"model.z_augment=True .*; turn_span='circle' does not\)\)$"):
        reconstruct(params, kp, vis, turns=3)
    for bad in (0, -2, True):
        with pytest.raises(ValueError, match=r"^turns=.* \(must be an integer >= 1\)$"):
            reconstruct(plain, kp, vis, turns=bad)
    # Round the circle: no in-plane augmentation needed, any number of copies; the model's
    # own span or the override give the same.
    circle = C3DPOParams(params.variables, CFG, lift.InferenceConfig(turns=4, turn_span="circle"))
    np.testing.assert_allclose(
        reconstruct(circle, kp, vis).shape_3d,
        _direct(circle, kp, vis)["shape_3d"], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(params, kp, vis, turns=4, turn_span="circle").shape_3d,
                               reconstruct(circle, kp, vis).shape_3d, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(circle, kp, vis, turn_span="augmentation",
                                           turns=1).shape_3d,
                               reconstruct(params, kp, vis).shape_3d, rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match=r"^turn_span='spiral' \(must be one of"):
        reconstruct(circle, kp, vis, turn_span="spiral")
    with pytest.raises(ValueError, match=r"^turns=4 \(must be an odd number"):
        reconstruct(circle, kp, vis, turn_span="augmentation")
    # Round the circle and the range: the range is the training augmentation's.
    with pytest.raises(ValueError, match=r"^turns=4 \(must be used with model.z_augment=True "
                       r".*turn_span 'circle_and_range' uses"):
        reconstruct(circle, kp, vis, turn_span="circle_and_range")
    # One pass is always allowed, even where turning is not (a perspective model).
    persp = C3DPOParams(params.variables, dataclasses.replace(CFG, projection_type="perspective"))
    K = np.broadcast_to(np.eye(3, dtype=np.float32), (4, 3, 3))
    np.testing.assert_allclose(reconstruct(persp, kp, vis, K=K, turns=1).shape_3d,
                               reconstruct(persp, kp, vis, K=K).shape_3d)



def test_refinement_override_the_models_own_setting_and_is_checked(params, monkeypatch):
    kp, vis = _inputs(4)
    kp = (kp - 200.0) / 50.0  # the training data's units
    # A shape layer of unit-sized shapes and modes: a well-posed fit.
    mean, modes = synthetic.shape_model(7, 3, 0.3, seed=0)
    variables = dict(params.variables, params=dict(params.variables["params"], shape_layer={
        "bias": jnp.asarray(mean.T.reshape(-1)),
        "kernel": jnp.asarray(modes.transpose(0, 2, 1).reshape(3, -1))}))
    params = C3DPOParams(variables, CFG)
    refined = C3DPOParams(variables, CFG, lift.InferenceConfig(refine_iters=5))
    own = reconstruct(refined, kp, vis)
    np.testing.assert_allclose(own.shape_3d, _direct(refined, kp, vis)["shape_3d"],
                               rtol=1e-5, atol=1e-4)
    assert np.abs(own.shape_3d - reconstruct(params, kp, vis).shape_3d).max() > 1e-3
    np.testing.assert_allclose(reconstruct(params, kp, vis, refine_iters=5).shape_3d,
                               own.shape_3d, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(refined, kp, vis, refine_iters=0).shape_3d,
                               reconstruct(params, kp, vis).shape_3d, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(reconstruct(params, kp, vis, refine_iters=np.int64(5)).shape_3d,
                               own.shape_3d, rtol=1e-5, atol=1e-4)  # numpy integers too
    for bad in (-1, True):
        with pytest.raises(ValueError, match=rf"^refine_iters={bad!r} \(must be an integer"):
            reconstruct(params, kp, vis, refine_iters=bad)
    persp = C3DPOParams(params.variables, dataclasses.replace(CFG, projection_type="perspective"))
    K = np.broadcast_to(np.eye(3, dtype=np.float32), (4, 3, 3))
    with pytest.raises(ValueError, match=r"^refine_iters=3 \(must be 0 \(no refinement\) for "
                       r"a perspective model"):
        reconstruct(persp, kp, vis, K=K, refine_iters=3)
    # one_handedness= reaches the model's option (its effect: model_test) as refine_iters=
    # does, and None keeps the model's.
    module = sys.modules["c3dpo_jax.reconstruct"]  # the package's attribute is the function
    seen = []

    def spy(p, *arrays):
        seen.append(p.inference.one_handedness)
        return _reconstruct_batch(p, *arrays)

    monkeypatch.setattr(module, "_reconstruct_batch", spy)
    handed = C3DPOParams(variables, CFG, lift.InferenceConfig(one_handedness=True))
    for p, option in ((params, True), (handed, False), (handed, None), (params, None)):
        reconstruct(p, kp, vis, one_handedness=option)
    assert seen == [True, False, True, False]
    with pytest.raises(ValueError, match=r"^one_handedness=True \(must be False for a "
                       r"perspective model"):
        reconstruct(persp, kp, vis, K=K, one_handedness=True)


def test_a_body_reference_turns_one_handedness_on_and_is_checked(params, monkeypatch):
    """``handedness_reference=`` reaches the model's option (its effect: lift_test) and turns
    ``one_handedness`` on unless it is False; a body of another joint order, an unknown
    name and an unresolved one are refused in one line."""
    cfg17 = dataclasses.replace(CFG, n_keypoints=17)
    p17 = C3DPOParams(model.init_variables(jax.random.key(1), cfg17), cfg17)
    kp, vis = _inputs(3, n=17)
    module = sys.modules["c3dpo_jax.reconstruct"]  # the package's attribute is the function
    seen = []

    def spy(p, *arrays):
        seen.append((p.inference.one_handedness, p.inference.handedness_reference))
        return _reconstruct_batch(p, *arrays)

    monkeypatch.setattr(module, "_reconstruct_batch", spy)
    reconstruct(p17, kp, vis, handedness_reference="h36m")
    reconstruct(p17, kp, vis, one_handedness=True, handedness_reference="mean_shape")
    reconstruct(p17, kp, vis, handedness_reference="mean_shape")
    reconstruct(p17, kp, vis, handedness_reference="coco")
    reconstruct(p17, kp, vis, handedness_reference="h36m", one_handedness=False)
    assert seen == [(True, "h36m"), (True, "mean_shape"), (False, "mean_shape"), (True, "coco"),
                    (False, "h36m")]
    kp7, vis7 = _inputs(3)
    for p, k, v, kwargs, message in (
            (params, kp7, vis7, {"handedness_reference": "h36m"},
             r"^handedness_reference='h36m' \(a body of 17 points in its joint order; the "
             r"model has 7\)"),
            (p17, kp, vis, {"handedness_reference": "smpl"},
             r"^handedness_reference='smpl' \(must be one of 'mean_shape', 'h36m', 'coco', "
             r"'body', 'views_mean', 'auto', or a body file"),
            (p17, kp, vis, {"handedness_reference": "auto"},
             r"^handedness_reference='auto' \(a training setting, resolved from the training "
             r"views")):
        with pytest.raises(ValueError, match=message):
            reconstruct(p, k, v, **kwargs)


def test_body_distance_is_the_procrustes_residual_and_warns_of_another_joint_order(
        monkeypatch, caplog):
    """``body_distance`` against scipy's orthogonal Procrustes (rotation or reflection) on
    unit-norm centred shapes: 0 for turned, mirrored, scaled, shifted copies of the body; and
    ``reconstruct`` with a body reference warns when the views' canonical shapes are far from
    it (points in another order), not when they are near."""
    from scipy.linalg import orthogonal_procrustes
    from scipy.spatial.transform import Rotation

    module = sys.modules["c3dpo_jax.reconstruct"]  # the package's attribute is the function
    body = np.asarray(lift.reference_body("h36m"), np.float64)
    rng = np.random.default_rng(3)
    shapes = body + 0.2 * rng.normal(size=(5, 17, 3))
    want = []
    for x in shapes:
        a, b = x - x.mean(0), body - body.mean(0)
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        r, _ = orthogonal_procrustes(a, b)
        want.append(np.linalg.norm(a @ r - b))
    np.testing.assert_allclose(module.body_distance(shapes, body), want, atol=1e-9)
    rots = Rotation.random(4, random_state=1).as_matrix()
    copies = 3.0 * np.einsum("bij,nj->bni", rots, body) * np.array([1, 1, -1]) + 5.0
    np.testing.assert_allclose(module.body_distance(copies, body), 0.0, atol=1e-6)

    cfg17 = dataclasses.replace(CFG, n_keypoints=17)
    p17 = C3DPOParams(model.init_variables(jax.random.key(1), cfg17), cfg17)
    kp, vis = _inputs(4, n=17)
    for canonical, warned in ((copies, False), (copies[:, rng.permutation(17)], True)):
        def fake(p, kp, vis, *rest, canonical=canonical):  # body: rest[-1]
            b = kp.shape[0]
            c = np.resize(canonical, (b, 17, 3))
            return Reconstruction(np.asarray(c), c, np.broadcast_to(np.eye(3), (b, 3, 3)),
                                  np.zeros((b, 3)), np.asarray(kp))

        monkeypatch.setattr(module, "_reconstruct_batch", fake)
        caplog.clear()
        reconstruct(p17, kp, vis, handedness_reference="h36m")
        assert ("far from the 'h36m' body" in caplog.text) == warned
        reconstruct(p17, kp, vis)  # no body asked for: nothing to check
        assert caplog.text.count("far from the") == warned


def test_batch_sizes_share_compiles_by_power_of_two_bucket(params):
    cfg = dataclasses.replace(CFG, n_keypoints=9)  # a model no other test compiled
    p = C3DPOParams(model.init_variables(jax.random.key(0), cfg), cfg)
    before = _reconstruct_batch._cache_size()
    for b in (3, 4, 3, 4):
        reconstruct(p, *_inputs(b, n=9))
    assert _reconstruct_batch._cache_size() - before == 1
    for b in (5, 6, 7, 8):
        reconstruct(p, *_inputs(b, n=9))
    assert _reconstruct_batch._cache_size() - before == 2


@pytest.mark.parametrize("kp_shape,vis_shape,edit,match", [
    ((3, 6, 2), (3, 6), None, "expects N = 7"),
    ((3, 7, 3), (3, 7), None, "expected"),
    ((2, 3, 7, 2), (3, 7), None, "expected"),
    ((3, 7, 2), (3, 6), None, r"vis has shape \(3, 6\), expected \(B, 7\)"),
    ((3, 7, 2), (2, 7), None, "batch size"),
    ((3, 7, 2), (3, 7), "nan", "NaN or inf"),
    ((3, 7, 2), (3, 7), "vis2", "only 0 and 1"),
    ((3, 7, 2), (3, 7), "empty", r"sample\(s\) \[1\] have no visible"),
    ((3, 7, 2), (3, 7), "K", "orthographic"),
])
def test_bad_input_raises_a_clear_value_error(params, kp_shape, vis_shape, edit, match):
    kp, vis = np.ones(kp_shape, np.float32), np.ones(vis_shape, np.float32)
    K = None
    if edit == "nan":
        kp[0, 0, 0] = np.nan
    elif edit == "vis2":
        vis[0, 0] = 2
    elif edit == "empty":
        vis[1] = 0
    elif edit == "K":
        K = np.eye(3)
    with pytest.raises(ValueError, match=match):
        reconstruct(params, kp, vis, K)


def test_a_notebook_with_64_bit_jax_gets_the_same_float32_reconstruction(params):
    kp, vis = _inputs(3, n=7)
    want = reconstruct(params, kp, vis, refine_iters=3)
    with jax.enable_x64(True):  # jax_enable_x64, as scientific notebooks often set it
        got = reconstruct(params, kp, vis, refine_iters=3)
    np.testing.assert_array_equal(got.shape_3d, want.shape_3d)


def test_complex_and_traced_keypoints_are_refused_in_one_line(params):
    kp, vis = np.ones((3, 7, 2)), np.ones((3, 7))
    with pytest.raises(ValueError, match="kp is complex"):
        reconstruct(params, kp + 1j, vis)
    with pytest.raises(ValueError, match="kp is a traced value: reconstruct runs on the host"):
        jax.jit(lambda k: reconstruct(params, k, vis).shape_3d)(kp)


def test_class_mask_is_checked(params, caplog):
    kp, vis = _inputs(2)
    with pytest.raises(ValueError, match=r"^class_mask must contain only 0 and 1$"):
        reconstruct(params, kp, vis, class_mask=np.full(7, 0.5))
    with caplog.at_level("WARNING"):
        reconstruct(params, kp, vis, class_mask=np.zeros(7))
    assert "sample(s) [0, 1] have visible keypoints outside their class_mask" in caplog.text


def test_perspective_model_needs_intrinsics():
    cfg = dataclasses.replace(CFG, projection_type="perspective", argmin_translation=False)
    p = C3DPOParams(model.init_variables(jax.random.key(0), cfg), cfg)
    kp, vis = _inputs(2)
    with pytest.raises(ValueError, match="perspective model: pass the intrinsics K"):
        reconstruct(p, kp, vis)
    K = np.array([[500.0, 0, 200], [0, 500, 200], [0, 0, 1]], np.float32)
    rec = reconstruct(p, kp, vis, K)
    assert np.all(np.isfinite(rec.shape_3d))
    np.testing.assert_array_equal(reconstruct(p, kp, vis, np.stack([K, K])).shape_3d,
                                  rec.shape_3d)  # one K per sample
    with pytest.raises(ValueError, match=r"^K has batch size 3 but kp has 2 \(give one K"):
        reconstruct(p, kp, vis, np.stack([K, K, K]))
    flat = np.stack([K, K * np.array([1, 1, 0], np.float32)[:, None]])  # a zero last row
    with pytest.raises(ValueError, match=r"^K of sample\(s\) \[1\] is singular"):
        reconstruct(p, kp, vis, flat)
    with pytest.raises(ValueError, match=r"^K of sample\(s\) \[0, 1\] has the last row "
                       r"\[200.0, 200.0, 1.0\]: .* \(a transposed K\?\)$"):
        reconstruct(p, kp, vis, K.T)


def test_load_from_workdir_or_step_dir_restores_the_saved_variables(params, tmp_path):
    workdir = save_workdir(params, str(tmp_path / "w"))
    for path in (workdir, os.path.join(workdir, "checkpoints", "0")):
        loaded = load(path)
        assert loaded.config == CFG and loaded.inference == params.inference
        same = jax.tree.map(lambda a, b: np.array_equal(np.asarray(a), np.asarray(b)),
                            loaded.variables, params.variables)
        assert all(jax.tree.leaves(same))
    with pytest.raises(FileNotFoundError, match="neither a workdir"):
        load(str(tmp_path))


def test_load_refuses_in_one_line_a_config_that_does_not_describe_the_checkpoint(
        params, tmp_path, capfd):
    # A hand-edited config.json (or one of another library version): the checkpoint holds
    # a basis of 3, the config says 4.
    workdir = save_workdir(params, str(tmp_path / "w"))
    path = os.path.join(workdir, "config.json")
    with open(path) as f:
        config = json.load(f)
    config["model"]["shape_basis_size"] = 4
    with open(path, "w") as f:
        json.dump(config, f)
    capfd.readouterr()
    with pytest.raises(ValueError) as err:
        load(workdir)
    message = str(err.value)
    assert "holds a network of other shapes than " + path in message
    assert "alpha_layer/kernel: (16, 3) stored, (16, 4) expected" in message
    assert "delete" not in message and "\n" not in message
    assert "Traceback" not in capfd.readouterr().err  # orbax never tried to read it


def _same(a, b) -> bool:
    return all(jax.tree.leaves(jax.tree.map(
        lambda x, y: np.array_equal(np.asarray(x), np.asarray(y)), a, b)))


def test_load_reads_a_training_checkpoint_without_an_optimiser(params, tmp_path):
    """A training run's checkpoint holds a TrainState with optimiser state; load reads only
    its params and batch_stats (no optimiser is built: the config names none, and the
    saved state is Adam's), and still proves each step against its checksums."""
    from c3dpo_jax.state import TrainState

    workdir = str(tmp_path / "run")
    tx, manager = optax.adam(1e-3), checkpoint.make_manager(workdir, save_every=1)
    scaled = {step: jax.tree.map(lambda a, s=step: a * s, params.variables) for step in (1, 2)}
    for step, v in scaled.items():
        state = TrainState(jnp.int32(step), v["params"], v["batch_stats"], tx.init(v["params"]))
        checkpoint.save(manager, step, state, force=True)
    manager.wait_until_finished()
    manager.close()
    run_config.save_config(workdir, {"model": CFG.to_dict()})
    assert _same(load(workdir).variables, scaled[2])
    step_dir = os.path.join(workdir, checkpoint.CHECKPOINT_DIR, "2")
    files = [os.path.join(d, f) for d, _, fs in os.walk(step_dir) for f in fs]
    biggest = pathlib.Path(max(files, key=os.path.getsize))
    data = bytearray(biggest.read_bytes())
    data[len(data) // 2] ^= 0xFF
    biggest.write_bytes(bytes(data))
    assert _same(load(workdir).variables, scaled[1])  # the damaged step 2 is skipped


def test_a_model_keeps_its_inference_options_through_its_workdir(params, tmp_path):
    """``save_workdir`` writes the inference options as config.json's own section, which
    ``load`` gives back; ``reconstruct`` takes every option by its field's name."""
    options = lift.InferenceConfig(refine_iters=4, refine_prior=0.5,
                                   replace_keypoints_with_input=False)
    workdir = save_workdir(C3DPOParams(params.variables, CFG, options), str(tmp_path / "w"))
    with open(os.path.join(workdir, "config.json")) as f:
        assert json.load(f)["inference"] == json.loads(json.dumps(options.to_dict()))
    loaded = load(workdir)
    assert loaded.inference == options
    kp, vis = _inputs(3)
    np.testing.assert_allclose(reconstruct(loaded, kp, vis).shape_3d,
                               reconstruct(params, kp, vis, **options.to_dict()).shape_3d)
    with pytest.raises(ValueError, match=r"^unknown inference option\(s\) \['turn'\]"):
        reconstruct(params, kp, vis, turn=3)


def test_package_exports_the_public_api():
    assert c3dpo_jax.load is load and c3dpo_jax.reconstruct is reconstruct
    for name in ("from_official", "Reconstruction", "ModelConfig", "C3DPOParams"):
        assert hasattr(c3dpo_jax, name)
