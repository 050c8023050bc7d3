"""C3DPO's network and its training forward pass, for ONE example, plus the model's
static settings (``ModelConfig``) and the geometry both forward passes share.

Glossary: N keypoints, D shape-basis size, S canonicalisation samples. Points are
rows: ``kp (N, 2)``, ``X (N, 3)``; rotations act as ``X @ R.T`` (see ``so3``).

``forward_train`` runs under ``jax.vmap(..., axis_name="batch")`` (BatchNorm takes its
statistics over that axis): given an example and its random rotations (``TrainRotations``)
it returns squared distances of eq. 4 (reprojection), 5 (canonicalisation) and 6 (in-plane
equivariance), which ``losses`` turns into the objective. The eval pass, with the options
of ``lift.InferenceConfig``, is ``lift.forward_eval``.
"""

import contextlib
import dataclasses
import functools
from collections.abc import Mapping
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
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
    """``lift.forward_eval``'s outputs for one example (batched, each with a leading B): a
    frozen dataclass, a pytree and a read-only mapping (``pred.alpha``, ``pred["alpha"]``,
    ``dict(pred)``). "Normalised" is the network's frame: the input centred (``kp_mean``)
    and times ``kp_scale``, after calibration with K for perspective models. The options
    named below are ``lift.InferenceConfig``'s.

    Attributes:
      shape_3d: (N, 3) the 3D output in the input's coordinates (calibrated for perspective
        models): xy the input where visible (``replace_keypoints_with_input``) else the
        reprojection, depth divided by ``kp_scale``.
      shape_camera: (N, 3) ``scale * X @ R.T + translation``, normalised; with ``turns``
        > 1 its depth (and shape_3d's) is the median over the turned copies kept, while X,
        R, theta and alpha are the unturned view's.
      shape_canonical: (N, 3) the canonical shape X (points outside the class are 0).
      rotation: (3, 3) the camera rotation R = exp_map(theta).
      theta: (3,) R's axis-angle vector.
      alpha: (D,) shape-basis coefficients (with ``refine_iters`` > 0, theta and alpha
        are Phi's refined; see ``lift.refine_camera_and_shape``). With ``one_handedness``,
        a view given its mirror image has X the mirror of the basis' shape for alpha, and
        R, theta and the depth mirrored to match (``lift.one_handedness``).
      translation: (3,) camera translation (zeros + ``depth_offset`` unless predicted).
      scale: () camera scale (1 unless ``camera_scale``).
      kp_reprojected: (N, 2) shape_camera projected back to input coordinates (pixels
        for perspective models).
      kp_norm: (N, 2) the network's normalised input.
      kp_mean: (2,) the centre removed from the input (calibrated for perspective).
      kp_scale: () the factor the centred input was multiplied by: ``keypoint_rescale``
        (over the view's RMS radius with ``keypoint_scaling="per_view"``).
      dist_sq: (N,) squared distance of each reprojected point to the normalised input,
        unmasked (``losses.LossConfig.penalty`` turns it into the reprojection term).
      handedness_flipped: () 1 where the view was given its mirror image (``one_handedness``,
        or a body's one decision for the whole model), else 0: ``shape_canonical`` with its
        third axis negated there is the model's own canonical shape (``lift.own_handedness``).
    """

    shape_3d: Leaf
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
    """What the network is and how it trains: every option of the release's ``C3DPO``
    model (names as in the release) but the ones that act at inference only, which are
    ``lift.InferenceConfig``'s."""

    n_keypoints: int = 17
    shape_basis_size: int = 10
    n_fully_connected: int = 1024
    n_layers: int = 6
    keypoint_norm_type: str = "to_mean"  # "to_mean" | "to_root"
    root_joint: int = 0
    keypoint_rescale: float = 1.0
    # How the centred input is scaled: "global" (the release's) by ``keypoint_rescale``
    # alone; "per_view" (not in the release) each view also divided by its own RMS radius and
    # its reconstruction multiplied by it, so that Phi sees every view at one size (people at
    # different distances; orthographic models only); "auto" (a training config's value),
    # resolved from the training views by ``resolve.resolve_keypoint_scaling``.
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
    # Not in the release (0): this many more of Psi's samples are reflections (a rotation
    # times diag(1, 1, -1)) for Psi to undo: canonicalisation over O(3), not SO(3).
    n_rand_reflections: int = 0
    canonicalization_rot_angle: float = 3.141592653589793
    weight_init_std: float = 0.01
    # Matmul precision of the forward passes (``jax.default_matmul_precision``; params stay
    # float32): "default", "float32" / "highest", "tensorfloat32" / "high", "bfloat16" (which
    # also casts the trunks' dense operands to bfloat16, float32 accumulation, also on CPU).
    matmul_precision: str = "default"

    def __post_init__(self):
        """Unknown projections, scalings and centrings, however the config was made."""
        problems = []
        for name, known in (("projection_type", ("orthographic", "perspective")),
                            ("keypoint_norm_type", ("to_mean", "to_root"))):
            if getattr(self, name) not in known:
                problems.append(f"{name}={getattr(self, name)!r} (known: {', '.join(known)})")
        if self.keypoint_scaling not in (*KEYPOINT_SCALINGS, "auto"):
            problems.append(f"keypoint_scaling={self.keypoint_scaling!r} (known: "
                            f"{', '.join(KEYPOINT_SCALINGS)}, auto)")
        elif why := keypoint_scaling_problem(self.keypoint_scaling, self.projection_type):
            problems.append(f"keypoint_scaling={self.keypoint_scaling!r} ({why})")
        if problems:
            raise ValueError("model config: " + "; ".join(problems))

    @classmethod
    def from_dict(cls, d) -> "ModelConfig":
        """From a dict or ConfigDict; unknown keys are an error, not silently dropped.
        What a saved model section may hold that is another config's here is skipped: the
        release's loss options (``MOVED_TO_LOSS``) and the inference options
        (``MOVED_TO_INFERENCE``, which ``lift.saved_options`` reads)."""
        d = {k: v for k, v in dict(d).items()
             if k not in MOVED_TO_LOSS and k not in MOVED_TO_INFERENCE}
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown model option(s) {unknown}; known: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# The release's model options that are loss options here (``losses.LossConfig``).
MOVED_TO_LOSS = ("huber_scaling", "reprojection_normalization", "squared_reprojection_loss")
# Model options a saved config.json may hold that are ``lift.InferenceConfig``'s fields,
# each with that field's name.
MOVED_TO_INFERENCE = {
    **{f"test_time_{name}": name for name in (
        "refine_iters", "refine_prior", "turns", "turn_span", "one_handedness",
        "handedness_reference", "handedness_body")},
    "replace_keypoints_with_input": "replace_keypoints_with_input"}

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
    """Runs ``fn`` with JAX's 64-bit mode off: the library computes in float32, also in a
    notebook that has turned ``jax_enable_x64`` on (where Python floats would enter as
    float64). For the host entry points (``reconstruct``, ``train.train_and_evaluate``)."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(False):
            return fn(*args, **kwargs)

    return wrapped


def under_precision(fn):
    """Runs ``fn`` under ``_precision(cfg)``, ``cfg`` its keyword or positional config."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        cfg = kwargs.get("cfg") or next(a for a in args if isinstance(a, ModelConfig))
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
    net, n = make_network(cfg), cfg.n_keypoints
    return dict(net.init(key, jnp.zeros((n, 2)), jnp.ones((n,)), False))


def variables_shape(cfg: ModelConfig) -> Variables:
    """``init_variables``' pytree as ``jax.ShapeDtypeStruct`` leaves, computing nothing:
    the template a checkpoint's variables are restored onto."""
    return jax.eval_shape(lambda k: init_variables(k, cfg), jax.random.key(0))


def camera_frame(cfg: ModelConfig, phi_out, x_canon):
    """Camera-frame shape ``s R X`` (N, 3), the translation ``T`` (3,) and the rotation."""
    rot = so3.exp_map(phi_out["theta"])
    t = phi_out["translation"]
    if cfg.camera_xy_translation:
        t = t * jnp.array([1.0, 1.0, 0.0])
    t = t + jnp.array([0.0, 0.0, cfg.depth_offset])
    return phi_out["scale"] * x_canon @ rot.T, t, rot


KEYPOINT_SCALINGS = ("global", "per_view")
# The least RMS radius "per_view" divides a view by (normalised units, the training views'
# median about 1): a view whose points nearly coincide is not divided by 0.
MIN_VIEW_RADIUS = 1e-3


def normalised_input(cfg: ModelConfig, kp, vis, intrinsics):
    """``(kp_cal, kp_norm, centre, scale)``: calibrated keypoints (perspective), the
    network's centred, rescaled input, the centre removed and the factor the centred points
    were multiplied by. Hidden points are zeroed first (1e20, NaN never reach arithmetic)."""
    if cfg.keypoint_rescale == 0:  # the config's "from the data", never resolved
        raise ValueError("model.keypoint_rescale=0 means 'set it from the training data' and "
                         "was not resolved: the network would see zeros. Resolve it first "
                         "(resolve.resolve_input_scale(config, train_data), as "
                         "train_and_evaluate does; a loaded model has it)")
    if cfg.keypoint_scaling == "auto":
        raise ValueError("model.keypoint_scaling='auto' means 'from the training data' and was "
                         "not resolved (resolve.resolve_keypoint_scaling(config, train_data), "
                         "as train_and_evaluate does; a loaded model has it)")
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


def canonical_shape(net, params, alpha, class_mask):
    """Canonical shape (N, 3) from basis coefficients; points outside the class are 0."""
    return net.apply({"params": params}, alpha, method="shape") * class_mask[:, None]


def mean_shape(net, params, class_mask):
    """The basis' mean shape (N, 3): the canonical shape of coefficients 0."""
    return canonical_shape(net, params, jnp.zeros(net.shape_basis_size), class_mask)


def class_centred(x, class_mask):
    """``x`` (N, C) minus the mean of its class's points, the other points zeroed."""
    return (x - geometry.masked_mean(x, class_mask)[None]) * class_mask[:, None]


def reproject(cfg: ModelConfig, x_cam, kp_norm, vis):
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


@under_precision
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
      ``(terms, batch_stats)``, the updated BatchNorm statistics and squared distances
      that ``losses`` penalises and reduces: ``dist_sq`` (N,) of each reprojected point to
      the normalised input (unmasked); ``canon_dist_sq`` (S, N) of each point of Psi's
      reconstruction of each randomly rotated canonical shape to that shape (S = 0 without
      Psi); ``deform_sq`` (N,) of each canonical point to the mean shape's; with the 3D
      ground truth ``kp3d`` (camera frame, input units), ``sup_dist_sq`` (N,) of each
      camera-frame point to it, both class-centred, in network units. Also ``x_canon``
      (N, 3), the canonical shape, and ``mean_shape``.
    """
    net = make_network(cfg)
    params, stats = variables["params"], variables["batch_stats"]
    _, kp_norm, _, scale = normalised_input(cfg, kp, vis, intrinsics)

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

    x_canon = canonical_shape(net, params, phi_out["alpha"], class_mask)
    x_cam, t, _ = camera_frame(cfg, phi_out, x_canon)
    r_aug3 = jnp.eye(3).at[:2, :2].set(r_aug)
    x_cam = (x_cam + t[None]) @ r_aug3  # applies R_aug^T to column vectors
    _, _, dist_sq = reproject(cfg, x_cam, kp_norm, vis)
    mean = canonical_shape(net, params, jnp.zeros_like(phi_out["alpha"]), class_mask)
    terms = {"dist_sq": dist_sq, "canon_dist_sq": jnp.zeros((0, cfg.n_keypoints)),
             "deform_sq": jnp.sum((x_canon - mean) ** 2, axis=-1), "x_canon": x_canon,
             "mean_shape": mean}
    if kp3d is not None:
        terms["sup_dist_sq"] = jnp.sum((class_centred(x_cam, class_mask) - class_centred(
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
        x_hat = canonical_shape(net, params, alpha_psi, class_mask)
        return jnp.sum((x_hat - x_canon) ** 2, axis=-1), upd["batch_stats"]

    # Psi's BatchNorm statistics are means over the samples: one value (out_axes None).
    return jax.vmap(one, out_axes=(0, None), axis_name="sample")(rots)


def orthographic_only(used: bool, off: str, projection_type: str) -> str:
    """Why a setting for orthographic models (``off``: its value that turns it off) cannot
    be ``used`` with this projection ('' if it can)."""
    if used and projection_type == "perspective":  # another value has its own problem
        return f"must be {off} for a perspective model: orthographic models only"
    return ""


def keypoint_scaling_problem(scaling: str, projection_type: str) -> str:
    """Why ``keypoint_scaling=scaling`` cannot be used with this projection ('' if it can):
    a perspective view's calibrated points are not a shape's projection up to a scale."""
    return orthographic_only(scaling == "per_view", "'global' or 'auto'", projection_type)
