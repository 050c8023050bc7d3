"""C3DPO's pure forward passes, for ONE example, plus the model's static settings.

Glossary: N keypoints, D shape-basis size, S canonicalisation samples. Points are
rows: ``kp (N, 2)``, ``X (N, 3)``; rotations act as ``X @ R.T`` (see ``so3``).

``forward_train`` must run under ``jax.vmap(..., axis_name="batch")`` (BatchNorm
takes its statistics over that axis); ``forward_eval`` uses running statistics and
runs anywhere. Paper equations: reprojection (eq. 4, l1), canonicalisation (eq. 5,
l2), in-plane equivariance (eq. 6, l3). The model is geometry: given an example and
its random rotations (``TrainRotations``) it returns squared distances, and ``losses``
draws the rotations and turns the distances into the objective (penalty, reductions,
weights, with their options in ``losses.LossConfig``).
"""

import contextlib
import dataclasses
import functools
import json
import os
from collections.abc import Mapping
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np
from jaxtyping import Array, Float

from c3dpo_jax import geometry, so3
from c3dpo_jax.networks import C3DPONet
from c3dpo_jax.types import Kp2, Kp3, Vis

Variables = dict[str, Any]
# A pytree leaf: a jax.Array, numpy after ``device_get``, a ShapeDtypeStruct under
# ``eval_shape`` (so a field's annotation cannot be ``Array``; shapes are in docstrings).
Leaf = Any


@flax.struct.dataclass
class Prediction(Mapping):
    """``forward_eval``'s outputs for one example (under ``vmap``, each with a leading B).

    A frozen dataclass and a pytree (``vmap``, ``jit`` and ``device_get`` keep the type),
    and a read-only mapping from field name to array, so ``pred.alpha``,
    ``pred["alpha"]``, ``pred.items()`` and ``dict(pred)`` all work (the mapping view
    serves code that reads the outputs as a dict). "Normalised" is the network's frame: the input
    centred (``kp_mean``) and times ``keypoint_rescale`` (and over the view's RMS radius
    with ``keypoint_scaling="per_view"``), after calibration with K for perspective models.

    Attributes:
      shape_image_coord: (N, 3) the 3D output in the input's coordinates: xy the input
        where visible (``replace_keypoints_with_input``) else the reprojection, depth
        divided by the normalisation's factor (``keypoint_rescale``; calibrated units for
        perspective models).
      shape_camera: (N, 3) ``scale * X @ R.T + translation``, normalised; with
        ``test_time_turns`` > 1 its depth (and shape_image_coord's) is the median over
        the turned copies kept, while X, R, theta and alpha are the unturned view's.
      shape_canonical: (N, 3) the canonical shape X (points outside the class are 0).
      rotation: (3, 3) the camera rotation R = exp_map(theta).
      theta: (3,) R's axis-angle vector.
      alpha: (D,) shape-basis coefficients (with ``test_time_refine_iters`` > 0, theta
        and alpha are Phi's refined; see ``refine_camera_and_shape``). With
        ``test_time_one_handedness``, a view given its mirror image has X the mirror of
        the basis' shape for alpha, and R, theta and the depth mirrored to match
        (``one_handedness``).
      translation: (3,) camera translation (zeros + ``depth_offset`` unless predicted).
      scale: () camera scale (1 unless ``camera_scale``).
      kp_reprojected: (N, 2) shape_camera projected back to input coordinates (pixels
        for perspective models).
      kp_norm: (N, 2) the network's normalised input.
      kp_mean: (2,) the centre removed from the input (calibrated for perspective).
      kp_scale: () the factor the centred input was multiplied by (``keypoint_rescale``,
        over the view's RMS radius with ``keypoint_scaling="per_view"``): the normalised
        frame's units are the input's times it.
      dist_sq: (N,) squared distance of each reprojected point to the normalised input,
        unmasked (``losses.LossConfig.penalty`` turns it into the reprojection term).
      handedness_flipped: () 1 where ``test_time_one_handedness`` gave the view its mirror
        image, else 0: ``shape_canonical`` with its third axis negated there is the model's
        own canonical shape (``own_handedness``).
    """

    shape_image_coord: Leaf
    shape_camera: Leaf
    shape_canonical: Leaf
    rotation: Leaf
    theta: Leaf
    alpha: Leaf
    translation: Leaf
    scale: Leaf
    kp_reprojected: Leaf
    kp_norm: Leaf
    kp_mean: Leaf
    kp_scale: Leaf
    dist_sq: Leaf
    handedness_flipped: Leaf

    def __getitem__(self, name: str) -> Leaf:
        if name not in _PREDICTION_FIELDS:
            raise KeyError(name)
        return getattr(self, name)

    def __iter__(self):
        return iter(_PREDICTION_FIELDS)

    def __len__(self) -> int:
        return len(_PREDICTION_FIELDS)


_PREDICTION_FIELDS = tuple(f.name for f in dataclasses.fields(Prediction))


def own_handedness(shapes, handedness_flipped):
    """Shapes ``(..., N, 3)`` of a ``Prediction`` with the mirroring of
    ``test_time_one_handedness`` undone (the third axis negated where ``handedness_flipped``,
    shape ``(...)``): the model's own ``shape_canonical``, and its own camera-frame or
    image-coordinate depths up to their offset; numpy or jax arrays alike."""
    flipped = handedness_flipped[..., None, None] > 0
    return shapes * (1.0 - 2.0 * (flipped & (np.arange(3) == 2)))


class TrainRotations(NamedTuple):
    """The random rotations of one training example (drawn by ``losses.draw_rotations``).

    Attributes:
      augment: (2, 2) in-plane rotation of the input, undone on the output (identity
        without ``z_augment``).
      equivariance: (2, 2) in-plane rotation of the second copy whose shape coefficients
        are used (eq. 6; unused without ``z_equivariance``).
      canonicalisation: (S, 3, 3) the rotations of the canonical shape that Psi must undo
        (eq. 5; S = 0 without Psi).
    """

    augment: Leaf
    equivariance: Leaf
    canonicalisation: Leaf


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Every option of the release's ``C3DPO`` model (names as in the release)."""

    n_keypoints: int = 17
    shape_basis_size: int = 10
    n_fully_connected: int = 1024
    n_layers: int = 6
    keypoint_norm_type: str = "to_mean"  # "to_mean" | "to_root"
    root_joint: int = 0
    keypoint_rescale: float = 1.0
    # How the centred input is scaled (``KEYPOINT_SCALINGS``): "global", the release's, by
    # ``keypoint_rescale`` alone; "per_view" (not in the release), each view also divided by
    # its own RMS radius about the visible points' mean and its reconstruction multiplied by
    # it, so that Phi sees every view at one size and a shape seen at any size gets the same
    # factorisation (people at different distances from the camera; the training loss then
    # weighs every view alike; orthographic models only); "auto" (a training config's value),
    # "per_view" when the training views' sizes differ widely, else "global"
    # (``resolve.resolve_keypoint_scaling``).
    keypoint_scaling: str = "global"
    projection_type: str = "orthographic"  # "orthographic" | "perspective"
    perspective_depth_threshold: float = 0.1
    argmin_translation: bool = False
    camera_translation: bool = False
    camera_xy_translation: bool = False
    depth_offset: float = 0.0
    camera_scale: bool = False
    z_augment: bool = False
    z_augment_rot_angle: float = 0.3925
    z_equivariance: bool = True
    z_equivariance_rot_angle: float = 0.3925
    independent_phi_for_aug: bool = True
    canonicalization: bool = True
    canonicalization_n_layers: int = 6
    canonicalization_n_fully_connected: int = 1024
    n_rand_samples: int = 4
    # Not in the release (0): this many more of Psi's samples are reflections (a uniform
    # rotation times diag(1, 1, -1)), which Psi must undo as well: canonicalisation over
    # O(3) instead of SO(3), so that the canonical shapes cannot hold both a shape and its
    # mirror image (``losses.LossConfig``, "reflections").
    n_rand_reflections: int = 0
    canonicalization_rot_angle: float = 3.141592653589793
    replace_keypoints_with_input: bool = True
    weight_init_std: float = 0.01
    # Not in the release (which is 1): at inference, each view is also turned in-plane
    # about its centre and the depth of every point is the median over copies (an
    # orthographic depth does not change under an in-plane turn); orthographic models only
    # (see ``forward_eval``). ``test_time_turn_span``: "augmentation", the copies spread
    # evenly over +-z_augment_rot_angle (the training augmentation's range; odd turns,
    # models trained with z_augment), all of them kept; "circle", spread evenly round the
    # full circle, only the copies whose 2D reprojection error is within
    # ``TURN_KEEP_RATIO`` of the lowest kept (a copy the network is lost on fits its own
    # turned input badly); "circle_and_range", round the circle, the copies "circle" keeps
    # and every copy within the augmentation's range (models trained with z_augment).
    test_time_turns: int = 1
    test_time_turn_span: str = "augmentation"  # "augmentation" | "circle" | "circle_and_range"
    # Not in the release (which is 0): at inference, Phi's camera and coefficients are the
    # start of ``test_time_refine_iters`` Levenberg-Marquardt steps on the view's mean
    # squared 2D reprojection distance plus ``test_time_refine_prior`` times the mean
    # squared distance of the canonical shape's points to Phi's (orthographic models only;
    # every turned copy is refined; see ``refine_camera_and_shape``).
    test_time_refine_iters: int = 0
    test_time_refine_prior: float = 0.3
    # Not in the release (False): at inference, a view whose canonical shape is, up to a
    # rotation, nearer to the mirror image of the basis' mean shape than to the mean shape
    # is given its mirror image, which fits the 2D points equally (orthographic models only;
    # see ``one_handedness``): every view then has the mean shape's handedness.
    test_time_one_handedness: bool = False
    # What the views' handedness is taken from with ``test_time_one_handedness``:
    # "mean_shape" (the basis' mean shape, whose handedness the 2D views cannot tell from
    # its mirror image's) or a body of a known joint order (``HANDEDNESS_REFERENCES``):
    # each view is then given the handedness of that body, so that a model whose mean shape
    # came out mirrored still gives the body's own. "auto" (a training config's value,
    # resolved from the training views by ``resolve.resolve_handedness``): a body whose
    # projections fit the training views, with ``test_time_one_handedness`` on, else the
    # mean shape. "body": the body in ``test_time_handedness_body`` (a training config may
    # name a file instead, ``BODY_FILE_SUFFIXES``, which ``resolve.resolve_handedness`` reads).
    test_time_handedness_reference: str = "mean_shape"
    # With test_time_handedness_reference="body": one 3D example of the points, N rows of
    # (x, y, z) in the model's order, in any position, orientation and scale (a frame of
    # motion capture, a rig's rest pose): each view takes the handedness that two references
    # favour together, the example and the basis' mean shape given the example's handedness
    # (``mean_shape_handed_as``, ``handedness_evidence``, ``one_handedness``).
    test_time_handedness_body: tuple = ()
    # Matmul precision of the forward passes (params stay float32): "default" (the
    # backend's choice: float32 on CPU, may be tf32 on GPU), "float32" / "highest",
    # "tensorfloat32" / "high", "bfloat16"; see ``jax.default_matmul_precision``.
    # "bfloat16" also casts the trunks' dense operands to bfloat16 explicitly (float32
    # accumulation), which XLA's CPU backend honours where the precision flag is ignored.
    matmul_precision: str = "default"

    def __post_init__(self):
        """The options that would otherwise change inference silently (an even number of
        turns, an unknown span or projection, a negative prior), checked however the config
        was made: ``validation.check_config`` says the same of a run's config, field by
        field; this covers ``ModelConfig(...)``, ``dataclasses.replace`` and a hand-edited
        config.json read by ``load``."""
        problems = []
        body = self.test_time_handedness_body
        try:  # rows of floats, hashable (a saved config holds lists)
            object.__setattr__(self, "test_time_handedness_body",
                               tuple(tuple(float(v) for v in row) for row in body))
        except (TypeError, ValueError):
            problems.append(f"test_time_handedness_body={body!r} (rows of three numbers)")
        for name, known in (("projection_type", ("orthographic", "perspective")),
                            ("keypoint_norm_type", ("to_mean", "to_root")),
                            ("test_time_turn_span", TURN_SPANS)):
            if getattr(self, name) not in known:
                problems.append(f"{name}={getattr(self, name)!r} (known: {', '.join(known)})")
        turns, iters, prior = (self.test_time_turns, self.test_time_refine_iters,
                               self.test_time_refine_prior)
        if not (isinstance(turns, int | np.integer) and turns >= 1):
            problems.append(f"test_time_turns={turns!r} (must be an integer >= 1)")
        elif self.test_time_turn_span in TURN_SPANS and self.projection_type in (
                "orthographic", "perspective"):
            why = turns_problem(int(turns), self.projection_type, self.z_augment,
                                self.z_augment_rot_angle, self.test_time_turn_span)
            if why:
                problems.append(f"test_time_turns={turns} ({why})")
        if not (isinstance(iters, int | np.integer) and iters >= 0):
            problems.append(f"test_time_refine_iters={iters!r} (must be an integer >= 0)")
        elif why := refine_problem(int(iters), self.projection_type):
            problems.append(f"test_time_refine_iters={iters} ({why})")
        if not prior >= 0:  # NaN too
            problems.append(f"test_time_refine_prior={prior!r} (must be >= 0)")
        if self.keypoint_scaling not in (*KEYPOINT_SCALINGS, "auto"):
            problems.append(f"keypoint_scaling={self.keypoint_scaling!r} (known: "
                            f"{', '.join(KEYPOINT_SCALINGS)}, auto)")
        elif why := keypoint_scaling_problem(self.keypoint_scaling, self.projection_type):
            problems.append(f"keypoint_scaling={self.keypoint_scaling!r} ({why})")
        if handedness_problem(bool(self.test_time_one_handedness), self.projection_type):
            problems.append("test_time_one_handedness=True ("
                            + handedness_problem(True, self.projection_type) + ")")
        if why := reference_problem(self.test_time_handedness_reference, self.n_keypoints,
                                    bool(self.test_time_one_handedness),
                                    self.test_time_handedness_body):
            problems.append(f"test_time_handedness_reference="
                            f"{self.test_time_handedness_reference!r} ({why})")
        elif self.test_time_handedness_body and self.test_time_handedness_reference != "body":
            problems.append("test_time_handedness_body is given but test_time_handedness_"
                            f"reference is {self.test_time_handedness_reference!r}, not 'body'")
        if problems:
            raise ValueError("model config: " + "; ".join(problems))

    @classmethod
    def from_dict(cls, d) -> "ModelConfig":
        """From a dict or ConfigDict; unknown keys are an error, not silently dropped.
        The loss options that older runs saved in their model section (now
        ``losses.LossConfig``'s) are skipped: they change nothing in the model."""
        d = {k: v for k, v in dict(d).items() if k not in MOVED_TO_LOSS}
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown model option(s) {unknown}; known: {sorted(names)}")
        body = d.get("test_time_handedness_body")
        if isinstance(body, list | np.ndarray):  # JSON's lists
            d["test_time_handedness_body"] = tuple(tuple(row) if isinstance(
                row, list | np.ndarray) else row for row in body)
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# The release's model options that are loss options here (``losses.LossConfig``).
MOVED_TO_LOSS = ("huber_scaling", "reprojection_normalization", "squared_reprojection_loss")

_PRECISIONS = ("default", "bfloat16", "tensorfloat32", "float32", "high", "highest",
               "bfloat16_3x")


def _precision(cfg: ModelConfig):
    """Context manager that applies ``cfg.matmul_precision`` while tracing."""
    if cfg.matmul_precision not in _PRECISIONS:
        raise ValueError(f"unknown matmul_precision {cfg.matmul_precision!r}; known: {_PRECISIONS}")
    if cfg.matmul_precision == "default":
        return contextlib.nullcontext()
    return jax.default_matmul_precision(cfg.matmul_precision)


def single_precision(fn):
    """Runs ``fn`` with JAX's 64-bit mode off: the library computes in float32 (parameters,
    optimiser state, BatchNorm statistics), also in a notebook that has turned
    ``jax_enable_x64`` on, where Python floats would otherwise enter as float64. For the
    host entry points (``reconstruct``, ``train.train_and_evaluate``, ...)."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(False):
            return fn(*args, **kwargs)

    return wrapped


def _under_precision(fn):
    """Runs ``fn(..., cfg)`` (``cfg`` its last argument) under ``_precision(cfg)``."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        cfg = kwargs["cfg"] if "cfg" in kwargs else args[-1]
        with _precision(cfg):
            return fn(*args, **kwargs)

    return wrapped


def make_network(cfg: ModelConfig) -> C3DPONet:
    # Without independent_phi_for_aug both in-plane copies share BatchNorm statistics.
    phi_axes = "batch" if cfg.independent_phi_for_aug else ("batch", "copy")
    return C3DPONet(
        n_keypoints=cfg.n_keypoints,
        shape_basis_size=cfg.shape_basis_size,
        n_fully_connected=cfg.n_fully_connected,
        n_layers=cfg.n_layers,
        psi_n_fully_connected=cfg.canonicalization_n_fully_connected,
        psi_n_layers=cfg.canonicalization_n_layers,
        camera_translation=cfg.camera_translation,
        camera_scale=cfg.camera_scale,
        weight_init_std=cfg.weight_init_std,
        phi_axis_name=phi_axes,
        matmul_dtype=jnp.bfloat16 if cfg.matmul_precision == "bfloat16" else None,
    )


def init_variables(key: jax.Array, cfg: ModelConfig) -> Variables:
    """Random parameters and BatchNorm statistics (eval-mode init, no batch needed)."""
    net = make_network(cfg)
    n = cfg.n_keypoints
    return dict(net.init(key, jnp.zeros((n, 2)), jnp.ones((n,)), False))


def variables_shape(cfg: ModelConfig) -> Variables:
    """``init_variables``' pytree as ``jax.ShapeDtypeStruct`` leaves, computing nothing:
    the template a checkpoint's variables are restored onto."""
    return jax.eval_shape(lambda k: init_variables(k, cfg), jax.random.key(0))


def _camera(cfg: ModelConfig, phi_out, x_canon):
    """Camera-frame shape ``s R X + T`` and the rotation."""
    rot = so3.exp_map(phi_out["theta"])
    t = phi_out["translation"]
    if cfg.camera_xy_translation:
        t = t * jnp.array([1.0, 1.0, 0.0])
    t = t + jnp.array([0.0, 0.0, cfg.depth_offset])
    return phi_out["scale"] * x_canon @ rot.T, t, rot


KEYPOINT_SCALINGS = ("global", "per_view")
# The least RMS radius "per_view" scaling divides a view by (in the normalised units, where
# the training views' median is about 1): a view whose visible points nearly coincide is
# scaled up at most this much instead of dividing by 0.
MIN_VIEW_RADIUS = 1e-3


def _normalised_input(cfg: ModelConfig, kp, vis, intrinsics):
    """``(kp_cal, kp_norm, centre, scale)``: calibrated keypoints (perspective), the
    network's centred, rescaled input, the centre that was removed and the factor the
    centred points were multiplied by (``keypoint_rescale``, over the view's RMS radius
    with ``keypoint_scaling="per_view"``). Hidden points are zeroed first: whatever they
    hold (1e20, NaN) never reaches the arithmetic."""
    if cfg.keypoint_rescale == 0:  # the config's "from the data", never resolved
        raise ValueError("model.keypoint_rescale=0 means 'set it from the training data' and "
                         "was not resolved: the network would see zeros. Resolve it first "
                         "(resolve.resolve_input_scale(config, train_data), as "
                         "train_and_evaluate does; a loaded model has it)")
    if cfg.keypoint_scaling == "auto":
        raise ValueError("model.keypoint_scaling='auto' means 'from the training data' and was "
                         "not resolved (resolve.resolve_keypoint_scaling(config, train_data), as "
                         "train_and_evaluate does; a loaded model has it)")
    kp = jnp.where(vis[:, None] > 0, kp, 0.0)
    if cfg.projection_type == "perspective":
        if intrinsics is None:
            raise ValueError("a perspective model needs per-sample intrinsics K")
        kp = geometry.calibrate(kp, intrinsics)
    kp_norm, centre = geometry.normalise_keypoints(
        kp, vis, norm_type=cfg.keypoint_norm_type,
        rescale=cfg.keypoint_rescale, root_joint=cfg.root_joint,
    )
    scale = jnp.asarray(cfg.keypoint_rescale, kp_norm.dtype)
    if cfg.keypoint_scaling == "per_view":
        centred = kp_norm - geometry.masked_mean(kp_norm, vis)[None]  # to_root: not centred
        radius = jnp.sqrt(geometry.masked_mean(jnp.sum(centred**2, -1), vis))
        radius = jnp.maximum(radius, MIN_VIEW_RADIUS)
        kp_norm, scale = kp_norm / radius, scale / radius
    return kp, kp_norm, centre, scale


def _shape(net, params, alpha, class_mask):
    """Canonical shape (N, 3) from basis coefficients; points outside the class are 0."""
    return net.apply({"params": params}, alpha, method="shape") * class_mask[:, None]


def _class_centred(x, class_mask):
    """``x`` (N, C) minus the mean of its class's points, the other points zeroed."""
    return (x - geometry.masked_mean(x, class_mask)[None]) * class_mask[:, None]


def _reproject(cfg: ModelConfig, x_cam, kp_norm, vis):
    """``(proj, depth, dist_sq)``: projection of the camera-frame shape, its depth and
    the squared distance of each projected point to the normalised input."""
    proj, depth = geometry.project(
        x_cam,
        projection_type=cfg.projection_type,
        depth_threshold=cfg.perspective_depth_threshold,
    )
    if cfg.argmin_translation:
        proj = geometry.argmin_translation(proj, kp_norm, vis)
    return proj, depth, jnp.sum((proj - kp_norm) ** 2, axis=-1)


@_under_precision
def forward_train(
    variables: Variables,
    kp: Kp2,
    vis: Vis,
    class_mask: Float[Array, " N"],
    intrinsics: Float[Array, "3 3"] | None,
    rotations: TrainRotations,
    kp3d: Kp3 | None = None,
    *,
    cfg: ModelConfig,
) -> tuple[dict[str, Array], dict[str, Any]]:
    """Training forward pass of one example, under ``vmap(axis_name="batch")``: a pure
    function of its inputs and of the example's ``rotations``.

    Returns:
      ``(terms, batch_stats)``: ``dist_sq`` (N,), the squared distance of each
      reprojected point to the normalised input (unmasked), and ``canon_dist_sq``
      (S, N), the squared distance of each point of Psi's reconstruction of each randomly
      rotated canonical shape to that shape (S = 0 without Psi), ``deform_sq`` (N,), the
      squared distance of each point of the canonical shape to the mean shape (its
      deformation); with the example's 3D ground truth ``kp3d`` (camera frame, the input's
      units; orthographic models), also ``sup_dist_sq`` (N,), the squared distance of each
      point of the camera-frame shape to it, both centred on their class's points, in the
      network's input units; ``x_canon`` (N, 3), the canonical shape (``losses.multiview``
      compares those of one frame's views). The updated BatchNorm statistics. ``losses``
      penalises and reduces them.
    """
    net = make_network(cfg)
    params, stats = variables["params"], variables["batch_stats"]
    _, kp_norm, _, scale = _normalised_input(cfg, kp, vis, intrinsics)

    def phi(kp_in, stats):
        out, upd = net.apply(
            {"params": params, "batch_stats": stats}, kp_in, vis, True,
            method="phi", mutable=["batch_stats"],
        )
        return out, upd["batch_stats"]

    # z_augment: rotate the input in-plane; the rotation is undone on the 3D output.
    r_aug = rotations.augment
    kp_in = kp_norm @ r_aug.T
    if cfg.z_equivariance:
        # Eq. 6: camera from the first copy, shape coefficients from a copy rotated again.
        copies = jnp.stack([kp_in, kp_in @ rotations.equivariance.T])
        if cfg.independent_phi_for_aug:
            out1, stats = phi(copies[0], stats)
            out2, stats = phi(copies[1], stats)
        else:
            # BatchNorm's statistics are means over the copies: one value (out_axes None).
            outs, stats = jax.vmap(phi, in_axes=(0, None), out_axes=(0, None),
                                   axis_name="copy")(copies, stats)
            out1, out2 = (jax.tree.map(lambda a, i=i: a[i], outs) for i in range(2))
        phi_out = dict(out1, alpha=out2["alpha"])
    else:
        phi_out, stats = phi(kp_in, stats)

    x_canon = _shape(net, params, phi_out["alpha"], class_mask)
    x_cam, t, _ = _camera(cfg, phi_out, x_canon)
    r_aug3 = jnp.eye(3).at[:2, :2].set(r_aug)
    x_cam = (x_cam + t[None]) @ r_aug3  # applies R_aug^T to column vectors
    _, _, dist_sq = _reproject(cfg, x_cam, kp_norm, vis)
    mean_shape = _shape(net, params, jnp.zeros_like(phi_out["alpha"]), class_mask)
    terms = {"dist_sq": dist_sq, "canon_dist_sq": jnp.zeros((0, cfg.n_keypoints)),
             "deform_sq": jnp.sum((x_canon - mean_shape) ** 2, axis=-1), "x_canon": x_canon,
             "mean_shape": mean_shape}
    if kp3d is not None:
        terms["sup_dist_sq"] = jnp.sum((_class_centred(x_cam, class_mask) - _class_centred(
            kp3d * scale, class_mask)) ** 2, axis=-1)
    if cfg.canonicalization:
        terms["canon_dist_sq"], stats = _canonicalisation(
            net, params, stats, x_canon, class_mask, rotations.canonicalisation
        )
    return terms, stats


def _canonicalisation(net, params, stats, x_canon, class_mask, rots):
    """Eq. 5: Psi must undo the rotations ``rots`` of the (not detached) canonical shape."""

    def one(rot):
        alpha_psi, upd = net.apply(
            {"params": params, "batch_stats": stats}, x_canon @ rot.T, True,
            method="psi", mutable=["batch_stats"],
        )
        x_hat = _shape(net, params, alpha_psi, class_mask)
        return jnp.sum((x_hat - x_canon) ** 2, axis=-1), upd["batch_stats"]

    # Psi's BatchNorm statistics are means over the samples: one value (out_axes None).
    return jax.vmap(one, out_axes=(0, None), axis_name="sample")(rots)


TURN_SPANS = ("augmentation", "circle", "circle_and_range")
# "circle": the copies kept are those whose mean 2D reprojection distance is at most this
# times the lowest of the view's copies (experiments/dev_suite, "Turned copies round the
# circle, chosen by their 2D fit").
TURN_KEEP_RATIO = 1.1
# "circle_and_range": a copy counts as within the augmentation's range up to this many
# radians beyond it (the circle's grid of 32 puts a copy at 2 pi / 16 = 0.39270 rad, the
# release's range being 0.3925).
TURN_RANGE_SLACK = 1e-3


def turns_problem(turns: int, projection_type: str, z_augment: bool,
                  z_augment_rot_angle: float, span: str = "augmentation") -> str:
    """Why ``test_time_turns=turns`` cannot be used with these settings ('' if it can; a
    single pass always can). ``span`` is one of ``TURN_SPANS``."""
    if turns == 1:
        return ""
    ranged = span != "circle"  # the training augmentation's range is used
    why = [
        "an odd number" if span == "augmentation" and turns % 2 == 0 else "",
        "used with model.projection_type='orthographic' only"
        if projection_type == "perspective" else "",
        f"used with model.z_augment=True and model.z_augment_rot_angle > 0 only (span "
        f"{span!r} uses the training augmentation's range; model.test_time_turn_span="
        "'circle' does not)"
        if ranged and (not z_augment or z_augment_rot_angle == 0) else "",
    ]
    return "must be " + " and ".join(w for w in why if w) if any(why) else ""


def turn_angles(cfg: ModelConfig) -> Float[Array, " A"]:
    """The ``test_time_turns - 1`` nonzero in-plane angles of the turned copies: pairs
    +-a spread evenly up to ``z_augment_rot_angle`` ("augmentation"), or steps of
    2 pi / ``test_time_turns`` round the circle ("circle", "circle_and_range")."""
    if cfg.test_time_turn_span != "augmentation":
        return 2 * jnp.pi * jnp.arange(1, cfg.test_time_turns) / cfg.test_time_turns
    k = (cfg.test_time_turns - 1) // 2
    half = cfg.z_augment_rot_angle * jnp.arange(1, k + 1) / k
    return jnp.concatenate([half, -half])


def turns_in_range(cfg: ModelConfig) -> np.ndarray:
    """(``test_time_turns``,) bool, static: which copies of "circle_and_range" (the view
    itself first, then ``turn_angles``) are turned by at most ``z_augment_rot_angle`` plus
    ``TURN_RANGE_SLACK``, either way round."""
    turned_by = 2 * np.pi * np.arange(cfg.test_time_turns) / cfg.test_time_turns
    off = np.abs(np.remainder(turned_by + np.pi, 2 * np.pi) - np.pi)
    return off <= cfg.z_augment_rot_angle + TURN_RANGE_SLACK


def orthographic_only(used: bool, off: str, projection_type: str) -> str:
    """The problem of a setting for orthographic models (``off``: its value that turns it
    off) when it is ``used`` with another projection; '' otherwise."""
    if used and projection_type == "perspective":  # another value has its own problem
        return f"must be {off} for a perspective model: orthographic models only"
    return ""


def refine_problem(iters: int, projection_type: str) -> str:
    """Why ``test_time_refine_iters=iters`` cannot be used with this projection ('' if it
    can; 0, no refinement, always can)."""
    return orthographic_only(iters > 0, "0 (no refinement)", projection_type)


def keypoint_scaling_problem(scaling: str, projection_type: str) -> str:
    """Why ``keypoint_scaling=scaling`` cannot be used with this projection ('' if it can):
    a perspective view's calibrated points are not a shape's projection up to a scale."""
    return orthographic_only(scaling == "per_view", "'global' or 'auto'", projection_type)


def handedness_problem(one_handedness: bool, projection_type: str) -> str:
    """Why ``test_time_one_handedness`` cannot be used with this projection ('' if it can)."""
    return orthographic_only(one_handedness, "False", projection_type)


# Bodies whose handedness ``test_time_handedness_reference`` can give every view, with the
# number of points of their joint order (the built-in humans' average body,
# ``data.humans.mean_pose``): "h36m", a person in Human3.6M's 17-joint order (pelvis,
# right leg, left leg, spine, thorax, neck, head, left arm, right arm, as
# ``skeletons.SKELETONS["h36m"]`` joins them); "coco", in COCO's 17 person keypoints, the
# common 2D detectors' order (nose, eyes, ears, then shoulders, elbows, wrists, hips, knees,
# ankles, left before right; ``data.humans.coco_from_h36m``).
HANDEDNESS_REFERENCES = {"mean_shape": None, "h36m": 17, "coco": 17}
# Files a training config (``test_time_handedness_reference``), ``reconstruct`` and
# c3dpo-predict take a body from (``read_body``).
BODY_FILE_SUFFIXES = (".npy", ".json", ".txt", ".csv")
# A body whose centred points' smallest singular value is below this fraction of their
# largest lies near a plane (or a line): its mirror image is nearly itself, so it has no
# handedness to give (the built-in humans' average body: 0.20).
BODY_MIN_THICKNESS = 0.05


def is_body_file(name) -> bool:
    """Whether ``name`` names a file to read a body from (by its suffix)."""
    return isinstance(name, str) and name.lower().endswith(BODY_FILE_SUFFIXES)


def read_body(path: str) -> np.ndarray:
    """The (N, 3) body in ``path``: a ``.npy`` array, a ``.json`` list of N ``[x, y, z]``,
    or ``.txt`` / ``.csv`` text of N rows of three numbers (spaces or commas). One-line
    ``ValueError`` for a file that cannot be read as that."""
    path = os.path.expanduser(path)
    if not os.path.exists(path):
        raise ValueError(f"body file {path!r} does not exist")
    try:
        if path.lower().endswith(".npy"):
            body = np.load(path, allow_pickle=False)
        elif path.lower().endswith(".json"):
            with open(path, encoding="utf-8-sig") as f:
                body = json.load(f)
        else:
            with open(path, encoding="utf-8-sig") as f:
                body = np.loadtxt(f.read().replace(",", " ").splitlines(), ndmin=2)
        body = np.asarray(body, np.float64)
    except (ValueError, TypeError, OSError) as err:
        raise ValueError(f"body file {path!r} is not N rows of (x, y, z): "
                         f"{str(err).splitlines()[0] if str(err) else type(err).__name__}"
                         ) from None
    if body.ndim != 2 or body.shape[1] != 3:
        raise ValueError(f"body file {path!r} holds an array of shape {body.shape}; a body is "
                         "N rows of (x, y, z)")
    return body


def body_problem(body, n_keypoints: int) -> str:
    """Why ``body`` cannot give the views of a model of ``n_keypoints`` points their
    handedness ('' if it can)."""
    try:
        b = np.asarray(body, np.float64)
    except (TypeError, ValueError):
        return "a body is N rows of (x, y, z)"
    if b.shape != (n_keypoints, 3):
        return (f"a body of the model's {n_keypoints} points, N rows of (x, y, z); "
                f"got shape {b.shape}")
    if not np.isfinite(b).all():
        return "the body has NaN or inf"
    s = np.linalg.svd(b - b.mean(0), compute_uv=False)
    if not s[0] > 0 or s[2] < BODY_MIN_THICKNESS * s[0]:
        return ("the body's points lie near one plane, so its mirror image is nearly itself "
                "and it has no handedness to give")
    return ""


def reference_problem(name, n_keypoints: int, one_handedness: bool = True,
                      body=()) -> str:
    """Why ``test_time_handedness_reference=name`` (with ``test_time_handedness_body=body``
    for "body") cannot be used ('' if it can)."""
    if name == "auto":
        return ""
    if isinstance(name, str) and name == "body":
        if not len(body):
            return ("test_time_handedness_body is empty: give its N rows of (x, y, z), or "
                    f"name a body file ({', '.join(BODY_FILE_SUFFIXES)}) in a training config")
        if why := body_problem(body, n_keypoints):
            return why
        return "" if one_handedness else "used with test_time_one_handedness=True only"
    if is_body_file(name):
        return ("a body file is read when training starts (resolve.resolve_handedness); a "
                "model holds its points as 'body'")
    if not isinstance(name, str) or name not in HANDEDNESS_REFERENCES:
        return f"known: {', '.join(HANDEDNESS_REFERENCES)}, body, auto"
    n = HANDEDNESS_REFERENCES[name]
    if n is not None and n != n_keypoints:
        return f"a body of {n} points in its joint order; the model has {n_keypoints}"
    if n is not None and not one_handedness:
        return "used with test_time_one_handedness=True only"
    return ""


@functools.lru_cache
def _body(name: str) -> np.ndarray:
    """The body ``name`` as a read-only numpy array, made once per process (numpy, not jax:
    a jax array made while a function is traced would be that trace's)."""
    from c3dpo_jax.data import humans  # numpy only; loaded when a body is asked for

    body = np.asarray(humans.mean_pose(order=name), np.float32)
    body.setflags(write=False)
    return body


def handedness_reference(name: str, body=()) -> Array | None:
    """The (N, 3) body ``name`` of ``HANDEDNESS_REFERENCES``, or ``body`` for "body"
    (None: the mean shape)."""
    if name == "body":
        return jnp.asarray(np.asarray(body, np.float32))
    if name == "auto":
        raise ValueError("model.test_time_handedness_reference='auto' means 'from the training "
                         "data' and was not resolved (resolve.resolve_handedness(config, "
                         "train_data), as train_and_evaluate does; a loaded model has it)")
    if HANDEDNESS_REFERENCES[name] is None:
        return None
    return jnp.asarray(_body(name))


def mean_shape_handed_as(net, params, class_mask, body):
    """The basis' mean shape, mirrored (third axis negated) when it is nearer, up to a
    proper rotation, to the mirror image of ``body`` (N, 3) than to the body. A user's body
    (``test_time_handedness_reference="body"``) is one example in one pose, which the views
    of other poses may not resemble; the mean shape, the model's typical pose, may. So a
    view weighs both (``one_handedness`` with the two references)."""
    mean = _shape(net, params, jnp.zeros(net.shape_basis_size), class_mask)
    return mean * jnp.where(_nearer_mirror(mean, body, class_mask),
                            jnp.array([1.0, 1.0, -1.0]), 1.0)[None]


def _nearer_mirror(x, reference, class_mask):
    """Whether the best orthogonal map of the centred shape ``x`` onto ``reference`` is a
    reflection (det of their cross-covariance < 0): ``x`` is nearer, up to a proper
    rotation, to the reference's mirror image than to the reference."""
    return jnp.linalg.det(_class_centred(x, class_mask).T
                          @ _class_centred(reference, class_mask)) < 0


def handedness_evidence(x, reference, class_mask, floor=0.0):
    """How much better a proper rotation than a reflection maps the shape ``x`` (N, 3) onto
    ``reference``: ``(r_mirror - r_proper) / (r_mirror + r_proper)`` of the two Procrustes
    residuals of the centred, unit-size shapes, in [-1, 1] (negative: nearer the mirror
    image)."""
    a, b = (_class_centred(y, class_mask) for y in (x, reference))
    a, b = (y / jnp.maximum(jnp.linalg.norm(y), 1e-12) for y in (a, b))
    cov = a.T @ b
    sigma = jnp.linalg.svd(cov, compute_uv=False)
    third = jnp.sign(jnp.linalg.det(cov)) * sigma[2]
    proper, mirror = (jnp.sqrt(jnp.maximum(2.0 - 2.0 * (sigma[0] + sigma[1] + sign * third),
                                           floor)) for sign in (1.0, -1.0))
    return (mirror - proper) / jnp.maximum(mirror + proper, 1e-12)


def one_handedness(net, params, x_cam, t, x_canon, rot, theta, class_mask, reference=None):
    """``(x_cam, x_canon, rot, theta)`` of one view, mirrored when its canonical shape
    ``x_canon`` is nearer, up to a proper rotation, to the mirror image of ``reference``
    (N, 3), by default the basis' mean shape, than to the reference itself (the best
    orthogonal map from one centred shape onto the other is then a reflection: det of their
    cross-covariance < 0; comparing the two Procrustes residuals says the same). With a
    tuple of references, mirrored when the sum of their ``handedness_evidence`` is
    negative. The mirror image:
    the camera-frame depth reflected about the translation's (``t``; an orthographic view's
    2D points unchanged), the canonical shape's third axis negated and the rotation
    conjugated by that reflection (``theta``'s first two components negated), so that
    ``scale * x_canon @ rot.T + t`` is still ``x_cam``. Also returns 1.0 where the view was
    mirrored, else 0.0."""
    if reference is None:
        reference = _shape(net, params, jnp.zeros(net.shape_basis_size), class_mask)
    if isinstance(reference, tuple):
        mirrored = sum(handedness_evidence(x_canon, r, class_mask) for r in reference) < 0
    else:
        mirrored = _nearer_mirror(x_canon, reference, class_mask)
    flip = jnp.where(mirrored, jnp.array([1.0, 1.0, -1.0]), 1.0)
    x_cam = (x_cam - t[None]) * flip[None] + t[None]
    theta = theta * jnp.where(mirrored, jnp.array([-1.0, -1.0, 1.0]), 1.0)  # log of F R F
    return (x_cam, x_canon * flip[None], flip[:, None] * rot * flip[None], theta,
            mirrored.astype(x_cam.dtype))


# Levenberg-Marquardt's damping: its start, and its factors after a step that lowers the
# cost (accepted) and after one that does not (rejected, the damping raised).
REFINE_DAMPING, REFINE_DAMPING_DOWN, REFINE_DAMPING_UP = 1e-3, 0.3, 10.0


def refine_camera_and_shape(cfg: ModelConfig, net, params, phi_out, kp_norm, vis, class_mask):
    """Phi's output ``phi_out`` with its ``theta`` and ``alpha`` refined for one view:
    ``cfg.test_time_refine_iters`` Levenberg-Marquardt steps from Phi's values on the mean
    squared 2D distance of the reprojected visible points to ``kp_norm`` plus
    ``cfg.test_time_refine_prior`` times the mean squared distance of the canonical shape's
    points (those of ``class_mask``) to Phi's canonical shape. Scale and translation stay
    Phi's. A step that does not lower the cost is not taken (the damping rises instead), so
    the cost never rises above Phi's."""
    x_phi = _shape(net, params, phi_out["alpha"], class_mask)
    w2d = jnp.sqrt(vis / jnp.maximum(jnp.sum(vis), 1.0))[:, None]
    w3d = jnp.sqrt(cfg.test_time_refine_prior * class_mask
                   / jnp.maximum(jnp.sum(class_mask), 1.0))[:, None]

    def residuals(p):
        out = dict(phi_out, theta=p[:3], alpha=p[3:])
        x_canon = _shape(net, params, out["alpha"], class_mask)
        x_cam, t, _ = _camera(cfg, out, x_canon)
        proj, _, _ = _reproject(cfg, x_cam + t[None], kp_norm, vis)
        return jnp.concatenate([((proj - kp_norm) * w2d).ravel(),
                                ((x_canon - x_phi) * w3d).ravel()])

    def step(carry, _):
        p, damping = carry
        # One pass gives the residuals and their Jacobian (the residuals as jacfwd's aux).
        jac, r = jax.jacfwd(lambda q: (lambda v: (v, v))(residuals(q)), has_aux=True)(p)
        normal = jac.T @ jac
        # Marquardt's scaling, floored so that a direction the cost does not see (a hidden
        # view's rotation, an unused basis vector) still gets a damped, finite step.
        # The damped normal matrix is symmetric positive definite: Cholesky, not LU.
        delta = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(
            normal + damping * jnp.diag(jnp.diag(normal) + 1e-9)), -jac.T @ r)
        # False for a NaN step: it is not taken.
        lower = jnp.sum(residuals(p + delta) ** 2) < jnp.sum(r**2)
        return (jnp.where(lower, p + delta, p),
                damping * jnp.where(lower, REFINE_DAMPING_DOWN, REFINE_DAMPING_UP)), None

    start = jnp.concatenate([phi_out["theta"], phi_out["alpha"]])
    (p, _), _ = jax.lax.scan(step, (start, jnp.asarray(REFINE_DAMPING)), None,
                             length=cfg.test_time_refine_iters)
    return dict(phi_out, theta=p[:3], alpha=p[3:])


def _phi_eval(cfg: ModelConfig, net, variables, kp_norm, vis, class_mask):
    """Phi's eval-mode output for one view, refined when ``test_time_refine_iters`` > 0."""
    out = net.apply(variables, kp_norm, vis, False, method="phi")
    if cfg.test_time_refine_iters > 0:
        out = refine_camera_and_shape(cfg, net, variables["params"], out, kp_norm, vis,
                                      class_mask)
    return out


def _turned_depth(cfg: ModelConfig, net, variables, kp_norm, vis, class_mask, x_cam):
    """The median depth (N,) over the view (camera-frame shape ``x_cam``) and its copies
    turned in-plane by ``turn_angles``, each copy's depth about its visible mean with its
    sign matched to the unturned view's ("circle": over the copies whose mean 2D
    reprojection distance to their own turned input is within ``TURN_KEEP_RATIO`` of the
    lowest; "circle_and_range": those and every copy within ``z_augment_rot_angle`` (plus
    ``TURN_RANGE_SLACK``) of the view), then the unturned mean depth added back."""
    w = vis / jnp.maximum(jnp.sum(vis), 1.0)

    def centred_depth_and_fit(x, kp_in):
        _, depth, dist_sq = _reproject(cfg, x, kp_in, vis)
        return depth - jnp.sum(w * depth), jnp.sum(w * jnp.sqrt(dist_sq))

    centred, fit = centred_depth_and_fit(x_cam, kp_norm)

    def copy(angle):
        c, s = jnp.cos(angle), jnp.sin(angle)
        turned = kp_norm @ jnp.array([[c, s], [-s, c]])
        out = _phi_eval(cfg, net, variables, turned, vis, class_mask)
        x, t, _ = _camera(cfg, out, _shape(net, variables["params"], out["alpha"], class_mask))
        d, f = centred_depth_and_fit(x + t[None], turned)
        return jnp.where(jnp.sum(w * d * centred) < 0, -d, d), f

    depths, fits = jax.vmap(copy)(turn_angles(cfg))
    depths = jnp.concatenate([centred[None], depths])
    if cfg.test_time_turn_span != "augmentation":
        fits = jnp.concatenate([fit[None], fits])
        keep = fits <= TURN_KEEP_RATIO * jnp.min(fits)
        if cfg.test_time_turn_span == "circle_and_range":
            keep = keep | turns_in_range(cfg)
        median = jnp.nanmedian(jnp.where(keep[:, None], depths, jnp.nan), axis=0)
    else:
        median = jnp.median(depths, axis=0)
    return median + (x_cam[:, 2] - centred)


@_under_precision
def forward_eval(
    variables: Variables,
    kp: Kp2,
    vis: Vis,
    class_mask: Float[Array, " N"],
    intrinsics: Float[Array, "3 3"] | None,
    cfg: ModelConfig,
) -> Prediction:
    """Eval-mode reconstruction of one example (running BatchNorm statistics, no Psi);
    the fields of the ``Prediction`` are documented there."""
    net = make_network(cfg)
    kp_cal, kp_norm, centre, scale = _normalised_input(cfg, kp, vis, intrinsics)
    phi_out = _phi_eval(cfg, net, variables, kp_norm, vis, class_mask)
    x_canon = _shape(net, variables["params"], phi_out["alpha"], class_mask)
    x_cam, t, rot = _camera(cfg, phi_out, x_canon)
    x_cam = x_cam + t[None]
    if cfg.test_time_turns > 1:
        x_cam = x_cam.at[:, 2].set(_turned_depth(cfg, net, variables, kp_norm, vis, class_mask,
                                                 x_cam))
    theta, flipped = phi_out["theta"], jnp.zeros((), x_cam.dtype)
    if cfg.test_time_one_handedness:
        problem = handedness_problem(True, cfg.projection_type)
        if problem:
            raise ValueError(f"test_time_one_handedness=True ({problem})")
        reference = handedness_reference(cfg.test_time_handedness_reference,
                                         cfg.test_time_handedness_body)
        if cfg.test_time_handedness_reference == "body":  # the example and the mean shape
            reference = (reference, mean_shape_handed_as(net, variables["params"], class_mask,
                                                         reference))
        x_cam, x_canon, rot, theta, flipped = one_handedness(
            net, variables["params"], x_cam, t, x_canon, rot, theta, class_mask, reference)
    proj, depth, dist_sq = _reproject(cfg, x_cam, kp_norm, vis)
    reproj_image = geometry.unnormalise_keypoints(proj, centre, scale)
    image_xy = reproj_image
    if cfg.replace_keypoints_with_input:
        image_xy = jnp.where(vis[:, None] > 0, kp_cal, reproj_image)
    shape_image = jnp.concatenate([image_xy, depth[:, None] / scale], axis=1)
    if cfg.projection_type == "perspective":
        # Reprojections back to pixels; shape_image_coord stays in calibrated units.
        reproj_image = geometry.uncalibrate(reproj_image, intrinsics)
    return Prediction(
        shape_image_coord=shape_image,
        shape_camera=x_cam,
        shape_canonical=x_canon,
        rotation=rot,
        theta=theta,
        alpha=phi_out["alpha"],
        translation=t,
        scale=phi_out["scale"],
        kp_reprojected=reproj_image,
        kp_norm=kp_norm,
        kp_mean=centre,
        kp_scale=scale,
        dist_sq=dist_sq,
        handedness_flipped=flipped,
    )
