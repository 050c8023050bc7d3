"""Official PyTorch weights (facebookresearch/c3dpo_nrsfm) -> ``C3DPOParams``.

The release writes dense layers as 1x1 convolutions with weights ``(out, in, 1, 1)``;
flax ``Dense`` kernels are ``(in, out)``. Its trunks are ``nn.Sequential`` s: index 0 is
the first layer (``conv1``, ``bn1``), indices 1..L the residual blocks
(``conv1..3``, ``bn1..3``), which become ``conv1``/``bn1`` and ``block1..L`` here.
BatchNorm ``weight, bias, running_mean, running_var`` become ``scale, bias`` (params)
and ``mean, var`` (batch_stats); ``num_batches_tracked`` is dropped.
"""

import re
from typing import Any

import jax
import numpy as np
from absl import logging

from c3dpo_jax import model
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.model import ModelConfig
from c3dpo_jax.reconstruct import C3DPOParams

# Release constructor argument -> ModelConfig field (same name unless listed).
_SAME = (
    "n_keypoints", "shape_basis_size", "n_fully_connected", "n_layers", "keypoint_rescale",
    "keypoint_norm_type", "root_joint", "projection_type", "perspective_depth_threshold",
    "argmin_translation", "camera_translation", "camera_xy_translation", "depth_offset",
    "camera_scale", "z_augment", "z_augment_rot_angle", "z_equivariance",
    "z_equivariance_rot_angle", "independent_phi_for_aug", "weight_init_std",
)
# Release constructor arguments that are inference options here (``lift.InferenceConfig``).
_INFERENCE = ("replace_keypoints_with_input",)
_CANON = {
    "use": "canonicalization", "n_layers": "canonicalization_n_layers",
    "n_fully_connected": "canonicalization_n_fully_connected",
    "n_rand_samples": "n_rand_samples", "rot_angle": "canonicalization_rot_angle",
}
# Training-only or plotting options of the release (its loss options are
# ``losses.LossConfig``'s here): accepted, not needed for inference.
_IGNORED = ("loss_weights", "log_vars", "connectivity_setup") + model.MOVED_TO_LOSS


def model_config_from_official(config: dict[str, Any]) -> ModelConfig:
    """The release's ``C3DPO(**kwargs)`` dict -> ``ModelConfig``; unknown keys raise."""
    fields, unknown = {}, []
    for key, value in config.items():
        if key in _SAME:
            fields[key] = value
        elif key == "canonicalization":
            for sub, sub_value in dict(value).items():
                if sub in _CANON:
                    fields[_CANON[sub]] = sub_value
                else:
                    unknown.append(f"canonicalization.{sub}")
        elif key in _INFERENCE:
            continue  # inference_from_official's
        elif key in _IGNORED:
            logging.info("ignoring the release option %r (not used at inference)", key)
        else:
            unknown.append(key)
    if unknown:
        raise ValueError(f"unknown release option(s) {sorted(unknown)}; known: "
                         f"{sorted(_SAME + _INFERENCE + _IGNORED)} and "
                         f"canonicalization.{sorted(_CANON)}")
    return ModelConfig(**fields)


def inference_from_official(config: dict[str, Any]) -> InferenceConfig:
    """The inference options of the release's ``C3DPO(**kwargs)`` dict (the others are the
    release's inference, the defaults)."""
    return InferenceConfig(**{k: config[k] for k in _INFERENCE if k in config})


def _dense(sd: dict, name: str) -> dict[str, np.ndarray]:
    w = np.asarray(sd[f"{name}.weight"], np.float32)
    return {"kernel": w.reshape(w.shape[0], w.shape[1]).T,
            "bias": np.asarray(sd[f"{name}.bias"], np.float32)}


def _bn(sd: dict, name: str) -> tuple[dict, dict]:
    get = lambda field: np.asarray(sd[f"{name}.{field}"], np.float32)  # noqa: E731
    return ({"scale": get("weight"), "bias": get("bias")},
            {"mean": get("running_mean"), "var": get("running_var")})


def _trunk(sd: dict, prefix: str, n_layers: int) -> tuple[dict, dict]:
    params = {"conv1": _dense(sd, f"{prefix}.0.conv1")}
    params["bn1"], stats = _bn(sd, f"{prefix}.0.bn1")
    stats = {"bn1": stats}
    for i in range(1, n_layers + 1):
        block_p, block_s = {}, {}
        for j in (1, 2, 3):
            block_p[f"conv{j}"] = _dense(sd, f"{prefix}.{i}.conv{j}")
            block_p[f"bn{j}"], block_s[f"bn{j}"] = _bn(sd, f"{prefix}.{i}.bn{j}")
        params[f"block{i}"], stats[f"block{i}"] = block_p, block_s
    return params, stats


def _check_keys(sd: dict, cfg: ModelConfig) -> None:
    used = re.compile(r"^(phi|psi)\.\d+\.(conv|bn)\d\.|^(alpha_layer|alpha_layer_psi|rot_layer|"
                      r"shape_layer|translation_layer|scale_layer\.0)\.")
    extra = sorted(k for k in sd if not used.match(k))
    if extra:
        raise ValueError(f"unexpected state_dict entries {extra[:10]}")
    n_phi = len({k.split(".")[1] for k in sd if k.startswith("phi.")}) - 1
    if n_phi != cfg.n_layers:
        raise ValueError(f"state_dict has {n_phi} Phi blocks but the config says "
                         f"n_layers={cfg.n_layers}")


def from_official(state_dict: dict[str, np.ndarray], config: dict[str, Any]) -> C3DPOParams:
    """Converts the release's ``state_dict`` (numpy arrays) and ``C3DPO(**kwargs)`` dict.

    Returns:
      ``C3DPOParams`` whose parameter tree matches ``model.init_variables`` exactly.
    """
    cfg = model_config_from_official(config)
    sd = {k: np.asarray(v) for k, v in state_dict.items()}
    _check_keys(sd, cfg)
    params, stats = {}, {}
    params["phi_trunk"], stats["phi_trunk"] = _trunk(sd, "phi", cfg.n_layers)
    params["psi_trunk"], stats["psi_trunk"] = _trunk(sd, "psi", cfg.canonicalization_n_layers)
    heads = {"alpha_layer": "alpha_layer", "rot_layer": "rot_layer",
             "shape_layer": "shape_layer", "alpha_layer_psi": "alpha_layer_psi"}
    if cfg.camera_translation:
        heads["translation_layer"] = "translation_layer"
    if cfg.camera_scale:
        heads["scale_layer"] = "scale_layer.0"
    for ours, theirs in heads.items():
        params[ours] = _dense(sd, theirs)
    variables = {"params": params, "batch_stats": stats}
    expected = jax.eval_shape(lambda k: model.init_variables(k, cfg), jax.random.key(0))
    got = jax.tree.map(lambda a: a.shape, variables)
    want = jax.tree.map(lambda a: a.shape, expected)
    if got != want:
        raise ValueError("converted parameters do not match the model's layout: "
                         f"{jax.tree_util.tree_structure(got)} vs "
                         f"{jax.tree_util.tree_structure(want)}")
    return C3DPOParams(variables=jax.tree.map(np.asarray, variables), config=cfg,
                       inference=inference_from_official(config))


def load_official_pth(path: str, config: dict[str, Any]) -> C3DPOParams:
    """Reads a release ``.pth`` file (needs PyTorch, imported only here) and converts it."""
    try:
        import torch
    except ImportError:
        raise ImportError("reading a .pth file needs PyTorch: pip install torch (or "
                          "'c3dpo_jax[torch]'); the converted model then runs without it") from None
    obj = torch.load(path, map_location="cpu", weights_only=False)
    state_dict = obj.get("state_dict", obj) if isinstance(obj, dict) else obj
    return from_official({k: v.detach().cpu().numpy() for k, v in state_dict.items()}, config)
