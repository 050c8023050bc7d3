"""Training data on the devices: placement, the data-parallel mesh, and the sampling of
each step's batch (inside the compiled chunk, ``train.make_train_chunk``).

Glossary: M samples, B batch. The training arrays stay on the device for the whole run;
every step draws its ``B`` indices with replacement (as the release), class-balanced when
the arrays carry the class tables that ``device_train_data`` adds, or, for
``loss.w_multiview``, ``B / V`` frames, each with ``V`` of its views (the frame tables).
"""

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from c3dpo_jax.data import KeypointData

# The lookup tables of the samplers: not per-sample arrays.
TABLES = ("class_start", "class_count", "frame_start", "frame_count")


def device_train_data(data: KeypointData, class_balanced: bool, with_3d: bool = False,
                      by_frame: bool = False):
    """Training arrays for the device (``with_3d``: the 3D ground truth too, ``kp3d``);
    sorted by class with lookup tables if balanced, or by frame (``data.frame``) with
    lookup tables if ``by_frame``."""
    tables = {}
    if by_frame:
        if data.frame is None:
            raise ValueError("config.loss.w_multiview > 0 links the views of one frame, and "
                             "the train split has no frame ids ('frame_id' in its JSON "
                             "entries, which the importer writes)")
        data = data.subset(np.argsort(data.frame, kind="stable"))
        _, starts, counts = np.unique(data.frame, return_index=True, return_counts=True)
        if counts.max() < 2:
            raise ValueError("config.loss.w_multiview > 0 links the views of one frame, and "
                             "no frame of the train split has two views (each 'frame_id' "
                             "is used once)")
        tables = {"frame_start": starts.astype(np.int32), "frame_count": counts.astype(np.int32)}
    elif class_balanced and data.group is not None:
        data = data.subset(np.argsort(data.group, kind="stable"))
        counts = np.bincount(data.group, minlength=len(data.group_names))
        present = counts > 0
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tables = {"class_start": starts[present].astype(np.int32),
                  "class_count": counts[present].astype(np.int32)}
    if with_3d:
        tables["kp3d"] = data.kp3d.astype(np.float32)
    return jax.device_put(dict(data.model_inputs(), **tables))


def sample_indices(data, key, batch_size: int, views: int = 0):
    """Indices drawn with replacement; class-balanced when ``data`` has class tables; with
    frame tables, ``batch_size / views`` frames drawn with replacement, each giving
    ``views`` consecutive indices of its views (distinct where it has that many, from a
    random one on, cyclically)."""
    n = data["vis"].shape[0]
    if "frame_start" in data:
        k_frame, k_first = jax.random.split(key)
        frame = jax.random.randint(k_frame, (batch_size // views,), 0,
                                   data["frame_start"].shape[0])
        count = data["frame_count"][frame]
        first = jax.random.randint(k_first, frame.shape, 0, count)
        offset = (first[:, None] + jax.numpy.arange(views)[None]) % count[:, None]
        return (data["frame_start"][frame][:, None] + offset).reshape(-1)
    if "class_start" not in data:
        return jax.random.randint(key, (batch_size,), 0, n)
    k_class, k_item = jax.random.split(key)
    cls = jax.random.randint(k_class, (batch_size,), 0, data["class_start"].shape[0])
    offset = jax.random.randint(k_item, (batch_size,), 0, data["class_count"][cls])
    return data["class_start"][cls] + offset


def make_mesh(n_devices: int | None = None) -> Mesh:
    """A 1D mesh with axis ``"data"`` over the first ``n_devices`` devices (default all)."""
    devices = jax.devices()[: n_devices or jax.device_count()]
    return Mesh(np.array(devices), ("data",))


def replicate(tree, mesh: Mesh):
    """Copies every array of ``tree`` onto every device of ``mesh``."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))
