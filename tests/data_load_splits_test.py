"""config.data -> splits for every source, with the default config's sections."""

import pytest

from c3dpo_jax.data import download, load_splits
from configs import categories as categories_cfg
from configs import default, own_json
from configs import humans as humans_cfg


def test_builtin_sources_match_their_configs():
    for module in (humans_cfg, categories_cfg):
        c = module.get_config("smoke")
        train, test = load_splits(c.data)
        assert train.n_keypoints == test.n_keypoints == c.model.n_keypoints
        assert len(train) > len(test) > 0


def test_synthetic_source_is_unchanged():
    c = default.apply_variants(default.get_config(), "smoke")
    train, _ = load_splits(c.data)
    assert train.kp.shape == (256, 20, 2) and train.name == "synthetic"


def test_own_json_needs_paths_and_release_resolves_names(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="--config.data.train_path=TRAIN.json"):
        load_splits(own_json.get_config().data)
    c = default.get_config()
    c.data.source, c.data.name, c.data.data_dir = "release", "h36m", str(tmp_path)
    seen = {}
    monkeypatch.setattr(download, "dataset_files",
                        lambda name, directory: seen.update(n=name, d=directory) or ("a", "b"))
    with pytest.raises(FileNotFoundError, match="'a' does not exist"):
        load_splits(c.data)
    assert seen == {"n": "h36m", "d": str(tmp_path)}
    c.data.source = "nope"
    with pytest.raises(ValueError, match="unknown config.data.source 'nope'"):
        load_splits(c.data)
