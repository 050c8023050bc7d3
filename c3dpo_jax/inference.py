"""The one batched eval-mode forward pass, and the padding that keeps its shapes fixed.

Glossary: B batch, N keypoints, M samples of a split.

One path from a model to 3D: the per-example ``lift.forward_eval`` -> ``forward_batch``
(vmapped over the batch; running BatchNorm statistics, so examples do not interact) ->
``reconstruct.reconstruct`` (a user's keypoints, checked on the host). A split is
evaluated through ``predict_split``, which runs ``forward_batch`` over the whole split and
keeps the outputs ``reconstruct`` does not return (``handedness_flipped``, the normalised
frame's); the training loop, ``--mode=eval``, the benchmark and the experiments use them.
Batches are padded to a fixed size by repeating valid samples (``wrap_indices``), so one
compiled function serves every batch of that size and the padding rows are real inputs,
never NaN-prone zeros.
"""

import dataclasses
from functools import partial

import jax
import numpy as np

from c3dpo_jax import baselines, evaluation, geometry, lift, model
from c3dpo_jax.data import bodies
from c3dpo_jax.data.dataset import KeypointData
from c3dpo_jax.lift import InferenceConfig

# training_views_mean: the training views it averages (the analysis that chose the reference
# used 2,000: experiments/dev_suite/handedness.md, "The decision at the output").
VIEWS_MEAN_VIEWS = 2000
# with_views_mean: the share of training views whose own canonical shape reverses the views'
# mean's small corners above which the tetrahedra are not trusted (evidence:
# experiments/dev_suite/handedness.md, "The decision at the output").
TETRAHEDRA_TRUST = 0.1


def forward_batch(variables: model.Variables, kp, vis, class_mask, intrinsics, body,
                  cfg: model.ModelConfig, options: InferenceConfig) -> model.Prediction:
    """``lift.forward_eval`` over a batch: ``kp (B, N, 2)``, ``vis`` and ``class_mask``
    ``(B, N)``, ``intrinsics (B, 3, 3)`` or None, ``body (N, 3)`` or None (one for the
    batch, ``lift.options_body``); returns its ``Prediction`` with a leading B on every
    field."""
    fn = partial(lift.forward_eval, variables, cfg=cfg, options=options)
    return jax.vmap(fn, in_axes=(0, 0, 0, None if intrinsics is None else 0, None))(
        kp, vis, class_mask, intrinsics, body
    )


# ``forward_batch`` compiled once per model, options and batch shape (the configs are static).
_forward_batch = jax.jit(forward_batch, static_argnames=("cfg", "options"))


def wrap_indices(start: int, size: int, m: int) -> np.ndarray:
    """Rows ``start .. start + size - 1`` of an ``m``-row array, wrapping around past the
    end: a fixed-size batch whose padding repeats valid samples."""
    return np.arange(start, start + size) % m


def bucket_size(b: int) -> int:
    """The power of two at or above ``b``: padded batch sizes, so a compiled function
    serves every batch size up to it."""
    return 1 << max(b - 1, 0).bit_length()


def predict_split(variables, data: KeypointData, model_cfg: model.ModelConfig,
                  options: InferenceConfig, batch_size: int = 1024) -> dict[str, np.ndarray]:
    """Eval-mode outputs for a whole split, a dict ``{field of model.Prediction: (M, ...)}``
    of numpy arrays, computed in compiled batches of ``min(batch_size, M)`` (the last one
    padded by wrapping around)."""
    inputs = data.model_inputs()
    body = lift.options_body(options)
    m = len(data)
    batch_size = min(batch_size, m)
    outputs = []
    for start in range(0, m, batch_size):
        idx = wrap_indices(start, batch_size, m)
        out = _forward_batch(variables, inputs["kp"][idx], inputs["vis"][idx],
                             inputs["class_mask"][idx],
                             None if "intrinsics" not in inputs else inputs["intrinsics"][idx],
                             body, cfg=model_cfg, options=lift.static_options(options))
        outputs.append(jax.device_get(out))
    return {k: np.concatenate([o[k] for o in outputs])[:m] for k in outputs[0]}


def training_views_mean(variables, data: KeypointData, model_cfg: model.ModelConfig,
                        options: InferenceConfig, max_views: int = VIEWS_MEAN_VIEWS,
                        batch_size: int = 1024) -> tuple[tuple, float]:
    """The rows of ``handedness_reference="views_mean"``: each point's mean canonical shape
    over up to ``max_views`` views of ``data`` (the training split; a fixed random choice)
    as the model lifts them with ``options``, each with its own handedness, over the views
    whose class has the point; and the share of those views whose canonical shape reverses
    the rows' small corners (``lift.local_handedness_evidence`` < 0)."""
    idx = np.sort(np.random.default_rng(0).permutation(len(data))[:max_views])
    views = data.subset(idx)
    pred = predict_split(variables, views, model_cfg, lift.without_handedness(options),
                         batch_size)
    shapes = jax.numpy.asarray(pred["shape_canonical"], jax.numpy.float32)
    mask = jax.numpy.asarray(views.model_inputs()["class_mask"], jax.numpy.float32)
    rows = geometry.point_means(shapes, mask)
    evidence = jax.vmap(lift.local_handedness_evidence, (0, None, 0))(shapes, rows, mask)
    return (tuple(tuple(float(v) for v in row) for row in np.asarray(rows)),
            float(np.mean(np.asarray(evidence) < 0)))


def with_views_mean(options: InferenceConfig, variables, data: KeypointData,
                    model_cfg: model.ModelConfig) -> tuple[InferenceConfig, float | None]:
    """``options`` with the training views' mean rows of ``variables`` filled in, when its
    reference is "views_mean" (``training_views_mean`` of ``data``), and the share of those
    views whose own canonical shape reverses the rows' small corners; else ``options`` as
    they are and None. With the tetrahedra evidence, when that share is above
    ``TETRAHEDRA_TRUST`` (shapes whose points deform freely, so that a corner's chirality
    does not name a view's handedness), or when the rows lie near one plane
    (``bodies.body_problem``), the views keep the model's own handedness instead (the
    reference "mean_shape", without ``one_handedness``)."""
    if options.handedness_reference != "views_mean":
        return options, None
    rows, reversed_share = training_views_mean(variables, data, model_cfg, options)
    flat = bodies.body_problem(rows, model_cfg.n_keypoints)  # no handedness to give
    if flat or (options.handedness_evidence == "tetrahedra"
                and reversed_share > TETRAHEDRA_TRUST):
        return lift.without_handedness(options), reversed_share
    return dataclasses.replace(options, handedness_body=rows), reversed_share


def evaluate_split(variables, data: KeypointData, model_cfg: model.ModelConfig,
                   options: InferenceConfig, protocol: str, batch_size: int = 1024) -> dict:
    """Test metrics: MPJPE/stress when the split has 3D ground truth, and always the
    2D reprojection error of the visible points (the only score for 2D-only data) and,
    for single-class data, ``mirrored`` (``evaluation.mirrored_fraction``: how mixed the
    handedness of the canonical shapes is, also without 3D ground truth; the model's own
    shapes, before ``one_handedness`` gives every view one handedness, so that it says what
    training learnt)."""
    pred = predict_split(variables, data, model_cfg, options, batch_size)
    # kp_reprojected is in the input's units (pixels for perspective models too).
    reproj = evaluation.reprojection_error(pred["kp_reprojected"], data)
    out = {"n_samples": len(data), "reprojection": reproj}
    if data.class_mask is None:  # one object class: one mean shape to compare handedness
        out["mirrored"] = evaluation.mirrored_fraction(
            lift.own_handedness(pred["shape_canonical"], pred["handedness_flipped"]))
    if data.kp3d is not None and protocol != "none":
        out.update(evaluation.evaluate(pred["shape_3d"], data, protocol))
    return out


def evaluate_baselines(train: KeypointData, test: KeypointData, protocol: str) -> dict:
    """Scores of the trivial baselines (orthographic data with 3D ground truth only)."""
    if train.kp3d is None or test.kp3d is None or test.intrinsics is not None or protocol == "none":
        return {}
    mean_shape = baselines.procrustes_mean_shape(train.kp3d)
    preds = baselines.predict(mean_shape, test.kp, test.vis)
    return {name: evaluation.evaluate(p, test, protocol) for name, p in preds.items()}
