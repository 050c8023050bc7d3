"""Official weights -> JAX: the converted model reproduces the release's outputs."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from c3dpo_jax import convert, lift, losses, model
from c3dpo_jax.networks import C3DPONet
from c3dpo_jax.reconstruct import load, reconstruct, save_workdir

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIXTURE = os.path.join(ROOT, "tests", "testdata", "parity_small.npz")
ROT_TOL, EXACT_TOL = 1e-3, 1e-5  # release's expm divides by (angle + 1e-4): fixtures/README


@pytest.fixture(scope="module")
def fixture():
    f = np.load(FIXTURE)
    return {k: f[k] for k in f.files}


@pytest.fixture(scope="module")
def converted(fixture):
    sd = {k.removeprefix("sd/"): v for k, v in fixture.items() if k.startswith("sd/")}
    return convert.from_official(sd, json.loads(str(fixture["config_json"])))


def _t(a):
    """Release layout (B, C, N) -> ours (B, N, C)."""
    return np.swapaxes(a, -1, -2)


@pytest.fixture(scope="module")
def phi_outputs(fixture, converted):
    kp, vis = _t(fixture["kp_loc"]), fixture["kp_vis"]
    def fn(k, v):
        return lift.forward_eval(converted.variables, k, v, jnp.ones(17), None, None,
                                 converted.config, converted.inference)

    return {k: np.asarray(v) for k, v in jax.jit(jax.vmap(fn))(kp, vis).items()}


def test_release_options_map_to_model_config(fixture, converted):
    cfg = converted.config
    sizes = (cfg.n_keypoints, cfg.shape_basis_size, cfg.n_fully_connected, cfg.n_layers)
    assert sizes == (17, 10, 128, 2)
    assert (cfg.canonicalization_n_layers, cfg.canonicalization_n_fully_connected) == (2, 128)
    assert cfg.canonicalization and not cfg.argmin_translation
    assert converted.inference == lift.InferenceConfig()  # the release's inference
    assert not convert.inference_from_official(
        {"replace_keypoints_with_input": False}).replace_keypoints_with_input


def test_unknown_release_options_are_rejected_by_name():
    with pytest.raises(ValueError, match="bogus.*canonicalization.wat"):
        convert.model_config_from_official({"n_keypoints": 5, "bogus": 1,
                                            "canonicalization": {"wat": 2}})


def test_converted_tree_has_the_layout_of_a_fresh_model(converted):
    fresh = model.init_variables(jax.random.key(1), converted.config)
    same = jax.tree.map(lambda a, b: a.shape == b.shape, converted.variables, fresh)
    assert all(jax.tree.leaves(same))


def test_converted_model_reproduces_rotation_free_outputs_exactly(fixture, phi_outputs):
    out = phi_outputs
    np.testing.assert_allclose(out["kp_norm"], _t(fixture["out/kp_loc_norm"]), atol=EXACT_TOL)
    np.testing.assert_allclose(out["kp_mean"], fixture["out/kp_mean"], atol=EXACT_TOL)
    np.testing.assert_allclose(out["alpha"], fixture["out/phi/shape_coeff"], atol=EXACT_TOL)
    np.testing.assert_allclose(out["shape_canonical"], _t(fixture["out/phi/shape_canonical"]),
                               atol=EXACT_TOL)
    np.testing.assert_allclose(out["theta"], fixture["out/phi/R_log"], atol=EXACT_TOL)
    np.testing.assert_allclose(out["translation"], fixture["out/phi/T"], atol=EXACT_TOL)
    np.testing.assert_allclose(out["scale"], fixture["out/phi/scale"], atol=EXACT_TOL)


def test_converted_model_reproduces_rotation_dependent_outputs(fixture, phi_outputs):
    out = phi_outputs
    np.testing.assert_allclose(out["rotation"], fixture["out/phi/R"], atol=ROT_TOL)
    np.testing.assert_allclose(out["shape_camera"], _t(fixture["out/phi/shape_camera_coord"]),
                               atol=ROT_TOL)
    np.testing.assert_allclose(out["shape_3d"], _t(fixture["out/shape_image_coord"]),
                               atol=ROT_TOL)
    # The release's normalised reprojection; its "image" version has visible points
    # replaced by the input, i.e. the xy of shape_3d (the release's shape_image_coord).
    np.testing.assert_allclose(out["kp_reprojected"] - out["kp_mean"][:, None],
                               _t(fixture["out/kp_reprojected"]), atol=ROT_TOL)
    np.testing.assert_allclose(out["shape_3d"][..., :2],
                               _t(fixture["out/kp_reprojected_image"]), atol=ROT_TOL)
    vis = fixture["kp_vis"]
    repro = losses.huber(jnp.asarray(out["dist_sq"]), 0.01)  # the release's huber_scaling
    l_repro = (repro * vis).sum() / vis.sum()  # kp_total_count normalisation
    np.testing.assert_allclose(l_repro, fixture["out/l_reprojection"], atol=ROT_TOL)


def test_converted_psi_reproduces_the_release_canonicaliser(fixture, converted):
    net = model.make_network(converted.config)
    assert isinstance(net, C3DPONet)

    def psi(x):
        alpha = net.apply(converted.variables, x, False, method="psi")
        return alpha, net.apply(converted.variables, alpha, method="shape")

    alpha, shape = jax.vmap(psi)(_t(fixture["psi_in"]))
    np.testing.assert_allclose(alpha, fixture["psi_out/shape_coeff"], atol=EXACT_TOL)
    np.testing.assert_allclose(shape, _t(fixture["psi_out/shape_canonical"]), atol=EXACT_TOL)


def test_missing_torch_gives_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ImportError, match="needs PyTorch"):
        convert.load_official_pth(str(tmp_path / "x.pth"), {})


def test_converted_model_saved_as_workdir_loads_and_evaluates_from_the_cli(
        fixture, converted, tmp_path):
    from configs import synthetic

    config = synthetic.get_config("smoke")
    config.data.synthetic.n_keypoints = 17
    workdir = save_workdir(converted, str(tmp_path / "run"), config.to_dict())
    loaded = load(workdir)
    assert loaded.config == converted.config
    kp, vis = _t(fixture["kp_loc"]), fixture["kp_vis"]
    rec = reconstruct(loaded, kp, vis)
    np.testing.assert_allclose(rec.shape_3d, _t(fixture["out/shape_image_coord"]), atol=ROT_TOL)
    overrides = [f"--config.model.{k}={v}" for k, v in [
        ("n_keypoints", 17), ("n_fully_connected", 128), ("n_layers", 2),
        ("canonicalization_n_fully_connected", 128), ("canonicalization_n_layers", 2),
        ("argmin_translation", False), ("z_augment", False)]]
    proc = subprocess.run(
        [sys.executable, "-m", "c3dpo_jax.main", "--config=configs/synthetic.py:smoke",
         f"--workdir={workdir}", "--mode=eval", "--config.data.synthetic.n_keypoints=17",
         *overrides],
        cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(os.path.join(workdir, "eval_results.json")) as f:
        results = json.load(f)
    assert results["final"]["step"] == 0 and np.isfinite(results["final"]["mpjpe"])
