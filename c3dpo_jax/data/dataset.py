"""``KeypointData``: one split of a dataset as arrays, and config -> splits.

Glossary: M samples, N keypoints. Keypoints ``kp (M, N, 2)``, visibility
``vis (M, N)`` in {0, 1}, optional 3D ground truth ``kp3d (M, N, 3)`` in the camera
frame, optional ``class_mask (M, N)``, ``kp_defined (M, N)``, ``intrinsics (M, 3, 3)``,
``scale (M,)`` (h36m's metric scale), and ``group (M,)`` integer ids with
``group_names`` (actions for h36m, classes for multi-class data) used by the
evaluation protocol.
"""

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class KeypointData:
    kp: np.ndarray
    vis: np.ndarray
    kp3d: np.ndarray | None = None
    class_mask: np.ndarray | None = None
    kp_defined: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    scale: np.ndarray | None = None
    group: np.ndarray | None = None
    group_names: tuple[str, ...] = ()
    name: str = ""

    def __post_init__(self):
        m, n = self.vis.shape
        if self.kp.shape != (m, n, 2):
            raise ValueError(f"kp has shape {self.kp.shape}, expected {(m, n, 2)} (from vis)")
        for field, tail in (("kp3d", (n, 3)), ("class_mask", (n,)), ("kp_defined", (n,)),
                            ("intrinsics", (3, 3)), ("scale", ()), ("group", ())):
            value = getattr(self, field)
            if value is not None and value.shape != (m, *tail):
                raise ValueError(f"{field} has shape {value.shape}, expected {(m, *tail)}")

    def __len__(self) -> int:
        return self.vis.shape[0]

    @property
    def n_keypoints(self) -> int:
        return self.vis.shape[1]

    def subset(self, idx) -> "KeypointData":
        """Rows ``idx`` of every per-sample array."""
        fields = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            fields[f.name] = value[idx] if isinstance(value, np.ndarray) else value
        return KeypointData(**fields)

    def model_inputs(self) -> dict[str, np.ndarray]:
        """The arrays the compiled step consumes (class mask of ones when absent)."""
        out = {
            "kp": self.kp.astype(np.float32),
            "vis": self.vis.astype(np.float32),
            "class_mask": (
                np.ones_like(self.vis, np.float32)
                if self.class_mask is None
                else self.class_mask.astype(np.float32)
            ),
        }
        if self.intrinsics is not None:
            out["intrinsics"] = self.intrinsics.astype(np.float32)
        return out


def load_splits(data_cfg) -> tuple[KeypointData, KeypointData]:
    """Returns ``(train, test)`` for a ``config.data`` section.

    ``train_path``/``test_path`` (the release's JSON format) win when set; otherwise
    ``source == "synthetic"`` generates the built-in low-rank dataset.
    """
    from c3dpo_jax.data import json_dataset, synthetic

    if data_cfg.train_path:
        if not data_cfg.test_path:
            raise ValueError("config.data.train_path is set but config.data.test_path is not")
        return json_dataset.load(data_cfg.train_path), json_dataset.load(data_cfg.test_path)
    if data_cfg.source == "synthetic":
        return synthetic.make_splits(**dict(data_cfg.synthetic))
    raise ValueError(
        f"dataset {data_cfg.get('name', '?')!r} needs files: pass "
        "--config.data.train_path=TRAIN.json --config.data.test_path=TEST.json "
        "(the release's JSON format, see README 'Data'), or use configs/synthetic.py"
    )
