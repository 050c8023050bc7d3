"""C3DPO (Novotny et al., ICCV 2019) in JAX/Flax.

Public API (light imports only; plotting lives in ``c3dpo_jax.visualise``)::

    from c3dpo_jax import load, reconstruct
    params = load("runs/synthetic")
    rec = reconstruct(params, kp, vis)  # kp (N, 2) or (B, N, 2), vis (N,) or (B, N)
    rec = reconstruct_data(params, test, n)  # the first n samples of a KeypointData
    rec = reconstruct(params, kp, vis, refine_iters=0)  # an InferenceConfig field, by name
"""

from c3dpo_jax.convert import from_official
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.model import ModelConfig
from c3dpo_jax.reconstruct import C3DPOParams, Reconstruction, load, reconstruct, reconstruct_data

__all__ = ["C3DPOParams", "InferenceConfig", "ModelConfig", "Reconstruction", "from_official",
           "load", "reconstruct", "reconstruct_data"]
