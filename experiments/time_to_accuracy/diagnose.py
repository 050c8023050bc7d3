"""Where a trained model's 3D error comes from: camera, shape or the linear model itself.

  python experiments/time_to_accuracy/run.py --dataset=face --save_variables=runs/face.msgpack
  python experiments/time_to_accuracy/diagnose.py --dataset=face --variables=runs/face.msgpack

Takes run.py's data and recipe flags (``--dataset``, ``--recipe``, ``--set``, ...: give the
ones the run had) and prints, as a table (and with ``--json=PATH`` as JSON), test MPJPE with
the C3DPO protocol of:

- ``network``: the model's own prediction (what run.py reports);
- ``network, training views``: the same on every 5th training view (over-fitting check);
- ``camera refit``: the predicted canonical shapes with a scaled orthographic camera fitted
  to each view's visible 2D points (the fitted-mean-shape baseline's camera) instead of
  Phi's rotation;
- ``learnt basis refit``: the model's own shape basis (its shape layer) fitted to each view
  by ``baselines.fit_shape_basis`` instead of taking Phi's coefficients (prior: the variance
  of Phi's test coefficients; ``--noise_var`` the isotropic noise);
- ``canonical shapes, oracle rotation`` / ``mean shape, oracle rotation``: the predicted
  canonical shapes / the Procrustes mean training shape under each view's best rotation
  onto the ground truth, or that of its mirror image if better (shape error alone, no
  camera error);
- ``PCA basis, oracle 3D fit``: the D-dimensional PCA of the training shapes fitted to each
  test shape's 3D ground truth (best rotation and coefficients): the linear model's own error;

and two 2D errors on the test views: the model's reprojection error, and the rigidly fitted
mean shape's residual (``2D residual, fitted mean shape``). The refits are test-time
optimisation, outside the method: they say what part of the error is the camera's.
"""

import json
import os
import sys

import flax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from c3dpo_jax import baselines, evaluation, inference, lift, model, resolve

FLAGS = flags.FLAGS


def oracle_rotation(shapes: np.ndarray, kp3d: np.ndarray) -> np.ndarray:
    """Each shape (M, N, 3), centred, under its best rotation onto the centred ``kp3d``; per
    shape the better of it and its mirror image (C3DPO's canonical frame may be mirrored,
    the reflection the protocol's depth flip resolves for the camera-frame output)."""
    dst_mean = kp3d.mean(1, keepdims=True)
    aligned = []
    for src in (shapes, shapes * np.array([1.0, 1.0, -1.0])):
        src = src - src.mean(1, keepdims=True)
        rot = baselines.kabsch(src, kp3d - dst_mean)
        aligned.append(np.einsum("mij,mnj->mni", rot, src) + dst_mean)
    err = [np.linalg.norm(a - kp3d, axis=-1).mean(1) for a in aligned]
    return np.where((err[1] < err[0])[:, None, None], aligned[1], aligned[0])


def pca_oracle_fit(basis: baselines.ShapeBasis, kp3d: np.ndarray, n_iters: int = 10):
    """The basis fitted to each 3D shape: least-squares coefficients alternated with the
    best rotation of the ground truth onto the model (M, N, 3), in the truth's frame."""
    gt = kp3d - kp3d.mean(1, keepdims=True)
    flat = basis.basis.reshape(len(basis.basis), -1)  # (D, 3N), orthonormal rows
    fit = np.broadcast_to(basis.mean, gt.shape)
    for _ in range(n_iters):
        rot = baselines.kabsch(gt, fit)  # truth -> model frame
        aligned = np.einsum("mij,mnj->mni", rot, gt)
        coef = (aligned - basis.mean).reshape(len(gt), -1) @ flat.T
        fit = basis.mean + (coef @ flat).reshape(gt.shape)
    return np.einsum("mji,mnj->mni", rot, fit) + kp3d.mean(1, keepdims=True)


def learnt_basis(variables, model_cfg, alpha: np.ndarray, noise_var: float):
    """The shape layer as a ``baselines.ShapeBasis``: mean = shape(0), modes = the layer's
    columns, orthonormalised (QR) so that Phi's coefficient variances carry over."""
    net = model.make_network(model_cfg)
    d = model_cfg.shape_basis_size
    codes = jnp.concatenate([jnp.zeros((1, d)), jnp.eye(d)])
    shapes = np.stack([np.asarray(net.apply({"params": variables["params"]}, a, method="shape"))
                       for a in codes]).astype(np.float64)
    mean, cols = shapes[0], (shapes[1:] - shapes[0]).reshape(d, -1)
    q, r = np.linalg.qr(cols.T)  # cols.T = q r: coefficients in q's frame are r @ alpha
    variances = np.maximum((alpha @ r.T).var(0), 1e-12)
    return baselines.ShapeBasis(mean, q.T.reshape(d, *mean.shape), variances, noise_var)


def rigid_residual_2d(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> float:
    """Mean 2D distance of the visible points to the rigidly fitted mean shape's projection."""
    scale, rows, centred, kp_mean = baselines.fit_camera(mean_shape, kp, vis)
    xy = scale[:, None, None] * np.einsum("mij,mnj->mni", rows, centred) + kp_mean[:, None]
    return float((np.linalg.norm(xy - kp, axis=-1) * vis).sum() / vis.sum())


def diagnose(variables, train_data, test_data, protocol: str, model_cfg, options,
             noise_var: float):
    def score(pred, data=test_data):
        return float(evaluation.evaluate(np.asarray(pred), data, protocol)["mpjpe"])

    pred = {k: np.asarray(v, np.float64) for k, v in inference.predict_split(
        variables, test_data, model_cfg, options).items()}
    every5 = train_data.subset(np.arange(0, len(train_data), 5))
    mean_shape = baselines.procrustes_mean_shape(train_data.kp3d)
    pca = baselines.pca_shape_basis(train_data.kp3d, model_cfg.shape_basis_size)
    canon = pred["shape_canonical"]
    own = learnt_basis(variables, model_cfg, pred["alpha"], noise_var)
    return {
        "network": score(pred["shape_3d"]),
        "network, training views": score(inference.predict_split(
            variables, every5, model_cfg, options)["shape_3d"], every5),
        "camera refit": score(baselines.fit_mean_shape(canon, test_data.kp, test_data.vis)),
        "learnt basis refit": score(baselines.fit_shape_basis(own, test_data.kp, test_data.vis)),
        "canonical shapes, oracle rotation": score(oracle_rotation(canon, test_data.kp3d)),
        "mean shape, oracle rotation": score(oracle_rotation(
            np.broadcast_to(mean_shape, canon.shape), test_data.kp3d)),
        "PCA basis, oracle 3D fit": score(pca_oracle_fit(pca, test_data.kp3d)),
        "fitted mean shape (baseline)": score(
            baselines.fit_mean_shape_one_scale(mean_shape, test_data.kp, test_data.vis)),
        "2D reprojection, network": evaluation.reprojection_error(
            pred["kp_reprojected"], test_data),
        "2D residual, fitted mean shape": rigid_residual_2d(
            mean_shape, test_data.kp, test_data.vis),
    }


def main(argv):
    del argv
    if not FLAGS.variables:
        raise app.UsageError("--variables is required (a file written by run.py --save_variables)")
    train_data, test_data, protocol = run.load_dataset(
        FLAGS.dataset, FLAGS.views_per_frame, FLAGS.cameras, FLAGS.data_seed)
    c = run.recipe_config(FLAGS.recipe, FLAGS.dataset, train_data.n_keypoints, protocol)
    c = resolve.resolve_from_data(c, train_data)
    model_cfg = model.ModelConfig.from_dict(c.model)
    options = lift.inference_config(model_cfg, lift.InferenceConfig.from_dict(c.inference))
    with open(FLAGS.variables, "rb") as f:
        variables = flax.serialization.msgpack_restore(f.read())
    options = inference.with_views_mean(options, variables, train_data, model_cfg)[0]
    result = diagnose(variables, train_data, test_data, protocol, model_cfg, options,
                      FLAGS.noise_var)
    width = max(map(len, result))
    for name, value in result.items():
        print(f"{name:<{width}}  {value:.4f}")
    if FLAGS.json:
        with open(FLAGS.json, "w") as f:
            json.dump(dict(dataset=run.dataset_name(FLAGS.dataset), recipe=FLAGS.recipe,
                           variables=FLAGS.variables, figures=result), f, indent=1)


if __name__ == "__main__":
    # Flags only when run as a script, so that tests can import the functions above.
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import run  # run.py's flags: --dataset, --recipe, --set, --views_per_frame, ...
    from runner import run_main

    flags.DEFINE_string("variables", None, "model variables written by run.py --save_variables")
    flags.DEFINE_float("noise_var", 1e-6, "isotropic noise variance of the learnt-basis refit")
    flags.DEFINE_string("json", "", "also write the figures here")
    run_main(main)
