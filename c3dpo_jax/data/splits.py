"""A config's ``data`` section -> ``(train, test)`` ``KeypointData``: the release's JSON
files, a downloaded release dataset or a built-in generator.

This module sits above the data layer: it imports the generators and readers, which
import only ``dataset`` (so nothing in ``data/`` imports in a circle).
"""

from c3dpo_jax.data import categories, download, humans, json_dataset, synthetic
from c3dpo_jax.data.dataset import KeypointData, check_spread


def load_splits(data_cfg) -> tuple[KeypointData, KeypointData]:
    """Returns ``(train, test)`` for a ``config.data`` section.

    ``train_path``/``test_path`` (the release's JSON format) win when set; otherwise
    ``source`` picks a generated dataset (``"synthetic"``, ``"humans"``,
    ``"categories"``, with parameters in ``config.data.<source>``) or ``"release"``,
    which resolves ``config.data.name`` to the release's files (downloaded once).
    Errors name the split; a split with no spread at all is an error (``check_spread``).
    """
    splits = _load_splits(data_cfg)
    for split, data in zip(("train", "test"), splits, strict=True):
        check_spread(data, split)
    return splits


def _load_splits(data_cfg) -> tuple[KeypointData, KeypointData]:
    def load_json(path, split):
        try:
            return json_dataset.load(path, min_visible=data_cfg.get("min_visible", 2),
                                     drop_invalid=data_cfg.get("drop_invalid", False))
        except ValueError as err:
            raise ValueError(f"{split} split: {err}") from None

    if data_cfg.train_path:
        if not data_cfg.test_path:
            raise ValueError("config.data.train_path is set but config.data.test_path is not")
        return load_json(data_cfg.train_path, "train"), load_json(data_cfg.test_path, "test")
    generators = {"synthetic": synthetic.make_splits, "humans": humans.make_splits,
                  "categories": categories.make_splits}
    if data_cfg.source in generators:
        return generators[data_cfg.source](**dict(data_cfg[data_cfg.source]))
    if data_cfg.source == "json":
        raise ValueError("this config trains on your own JSON files: pass "
                         "--config.data.train_path=TRAIN.json --config.data.test_path=TEST.json")
    if data_cfg.source == "release":
        paths = download.dataset_files(data_cfg.name, directory=data_cfg.get("data_dir") or None)
        return load_json(paths[0], "train"), load_json(paths[1], "test")
    raise ValueError(
        f"unknown config.data.source {data_cfg.source!r}: one of {sorted(generators)} or "
        "'release'; or pass --config.data.train_path=TRAIN.json "
        "--config.data.test_path=TEST.json (the release's JSON format, see docs/data.md)"
    )
