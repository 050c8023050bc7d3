"""Settings a config leaves to the training data, resolved once, before training.

``resolve_from_data(config, train_data, saved)`` returns a copy of the config with each of
them set: the input scale (``model.keypoint_rescale = 0``), the scaling of each view
(``model.keypoint_scaling = "auto"``) and the body whose handedness the views take at
inference (``inference.handedness_reference``: "auto" or a body file). A run's config.json
holds the values, so that inference, a resumed run and ``--mode=eval`` use the same ones:
``saved`` (a workdir's config.json) wins where it has them. ``train.train_and_evaluate``
and ``evaluate_workdir.evaluate_checkpoint`` call it; so do experiments that build a model
by hand.

Glossary: M views of the training split, N keypoints.
"""

import numpy as np
from absl import logging

from c3dpo_jax import baselines, lift
from c3dpo_jax.data import KeypointData, alike_view_size_ratio, auto_keypoint_rescale, bodies

# Evidence: experiments/dev_suite/handedness.md, "The handedness of a human body".
BODY_FIT_2D = 0.6  # resolve_handedness: a body's fit below it names the views' joint order
BODY_FIT_VIEWS = 500  # training views it is measured on (evenly spaced through the split)
# Evidence: experiments/dev_suite/data_variants.md, "People at different distances".
ALIKE_SIZE_RATIO = 1.18  # resolve_keypoint_scaling: views' size ratio above it, per view
# How "auto" without a body weighs a view against the training views' mean: its output, by
# its tetrahedra (evidence: experiments/dev_suite/handedness.md, "The decision at the output").
VIEWS_MEAN_SETTINGS = {"handedness_evidence": "tetrahedra", "handedness_from_output": True}


def resolve_input_scale(config, train_data: KeypointData, saved: dict | None = None):
    """``model.keypoint_rescale = 0`` means "from the data": a copy of ``config`` with the
    value a saved config (``saved``, a workdir's config.json) holds, else the one
    ``auto_keypoint_rescale`` gives for the training split (written to config.json, so
    inference uses the same number); other values are returned unchanged."""
    if config.model.keypoint_rescale != 0:
        return config
    config = config.copy_and_resolve_references()
    perspective = config.model.projection_type == "perspective"
    config.model.keypoint_rescale = ((saved or {}).get("model", {}).get("keypoint_rescale")
                                     or auto_keypoint_rescale(train_data, calibrate=perspective))
    logging.info("input scale from the training data: model.keypoint_rescale=%.6g",
                 config.model.keypoint_rescale)
    return config


def body_fit_2d(body: np.ndarray, data: KeypointData, n_views: int = BODY_FIT_VIEWS) -> float:
    """The median over up to ``n_views`` views of ``data`` of the RMS 2D distance of the
    body's projection under the view's best rigid camera (``baselines.fit_camera``) to its
    visible points, over their RMS radius about their mean (0: the body itself; about 1:
    no likeness)."""
    idx = np.unique(np.linspace(0, len(data) - 1, min(n_views, len(data))).astype(int))
    kp, vis = data.kp[idx].astype(np.float64), data.vis[idx].astype(np.float64)
    camera = baselines.fit_camera(np.asarray(body, np.float64), kp, vis)
    error = baselines.reprojection_residual(baselines.project(*camera), kp, vis)
    centred = kp - baselines.visible_mean(kp, vis)[:, None]
    radius = baselines.visible_mean((centred ** 2).sum(-1, keepdims=True), vis)[:, 0]
    return float(np.median(np.sqrt(error / np.maximum(radius, 1e-12))))


def resolve_handedness(config, train_data: KeypointData, saved: dict | None = None):
    """``inference.handedness_reference = "auto"`` means "from the data": a copy of
    ``config`` with the value (and ``one_handedness``, or on if ``config`` turns it on) a
    saved config holds, else the built-in body (``bodies.HUMAN_BODIES``) of the model's
    number of points whose projections fit the training views best, if they fit it
    (``body_fit_2d`` below ``BODY_FIT_2D``: points in its joint order), with
    ``one_handedness`` on (the body decides each view: a model's own views can split even
    when trained to one handedness; evidence: experiments/dev_suite/handedness.md), else
    "views_mean" with ``one_handedness`` on and ``VIEWS_MEAN_SETTINGS`` (each output takes
    the handedness its small tetrahedra show against the training views' mean canonical
    shape, whose rows the run fills, or the model's own where the training views' shapes do
    not keep their corners: ``inference.with_views_mean``); "mean_shape" for a perspective
    model (a saved "views_mean" keeps how its views were weighed). A body file
    (``bodies.BODY_FILE_SUFFIXES``) is read into ``handedness_body`` with the reference
    "body" and ``one_handedness`` on (a saved config's body, when it has one: a resumed run
    keeps the body it started with). Other values are returned unchanged."""
    reference = config.inference.handedness_reference
    before = lift.saved_options(saved or {})
    if bodies.is_body_file(reference):
        config = config.copy_and_resolve_references()
        if before.get("handedness_reference") == "body":
            body = np.asarray(before["handedness_body"], np.float64)
        else:
            body = bodies.read_body(reference)
        if why := bodies.body_problem(body, config.model.n_keypoints):
            raise ValueError(f"config.inference.handedness_reference={reference!r} ({why})")
        config.inference.handedness_reference = "body"
        config.inference.handedness_body = tuple(map(tuple, body.tolist()))
        config.inference.one_handedness = True
        return config
    if reference != "auto":
        return config
    config = config.copy_and_resolve_references()
    if before.get("handedness_reference", "auto") != "auto":
        config.inference.handedness_reference = before["handedness_reference"]
        # one_handedness=True given now (e.g. --mode=eval) holds beside the saved reference
        config.inference.one_handedness = (bool(before.get("one_handedness"))
                                           or bool(config.inference.one_handedness))
        if before["handedness_reference"] == "views_mean":  # and how it was weighed
            for key in VIEWS_MEAN_SETTINGS:
                config.inference[key] = before.get(key, VIEWS_MEAN_SETTINGS[key])
        return config
    config.inference.handedness_reference = "mean_shape"
    if config.model.projection_type != "orthographic":
        return config
    fits = {name: body_fit_2d(bodies.human_body(name), train_data)
            for name, n in bodies.HUMAN_BODIES.items() if n == config.model.n_keypoints}
    name = min(fits, key=fits.get, default=None)  # bodies of one number of points: the nearest
    if name is not None and fits[name] < BODY_FIT_2D:
        config.inference.handedness_reference = name
        config.inference.one_handedness = True
        logging.info("handedness at inference from the %r body: the training views fit its "
                     "joint order (2D distance %.2f, below %.2f)", name, fits[name], BODY_FIT_2D)
        return config
    config.inference.handedness_reference = "views_mean"
    config.inference.one_handedness = True
    config.inference.update(VIEWS_MEAN_SETTINGS)
    return config


def resolve_keypoint_scaling(config, train_data: KeypointData, saved: dict | None = None):
    """``model.keypoint_scaling = "auto"`` means "from the data": a copy of ``config`` with
    the value a saved config holds ("global" for one that predates the option), else
    "per_view" for an orthographic model whose training views that look alike differ in
    size by more than ``ALIKE_SIZE_RATIO`` (subjects at different distances), else
    "global"; other values are returned unchanged."""
    if config.model.get("keypoint_scaling") != "auto":
        return config
    config = config.copy_and_resolve_references()
    if saved and "model" in saved:  # a run made before the option had one input scale
        config.model.keypoint_scaling = saved["model"].get("keypoint_scaling", "global")
        if config.model.keypoint_scaling != "auto":
            return config
    config.model.keypoint_scaling = "global"
    if config.model.projection_type != "orthographic":
        return config
    ratio = alike_view_size_ratio(train_data)
    if ratio > ALIKE_SIZE_RATIO:
        config.model.keypoint_scaling = "per_view"
        logging.info("each view scaled by its own size (model.keypoint_scaling=per_view): "
                     "training views that look alike differ in size by %.2fx (median), above "
                     "%.2fx, as for subjects at different distances", ratio, ALIKE_SIZE_RATIO)
    return config


def resolve_from_data(config, train_data: KeypointData, saved: dict | None = None):
    """``config`` with the settings it leaves to the training data resolved: the input scale
    (``resolve_input_scale``), the scaling of each view (``resolve_keypoint_scaling``) and the
    handedness at inference (``resolve_handedness``), each from ``saved`` (a workdir's
    config.json) when it holds them."""
    config = resolve_keypoint_scaling(resolve_input_scale(config, train_data, saved),
                                      train_data, saved)
    return resolve_handedness(config, train_data, saved)
