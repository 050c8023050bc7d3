"""Workdir reuse: a workdir without checkpoints takes any run; one with checkpoints refuses,
before anything is written, a run with another model, optimiser or training data."""

import json
import os

import pytest

from c3dpo_jax import checkpoint, run_config, train
from c3dpo_jax.reconstruct import load
from configs import default


def _config(**changes):
    c = default.apply_variants(default.get_config(), "smoke")
    c.model.n_keypoints = c.data.synthetic.n_keypoints = 8
    c.model.shape_basis_size = 3
    c.train.num_steps, c.train.ckpt_every, c.train.log_every = 10, 10, 5
    c.train.progress_bar = False
    c.update_from_flattened_dict(changes)
    return c


def _workdir(tmp_path, with_checkpoint: bool):
    workdir = str(tmp_path / "w")
    os.makedirs(os.path.join(workdir, "checkpoints", "10" if with_checkpoint else ""))
    run_config.save_config(workdir, _config().to_dict())
    return workdir


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"optim.optimizer": "adam"}, "optim.optimizer: 'sgd' in the checkpoint's run, 'adam' now"),
        ({"optim.lr_milestones": (3,)}, "optim.lr_milestones: [] in the checkpoint's run, [3] now"),
        ({"model.shape_basis_size": 4}, "model.shape_basis_size: 3 in the checkpoint's run, 4 now"),
        ({"data.synthetic.seed": 1}, "data.synthetic.seed: 0 in the checkpoint's run, 1 now"),
        (
            {"data.source": "humans"},
            "data.source: 'synthetic' in the checkpoint's run, 'humans' now",
        ),
        (
            {"data.train_path": "a.json"},
            "data.train_path: '' in the checkpoint's run, 'a.json' now",
        ),
        ({"data.class_balanced": True}, "data.class_balanced: False in the checkpoint's run"),
        # The objective, the seed and the batches: a resumed run under other ones would
        # continue the old run while config.json described the new settings.
        ({"loss.w_canonicalization": 3.0},
         "loss.w_canonicalization: 1.0 in the checkpoint's run, 3.0 now"),
        ({"seed": 1}, "seed: 0 in the checkpoint's run, 1 now"),
        ({"train.batch_size": 64}, "train.batch_size: 32 in the checkpoint's run, 64 now"),
        ({"train.samples_per_epoch": 64}, "train.samples_per_epoch: 320 in the checkpoint's run"),
    ],
)
def test_another_run_is_refused_only_where_checkpoints_exist(tmp_path, change, named):
    workdir = _workdir(tmp_path, with_checkpoint=True)
    with pytest.raises(ValueError) as err:
        run_config.check_workdir(workdir, _config(**change).to_dict())
    text = str(err.value)
    assert text.startswith(f"{workdir} holds checkpoints of another run (") and named in text
    assert "\n" not in text and "use a new --workdir" in text
    empty = _workdir(tmp_path / "empty", with_checkpoint=False)
    run_config.check_workdir(empty, _config(**change).to_dict())  # nothing to protect


@pytest.mark.parametrize(
    "change",
    [
        {"train.num_steps": 50},
        {"train.ckpt_every": 5},
        {"data.protocol": "none"},
        {"data.test_path": "b.json"},
        {"inference.refine_iters": 5},  # inference only
        {"train.epochs": 20},
    ],
)
def test_what_a_resumed_run_may_change(tmp_path, change):
    run_config.check_workdir(_workdir(tmp_path, with_checkpoint=True), _config(**change).to_dict())


def test_fields_only_one_config_has_are_not_compared(tmp_path):
    workdir = _workdir(tmp_path, with_checkpoint=True)
    newer = _config().to_dict()
    newer["optim"]["an_option_added_later"] = 1
    run_config.check_workdir(workdir, newer)


def test_checkpoints_without_their_config_are_refused(tmp_path):
    workdir = _workdir(tmp_path, with_checkpoint=True)
    os.remove(os.path.join(workdir, "config.json"))
    with pytest.raises(ValueError, match="holds checkpoints but no config.json, so which run "
                                         "they belong to is unknown"):
        run_config.check_workdir(workdir, _config().to_dict())


def test_the_same_training_data_under_another_path_is_the_same_run(tmp_path):
    """The training data's fingerprint, not the path that named it, says what a run learnt
    from: a moved data folder or a relative path for an absolute one resumes."""
    workdir = str(tmp_path / "w")
    os.makedirs(os.path.join(workdir, "checkpoints", "10"))
    saved = dict(_config(**{"data.train_path": "/data/a_train.json"}).to_dict(),
                 train_data_sha256="0123456789abcdef")
    run_config.save_config(workdir, saved)
    moved = dict(saved, data=dict(saved["data"], train_path="elsewhere/a_train.json"))
    run_config.check_workdir(workdir, moved)
    with pytest.raises(ValueError, match="train_data_sha256: '0123456789ab' in the checkpoint"):
        run_config.check_workdir(workdir, dict(moved, train_data_sha256="fedcba9876543210"))


def test_config_json_is_replaced_whole(tmp_path):
    run_config.save_config(str(tmp_path), {"a": 1})
    run_config.save_config(str(tmp_path), {"a": 2})
    assert os.listdir(tmp_path) == ["config.json"]
    assert run_config.load_config(str(tmp_path)) == {"a": 2}


def test_a_damaged_config_json_is_named_in_one_line(tmp_path):
    run_config.save_config(str(tmp_path), _config().to_dict())
    path = tmp_path / "config.json"
    path.write_text(path.read_text()[:200])  # cut short, as by a full disk
    for read in (run_config.load_config, load):
        with pytest.raises(ValueError, match=f"^{path} is not valid JSON .*: it holds the run's"):
            read(str(tmp_path))


def test_a_failed_run_leaves_the_workdir_reusable_and_a_refused_one_leaves_it_intact(tmp_path):
    workdir = str(tmp_path / "run")
    with pytest.raises(ValueError, match="set --config.model.n_keypoints=8"):
        train.train_and_evaluate(_config(**{"model.n_keypoints": 7}), workdir)
    assert not os.path.exists(workdir)  # nothing made for a run that never ran
    result = train.train_and_evaluate(_config(), workdir)  # the suggested K, same workdir
    assert result["final"]["step"] == 10
    assert os.path.exists(tmp_path / "run" / "checkpoints" / "10" / checkpoint.CHECKSUM_FILE)
    saved = (tmp_path / "run" / "config.json").read_bytes()
    for change in ({"optim.optimizer": "adam"}, {"data.synthetic.seed": 5}):
        with pytest.raises(ValueError, match="holds checkpoints of another run"):
            train.train_and_evaluate(_config(**change), workdir)
        assert (tmp_path / "run" / "config.json").read_bytes() == saved
    assert load(workdir).config.n_keypoints == 8
    assert json.loads(saved)["optim"]["optimizer"] == "sgd"


def test_a_batch_larger_than_the_training_split_is_warned_about(tmp_path, caplog):
    with caplog.at_level("WARNING"):
        train.train_and_evaluate(_config(**{"data.synthetic.n_train": 20,
                                             "train.num_steps": 5}), str(tmp_path / "run"))
    assert ("config.train.batch_size=32 is larger than the 20 training views: every batch "
            "repeats views") in caplog.text


def test_a_training_file_edited_in_place_is_refused_on_resume(tmp_path):
    from c3dpo_jax.data import json_dataset, synthetic

    data = synthetic.make_split(64, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.0,
                                noise=0.0, perspective=False, shape_seed=0, seed=3)
    train_path, test_path = str(tmp_path / "train.json"), str(tmp_path / "test.json")
    json_dataset.save(data, train_path)
    json_dataset.save(data, test_path)
    files = {"data.train_path": train_path, "data.test_path": test_path}
    workdir = str(tmp_path / "run")
    train.train_and_evaluate(_config(**files), workdir)
    recorded = run_config.load_config(workdir)["train_data_sha256"]
    train.train_and_evaluate(_config(**files), workdir)  # same file: resumes (re-evaluates)
    with open(train_path) as f:
        obj = json.load(f)
    entries = obj["data"] if isinstance(obj, dict) else obj
    entries[5]["kp_loc"][0][2] += 0.25  # one visible coordinate, same path
    with open(train_path, "w") as f:
        json.dump(obj, f)
    with pytest.raises(ValueError, match="train_data_sha256: '[0-9a-f]{12}' in the checkpoint"):
        train.train_and_evaluate(_config(**files), workdir)
    assert run_config.load_config(workdir)["train_data_sha256"] == recorded  # untouched


def _git(*args):
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run(["git", "-C", root, *args], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def test_the_workdir_records_the_software_and_a_resumption_by_other_software(
        tmp_path, monkeypatch):
    import importlib.metadata

    workdir = str(tmp_path / "run")
    train.train_and_evaluate(_config(), workdir)
    (record,) = run_config.load_config(workdir)["software"]
    assert record["c3dpo_jax"] == importlib.metadata.version("c3dpo_jax")
    assert record["jax"] == importlib.metadata.version("jax")
    assert record["git_commit"] == _git("rev-parse", "HEAD")  # None outside a git checkout
    if record["git_commit"] is not None:
        dirty = _git("status", "--porcelain", "--untracked-files=no", "--", "c3dpo_jax")
        assert record["git_dirty"] == bool(dirty)
    train.train_and_evaluate(_config(), workdir)  # same software: one record
    assert run_config.load_config(workdir)["software"] == [record]
    other = dict(record, c3dpo_jax="9.9.9")
    monkeypatch.setattr(run_config, "software_record", lambda: other)
    train.train_and_evaluate(_config(**{"train.num_steps": 20}), workdir)
    assert run_config.load_config(workdir)["software"] == [record, other]
    fresh = str(tmp_path / "fresh")  # a new workdir starts its own history
    train.train_and_evaluate(_config(), fresh)
    assert run_config.load_config(fresh)["software"] == [other]


def test_the_pictures_find_the_data_files_from_any_directory(tmp_path, monkeypatch, caplog):
    from c3dpo_jax import visualise
    from c3dpo_jax.data import json_dataset, synthetic

    data = synthetic.make_split(64, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.0,
                                noise=0.0, perspective=False, shape_seed=0, seed=3)
    (tmp_path / "data").mkdir()
    json_dataset.save(data, str(tmp_path / "data" / "train.json"))
    obj = json.loads((tmp_path / "data" / "train.json").read_text())
    obj = {"dataset": "mine", "y_up": True, "skeleton": [[0, 1]],
           "data": obj["data"] if isinstance(obj, dict) else obj}
    (tmp_path / "data" / "test.json").write_text(json.dumps(obj))
    monkeypatch.chdir(tmp_path / "data")  # paths as a user types them, relative
    train.train_and_evaluate(
        _config(**{"data.train_path": "train.json", "data.test_path": "test.json"}), "../run")
    monkeypatch.chdir(tmp_path)  # elsewhere, the same relative paths name nothing
    config = run_config.load_config("run")
    assert config["data"]["test_path"] == "test.json"  # the config as given
    assert visualise.run_style(config) == {"y_up": True, "skeleton": [[0, 1]], "unit": ""}
    os.rename(tmp_path / "data", tmp_path / "moved")
    assert visualise.run_style(config) == {"skeleton": None, "y_up": False, "unit": ""}
    assert "data file " + str(tmp_path / "data" / "test.json") + " is not found" in caplog.text


def test_a_finished_run_extended_keeps_its_final_evaluation_on_the_curve(tmp_path):
    workdir = str(tmp_path / "run")
    # Evaluations every 5 steps, as the logging: one compiled chunk length (5) for both runs.
    first = train.train_and_evaluate(_config(**{"train.eval_every_steps": 5}), workdir)
    assert [h["step"] for h in first["history"]] == [5] and first["final"]["step"] == 10
    longer = _config(**{"train.eval_every_steps": 5, "train.num_steps": 20})
    results = train.train_and_evaluate(longer, workdir)
    assert [h["step"] for h in results["history"]] == [5, 10, 15]
    assert results["history"][1] == first["final"] and results["final"]["step"] == 20


def test_a_metrics_line_cut_short_by_a_kill_does_not_block_the_resumption(tmp_path, caplog):
    from c3dpo_jax import run_records

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"loss": 1.0, "step": 5}\n{"loss": 0.9, "step": 10}\n{"loss": 0.5, "st')
    with caplog.at_level("WARNING"):
        run_records.trim_metrics(str(tmp_path), 10)
    assert path.read_text() == '{"loss": 1.0, "step": 5}\n{"loss": 0.9, "step": 10}\n'
    assert "dropped a line that is not a JSON record" in caplog.text
    run_records.trim_metrics(str(tmp_path), 5)
    assert path.read_text() == '{"loss": 1.0, "step": 5}\n'


def test_a_loss_that_is_not_finite_right_after_a_resume_names_the_checkpoint(tmp_path):
    """A checkpoint without its checksum record is only checked for finite values: damaged
    arrays that read back as huge finite numbers load, and the first steps diverge. The
    learning rate is not what to change then, the checkpoint is the suspect."""
    import re
    import shutil

    import jax
    import jax.numpy as jnp

    from c3dpo_jax.state import create_train_state

    workdir = str(tmp_path / "run")
    train.train_and_evaluate(_config(), workdir)
    spec = train.RunSpec.from_config(_config())
    template = create_train_state(jax.random.key(0), spec.model, spec.optimizer())
    state, _ = checkpoint.restore_latest(workdir, template)
    step_dir = os.path.join(workdir, "checkpoints", "10")
    shutil.rmtree(step_dir)
    manager = checkpoint.make_manager(workdir, 10)
    huge = jax.tree.map(lambda p: jnp.full_like(p, 3e38), state.params)  # finite, absurd
    checkpoint.save(manager, 10, state.replace(params=huge), force=True)
    manager.wait_until_finished()
    manager.close()
    os.remove(os.path.join(step_dir, checkpoint.CHECKSUM_FILE))  # as a kill before it leaves
    with pytest.raises(FloatingPointError, match=re.escape(
            f"right after resuming from the checkpoint {step_dir}, the first suspect (damaged "
            "files can read back as finite numbers); training stopped: move that folder aside "
            "to resume from the checkpoint before it")) as err:
        train.train_and_evaluate(_config(**{"train.num_steps": 20}), workdir)
    assert str(err.value).startswith("loss is not finite at step 10 (")
    assert "optim.lr" not in str(err.value)
