"""Datasets as numpy arrays: the release's JSON files and built-in generated data."""

from c3dpo_jax.data.dataset import KeypointData, alike_view_size_ratio, auto_keypoint_rescale
from c3dpo_jax.data.splits import load_splits

__all__ = ["KeypointData", "alike_view_size_ratio", "auto_keypoint_rescale", "load_splits"]
