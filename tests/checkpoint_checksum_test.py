"""Checkpoints prove themselves: every finished save records the sha256 of its files, and
a newest checkpoint that is corrupt in any of eight ways is skipped for the intact one."""

import json
import os
import pathlib
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

from c3dpo_jax import checkpoint

TEMPLATE = {"w": jnp.zeros((64, 64)), "n": jnp.int32(0)}


def _weights(step: int):
    return np.random.default_rng(step).normal(size=(64, 64)).astype(np.float32)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Steps 1..5 saved with max_to_keep=3: steps 3, 4, 5 remain."""
    workdir = str(tmp_path_factory.mktemp("saved"))
    manager = checkpoint.make_manager(workdir, save_every=1)
    for step in range(1, 6):  # random values: the array data is the biggest file
        checkpoint.save(manager, step, {"w": jnp.asarray(_weights(step)), "n": jnp.int32(step)})
    manager.close()
    return workdir


def _files(folder: str) -> list[str]:
    return sorted(
        (os.path.join(d, f) for d, _, fs in os.walk(folder) for f in fs), key=os.path.getsize
    )


def test_every_kept_step_records_the_checksum_of_each_of_its_files(saved):
    ckpts = os.path.join(saved, checkpoint.CHECKPOINT_DIR)
    assert sorted(os.listdir(ckpts)) == ["3", "4", "5"]
    for step in ("3", "4", "5"):
        folder = os.path.join(ckpts, step)
        with open(os.path.join(folder, checkpoint.CHECKSUM_FILE)) as f:
            recorded = json.load(f)
        files = {os.path.relpath(p, folder) for p in _files(folder)}
        assert set(recorded) == files - {checkpoint.CHECKSUM_FILE} and len(recorded) > 5


def _flip(path, n=3):
    data = bytearray(pathlib.Path(path).read_bytes())
    for i in np.random.default_rng(0).choice(len(data), n, replace=False):
        data[i] ^= 0xFF
    pathlib.Path(path).write_bytes(bytes(data))


def _damage(folder: str, how: str) -> None:
    biggest = _files(folder)[-1]  # the array data
    if how == "flip_3_bytes":
        _flip(biggest)
    elif how == "randomise_data":
        size = os.path.getsize(biggest)
        pathlib.Path(biggest).write_bytes(np.random.default_rng(1).bytes(size))
    elif how == "delete_data":
        os.remove(biggest)
    elif how == "truncate_data":
        os.truncate(biggest, os.path.getsize(biggest) // 2)
    elif how == "delete_item_metadata":
        os.remove(os.path.join(folder, "default", "_METADATA"))
    elif how == "delete_step_metadata":
        os.remove(os.path.join(folder, "_CHECKPOINT_METADATA"))
    elif how == "empty_folder":  # a kill during max_to_keep's clean-up
        for path in _files(folder):
            os.remove(path)
    elif how == "garbled_record":
        pathlib.Path(folder, checkpoint.CHECKSUM_FILE).write_text("{not json")


CORRUPTIONS = [
    "flip_3_bytes",
    "randomise_data",
    "delete_data",
    "truncate_data",
    "delete_item_metadata",
    "delete_step_metadata",
    "empty_folder",
    "garbled_record",
]


@pytest.mark.parametrize("how", CORRUPTIONS)
def test_each_corruption_of_the_newest_falls_back_to_the_previous_step(
    saved, tmp_path, how, caplog
):
    workdir = str(tmp_path / "w")
    shutil.copytree(saved, workdir)
    _damage(os.path.join(workdir, checkpoint.CHECKPOINT_DIR, "5"), how)
    state, step = checkpoint.restore_latest(workdir, TEMPLATE)
    assert step == 4 and int(state["n"]) == 4
    np.testing.assert_array_equal(state["w"], _weights(4))
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("/5 " in w and "\n" not in w for w in warnings), warnings


def test_flipped_bytes_are_caught_by_the_checksum_before_orbax_reads(saved, tmp_path, caplog):
    workdir = str(tmp_path / "w")
    shutil.copytree(saved, workdir)
    folder = os.path.join(workdir, checkpoint.CHECKPOINT_DIR, "5")
    _flip(_files(folder)[-1])
    _, step = checkpoint.restore_latest(workdir, TEMPLATE)
    assert step == 4
    assert "checkpoint" in caplog.text and "/5 cannot be read (" in caplog.text
    assert "fails its sha256 checksum)" in caplog.text


def test_a_step_without_a_record_is_still_used(saved, tmp_path):
    workdir = str(tmp_path / "w")
    shutil.copytree(saved, workdir)
    os.remove(os.path.join(workdir, checkpoint.CHECKPOINT_DIR, "5", checkpoint.CHECKSUM_FILE))
    state, step = checkpoint.restore_latest(workdir, TEMPLATE)
    assert step == 5
    np.testing.assert_array_equal(state["w"], _weights(5))


def test_nothing_intact_is_one_error(saved, tmp_path):
    workdir = str(tmp_path / "w")
    shutil.copytree(saved, workdir)
    for step in ("3", "4", "5"):
        _flip(_files(os.path.join(workdir, checkpoint.CHECKPOINT_DIR, step))[-1])
    with pytest.raises(
        ValueError,
        match=r"no checkpoint under .* can be read \(steps "
        r"\[5, 4, 3\]\)",
    ):
        checkpoint.restore_latest(workdir, TEMPLATE)
