"""The robust penalty of C3DPO's loss terms, on squared distances (the release's
pseudo-Huber). Below ``model`` in the import order: the forward passes apply it per
point (training terms, ``Prediction.repro``) and ``losses`` reduces what they return.
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
