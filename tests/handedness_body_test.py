"""A body of the user's own points for the handedness at inference: one 3D example of the
points, from an array or a file, in any position, orientation and scale, gives the model's
mean shape its handedness and every view the mean shape's
(``inference.handedness_reference="body"``)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import procrustes_evidence
from scipy.spatial.transform import Rotation

from c3dpo_jax import C3DPOParams, lift, model, reconstruct, resolve, train
from c3dpo_jax.data import KeypointData, bodies
from configs import default

K = 9
CFG = model.ModelConfig(n_keypoints=K, shape_basis_size=3, n_fully_connected=32, n_layers=1,
                        canonicalization_n_layers=1, canonicalization_n_fully_connected=32,
                        z_augment=True)


def _rig(seed=0):
    """A non-planar body of K points (a random 'skeleton' in no known joint order)."""
    return np.random.default_rng(seed).normal(size=(K, 3)) * [1.0, 0.8, 0.5]


def _orthogonal_residual(x, ref, proper):
    """The least-squares residual of ``ref`` from ``x`` under the best proper rotation or
    the best reflection (numpy SVD, both centred), an independent check of handedness."""
    x, ref = x - x.mean(0), ref - ref.mean(0)
    u, _, vt = np.linalg.svd(x.T @ ref)
    d = np.sign(np.linalg.det(u @ vt)) * (1 if proper else -1)
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    return np.linalg.norm(x @ rot - ref)


def _variables(seed, mean_shape):
    """A model's variables with its basis' mean shape set to ``mean_shape`` (N, 3) (an
    initialised one is 0, which has no handedness)."""
    variables = model.init_variables(jax.random.key(seed), CFG)
    params = jax.tree.map(lambda a: a, variables["params"])
    for layout in (mean_shape, mean_shape.T):  # the basis' layout of the flat bias
        params["shape_layer"]["bias"] = jnp.asarray(layout.reshape(-1), jnp.float32)
        got = model.mean_shape(model.make_network(CFG), params, jnp.ones(K))
        if np.allclose(got, mean_shape, atol=1e-6):
            return dict(variables, params=params)
    raise AssertionError("the mean shape is not the shape layer's bias")


def test_the_mean_shape_takes_the_body_s_handedness_in_any_pose_orientation_and_scale():
    """``mean_shape_handed_as``: the basis' mean shape, or its mirror image, whichever a
    proper rotation maps onto the body better (numpy's SVD); the same for the body turned,
    moved and scaled, and the mirror image for the body's mirror image."""
    variables = _variables(0, _rig(7))
    net = model.make_network(CFG)
    mean = np.asarray(lift.mean_shape_handed_as(
        net, variables["params"], jnp.ones(K), jnp.asarray(_rig(), jnp.float32)), np.float64)
    assert _orthogonal_residual(mean, _rig(), True) < _orthogonal_residual(mean, _rig(), False)
    moved = 3.0 * _rig() @ Rotation.random(random_state=5).as_matrix().T + [4.0, -2.0, 7.0]
    for body, sign in ((moved, 1.0), (_rig() * [1.0, 1.0, -1.0], -1.0)):
        got = lift.mean_shape_handed_as(net, variables["params"], jnp.ones(K),
                                         jnp.asarray(body, jnp.float32))
        np.testing.assert_allclose(got, mean * [1.0, 1.0, sign], atol=1e-6)
    # Whichever handedness the mean shape came out with, it ends with the body's.
    for seed in range(1, 6):
        v = _variables(seed, _rig(seed + 7) * np.array([1.0, 1.0, -1.0]) ** seed)
        m = np.asarray(lift.mean_shape_handed_as(net, v["params"], jnp.ones(K),
                                                  jnp.asarray(_rig(), jnp.float32)))
        assert _orthogonal_residual(m, _rig(), True) < _orthogonal_residual(m, _rig(), False)


@pytest.mark.parametrize("change, message", [
    ({"handedness_reference": "body"}, r"handedness_body is empty"),
    ({"handedness_reference": "body", "handedness_body": ((0, 0, 1),) * K},
     r"near one plane"),
    ({"handedness_reference": "body",
      "handedness_body": tuple(map(tuple, _rig()[:5]))},
     r"a body of the model's 9 points, N rows of \(x, y, z\); got shape \(5, 3\)"),
    ({"handedness_reference": "body",
      "handedness_body": tuple(map(tuple, np.where(np.eye(K, 3) > 0, np.nan,
                                                    _rig())))},
     r"the body has NaN or inf"),
    ({"handedness_body": tuple(map(tuple, _rig()))},
     r"handedness_body is given but handedness_reference is "
     r"'mean_shape', not 'body'"),
    ({"handedness_reference": "body", "handedness_body": (1, 2, 3)},
     r"handedness_body=\(1, 2, 3\) \(rows of three numbers\)"),
])
def test_a_body_that_cannot_give_a_handedness_is_refused_in_one_line(change, message):
    base = lift.InferenceConfig(one_handedness=True)
    with pytest.raises(ValueError, match=message):
        lift.inference_config(CFG, dataclasses.replace(base, **change))


def test_a_body_file_in_an_inference_config_is_read_on_the_host(tmp_path):
    """A body file named as the reference (a training config's, before it is resolved into
    "body") is read where the body is resolved, ``lift.reference_body``."""
    path = tmp_path / "rig.npy"
    np.save(path, _rig())
    options = lift.InferenceConfig(one_handedness=True, handedness_reference=str(path))
    np.testing.assert_allclose(lift.options_body(options), _rig().astype(np.float32))


def test_a_model_keeps_its_body_through_a_saved_config():
    """The saved config (JSON: lists) gives back the same, hashable, config."""
    options = lift.InferenceConfig(one_handedness=True, handedness_reference="body",
                                   handedness_body=tuple(map(tuple, _rig().tolist())))
    again = lift.InferenceConfig.from_dict(json.loads(json.dumps(options.to_dict())))
    assert again == options and hash(again) == hash(options)


@pytest.mark.parametrize("suffix", [".npy", ".json", ".txt", ".csv"])
def test_a_body_file_is_read_and_a_bad_one_named(tmp_path, suffix):
    body = _rig()
    path = tmp_path / f"rig{suffix}"
    if suffix == ".npy":
        np.save(path, body)
    elif suffix == ".json":
        path.write_text(json.dumps(body.tolist()))
    else:
        sep = "," if suffix == ".csv" else " "
        path.write_text("\n".join(sep.join(repr(v) for v in row) for row in body.tolist())
                        + "\n")
    np.testing.assert_array_equal(bodies.read_body(str(path)), body)
    bad = tmp_path / f"bad{suffix}"
    if suffix == ".npy":
        np.save(bad, body[:, :2])
        expected = r"holds an array of shape \(9, 2\); a body is N rows of \(x, y, z\)"
    else:
        bad.write_text("[[1, 2, 3], [4, 5]]" if suffix == ".json" else "1 2 3\n4 five 6\n")
        expected = r"is not N rows of \(x, y, z\)"
    with pytest.raises(ValueError, match=f"body file '.*bad{suffix}' {expected}"):
        bodies.read_body(str(bad))
    with pytest.raises(ValueError, match="does not exist"):
        bodies.read_body(str(tmp_path / f"missing{suffix}"))


def test_training_reads_the_body_file_into_the_model(tmp_path):
    """``resolve.resolve_handedness``: a body file named in the config becomes the model's
    "body" with one handedness on; a resumed run keeps the body it started with (also one
    saved in its model section); a body of another number of points is refused in one
    line."""
    path = tmp_path / "rig.npy"
    np.save(path, _rig())
    c = default.get_config()
    c.model.n_keypoints = K
    c.inference.handedness_reference = str(path)
    data = KeypointData(kp=np.zeros((4, K, 2)), vis=np.ones((4, K)))  # not read for a file
    got = resolve.resolve_handedness(c, data).inference
    assert (got.handedness_reference, got.one_handedness) == ("body", True)
    np.testing.assert_allclose(np.asarray(got.handedness_body), _rig())
    lift.inference_config(CFG, lift.InferenceConfig.from_dict(got))  # a valid config
    for earlier in ({"inference": {"handedness_reference": "body",
                                   "handedness_body": _rig(1).tolist()}},
                    {"model": {"test_time_handedness_reference": "body",
                               "test_time_handedness_body": _rig(1).tolist()}}):
        kept = resolve.resolve_handedness(c, data, earlier).inference
        np.testing.assert_allclose(np.asarray(kept.handedness_body), _rig(1))
    c.model.n_keypoints = K + 1
    with pytest.raises(ValueError, match=r"rig.npy' \(a body of the model's 10 points"):
        resolve.resolve_handedness(c, data)


def test_reconstruct_takes_a_body_as_an_array_or_a_file(tmp_path):
    """``reconstruct(..., handedness_reference=body)``: each view weighs the body and the
    mean shape handed as the body (checked with numpy's SVD), the 2D fit is the one
    without it, a file gives the same, and the body's mirror image mirrors every view."""
    variables = _variables(3, _rig() + 0.3 * _rig(9))  # a mean shape like the body
    # Large basis vectors, so that the views' shapes differ enough to take both sides.
    kernel = variables["params"]["shape_layer"]["kernel"]
    variables["params"]["shape_layer"]["kernel"] = 50.0 * jax.random.normal(
        jax.random.key(8), kernel.shape)
    params = C3DPOParams(variables, CFG)
    body = _rig()
    kp = np.random.default_rng(4).normal(size=(12, K, 2))
    vis = np.ones((12, K))
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(body.tolist()))
    off = reconstruct(params, kp, vis)
    on = reconstruct(params, kp, vis, handedness_reference=body)
    from_file = reconstruct(params, kp, vis, handedness_reference=str(path))
    mirror = reconstruct(params, kp, vis, handedness_reference=body * [1.0, 1.0, -1.0])
    np.testing.assert_allclose(on.kp_reprojected, off.kp_reprojected, atol=1e-5)
    np.testing.assert_allclose(from_file.shape_3d, on.shape_3d, atol=1e-6)
    np.testing.assert_allclose(mirror.shape_canonical, on.shape_canonical * [1.0, 1.0, -1.0],
                               atol=1e-5)
    # Each view is mirrored when the sum, over the body and the mean shape handed as the
    # body, of (mirror residual - proper residual) / their sum is negative (numpy's SVD).
    mean = np.asarray(lift.mean_shape_handed_as(model.make_network(CFG), variables["params"],
                                                 jnp.ones(K), jnp.asarray(body, jnp.float32)))
    assert _orthogonal_residual(mean, body, True) < _orthogonal_residual(mean, body, False)

    flips = []
    for x_own, x_on in zip(off.shape_canonical, on.shape_canonical, strict=True):
        mirrored = procrustes_evidence(x_own, body) + procrustes_evidence(x_own, mean) < 0
        flips.append(mirrored)
        np.testing.assert_allclose(x_on, x_own * ([1.0, 1.0, -1.0] if mirrored else 1.0),
                                   atol=1e-5)
    assert len(set(flips)) == 2  # views of both kinds: the rule is seen at work
    with pytest.raises(ValueError, match=r"^handedness_body \(the body's points lie near"):
        reconstruct(params, kp, vis, handedness_reference=np.zeros((K, 3)) + [0, 0, 1])


def test_a_run_given_a_body_file_keeps_the_body_and_resumes(tmp_path):
    """End to end: a run whose config names a body file saves the body with the model
    (``load`` gives it back, one handedness on), and the same command resumes it."""
    import c3dpo_jax

    body = np.random.default_rng(0).normal(size=(8, 3))
    np.save(tmp_path / "rig.npy", body)
    c = default.apply_variants(default.get_config(), "smoke")
    c.model.n_keypoints = c.data.synthetic.n_keypoints = 8
    c.model.shape_basis_size = 3
    c.inference.handedness_reference = str(tmp_path / "rig.npy")
    c.train.ckpt_every, c.train.progress_bar = 5, False
    c.train.num_steps = 5
    train.train_and_evaluate(c, str(tmp_path / "run"))
    (tmp_path / "rig.npy").unlink()  # the model holds the body; the file is not read again
    c.train.num_steps = 10
    out = train.train_and_evaluate(c, str(tmp_path / "run"))
    assert out["final"]["step"] == 10
    got = c3dpo_jax.load(str(tmp_path / "run")).inference
    assert (got.handedness_reference, got.one_handedness) == ("body", True)
    np.testing.assert_allclose(np.asarray(got.handedness_body), body)


def test_c3dpo_predict_takes_a_body_file(tmp_path):
    """``c3dpo-predict --handedness_reference=FILE`` (``predict.run``) gives what
    ``reconstruct`` gives with the body's array."""
    from c3dpo_jax import predict
    from c3dpo_jax.reconstruct import save_workdir

    params = C3DPOParams(_variables(3, _rig() * [1.0, 1.0, -1.0]), CFG)
    workdir = save_workdir(params, str(tmp_path / "run"))
    kp = np.random.default_rng(4).normal(size=(4, K, 2))
    path = tmp_path / "poses.json"
    path.write_text(json.dumps([{"kp_loc": k.T.tolist(), "kp_vis": [1] * K} for k in kp]))
    np.savetxt(tmp_path / "rig.csv", _rig(), delimiter=",")
    got = predict.run(workdir, str(path), str(tmp_path / "out.npz"),
                      handedness_reference=str(tmp_path / "rig.csv"))
    want = reconstruct(params, kp, np.ones((4, K)), handedness_reference=_rig())
    np.testing.assert_allclose(got.shape_3d, want.shape_3d, atol=1e-5)
    own = reconstruct(params, kp, np.ones((4, K)))
    assert not np.allclose(got.shape_canonical, own.shape_canonical, atol=1e-3)  # mirrored


def test_a_run_stores_its_training_views_mean_and_inference_uses_it(tmp_path):
    """``handedness_reference="views_mean"``, weighed at the output: the run evaluates with
    the rows of each evaluation's model and writes the last ones into config.json: the mean
    canonical shape of the training views (numpy, from the
    model's own predictions), which ``load`` gives back, ``reconstruct`` uses and
    ``--mode=eval`` recomputes for the step it scores, with the same scores."""
    import c3dpo_jax
    from c3dpo_jax import evaluate_workdir, inference
    from c3dpo_jax.data import load_splits

    c = default.apply_variants(default.get_config(), "smoke")
    c.model.n_keypoints = c.data.synthetic.n_keypoints = 8
    c.model.shape_basis_size = 3
    # The whole-shape evidence: the tetrahedra's trust check (below) is not at stake here.
    c.inference.update(handedness_reference="views_mean", one_handedness=True,
                       handedness_from_output=True)
    c.train.ckpt_every, c.train.progress_bar = 5, False
    c.train.num_steps = 5
    workdir = str(tmp_path / "run")
    out = train.train_and_evaluate(c, workdir)
    params = c3dpo_jax.load(workdir)
    got = params.inference
    assert (got.handedness_reference, got.one_handedness, got.handedness_evidence,
            got.handedness_from_output) == ("views_mean", True, "procrustes", True)
    train_data, _ = load_splits(c.data)
    idx = np.sort(np.random.default_rng(0).permutation(len(train_data))[
        :inference.VIEWS_MEAN_VIEWS])
    views = train_data.subset(idx)
    own = reconstruct(params, views.kp, views.vis, one_handedness=False,
                      handedness_reference="mean_shape")
    np.testing.assert_allclose(np.asarray(got.handedness_body),
                               own.shape_canonical.mean(0), rtol=1e-4, atol=1e-5)
    rec = reconstruct(params, views.kp, views.vis)
    # Views mirrored exactly where their output is nearer the rows' mirror image.
    output = np.concatenate([rec.shape_3d[..., :2], own.shape_3d[..., 2:]], -1)
    evidence = jax.vmap(lift.handedness_evidence, (0, None, None))(
        jnp.asarray(output, jnp.float32), jnp.asarray(got.handedness_body, jnp.float32),
        jnp.ones(8))
    flipped = np.asarray(evidence) < 0
    assert 0 < flipped.mean() < 1  # the 5-step model's outputs are split
    def centred_depth(r):
        return r.shape_3d[..., 2] - r.shape_3d[..., 2].mean(1, keepdims=True)

    np.testing.assert_allclose(centred_depth(rec), np.where(flipped[:, None], -1.0, 1.0)
                               * centred_depth(own), atol=1e-4)
    scored = evaluate_workdir.evaluate_checkpoint(c, workdir, save=False)["final"]
    for key in ("mpjpe", "mpjpe_global", "mpjpe_orig", "mirrored"):
        np.testing.assert_allclose(scored[key], out["final"][key], rtol=1e-5)
    assert "inference" not in scored  # the rows are not an option that differs


@pytest.mark.parametrize("spread, depth, trusted", [(0.02, 1.0, True), (30.0, 1.0, False),
                                                    (0.02, 1e-4, False)])
def test_the_tetrahedra_are_trusted_only_where_the_training_shapes_keep_their_corners(
        spread, depth, trusted):
    """``inference.with_views_mean`` with the tetrahedra: canonical shapes near one mean
    (a basis of small modes) keep its small corners, and the views' mean is the reference;
    modes that move the points by a third of the shape's size deform it freely, more than
    ``TETRAHEDRA_TRUST`` of the views reverse the corners (numpy's determinants), and the
    views keep the model's own handedness; so do views of a flat mean shape, which has no
    handedness to give."""
    from scipy.spatial import cKDTree

    from c3dpo_jax import inference
    from c3dpo_jax.data import KeypointData

    variables = _variables(0, _rig(3) * [1.0, 1.0, depth])
    rng = np.random.default_rng(1)
    kernel = variables["params"]["shape_layer"]["kernel"]
    variables["params"]["shape_layer"]["kernel"] = jnp.asarray(
        spread * rng.normal(size=kernel.shape), jnp.float32)
    data = KeypointData(kp=rng.normal(size=(64, K, 2)).astype(np.float32),
                        vis=np.ones((64, K), np.float32))
    options = lift.InferenceConfig(handedness_reference="views_mean", one_handedness=True,
                                   **resolve.VIEWS_MEAN_SETTINGS)
    own = reconstruct(C3DPOParams(variables, CFG), data.kp, data.vis).shape_canonical
    rows = own.mean(0)
    corners = cKDTree(rows).query(rows, k=4)[1]

    def chirality(y):
        edges = y[..., corners[:, 1:], :] - y[..., corners[:, :1], :]
        return np.linalg.det(edges) / np.prod(np.linalg.norm(edges, axis=-1), -1)

    reversed_share = np.mean((chirality(own) * chirality(rows)).sum(-1) < 0)
    thin = np.linalg.svd(rows - rows.mean(0), compute_uv=False)
    flat = thin[2] < bodies.BODY_MIN_THICKNESS * thin[0]
    assert (reversed_share <= inference.TETRAHEDRA_TRUST and not flat) == trusted
    got, share = inference.with_views_mean(options, variables, data, CFG)
    if not flat:  # a flat shape's corners have no reliable sign to compare
        np.testing.assert_allclose(share, reversed_share)
    if trusted:
        assert got.handedness_reference == "views_mean" and got.one_handedness
        np.testing.assert_allclose(np.asarray(got.handedness_body), rows, rtol=1e-4,
                                   atol=1e-5)
    else:
        assert (got.handedness_reference, got.one_handedness, got.handedness_body) == (
            "mean_shape", False, ())
