"""Checkpoints: a damaged newest checkpoint is skipped for the newest intact one."""

import os
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

from c3dpo_jax import checkpoint


def _weights(step: int):
    return np.random.default_rng(step).normal(size=(64, 64)).astype(np.float32)


def _save_three(workdir: str):
    manager = checkpoint.make_manager(workdir, save_every=1)
    for step in (1, 2, 3):  # random values: the array data is the biggest file
        checkpoint.save(manager, step, {"w": jnp.asarray(_weights(step)), "n": jnp.int32(step)})
    manager.wait_until_finished()
    manager.close()
    return os.path.join(workdir, checkpoint.CHECKPOINT_DIR)


def _files(folder: str) -> list[str]:
    return sorted((os.path.join(d, f) for d, _, fs in os.walk(folder) for f in fs),
                  key=os.path.getsize)


TEMPLATE = {"w": jnp.zeros((64, 64)), "n": jnp.int32(0)}


# A failed read leaves orbax's asynchronous readers un-awaited; Python reports them as
# unraisable exceptions when they are collected, which is not what these tests are about.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize("damage", ["delete_data", "truncate_data", "empty_folder",
                                    "item_folder_gone", "bare_step_folder"])
def test_a_damaged_newest_checkpoint_is_skipped_for_the_previous_one(tmp_path, damage, caplog):
    ckpts = _save_three(str(tmp_path))
    newest = os.path.join(ckpts, "3")
    if damage == "empty_folder":  # e.g. a kill during max_to_keep's clean-up
        for path in _files(newest):
            os.remove(path)
    elif damage == "item_folder_gone":  # the saved tree's folder and the record deleted
        shutil.rmtree(os.path.join(newest, "default"))
        os.remove(os.path.join(newest, checkpoint.CHECKSUM_FILE))
    elif damage == "bare_step_folder":  # a step folder holding nothing at all
        shutil.rmtree(newest)
        os.makedirs(newest)
    else:
        biggest = _files(newest)[-1]  # the array data
        if damage == "delete_data":
            os.remove(biggest)
        else:
            with open(biggest, "r+b") as f:
                f.truncate(os.path.getsize(biggest) // 2)
    state, step = checkpoint.restore_latest(str(tmp_path), TEMPLATE)
    assert step == 2 and int(state["n"]) == 2
    np.testing.assert_array_equal(state["w"], _weights(2))
    assert "checkpoint" in caplog.text and "/3 cannot be read" in caplog.text
    if damage in ("bare_step_folder", "item_folder_gone"):
        assert "(its saved state is missing: an empty or partly deleted step folder)" in caplog.text
    # In one line of its own: orbax's several about the missing files are not shown.
    assert not [r for r in caplog.records if f"{os.sep}orbax{os.sep}" in r.pathname]
    with pytest.raises(ValueError, match="checkpoint 3 .* cannot be read"):
        checkpoint.restore_latest(str(tmp_path), TEMPLATE, step=3)
    with pytest.raises(FileNotFoundError,
                       match=r"no checkpoint 9 under .* \(its steps: \[1, 2, 3\]\)"):
        checkpoint.restore_latest(str(tmp_path), TEMPLATE, step=9)
    # Training resumes from step 2 and saves step 3 again: the damaged one is moved aside.
    manager = checkpoint.make_manager(str(tmp_path), save_every=1)
    assert int(checkpoint.restore_or_init(manager, TEMPLATE)["n"]) == 2
    assert "moved the unreadable checkpoint" in caplog.text
    checkpoint.save(manager, 3, {"w": _weights(3), "n": jnp.int32(3)})
    manager.wait_until_finished()
    manager.close()
    assert sorted(os.listdir(ckpts)) == ["1", "2", "3", "3.unreadable"]
    state, step = checkpoint.restore_latest(str(tmp_path), TEMPLATE)
    assert step == 3 and int(state["n"]) == 3


def test_non_finite_values_are_not_restored_and_no_intact_checkpoint_is_an_error(tmp_path):
    manager = checkpoint.make_manager(str(tmp_path), save_every=1)
    checkpoint.save(manager, 1, {"w": jnp.full((64, 64), jnp.nan), "n": jnp.int32(1)})
    manager.wait_until_finished()
    manager.close()
    with pytest.raises(ValueError, match="no checkpoint under .* can be read"):
        checkpoint.restore_latest(str(tmp_path), TEMPLATE)
    with pytest.raises(FileNotFoundError, match="no checkpoint found"):
        checkpoint.restore_latest(str(tmp_path / "elsewhere"), TEMPLATE)
    assert not (tmp_path / "elsewhere").exists()  # reading makes no folder


def test_a_new_run_removes_the_uncommitted_saves_of_a_killed_one(tmp_path):
    ckpts = _save_three(str(tmp_path))
    left = os.path.join(ckpts, "7.orbax-checkpoint-tmp")  # a save that never committed
    os.makedirs(os.path.join(left, "default"))
    manager = checkpoint.make_manager(str(tmp_path), save_every=1)
    assert int(checkpoint.restore_or_init(manager, TEMPLATE)["n"]) == 3
    checkpoint.save(manager, 4, {"w": jnp.asarray(_weights(4)), "n": jnp.int32(4)})
    manager.close()
    assert sorted(os.listdir(ckpts)) == ["2", "3", "4"]
