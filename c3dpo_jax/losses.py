"""C3DPO's losses: the pseudo-Huber penalty and the batch reductions of its terms.

Glossary: B batch, N keypoints, S canonicalisation samples. The per-example forward
(``model.forward_train``) returns elementwise terms; this module owns the one explicit
masked reduction of each, so the normalisation is written down in one place.

Paper: eq. 4 (l1, reprojection), eq. 5 (l2, canonicalisation), eq. 6 (l3, the
reprojection loss with the shape coefficients of an in-plane rotated copy).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float


def huber(dist_sq: Float[Array, "*S"], scaling: float) -> Float[Array, "*S"]:
    """Pseudo-Huber of a squared distance: ``(sqrt(1 + d2/eps^2) - 1) * eps``.

    Written on the squared distance so its gradient is finite at a perfect fit
    (the norm itself is not differentiable at 0), and in the algebraically equal form
    ``d2 / (eps (sqrt(1 + d2/eps^2) + 1))``, which has no cancellation for tiny
    residuals in float32.
    """
    return dist_sq / (scaling * (jnp.sqrt(1.0 + dist_sq / scaling**2) + 1.0))


def reprojection(
    repro: Float[Array, "B N"], vis: Float[Array, "B N"], normalization: str
) -> Float[Array, ""]:
    """Masked mean of per-point reprojection errors over the batch.

    ``kp_total_count`` divides the sum over all visible points of the batch by their
    number (the release's default); ``kp_count_per_image`` averages each image over its
    own visible points first, then averages the images (the release crashes on this
    option; here it works).
    """
    masked = jnp.where(vis > 0, repro * vis, 0.0)  # a hidden point's inf never becomes NaN
    if normalization == "kp_total_count":
        return jnp.sum(masked) / jnp.maximum(jnp.sum(vis), 1.0)
    if normalization == "kp_count_per_image":
        return jnp.mean(jnp.sum(masked, axis=1) / jnp.maximum(jnp.sum(vis, axis=1), 1.0))
    raise ValueError(f"unknown reprojection_normalization {normalization!r}")


def canonicalisation(canon: Float[Array, "B S"]) -> Float[Array, ""]:
    """Mean over examples and random rotations of the per-sample point means."""
    if canon.shape[-1] == 0:
        return jnp.zeros(())
    return jnp.mean(canon)
