"""Use a trained model: ``load(workdir)`` then ``reconstruct(params, kp, vis)``.

Glossary: B batch, N keypoints, D shape-basis size. Inputs are user coordinates
(pixels, or whatever units the model was trained on), points on the last axis:
``kp (N, 2)`` or ``(B, N, 2)``, ``vis (N,)`` or ``(B, N)`` in {0, 1}.

``reconstruct`` checks its input on the host (clear one-line ``ValueError`` s, before
any tracing: shapes, an empty batch, NaN/inf or absurd values at visible points, a
sample with nothing visible; a warning when the keypoints' scale is far from the training
data's), pads the batch to the next power of two and runs the one jitted batched
eval forward (``inference.forward_batch`` of ``lift.forward_eval``, with the model's
inference options or the ones passed): a model compiles once per bucket size (1, 2, 4,
...), not once per batch size. Outputs are numpy arrays with the input's leading
dimensions.
"""

import json
import os
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from absl import logging
from jax.typing import ArrayLike

from c3dpo_jax import checkpoint, inference, lift, model, run_config
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.model import ModelConfig


@flax.struct.dataclass
class C3DPOParams:
    """A model ready for inference: ``{"params", "batch_stats"}``, what the network is
    (``config``) and how it lifts a view (``inference``, its own options, which
    ``reconstruct``'s arguments override), both static."""

    variables: Any
    config: ModelConfig = flax.struct.field(pytree_node=False)
    inference: InferenceConfig = flax.struct.field(pytree_node=False, default=InferenceConfig())


class Reconstruction(NamedTuple):
    """Numpy outputs; leading dims ``*B`` as the input's (none for one sample).

    shape_3d (*B, N, 3): the 3D points in the camera frame, in the input's units
      (``model.Prediction.shape_3d``): x, y are the input itself at visible
      points and the reprojection at hidden ones; depth is relative (compare shapes with
      their mean depth removed) and, from one view, its sign is ambiguous (a view and its
      depth mirror image fit the same points). A perspective model's x, y are calibrated
      (``K^-1`` applied), not pixels.
    shape_canonical (*B, N, 3): the shape in the model's canonical frame, in the network's
      units (the input times ``params.config.keypoint_rescale``, centred; with
      ``keypoint_scaling="per_view"`` each view at unit RMS radius): up to the model's scale and
      translation, the camera-frame shape in those units is ``shape_canonical @
      rotation.T``.
    rotation (*B, 3, 3): the camera rotation (canonical frame -> camera frame).
    alpha (*B, D): shape-basis coefficients.
    kp_reprojected (*B, N, 2): the 3D shape projected back to input coordinates.
    """

    shape_3d: np.ndarray
    shape_canonical: np.ndarray
    rotation: np.ndarray
    alpha: np.ndarray
    kp_reprojected: np.ndarray


def split_path(path: str) -> tuple[str, int | None]:
    """``workdir`` or ``workdir/checkpoints/<step>`` -> (workdir, step or None)."""
    path = os.path.abspath(os.path.expanduser(path))
    if os.path.exists(os.path.join(path, run_config.CONFIG_FILE)):
        return path, None
    parent, step = os.path.split(path)
    workdir, ckpt_dir = os.path.split(parent)
    if ckpt_dir == checkpoint.CHECKPOINT_DIR and step.isdigit():
        return workdir, int(step)
    raise FileNotFoundError(
        f"{path!r} is neither a workdir (with {run_config.CONFIG_FILE}) nor a "
        f"checkpoint step directory (WORKDIR/{checkpoint.CHECKPOINT_DIR}/<step>)"
    )


def load(path: str) -> C3DPOParams:
    """Loads a trained model from a workdir (latest step) or one checkpoint step dir."""
    workdir, step = split_path(path)
    config = run_config.load_config(workdir)
    if config is None or "model" not in config:
        raise ValueError(f"{workdir}/{run_config.CONFIG_FILE} has no 'model' section")
    model_cfg = ModelConfig.from_dict(config["model"])
    options = lift.inference_config(
        model_cfg, InferenceConfig.from_dict(lift.saved_options(config)))
    variables, _ = checkpoint.restore_variables(workdir, model.variables_shape(model_cfg), step)
    return C3DPOParams(variables=variables, config=model_cfg, inference=options)


def save_workdir(params: C3DPOParams, workdir: str, config_dict: dict | None = None) -> str:
    """Writes ``params`` as a c3dpo_jax workdir (config.json + an orbax checkpoint of the
    variables) that ``load``, ``predict`` and ``--mode=eval`` read. It holds no optimiser
    state: it is a model to use, not a run to resume.

    Args:
      params: the model.
      workdir: directory to create.
      config_dict: a full resolved config (e.g. ``get_config().to_dict()``); its
        ``model`` and ``inference`` sections are replaced by ``params``' own.

    Returns:
      The workdir.
    """
    config = json.loads(json.dumps(dict(config_dict or {}), default=list))
    config["model"] = params.config.to_dict()
    config["inference"] = params.inference.to_dict()
    config["software"] = [run_config.software_record()]  # what wrote it (e.g. a conversion)
    os.makedirs(workdir, exist_ok=True)
    run_config.save_config(workdir, config)
    checkpoint.save_variables(workdir, params.variables)
    return workdir


# Centred visible points further than this from their mean, in the model's normalised
# units (training data lies within a few units), are not keypoints the model can read.
MAX_NORMALISED_EXTENT = 1e4


def _numeric(name: str, x, dtype=np.float32) -> np.ndarray:
    if isinstance(x, jax.core.Tracer):
        raise ValueError(f"{name} is a traced value: reconstruct runs on the host (it checks "
                         "its input, then runs one compiled batch); under jax.jit, vmap or "
                         "grad use inference.forward_batch or lift.forward_eval")
    try:
        raw = np.asarray(x)
        if not np.iscomplexobj(raw):
            return raw.astype(dtype)
    except (TypeError, ValueError) as err:
        first = (str(err).splitlines() or [""])[0]
        raise ValueError(f"{name} is not a numeric array (a ragged or non-numeric list? "
                         f"{first})") from None
    raise ValueError(f"{name} is complex; keypoints are real coordinates")


def _as_batch(name: str, x, tail: tuple[int, ...], single: bool, finite: bool = True,
              dtype=np.float32):
    x = _numeric(name, x, dtype)
    want = tail if single else ("B", *tail)
    if x.ndim != len(want) or x.shape[x.ndim - len(tail):] != tail:
        raise ValueError(f"{name} has shape {x.shape}, expected "
                         f"({', '.join(str(d) for d in want)}{',' if len(want) == 1 else ''})")
    if finite and not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf")
    return x[None] if single else x


def _samples(idx: np.ndarray) -> str:
    return f"sample(s) {idx[:10].tolist()}" + (" ..." if idx.size > 10 else "")


def _check_values(cfg: ModelConfig, kp: np.ndarray, vis: np.ndarray, K) -> np.ndarray:
    """Visible points must be finite, and their spread in the model's normalised units
    below ``MAX_NORMALISED_EXTENT`` (float32 cannot reconstruct 1e20-sized inputs).
    Returns their mean (B, 1, 2) in float64 (of the calibrated points when ``K`` is given)."""
    shown = vis[..., None] > 0
    bad = np.flatnonzero((shown & ~np.isfinite(kp)).any((1, 2)))
    if bad.size:
        raise ValueError(f"kp contains NaN or inf at visible points of {_samples(bad)}")
    pts = np.where(shown, kp, 0.0).astype(np.float64)
    if K is not None:  # the model centres and scales calibrated points
        homog = np.concatenate([pts, np.ones_like(pts[..., :1])], -1)
        ray = np.einsum("bij,bnj->bni", np.linalg.inv(np.asarray(K, np.float64)), homog)
        with np.errstate(divide="ignore", invalid="ignore"):
            pts = ray[..., :2] / ray[..., 2:]
    mean = (pts * shown).sum(1, keepdims=True) / np.maximum(shown.sum(1, keepdims=True), 1)
    with np.errstate(invalid="ignore", over="ignore"):
        extent = np.where(shown, np.abs(pts - mean), 0.0).max((1, 2)) * cfg.keypoint_rescale
    bad = np.flatnonzero(~(extent <= MAX_NORMALISED_EXTENT))
    if bad.size:
        raise ValueError(
            f"kp of {_samples(bad)}: the visible points lie up to {extent[bad[0]]:.3g} from "
            f"their mean in the model's normalised units (keypoint_rescale "
            f"{cfg.keypoint_rescale:g}; its training data lies within a few units, the limit "
            f"is {MAX_NORMALISED_EXTENT:g}): are the coordinates corrupt or in other units?")
    if cfg.keypoint_scaling != "per_view":  # one that scales each view itself takes any units
        _warn_if_other_units(cfg, pts, shown, mean)
    return mean


# A warning when the inputs' scale is further than this factor from the training data's.
SCALE_WARNING_RATIO = 3.0


def _input_scale_ratio(cfg: ModelConfig, pts: np.ndarray, shown: np.ndarray,
                      mean: np.ndarray) -> float:
    """The inputs' median RMS radius about their visible mean in the model's normalised
    units (``keypoint_rescale`` times the input's; calibrated points for perspective
    models). The training views' is 1: the input scale is set so (``keypoint_rescale=0``)
    or was fixed by the paper's rule of about that. Views whose visible points coincide
    have no scale (``_warn_if_other_units`` names them); nan when no view has one."""
    count = shown[..., 0].sum(1)
    scaled = (count > 1) & ~_coincide(pts, shown)
    sq = (np.where(shown, pts - mean, 0.0) ** 2).sum((1, 2))
    with np.errstate(invalid="ignore", over="ignore"):
        radius = np.sqrt(sq[scaled] / count[scaled]) * cfg.keypoint_rescale
    return float(np.median(radius)) if radius.size else float("nan")


def _coincide(pts: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """(B,) whether a view's two or more visible points are all at one place."""
    hi = np.where(shown, pts, -np.inf).max(1)
    lo = np.where(shown, pts, np.inf).min(1)
    return (shown[..., 0].sum(1) > 1) & np.all(hi == lo, -1)


def _warn_if_other_units(cfg: ModelConfig, pts, shown, mean) -> None:
    """One warning line for views whose two or more visible points all coincide (no shape
    to lift), and one when the other views' scale is beyond ``SCALE_WARNING_RATIO`` times
    the training data's."""
    coincide = np.flatnonzero(_coincide(pts, shown))
    if coincide.size:
        logging.warning("kp of %s: the visible points coincide (all at one place), so the "
                        "view shows no shape; its 3D shape is the model's guess",
                        _samples(coincide))
    ratio = _input_scale_ratio(cfg, pts, shown, mean)
    if ratio > SCALE_WARNING_RATIO or ratio < 1 / SCALE_WARNING_RATIO:
        logging.warning(
            "kp: the keypoints' spread is %.3gx the training data's (median RMS radius %.3g "
            "in the model's normalised units, the training views' 1; keypoint_rescale %g): "
            "keypoints in other units (e.g. pixels for a model trained in metres) give a "
            "wrong 3D shape; convert them to the training data's units",
            ratio, ratio, cfg.keypoint_rescale)


def _check_inputs(cfg: ModelConfig, kp, vis, K, class_mask):
    """Host-side validation; returns batched float32 arrays (K and class_mask may be None)
    and, for an orthographic model, each view's kp centred on its visible points in float64
    with that centre ``offset`` (B, 1, 2) (0 for a perspective model, whose calibration is
    not translation-invariant): coordinates far from 0 (e.g. 1e6) keep their precision."""
    n = cfg.n_keypoints
    kp = _numeric("kp", kp, np.float64)
    if kp.ndim not in (2, 3) or kp.shape[-1] != 2:
        raise ValueError(f"kp has shape {kp.shape}, expected (N, 2) or (B, N, 2) with N = {n}")
    if kp.shape[-2] != n:
        raise ValueError(f"kp has {kp.shape[-2]} keypoints but the model expects N = {n}")
    single = kp.ndim == 2
    if not single and kp.shape[0] == 0:
        raise ValueError("kp is an empty batch (B = 0): pass at least one sample")
    kp = _as_batch("kp", kp, (n, 2), single, finite=False,  # hidden points may hold anything
                   dtype=np.float64)
    vis = _as_batch("vis", vis, (n,), single)
    if vis.shape[0] != kp.shape[0]:
        raise ValueError(f"vis has batch size {vis.shape[0]} but kp has {kp.shape[0]}")
    if np.any((vis != 0) & (vis != 1)):
        raise ValueError("vis must contain only 0 and 1")
    empty = np.flatnonzero(vis.sum(axis=1) == 0)
    if empty.size:
        raise ValueError(f"{_samples(empty)} have no visible keypoint")
    lone = np.flatnonzero(vis.sum(axis=1) == 1)
    if lone.size:  # training needs two (data.min_visible): one point says nothing of the shape
        logging.warning("%s have one visible keypoint: their 3D shape is the model's guess, "
                        "not a lift of the view", _samples(lone))
    if class_mask is not None:
        one = np.ndim(class_mask) == 1
        class_mask = np.broadcast_to(_as_batch("class_mask", class_mask, (n,), one), vis.shape)
        if np.any((class_mask != 0) & (class_mask != 1)):
            raise ValueError("class_mask must contain only 0 and 1")
        outside = np.flatnonzero((vis * (1 - class_mask)).sum(1) > 0)
        if outside.size:  # the model's shape is 0 there: those points are not lifted
            logging.warning("%s have visible keypoints outside their class_mask: the model "
                            "lifts only the points of its class", _samples(outside))
    if cfg.projection_type == "perspective":
        if K is None:
            raise ValueError(
                "this is a perspective model: pass the intrinsics K, (3, 3) or (B, 3, 3)")
        K = _as_batch("K", K, (3, 3), np.ndim(K) == 2)
        if K.shape[0] not in (1, vis.shape[0]):
            raise ValueError(f"K has batch size {K.shape[0]} but kp has {vis.shape[0]} (give one "
                             "K for all, or one per sample)")
        K = np.broadcast_to(K, (*vis.shape[:1], 3, 3))
        with np.errstate(all="ignore"):
            singular = np.flatnonzero(~(np.abs(np.linalg.det(K.astype(np.float64))) > 1e-12))
        if singular.size:
            raise ValueError(f"K of {_samples(singular)} is singular: intrinsics have a focal "
                             "length on the diagonal and [0, 0, 1] as the last row")
        big = np.abs(K).max((1, 2))
        skewed = np.flatnonzero(np.abs(K[:, 2, :2]).max(1) > 1e-6 * big)
        if skewed.size:
            row = K[skewed[0], 2].tolist()
            raise ValueError(f"K of {_samples(skewed)} has the last row {row}: intrinsics have "
                             "[0, 0, 1] there and the principal point in the last column (a "
                             "transposed K?)")
    elif K is not None:
        raise ValueError("K was given but the model is orthographic (it takes no intrinsics)")
    mean = _check_values(cfg, kp, vis, K)  # (B, 1, 2) of the visible points, float64
    # The model is translation-equivariant for orthographic views, not for perspective ones.
    offset = np.zeros_like(mean) if cfg.projection_type == "perspective" else mean
    kp = np.where(vis[..., None] > 0, kp - offset, 0.0).astype(np.float32)
    return single, kp, offset, vis, K, class_mask


@jax.jit
def _reconstruct_batch(params: C3DPOParams, kp, vis, class_mask, K, body):
    out = inference.forward_batch(params.variables, kp, vis, class_mask, K, body,
                                  params.config, params.inference)
    return Reconstruction(out.shape_3d, out.shape_canonical, out.rotation, out.alpha,
                          out.kp_reprojected)


# The median distance of the views' canonical shapes to a body of ``HANDEDNESS_REFERENCES``
# (each shape and the body centred and scaled to unit norm, after the best rotation or
# reflection: 0 for copies of the body, at most sqrt(2)) above which the points are
# probably in another joint order (evidence: experiments/dev_suite/handedness.md).
BODY_DISTANCE_WARNING = 0.8


def body_distance(shapes, body) -> np.ndarray:
    """(B,) distance of each shape (B, N, 3) to ``body`` (N, 3) up to a rotation, a
    reflection and a scale: both centred and of unit norm, sqrt(2 - 2 * the sum of the
    singular values of their cross-covariance)."""
    def unit(x):
        x = x - x.mean(-2, keepdims=True)
        return x / np.maximum(np.linalg.norm(x, axis=(-2, -1), keepdims=True), 1e-12)

    shapes, body = unit(np.asarray(shapes, np.float64)), unit(np.asarray(body, np.float64))
    sigma = np.linalg.svd(np.einsum("bni,nj->bij", shapes, body), compute_uv=False)
    return np.sqrt(np.maximum(2.0 - 2.0 * sigma.sum(-1), 0.0))


def _warn_if_not_the_body(options: InferenceConfig, body, canonical: np.ndarray) -> None:
    """A warning when the views, taking their handedness from ``body`` (None: none), do not
    look like it: points in another order than the body's take a handedness that means
    nothing."""
    if body is None:
        return
    distance = float(np.median(body_distance(canonical, np.asarray(body))))
    if distance > BODY_DISTANCE_WARNING:
        name = options.handedness_reference
        logging.warning(
            "the views' shapes are far from %s whose handedness they were given (median "
            "distance %.2f up to a rotation, mirror and scale; views in its joint order are "
            "within about 0.5, shuffled points about 1.3): check that the points are in its "
            "joint order (%s), or the handedness may be wrong",
            "the given body" if name == "body" else f"the {name!r} body", distance,
            "the model's" if name == "body" else "lift.HANDEDNESS_REFERENCES")


@model.single_precision
def reconstruct(
    params: C3DPOParams,
    kp: ArrayLike | list,
    vis: ArrayLike | list,
    K: ArrayLike | None = None,
    class_mask: ArrayLike | None = None,
    **options,
) -> Reconstruction:
    """3D reconstruction of 2D keypoints with a trained model (eval mode).

    Args:
      params: from ``load`` or ``convert.from_official``.
      kp: (N, 2) or (B, N, 2) keypoints in the units the model was trained on
        (invisible points may hold anything, NaN included; they are zeroed).
      vis: (N,) or (B, N), 1 visible, 0 not; every sample needs a visible point.
      K: intrinsics (3, 3) or (B, 3, 3); required by perspective models only.
      class_mask: (N,) or (B, N) block of the sample's class (multi-class models).
      **options: inference options, each a field of ``lift.InferenceConfig`` by its name
        (None or absent: the model's own, ``params.inference``): ``refine_iters``,
        ``refine_prior``, ``turns``, ``turn_span``, ``one_handedness``,
        ``handedness_reference``, ``handedness_body``, ``replace_keypoints_with_input``.
        ``handedness_reference`` (and ``handedness_body``) also take one 3D example of the
        points, an (N, 3) array or a file (``bodies.read_body``: .npy, .json, .txt, .csv),
        in any position, orientation and scale; a body given without ``one_handedness``
        turns it on, and with ``one_handedness=False`` it gives the whole model one mirror
        decision (``lift.InferenceConfig``). Checked against the model in one line
        (``lift.inference_config``).

    Returns:
      A ``Reconstruction`` of numpy arrays with the input's leading dimensions;
      ``shape_3d`` and ``kp_reprojected`` are float64 unless ``kp`` is a float32 (or
      float16) array, so coordinates far from 0 keep their precision (an orthographic
      model lifts each view centred on its visible points, in float64).
    """
    params = params.replace(inference=lift.inference_config(params.config, params.inference,
                                                            **options))
    precise = getattr(kp, "dtype", None) not in (np.float32, np.float16)  # lists: float64
    single, kp, offset, vis, K, class_mask = _check_inputs(params.config, kp, vis, K,
                                                           class_mask)
    if class_mask is None:
        class_mask = np.ones_like(vis)
    b = kp.shape[0]
    idx = inference.wrap_indices(0, inference.bucket_size(b), b)
    padded = [None if a is None else jnp.asarray(a[idx]) for a in (kp, vis, class_mask, K)]
    body = lift.options_body(params.inference)
    out = Reconstruction(*(np.asarray(a[:b]) for a in jax.device_get(
        _reconstruct_batch(params, *padded, body))))
    # The centre back on, in the input's precision (float32 for float32 input).
    dtype = np.float64 if precise else np.float32
    out = out._replace(
        shape_3d=np.concatenate([out.shape_3d[..., :2] + offset, out.shape_3d[..., 2:]],
                                -1).astype(dtype),
        kp_reprojected=(out.kp_reprojected + offset).astype(dtype))
    bad = np.flatnonzero(~np.isfinite(out.shape_3d).all((1, 2)))
    if bad.size:  # a safety net: the checks above should leave nothing to catch here
        raise ValueError(f"the reconstruction of {_samples(bad)} is not finite")
    _warn_if_not_the_body(params.inference, body, out.shape_canonical)
    return Reconstruction(*(a[0] if single else a for a in out))


def reconstruct_data(params: C3DPOParams, data, n: int | None = None) -> Reconstruction:
    """``reconstruct`` of the first ``n`` samples (all: None) of a ``KeypointData``, with its
    class masks and, for a perspective model, its intrinsics."""
    n = len(data) if n is None else min(n, len(data))
    perspective = params.config.projection_type == "perspective"
    return reconstruct(params, data.kp[:n], data.vis[:n],
                       K=data.intrinsics[:n] if perspective else None,
                       class_mask=None if data.class_mask is None else data.class_mask[:n])
