"""Per-example keypoint geometry: masked means, normalisation, projection, intrinsics.

Glossary: N keypoints; points on the last axis (``(N, 2)``, ``(N, 3)``); visibility
``vis`` is ``(N,)`` float in {0, 1}. Everything here is written for one sample and
batched with ``jax.vmap`` by callers.

Paper: Sec. 4.4 (zero-centring and scaling of the input keypoints; the camera
translation estimated from the means of the visible points).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from c3dpo_jax.types import Kp2, Kp3, Vis


def masked_mean(x: Float[Array, " N *C"], mask: Float[Array, " N"]) -> Float[Array, "*C"]:
    """Mean of the rows of ``x`` where ``mask`` is 1 (0 when no row is selected). Rows
    where ``mask`` is 0 are selected away, not multiplied by 0 (inf * 0 is NaN)."""
    m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
    return jnp.sum(jnp.where(m > 0, x * m, 0.0), axis=0) / jnp.maximum(jnp.sum(mask), 1.0)


def point_means(x: Float[Array, "M N *C"], mask: Float[Array, "M N"]) -> Float[Array, " N *C"]:
    """Each point's ``masked_mean`` over the examples whose ``mask`` has it."""
    return jax.vmap(masked_mean, in_axes=(1, 1))(x, mask)


def normalise_keypoints(
    kp: Kp2, vis: Vis, *, norm_type: str, rescale: float, root_joint: int = 0
) -> tuple[Kp2, Float[Array, "2"]]:
    """Centres keypoints (``to_mean``: visible mean; ``to_root``: one joint) and scales.

    Returns:
      ``(kp_norm, centre)`` with ``kp_norm = (kp - centre) * rescale`` for every
      point; the network masks invisible points itself (as the release does).
    """
    if norm_type == "to_mean":
        centre = masked_mean(kp, vis)
    elif norm_type == "to_root":
        centre = kp[root_joint]
    else:
        raise ValueError(f"unknown keypoint_norm_type {norm_type!r}")
    return (kp - centre[None]) * rescale, centre


def unnormalise_keypoints(kp_norm: Kp2, centre: Float[Array, "2"],
                          rescale: float | Float[Array, ""]) -> Kp2:
    """Inverse of ``normalise_keypoints`` (for every point, visible or not); ``rescale``
    the factor the centred points were multiplied by."""
    return kp_norm / rescale + centre[None]


def project(
    x_cam: Kp3, *, projection_type: str, depth_threshold: float = 0.1
) -> tuple[Kp2, Float[Array, " N"]]:
    """Projects camera-frame points; returns ``(xy, depth)``.

    Perspective divides by the depth clamped from below at ``depth_threshold``
    (as the release's ``perspective_depth_threshold``), so points behind the camera
    cannot produce infinities.
    """
    depth = x_cam[:, 2]
    if projection_type == "orthographic":
        return x_cam[:, :2], depth
    if projection_type == "perspective":
        return x_cam[:, :2] / jnp.maximum(depth, depth_threshold)[:, None], depth
    raise ValueError(f"unknown projection_type {projection_type!r}")


def argmin_translation(proj: Kp2, target: Kp2, vis: Vis) -> Kp2:
    """Shifts ``proj`` so the mean of its visible points matches that of ``target``.

    This is the least-squares 2D translation of paper Sec. 4.4 ("the camera
    translation as the difference vector between the mean of the input visible
    points and the re-projected visible 3D shape keypoints").
    """
    return proj + masked_mean(target - proj, vis)[None]


def calibrate(kp: Kp2, intrinsics: Float[Array, "3 3"]) -> Kp2:
    """Pixel coordinates -> normalised camera coordinates ``K^-1 [u, v, 1]``."""
    homog = jnp.concatenate([kp, jnp.ones_like(kp[:, :1])], axis=1)
    ray = homog @ jnp.linalg.inv(intrinsics).T
    return ray[:, :2] / ray[:, 2:3]


def uncalibrate(kp: Kp2, intrinsics: Float[Array, "3 3"]) -> Kp2:
    """Normalised camera coordinates -> pixel coordinates ``K [x, y, 1]``."""
    homog = jnp.concatenate([kp, jnp.ones_like(kp[:, :1])], axis=1)
    pix = homog @ intrinsics.T
    return pix[:, :2] / pix[:, 2:3]
